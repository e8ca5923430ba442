"""Procedural spheres: boxes in a BLAS, intersected by a shader in both backends, against the
analytic answer computed in float64 with numpy; every query kind and tier on scenes with spheres
(the f64 tiers, counts, all hits, contains and distances on the host) against the same."""

import numpy as np
import pytest

import vkray
from oracle import box, in_threads, load_mesh, random_rays

TIERS = ["fast", "refined", "exact", "reference"]
F64_TIERS = ["refined", "exact", "reference"]


def roots(centers, radii, origins, directions):
    """Each ray's line against each sphere, in float64: (discriminant, near root, far root), each
    (rays, spheres); the line misses where the discriminant is negative."""
    f = origins[:, None, :] - centers[None, :, :]
    a = np.sum(directions**2, axis=1)[:, None]
    b = np.sum(f * directions[:, None, :], axis=2)
    c = np.sum(f**2, axis=2) - radii[None, :] ** 2
    disc = b**2 - a * c
    root = np.sqrt(np.maximum(disc, 0))
    return disc, (-b - root) / a, (-b + root) / a


def analytic(centers, radii, origins, directions):
    """Nearest t >= 0 of each ray over all spheres (inf on a miss) and the sphere's index."""
    disc, near, far = roots(centers, radii, origins, directions)
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
    stretched = np.diag([1.0, 2.0, 1.0, 1.0])
    ellipsoid = any_device.scene(vkray.Instance(spheres, stretched))
    for query in (ellipsoid.distance, ellipsoid.closest_points, ellipsoid.signed_distance):
        with pytest.raises(vkray.UnsupportedError, match="keep them round"):
            query([[0, 0, 5]])
    # Positions of sphere hits: origin + t * direction.
    hits = scene.intersect([[0, 0, 5], [0, 3, 5]], [0, 0, -1], outputs=["t", "position"])
    np.testing.assert_allclose(hits.position[0], [0, 0, 1], atol=1e-6)
    assert np.isnan(hits.position[1]).all()


# ---------------------------------------------------------------------------------------------
# Every query kind and tier


def all_roots(centers, radii, origins, directions, tmin=0.0):
    """Each ray's crossings of the spheres at t >= tmin (entry and exit, a tangent twice), sorted:
    (t, sphere) lists per ray, in float64."""
    disc, near, far = roots(centers, radii, origins, directions)
    out = []
    for i in range(len(origins)):
        hits = [(t, k) for k in np.flatnonzero(disc[i] >= 0) for t in (near[i, k], far[i, k]) if t >= tmin]
        out.append(sorted(hits))
    return out


def placed_spheres(device, seed, n=60, transform=None):
    """`n` overlapping spheres, placed by `transform` (a rotation, a mirror, a scale of 1.5 and a
    shift by default), and their centres and radii in the world."""
    rng = np.random.default_rng(seed)
    centers = rng.uniform(-3, 3, (n, 3))
    radii = rng.uniform(0.3, 1.2, n)
    if transform is None:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        transform = np.eye(4)
        transform[:3, :3] = 1.5 * q @ np.diag([1.0, 1.0, -1.0])
        transform[:3, 3] = [0.5, -1.0, 2.0]
    world = centers @ transform[:3, :3].T + transform[:3, 3]
    scale = np.cbrt(abs(np.linalg.det(transform[:3, :3])))
    scene = device.scene(vkray.Instance(device.spheres(centers, radii), transform))
    return scene, world, radii * scale


def test_every_tier_of_closest_hits_matches_the_analytic_answer(device):
    """Closest hits and occlusion of spheres placed by a mirroring, scaling, rotating instance:
    the f64 tiers (the host's tracer on either engine) to f64's rounding, the fast tier to
    f32's; the exact and reference tiers equal bit for bit; origins inside spheres hit where
    they leave."""
    scene, centers, radii = placed_spheres(device, 71)
    rng = np.random.default_rng(72)
    origins = rng.uniform(-6, 6, (3000, 3))
    directions = rng.normal(size=(3000, 3))
    t, index = analytic(centers, radii, origins, directions)
    fields = ["t", "prim_id", "instance_id", "uv", "normal", "position"]
    answers = {p: scene.intersect(origins, directions, precision=p, outputs=fields) for p in TIERS}
    for precision, hits in answers.items():
        np.testing.assert_array_equal(hits.hit, np.isfinite(t), err_msg=precision)
        hit = hits.hit
        assert (hits.prim_id[hit] == index[hit]).mean() > 0.999, precision
        rtol = 1e-12 if precision != "fast" else 1e-5
        np.testing.assert_allclose(hits.t[hit], t[hit], rtol=rtol, atol=rtol * 10)
        points = origins[hit] + t[hit, None] * directions[hit]
        np.testing.assert_allclose(hits.position[hit], points, atol=rtol * 100)
        same = hits.prim_id == index
        normal = (points - centers[index[hit]]) / radii[index[hit], None]
        np.testing.assert_allclose(hits.normal[hit][same[hit]], normal[same[hit]], atol=1e-4)
        assert np.isnan(hits.uv[hit]).all()
        np.testing.assert_array_equal(scene.occluded(origins, directions, precision=precision), hits.hit)
    for field in fields:
        np.testing.assert_array_equal(getattr(answers["exact"], field), getattr(answers["reference"], field))
    inside = (np.linalg.norm(origins[:, None] - centers[None], axis=2) < radii).any(axis=1)
    assert answers["exact"].hit[inside].all() and inside.sum() > 50


def test_counts_and_all_hits_meet_both_crossings(device):
    """Every tier counts and lists each sphere twice (where the ray enters and where it leaves;
    once from inside), the hits in t order, as the analytic roots have them."""
    scene, centers, radii = placed_spheres(device, 73)
    rng = np.random.default_rng(74)
    origins = rng.uniform(-6, 6, (1500, 3))
    directions = rng.normal(size=(1500, 3))
    roots = all_roots(centers, radii, origins, directions)
    expected_counts = np.array([len(r) for r in roots])
    expected_t = np.concatenate([[t for t, _ in r] for r in roots])
    expected_prim = np.concatenate([[k for _, k in r] for r in roots]).astype(np.int32)
    for precision in TIERS:
        if precision != "refined":
            np.testing.assert_array_equal(scene.count(origins, directions, precision=precision), expected_counts)
        hits = scene.intersect_all(origins, directions, precision=precision)
        np.testing.assert_array_equal(np.diff(hits.offsets), expected_counts, err_msg=precision)
        rtol = 1e-12 if precision != "fast" else 1e-5
        np.testing.assert_allclose(hits.t, expected_t, rtol=rtol, atol=rtol * 10)
        assert (hits.prim_id == expected_prim).mean() > 0.999
        assert hits.t.dtype == (np.float32 if precision == "fast" else np.float64)
    assert expected_counts.max() >= 6


def test_contains_is_inside_any_sphere_or_the_box(device):
    """Overlapping spheres beside a closed box: inside any sphere (two overlapping spheres hold
    their common part: crossings' parity alone would say outside) or inside the box, by parity
    and by winding number, in both f64 tiers."""
    scene_spheres, centers, radii = placed_spheres(device, 75)
    v, f = box((4.0, 4.0, 4.0), (7.0, 7.5, 6.0))
    spheres = scene_spheres.instances[0]
    scene = device.scene([spheres, vkray.Instance(device.mesh(v, f))])
    rng = np.random.default_rng(76)
    points = rng.uniform(-6, 8, (20000, 3))
    gap = np.abs(np.linalg.norm(points[:, None] - centers[None], axis=2) - radii)
    points = points[gap.min(axis=1) > 1e-6]
    in_spheres = (np.linalg.norm(points[:, None] - centers[None], axis=2) < radii).any(axis=1)
    in_box = ((points > [4, 4, 4]) & (points < [7, 7.5, 6])).all(axis=1)
    overlapped = ((np.linalg.norm(points[:, None] - centers[None], axis=2) < radii).sum(axis=1) >= 2).sum()
    assert overlapped > 100 and in_box.sum() > 50
    for precision in ("exact", "reference"):
        for method in ("parity", "winding"):
            inside = scene.contains(points, precision=precision, method=method)
            np.testing.assert_array_equal(inside, in_spheres | in_box, err_msg=f"{precision} {method}")


def test_distances_to_spheres_in_every_tier(device):
    """Distances, closest points and signed distances of points to spheres (placed by a mirroring
    rotation and a scale): | |p - c| - r | at its least, the point on the sphere towards p,
    negative inside."""
    scene, centers, radii = placed_spheres(device, 77)
    rng = np.random.default_rng(78)
    points = rng.uniform(-7, 7, (4000, 3))
    gaps = np.abs(np.linalg.norm(points[:, None] - centers[None], axis=2) - radii)
    nearest = gaps.argmin(axis=1)
    expected = gaps.min(axis=1)
    inside = (np.linalg.norm(points[:, None] - centers[None], axis=2) < radii).any(axis=1)
    for precision in ("fast", "exact", "reference"):
        rtol = 1e-12 if precision != "fast" else 1e-6
        distance = scene.distance(points, precision=precision)
        np.testing.assert_allclose(distance, expected, rtol=rtol, atol=rtol)
        found = scene.closest_points(points, precision=precision)
        assert (found.prim_id == nearest).mean() > 0.999
        away = points - centers[nearest]
        on_sphere = centers[nearest] + away * (radii[nearest] / np.linalg.norm(away, axis=1))[:, None]
        np.testing.assert_allclose(found.position, on_sphere, atol=10 * rtol)
        signed = scene.signed_distance(points, precision=precision)
        np.testing.assert_allclose(signed, np.where(inside, -expected, expected), rtol=rtol, atol=rtol)


def test_transmittance_through_spheres_and_a_veil(device):
    """Opaque spheres keep no light; a veil of opacity 0.25 keeps 0.75 of it, in every tier."""
    rng = np.random.default_rng(79)
    veil = device.mesh(np.array([[-10, -10, 8.0], [10, -10, 8.0], [10, 10, 8.0], [-10, 10, 8.0]]),
                       np.array([[0, 1, 2], [0, 2, 3]]), opacity=0.25)
    scene_spheres, centers, radii = placed_spheres(device, 80)
    scene = device.scene([scene_spheres.instances[0], vkray.Instance(veil)])
    origins = np.column_stack([rng.uniform(-5, 5, (3000, 2)), np.full(3000, -8.0)])
    directions = np.tile([0.0, 0.0, 1.0], (3000, 1))
    t, _ = analytic(centers, radii, origins, directions)
    expected = np.where(np.isfinite(t), 0.0, 0.75)
    for precision in TIERS:
        kept = scene.transmittance(origins, directions, precision=precision)
        np.testing.assert_allclose(kept, expected, rtol=1e-6, err_msg=precision)
    assert 200 < np.isfinite(t).sum() < 2800


def test_sphere_queries_from_several_threads(device):
    """Counts, contains, distances and exact hits on one scene of spheres from four threads at
    once: each thread's answers are the single-threaded ones."""
    scene, centers, radii = placed_spheres(device, 81)
    rng = np.random.default_rng(82)
    origins = rng.uniform(-6, 6, (2000, 3))
    directions = rng.normal(size=(2000, 3))

    def answers(_):
        return (scene.count(origins, directions, precision="exact"), scene.contains(origins),
                scene.distance(origins), scene.intersect(origins, directions, precision="exact").t)

    alone = answers(0)
    for together in in_threads(4, answers):
        for a, b in zip(together, alone):
            np.testing.assert_array_equal(a, b)
