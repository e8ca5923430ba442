"""Query semantics: interval bounds, occlusion, outputs, shapes, chunking, the GIL, backends."""

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import vkray
from conftest import BACKENDS, make_device
from oracle import embree, load_mesh, random_rays

# One triangle in the plane z = 1 covering (0,0)-(1,0)-(0,1).
TRIANGLE = (np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float32), np.array([[0, 1, 2]], np.int32))


@pytest.fixture
def triangle_scene(device):
    return device.scene(device.mesh(*TRIANGLE))


def test_t_is_in_units_of_direction_length(triangle_scene):
    hits = triangle_scene.intersect([[0.2, 0.2, 0.0]] * 3, [[0, 0, 1], [0, 0, 2], [0, 0, 0.25]])
    np.testing.assert_allclose(hits.t, [1.0, 0.5, 4.0], rtol=1e-6)


def test_tmin_tmax_bound_the_interval(triangle_scene):
    o = [0.2, 0.2, 0.0]
    d = [0.0, 0.0, 1.0]
    # One ray in, 0-d results out, as numpy broadcasting gives.
    assert triangle_scene.intersect(o, d, tmax=0.5).hit.shape == ()
    assert not triangle_scene.intersect(o, d, tmax=0.5).hit
    assert triangle_scene.intersect(o, d, tmax=1.5).hit
    assert not triangle_scene.intersect(o, d, tmin=1.5).hit
    assert triangle_scene.intersect(o, d, tmin=0.5, tmax=1.5).hit
    # Per-ray bounds, broadcast against one ray.
    tmax = np.array([0.5, 0.999, 1.001, np.inf])
    assert triangle_scene.intersect(o, d, tmax=tmax).hit.tolist() == [False, False, True, True]
    tmin = np.array([0.0, 0.999, 1.001, 2.0])
    assert triangle_scene.intersect(o, d, tmin=tmin).hit.tolist() == [True, True, False, False]
    assert triangle_scene.occluded(o, d, tmin=tmin).tolist() == [True, True, False, False]


def test_one_origin_repeated_by_broadcasting_is_neither_copied_nor_answered_differently(device):
    """A camera's eye as ``np.broadcast_to(eye, (n, 3))`` (a stride-0 view, in a batch of any
    shape) answers as the same rays written out, and vkray does not write the n rows out itself
    (numpy's allocations, which tracemalloc sees, stay far below the rows' size)."""
    import tracemalloc

    v, f = load_mesh("fandisk")
    scene = device.scene(device.mesh(v, f))
    eye = v.mean(axis=0) + np.array([0.0, 0.0, 3.0]) * np.ptp(v, axis=0).max()
    directions = (v.mean(axis=0) - eye) + np.random.default_rng(3).uniform(-0.5, 0.5, (200, 1000, 3))
    repeated = np.broadcast_to(eye, directions.shape)
    written = np.ascontiguousarray(repeated)
    want_hits, want_counts = scene.intersect(written, directions), scene.count(written, directions)
    tracemalloc.start()
    try:
        hits, counts = scene.intersect(repeated, directions), scene.count(repeated, directions)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert want_hits.hit.mean() > 0.3
    np.testing.assert_array_equal(hits.t, want_hits.t)
    np.testing.assert_array_equal(hits.prim_id, want_hits.prim_id)
    np.testing.assert_array_equal(counts, want_counts)
    # The answers' own arrays take about 7 MB; the eye written out would add 4.8 MB.
    answers = sum(getattr(hits, name).nbytes for name in vkray.HIT_FIELDS if getattr(hits, name) is not None)
    answers += counts.nbytes
    assert peak < answers + 2_000_000, (peak, answers)


def one_row_batches(v):
    """(origins, directions) pairs whose inputs are each one row repeated by broadcasting (or a
    single (3,) vector): the batch's size comes from the broadcast shapes alone."""
    eye = v.mean(axis=0) + np.array([0.0, 0.0, 3.0]) * np.ptp(v, axis=0).max()
    toward = v.mean(axis=0) - eye
    return [
        (np.broadcast_to(eye, (500, 3)), toward),
        (eye, np.broadcast_to(toward, (500, 3))),
        (np.broadcast_to(eye, (500, 3)), np.broadcast_to(toward, (500, 3))),
        (np.broadcast_to(eye, (2, 1, 3)), np.broadcast_to(toward, (1, 250, 3))),
    ]


def check_one_row_batches(scene, v):
    for origins, directions in one_row_batches(v):
        shape = np.broadcast_shapes(np.shape(origins)[:-1], np.shape(directions)[:-1])
        written = [np.ascontiguousarray(np.broadcast_to(a, shape + (3,))) for a in (origins, directions)]
        hits, want = scene.intersect(origins, directions), scene.intersect(*written)
        assert hits.t.shape == shape and np.isfinite(hits.t).all()
        np.testing.assert_array_equal(hits.t, want.t)
        np.testing.assert_array_equal(scene.count(origins, directions), scene.count(*written))
        np.testing.assert_array_equal(scene.occluded(origins, directions), np.ones(shape, bool))


def test_inputs_each_one_row_answer_the_whole_broadcast_batch(device):
    """Origins and directions each one row (a single vector, or a row repeated by broadcasting)
    answer every ray of the batch their shapes broadcast to, as the rays written out do."""
    v, f = load_mesh("fandisk")
    check_one_row_batches(device.scene(device.mesh(v, f)), v)


def test_a_group_answers_inputs_each_one_row_for_the_whole_batch():
    """The same through a DeviceGroup, which splits the batch's rays over its devices: every
    piece answers its own rows (a piece that answered fewer would leave rows unwritten)."""
    v, f = load_mesh("fandisk")
    group = vkray.DeviceGroup(["cpu", "cpu"])
    check_one_row_batches(group.scene([group.mesh(v, f)]), v)


def test_rays_from_behind_and_missing(triangle_scene):
    hits = triangle_scene.intersect(
        [[0.2, 0.2, 2.0], [0.9, 0.9, 0.0], [0.2, 0.2, 0.0]], [[0, 0, -1], [0, 0, 1], [0, 0, -1]]
    )
    assert hits.hit.tolist() == [True, False, False]
    # Back faces are hit too (no culling); the normal keeps the triangle's winding.
    np.testing.assert_allclose(hits.normal[0], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(hits.uv[0], [0.2, 0.2], atol=1e-6)


def test_occluded_equals_intersect_hit(device):
    v, f = load_mesh("stanford-bunny")
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 50000, seed=5)
    tmax = np.random.default_rng(5).uniform(0.2, 1.2, len(origins))
    hits = scene.intersect(origins, directions, tmax=tmax)
    blocked = scene.occluded(origins, directions, tmax=tmax)
    np.testing.assert_array_equal(blocked, hits.hit)
    assert 0.1 < blocked.mean() < 0.9
    np.testing.assert_array_equal(blocked, embree([(v, f)], origins, directions, tmax=tmax, query="OCCLUDED"))


def test_the_core_makes_hit_bools_as_it_copies_hits_out(device):
    """The core's "hit" output (a bool a ray, occluded's answer) is prim_id >= 0 of the same
    trace, in every tier, beside prim_id or alone, from several threads at once, also where the
    f64 tiers turn the GPU's hits into misses (tmax at each hit's f32 t); queries of other kinds,
    closest_points and out= refuse it."""
    from test_precision import tiers

    v, f = load_mesh("stanford-bunny")
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 20000, seed=8)
    tmax = np.random.default_rng(8).uniform(0.2, 1.2, len(origins))
    batch = vkray._device._RayBatch(vkray.RayQuery("intersect", origins, directions, 0.0, tmax))

    def trace(query, fields, precision="fast", **kw):
        return scene._core.trace(*batch.arrays, query, fields, precision, None, batch.mask, **kw)

    for precision in tiers(device):
        both = trace("closest", ["prim_id", "hit"], precision)
        assert both["hit"].dtype == np.bool_ and both["hit"].shape == (len(origins),)
        np.testing.assert_array_equal(both["hit"], both["prim_id"] >= 0, err_msg=precision)
        assert 0.1 < both["hit"].mean() < 0.9
        with ThreadPoolExecutor(3) as pool:
            alone = list(pool.map(lambda tier: trace("occluded", ["hit"], tier)["hit"], [precision] * 3))
        for answer in alone:
            np.testing.assert_array_equal(answer, both["hit"], err_msg=precision)
    t = trace("closest", ["t"])["t"]
    met = np.isfinite(t)
    batch = vkray._device._RayBatch(vkray.RayQuery("intersect", origins, directions, 0.0, np.where(met, t, 1.0)))
    for precision in tiers(device):
        both = trace("closest", ["prim_id", "hit"], precision)
        np.testing.assert_array_equal(both["hit"], both["prim_id"] >= 0, err_msg=f"{precision}, tmax at t")
        if precision != "fast":
            assert (both["prim_id"][met] < 0).sum() > 100, precision  # the f64 tiers' misses at tmax
    with pytest.raises(ValueError, match="hit .* closest and occluded"):
        trace("count", ["hit"])
    with pytest.raises(ValueError, match="not an output of closest_points"):
        scene._core.closest_points(origins, ["hit"], np.inf, "exact")
    with pytest.raises(ValueError, match="no output of out="):
        trace("closest", ["hit"], out={"hit": np.zeros(len(origins), bool)})


def test_outputs_select_fields(triangle_scene):
    hits = triangle_scene.intersect([0.2, 0.2, 0.0], [0, 0, 1], outputs=["normal"])
    assert hits.t is None and hits.uv is None
    assert hits.normal is not None and hits.prim_id is not None  # prim_id keeps Hits.hit working
    assert hits.hit
    every = triangle_scene.intersect([[0.2, 0.2, 0.0]], [0, 0, 1], outputs=vkray.HIT_FIELDS)
    assert every.geometry_id.tolist() == [0]
    with pytest.raises(ValueError, match="unknown hit fields"):
        triangle_scene.intersect([0.2, 0.2, 0.0], [0, 0, 1], outputs=["colour"])


def test_hits_keep_the_rays_shape(triangle_scene):
    ys, xs = np.mgrid[0.01:0.99:8j, 0.02:0.97:5j]  # no ray through an edge
    origins = np.stack([xs, ys, np.zeros_like(xs)], axis=-1)
    hits = triangle_scene.intersect(origins, [0, 0, 1])
    assert hits.t.shape == (8, 5) and hits.uv.shape == (8, 5, 2) and hits.normal.shape == (8, 5, 3)
    np.testing.assert_array_equal(hits.hit, xs + ys < 1.0)
    assert 0 < hits.hit.sum() < hits.hit.size
    assert triangle_scene.occluded(origins, [0, 0, 1]).shape == (8, 5)


def test_zero_rays(triangle_scene):
    hits = triangle_scene.intersect(np.zeros((0, 3)), np.zeros((0, 3)))
    assert hits.t.shape == (0,) and hits.uv.shape == (0, 2) and hits.normal.shape == (0, 3) and len(hits) == 0
    assert triangle_scene.occluded(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_empty_scene_misses_everything(device):
    hits = device.scene([]).intersect([[0, 0, 0]], [[0, 0, 1]])
    assert hits.hit.tolist() == [False] and hits.prim_id.tolist() == [-1]


def test_mixed_dtypes_and_layouts_agree(triangle_scene):
    rng = np.random.default_rng(6)
    o = np.column_stack([rng.uniform(-0.2, 1.2, (500, 2)), np.zeros(500)])
    d = np.tile([0.0, 0.0, 1.0], (500, 1))
    base = triangle_scene.intersect(o, d)
    fortran = triangle_scene.intersect(np.asfortranarray(o.astype(np.float32)), d[:, ::-1][:, ::-1])
    np.testing.assert_array_equal(base.t, fortran.t)
    strided = np.zeros((500, 6))
    strided[:, ::2] = o
    np.testing.assert_array_equal(triangle_scene.intersect(strided[:, ::2], d).t, base.t)
    np.testing.assert_array_equal(triangle_scene.intersect(o.tolist(), d.astype(np.int64)).t, base.t)


def test_chunk_boundaries_do_not_change_results(device):
    v, f = load_mesh("spot")
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 10007, seed=7)
    whole = scene.intersect(origins, directions, outputs=vkray.HIT_FIELDS)
    saved = device.chunk_rays
    try:
        device.chunk_rays = 1000  # 11 chunks, the last one partial, two in flight
        chunked = scene.intersect(origins, directions, outputs=vkray.HIT_FIELDS)
        # Rays are checked as each chunk is packed: a bad ray in chunk 9, with chunks in flight,
        # is reported by its own row, and the device carries on.
        bad = directions.copy()
        bad[8500] = np.nan
        with pytest.raises(ValueError, match="directions row 8500 is not finite"):
            scene.intersect(origins, bad)
        with pytest.raises(ValueError):
            device.chunk_rays = 0
    finally:
        device.chunk_rays = saved
    for name in vkray.HIT_FIELDS:
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), err_msg=name)


def test_profile_splits_host_and_gpu_time(device):
    v, f = load_mesh("stanford-bunny")
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 50_000, seed=3)
    scene.intersect(origins, directions)
    p = device.last_trace_profile
    # Chunks are paced (src/trace/pacer.rs): the first 2^14 rays a host thread on the CPU engine
    # (`first_on_cpu`, two threads at least), 2^15 on a software GPU (lavapipe), 2^20 on a GPU.
    if device.engine == "cpu":
        first = 2**14 * max(p["host_threads"], 2)
    else:
        first = 2**15 if device.info.is_software else 2**20
    assert p["rays"] == 50_000 and (p["chunks"] >= 2 if first < 50_000 else p["chunks"] == 1)
    if device.engine == "cpu":
        # The host does it all, block by block: packing, Embree's traversal, writing the fields
        # (host_f64's place).
        assert p["gpu_trace"] is None and 0 < p["pack"] + p["host_f64"] + p["unpack"] <= p["total"]
        scene.intersect_all(origins, directions)
        p = device.last_trace_profile
        assert p["rays"] == 50_000 and 0 < p["total"] and p["gpu_trace"] is None
        return
    host = p["pack"] + p["submit"] + p["wait"] + p["unpack"]
    assert 0 < host <= p["total"]
    if device.limits["timestamp_valid_bits"]:
        # The device's clock: the trace itself takes time, and all GPU phases fit in the wait.
        assert p["gpu_trace"] > 0
        assert p["gpu_upload"] + p["gpu_trace"] + p["gpu_readback"] <= p["total"]
    else:
        assert p["gpu_trace"] is None
    assert p["store"] == 0.0
    # All hits: a counting pass, then a storing pass over each chunk (two chunks at least on a CPU
    # device); the storing passes' time apart.
    scene.intersect_all(origins, directions)
    p = device.last_trace_profile
    assert (p["chunks"] >= 2 if first < 50_000 else p["chunks"] == 1) and 0 < p["store"] < p["total"]
    if device.limits["timestamp_valid_bits"]:
        assert p["gpu_upload"] + p["gpu_trace"] + p["gpu_readback"] <= p["total"]


def test_ten_million_rays(device):
    """Beyond one chunk (and, on lavapipe, well past nothing but the staging bound)."""
    n = 10_000_000
    assert n > device.chunk_rays
    v = np.array([[-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], np.float32)
    scene = device.scene(device.mesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.uint16)))
    rng = np.random.default_rng(8)
    origins = np.zeros((n, 3), np.float32)
    origins[:, :2] = rng.uniform(-1.5, 1.5, (n, 2))
    hits = scene.intersect(origins, np.array([0, 0, 2], np.float32), outputs=["t"])
    inside = np.all(np.abs(origins[:, :2]) < 1, axis=1)
    edge = np.any(np.abs(np.abs(origins[:, :2]) - 1) < 1e-6, axis=1)
    assert np.array_equal(np.isfinite(hits.t)[~edge], inside[~edge])
    np.testing.assert_allclose(hits.t[inside], 0.5, rtol=1e-6)


def test_gil_is_released_while_tracing(device):
    """While the GPU works (the profile's `wait`), other Python threads run. Packing and unpacking
    hold the GIL by design, so the ticks are measured against the wait time alone."""
    v, f = load_mesh("stanford-bunny")
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 400_000, seed=9)
    done = threading.Event()
    worker = threading.Thread(target=lambda: (scene.intersect(origins, directions), done.set()))
    ticks = 0
    worker.start()
    while not done.is_set():
        ticks += 1
        time.sleep(0.001)
    worker.join()
    gpu_wait = device.last_trace_profile["wait"]
    # Had the wait held the GIL, this thread could not have ticked through it.
    assert ticks >= 0.3 * gpu_wait / 0.002, f"{ticks} ticks during {gpu_wait:.3f}s of GPU wait"


@pytest.mark.skipif(len(BACKENDS) < 2, reason="the device offers one backend")
@pytest.mark.parametrize("name", ["stanford-bunny", "fandisk", "spot", "cow", "teapot"])
def test_backends_return_identical_hits(name):
    v, f = load_mesh(name)
    origins, directions = random_rays(v, 30000, seed=10)
    results = []
    for backend in ("ray_query", "pipeline"):
        device = make_device(backend)
        scene = device.scene(device.mesh(v, f))
        results.append(scene.intersect(origins, directions, outputs=vkray.HIT_FIELDS))
    a, b = results
    for name in ("prim_id", "instance_id", "custom_index", "geometry_id"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    hit = a.hit
    ulps = np.abs(a.t[hit].view(np.int32).astype(np.int64) - b.t[hit].view(np.int32).astype(np.int64))
    assert ulps.max(initial=0) <= 1


def test_discrete_gpu_staging_path_gives_the_same_hits(device, tmp_path):
    """VKRAY_STAGING=1 takes the discrete-GPU path (staging buffers and copies) on any device."""
    import subprocess
    import sys

    if device.engine == "cpu":
        pytest.skip("the CPU engine has no staging: VKRAY_STAGING is a Vulkan device's path")
    v, f = load_mesh("cow")
    origins, directions = random_rays(v, 5000, seed=12)
    hits = device.scene(device.mesh(v, f)).intersect(origins, directions)
    np.savez(tmp_path / "rays.npz", v=v, f=f, o=origins, d=directions)
    script = (
        "import sys, numpy as np, vkray\n"
        "a = np.load(sys.argv[1])\n"
        f"d = vkray.Device(backend={device.backend!r}, validation={device.validation})\n"
        "h = d.scene(d.mesh(a['v'], a['f'])).intersect(a['o'], a['d'])\n"
        "np.savez(sys.argv[2], t=h.t, prim=h.prim_id, normal=h.normal)\n"
    )
    env = dict(__import__("os").environ, VKRAY_STAGING="1")
    command = [sys.executable, "-c", script, str(tmp_path / "rays.npz"), str(tmp_path / "out.npz")]
    subprocess.run(command, check=True, env=env)
    staged = np.load(tmp_path / "out.npz")
    np.testing.assert_array_equal(staged["t"], hits.t)
    np.testing.assert_array_equal(staged["prim"], hits.prim_id)
    np.testing.assert_array_equal(staged["normal"], hits.normal)


def test_out_writes_the_same_hits_into_the_callers_arrays(device):
    """intersect(out=hits) writes every field into the earlier call's arrays (filled with junk
    first: every element is written), equal to a fresh call's, which agrees with Embree."""
    v, f = load_mesh("spot")
    scene = device.scene(device.mesh(v, f))
    # Rays of shape (50, 100, 3): the arrays are reshaped views of out's, not copies.
    o1, d1, o2, d2 = (a.astype(np.float32).reshape(50, 100, 3) for a in (*random_rays(v, 5000, seed=3),
                                                                         *random_rays(v, 5000, seed=4)))
    for fields in (vkray.HIT_FIELDS, ("t", "prim_id")):
        previous = scene.intersect(o1, d1, outputs=fields)
        for name in fields:
            array = getattr(previous, name)
            array[...] = -7 if array.dtype.kind == "i" else np.float32(1234.5)
        fresh = scene.intersect(o2, d2, outputs=fields)
        reused = scene.intersect(o2, d2, outputs=fields, out=previous)
        for name in fields:
            got = getattr(reused, name)
            assert np.shares_memory(got, getattr(previous, name)), name
            np.testing.assert_array_equal(got, getattr(fresh, name), err_msg=name)
    reference = embree([(v, f)], o2.reshape(-1, 3), d2.reshape(-1, 3))
    assert (reused.hit.reshape(-1) == (reference["primID"] >= 0)).mean() >= 0.999


def test_out_is_refused_where_it_cannot_be_written(triangle_scene):
    o = np.zeros((4, 3), np.float32)
    d = np.tile(np.array([0.1, 0.1, 1.0], np.float32), (4, 1))
    hits = triangle_scene.intersect(o, d, outputs=("t", "prim_id"))
    with pytest.raises(TypeError, match="Hits"):
        triangle_scene.intersect(o, d, out={"t": hits.t})
    with pytest.raises(ValueError, match="shape"):
        triangle_scene.intersect(o[:3], d[:3], outputs=("t", "prim_id"), out=hits)
    with pytest.raises(ValueError, match="no uv"):
        triangle_scene.intersect(o, d, outputs=("t", "uv"), out=hits)
    with pytest.raises(ValueError, match="widths"):
        triangle_scene.intersect(o, d, outputs=("t", "prim_id"), precision="reference", out=hits)
    hits.t.flags.writeable = False
    with pytest.raises(ValueError, match="writeable"):
        triangle_scene.intersect(o, d, outputs=("t", "prim_id"), out=hits)
    # An output sharing memory with the rays: numpy's borrow tracking refuses it in the core.
    rays = np.zeros((4, 3), np.float32)
    rays[:, 2] = 1.0
    sharing = vkray.Hits((4,), {"t": rays.reshape(-1)[:4], "prim_id": np.empty(4, np.int32)}, "fast")
    with pytest.raises(ValueError, match="shares memory"):
        triangle_scene.intersect(o, rays, outputs=("t", "prim_id"), out=sharing)
    # The core refuses it too (numpy's borrow tracking), whatever the Python layer checked.
    with pytest.raises(ValueError, match="cannot be written by this call"):
        triangle_scene._core.trace(o, rays, 0.0, np.inf, "closest", ["t", "prim_id"], out={"t": sharing.t})
    np.testing.assert_array_equal(rays[:, 2], 1.0)  # nothing was written into the rays
    wrong_dtype = vkray.Hits((4,), {"t": np.empty(4, np.float64), "prim_id": np.empty(4, np.int32)}, "fast")
    with pytest.raises(ValueError, match="float32"):
        triangle_scene.intersect(o, d, outputs=("t", "prim_id"), out=wrong_dtype)


def test_out_from_several_threads(device):
    """Threads each looping over frames into their own out= arrays get a fresh call's answers."""
    v, f = load_mesh("spot")
    scene = device.scene(device.mesh(v, f))
    rays = [random_rays(v, 3001, seed=20 + k) for k in range(4)]
    expected = [scene.intersect(o, d) for o, d in rays]
    failures = []

    def worker(k):
        try:
            hits = scene.intersect(*rays[(k + 1) % 4])
            for frame in range(6):
                hits = scene.intersect(*rays[(k + frame) % 4], out=hits)
                want = expected[(k + frame) % 4]
                for name in vkray.DEFAULT_FIELDS:
                    np.testing.assert_array_equal(getattr(hits, name), getattr(want, name), err_msg=name)
        except Exception as e:  # noqa: BLE001 - reported below
            failures.append(e)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not failures, failures


def test_an_array_being_written_is_refused_as_another_calls_input(device):
    """While one call writes out='s arrays (its progress callback runs between chunks), another
    call given one of them as input gets a ValueError, not a panic."""
    scene = device.scene(device.mesh(*TRIANGLE))
    n = 8000
    o = np.zeros((n, 3))
    d = np.tile([0.1, 0.1, 1.0], (n, 1))
    hits = scene.intersect(o, d, outputs=("t", "prim_id"), precision="exact")  # t: float64, as tmax
    seen = []

    def progress(done, total):
        try:
            scene.intersect(o, d, tmax=hits.t, precision="exact")
            seen.append("read")
        except ValueError as e:
            seen.append(str(e))

    saved = device.chunk_rays
    try:
        device.chunk_rays = 1000
        scene._core.trace(o, d, 0.0, np.inf, "closest", ["t", "prim_id"], "exact", progress=progress,
                          out={"t": hits.t, "prim_id": hits.prim_id})
    finally:
        device.chunk_rays = saved
    assert seen and all("another call is writing it" in m for m in seen), seen
    np.testing.assert_array_equal(hits.prim_id, 0)
