"""vkray.dask on a cluster of two worker processes (lavapipe twice, as two GPUs; three threads
each, `local_cluster`'s default, under the validation layer as the suite is): each function's computed arrays equal one
process's `Scene` answer, whatever the chunking; the scene reaches each worker once per
computation and is built once per worker; a worker killed in the middle of a computation is
replaced, its tasks run again, and the result is still the same: nothing lost, nothing twice."""

import os
import signal
import threading
import time

import numpy as np
import pytest

pytest.importorskip("dask.distributed")

import dask  # noqa: E402
import dask.array as da  # noqa: E402
from dask.distributed import Client, get_task_stream  # noqa: E402

import vkray  # noqa: E402
import vkray.dask as vkray_dask  # noqa: E402
from conftest import VALIDATION  # noqa: E402
from oracle import box, triangle_soup  # noqa: E402
from test_precision import tiers  # noqa: E402
from vkray._device_group import usable_cores  # noqa: E402

N = 4001
UNEVEN = (700, 1300, 1, 999, 1001)  # chunks of the origins; directions are chunked otherwise
SHIFT = np.array([[1.0, 0, 0, 0.4], [0, 1, 0, 0.3], [0, 0, 1, 0.2], [0, 0, 0, 1]])


@pytest.fixture(scope="module")
def client():
    """Two workers on device 0 (lavapipe), three threads each; the validation layer on in each, as
    it is in this process, so that any message it reports fails the task and the test."""
    env = {"VKRAY_VALIDATION": "1"} if VALIDATION else {}
    with vkray_dask.local_cluster([0, 0], env=env) as cluster, Client(cluster) as client:
        client.wait_for_workers(2)
        yield client


@pytest.fixture
def any_device():
    """The device the workers open (`vkray.Device()`: the best one, the CPU engine on a machine
    without a ray-tracing GPU), so that the answers compare bit for bit."""
    return vkray.default_device()


def solids_spec(shift=SHIFT):
    """Two closed boxes (the second shifted) and a soup, as numpy arrays."""
    return vkray_dask.SceneSpec(
        [box(), triangle_soup(100, seed=20)],
        [{"mesh": 0, "custom_index": 3}, {"mesh": 0, "transform": shift, "mask": 0x2}, {"mesh": 1}],
    )


def rays(n, seed):
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-0.8, 1.8, (n, 3))
    return origins, rng.uniform(0.0, 1.0, (n, 3)) - origins


def chunked(array, chunks):
    return da.from_array(array, chunks=(chunks, 3))


def assert_fields_equal(got, lazy, want, names):
    """Computed fields equal one Scene's, with the dtypes and shapes the lazy arrays announced."""
    assert sorted(got) == sorted(lazy) == sorted(names)
    for name in names:
        expected = getattr(want, name)
        assert got[name].dtype == lazy[name].dtype == expected.dtype, name
        assert got[name].shape == lazy[name].shape == expected.shape, name
        np.testing.assert_array_equal(got[name], expected, err_msg=name)


def test_every_function_answers_what_one_process_answers(client, any_device):
    spec = solids_spec()
    scene = spec.build(any_device)
    o, d = rays(N, 21)
    origins, directions = chunked(o, UNEVEN), chunked(d, 1000)
    tmax = np.random.default_rng(21).uniform(0.5, 3.0, N)
    points = np.random.default_rng(22).uniform(-0.5, 1.8, (N, 3))
    p = chunked(points, (2000, 5, 1996))
    precisions = [x for x in ("fast", "exact") if x in tiers(any_device)]

    lazy = {f"intersect {x}": vkray_dask.intersect(spec, origins, directions, outputs=vkray.HIT_FIELDS, precision=x)
            for x in precisions}
    lazy["intersect masked"] = vkray_dask.intersect(spec, origins, directions, tmax=da.from_array(tmax, 900), mask=1)
    lazy["closest"] = vkray_dask.closest_points(spec, p, outputs=vkray.CLOSEST_FIELDS)
    lazy["closest exact"] = vkray_dask.closest_points(spec, p, max_distance=0.3, precision="exact")
    arrays = {
        "occluded": vkray_dask.occluded(spec, origins, directions, tmax=tmax),
        "count": vkray_dask.count(spec, origins, directions, precision=precisions[-1]),
        "contains": vkray_dask.contains(spec, p, method="winding"),
    }
    got, got_arrays = dask.compute(lazy, arrays)

    for x in precisions:
        want = scene.intersect(o, d, outputs=vkray.HIT_FIELDS, precision=x)
        assert_fields_equal(got[f"intersect {x}"], lazy[f"intersect {x}"], want, vkray.HIT_FIELDS)
    want = scene.intersect(o, d, tmax=tmax, mask=1)
    assert_fields_equal(got["intersect masked"], lazy["intersect masked"], want, vkray.DEFAULT_FIELDS)
    want = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS)
    assert_fields_equal(got["closest"], lazy["closest"], want, vkray.CLOSEST_FIELDS)
    want = scene.closest_points(points, max_distance=0.3, precision="exact")
    assert_fields_equal(got["closest exact"], lazy["closest exact"], want, lazy["closest exact"].keys())
    wanted = {
        "occluded": scene.occluded(o, d, tmax=tmax),
        "count": scene.count(o, d, precision=precisions[-1]),
        "contains": scene.contains(points, method="winding"),
    }
    for name, want in wanted.items():
        assert got_arrays[name].dtype == arrays[name].dtype == want.dtype, name
        np.testing.assert_array_equal(got_arrays[name], want, err_msg=name)
    assert 0 < wanted["occluded"].mean() < 1 and 0 < wanted["contains"].mean() < 1
    assert origins.chunks[0] == arrays["count"].chunks[0] == UNEVEN


def test_a_builder_and_parity(client, any_device):
    """A scene from a builder (a closure, pickled by value) and contains' parity on closed boxes:
    one process's answers, on 0 rays too."""
    shift = SHIFT.copy()

    def build(device):
        cube = device.mesh(*box())
        return device.scene([cube, vkray.Instance(cube, shift, custom_index=5)])

    scene = build(any_device)
    points = np.random.default_rng(23).uniform(-0.5, 1.8, (N, 3))
    inside = vkray_dask.contains(build, chunked(points, 1500))
    counts = vkray_dask.count(build, *(chunked(a, 999) for a in rays(N, 24)), precision="reference")
    empty = vkray_dask.occluded(build, np.zeros((0, 3)), np.zeros((0, 3)))
    got_inside, got_counts, got_empty = dask.compute(inside, counts, empty)
    np.testing.assert_array_equal(got_inside, scene.contains(points))
    np.testing.assert_array_equal(got_counts, scene.count(*rays(N, 24), precision="reference"))
    assert got_empty.shape == (0,) and got_empty.dtype == bool
    assert 0 < got_inside.mean() < 1


def test_the_scene_reaches_each_worker_once_and_is_built_once(client):
    """12 chunks over 2 workers: each worker receives the spec at most once per computation and
    builds its scene at most once, then keeps it for the next computation."""
    spec = solids_spec(SHIFT + np.eye(4, k=3) * np.random.default_rng().uniform(0.1, 0.2))  # a new scene
    before = client.run(vkray_dask.cache_info)
    origins, directions = (chunked(a, 350) for a in rays(N, 25))
    assert origins.numblocks[0] == 12
    vkray_dask.count(spec, origins, directions).compute()
    middle = client.run(vkray_dask.cache_info)
    vkray_dask.occluded(spec, origins, directions).compute()
    after = client.run(vkray_dask.cache_info)
    for worker in before:
        assert after[worker]["device"] == "0/"  # VKRAY_DEVICE, set per worker
        assert middle[worker]["specs_received"] - before[worker]["specs_received"] <= 1
        assert after[worker]["specs_received"] - middle[worker]["specs_received"] <= 1
        assert middle[worker]["builds"] - before[worker]["builds"] <= 1
        assert after[worker]["builds"] == middle[worker]["builds"]
    assert sum(middle[w]["builds"] - before[w]["builds"] for w in before) >= 1


def test_errors_are_one_process_errors(client, any_device):
    """Bad rows raise at compute time what one Scene raises for the whole batch (the row counted
    in the whole batch); bad shapes, options and specs when the graph is made."""
    spec = solids_spec()
    o, d = rays(N, 26)
    o[2500] = np.nan  # in the third chunk of UNEVEN
    with pytest.raises(ValueError) as want:
        spec.build(any_device).occluded(o, d)
    with pytest.raises(ValueError) as got:
        vkray_dask.occluded(spec, chunked(o, UNEVEN), chunked(d, UNEVEN)).compute()
    assert str(got.value) == str(want.value) and str(want.value).startswith("origins row 2500 is not finite")
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        vkray_dask.contains(spec, da.zeros((10, 2)))
    with pytest.raises(ValueError, match="same shape"):
        vkray_dask.count(spec, da.zeros((10, 3)), da.zeros((9, 3)))
    with pytest.raises(ValueError, match="one per ray"):
        vkray_dask.count(spec, da.zeros((10, 3)), da.ones((10, 3)), tmax=np.ones(9))
    single = spec.build(any_device)
    for bad in ("nonsense", None):  # one device's error type and message
        with pytest.raises((ValueError, TypeError)) as want:
            single.intersect(np.zeros((10, 3)), np.ones((10, 3)), precision=bad)
        with pytest.raises(type(want.value), match="precision") as got:
            vkray_dask.intersect(spec, da.zeros((10, 3)), da.ones((10, 3)), precision=bad)
        if bad is not None:
            assert str(got.value) == str(want.value)
    for ragged in ([[0, 0, 0], [1, 2]], np.array([["a", "b", "c"], ["d", "e", "f"]], dtype=object)):
        with pytest.raises(TypeError) as want:
            single.occluded(ragged, np.ones((2, 3)))
        with pytest.raises(TypeError) as got:
            vkray_dask.occluded(spec, ragged, np.ones((2, 3)))
        assert str(got.value) == str(want.value)
    masked = chunked(o, UNEVEN)[da.from_array(np.arange(N) % 3 == 0, chunks=UNEVEN)]
    with pytest.raises(ValueError, match=r"unknown size .* origins.compute_chunk_sizes\(\)"):
        vkray_dask.occluded(spec, masked, masked)
    with pytest.raises(ValueError, match=r"points has chunks of unknown size"):
        vkray_dask.closest_points(spec, masked)
    with pytest.raises(ValueError, match="unknown hit fields"):
        vkray_dask.intersect(spec, da.zeros((10, 3)), da.ones((10, 3)), outputs=["colour"])
    with pytest.raises(TypeError, match="cuda=True are not for it"):
        vkray_dask.intersect(spec, da.zeros((10, 3)), da.ones((10, 3)), cuda=True)
    with pytest.raises(ValueError, match="unknown keys"):
        vkray_dask.SceneSpec([box()], [{"mesh": 0, "colour": 1}])
    with pytest.raises(ValueError, match="mesh must be in"):
        vkray_dask.SceneSpec([box()], [{"mesh": 1}])
    with pytest.raises(TypeError, match="SceneSpec or a builder"):
        vkray_dask.count(box(), da.zeros((10, 3)), da.ones((10, 3)))


def test_a_spec_keeps_its_content_when_the_callers_arrays_change(client, any_device):
    """The spec copies the meshes: changing the caller's arrays after neither changes the scene
    its key names nor lets a stale scene answer for another spec of the same key."""
    v, f = box()
    moving = v.copy()
    spec = vkray_dask.SceneSpec([(moving, f)])
    moving += [0.4, 0.0, 0.0]
    o, d = rays(N, 27)
    want = vkray_dask.SceneSpec([(v.copy(), f)]).build(any_device).intersect(o, d, outputs=["t", "prim_id"])
    (got,) = dask.compute(vkray_dask.intersect(spec, chunked(o, UNEVEN), chunked(d, UNEVEN), outputs=["t", "prim_id"]))
    np.testing.assert_array_equal(got["t"], want.t)
    assert spec.key == vkray_dask.SceneSpec([(v, f)]).key
    with pytest.raises(ValueError, match="at least one device"):
        vkray_dask.local_cluster([])
    with pytest.raises(ValueError, match=r"threads_per_worker must be in \[1, 1024\], got 0"):
        vkray_dask.local_cluster([0], threads_per_worker=0)
    with pytest.raises(TypeError, match="threads_per_worker must be an integer"):
        vkray_dask.local_cluster([0], threads_per_worker="2")


def test_specs_are_named_by_their_content():
    v, f = box()
    assert vkray_dask.SceneSpec([(v, f)]).key == vkray_dask.SceneSpec([(v.copy(), f.copy())]).key
    assert vkray_dask.SceneSpec([(v, f)]).key != vkray_dask.SceneSpec([(v + 1e-9, f)]).key
    assert vkray_dask.SceneSpec([(v, f)]).key != vkray_dask.SceneSpec([(v, f)], [{"mesh": 0, "mask": 1}]).key
    assert vkray_dask.SceneSpec([(v, f)]).key != vkray_dask.SceneSpec([(v.astype(np.float32), f)]).key


def test_a_worker_killed_mid_computation_is_replaced_and_nothing_is_lost(client, any_device, tmp_path):
    """The last chunk's directions wait for a gate (a file), so that the computation is under way
    until the test opens it. Once a worker holds traced chunks, the test kills that worker's
    process: the chunks it traced are lost with it. Dask replaces the worker, traces the lost
    chunks again, and the answers equal one process's, each ray's once, in order."""
    spec = solids_spec(SHIFT + np.eye(4, k=3) * np.random.default_rng().uniform(0.2, 0.3))  # a new scene
    o, d = rays(N, 27)
    gate = str(tmp_path / "open")
    pids = client.run(os.getpid)

    def wait_at_the_gate(block, block_info=None):
        if block_info[None]["chunk-location"][0] == 9:
            deadline = time.monotonic() + 120
            while not os.path.exists(gate) and time.monotonic() < deadline:
                time.sleep(0.01)
        return block

    directions = chunked(d, 401).map_blocks(wait_at_the_gate, dtype=d.dtype)
    fields = ("t", "prim_id", "instance_id")
    hits = vkray_dask.intersect(spec, chunked(o, 401), directions, outputs=fields)
    assert directions.numblocks[0] == 10
    with get_task_stream(client) as stream:
        started = time.time()
        futures = client.compute(hits)
        victim = None
        deadline = time.monotonic() + 120
        while victim is None and time.monotonic() < deadline:
            # A worker that traced a chunk: what came of it stays there until the gate opens.
            done = client.get_task_stream(start=started)
            victim = next((t["worker"] for t in done if "vkray-intersect" in str(t["key"])), None)
            time.sleep(0.01)
        assert victim is not None, "no worker traced a chunk"
        os.kill(pids[victim], signal.SIGKILL)
        open(gate, "w").close()
        got = futures.result(timeout=120)
    traced = [task["key"] for task in stream.data if "vkray-intersect" in str(task["key"])]
    assert len(traced) > 10 and len(set(traced)) == 10  # some chunks traced twice: lost, then traced again
    want = spec.build(any_device).intersect(o, d, outputs=fields)
    assert_fields_equal(got, hits, want, fields)
    client.wait_for_workers(2, timeout=120)
    assert len(set(pids.values()) - set(client.run(os.getpid).values())) == 1  # one worker process was replaced


def test_rays_from_one_array_are_computed_once_per_chunk(client, any_device, tmp_path):
    """Origins and directions sliced from one (N, 6) dask array, each chunk of which is made by a
    task upstream (generated, read from a file): each such task runs once per computation, not
    once for the origins and again for the directions (no graph optimization that fuses it into
    both slices)."""
    spec = solids_spec()
    o, d = rays(N, 28)
    log = tmp_path / "made"

    def make(block):
        with open(log, "a") as f:  # several worker processes append: one line per run
            f.write(f"{block.shape[0]}\n")
        return block

    both = da.from_array(np.hstack([o, d]), chunks=(1000, 6)).map_blocks(make, dtype=o.dtype)
    hits = vkray_dask.intersect(spec, both[:, :3], both[:, 3:], outputs=["t", "prim_id"])
    blocked = vkray_dask.occluded(spec, both[:, :3], both[:, 3:])
    got, got_blocked = dask.compute(hits, blocked)
    runs = [int(n) for n in log.read_text().split() if n != "0"]  # 0: dask's try on an empty block
    assert sorted(runs) == sorted(both.chunks[0])  # each chunk made once, for both queries
    want = spec.build(any_device).intersect(o, d, outputs=["t", "prim_id"])
    assert_fields_equal(got, hits, want, ["t", "prim_id"])
    np.testing.assert_array_equal(got_blocked, want.hit)


def test_local_clusters_share_the_cores(client):
    """Each of local_cluster's workers runs its host passes on its share of the cores
    (RAYON_NUM_THREADS), unless this process's environment chose for them."""
    expected = os.environ.get("RAYON_NUM_THREADS", str(max(1, usable_cores() // 2)))
    found = client.run(lambda: os.environ.get("RAYON_NUM_THREADS"))
    assert len(found) == 2 and set(found.values()) == {expected}


def test_local_clusters_share_the_machines_memory(client):
    """Each of local_cluster's workers may hold its share of the machine's memory (two workers:
    half each), not a Nanny's default share of one thread's (the machine over its CPU cores)."""
    from distributed.system import MEMORY_LIMIT

    limits = [w["memory_limit"] for w in client.scheduler_info()["workers"].values()]
    assert len(limits) == 2 and all(abs(limit - MEMORY_LIMIT / 2) <= 1 for limit in limits)
    with vkray_dask.local_cluster([0], memory_limit="1 GiB") as cluster, Client(cluster) as one:
        one.wait_for_workers(1)
        assert [w["memory_limit"] for w in one.scheduler_info()["workers"].values()] == [2**30]


_RELEASE_SLOW_BUILD = threading.Event()


def _slow_build(device):
    """A builder (pickled by reference, as a function of this module) that waits to be let go."""
    assert _RELEASE_SLOW_BUILD.wait(60)
    return device.scene(device.mesh(*triangle_soup(10, seed=31)))


def test_a_scene_being_built_holds_up_only_its_own_tasks(monkeypatch):
    """A worker's threads (here, this process's): while one scene is built, a task of a scene
    already built gets it at once and `cache_info` answers; other tasks of the scene being built
    wait for that one build and share it."""
    monkeypatch.setenv("VKRAY_VALIDATION", "1" if VALIDATION else "0")
    built = vkray_dask.SceneSpec([box()])
    release = _RELEASE_SLOW_BUILD
    release.clear()
    slow = vkray_dask.SceneSpec.from_builder(_slow_build)
    first = vkray_dask._worker_scene(built)
    builds = vkray_dask.cache_info()["builds"]
    results = [None, None]

    def get_slow(k):
        results[k] = vkray_dask._worker_scene(slow)

    waiting = [threading.Thread(target=get_slow, args=(k,)) for k in range(2)]
    for t in waiting:
        t.start()
    try:
        time.sleep(0.2)
        meanwhile = []
        def ask():
            meanwhile.extend([vkray_dask._worker_scene(built), vkray_dask.cache_info()])

        other = threading.Thread(target=ask)
        other.start()
        other.join(5)
        assert meanwhile and meanwhile[0] is first, "a built scene's task waited for another scene's build"
        assert slow.key not in meanwhile[1]["scenes"]
    finally:
        release.set()
        for t in waiting:
            t.join(60)
    assert results[0] is results[1] is not None
    assert vkray_dask.cache_info()["builds"] == builds + 1


def test_each_chunk_is_one_task_and_one_more_per_field(client):
    """A chunk's query is one task and each field one task taking it out of the answer; a query
    that returns one array, one task a chunk. No alias tasks (`da.from_delayed` and
    `da.concatenate` made two more per field, each a task the workers ran)."""
    spec = solids_spec()
    o, d = rays(N, 29)
    origins, directions = chunked(o, UNEVEN), chunked(d, UNEVEN)
    hits = vkray_dask.intersect(spec, origins, directions, outputs=["t", "prim_id"])
    blocked = vkray_dask.occluded(spec, origins, directions)
    with get_task_stream(client) as stream:
        dask.compute(hits, blocked)
    ran = [str(t["key"]) for t in stream.data if "vkray-scene-" not in str(t["key"])]
    chunks = len(UNEVEN)
    queries = [k for k in ran if "vkray-intersect-" in k]
    fields = [k for k in ran if "-of-intersect-" in k]
    assert len(queries) == chunks and len(fields) == 2 * chunks, ran
    assert len([k for k in ran if "vkray-" in k]) == 4 * chunks, ran  # the occluded: one a chunk
    assert not [k for k in ran if "from-value" in k or "concatenate" in k], ran


def _loaded(array):
    return array


def test_keys_of_the_callers_named_as_fields_are_not_taken_for_them(client, any_device):
    """Rays that a caller's graph holds under the keys "result" and "t" (as a field is named):
    the answers are still the fields, not those arrays."""
    spec = solids_spec()
    o, d = rays(N, 33)
    origins = da.from_delayed(dask.delayed(_loaded)(o, dask_key_name="result"), shape=o.shape, dtype=o.dtype)
    directions = da.from_delayed(dask.delayed(_loaded)(d, dask_key_name="t"), shape=d.shape, dtype=d.dtype)
    blocked = vkray_dask.occluded(spec, origins, directions)
    hits = vkray_dask.intersect(spec, origins, directions, outputs=["t", "prim_id"])
    got_blocked, got_hits = dask.compute(blocked, hits)
    scene = spec.build(any_device)
    np.testing.assert_array_equal(got_blocked, scene.occluded(o, d))
    assert_fields_equal(got_hits, hits, scene.intersect(o, d, outputs=["t", "prim_id"]), ("t", "prim_id"))
