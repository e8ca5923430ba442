"""Procedural spheres: boxes in a BLAS, intersected by a shader in both backends, against the
analytic answer computed in float64 with numpy."""

import numpy as np
import pytest

import vkray
from oracle import load_mesh, random_rays


def analytic(centers, radii, origins, directions):
    """Nearest t >= 0 of each ray over all spheres (inf on a miss) and the sphere's index."""
    f = origins[:, None, :] - centers[None, :, :]
    a = np.sum(directions**2, axis=1)[:, None]
    b = np.sum(f * directions[:, None, :], axis=2)
    c = np.sum(f**2, axis=2) - radii[None, :] ** 2
    disc = b**2 - a * c
    root = np.sqrt(np.maximum(disc, 0))
    near, far = (-b - root) / a, (-b + root) / a
    t = np.where(near >= 0, near, far)
    t = np.where((disc >= 0) & (t >= 0), t, np.inf)
    return t.min(axis=1), np.where(np.isfinite(t.min(axis=1)), t.argmin(axis=1), -1)


def test_spheres_match_the_analytic_answer(device):
    rng = np.random.default_rng(61)
    centers = rng.uniform(-5, 5, (300, 3))
    radii = rng.uniform(0.05, 0.5, 300)
    scene = device.scene(device.spheres(centers, radii))
    origins = rng.uniform(-8, 8, (20000, 3))
    directions = rng.normal(size=(20000, 3))
    hits = scene.intersect(origins, directions)
    t, index = analytic(centers, radii, origins, directions)
    np.testing.assert_array_equal(hits.hit, np.isfinite(t))
    assert (hits.prim_id == index).mean() > 0.9999
    same = hits.hit & (hits.prim_id == index)
    # f32: distances along the ray agree to a few ulps of the scene's size (10 units).
    error = np.abs(hits.t[same] - t[same]) * np.linalg.norm(directions[same], axis=1)
    assert error.max() <= 1e-5 * 10
    points = origins[same] + t[same, None] * directions[same]
    expected = (points - centers[index[same]]) / radii[index[same], None]
    np.testing.assert_allclose(hits.normal[same], expected, atol=1e-4)
    assert np.isnan(hits.uv[same]).all()
    np.testing.assert_array_equal(scene.occluded(origins, directions), hits.hit)


def test_small_far_spheres_stay_accurate(device):
    """A sphere of radius 1e-3 at distance 1e4: the textbook quadratic loses every digit of t's
    difference from the far root; the careful one keeps f32's relative precision."""
    centers = np.array([[1e4, 0.0, 0.0], [0.0, 1e4, 0.0]])
    scene = device.scene(device.spheres(centers, 1e-3))
    origins = np.zeros((2, 3))
    directions = np.array([[1.0, 1e-8, 0.0], [0.0, 1.0, 2e-8]])
    hits = scene.intersect(origins, directions)
    t, _ = analytic(centers, np.full(2, 1e-3), origins, directions)
    assert hits.hit.all()
    np.testing.assert_allclose(hits.t, t, rtol=1e-6)


def test_spheres_mix_with_triangles_and_transforms(device):
    """The bunny and a sphere set (moved and scaled uniformly by an instance transform) in one
    scene: every ray reports the nearer of the two, as each alone would have it."""
    v, f = load_mesh("stanford-bunny")
    rng = np.random.default_rng(62)
    centers = rng.uniform(v.min(axis=0), v.max(axis=0), (40, 3))
    radii = rng.uniform(0.002, 0.01, 40)
    place = np.eye(4)
    place[:3, :3] *= 1.5
    place[:3, 3] = [0.01, -0.02, 0.03]
    spheres = device.spheres(centers, radii)
    bunny = device.mesh(v, f)
    scene = device.scene([vkray.Instance(bunny), vkray.Instance(spheres, place, custom_index=7)])
    origins, directions = random_rays(v, 20000, seed=63)
    hits = scene.intersect(origins, directions)
    tri = device.scene(bunny).intersect(origins, directions)
    t_sphere, index = analytic(centers * 1.5 + place[:3, 3], radii * 1.5, origins, directions)
    sphere_first = t_sphere < tri.t
    np.testing.assert_array_equal(hits.instance_id[sphere_first], 1)
    np.testing.assert_array_equal(hits.custom_index[sphere_first], 7)
    np.testing.assert_array_equal(hits.prim_id[sphere_first], index[sphere_first])
    # f32 in the bunny's frame: distances agree to a few f32 ulps of the scene's size.
    size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    error = np.abs(hits.t[sphere_first] - t_sphere[sphere_first]) * np.linalg.norm(directions[sphere_first], axis=1)
    assert error.max() <= 1e-5 * size
    tri_first = tri.hit & ~sphere_first
    assert (hits.prim_id[tri_first] == tri.prim_id[tri_first]).mean() > 0.9999
    assert sphere_first.sum() > 100 and tri_first.sum() > 1000


def test_sphere_errors(any_device):
    with pytest.raises(ValueError, match="radius 1 must be finite and > 0"):
        any_device.spheres([[0, 0, 0], [1, 1, 1]], [1.0, 0.0])
    with pytest.raises(ValueError, match="radii must be one value or 2"):
        any_device.spheres([[0, 0, 0], [1, 1, 1]], [1.0, 2.0, 3.0])
    spheres = any_device.spheres([[0, 0, 0]], 1.0)
    assert spheres.kind == "spheres" and "spheres" in repr(spheres)
    scene = any_device.scene(spheres)
    for precision in ("refined", "exact", "reference"):
        with pytest.raises(vkray.UnsupportedError, match="precision='fast'"):
            scene.intersect([0, 0, 5], [0, 0, -1], precision=precision)
    # Positions of sphere hits: origin + t * direction.
    hits = scene.intersect([[0, 0, 5], [0, 3, 5]], [0, 0, -1], outputs=["t", "position"])
    np.testing.assert_allclose(hits.position[0], [0, 0, 1], atol=1e-6)
    assert np.isnan(hits.position[1]).all()
