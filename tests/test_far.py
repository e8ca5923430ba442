"""Far from the scene (issue 9, defect 5): ray origins finite in float32 but up to 1e38 away, a
refit that moves instances far off, and spheres whose squared sizes leave float32's range. Each
either works (f64 where it matters) or raises; the reference tier and analytic answers judge."""

import numpy as np
import pytest

import vkray

SQUARE = (np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 2, 3]]))


@pytest.mark.parametrize("distance", [1e5, 1e20, 1e30, 1e38])
def test_origins_far_away_hit_what_the_reference_hits(device, distance):
    """Before, the fast tier missed these without a word: the f32 origin lost the scene."""
    scene = device.scene(device.mesh(*SQUARE))
    rng = np.random.default_rng(5)
    xy = rng.uniform(0.05, 0.95, (64, 2))
    origins = np.column_stack([xy, np.full(64, distance)]).astype(np.float32)
    directions = np.array([[0, 0, -1.0]], np.float32)
    want = scene.intersect(origins, directions, precision="reference")
    assert want.hit.all()
    for tier in ("fast", "refined"):
        got = scene.intersect(origins, directions, precision=tier)
        np.testing.assert_array_equal(got.prim_id, want.prim_id, err_msg=tier)
        np.testing.assert_allclose(got.t, want.t, rtol=1e-6, err_msg=tier)
    # Rays that stop short of the scene, or start beyond it going away, miss.
    assert not scene.intersect(origins, directions, tmax=0.5 * distance).hit.any()
    assert not scene.intersect(origins, -directions).hit.any()


def test_far_oblique_origins_agree_with_the_reference(device):
    scene = device.scene(device.mesh(*SQUARE))
    rng = np.random.default_rng(6)
    targets = np.column_stack([rng.uniform(0.1, 0.9, (256, 2)), np.zeros(256)])
    directions = rng.normal(size=(256, 3))
    directions[:, 2] = -np.abs(directions[:, 2]) - 0.5
    origins = targets - 1e7 * directions
    want = scene.intersect(origins, directions, precision="reference")
    got = scene.intersect(origins, directions)
    assert (got.prim_id == want.prim_id).mean() > 0.98  # shared-edge rays may differ in f32
    hit = want.hit & got.hit
    np.testing.assert_allclose(got.t[hit], want.t[hit], rtol=1e-6)


@pytest.mark.parametrize("offset, scale", [(1e12, 1.0), (1e30, 1e17)])
def test_refit_far_away_keeps_the_fast_tier_right(device, offset, scale):
    """Before, a refit kept the scene's frame: instances moved 1e12 away lost f32 precision in it,
    and 1e30 away (a mesh scaled to 1e17, so that f64 still resolves it) left nothing of it.
    Sizes stay where their squares fit in float32: hardware triangle tests run in f32 (on the
    H100 a square scaled to 1e26 reported only its first triangle)."""
    if scale > 1 and "nvidia" in device.info.driver.lower():
        # Seen on the H100: with an instance transform scaling by 1e17 the hardware's f32 triangle
        # test reports the first triangle of the square for every ray (a mesh of that size, with
        # no scale in the transform, traces right: the next test).
        pytest.xfail("NVIDIA's f32 triangle test under an instance scale of 1e17")
    mesh = device.mesh(*SQUARE)
    scene = device.scene([vkray.Instance(mesh), vkray.Instance(mesh, np.eye(4))], allow_update=True)
    moved = np.stack([np.eye(4), np.eye(4)])
    moved[:, :3, :3] *= scale
    moved[0, :3, 3] = [offset, -2 * offset, 0.5 * offset]
    moved[1, :3, 3] = moved[0, :3, 3] + [4 * scale, 0, 0]
    scene.update(transforms=moved)
    rng = np.random.default_rng(7)
    xy = rng.uniform(0.05, 0.95, (64, 2))
    origins = moved[0, :3, 3] + scale * np.column_stack([xy, np.full(64, 3.0)])
    directions = [0.0, 0.0, -1.0]
    want = scene.intersect(origins, directions, precision="reference")
    got = scene.intersect(origins, directions)
    assert want.hit.all()
    np.testing.assert_array_equal(got.instance_id, want.instance_id)
    np.testing.assert_array_equal(got.prim_id, want.prim_id)
    np.testing.assert_allclose(got.t, want.t, rtol=1e-6)


def test_instances_float32_cannot_hold_together_raise(device):
    mesh = device.mesh(*SQUARE)
    left, right = np.diag([3e38, 3e38, 3e38, 1.0]), np.diag([3e38, 3e38, 3e38, 1.0])
    left[0, 3], right[0, 3] = -3e38, 3e38  # together x in [-3e38, 6e38]: no frame holds both in f32
    with pytest.raises(ValueError, match="float32"):
        device.scene([vkray.Instance(mesh, left), vkray.Instance(mesh, right)])


def test_sphere_radii_whose_squares_leave_float32_raise(device):
    with pytest.raises(ValueError, match="radius 0"):
        device.spheres([[0.0, 0.0, 0.0]], 1e19)
    with pytest.raises(ValueError, match="span"):
        device.spheres([[0.0, 0.0, 0.0], [2e18, 0.0, 0.0]], 1.0)


@pytest.mark.parametrize("radii_away", [1e3, 1e6, 1e9])
def test_spheres_seen_from_far_away(device, radii_away):
    """Before, an origin 1e9 radii away reported the far side, missed, or gave a NaN normal."""
    scene = device.scene(device.spheres([[0.0, 0.0, 0.0]], 1.0))
    offsets = np.array([[0.0, 0.0], [0.3, -0.2], [0.5, 0.5]])
    origins = np.column_stack([offsets, np.full(3, radii_away)])
    hits = scene.intersect(origins, [0.0, 0.0, -1.0])
    z = np.sqrt(1 - np.sum(offsets**2, axis=1))  # the near side
    assert hits.hit.all()
    np.testing.assert_allclose(hits.t, radii_away - z, rtol=1e-6)
    assert np.isfinite(hits.normal).all()
    np.testing.assert_allclose(hits.normal, np.column_stack([offsets, z]), atol=1e-3)


@pytest.mark.parametrize("offset, size", [(1e12, 1.0), (1e30, 1e17)])
def test_mesh_refit_far_away_keeps_the_fast_tier_right(device, offset, size):
    """Before, a refitted mesh kept the frame it was built in: vertices moved 1e12 away lost
    f32 precision in it (the sizes are chosen so that f64 still resolves the surface)."""
    v, f = SQUARE
    mesh = device.mesh(v * size, f, allow_update=True)
    scene = device.scene(mesh)
    moved = v * size + [offset, -offset, 0.5 * offset]
    mesh.update(moved)
    scene.update()
    rng = np.random.default_rng(8)
    xy = rng.uniform(0.05, 0.95, (64, 2))
    origins = moved[0] + size * np.column_stack([xy, np.full(64, 3.0)])
    want = scene.intersect(origins, [0.0, 0.0, -1.0], precision="reference")
    got = scene.intersect(origins, [0.0, 0.0, -1.0])
    assert want.hit.all()
    np.testing.assert_array_equal(got.prim_id, want.prim_id)
    np.testing.assert_allclose(got.t, want.t, rtol=1e-6)


@pytest.mark.parametrize("distance", [20.0, 1e6, 1e12, 1e30])
def test_transmittance_of_far_rays_is_the_light_kept(device, distance):
    """A far ray is advanced towards the scene before f32 traversal and its `t` corrected after;
    transmittance's `t` is the light a ray keeps, which no advance may touch (the fast tier of a
    Vulkan device answered 0.75 + 1e6 for a ray from 1e6 away through a veil of opacity 0.25).
    Two veils, of opacity 0.25 and 0.5: 0.375 of the light through both, all of it beside them."""
    v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    lifted = np.eye(4)
    lifted[2, 3] = 0.5
    scene = device.scene([device.mesh(v, f, opacity=0.25), vkray.Instance(device.mesh(v, f, opacity=0.5), lifted)])
    origins = np.array([[0.1, 0.2, -distance], [0.5, -0.5, -distance], [3.0, 0.0, -distance]])
    for precision in ("fast", "refined", "exact", "reference"):
        kept = scene.transmittance(origins, [0.0, 0.0, 1.0], precision=precision)
        np.testing.assert_allclose(kept, [0.375, 0.375, 1.0], rtol=1e-6, err_msg=precision)
