"""vkray.DeviceGroup: lavapipe opened two or three times, as several GPUs are. Every query kind
answers what one device answers, ray for ray and field for field (dtypes and shapes too), however
the rays are split (fixed uneven shares, measured speeds, empty pieces, fewer rays than devices),
from several threads at once; analytic answers on a unit box; bad input raises what one device
raises; a failing piece or Ctrl-C stops every piece."""

import os
import signal
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import vkray
from conftest import BACKENDS, VALIDATION, VULKAN_INDEX, make_device
from oracle import box, triangle_soup
from test_precision import tiers
from vkray._device_group import _MIN_TIMED_RAYS, _Speeds, split, usable_cores

N = 3001  # rays per batch: not a multiple of any group size
ROTATE_SHIFT = np.array([[0.0, -1, 0, 0.6], [1, 0, 0, 0.2], [0, 0, 1, -0.3], [0, 0, 0, 1]])
QUAD = (np.array([[-1, -1, 0.5], [2, -1, 0.5], [2, 2, 0.5], [-1, 2, 0.5]]), np.array([[0, 1, 2], [0, 2, 3]]))

_groups = {}


def make_group(copies=2, weights=None, backend=BACKENDS[0]):
    """The session's device of this backend and ``copies - 1`` more openings of it, as one group."""
    key = (copies, None if weights is None else tuple(weights), backend)
    if key not in _groups:
        others = [vkray.Device(backend=backend, validation=VALIDATION) for _ in range(copies - 1)]
        _groups[key] = vkray.DeviceGroup([make_device(backend)] + others, weights=weights)
    return _groups[key]


def mixed_scene(builder, instance):
    """Triangle soup, a rotated box (masked) and a translucent quad, on a Device (with
    vkray.Instance) or a DeviceGroup (with vkray.GroupInstance)."""
    soup = builder.mesh(*triangle_soup(150, seed=3))
    cube = builder.mesh(*box())
    veil = builder.mesh(*QUAD, opacity=[0.3, 0.8])
    return builder.scene(
        [
            instance(soup, custom_index=5),
            instance(cube, ROTATE_SHIFT, custom_index=7, mask=0x3),
            instance(veil, custom_index=9),
        ]
    )


def solids_scene(builder, instance):
    """Two closed boxes, one of them rotated: contains' parity needs closed meshes."""
    cube = builder.mesh(*box())
    return builder.scene([instance(cube), instance(cube, ROTATE_SHIFT)])


def rays(n, seed):
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-0.8, 1.8, (n, 3))
    return origins, rng.uniform(0.0, 1.0, (n, 3)) - origins


def points(n, seed):
    return np.random.default_rng(seed).uniform(-0.5, 1.5, (n, 3))


def assert_same(got, want, what=""):
    """Equal results: arrays (values, dtype, shape), or every field of Hits, AllHits and Closest."""
    if isinstance(want, np.ndarray):
        assert got.dtype == want.dtype and got.shape == want.shape, what
        np.testing.assert_array_equal(got, want, err_msg=what)
        return
    assert type(got) is type(want) and got.shape == want.shape and got.precision == want.precision, what
    names = set(vkray.HIT_FIELDS) | set(vkray.CLOSEST_FIELDS) | {"offsets", "ray_index", "counts"}
    for name in sorted(names):
        a, b = getattr(got, name, None), getattr(want, name, None)
        assert (a is None) == (b is None), (what, name)
        if b is not None:
            assert a.dtype == b.dtype and a.shape == b.shape, (what, name)
            np.testing.assert_array_equal(a, b, err_msg=f"{what}: {name}")


def every_query(scene, precision, seed=0):
    """(name, call) for every query kind of SceneLike, on rays and points of one batch."""
    o, d = rays(N, seed)
    tmax = np.random.default_rng(seed).uniform(0.5, 3.0, N)
    p = points(N, seed)
    distance_tier = "exact" if precision == "exact" else "reference"
    return [
        ("intersect", lambda: scene.intersect(o, d, outputs=vkray.HIT_FIELDS, precision=precision)),
        ("intersect masked", lambda: scene.intersect(o, d, mask=0x4, tmax=tmax, precision=precision)),
        ("intersect out=", lambda: scene.intersect(o, d, precision=precision, out=scene.intersect(
            *rays(N, seed + 1), precision=precision))),
        ("occluded", lambda: scene.occluded(o, d, tmax=tmax, precision=precision)),
        ("intersect_all", lambda: scene.intersect_all(o, d, outputs=vkray.HIT_FIELDS, precision=precision)),
        ("intersect_all max_hits", lambda: scene.intersect_all(o, d, max_hits=2, precision=precision)),
        ("count", lambda: scene.count(o, d, precision=precision, opacity_threshold=0.5)),
        ("transmittance", lambda: scene.transmittance(o, d, tmax=tmax, precision=precision)),
        ("closest_points", lambda: scene.closest_points(p, outputs=vkray.CLOSEST_FIELDS, precision=distance_tier)),
        ("distance", lambda: scene.distance(p, max_distance=0.2, precision=distance_tier)),
        ("contains winding", lambda: scene.contains(p, method="winding")),
    ]


def solid_queries(scene):
    p = points(N, 1)
    return [
        ("contains", lambda: scene.contains(p)),
        ("signed_distance", lambda: scene.signed_distance(p)),
    ]


def group_precisions(group):
    return [p for p in ("fast", "exact") if p in tiers(group.devices[0])]


@pytest.mark.parametrize("weights", [None, (5, 1), (0, 1)], ids=["equal", "5-to-1", "all-on-one"])
def test_every_query_answers_what_one_device_answers(weights):
    """Every query kind, every GPU tier, rays split equally (too few rays to measure the devices),
    5 to 1, or all on the second device: each answer equals one device's, field for field."""
    group = make_group(2, weights)
    device = group.devices[0]
    scenes = [mixed_scene(group, vkray.GroupInstance), mixed_scene(device, vkray.Instance)]
    solids = [solids_scene(group, vkray.GroupInstance), solids_scene(device, vkray.Instance)]
    for precision in group_precisions(group):
        for (name, grouped), (_, single) in zip(*(every_query(s, precision) for s in scenes)):
            assert_same(grouped(), single(), f"{name} {precision}")
    for (name, grouped), (_, single) in zip(*(solid_queries(s) for s in solids)):
        assert_same(grouped(), single(), name)


def test_answers_copied_in_blocks_by_several_threads(monkeypatch):
    """The pieces' answers copied into the batch's arrays by blocks of a few rows on several
    threads (as big answers are: here blocks of 64 bytes, so that 3001 rays make many, the last
    one short): every query kind still answers what one device answers."""
    monkeypatch.setattr(vkray._device_group, "_COPY_BLOCK_BYTES", 64)
    group = make_group(3, (3, 1, 2))
    device = group.devices[0]
    scenes = [mixed_scene(group, vkray.GroupInstance), mixed_scene(device, vkray.Instance)]
    for (name, grouped), (_, single) in zip(*(every_query(s, group_precisions(group)[-1]) for s in scenes)):
        assert_same(grouped(), single(), name)


def test_split_hits_are_written_by_the_devices_into_the_batch(monkeypatch):
    """A split intersect's pieces write their hits straight into the batch's arrays (nothing is
    copied after them), in every tier; occluded's pieces are still copied in. Answers are one
    device's."""
    copied = []
    copy_rows = vkray._device_group._copy_rows
    monkeypatch.setattr(
        vkray._device_group, "_copy_rows", lambda dst, src: (copied.append(len(src)), copy_rows(dst, src))
    )
    group = make_group(3, (3, 1, 2))
    device = group.devices[0]
    scenes = [mixed_scene(group, vkray.GroupInstance), mixed_scene(device, vkray.Instance)]
    o, d = rays(N, 11)
    for precision in tiers(device):
        for outputs in (None, vkray.HIT_FIELDS, ["t"]):
            got, want = (s.intersect(o, d, outputs=outputs, precision=precision) for s in scenes)
            assert_same(got, want, f"{precision} {outputs}")
    assert copied == []
    assert_same(scenes[0].occluded(o, d), scenes[1].occluded(o, d))
    assert len(copied) == 3 and sum(copied) == N


@pytest.mark.parametrize("weights", [None, (0, 1)], ids=["split", "all-on-one"])
def test_out_is_written_in_place_by_every_piece(weights):
    """intersect(out=hits): split or whole, the answers land in out's own arrays (filled with junk
    first), equal to one device's fresh answers."""
    group = make_group(2, weights)
    scene = mixed_scene(group, vkray.GroupInstance)
    single = mixed_scene(group.devices[0], vkray.Instance)
    o, d = rays(N, 5)
    out = scene.intersect(*rays(N, 6), outputs=vkray.HIT_FIELDS)
    for name in vkray.HIT_FIELDS:
        array = getattr(out, name)
        array[...] = -7 if array.dtype.kind == "i" else 1234.5
    got = scene.intersect(o, d, outputs=vkray.HIT_FIELDS, out=out)
    for name in vkray.HIT_FIELDS:
        assert np.shares_memory(getattr(got, name), getattr(out, name)), name
    assert_same(got, single.intersect(o, d, outputs=vkray.HIT_FIELDS))
    with pytest.raises(ValueError, match="shape"):
        scene.intersect(o[:-1], d[:-1], outputs=vkray.HIT_FIELDS, out=out)
    # Split or whole, the same refusals: one array for two fields, an array of another dtype.
    ids = np.empty(len(o), np.int32)
    with pytest.raises(ValueError, match="shares memory"):
        scene.intersect(o, d, outputs=("prim_id", "instance_id"),
                        out=vkray.Hits(out.shape, {"prim_id": ids, "instance_id": ids}))
    with pytest.raises(ValueError, match="int32"):
        scene.intersect(o, d, outputs=("prim_id",), out=vkray.Hits(out.shape, {"prim_id": ids.astype(np.int64)}))


class _FakeCudaArray:
    """Claims to be a CUDA array of cuda:7 (DLPack device type 2), as torch's would."""

    shape = (10, 3)

    def __dlpack__(self, stream=None):
        raise AssertionError("never read: no device of the group is cuda:7")

    def __dlpack_device__(self):
        return (2, 7)


def test_cuda_rays_of_a_gpu_outside_the_group_are_named():
    group = make_group(2)
    scene = mixed_scene(group, vkray.GroupInstance)
    with pytest.raises(ValueError, match="the arrays live on cuda:7, which is none of this group's devices"):
        scene.intersect(_FakeCudaArray(), _FakeCudaArray())


def test_cuda_points_of_a_gpu_outside_the_group_are_named():
    """CUDA points go to the group's device that is their GPU (answered there through the host):
    none is cuda:7."""
    group = make_group(2)
    scene = mixed_scene(group, vkray.GroupInstance)
    for query in (scene.distance, scene.contains, scene.closest_points):
        with pytest.raises(ValueError, match="the arrays live on cuda:7, which is none of this group's devices"):
            query(_FakeCudaArray())


def test_cuda_answers_of_host_arrays_are_refused_by_a_group():
    """cuda=True in a group is for sensors (their answer lands on the GPU that traced them); host
    arrays have no GPU to answer on."""
    group = make_group(2)
    scene = mixed_scene(group, vkray.GroupInstance)
    with pytest.raises(TypeError, match="cuda=True in a DeviceGroup is for sensors"):
        scene.intersect(*rays(N, 5), cuda=True)
    camera = vkray.PinholeCamera(8, 6, fov_deg=60.0, eye=[0.0, 0.0, 5.0], target=[0.0, 0.0, 0.0], up=[0, 1, 0])
    if all(d.cuda_device is None for d in group.devices):
        with pytest.raises(TypeError, match="none of this group's devices shares memory with CUDA"):
            scene.intersect(camera, cuda=True)


def test_the_split_follows_the_weights():
    """5 to 1 over 3001 rays: the second device traces rays 2501-3000, the first the rest."""
    group = make_group(2, (5, 1))
    assert split(N, [5, 1]) == [(0, 2501), (2501, 3001)]
    scene = mixed_scene(group, vkray.GroupInstance)
    scene.occluded(*rays(N, 2))
    assert [d.last_trace_profile["rays"] for d in group.devices] == [2501, 500]


def test_shapes_shared_rows_and_per_ray_arguments():
    """Batch shape S = (23, 29), one origin for every ray, per-ray tmin/tmax/mask arrays and float32
    rays: split as one device reads them."""
    group = make_group(2, (2, 3))
    scene = mixed_scene(group, vkray.GroupInstance)
    single = scene.per_device[0]
    rng = np.random.default_rng(4)
    eye = np.array([0.4, 0.5, 2.5])
    directions = (rng.uniform(-0.5, 1.5, (23, 29, 3)) - eye).astype(np.float32)
    arguments = dict(tmin=rng.uniform(0, 0.5, (23, 29)), tmax=rng.uniform(1.0, 4.0, (23, 29)))
    arguments["mask"] = rng.integers(0, 256, (23, 29))
    for query in ("intersect", "occluded", "intersect_all", "count", "transmittance"):
        got = getattr(scene, query)(eye, directions, **arguments)
        assert_same(got, getattr(single, query)(eye, directions, **arguments), query)
    assert scene.intersect(eye, directions).t.shape == (23, 29)
    # One direction for every origin, tmax per ray:
    origins = rng.uniform(-0.5, 1.5, (500, 3))
    assert_same(scene.count(origins, [0, 0, 1], tmax=np.full(500, 2.0)), single.count(origins, [0, 0, 1], tmax=2.0))


def test_no_rays_one_ray_and_fewer_rays_than_devices():
    """0 rays, a single ray (0-d results), and 1 or 2 rays over three devices: one device's answers."""
    group = make_group(3)
    scene = mixed_scene(group, vkray.GroupInstance)
    single = scene.per_device[0]
    o, d = rays(4, 5)
    for batch in ((np.zeros((0, 3)), np.zeros((0, 3))), (o[0], d[0]), (o[:1], d[:1]), (o[:2], d[:2])):
        for query in ("intersect", "occluded", "intersect_all", "count", "transmittance"):
            assert_same(getattr(scene, query)(*batch), getattr(single, query)(*batch), query)
        p = batch[0]
        assert_same(scene.closest_points(p), single.closest_points(p))
        assert_same(scene.contains(p, method="winding"), single.contains(p, method="winding"))
    assert scene.intersect(o[0], d[0]).t.shape == ()
    assert scene.intersect(np.zeros((0, 3)), np.zeros((0, 3))).uv.shape == (0, 2)


def test_analytic_answers_on_a_unit_box():
    """Rays straight down onto the unit box: t, normal, two crossings; points' distances and
    inside-or-outside from the box's own geometry (no vkray)."""
    group = make_group(2, (1, 2))
    scene = group.scene(group.mesh(*box()))
    rng = np.random.default_rng(6)
    xy = rng.uniform(0.01, 0.99, (N, 2))
    height = rng.uniform(1.5, 3.0, N)
    origins = np.column_stack([xy, height])
    hits = scene.intersect(origins, [0, 0, -1], precision="exact" if "exact" in group_precisions(group) else "fast")
    np.testing.assert_allclose(hits.t, height - 1.0, rtol=1e-6)
    np.testing.assert_array_equal(hits.normal, np.tile(np.float32([0, 0, 1]), (N, 1)))
    np.testing.assert_array_equal(scene.count(origins, [0, 0, -1], precision="reference"), np.full(N, 2))
    p = points(N, 7)
    outside = np.maximum(np.maximum(-p, p - 1), 0)
    inside_depth = np.minimum(p, 1 - p).min(axis=1)
    inside = (outside == 0).all(axis=1)
    want = np.where(inside, -inside_depth, np.linalg.norm(outside, axis=1))
    np.testing.assert_allclose(scene.signed_distance(p), want, atol=1e-12)
    np.testing.assert_array_equal(scene.contains(p), inside)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sensors_answer_what_one_device_answers(backend):
    """A camera and a two-echo lidar (each traced whole on one device): every query kind."""
    group = make_group(2, None, backend)
    scene = mixed_scene(group, vkray.GroupInstance)
    single = scene.per_device[0]
    camera = vkray.PinholeCamera(40, 30, fov_deg=70, eye=[0.5, 0.5, 3.0], target=[0.5, 0.5, 0.0], up=[0, 1, 0])
    pose = np.eye(4)
    pose[:3, 3] = [0.5, 0.5, 0.2]
    lidar = vkray.Lidar([-30.0, -10.0, 10.0, 30.0], 90, pose=pose, max_range=5.0, echoes=2)
    for sensor in (camera, lidar):
        for query in ("intersect", "occluded", "intersect_all", "count", "transmittance"):
            assert_same(getattr(scene, query)(sensor), getattr(single, query)(sensor), f"{query} {sensor!r}")
    assert scene.intersect(lidar).t.shape == (4, 90, 2)


def test_several_threads_at_once():
    """Four threads each run every query kind (and a sensor) on one GroupScene, at once: every
    answer is one device's."""
    group = make_group(2, (3, 2))
    device = group.devices[0]
    scenes = [mixed_scene(group, vkray.GroupInstance), mixed_scene(device, vkray.Instance)]
    solids = [solids_scene(group, vkray.GroupInstance), solids_scene(device, vkray.Instance)]
    camera = vkray.PinholeCamera(32, 24, fov_deg=60, eye=[0.5, 0.5, 3.0], target=[0.5, 0.5, 0.0], up=[0, 1, 0])

    def queries(k, seed):
        calls = every_query(scenes[k], "fast", seed) + solid_queries(solids[k])
        return calls + [("camera", lambda: scenes[k].intersect(camera))]

    def run_all(k, seed):
        return [(name, call()) for name, call in queries(k, seed)]

    wanted = [run_all(1, seed) for seed in range(4)]
    with ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(run_all, [0] * 4, range(4)))
    for answer, want in zip(answers, wanted):
        for (name, got), (_, expected) in zip(answer, want):
            assert_same(got, expected, name)


@pytest.mark.parametrize("threads", [1, 3])
def test_a_device_on_threads_of_its_own_answers_as_on_the_shared_pool(threads):
    """Device(host_threads=k): every query kind, from three threads at once while a fourth
    changes the device's threads under them, answers what the session's device answers."""
    device = vkray.Device(backend=BACKENDS[0], validation=VALIDATION, host_threads=threads)
    assert device.host_threads == threads
    single = make_device(BACKENDS[0])
    assert single.host_threads is None
    scenes = [mixed_scene(device, vkray.Instance), mixed_scene(single, vkray.Instance)]
    solids = [solids_scene(device, vkray.Instance), solids_scene(single, vkray.Instance)]

    def run_all(k, seed):
        return [(name, call()) for name, call in every_query(scenes[k], "fast", seed) + solid_queries(solids[k])]

    wanted = [run_all(1, seed) for seed in range(3)]
    stop = threading.Event()

    def switch():
        while not stop.is_set():
            for choice in (2, None, threads):
                device.host_threads = choice
                time.sleep(0.01)

    switcher = threading.Thread(target=switch)
    switcher.start()
    try:
        with ThreadPoolExecutor(3) as pool:
            answers = list(pool.map(run_all, [0] * 3, range(3)))
    finally:
        stop.set()
        switcher.join()
    for answer, want in zip(answers, wanted):
        for (name, got), (_, expected) in zip(answer, want):
            assert_same(got, expected, name)
    o, d = rays(N, 9)
    shared = single.last_trace_profile["host_threads"]  # the session device's: the shared pool
    for choice, used in ((threads, threads), (None, shared), (threads + 1, threads + 1)):
        device.host_threads = choice
        assert device.host_threads == choice
        for query in (scenes[0].intersect, scenes[0].occluded, scenes[0].intersect_all, scenes[0].count):
            query(o, d)
            assert device.last_trace_profile["host_threads"] == used, (query, choice)
        scenes[0].closest_points(points(N, 9))
        assert device.last_trace_profile["host_threads"] == used


def test_devices_the_group_opens_share_the_cores():
    """A group of k devices gives each device it opens 1/k of the cores for its host passes (or
    host_threads each); devices it is given keep theirs; one device keeps the shared pool. Its
    answers are one device's."""
    group = vkray.DeviceGroup([VULKAN_INDEX, VULKAN_INDEX], backend=BACKENDS[0], validation=VALIDATION)
    share = max(1, usable_cores() // 2)
    assert [d.host_threads for d in group.devices] == [share, share]
    given = vkray.DeviceGroup(
        [group.devices[0], VULKAN_INDEX], host_threads=3, backend=BACKENDS[0], validation=VALIDATION
    )
    assert [d.host_threads for d in given.devices] == [share, 3]
    assert vkray.DeviceGroup([VULKAN_INDEX], backend=BACKENDS[0], validation=VALIDATION).devices[0].host_threads is None
    single = make_device(BACKENDS[0])
    scenes = [mixed_scene(group, vkray.GroupInstance), mixed_scene(single, vkray.Instance)]
    for (name, grouped), (_, one) in zip(*(every_query(s, "fast", seed=5) for s in scenes)):
        assert_same(grouped(), one(), name)


def test_builders_and_updates_match_one_device():
    """meshes(), mesh_from_parts, spheres, Mesh.update and Scene.update on a group: one device's
    answers after the same builds and updates."""
    group = make_group(2, (1, 1))
    device = group.devices[0]
    soups = [triangle_soup(40, seed=s) for s in (8, 9)]
    answers = []
    for builder, instance in ((group, vkray.GroupInstance), (device, vkray.Instance)):
        first, second = builder.meshes(soups, allow_update=True)
        parts = builder.mesh_from_parts([soups[0], (soups[1][0], soups[1][1], ROTATE_SHIFT)])
        balls = builder.spheres(points(20, 10), 0.05)
        scene = builder.scene([instance(first), instance(second), instance(parts, custom_index=3)], allow_update=True)
        o, d = rays(N, 11)
        before = scene.intersect(o, d, outputs=vkray.HIT_FIELDS)
        first.update(soups[0][0] + [0.0, 0.0, 0.1])
        scene.update(transforms=np.stack([np.eye(4), ROTATE_SHIFT, np.eye(4)]), masks=[0xFF, 0x1, 0xFF])
        after = scene.intersect(o, d, outputs=vkray.HIT_FIELDS)
        spheres = builder.scene(balls).intersect(o, d)
        answers.append((before, after, spheres))
    for got, want, what in zip(*answers, ("before", "after", "spheres")):
        assert_same(got, want, what)
    assert not np.array_equal(answers[0][0].t, answers[0][1].t)  # the update moved something


def test_updates_never_meet_a_query_half_way():
    """A thread moves the box back and forth (GroupScene.update) while three threads query: every
    answer is one device's before the update or after it, never pieces of both."""
    group = make_group(2, (1, 1))
    scene = group.scene([group.mesh(*box())], allow_update=True)
    o, d = rays(N, 18)
    poses = [np.eye(4)[None], ROTATE_SHIFT[None]]
    answers = []
    for pose in poses:
        scene.update(transforms=pose)
        answers.append(scene.per_device[0].intersect(o, d, outputs=["t", "prim_id"]))
    assert not np.array_equal(answers[0].prim_id, answers[1].prim_id)
    stop = threading.Event()

    def move():
        k = 0
        while not stop.is_set():
            k += 1
            scene.update(transforms=poses[k % 2])
        return k

    def query(_):
        got = [scene.intersect(o, d, outputs=["t", "prim_id"]) for _ in range(10)]
        return [[np.array_equal(h.t, a.t) and np.array_equal(h.prim_id, a.prim_id) for a in answers] for h in got]

    with ThreadPoolExecutor(4) as pool:
        mover = pool.submit(move)
        matches = sum(pool.map(query, range(3)), [])
        stop.set()
        assert mover.result() > 5
    assert all(any(match) for match in matches)


def test_speeds_are_measured_and_size_the_pieces():
    """Unmeasured devices share equally; a piece's rays per second updates its device's moving
    average (pieces too small to tell are ignored); shares follow the averages."""
    speeds = _Speeds(3)
    assert speeds.weights("count/fast") == [1.0, 1.0, 1.0]
    speeds.record("count/fast", 0, _MIN_TIMED_RAYS, 1.0)
    speeds.record("count/fast", 1, 100, 1e-9)  # too few rays to tell
    assert speeds.weights("count/fast") == [_MIN_TIMED_RAYS] * 3
    speeds.record("count/fast", 1, 3 * _MIN_TIMED_RAYS, 1.0)
    speeds.record("count/fast", 0, 3 * _MIN_TIMED_RAYS, 1.0)  # average of 1x and 3x: 2x
    assert speeds.weights("count/fast") == [2 * _MIN_TIMED_RAYS, 3 * _MIN_TIMED_RAYS, 2.5 * _MIN_TIMED_RAYS]
    assert speeds.weights("intersect/fast") == [1.0, 1.0, 1.0]  # per query kind
    assert split(10, [2, 3, 2.5]) == [(0, 3), (3, 7), (7, 10)]
    assert split(2, [1, 1, 1]) == [(0, 1), (1, 1), (1, 2)]
    # A group measures its devices on queries big enough to tell:
    group = vkray.DeviceGroup(make_group(2).devices)
    scene = group.scene(group.mesh(*box()))
    o, d = rays(2 * _MIN_TIMED_RAYS + 10, 12)
    scene.occluded(o, d)
    measured = group.speeds["occluded/fast"]
    assert all(s is not None and s > 0 for s in measured)
    assert group.weights("occluded/fast") == measured


def test_bad_input_raises_what_one_device_raises():
    """Each bad call raises on the group the error one device raises: same type, same message
    (rows counted in the caller's batch, the earliest bad row first)."""
    group = make_group(2, (1, 3))
    scene = mixed_scene(group, vkray.GroupInstance)
    single = scene.per_device[0]
    o, d = rays(N, 13)
    late_nan = o.copy()
    late_nan[2900] = np.nan  # in the second piece (rays 750-3000)
    # Rays 0-14999 in the first piece, 15000-59999 in the second: the second piece finds its bad ray
    # (in its first chunk of 256) long before the first piece reaches its own, whose row one device
    # names: the first piece must run on.
    two_bad, d_long = rays(60_000, 14)
    two_bad[15_010] = np.nan
    two_bad[14_500] = np.inf
    tmin = np.zeros(N)
    tmin[1800] = 5.0
    bad_calls = [
        lambda s: s.intersect(late_nan, d),
        lambda s: s.occluded(two_bad, d_long),
        lambda s: s.count(o, d, tmin=tmin, tmax=1.0),
        lambda s: s.intersect_all(o, d * 0),
        lambda s: s.intersect(o, d[:10]),
        lambda s: s.intersect(o, d, outputs=["colour"]),
        lambda s: s.intersect(o, d, precision="nonsense"),
        lambda s: s.occluded(o, d, mask=256),
        lambda s: s.intersect_all(o, d, max_hits=0),
        lambda s: s.count(o),
        lambda s: s.closest_points(late_nan),
        lambda s: s.contains(o),  # parity, but the soup is open
        lambda s: s.contains(o, method="vote"),
        lambda s: s.distance(o[:, :2]),
        lambda s: s.transmittance(vkray.PinholeCamera(4, 4, fov_deg=60, eye=[0, 0, 1], target=[0, 0, 0]), d),
        # One device checks every point before the tier: the piece without the bad point must not
        # answer with the tier's error.
        lambda s: s.closest_points(late_nan, precision="refined"),
        lambda s: s.distance(late_nan, precision="refined"),
        lambda s: s.contains(late_nan, method="winding", precision="fast"),
        lambda s: s.contains(o.astype(complex), method="vote"),  # the method first, as one device
        lambda s: s.intersect(o, d, outputs=["uv", "prim_id"], out=wide_uv),
    ]
    wide_uv = vkray.Hits((N,), {"uv": np.zeros((N, 3), np.float32), "prim_id": np.zeros(N, np.int32)}, "fast")
    saved = group.chunk_rays
    group.chunk_rays = 256
    try:
        for k, call in enumerate(bad_calls):
            with pytest.raises(Exception) as want:
                call(single)
            with pytest.raises(type(want.value)) as got:
                call(scene)
            assert type(got.value) is type(want.value) and str(got.value) == str(want.value), k
    finally:
        group.chunk_rays = saved[0]
    assert_same(scene.occluded(o, d), single.occluded(o, d))  # every device still usable


def test_a_failing_piece_stops_the_pieces_after_it():
    """A bad first ray fails the first piece at once: the second piece stops at its next chunk
    instead of tracing its 90000 rays (its device's last finished trace is still the one before)."""
    group = make_group(2, (1, 9))
    scene = group.scene(group.mesh(*triangle_soup(500, seed=14)))
    o, d = rays(100_000, 15)
    o[0] = np.nan
    saved = group.chunk_rays
    group.chunk_rays = 512
    try:
        scene.per_device[1].occluded(o[1:8], d[1:8])
        with pytest.raises(ValueError, match="origins row 0 is not finite"):
            scene.count(o, d)
    finally:
        group.chunk_rays = saved[0]
    assert group.devices[1].last_trace_profile["rays"] == 7
    assert group._busy == [0, 0]


def test_ctrl_c_stops_every_piece():
    """SIGINT while the calling thread waits for the pieces: KeyboardInterrupt soon after, no piece
    left running, and the devices trace again."""
    group = make_group(2, (1, 1))
    scene = group.scene(group.mesh(*triangle_soup(2000, seed=16)))
    o, d = rays(150_000, 17)
    saved = group.chunk_rays
    group.chunk_rays = 2048
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    # Python's own handler, even where the parent ignores SIGINT (a shell's background job, as
    # `nohup ... &`): Python then keeps SIG_IGN, and the signal never arrives.
    ignored = signal.signal(signal.SIGINT, signal.default_int_handler)
    started = time.perf_counter()
    try:
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            # A fast GPU may finish one query before the signal: it lands in a later one.
            while time.perf_counter() - started < 30.0:
                scene.count(o, d)
            pytest.fail("no KeyboardInterrupt within 30 s of SIGINT")
        stopped = time.perf_counter() - started
    finally:
        timer.join()
        signal.signal(signal.SIGINT, ignored)
        group.chunk_rays = saved[0]
    assert stopped < 2.0 and group._busy == [0, 0]
    assert_same(scene.count(o[:100], d[:100]), scene.per_device[1].count(o[:100], d[:100]))


def test_one_progress_bar_for_every_piece(monkeypatch):
    """progress=True: one bar, fed by every piece's chunks, rising to the whole batch, then closed."""
    reports, closed = [], []

    class Recorder:
        def __init__(self, what, unit="ray"):
            self.what = what

        def __call__(self, done, total):
            reports.append((self.what, done, total))

        def close(self):
            closed.append(self.what)

    monkeypatch.setattr(vkray._progress, "Progress", Recorder)
    group = make_group(2, (1, 2))
    scene = group.scene(group.mesh(*box()))
    saved = group.chunk_rays
    group.chunk_rays = 256
    try:
        scene.count(*rays(N, 19), progress=True)
    finally:
        group.chunk_rays = saved[0]
    assert closed == ["count"] and {what for what, _, _ in reports} == {"count"}
    done = [d for _, d, _ in reports]
    assert all(total == N for _, _, total in reports) and len(done) >= N // 256 and max(done) == N
    assert (np.diff(done) >= 0).all() and done[-1] == N


def test_group_arguments():
    """Devices by index, twice; a bad weight list; a mesh from another group; a Device's mesh."""
    group = vkray.DeviceGroup([VULKAN_INDEX, VULKAN_INDEX], backend=BACKENDS[0], validation=VALIDATION)
    assert len(group) == 2 and group.devices[0] is not group.devices[1]
    assert all(d.info.index == VULKAN_INDEX for d in group.devices)
    with pytest.raises(ValueError, match="weights must be 2 finite numbers"):
        vkray.DeviceGroup(group.devices, weights=[1, -1])
    with pytest.raises(ValueError, match="weights must be 2 finite numbers"):
        vkray.DeviceGroup(group.devices, weights=[np.inf, 1])
    with pytest.raises(TypeError, match="weights must be a list of numbers"):
        vkray.DeviceGroup(group.devices, weights="12")
    for one in (0, "llvmpipe", group.devices[0]):
        with pytest.raises(TypeError, match="devices must be a list"):
            vkray.DeviceGroup(one)
    with pytest.raises(ValueError, match="at least one device"):
        vkray.DeviceGroup([])
    other = make_group(2)
    with pytest.raises(ValueError, match="another DeviceGroup"):
        group.scene(other.mesh(*box()))
    with pytest.raises(TypeError, match="GroupMesh or a GroupInstance"):
        group.scene(group.devices[0].mesh(*box()))
    with pytest.raises(TypeError, match="custom_index"):
        vkray.GroupInstance(group.mesh(*box()), custom_index=1.5)
    # Every ray-tracing GPU, else the CPU engine (here), else the software devices.
    default = vkray.DeviceGroup()
    gpus = [d.index for d in vkray.devices() if d.engine == "vulkan" and not d.is_software]
    cpu = [d.index for d in vkray.devices() if d.engine == "cpu"]
    assert [d.info.index for d in default.devices] == (gpus or cpu)


@pytest.mark.filterwarnings("ignore:This process .* is multi-threaded, use of fork:DeprecationWarning")
def test_a_forked_child_is_refused_at_once():
    """A group that ran a query, then a fork: in the child its next query raises
    ForkedDeviceError at once (its devices' threads stay in the parent), as a Device does,
    instead of waiting forever for them."""
    group = make_group(2)
    scene = mixed_scene(group, vkray.GroupInstance)
    o, d = rays(N, 21)
    scene.count(o, d)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: report what the query raised, and leave at once
        try:
            signal.alarm(30)  # a hang ends the child, and the parent sees no answer
            try:
                scene.count(o, d)
                answer = b"no error"
            except vkray.ForkedDeviceError as exc:
                answer = b"ForkedDeviceError: " + str(exc).encode()
            except BaseException as exc:  # reported to the parent
                answer = type(exc).__name__.encode()
            os.write(write, answer)
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as pipe:
        answer = pipe.read().decode()
    os.waitpid(pid, 0)
    assert answer.startswith("ForkedDeviceError: this DeviceGroup was opened in process"), answer
    assert_same(scene.count(o, d), scene.per_device[0].count(o, d))  # the parent's group still answers


def test_a_group_tells_and_frees_the_staging_its_devices_keep():
    """After a split query each device keeps the staging it used; the group frees all of it."""
    group = vkray.DeviceGroup([vkray.Device(backend=BACKENDS[0], validation=VALIDATION) for _ in range(2)])
    scene = group.scene([vkray.GroupInstance(group.mesh(*box()))])
    o, d = rays(N, 41)
    scene.intersect(o, d, outputs=["t"])
    kept = group.idle_memory
    assert len(kept) == 2 and all(k["bytes"] > 0 and k["kept"] > 0 and k["made"] > 0 for k in kept), kept
    group.release_idle_memory()
    assert group.idle_memory == [{"bytes": 0, "kept": 0, "made": k["made"], "pinned_bytes": 0} for k in kept]
