"""Every query of CUDA arrays (torch, cupy) answers in CUDA memory: the queries and tiers without
a GPU-resident path (the refined tier, the point queries, all hits a ray of which the GPU cannot
settle) go through the host and hand back `vkray.CudaArray`s on the arrays' GPU. The oracle: the
same query of numpy arrays, which must agree bit for bit (checked against Embree, brute force and
analytic answers elsewhere). Runs where torch sees a CUDA GPU that is the vkray device."""

from __future__ import annotations

import numpy as np
import pytest

import oracle
import vkray

torch = pytest.importorskip("torch")
if not torch.cuda.is_available():
    pytest.skip("torch sees no CUDA GPU", allow_module_level=True)

DEVICE = vkray.Device()


@pytest.fixture(scope="module")
def bunny():
    v, f = oracle.load_mesh("stanford-bunny")
    scene = DEVICE.scene([DEVICE.mesh(v, f)])
    if DEVICE.cuda_device is None:
        pytest.skip("this vkray device shares no memory with CUDA")
    return v, scene


def cuda(array: np.ndarray):
    return torch.from_numpy(np.ascontiguousarray(array)).cuda()


def on_host(array) -> np.ndarray:
    assert isinstance(array, vkray.CudaArray), type(array)
    return torch.from_dlpack(array).cpu().numpy()


def assert_same(found, expected, err_msg=""):
    """Equal values, dtypes and shapes (numpy's own check lets a dtype or a 0-d shape differ)."""
    np.testing.assert_array_equal(found, expected, err_msg=err_msg, strict=True)


@pytest.fixture
def never_through_host(monkeypatch):
    """Fails a query that would copy CUDA arrays through the host: a test of the GPU-resident path
    must not pass by the host path's (equal) answers."""

    def refuse(self, query, run):
        raise AssertionError(f"{query.kind} (precision={query.precision!r}) went through the host")

    monkeypatch.setattr(vkray._device.Scene, "_through_host", refuse)


def points_around(v: np.ndarray, n: int, seed: int) -> np.ndarray:
    lo, hi = v.min(axis=0), v.max(axis=0)
    pad = 0.1 * (hi - lo)
    return np.random.default_rng(seed).uniform(lo - pad, hi + pad, (n, 3))


@pytest.mark.parametrize("precision", ["fast", "refined", "exact", "reference"])
def test_ray_queries_of_every_tier_answer_on_the_gpu(bunny, precision):
    v, scene = bunny
    o, d = oracle.random_rays(v, 20_000, seed=1)
    fields = ["t", "prim_id", "uv", "normal", "position"]
    hits = scene.intersect(cuda(o), cuda(d), outputs=fields, precision=precision)
    want = scene.intersect(o, d, outputs=fields, precision=precision)
    for name in fields:
        assert_same(on_host(getattr(hits, name)), getattr(want, name), err_msg=name)
    assert "on cuda" in repr(hits)
    blocked = scene.occluded(cuda(o), cuda(d), precision=precision)
    assert blocked.dtype == "int32"  # as the fast tier's GPU-resident answer: the blocking triangle
    assert_same(on_host(blocked) >= 0, scene.occluded(o, d, precision=precision))
    counts = scene.count(cuda(o), cuda(d), precision=precision)
    assert_same(on_host(counts), scene.count(o, d, precision=precision))
    light = scene.transmittance(cuda(o), cuda(d), precision=precision)
    assert_same(on_host(light), scene.transmittance(o, d, precision=precision))


@pytest.mark.parametrize("precision", ["fast", "exact"])
def test_all_hits_come_back_as_cuda_csr_arrays(bunny, precision):
    v, scene = bunny
    o, d = oracle.random_rays(v, 20_000, seed=2)
    found = scene.intersect_all(cuda(o), cuda(d), precision=precision, outputs=["t", "prim_id"])
    want = scene.intersect_all(o, d, precision=precision, outputs=["t", "prim_id"])
    for name in ("offsets", "ray_index", "counts", "t", "prim_id"):
        assert_same(on_host(getattr(found, name)), getattr(want, name), err_msg=name)
    assert found.offsets.dtype == "int64" and len(found) == 20_000
    assert want.counts.max() >= 4  # rays through the bunny cross it several times
    with pytest.raises(TypeError, match="on the GPU"):
        found[0]


ALL_HIT_FIELDS = ["t", "uv", "prim_id", "instance_id", "geometry_id"]


def assert_same_all_hits(found, want, fields, err_msg=""):
    """Every array of two `AllHits`, one in CUDA memory, equal bit for bit."""
    for name in ["offsets", "ray_index", "counts"] + fields:
        assert_same(on_host(getattr(found, name)), getattr(want, name), err_msg=f"{name} {err_msg}")
    assert found.shape == want.shape


@pytest.mark.parametrize("precision", ["fast", "exact"])
def test_all_hits_of_cuda_rays_stay_on_the_gpu(bunny, precision, never_through_host):
    """All hits of CUDA rays, traced, stored and written as columns without the host: every field
    equal to the numpy path's bit for bit, for random and camera rays, float32 and float64, a
    tmax array, max_hits, and rays 1e6 away (the fast tier's
    far rays, advanced before tracing and their hits' t moved back on the GPU), and one field
    alone."""
    v, scene = bunny
    o, d = oracle.random_rays(v, 20_000, seed=40)
    eye, directions = oracle.camera_rays(v, 96, 64)
    far = o + 1e6 * np.array([0.6, 0.0, 0.8])
    cases = {
        "random": (o, d, {}),
        "float32": (o.astype(np.float32), d.astype(np.float32), {}),
        "camera": (np.broadcast_to(eye, directions.shape), directions, {}),
        "tmax": (o, d, {"tmax": np.random.default_rng(41).uniform(0.0, 3.0, len(o))}),
        "max_hits": (o, d, {"max_hits": 2}),
        "cull": (o, d, {"cull": "back"}),
        "far": (far, o - far, {}),
    }
    for name, (origins, dirs, options) in cases.items():
        on_gpu = {k: cuda(a) if isinstance(a, np.ndarray) else a for k, a in options.items()}
        found = scene.intersect_all(cuda(origins), cuda(dirs), outputs=ALL_HIT_FIELDS, precision=precision, **on_gpu)
        want = scene.intersect_all(origins, dirs, outputs=ALL_HIT_FIELDS, precision=precision, **options)
        assert_same_all_hits(found, want, ALL_HIT_FIELDS, name)
        assert want.ray_index.size > 1000, name
    one = scene.intersect_all(cuda(o), cuda(d), outputs=["geometry_id"], precision=precision)
    assert_same_all_hits(one, scene.intersect_all(o, d, outputs=["geometry_id"], precision=precision), ["geometry_id"])
    profile = DEVICE.last_trace_profile
    assert profile["gpu_columns"] >= 1 and profile["rays"] == len(o), profile


def test_all_hits_of_cuda_rays_through_translucent_and_placed_instances(never_through_host):
    """A scene of instances (one mirrored, one translucent): the GPU-resident all hits keep the
    opaque hits only (and the translucent ones where the threshold lets them count), each with
    its instance, as numpy's do."""
    if DEVICE.cuda_device is None:
        pytest.skip("this vkray device shares no memory with CUDA")
    v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    lifted, mirrored = np.eye(4), np.diag([-1.0, 1.0, 1.0, 1.0])
    lifted[2, 3], mirrored[2, 3] = 0.5, 1.0
    scene = DEVICE.scene([
        DEVICE.mesh(v, f),
        vkray.Instance(DEVICE.mesh(v, f, opacity=0.25), lifted),
        vkray.Instance(DEVICE.mesh(v, f), mirrored),
    ])
    rng = np.random.default_rng(44)
    o = np.column_stack([rng.uniform(-1.2, 1.2, (2000, 2)), np.full(2000, -1.0)])
    d = np.tile([0.0, 0.0, 1.0], (2000, 1))
    fields = ["t", "uv", "prim_id", "instance_id", "geometry_id"]
    for precision in ("fast", "exact"):
        for threshold in (0.5, 0.2):
            found = scene.intersect_all(cuda(o), cuda(d), outputs=fields, precision=precision,
                                        opacity_threshold=threshold)
            want = scene.intersect_all(o, d, outputs=fields, precision=precision, opacity_threshold=threshold)
            assert_same_all_hits(found, want, fields, f"{precision} {threshold}")
            assert set(want.instance_id.tolist()) == ({0, 2} if threshold == 0.5 else {0, 1, 2})


def test_all_hits_of_cuda_rays_in_chunks(bunny, never_through_host, monkeypatch):
    """Many chunks of CUDA rays (each its own columns, joined on the GPU at the end), chunks cut
    short where their hits exceed the records' room (2,000 hits: the rest of the chunk traced
    again as the next), and an invalid ray named by its row as the numpy path names it."""
    v, scene = bunny
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 30_000, seed=42))
    before = DEVICE.chunk_rays
    DEVICE.chunk_rays = 4096
    try:
        for room in (None, 2000):
            if room is not None:
                monkeypatch.setenv("VKRAY_HIT_RECORD_BYTES", str(32 * room))
            for precision in ("fast", "exact"):
                found = scene.intersect_all(cuda(o), cuda(d), outputs=["t", "prim_id"], precision=precision)
                chunks = DEVICE.last_trace_profile["chunks"]
                want = scene.intersect_all(o, d, outputs=["t", "prim_id"], precision=precision)
                assert_same_all_hits(found, want, ["t", "prim_id"], f"{precision} room {room}")
                assert chunks >= (len(want.ray_index) // room if room else 8), chunks
    finally:
        DEVICE.chunk_rays = before
    broken = d.copy()
    broken[12_345] = np.nan
    for precision in ("fast", "exact"):
        with pytest.raises(ValueError, match="12345"):
            scene.intersect_all(cuda(o), cuda(broken), outputs=["t"], precision=precision)


def test_all_hits_the_gpu_cannot_settle_go_through_the_host(monkeypatch):
    """Rays through 40 stacked squares meet more hits than the GPU's lists settle (32): the query
    goes through the host and answers as numpy's; rays that meet few stay on the GPU. An exact
    query of a two-part mesh (whose exact hits name their part on the host) goes through the host
    too, as do no rays."""
    if DEVICE.cuda_device is None:
        pytest.skip("this vkray device shares no memory with CUDA")
    through = []
    original = vkray._device.Scene._through_host

    def counted(self, query, run):
        through.append(query.kind)
        return original(self, query, run)

    monkeypatch.setattr(vkray._device.Scene, "_through_host", counted)
    square = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    v = np.concatenate([square + [0.0, 0.0, 0.1 * k] for k in range(40)])
    f = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k for k in range(40)])
    scene = DEVICE.scene(DEVICE.mesh(v, f))
    rng = np.random.default_rng(43)
    o = np.column_stack([rng.uniform(-0.9, 0.9, (500, 2)), np.full(500, -1.0)])
    d = np.tile([0.0, 0.0, 1.0], (500, 1))
    for precision in ("fast", "exact"):
        found = scene.intersect_all(cuda(o), cuda(d), outputs=["t", "prim_id"], precision=precision)
        want = scene.intersect_all(o, d, outputs=["t", "prim_id"], precision=precision)
        assert_same_all_hits(found, want, ["t", "prim_id"], precision)
        assert (want.counts == 40).all()
    assert through == ["intersect_all", "intersect_all"]
    few = scene.intersect_all(cuda(o), cuda(d), tmax=1.35, outputs=["t"])
    assert_same(on_host(few.counts), np.full(500, 4, dtype=np.int64))
    assert len(through) == 2
    two = [(v[:4], f[:2]), (v[4:8], f[:2])]
    parts = DEVICE.scene(DEVICE.mesh_from_parts(two))
    found = parts.intersect_all(cuda(o), cuda(d), outputs=["geometry_id"], precision="exact")
    want = parts.intersect_all(o, d, outputs=["geometry_id"], precision="exact")
    assert_same(on_host(found.geometry_id), want.geometry_id)
    assert set(want.geometry_id.tolist()) == {0, 1}
    assert len(through) == 3
    empty = scene.intersect_all(cuda(o[:0]), cuda(d[:0]), outputs=["t"])
    assert on_host(empty.offsets).tolist() == [0] and len(through) == 4


@pytest.mark.parametrize("precision", ["fast", "exact", "reference"])
def test_point_queries_answer_on_the_gpu(bunny, precision):
    v, scene = bunny
    p = points_around(v, 20_000, seed=3)
    closest = scene.closest_points(cuda(p), precision=precision, outputs=["distance", "prim_id", "position"])
    want = scene.closest_points(p, precision=precision, outputs=["distance", "prim_id", "position"])
    for name in ("distance", "prim_id", "position"):
        assert_same(on_host(getattr(closest, name)), getattr(want, name), err_msg=name)
    assert "on cuda" in repr(closest)
    with pytest.raises(TypeError, match="on the GPU"):
        _ = closest.hit
    assert_same(on_host(scene.distance(cuda(p), precision=precision)),
                                  scene.distance(p, precision=precision))
    signed = scene.signed_distance(cuda(p), precision=precision)
    assert_same(on_host(signed), scene.signed_distance(p, precision=precision))
    assert (on_host(signed) < 0).any() and (on_host(signed) > 0).any()


def test_contains_answers_bools_on_the_gpu(bunny):
    v, f = oracle.load_mesh("fandisk")  # closed: parity, the default
    closed = DEVICE.scene([DEVICE.mesh(v, f)])
    p = points_around(v, 50_000, seed=4)
    inside = closed.contains(cuda(p.astype(np.float32)))
    assert inside.dtype == "bool" and inside.shape == (50_000,)
    want = closed.contains(p.astype(np.float32))
    assert torch.from_dlpack(inside).dtype == torch.bool
    assert_same(on_host(inside), want)
    assert 0 < want.sum() < len(want)
    v, scene = bunny  # with holes: the winding number
    p = points_around(v, 50_000, seed=5)
    winding = scene.contains(cuda(p), method="winding")
    assert_same(on_host(winding), scene.contains(p, method="winding"))


@pytest.mark.parametrize("name, method", [("fandisk", "parity"), ("stanford-bunny", "winding")])
def test_contains_reads_the_grid_on_the_gpu(monkeypatch, never_through_host, name, method):
    """Once the scene keeps its inside grid, `contains` of CUDA points never leaves the GPU
    (trace/vulkan/inside_points.rs): the points are copied into memory Vulkan shares, sorted by
    cell, a ray cast from each point of an undecided cell, the answers copied into CUDA memory.
    Equal to numpy's answers for f32 and f64 points, strided and shaped views, cupy arrays and
    several threads; the points near the surface that the CPU decides come back too; a point that
    is not finite is named."""
    if DEVICE.cuda_device is None:
        pytest.skip("this vkray device shares no memory with CUDA")
    monkeypatch.setenv("VKRAY_CONTAINS_GRID", "engine")  # the first large query builds the grid
    v, f = oracle.load_mesh(name)
    scene = DEVICE.scene([DEVICE.mesh(v, f)])
    p = points_around(v, 60_000, seed=21)
    # Points on the surface (vertices and edge midpoints), which the GPU's rays leave to the CPU
    # where their winding numbers round near 1/2.
    p = np.concatenate([p, v[:3000], 0.5 * (v[f[:3000, 0]] + v[f[:3000, 1]])])
    scene.contains(p, method=method)  # numpy: builds the grid
    assert scene._core.inside_grid(method == "winding") is not None
    want = scene.contains(p, method=method, precision="reference")
    assert 0 < want.sum() < len(want)
    # Chunks of an odd size: each chunk's answers land at its own first row.
    monkeypatch.setenv("VKRAY_POINT_CHUNK", "10001")
    for kind in (np.float64, np.float32):
        inside = scene.contains(cuda(p.astype(kind)), method=method)
        assert inside.dtype == "bool" and inside.shape == (len(p),)
        expected = scene.contains(p.astype(kind), method=method, precision="reference")
        assert_same(on_host(inside), expected, err_msg=kind.__name__)
    shaped = scene.contains(cuda(p[:60_000]).reshape(20, 3000, 3), method=method)
    assert_same(on_host(shaped), want[:60_000].reshape(20, 3000))
    transposed = cuda(np.ascontiguousarray(p.T)).T
    assert_same(on_host(scene.contains(transposed, method=method)), want)
    few = scene.contains(cuda(p[:100]), method=method)  # the kept grid serves small queries too
    assert_same(on_host(few), want[:100])
    cupy = pytest.importorskip("cupy")
    assert_same(cupy.from_dlpack(scene.contains(cupy.asarray(p), method=method)).get(), want)
    bad = p.copy()
    bad[4321, 2] = np.nan
    with pytest.raises(ValueError, match="points row 4321 is not finite"):
        scene.contains(cuda(bad), method=method)

    def work(k: int):
        return on_host(scene.contains(cuda(p[k::4]), method=method))

    for k, found in enumerate(oracle.in_threads(4, work)):
        assert_same(found, want[k::4], err_msg=f"thread {k}")
    # The point slots CUDA points went through serve host points next (a slot once kept the CUDA
    # points' address and read them in place of numpy's).
    q = points_around(v, 40_000, seed=22)
    assert_same(scene.contains(q, method=method), scene.contains(q, method=method, precision="reference"))
    signed = scene.signed_distance(q, method=method, precision="exact")
    assert_same(np.signbit(signed), np.signbit(scene.signed_distance(q, method=method)))


def test_contains_of_points_read_through_the_host(monkeypatch):
    """CUDA points the GPU's `contains` path cannot read in place go through the host, with the
    same answers, though the scene keeps its grid: one row expanded to every point (stride 0),
    leading axes that do not flatten into one, a progress bar."""
    if DEVICE.cuda_device is None:
        pytest.skip("this vkray device shares no memory with CUDA")
    monkeypatch.setenv("VKRAY_CONTAINS_GRID", "engine")
    v, f = oracle.load_mesh("fandisk")
    scene = DEVICE.scene([DEVICE.mesh(v, f)])
    p = points_around(v, 40_000, seed=23)
    want = scene.contains(p)  # builds the grid
    assert scene._core.inside_grid(False) is not None
    one = scene.contains(cuda(p[:1]).expand(1000, 3))
    assert one.shape == (1000,)
    assert_same(on_host(one), np.repeat(want[:1], 1000))
    grid = cuda(p.reshape(200, 200, 3))
    unflattened = grid.permute(1, 0, 2)[:, :150]  # leading axes (200, 150) that do not flatten
    assert_same(on_host(scene.contains(unflattened)), want.reshape(200, 200).T[:, :150])
    assert_same(on_host(scene.contains(cuda(p), progress=True)), want)


def test_shapes_strides_and_expanded_rays(bunny):
    v, scene = bunny
    p = points_around(v, 6_000, seed=5)
    grid = cuda(p).reshape(20, 300, 3)
    found = scene.distance(grid, precision="exact")
    assert found.shape == (20, 300)
    assert_same(on_host(found), scene.distance(p.reshape(20, 300, 3), precision="exact"))
    # A strided view (every other column of a wider tensor) and a transposed one.
    doubled = np.concatenate([p, p], axis=1)
    strided = cuda(doubled)[:, ::2]
    assert_same(on_host(scene.distance(strided)), scene.distance(doubled[:, ::2]))
    wider = np.random.default_rng(5).normal(size=(len(p), 7))
    wider[:, 2:5] = p
    sliced = cuda(wider)[:, 2:5]  # rows 56 bytes apart: only each row's 24 bytes cross the bus
    assert_same(on_host(scene.distance(sliced)), scene.distance(p))
    transposed = cuda(np.ascontiguousarray(p.T)).T
    inside = scene.contains(transposed, method="winding")
    assert_same(on_host(inside), scene.contains(p, method="winding"))
    # One origin expanded to every ray (stride 0), and per-ray bounds as CUDA arrays.
    o, d = oracle.random_rays(v, 4_000, seed=6)
    eye = cuda(o[:1]).expand(4_000, 3)
    tmax = np.random.default_rng(7).uniform(0.0, 2.0, 4_000)
    counts = scene.count(eye, cuda(d), tmax=cuda(tmax), precision="exact")
    assert_same(on_host(counts), scene.count(o[:1], d, tmax=tmax, precision="exact"))
    empty = scene.distance(torch.zeros((0, 3), device="cuda", dtype=torch.float64))
    assert empty.shape == (0,)


def test_reads_and_answers_follow_the_callers_streams(bunny):
    """Points written on a side stream after a long wait, queried at once: DLPack's stream
    argument orders the producer's writes before vkray's copy (an unordered read would see the
    NaN the points held before, and raise). The answer, read on another stream that first sleeps,
    is the one written."""
    v, scene = bunny
    p = points_around(v, 200_000, seed=8)
    want = scene.distance(p, precision="exact")
    side, reader = torch.cuda.Stream(), torch.cuda.Stream()
    source = cuda(p)
    points = torch.full_like(source, float("nan"))
    torch.cuda.synchronize()
    with torch.cuda.stream(side):
        torch.cuda._sleep(200_000_000)  # ~0.1 s of the GPU's clock before the points are written
        points.copy_(source)
        found = scene.distance(points, precision="exact")
    with torch.cuda.stream(reader):
        torch.cuda._sleep(50_000_000)
        got = torch.from_dlpack(found).clone()
    torch.cuda.synchronize()
    assert_same(got.cpu().numpy(), want)


def test_each_array_of_a_query_is_ordered_after_its_writes(bunny):
    """Rays whose second and third arrays (directions, tmax) are written on the caller's stream
    after a long wait, the first (origins) long ready: vkray asks torch to order the first array
    only (torch orders every tensor after its current stream, so one export covers the rest) and
    still reads what the stream wrote. A cupy array beside torch tensors is asked for its own."""
    v, scene = bunny
    o, d = oracle.random_rays(v, 200_000, seed=31)
    tmax = np.random.default_rng(32).uniform(0.5, 3.0, len(o))
    want = scene.count(o, d, tmax=tmax)
    side = torch.cuda.Stream()
    origins, source, limits = cuda(o), cuda(d), cuda(tmax)
    directions = torch.full_like(source, float("nan"))
    bounds = torch.full_like(limits, float("nan"))
    torch.cuda.synchronize()
    with torch.cuda.stream(side):
        torch.cuda._sleep(200_000_000)  # ~0.1 s of the GPU's clock before they are written
        directions.copy_(source)
        bounds.copy_(limits)
        counted = scene.count(origins, directions, tmax=bounds)
        got = torch.from_dlpack(counted).clone()
    torch.cuda.synchronize()
    assert_same(got.cpu().numpy(), want)
    cupy = pytest.importorskip("cupy")
    assert_same(on_host(scene.count(origins, cupy.asarray(d), tmax=limits)), want)


def test_a_cameras_hits_land_in_cuda_memory(bunny):
    """cuda=True: a sensor's (and host rays') answers in CUDA memory, equal to the host's."""
    v, scene = bunny
    centre = v.mean(axis=0)
    camera = vkray.PinholeCamera(64, 48, fov_deg=60.0, eye=centre + [0.0, 0.0, 0.4], target=centre, up=[0, 1, 0])
    hits = scene.intersect(camera, cuda=True)
    want = scene.intersect(camera)
    assert hits.t.shape == (48, 64) and "on cuda" in repr(hits)
    for name in ("t", "prim_id", "uv", "normal"):
        assert_same(on_host(getattr(hits, name)), getattr(want, name), err_msg=name)
    assert (on_host(hits.prim_id) >= 0).any()
    assert_same(on_host(scene.occluded(camera, cuda=True)) >= 0, scene.occluded(camera))
    assert_same(on_host(scene.count(camera, precision="exact", cuda=True)), scene.count(camera, precision="exact"))
    assert_same(on_host(scene.intersect_all(camera, cuda=True).offsets), scene.intersect_all(camera).offsets)
    o, d = oracle.random_rays(v, 1000, seed=18)
    assert_same(on_host(scene.transmittance(o, d, cuda=True)), scene.transmittance(o, d))
    with pytest.raises(TypeError, match="out= takes numpy hits"):
        scene.intersect(o, d, out=scene.intersect(o, d), cuda=True)


def test_large_arrays_cross_in_chunks(bunny):
    """Arrays of several megabytes cross the bus in chunks through pinned memory, both ways: odd
    sizes, the last chunk short, every element in its place."""
    v, scene = bunny
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 1_100_003, seed=16))  # 13.2 MB each
    counts = scene.count(cuda(o), cuda(d), precision="exact")  # 4.4 MB back
    assert_same(on_host(counts), scene.count(o, d, precision="exact"))
    p = points_around(v, 700_001, seed=17)  # positions back: 16.8 MB, three chunks both buffers
    want = scene.closest_points(p, precision="exact", outputs=["distance", "position"])
    found = scene.closest_points(cuda(p), precision="exact", outputs=["distance", "position"])
    assert_same(on_host(found.position), want.position)
    assert DEVICE.idle_memory["pinned_bytes"] > 0
    DEVICE.release_idle_memory()  # the page-locked memory goes; the next query takes new
    assert DEVICE.idle_memory["pinned_bytes"] == 0
    assert_same(on_host(scene.distance(cuda(p), precision="exact")), want.distance)


def lent(array: np.ndarray) -> bool:
    """Whether ``array``'s memory is a page-locked block vkray lent (its base chain holds one)."""
    while array is not None:
        if type(array).__name__ == "HostBlock":
            return True
        array = getattr(array, "base", None)
    return False


def test_answers_through_the_host_are_made_in_pinned_memory(bunny, monkeypatch):
    """A query of CUDA arrays through the host makes its answers in page-locked blocks, copied to
    CUDA memory from there; only its own thread's answers, only while it runs (an error included):
    four threads at once, each a CUDA query and then a numpy one, the same answers as numpy's."""
    v, scene = bunny
    made = []
    through_host = vkray._device.Scene._through_host

    def spying(self, query, run):
        def kept(scene_, q):
            answer = run(scene_, q)
            made.append(answer)
            return answer
        return through_host(self, query, kept)

    monkeypatch.setattr(vkray._device.Scene, "_through_host", spying)
    sets = [points_around(v, 150_001 + k, seed=40 + k) for k in range(4)]  # 3.6 MB of positions each
    fields = ["distance", "position", "prim_id", "uv", "normal"]
    expected = [scene.closest_points(p, precision="exact", outputs=fields) for p in sets]
    assert not any(lent(getattr(e, name)) for e in expected for name in fields)

    def work(k):
        runs = []
        for _ in range(3):
            found = scene.closest_points(cuda(sets[k]), precision="exact", outputs=fields)
            after = scene.closest_points(sets[k], precision="exact", outputs=fields)
            runs.append(({name: on_host(getattr(found, name)) for name in fields}, after))
        return runs

    for k, runs in enumerate(oracle.in_threads(len(sets), work)):
        for found, after in runs:
            for name in fields:
                assert_same(found[name], getattr(expected[k], name), err_msg=name)
                assert_same(getattr(after, name), getattr(expected[k], name), err_msg=name)
                assert not lent(getattr(after, name)), name  # a numpy query's answers are numpy's
    assert len(made) == 12
    assert all(lent(answer.position) and lent(answer.distance) for answer in made)
    bad = points_around(v, 300_000, seed=50)
    bad[123] = np.nan
    with pytest.raises(ValueError, match="123"):
        scene.distance(cuda(bad), precision="exact")
    assert not lent(scene.distance(bad[:122], precision="exact"))  # the error left no pinned answers on
    assert not lent(scene.distance(points_around(v, 300_000, seed=51), precision="exact"))


def test_one_ray_and_one_point_keep_their_shapes(bunny):
    v, scene = bunny
    o, d = oracle.random_rays(v, 1, seed=13)
    hits = scene.intersect(cuda(o[0]), cuda(d[0]), precision="exact")
    assert hits.t.shape == () and hits.prim_id.shape == ()
    assert_same(on_host(hits.t), scene.intersect(o[0], d[0], precision="exact").t)
    assert_same(on_host(scene.count(cuda(o[0]), cuda(d[0]), precision="exact")),
                scene.count(o[0], d[0], precision="exact"))
    point = points_around(v, 1, seed=14)[0]
    assert_same(on_host(scene.distance(cuda(point))), scene.distance(point))
    assert_same(on_host(scene.contains(cuda(point), method="winding")), scene.contains(point, method="winding"))


def test_the_host_path_answers_in_the_resident_paths_types(bunny):
    """`position` sends a fast-tier intersect through the host: its other fields keep the GPU-resident
    path's dtypes and values."""
    v, scene = bunny
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 10_000, seed=15))
    resident = scene.intersect(cuda(o), cuda(d), outputs=["t", "prim_id", "uv", "normal"])
    through = scene.intersect(cuda(o), cuda(d), outputs=["t", "prim_id", "uv", "normal", "position"])
    for name in ("t", "prim_id", "uv", "normal"):
        assert_same(on_host(getattr(through, name)), on_host(getattr(resident, name)), err_msg=name)
    assert through.position.dtype == "float32"
    assert_same(on_host(scene.occluded(cuda(o), cuda(d), precision="exact")) >= 0,
                on_host(scene.occluded(cuda(o), cuda(d))) >= 0)


@pytest.mark.parametrize("offset", [0.0, 1e7])
def test_exact_tier_of_cuda_rays_through_shared_edges(offset, never_through_host):
    """The exact tier's closest hits, occlusion and counts of CUDA rays, packed in f64 by the GPU
    (no trip through the host): rays through the vertices and edges a heightfield's triangles
    share cross it once, at every offset, float32 and float64 rays alike; every field the numpy
    path's, bit for bit (t and uv float64); an invalid ray named by its row."""
    if DEVICE.cuda_device is None:
        pytest.skip("this vkray device shares no memory with CUDA")
    n = 10
    v, f, _ = oracle.heightfield(n, seed=3, offset=offset)
    origins, directions = oracle.rays_through(oracle.shared_targets(v, f, n), seed=4)
    scene = DEVICE.scene(DEVICE.mesh(v, f))
    fields = ["t", "prim_id", "uv", "normal", "geometry_id", "instance_id", "custom_index"]
    for dtype in (np.float64, np.float32):
        o, d = origins.astype(dtype), directions.astype(dtype)
        counts = on_host(scene.count(cuda(o), cuda(d), precision="exact"))
        assert_same(counts, scene.count(o, d, precision="exact"), err_msg=str(dtype))
        if dtype == np.float64:
            assert (counts == 1).all(), f"{np.sum(counts == 0)} misses, {np.sum(counts > 1)} double counts"
        hits = scene.intersect(cuda(o), cuda(d), outputs=fields, precision="exact")
        want = scene.intersect(o, d, outputs=fields, precision="exact")
        for name in fields:
            assert_same(on_host(getattr(hits, name)), getattr(want, name), err_msg=f"{name} {dtype}")
        assert (want.prim_id >= 0).all() and want.t.dtype == np.float64
        blocked = on_host(scene.occluded(cuda(o), cuda(d), precision="exact"))
        assert_same(blocked >= 0, scene.occluded(o, d, precision="exact"), err_msg=str(dtype))
    tmax = np.full(len(origins), 4.0)
    assert_same(on_host(scene.count(cuda(origins), cuda(directions), tmax=cuda(tmax), precision="exact")),
                scene.count(origins, directions, tmax=tmax, precision="exact"))
    broken = directions.copy()
    broken[7] = 0.0
    for query in (scene.count, scene.intersect):
        with pytest.raises(ValueError, match="7"):
            query(cuda(origins), cuda(broken), precision="exact")


@pytest.mark.parametrize("distance", [2.0, 1e6])
def test_transmittance_of_cuda_rays_stays_on_the_gpu(distance, never_through_host):
    """Transmittance of CUDA rays in the fast and exact tiers, traced where they lie: two veils
    of opacity 0.25 and 0.5 keep 0.375 of the light, none beside them is lost, an opaque plate
    keeps none; a far ray's advance never touches the light (the numpy path's answers, bit for
    bit); and a scene with nothing translucent answers as the numpy path's occlusion does."""
    if DEVICE.cuda_device is None:
        pytest.skip("this vkray device shares no memory with CUDA")
    v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    lifted, plate = np.eye(4), np.eye(4)
    lifted[2, 3], plate[:3, 3] = 0.5, [4.0, 0.0, 1.0]
    veils = [DEVICE.mesh(v, f, opacity=0.25), vkray.Instance(DEVICE.mesh(v, f, opacity=0.5), lifted)]
    scene = DEVICE.scene(veils + [vkray.Instance(DEVICE.mesh(v, f), plate)])
    origins = np.array([[0.1, 0.2, -distance], [0.5, -0.5, -distance], [2.5, 0.0, -distance], [4.2, 0.3, -distance]])
    directions = np.tile([0.0, 0.0, 1.0], (4, 1))
    for dtype in (np.float32, np.float64):
        o, d = origins.astype(dtype), directions.astype(dtype)
        for precision in ("fast", "exact"):
            kept = on_host(scene.transmittance(cuda(o), cuda(d), precision=precision))
            assert_same(kept, scene.transmittance(o, d, precision=precision), err_msg=f"{dtype} {precision}")
            np.testing.assert_allclose(kept, [0.375, 0.375, 1.0, 0.0], rtol=1e-6)
    opaque = DEVICE.scene([vkray.Instance(DEVICE.mesh(v, f), plate)])
    for precision in ("fast", "exact"):
        light = opaque.transmittance(cuda(origins), cuda(directions), precision=precision)
        assert_same(on_host(light), opaque.transmittance(origins, directions, precision=precision))


def test_a_scene_with_spheres_answers_cuda_rays_as_numpy(bunny):
    """Counts and transmittance of a scene with spheres are the host's in every tier (the GPU
    traces spheres for closest hits and occlusion in the fast tier only): CUDA rays of those
    queries go through the host, and every query answers as for numpy rays."""
    v, _ = bunny
    spheres = DEVICE.spheres([[0.0, 0.0, 0.0], [0.0, 0.0, 3.0]], [1.0, 0.5])
    plate = np.eye(4)
    plate[2, 3] = 5.0
    quad = DEVICE.mesh(np.array([[-2.0, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]]), np.array([[0, 1, 2], [0, 2, 3]]),
                       opacity=0.5)
    scene = DEVICE.scene([spheres, vkray.Instance(quad, plate)])
    offsets = np.array([[0.0, 0, 0], [0.3, 0.2, 0], [1.5, 0, 0], [0.7, 0.6, 0], [3, 3, 0]])
    o = np.tile([0.0, 0.0, -10.0], (5, 1)) + offsets
    d = np.tile([0.0, 0.0, 1.0], (5, 1))
    for precision in ("fast", "exact"):
        counts = on_host(scene.count(cuda(o), cuda(d), precision=precision))
        assert_same(counts, scene.count(o, d, precision=precision), err_msg=precision)
        assert counts.tolist() == [5, 5, 1, 3, 0]
        light = on_host(scene.transmittance(cuda(o), cuda(d), precision=precision))
        assert_same(light, scene.transmittance(o, d, precision=precision), err_msg=precision)
    hits = scene.intersect(cuda(o), cuda(d))
    assert_same(on_host(hits.prim_id), scene.intersect(o, d).prim_id)


def test_errors_name_the_argument(bunny):
    v, scene = bunny
    p = points_around(v, 100, seed=9)
    p[42] = np.nan
    with pytest.raises(ValueError, match="42"):
        scene.distance(cuda(p))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        scene.contains(cuda(p[:, :2]), method="winding")
    o, d = oracle.random_rays(v, 100, seed=10)
    with pytest.raises(TypeError, match="origins is in host memory"):
        scene.intersect_all(o, cuda(d))
    with pytest.raises(TypeError, match="tmax is in host memory"):
        scene.intersect_all(cuda(o), cuda(d), tmax=np.ones(100))
    with pytest.raises(TypeError, match="float32 or float64"):
        scene.distance(cuda(p[:42]).half())
    for precision in ("fast", "exact", "refined"):
        with pytest.raises(TypeError, match="directions are needed"):
            scene.intersect(cuda(o), precision=precision)


def test_several_threads(bunny):
    """Six threads at once: signed distances through the host (points of 1.2 MB in through
    page-locked memory), and the GPU-resident exact counts, exact closest hits, transmittance and
    all hits of 300k rays each, the pools, lists and leases shared among them."""
    v, scene = bunny
    sets = [points_around(v, 50_000, seed=20 + k) for k in range(6)]
    expected = [scene.signed_distance(p, precision="exact") for p in sets]
    rays = [tuple(a.astype(np.float32) for a in oracle.random_rays(v, 300_000, seed=30 + k)) for k in range(6)]
    counted = [scene.count(o, d, precision="exact") for o, d in rays]
    nearest = [scene.intersect(o, d, outputs=["t"], precision="exact").t for o, d in rays]
    light = [scene.transmittance(o, d) for o, d in rays]
    every = [scene.intersect_all(o, d, outputs=["t"]) for o, d in rays]

    def work(k):
        runs = []
        o, d = cuda(rays[k][0]), cuda(rays[k][1])
        for _ in range(3):
            signed = on_host(scene.signed_distance(cuda(sets[k]), precision="exact"))
            counts = on_host(scene.count(o, d, precision="exact"))
            t = on_host(scene.intersect(o, d, outputs=["t"], precision="exact").t)
            hits = scene.intersect_all(o, d, outputs=["t"])
            listed = (on_host(hits.offsets), on_host(hits.t))
            runs.append((signed, counts, t, on_host(scene.transmittance(o, d)), listed))
        return runs

    for k, runs in enumerate(oracle.in_threads(len(sets), work)):
        for signed, counts, t, kept, (offsets, hit_t) in runs:
            assert_same(signed, expected[k])
            assert_same(counts, counted[k])
            assert_same(t, nearest[k])
            assert_same(kept, light[k])
            assert_same(offsets, every[k].offsets)
            assert_same(hit_t, every[k].t)


def test_cupy_arrays(bunny):
    cupy = pytest.importorskip("cupy")
    v, scene = bunny
    p = points_around(v, 10_000, seed=11)
    found = scene.signed_distance(cupy.asarray(p), precision="exact")
    assert_same(cupy.from_dlpack(found).get(), scene.signed_distance(p, precision="exact"))
    o, d = oracle.random_rays(v, 10_000, seed=12)
    hits = scene.intersect_all(cupy.asarray(o), cupy.asarray(d), precision="exact")
    want = scene.intersect_all(o, d, precision="exact")
    assert_same(cupy.from_dlpack(hits.offsets).get(), want.offsets)
