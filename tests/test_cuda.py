"""Rays that never leave the GPU: torch CUDA tensors in, `vkray.CudaArray` hits out, through
CUDA–Vulkan interop (memory and a timeline semaphore Vulkan exports and CUDA imports). Runs where
torch sees a CUDA GPU that is the vkray device (the H100 machines); skipped elsewhere. The
oracle: the same query on numpy arrays (checked against Embree and brute force elsewhere), which
must agree bit for bit."""

from __future__ import annotations

import gc

import numpy as np
import pytest

import oracle
import vkray

torch = pytest.importorskip("torch")
if not torch.cuda.is_available():
    pytest.skip("torch sees no CUDA GPU", allow_module_level=True)

DEVICE = vkray.Device()


def cuda_scene_or_skip():
    v, f = oracle.load_mesh("stanford-bunny")
    scene = DEVICE.scene([DEVICE.mesh(v, f)])
    try:
        scene.intersect(torch.zeros((1, 3), device="cuda"), torch.ones((1, 3), device="cuda"))
    except TypeError as exc:
        pytest.skip(f"this vkray device shares no memory with CUDA: {exc}")
    return v, scene


@pytest.fixture(scope="module")
def bunny():
    return cuda_scene_or_skip()


def on_host(array) -> np.ndarray:
    return torch.from_dlpack(array).cpu().numpy()


def assert_same(hits_gpu, hits_np, fields):
    for name in fields:
        np.testing.assert_array_equal(on_host(getattr(hits_gpu, name)), getattr(hits_np, name), err_msg=name)


EVERY = ["t", "prim_id", "instance_id", "custom_index", "uv", "normal", "geometry_id"]


def test_torch_in_torch_out_equals_numpy(bunny):
    v, scene = bunny
    o, d = oracle.random_rays(v, 200_000, seed=1)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    expected = scene.intersect(o32, d32, outputs=EVERY)
    hits = scene.intersect(torch.from_numpy(o32).cuda(), torch.from_numpy(d32).cuda(), outputs=EVERY)
    assert isinstance(hits.t, vkray.CudaArray) and hits.t.shape == (200_000,) and hits.uv.shape == (200_000, 2)
    t = torch.from_dlpack(hits.t)
    assert t.device.type == "cuda" and t.dtype == torch.float32
    assert_same(hits, expected, EVERY)
    assert expected.hit.sum() > 10_000
    blocked = scene.occluded(torch.from_numpy(o32).cuda(), torch.from_numpy(d32).cuda())
    np.testing.assert_array_equal(on_host(blocked) >= 0, scene.occluded(o32, d32))


def test_counts_of_cuda_rays_equal_numpy(bunny):
    """count on torch and cupy CUDA rays (fast tier) stays on the GPU: int32 counts in a
    CudaArray, equal to the numpy path's; far rays advanced on the GPU count alike; a cull and an
    opacity threshold pass through; other tiers are refused by name."""
    v, scene = bunny
    o, d = oracle.random_rays(v, 100_000, seed=12)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    counts = scene.count(torch.from_numpy(o32).cuda(), torch.from_numpy(d32).cuda())
    assert isinstance(counts, vkray.CudaArray) and counts.shape == (100_000,) and counts.dtype == "int32"
    expected = scene.count(o32, d32)
    np.testing.assert_array_equal(on_host(counts), expected)
    assert expected.max() >= 4
    back = scene.count(torch.from_numpy(o32).cuda(), torch.from_numpy(d32).cuda(), cull="back")
    np.testing.assert_array_equal(on_host(back), scene.count(o32, d32, cull="back"))
    eye = (v.mean(axis=0) + [0.0, 0.0, 1e6]).reshape(1, 3)
    far = v[np.random.default_rng(13).integers(0, len(v), 5000)] - eye
    np.testing.assert_array_equal(on_host(scene.count(torch.from_numpy(eye).cuda(), torch.from_numpy(far).cuda())),
                                  scene.count(eye, far))
    exact = scene.count(torch.from_numpy(o32).cuda(), torch.from_numpy(d32).cuda(), precision="exact")
    assert isinstance(exact, vkray.CudaArray) and exact.dtype == "int32"
    np.testing.assert_array_equal(on_host(exact), scene.count(o32, d32, precision="exact"))
    cupy = pytest.importorskip("cupy")
    np.testing.assert_array_equal(cupy.from_dlpack(scene.count(cupy.asarray(o), cupy.asarray(d))).get(),
                                  scene.count(o, d))


def test_float64_broadcast_bounds_and_far_rays(bunny):
    v, scene = bunny
    rng = np.random.default_rng(2)
    n = 50_000
    eye = (v.mean(axis=0) + [0.0, 0.0, 1e6]).reshape(1, 3)  # far: advanced on the GPU
    d = (v[rng.integers(0, len(v), n)] - eye).astype(np.float64)
    tmax = rng.uniform(0.5, 2.0, n)
    expected = scene.intersect(eye, d, tmax=tmax, outputs=["t", "prim_id"])
    hits = scene.intersect(torch.from_numpy(eye).cuda(), torch.from_numpy(d).cuda(),
                           tmax=torch.from_numpy(tmax).cuda(), outputs=["t", "prim_id"])
    assert_same(hits, expected, ["t", "prim_id"])
    assert expected.hit.sum() > 1000


def test_camera_shaped_rays(bunny):
    v, scene = bunny
    centre = v.mean(axis=0)
    camera = vkray.PinholeCamera(64, 48, fov_deg=60.0, eye=centre + [0.0, 0.0, 0.4], target=centre,
                                 up=[0.0, 1.0, 0.0])
    o, d = camera.rays()
    expected = scene.intersect(o, d)
    cuda = [torch.from_numpy(np.ascontiguousarray(a)).cuda() for a in (o, d)]
    hits = scene.intersect(*cuda)
    assert hits.t.shape == expected.t.shape
    assert_same(hits, expected, ["t", "prim_id", "normal"])


def test_non_contiguous_tensors(bunny):
    v, scene = bunny
    o, d = oracle.random_rays(v, 30_000, seed=3)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    expected = scene.intersect(o32, d32, outputs=["t", "prim_id"])
    both = torch.from_numpy(np.hstack([o32, d32])).cuda()  # rows 6 floats apart
    transposed = torch.from_numpy(np.ascontiguousarray(d32.T)).cuda().T  # columns 30000 apart
    assert not both[:, :3].is_contiguous() and not transposed.is_contiguous()
    assert_same(scene.intersect(both[:, :3], both[:, 3:], outputs=["t", "prim_id"]), expected, ["t", "prim_id"])
    assert_same(scene.intersect(both[:, :3], transposed, outputs=["t", "prim_id"]), expected, ["t", "prim_id"])
    every_other = torch.from_numpy(np.repeat(o32, 2, axis=0)).cuda()[::2]
    assert_same(scene.intersect(every_other, torch.from_numpy(d32).cuda(), outputs=["t"]), expected, ["t"])


def test_lifetimes(bunny):
    """The caller's tensors freed right after the call (their memory reused at once); hits that
    outlive their Scene and Device."""
    v, _ = bunny
    device = vkray.Device()
    vv, f = oracle.load_mesh("stanford-bunny")
    scene = device.scene([device.mesh(vv, f)])
    o, d = oracle.random_rays(v, 100_000, seed=4)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    expected = scene.intersect(o32, d32, outputs=["t", "prim_id"])
    origins, directions = torch.from_numpy(o32).cuda(), torch.from_numpy(d32).cuda()
    hits = scene.intersect(origins, directions, outputs=["t", "prim_id"])
    del origins, directions
    garbage = [torch.full((100_000, 3), float("nan"), device="cuda") for _ in range(4)]  # reuses their memory
    del scene, device
    gc.collect()
    t = torch.from_dlpack(hits.t)
    del hits
    gc.collect()
    torch.cuda.synchronize()
    np.testing.assert_array_equal(t.cpu().numpy(), expected.t)
    del garbage


def test_numpy_copy_and_repr(bunny):
    v, scene = bunny
    o, d = oracle.random_rays(v, 1000, seed=5)
    hits = scene.intersect(torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda())
    np.testing.assert_array_equal(np.asarray(hits.prim_id), scene.intersect(o, d).prim_id)
    assert "on cuda" in repr(hits) and "cuda:" in repr(hits.t)
    with pytest.raises(TypeError, match="on the GPU"):
        _ = hits.hit


def test_errors(bunny):
    v, scene = bunny
    o, d = oracle.random_rays(v, 1000, seed=6)
    d[321] = 0.0
    with pytest.raises(ValueError) as expected:
        scene.intersect(o, d)
    with pytest.raises(ValueError, match="row 321"):
        scene.intersect(torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda())
    assert "row 321" in str(expected.value)
    with pytest.raises(TypeError, match="directions is in host memory"):
        scene.intersect(torch.from_numpy(o).cuda(), d)  # numpy directions with CUDA origins
    with pytest.raises(TypeError, match="float32 or float64"):
        scene.intersect(torch.from_numpy(o).cuda().half(), torch.from_numpy(d).cuda())
    with pytest.raises(ValueError, match="row 321"):  # through the host: the same error
        scene.intersect(torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda(), precision="exact")
    with pytest.raises(TypeError, match="directions is in host memory"):
        scene.intersect(torch.from_numpy(o).cuda(), d, precision="exact")
    with pytest.raises(TypeError, match="out= takes numpy hits"):
        scene.intersect(torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda(), precision="exact",
                        out=scene.intersect(o[:1000:2], d[:1000:2], precision="exact"))
    if torch.cuda.device_count() > 1:
        with pytest.raises(TypeError, match="cuda:1"):
            scene.intersect(torch.from_numpy(o).to("cuda:1"), torch.from_numpy(d).to("cuda:1"))


def test_several_threads(bunny):
    v, scene = bunny
    batches = [oracle.random_rays(v, 20_000, seed=10 + k) for k in range(6)]
    expected = [scene.intersect(o.astype(np.float32), d.astype(np.float32)).t for o, d in batches]

    def work(k):
        o, d = (torch.from_numpy(a.astype(np.float32)).cuda() for a in batches[k])
        return [on_host(scene.intersect(o, d).t) for _ in range(3)]

    for runs, want in zip(oracle.in_threads(len(batches), work), expected):
        for found in runs:
            np.testing.assert_array_equal(found, want)


def test_cupy_reads_the_hits(bunny):
    cupy = pytest.importorskip("cupy")
    v, scene = bunny
    o, d = oracle.random_rays(v, 5000, seed=7)
    hits = scene.intersect(cupy.asarray(o), cupy.asarray(d))
    np.testing.assert_array_equal(cupy.from_dlpack(hits.prim_id).get(), scene.intersect(o, d).prim_id)


def cuda_groups(v, f):
    """Groups to split CUDA rays over: the same GPU opened twice (copies within one CUDA
    context), and every CUDA GPU where there are several (copies between GPUs), unequal weights."""
    members = [d.index for d in vkray.devices() if vkray.Device(d.index).cuda_device is not None]
    groups = [vkray.DeviceGroup([members[0], members[0]], weights=[1, 2])]
    if len(members) > 1:
        groups.append(vkray.DeviceGroup(members, weights=[1 + k % 2 for k in range(len(members))]))
    return [(g, g.scene([g.mesh(v, f)])) for g in groups]


@pytest.fixture(scope="module")
def groups(bunny):
    v, _ = bunny
    return cuda_groups(v, oracle.load_mesh("stanford-bunny")[1])


@pytest.fixture
def pieces(monkeypatch):
    """The devices that traced a piece of CUDA rays, call after call (cleared by the test)."""
    traced: list = []
    piece = vkray.Scene.trace_cuda_rows

    def counted(scene, batch, start, stop, *args):
        traced.append((start, stop))
        return piece(scene, batch, start, stop, *args)

    monkeypatch.setattr(vkray.Scene, "trace_cuda_rows", counted)
    return traced


def split_over(group, pieces) -> None:
    """The last call was split: one piece per device, covering the rays once."""
    assert len(pieces) == len(group.devices), pieces
    spans = sorted(pieces)
    assert all(a[1] == b[0] for a, b in zip(spans, spans[1:])) and spans[0][0] == 0, spans
    pieces.clear()


def test_a_group_splits_cuda_rays_and_hands_the_hits_back_on_their_gpu(bunny, groups, pieces):
    """Rays on cuda:N through a DeviceGroup: every member traces its piece (copied from cuda:N)
    and writes its hits back there; the hits equal numpy's on one Scene, for every field and
    occluded, for float64 rays from one eye with per-ray bounds, for strided and expanded tensors,
    and with culling, masks and opacity thresholds."""
    v, scene = bunny
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 100_003, seed=2))
    expected = scene.intersect(o, d, outputs=EVERY)
    rng = np.random.default_rng(5)
    eye = (v.mean(axis=0) + [0.0, 0.0, 1e5]).reshape(1, 3)
    d64 = v[rng.integers(0, len(v), 70_001)] - eye
    tmin, tmax = rng.uniform(0.0, 0.3, len(d64)), rng.uniform(0.5, 2.0, len(d64))
    expected64 = scene.intersect(eye, d64, tmin=tmin, tmax=tmax, outputs=["t", "prim_id"])
    assert expected64.hit.sum() > 1000
    options = dict(cull="front", mask=0x3, opacity_threshold=0.25)
    culled = scene.intersect(o, d, outputs=["t", "prim_id"], **options)  # the far side's faces
    assert culled.hit.sum() > 10_000 and (culled.t[culled.hit] > expected.t[culled.hit]).mean() > 0.9
    for group, group_scene in groups:
        for device in group.devices:
            where = f"cuda:{device.cuda_device}"
            rays = [torch.from_numpy(a).to(where) for a in (o, d)]
            hits = group_scene.intersect(*rays, outputs=EVERY)
            split_over(group, pieces)
            assert torch.from_dlpack(hits.t).device == torch.device(where)
            assert hits.t.shape == (len(o),) and hits.normal.shape == (len(o), 3)
            assert_same(hits, expected, EVERY)
            np.testing.assert_array_equal(on_host(group_scene.occluded(*rays)) >= 0, expected.hit)
            split_over(group, pieces)
            assert_same(group_scene.intersect(*rays, outputs=["t", "prim_id"], **options), culled, ["t", "prim_id"])
            split_over(group, pieces)
            far = group_scene.intersect(torch.from_numpy(eye).to(where), torch.from_numpy(d64).to(where),
                                        tmin=torch.from_numpy(tmin).to(where), tmax=torch.from_numpy(tmax).to(where),
                                        outputs=["t", "prim_id"])
            assert_same(far, expected64, ["t", "prim_id"])
            split_over(group, pieces)
            expanded = torch.from_numpy(eye[0]).to(where).expand(len(d64), 3)  # one row, stride 0
            far = group_scene.intersect(expanded, torch.from_numpy(d64).to(where),
                                        tmin=torch.from_numpy(tmin).to(where), tmax=torch.from_numpy(tmax).to(where),
                                        outputs=["t", "prim_id"])
            assert_same(far, expected64, ["t", "prim_id"])
            split_over(group, pieces)
            both = torch.from_numpy(np.hstack([o, d])).to(where)  # rows 6 floats apart
            transposed = torch.from_numpy(np.ascontiguousarray(d.T)).to(where).T  # columns n apart
            assert_same(group_scene.intersect(both[:, :3], transposed, outputs=["t", "prim_id"]), expected,
                        ["t", "prim_id"])
            split_over(group, pieces)


def test_cuda_rays_arrive_chunk_by_chunk(bunny):
    """Copied chunk by chunk, each chunk traced once its rows are in place: chunks of 777 rays
    (a device's `chunk_rays`), through one Scene and a split, with one-row eyes and per-ray
    bounds, equal the numpy path's hits."""
    v, scene = bunny
    f = oracle.load_mesh("stanford-bunny")[1]
    rng = np.random.default_rng(11)
    eye = (v.mean(axis=0) + [0.0, 0.0, 0.4]).reshape(1, 3)
    d = v[rng.integers(0, len(v), 10_001)] - eye
    tmax = rng.uniform(0.2, 2.0, len(d))
    expected = scene.intersect(eye, d, tmax=tmax, outputs=["t", "prim_id"])
    device = vkray.Device(DEVICE.info.index)
    device.chunk_rays = 777
    small = device.scene([device.mesh(v, f)])
    group = vkray.DeviceGroup([device, device.info.index], weights=[1, 1])
    group.chunk_rays = 777
    split = group.scene([group.mesh(v, f)])
    for target in (small, split):
        hits = target.intersect(torch.from_numpy(eye).cuda(), torch.from_numpy(d).cuda(),
                                tmax=torch.from_numpy(tmax).cuda(), outputs=["t", "prim_id"])
        assert_same(hits, expected, ["t", "prim_id"])
        # 10,001 rays: 13 chunks; each device's half (5,000 or 5,001): 7.
        assert device.last_trace_profile["chunks"] == (13 if target is small else 7)


def test_expanded_tensors_are_one_row(bunny):
    v, scene = bunny
    rng = np.random.default_rng(9)
    eye = (v.mean(axis=0) + [0.0, 0.0, 0.3]).astype(np.float32)
    d = (v[rng.integers(0, len(v), 5000)] - eye).astype(np.float32)
    expected = scene.intersect(eye, d, tmax=1.5, outputs=["t", "prim_id"])
    hits = scene.intersect(torch.from_numpy(eye).cuda().expand(len(d), 3), torch.from_numpy(d).cuda(),
                           tmax=torch.tensor(1.5, device="cuda").expand(len(d)), outputs=["t", "prim_id"])
    assert_same(hits, expected, ["t", "prim_id"])
    with pytest.raises(ValueError, match="same shape"):
        scene.intersect(torch.from_numpy(eye).cuda().expand(7, 3), torch.from_numpy(d).cuda())


def test_a_group_splits_rays_written_on_a_side_stream(bunny, groups, pieces):
    """Rays made on the caller's side stream and passed without a synchronization: DLPack orders
    the split after their writes; the hits are read on another stream after the call."""
    v, scene = bunny
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 300_000, seed=4))
    expected = scene.intersect(o, d, outputs=["t", "prim_id"])
    host = [torch.from_numpy(a).pin_memory() for a in (o, d)]
    for group, group_scene in groups:
        side = torch.cuda.Stream()
        with torch.cuda.stream(side):
            rays = [torch.full_like(h, float("nan"), device="cuda") for h in host]
            for _ in range(20):  # keeps the side stream busy before the rays are written
                torch.cuda._sleep(1_000_000)
            for r, h in zip(rays, host):
                r.copy_(h, non_blocking=True)
            hits = group_scene.intersect(*rays, outputs=["t", "prim_id"])
        split_over(group, pieces)
        other = torch.cuda.Stream()
        with torch.cuda.stream(other):
            t = torch.from_dlpack(hits.t).clone()
        other.synchronize()
        np.testing.assert_array_equal(t.cpu().numpy(), expected.t)
        assert_same(hits, expected, ["t", "prim_id"])


def test_a_split_of_cuda_rays_names_the_callers_row_and_outlives_the_rays(bunny, groups):
    """An invalid ray in the last piece is named by the caller's row; the caller's tensors freed
    (and their memory written over) right after the call leave the hits intact, which outlive
    the group's scene; a batch too small to split runs whole."""
    v, scene = bunny
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 60_000, seed=8))
    expected = scene.intersect(o, d, outputs=["t", "prim_id"])
    bad = d.copy()
    bad[59_990] = 0.0
    for _group, group_scene in groups:
        with pytest.raises(ValueError, match="row 59990"):
            group_scene.intersect(torch.from_numpy(o).cuda(), torch.from_numpy(bad).cuda())
        rays = [torch.from_numpy(a).cuda() for a in (o, d)]
        hits = group_scene.intersect(*rays, outputs=["t", "prim_id"])
        shapes = [r.shape for r in rays]
        del rays
        gc.collect()
        litter = [torch.full(s, float("nan"), device="cuda") for s in shapes]  # the freed blocks again
        assert_same(hits, expected, ["t", "prim_id"])
        del litter
    lone_group, lone_scene = cuda_groups(v, oracle.load_mesh("stanford-bunny")[1])[0]
    hits = lone_scene.intersect(torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda(), outputs=["t"])
    del lone_scene, lone_group
    gc.collect()
    np.testing.assert_array_equal(on_host(hits.t), expected.t)
    member = groups[0][0].devices[0]
    uneven = vkray.DeviceGroup([member, member], weights=[1, 1000])
    uneven_scene = uneven.scene([uneven.mesh(v, oracle.load_mesh("stanford-bunny")[1])])
    two = uneven_scene.intersect(torch.from_numpy(o[:2]).cuda(), torch.from_numpy(d[:2]).cuda(), outputs=["t"])
    np.testing.assert_array_equal(on_host(two.t), expected.t[:2])


def test_a_group_splits_cuda_rays_from_several_threads(bunny, groups):
    """Four threads split batches at once, their rays on different GPUs where there are several."""
    v, scene = bunny
    batches = [[a.astype(np.float32) for a in oracle.random_rays(v, 40_000, seed=20 + k)] for k in range(4)]
    expected = [scene.intersect(o, d).t for o, d in batches]
    for group, group_scene in groups:
        gpus = [f"cuda:{device.cuda_device}" for device in group.devices]

        def work(k, group_scene=group_scene, gpus=gpus):
            o, d = (torch.from_numpy(a).to(gpus[k % len(gpus)]) for a in batches[k])
            return [on_host(group_scene.intersect(o, d).t) for _ in range(3)]

        for runs, want in zip(oracle.in_threads(len(batches), work), expected):
            for found in runs:
                np.testing.assert_array_equal(found, want)


def test_cuda_rays_of_a_gpu_outside_the_group_are_named(bunny):
    v, _ = bunny
    members = [d for d in vkray.devices() if vkray.Device(d.index).cuda_device is not None]
    if len(members) < 2:
        pytest.skip("one CUDA GPU: no GPU outside a group of it")
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 1000, seed=2))
    alone = vkray.DeviceGroup([members[0].index])
    other = f"cuda:{vkray.Device(members[1].index).cuda_device}"
    lone = alone.scene([alone.mesh(v, oracle.load_mesh("stanford-bunny")[1])])
    with pytest.raises(ValueError, match=f"the rays live on {other}, which is none of this group's devices"):
        lone.intersect(torch.from_numpy(o).to(other), torch.from_numpy(d).to(other))
