"""The acceleration-structure lifecycle: refit (update) of meshes and scenes, compaction, and the
errors that guard them. The oracle is a fresh build of the same geometry, and the f64 reference."""

import numpy as np
import pytest

import vkray
from oracle import load_mesh, random_rays


def wobble(v, amount):
    """A smooth deformation: the same topology, vertices moved by up to `amount` of the size."""
    size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    return v + amount * size * np.sin(7 * v[:, [1, 2, 0]] / size)


def assert_same_hits(a, b, exact):
    if exact:
        # A refitted mesh keeps the frame (centre) it was built in, a fresh one centres anew: the
        # f64 geometry agrees to rounding, the triangles exactly.
        np.testing.assert_array_equal(a.prim_id, b.prim_id)
        np.testing.assert_allclose(a.t, b.t, rtol=1e-12)
    else:
        # f32 traversal of a refitted and of a fresh tree: the same triangles, t to f32 rounding.
        same = a.prim_id == b.prim_id
        assert same.mean() > 0.9999
        np.testing.assert_allclose(a.t[same & a.hit], b.t[same & a.hit], rtol=1e-5)


def test_refitted_mesh_traces_like_a_fresh_build(device):
    v, f = load_mesh("stanford-bunny")
    mesh = device.mesh(v, f, allow_update=True)
    scene = device.scene(mesh, allow_update=True)
    moved = wobble(v, 0.02)
    origins, directions = random_rays(moved, 20000, seed=31)
    mesh.update(moved)
    with pytest.raises(ValueError, match="call scene.update"):
        scene.intersect(origins, directions)
    scene.update()
    fresh = device.scene(device.mesh(moved, f))
    for tier in ("fast", "reference"):
        assert_same_hits(scene.intersect(origins, directions, precision=tier),
                         fresh.intersect(origins, directions, precision=tier), exact=tier == "reference")
    assert mesh.stats["update_seconds"] > 0
    assert scene.stats["update_seconds"] > 0


def test_refit_needs_allow_update_and_the_same_topology(any_device):
    v, f = load_mesh("spot")
    fixed = any_device.mesh(v, f)
    with pytest.raises(ValueError, match="allow_update=True"):
        fixed.update(v)
    mesh = any_device.mesh(v, f, allow_update=True)
    with pytest.raises(ValueError, match="same .* vertices"):
        mesh.update(v[:-1])
    with pytest.raises(ValueError, match="not finite"):
        mesh.update(np.where(np.arange(len(v))[:, None] == 3, np.nan, v))


def test_scene_without_allow_update_is_rebuilt_after_a_mesh_update(any_device):
    # The error chain must lead somewhere: a scene built without allow_update=True is rebuilt
    # (not refitted) by update(), and then traces the moved mesh.
    v, f = load_mesh("spot")
    mesh = any_device.mesh(v, f, allow_update=True)
    scene = any_device.scene(mesh)
    size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    moved = v + [0.0, 0.0, 3 * size]
    mesh.update(moved)
    o = np.array([[0.0, 0.0, -10 * size]])
    d = (v.mean(axis=0) + [0.0, 0.0, 3 * size]) - o
    with pytest.raises(ValueError, match=r"scene\.update\(\)"):
        scene.intersect(o, d)
    scene.update()
    fresh = any_device.scene(any_device.mesh(moved, f))
    got, want = scene.intersect(o, d), fresh.intersect(o, d)
    assert want.hit.all()
    np.testing.assert_array_equal(got.prim_id, want.prim_id)
    np.testing.assert_allclose(got.t, want.t, rtol=1e-6)


def test_scene_refit_moves_and_hides_instances(device):
    v, f = load_mesh("spot")
    mesh = device.mesh(v, f)
    size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    start = [np.eye(4), np.eye(4)]
    start[1][0, 3] = 2 * size
    scene = device.scene([vkray.Instance(mesh, t) for t in start], allow_update=True)
    moved = np.stack(start).copy()
    moved[0, :3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # a quarter turn
    moved[1, 1, 3] = 0.5 * size
    scene.update(transforms=moved)
    fresh = device.scene([vkray.Instance(mesh, t) for t in moved])
    everything = np.vstack([v, v @ moved[1, :3, :3].T + moved[1, :3, 3]])
    origins, directions = random_rays(everything, 20000, seed=32)
    for tier in ("fast", "reference"):
        a = scene.intersect(origins, directions, precision=tier)
        b = fresh.intersect(origins, directions, precision=tier)
        np.testing.assert_array_equal(a.instance_id, b.instance_id)
        assert_same_hits(a, b, exact=tier == "reference")
    scene.update(masks=[0xFF, 0])
    hidden = scene.intersect(origins, directions)
    assert hidden.hit.any() and not (hidden.instance_id == 1).any()
    assert scene.instances[1].mask == 0
    with pytest.raises(ValueError, match="shape"):
        scene.update(transforms=moved[:1])


def test_exact_tier_follows_refits(device):
    v, f = load_mesh("fandisk")
    mesh = device.mesh(v, f, allow_update=True)
    scene = device.scene(mesh, allow_update=True)
    origins, directions = random_rays(v, 5000, seed=33)
    try:
        scene.intersect(origins, directions, precision="exact")
    except vkray.UnsupportedError:
        pytest.skip("no exact tier on this backend")
    moved = wobble(v, 0.05)
    mesh.update(moved)
    scene.update()
    a = scene.intersect(origins, directions, precision="exact")
    b = scene.intersect(origins, directions, precision="reference")
    np.testing.assert_array_equal(a.prim_id, b.prim_id)
    np.testing.assert_allclose(a.t, b.t, rtol=1e-12)


@pytest.mark.parametrize("name", ["stanford-bunny", "teapot"])
def test_compaction_shrinks_and_keeps_hits(device, name):
    v, f = load_mesh(name)
    plain = device.mesh(v, f)
    compacted = device.mesh(v, f, compact=True)
    # The driver's compacted size, never more than built (lavapipe reports no saving; NVIDIA's
    # savings are in docs/benchmarks.md).
    assert compacted.stats["compacted"] and compacted.stats["bytes"] <= compacted.stats["built_bytes"]
    assert plain.stats["bytes"] == plain.stats["built_bytes"]
    origins, directions = random_rays(v, 20000, seed=34)
    a = device.scene(plain).intersect(origins, directions)
    b = device.scene(compacted).intersect(origins, directions)
    np.testing.assert_array_equal(a.prim_id, b.prim_id)
    np.testing.assert_array_equal(a.t, b.t)


def test_many_meshes_under_a_scratch_budget(device):
    """Five shared meshes built at once: one submission unbounded, several under a budget that
    holds about two builds' scratch, and every mesh traces as one built alone."""
    from oracle import MESH_NAMES

    items = [load_mesh(name) for name in MESH_NAMES]
    single = [device.mesh(v, f) for v, f in items]
    together = device.meshes(items)
    assert {m.stats["batch"] for m in together} == {0}
    scratch = sorted(m.stats["scratch_bytes"] for m in single)
    if device.engine == "cpu":
        # Embree builds each mesh on every core and frees its own scratch: no batches to bound.
        assert scratch[-1] == 0
        batched = device.meshes(items, budget_bytes=1, compact=True)
        assert {m.stats["batch"] for m in batched} == {0}
    else:
        batched = device.meshes(items, budget_bytes=scratch[-1] + scratch[-2], compact=True)
        batches = [m.stats["batch"] for m in batched]
        assert batches == sorted(batches) and batches[-1] >= 1
    for (v, _), alone, many, compacted in zip(items, single, together, batched):
        assert compacted.stats["compacted"] and compacted.stats["bytes"] <= compacted.stats["built_bytes"]
        origins, directions = random_rays(v, 3000, seed=35)
        expected = device.scene(alone).intersect(origins, directions)
        for mesh in (many, compacted):
            hits = device.scene(mesh).intersect(origins, directions)
            np.testing.assert_array_equal(hits.prim_id, expected.prim_id)
            np.testing.assert_array_equal(hits.t, expected.t)


def test_many_meshes_reject_what_cannot_fit(any_device):
    v, f = load_mesh("spot")
    with pytest.raises(ValueError, match="structure 0 needs .* bytes of build scratch"):
        any_device.meshes([(v, f)], budget_bytes=1)
    with pytest.raises(ValueError, match="mesh 1: faces row 0"):
        any_device.meshes([(v, f), (v, [[0, 1, len(v)]])])
    with pytest.raises(ValueError, match="budget_bytes"):
        any_device.meshes([(v, f)], budget_bytes=0)
    with pytest.raises(TypeError, match="pair"):
        any_device.meshes([v])


@pytest.mark.parametrize("vertex_format, tolerance", [("float16", 2e-3), ("snorm16", 1e-4)])
def test_quantized_vertices_save_memory_and_stay_close(device, vertex_format, tolerance):
    """16-bit vertices take 8 bytes instead of 12. Every tier traces the same quantized surface
    (the f64 tiers are given the dequantized vertices), so the tiers agree with each other as on
    float32 meshes; against the float32 mesh, hits move by at most the quantization step:
    2^-11 of the half-size for float16, 2^-15 for snorm16 (`tolerance` of the size, p99)."""
    if vertex_format not in device.limits["vertex_formats"]:
        pytest.skip(f"{device.name} does not build from {vertex_format}")
    v, f = load_mesh("stanford-bunny")
    size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    full = device.mesh(v, f)
    small = device.mesh(v, f, vertex_format=vertex_format, allow_update=True)
    assert small.stats["vertex_bytes"] == 8 * len(v) and full.stats["vertex_bytes"] == 12 * len(v)
    origins, directions = random_rays(v, 20000, seed=36)
    scene = device.scene(small)
    ref = scene.intersect(origins, directions, precision="reference")
    fast = scene.intersect(origins, directions)
    same = fast.prim_id == ref.prim_id
    assert same.mean() > 0.999
    np.testing.assert_allclose(fast.t[same & ref.hit], ref.t[same & ref.hit], rtol=1e-5)
    np.testing.assert_allclose(fast.normal[same & ref.hit], ref.normal[same & ref.hit], atol=1e-3)
    exact32 = device.scene(full).intersect(origins, directions, precision="reference")
    both = ref.hit & exact32.hit
    moved = np.abs(ref.t[both] - exact32.t[both]) * np.linalg.norm(directions[both], axis=1) / size
    assert np.percentile(moved, 99) < tolerance
    assert (ref.hit != exact32.hit).mean() < 0.01
    with pytest.raises(ValueError, match="beyond the range"):
        small.update(v * 3)
    with pytest.raises(ValueError, match="vertex_format must be"):
        device.mesh(v, f, vertex_format="unorm8")
