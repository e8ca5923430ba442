"""The leaner layouts host-packed rays take (geometry/rays.rs RayLayout; shaders/rays.glsl):
float32 rays of one interval are packed as 24 bytes a ray (origin and direction), and from one
origin as 12 (the direction), the rest in a header per chunk; other rays as 32. The oracle: the
same queries on a device that packs every ray in the full layout (VKRAY_PACK=full), bit for bit,
itself checked against Embree elsewhere; the bytes packed are read from the profile, so that a
layout not taken fails here. Far rays (advanced towards the scene) send their chunk back to the
full layout; scenes far from the world's origin, masks, every query kind the chunk loop runs, and
several threads at once."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import oracle
import vkray
from conftest import BACKENDS, VALIDATION

N = 5000
HEADER = 32  # bytes of a leaner layout's header, per chunk


@pytest.fixture(scope="module", params=BACKENDS)
def pair(request):
    """(leaner layouts, full layout only): VKRAY_PACK is read when a device opens."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.delenv("VKRAY_PACK", raising=False)
        lean = vkray.Device(backend=request.param, validation=VALIDATION)
        monkeypatch.setenv("VKRAY_PACK", "full")
        full = vkray.Device(backend=request.param, validation=VALIDATION)
        yield lean, full


def bunny_scenes(pair, shift=(0.0, 0.0, 0.0)):
    v, f = oracle.load_mesh("stanford-bunny")
    v = v + np.asarray(shift)
    return [device.scene(device.mesh(v, f)) for device in pair], v


def queries(scene, o, d, **bounds):
    """Every query kind the chunk loop packs rays for, by name."""
    hits = scene.intersect(o, d, outputs=vkray.HIT_FIELDS, **bounds)
    every = scene.intersect_all(o, d, outputs=["t", "prim_id"], **bounds)
    return {
        "intersect_all offsets": every.offsets,
        "intersect_all t": every.t,
        "intersect_all prim_id": every.prim_id,
        **{f"intersect {name}": getattr(hits, name) for name in vkray.HIT_FIELDS},
        "occluded": scene.occluded(o, d, **bounds),
        "count": scene.count(o, d, **bounds),
        "transmittance": scene.transmittance(o, d, **bounds),
        "intersect exact t": scene.intersect(o, d, outputs=["t"], precision="exact", **bounds).t
        if "exact" in _tiers(scene)
        else None,
    }


_exact = {}


def _tiers(scene):
    backend = scene.device.backend
    if backend not in _exact:
        from test_precision import tiers

        _exact[backend] = tiers(scene.device)
    return _exact[backend]


def assert_bitwise(got, want, what):
    for name, expected in want.items():
        if expected is None:
            continue
        a, b = np.asarray(got[name]), np.asarray(expected)
        assert a.dtype == b.dtype and a.shape == b.shape, (what, name)
        assert a.tobytes() == b.tobytes(), f"{what}: {name} differs in {int((a != b).sum())} values"


def packed_bytes(scene, *rays, **bounds):
    """The bytes of rays the host packed for `scene.intersect(*rays, **bounds)`."""
    scene.intersect(*rays, **bounds)
    return scene.device.last_trace_profile["ray_bytes"]


@pytest.mark.parametrize("shift", [(0.0, 0.0, 0.0), (3e4, -2e4, 1e4)], ids=["at the origin", "far from it"])
def test_leaner_layouts_answer_as_the_full_layout(pair, shift):
    """Random float32 rays (24 bytes a ray), a camera's from one origin (12), and rays the lean
    layouts do not take (per-ray bounds, float64: 32): every query kind answers as the full
    layout does, bit for bit."""
    (lean, full), v = bunny_scenes(pair, shift)
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, N, seed=4))
    eye, dirs = oracle.camera_rays(v, 80, 60)
    eye, dirs = eye.astype(np.float32), dirs.astype(np.float32)
    tmax = np.random.default_rng(4).uniform(0.05, 0.4, N)
    cases = [
        ("random", o, d, {}, 24 * N + HEADER),
        ("random, one interval", o, d, {"tmin": 0.01, "tmax": 0.3}, 24 * N + HEADER),
        ("camera", eye, dirs, {}, 12 * len(dirs) + HEADER),
        ("per-ray tmax", o, d, {"tmax": tmax}, 32 * N),
        ("float64", o.astype(np.float64), d.astype(np.float64), {}, 32 * N),
    ]
    for what, origins, directions, bounds, expected_bytes in cases:
        want = queries(full, origins, directions, **bounds)
        assert_bitwise(queries(lean, origins, directions, **bounds), want, what)
        lean_bytes = packed_bytes(lean, origins, directions, **bounds)
        full_bytes = packed_bytes(full, origins, directions, **bounds)
        assert (lean_bytes, full_bytes) == (expected_bytes, 32 * len(directions)), what


def test_repeated_origins_take_the_camera_layout(pair):
    """A camera's rays with the origin repeated on every row (as trimesh's `camera_rays` gives
    them) are packed as rays from one origin (12 bytes a ray); one row whose origin differs, even
    by the sign of a zero, keeps every origin (24). Every query kind answers as the full layout,
    bit for bit."""
    (lean, full), v = bunny_scenes(pair)
    eye, dirs = oracle.camera_rays(v, 80, 60)
    dirs = dirs.astype(np.float32)
    n = len(dirs)
    repeated = np.repeat(eye.astype(np.float32).reshape(1, 3), n, axis=0)
    cases = [("repeated", repeated, 12 * n + HEADER)]
    for row in (1, n // 2, n - 1):
        moved = repeated.copy()
        moved[row, 1] = np.nextafter(moved[row, 1], np.float32(np.inf))
        cases.append((f"row {row} moved by an ulp", moved, 24 * n + HEADER))
    signed = repeated.copy()
    signed[:, 0] = 0.0
    signed[n - 1, 0] = -0.0
    cases.append(("a negative zero in the last row", signed, 24 * n + HEADER))
    for what, origins, expected_bytes in cases:
        want = queries(full, origins, dirs)
        assert_bitwise(queries(lean, origins, dirs), want, what)
        assert packed_bytes(lean, origins, dirs) == expected_bytes, what
        for query in (lean.count, lean.intersect_all):
            query(origins, dirs)
            assert lean.device.last_trace_profile["ray_bytes"] == expected_bytes, (what, query.__name__)


def test_exact_tier_takes_the_leaner_layouts(pair):
    """The exact tier packs float32 rays of one interval as given (24 bytes a ray, 12 from one
    origin, a header of 64 per chunk), which the shaders move into the scene's frame in f64;
    per-ray bounds and float64 rays take 64. Closest hits, counts and all hits equal the full
    layout's, bit for bit (the full layout's f64 rays are the host's)."""
    # Far from the world's origin: the shift the shaders subtract is large.
    (lean, full), v = bunny_scenes(pair, (3e6, -2e6, 1e6))
    if "exact" not in _tiers(lean):
        pytest.skip("no exact tier here")
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, N, seed=8))
    eye, dirs = oracle.camera_rays(v, 80, 60)
    eye, dirs = eye.astype(np.float32), dirs.astype(np.float32)
    tmax = np.random.default_rng(8).uniform(0.05, 0.4, N)
    cases = [
        ("random", o, d, {}, 24 * N + 64),
        ("camera", eye, dirs, {}, 12 * len(dirs) + 64),
        ("per-ray tmax", o, d, {"tmax": tmax}, 64 * N),
        ("float64", o.astype(np.float64), d.astype(np.float64), {}, 64 * N),
    ]
    for what, origins, directions, bounds, expected_bytes in cases:
        answers = []
        for scene in (lean, full):
            hits = scene.intersect(origins, directions, outputs=["t", "prim_id", "uv"], precision="exact", **bounds)
            packed = scene.device.last_trace_profile["ray_bytes"]
            every = scene.intersect_all(origins, directions, outputs=["t", "prim_id"], precision="exact", **bounds)
            counts = scene.count(origins, directions, precision="exact", **bounds)
            answers.append((packed, {"t": hits.t, "prim_id": hits.prim_id, "uv": hits.uv, "all t": every.t,
                                     "all offsets": every.offsets, "counts": counts}))
        (lean_bytes, got), (full_bytes, want) = answers
        assert_bitwise(got, want, what)
        assert (lean_bytes, full_bytes) == (expected_bytes, 64 * len(directions)), what


def test_a_chunk_with_a_far_ray_takes_the_full_layout(pair):
    """Chunks of 1000 rays, the third holding a ray from 1e6 radii away (advanced towards the
    scene before packing): that chunk and those after it are packed in full, the two before lean;
    the answers (t of the far ray included) are the full layout's."""
    (lean, full), v = bunny_scenes(pair)
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, N, seed=5))
    centre, radius = oracle.bounds(v)
    o[2500] = centre + np.array([1e6 * radius, 0, 0])
    d[2500] = [-1.0, 0.0, 0.0]
    devices = (lean.device, full.device)
    saved = [device.chunk_rays for device in devices]
    try:
        for device in devices:
            device.chunk_rays = 1000
        assert_bitwise(queries(lean, o, d), queries(full, o, d), "far ray")
        assert np.isfinite(lean.intersect(o, d).t[2500])
        assert packed_bytes(lean, o, d) == 2 * (24 * 1000 + HEADER) + 3 * 32 * 1000
        # A far ray and an invalid one in one chunk: the invalid one is named, as in full.
        bad = d.copy()
        bad[2600] = 0.0
        for scene in (lean, full):
            with pytest.raises(ValueError, match="2600"):
                scene.intersect(o, bad)
    finally:
        for device, rays in zip(devices, saved):
            device.chunk_rays = rays


def test_masks_tiny_chunks_and_invalid_rays(pair):
    """Per-ray masks ride beside the lean layouts; chunks too small for a header (1 ray) take the
    full layout; an invalid ray is named as the full layout names it."""
    (lean, full), v = bunny_scenes(pair)
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 300, seed=6))
    masks = np.random.default_rng(6).integers(0, 2, 300).astype(np.uint8)
    assert_bitwise(
        {"t": lean.intersect(o, d, mask=masks).t}, {"t": full.intersect(o, d, mask=masks).t}, "masks"
    )
    saved = lean.device.chunk_rays
    try:
        lean.device.chunk_rays = 1
        assert_bitwise({"t": lean.intersect(o[:7], d[:7]).t}, {"t": full.intersect(o[:7], d[:7]).t}, "1 a chunk")
        assert lean.device.last_trace_profile["ray_bytes"] == 32 * 7
    finally:
        lean.device.chunk_rays = saved
    bad = d.copy()
    bad[123] = 0.0
    for scene in (lean, full):
        with pytest.raises(ValueError, match="123"):
            scene.intersect(o, bad)
        with pytest.raises(ValueError, match="123"):
            scene.intersect(o[0], bad)


def test_several_threads_at_once(pair):
    (lean, full), v = bunny_scenes(pair)
    batches = [tuple(a.astype(np.float32) for a in oracle.random_rays(v, N, seed=10 + k)) for k in range(4)]
    batches[1] = (batches[1][0][0], batches[1][1])  # one origin for all
    want = [queries(full, o, d) for o, d in batches]
    with ThreadPoolExecutor(4) as threads:
        got = list(threads.map(lambda batch: queries(lean, *batch), batches))
    for k, (a, b) in enumerate(zip(got, want)):
        assert_bitwise(a, b, f"batch {k}")


def test_subnormal_float32_coordinates_reach_the_exact_tier_as_given(pair):
    """Float32 rays whose origin or direction has a subnormal coordinate (1e-40) are traced by
    the exact tier as those values (the shaders widen them from their bits: a GPU's conversion may
    flush them to zero): rays one such coordinate away from the edge x = 0 that two squares share
    hit the square on its side, as the full layout (the host's f64 rays) and the reference tier
    find, from one origin and each from its own."""
    v = np.array([[-1, -1, 0], [0, -1, 0], [0, 1, 0], [-1, 1, 0], [1, -1, 0], [1, 1, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])  # left square 0-1, right square 2-3
    scenes = [device.scene(device.mesh(v, f)) for device in pair]
    if "exact" not in _tiers(scenes[0]):
        pytest.skip("no exact tier here")
    tiny = np.float32(1e-40)
    assert 0 < tiny < np.finfo(np.float32).tiny
    one_origin = np.array([0.0, 0.3, -1.0], dtype=np.float32)
    directions = np.array([[tiny, 0, 1], [-tiny, 0, 1]], dtype=np.float32)
    own_origins = np.array([[tiny, 0.3, -1.0], [-tiny, 0.3, -1.0]], dtype=np.float32)
    straight = np.array([0, 0, 1], dtype=np.float32)
    for origins, dirs in ((one_origin, directions), (own_origins, straight)):
        answers = [scene.intersect(origins, dirs, outputs=["prim_id"], precision="exact").prim_id for scene in scenes]
        reference = scenes[1].intersect(origins, dirs, outputs=["prim_id"], precision="reference")
        np.testing.assert_array_equal(reference.prim_id // 2, [1, 0])  # right square, then left
        np.testing.assert_array_equal(answers[0], reference.prim_id)
        np.testing.assert_array_equal(answers[1], reference.prim_id)
