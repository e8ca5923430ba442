"""Precision tiers and the hard cases of ray casting. Every case states the correct answer and why;
the f64 tiers ("exact" on the GPU, "reference" on the CPU) must give it, the f32 tiers where noted.
"""

import numpy as np
import pytest

import vkray
from oracle import heightfield, load_mesh, random_rays, rays_through, shared_targets

_exact_support = {}


def tiers(device):
    """The tiers this device answers: "exact" needs shaderFloat64 and, in the pipeline backend, a
    driver that runs intersection shaders (vkray probes it and raises UnsupportedError if not)."""
    if device.backend not in _exact_support:
        scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
        try:
            scene.intersect([0.2, 0.2, 1.0], [0, 0, -1], precision="exact")
            _exact_support[device.backend] = True
        except vkray.UnsupportedError:
            _exact_support[device.backend] = False
    return [p for p in vkray.PRECISIONS if p != "exact" or _exact_support[device.backend]]


F64_TIERS = ("exact", "reference")


def test_pipeline_exact_is_answered_or_refused_clearly(device):
    scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    if "exact" in tiers(device):
        assert scene.intersect([0.2, 0.2, 1.0], [0, 0, -1], precision="exact").prim_id == 0
    else:
        with pytest.raises(vkray.UnsupportedError, match="precision='reference'"):
            scene.intersect([0.2, 0.2, 1.0], [0, 0, -1], precision="exact")
    with pytest.raises(ValueError, match="precision must be"):
        scene.intersect([0.2, 0.2, 1.0], [0, 0, -1], precision="double")


@pytest.mark.parametrize("name", ["stanford-bunny", "fandisk"])
def test_tiers_agree_with_the_reference_on_real_meshes(device, name):
    """Far from the origin (1e5), so that f32 would show its limits without re-centring."""
    v, f = load_mesh(name)
    v = v + 1e5
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 20000, seed=21)
    ref = scene.intersect(origins, directions, precision="reference", outputs=vkray.HIT_FIELDS)
    assert ref.precision == "reference" and ref.t.dtype == np.float64 and ref.position.dtype == np.float64
    for tier in tiers(device):
        hits = scene.intersect(origins, directions, precision=tier, outputs=vkray.HIT_FIELDS)
        assert hits.precision == tier
        assert hits.t.dtype == (np.float32 if tier == "fast" else np.float64)
        np.testing.assert_array_equal(hits.hit, ref.hit)
        same = hits.prim_id == ref.prim_id
        if tier in F64_TIERS:
            assert same.all()
            np.testing.assert_allclose(hits.t, ref.t, rtol=1e-12)
            np.testing.assert_allclose(hits.uv[ref.hit], ref.uv[ref.hit], atol=1e-9)
        else:
            # f32 traversal may pick the neighbour at an edge (a handful of rays).
            assert same.mean() > 0.999
            both = same & ref.hit
            rtol = 1e-5 if tier == "fast" else 1e-12  # grazing rays: a few f32 ulps of the scene
            np.testing.assert_allclose(hits.t[both], ref.t[both], rtol=rtol)
        hit = same & ref.hit
        np.testing.assert_allclose(hits.position[hit], ref.position[hit], rtol=0, atol=1e-9 if tier != "fast" else 0.02)
        # f32 normals of the bunny's smallest triangles lose a few digits to cancellation.
        np.testing.assert_allclose(hits.normal[hit], ref.normal[hit], atol=1e-4 if tier == "fast" else 1e-6)
        np.testing.assert_array_equal(scene.occluded(origins, directions, precision=tier), ref.hit)


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e5, 1e7])
def test_shared_edges_and_vertices_report_exactly_one_triangle(device, offset):
    """Rays through the vertices and edges that triangles of a random heightfield share. Correct
    answer: exactly one triangle per ray (the surface is closed there: no gap, no overlap), at
    t = 1 up to the rounding of the ray itself (its f64 origin and direction pass through the
    target within a few ulps of the offset). Each ray is traced against 18 scenes, each holding
    triangles that share no vertex, so that a ray reported by two triangles shows up as hits in
    two scenes."""
    n = 10
    v, f, color = heightfield(n, seed=3, offset=offset)
    targets = shared_targets(v, f, n)
    origins, directions = rays_through(targets, seed=4)
    scenes = [device.scene(device.mesh(v, f[color == c])) for c in range(18)]
    scale = 1.0  # the heightfield's cells are unit squares
    length = np.linalg.norm(directions, axis=1)
    ray_rounding = 8 * np.spacing(max(offset, 1.0)) / length
    reference = None
    for tier in sorted(tiers(device), key=lambda t: t != "reference"):
        counts = np.zeros(len(targets), int)
        for scene in scenes:
            hits = scene.intersect(origins, directions, precision=tier, outputs=["t"])
            counts += np.abs(hits.t - 1.0) * np.linalg.norm(directions, axis=1) < 1e-3 * scale
        whole = device.scene(device.mesh(v, f)).intersect(origins, directions, precision=tier, outputs=["t"])
        if tier in F64_TIERS:
            assert (counts == 1).all(), f"{tier}: {np.sum(counts == 0)} misses, {np.sum(counts > 1)} double counts"
            assert (np.abs(whole.t - 1.0) <= 1e-9 * scale + ray_rounding).all(), tier
            if reference is None:
                reference = whole.t
            # The two f64 tiers agree to 1e-9 of the scene, whatever the offset.
            assert np.abs(whole.t - reference).max() * length.max() <= 1e-9 * scale, tier
        else:
            # f32 traversal: recorded by examples/accuracy_vs_time.py, not promised.
            assert (counts >= 1).mean() > 0.95


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e5, 1e7])
def test_closed_fans_report_exactly_one_triangle(device, offset):
    """A closed fan of 11 triangles with irregular angles around a raised centre vertex: rays
    through the centre and through every spoke's midpoint, from random directions above. Correct
    answer: exactly one triangle each (the fan covers the centre's neighbourhood once). Each
    triangle is its own scene, so that a double count shows as hits in two scenes."""
    rng = np.random.default_rng(12)
    angles = 2 * np.pi * np.arange(11) / 11 + rng.uniform(-0.2, 0.2, 11)  # no gap of half a turn
    ring = np.column_stack([np.cos(angles), np.sin(angles), rng.uniform(-0.2, 0.2, 11)])
    v = np.vstack([[0.0, 0.0, 0.3], ring]) + offset
    f = np.array([[0, 1 + k, 1 + (k + 1) % 11] for k in range(11)])
    targets = np.vstack([v[0], 0.5 * (v[0] + v[1:])])
    targets = np.repeat(targets, 20, axis=0)
    origins, directions = rays_through(targets, seed=13)
    length = np.linalg.norm(directions, axis=1)
    scenes = [device.scene(device.mesh(v, f[k : k + 1])) for k in range(11)]
    for tier in tiers(device):
        counts = np.zeros(len(targets), int)
        for scene in scenes:
            t = scene.intersect(origins, directions, precision=tier, outputs=["t"]).t
            counts += np.abs(t - 1.0) * length < 1e-3
        if tier in F64_TIERS:
            assert (counts == 1).all(), f"{tier}: {np.sum(counts == 0)} misses, {np.sum(counts > 1)} double counts"
        else:
            assert (counts >= 1).mean() > 0.9, tier


def test_rays_in_a_triangles_plane_do_not_hit(device):
    """A ray inside the triangle's plane meets it in a segment, not a point: a zero-area
    projection, so no hit (Vulkan's and the watertight test's definition)."""
    scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    origins = np.array([[-1.0, 0.25, 0.0], [0.25, -1.0, 0.0], [-1.0, -1.0, 0.0]])
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    for tier in tiers(device):
        assert not scene.intersect(origins, directions, precision=tier).hit.any(), tier


def test_grazing_rays_on_slivers_agree_with_the_reference(device):
    """A sliver 1000 times longer than wide, hit by rays 1e-3 rad from its plane: the f64 tiers
    agree with each other exactly; the f32 tiers find the same triangle for all but a few."""
    rng = np.random.default_rng(5)
    n = 200
    x = np.repeat(np.arange(n, dtype=float), 2)
    y = np.tile([0.0, 1e-3], n)
    v = np.column_stack([x, y, np.zeros(2 * n)])
    f = np.array(
        [[2 * i, 2 * i + 2, 2 * i + 3] for i in range(n - 1)] + [[2 * i, 2 * i + 3, 2 * i + 1] for i in range(n - 1)]
    )
    scene = device.scene(device.mesh(v, f))
    targets = np.column_stack([rng.uniform(1, n - 2, 5000), rng.uniform(0, 1e-3, 5000), np.zeros(5000)])
    directions = np.column_stack([np.ones(5000), rng.uniform(-1e-3, 1e-3, 5000), -np.full(5000, 1e-3)])
    origins = targets - directions * 10
    ref = scene.intersect(origins, directions, precision="reference")
    assert ref.hit.mean() > 0.99
    for tier in tiers(device):
        hits = scene.intersect(origins, directions, precision=tier)
        agree = (hits.prim_id == ref.prim_id).mean()
        assert agree == 1.0 if tier in F64_TIERS else agree > 0.95, (tier, agree)


def test_degenerate_triangles_are_never_hit_and_keep_ids(device):
    """Zero-area triangles (a repeated index, collinear corners) have no inside: never hit, even
    by a ray through the very edge they lie on. The square's two triangles keep their own rows."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0]], float)
    f = np.array([[0, 0, 1], [0, 1, 2], [0, 4, 2], [0, 2, 3], [2, 2, 2]])
    scene = device.scene(device.mesh(v, f))
    origins = np.array([[0.7, 0.2, 1], [0.2, 0.7, 1], [0.5, 0.5, 1], [0.25, 0.25, 1]], float)
    for tier in tiers(device):
        hits = scene.intersect(origins, [0, 0, -1], precision=tier)
        assert hits.prim_id[:2].tolist() == [1, 3], tier
        # On the shared diagonal (where the collinear row 2 lies): one of the square's halves.
        assert np.isin(hits.prim_id[2:], [1, 3]).all(), tier


def test_hits_exactly_at_tmin_and_tmax(device):
    """The triangle is at t = 1 exactly. Every tier's interval is closed: tmax = 1 and tmin = 1
    both include it. The f64 tiers exclude it one f64 ulp either side. The fast tier widens the
    interval by one f32 ulp at each end (traversal compares in f32, and lavapipe missed t = 1 at
    tmax = 1 before), so it excludes the hit a little further out; "refined" checks its f64 t
    against the exact bounds, like the f64 tiers."""
    scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    o, d = [0.25, 0.25, 1.0], [0.0, 0.0, -1.0]
    for tier in tiers(device):
        if tier == "fast":
            below, above = 1.0 - 1e-6, 1.0 + 1e-6
        else:
            below, above = float(np.nextafter(1.0, 0.0)), float(np.nextafter(1.0, 2.0))
        assert scene.intersect(o, d, tmax=1.0, precision=tier).hit, tier
        assert scene.intersect(o, d, tmin=1.0, precision=tier).hit, tier
        assert scene.occluded(o, d, tmax=1.0, precision=tier), tier
        assert not scene.intersect(o, d, tmax=below, precision=tier).hit, tier
        assert not scene.intersect(o, d, tmin=above, precision=tier).hit, tier


def test_rays_starting_on_a_surface(device):
    """An origin on the triangle meets it at t = 0: a hit when tmin = 0 (closed interval) in the
    f64 tiers; f32 traversal may put that t an ulp below 0 and miss it (not promised). None once
    tmin > 0, or once the origin is moved off by `offset_origins`, in every tier."""
    scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    o = np.array([[0.25, 0.25, 0.0]])
    for tier in tiers(device):
        hits = scene.intersect(o, [0, 0, 1], precision=tier)
        if tier in F64_TIERS:
            assert hits.hit.all() and hits.t[0] == 0, tier
        assert not scene.intersect(o, [0, 0, 1], tmin=1e-3, precision=tier).hit.any(), tier
        moved = vkray.offset_origins(o, [[0, 0, 1]], [[0, 0, 1]], precision=tier)
        assert not scene.intersect(moved, [0, 0, 1], precision=tier).hit.any(), tier


@pytest.mark.parametrize("size", [1e-6, 1.0, 1e4])
def test_tiny_and_huge_triangles(device, size):
    """Rays through the centroids of triangles of side `size` (stacked 3 sizes apart), starting
    one size below each with a direction one size long: the triangle's own index, at t = 1."""
    rng = np.random.default_rng(6)
    corners = rng.uniform(0, 1, (50, 3, 2)) * size
    v = np.concatenate([corners, np.zeros((50, 3, 1))], axis=2).reshape(-1, 3)
    v[:, 2] = np.repeat(np.arange(50) * 3 * size, 3)  # one triangle per layer, no overlap in t
    f = np.arange(150).reshape(50, 3)
    scene = device.scene(device.mesh(v, f))
    centroids = v.reshape(50, 3, 3).mean(axis=1)
    origins = centroids - [0, 0, size]
    for tier in tiers(device):
        hits = scene.intersect(origins, [0, 0, size], precision=tier)
        area = np.abs(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])[:, 2])
        fat = area > 1e-3 * size**2  # slivers aside, the centroid is well inside
        assert (hits.prim_id[fat] == np.arange(50)[fat]).all(), tier
        # f32 traversal's t is good to a few ulps of the scene's extent (150 sizes here).
        np.testing.assert_allclose(hits.t[fat], 1.0, rtol=1e-4 if tier == "fast" else 1e-12)


@pytest.mark.parametrize("length", [1e-3, 1.0, 1e3])
def test_direction_lengths_and_odd_components(device, length):
    """t is in units of the direction's length: the same hit at t = 2 / length. Components 0,
    -0.0 and 1e-30 are all valid and must not produce NaN or a wrong side."""
    scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    origins = np.array([[0.25, 0.25, 2.0]] * 3)
    directions = np.array([[0.0, 0.0, -1.0], [-0.0, -0.0, -1.0], [1e-30, -1e-30, -1.0]]) * length
    for tier in tiers(device):
        hits = scene.intersect(origins, directions, precision=tier)
        assert hits.hit.all(), tier
        np.testing.assert_allclose(hits.t, 2.0 / length, rtol=1e-6 if tier == "fast" else 1e-15)


def test_mirrored_instances_flip_facing(device):
    """A mirror reverses the winding, so the geometric normal (right-handed in the winding) flips
    with it: the same triangle seen through x -> -x has normal -z instead of +z."""
    mesh = device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    scene = device.scene([vkray.Instance(mesh), vkray.Instance(mesh, mirror)])
    for tier in tiers(device):
        hits = scene.intersect([[0.2, 0.2, 1], [-0.2, 0.2, 1]], [0, 0, -1], precision=tier)
        assert hits.instance_id.tolist() == [0, 1], tier
        np.testing.assert_allclose(hits.normal, [[0, 0, 1], [0, 0, -1]], atol=1e-6)


def test_instance_translation_equals_baked_vertices(device):
    """Translating an instance by 1e6 and baking 1e6 into the vertices describe the same
    geometry up to the rounding of baking itself (an f64 ulp at 1e6 is 1.2e-10): the same
    triangles, and t and positions equal to 1e-9 in the f64 tiers."""
    v, f = load_mesh("spot")
    shift = np.array([1e6, -1e6, 1e6])
    baked = device.scene(device.mesh(v + shift, f))
    moved = np.eye(4)
    moved[:3, 3] = shift
    placed = device.scene([vkray.Instance(device.mesh(v, f), moved)])
    origins, directions = random_rays(v + shift, 5000, seed=7)
    for tier in tiers(device):
        a = baked.intersect(origins, directions, precision=tier, outputs=["t", "prim_id", "position"])
        b = placed.intersect(origins, directions, precision=tier, outputs=["t", "prim_id", "position"])
        same = a.prim_id == b.prim_id
        assert same.mean() > (0.9999 if tier not in F64_TIERS else 1.0 - 1e-12), tier
        hit = same & a.hit
        np.testing.assert_allclose(a.t[hit], b.t[hit], rtol=1e-6 if tier == "fast" else 1e-9)
        np.testing.assert_allclose(a.position[hit], b.position[hit], rtol=0, atol=0.5 if tier == "fast" else 1e-9)


def test_stacked_near_coincident_layers(device):
    """Two parallel squares 1e-6 apart, far from the origin (1e5): rays from above must hit the
    upper one. f32 without re-centring could not tell them apart at 1e5 (its ulp is 8e-3)."""
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    v = np.concatenate([square, square + [0, 0, 1e-6]]) + 1e5
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    scene = device.scene(device.mesh(v, f))
    rng = np.random.default_rng(8)
    origins = np.column_stack([rng.uniform(0.01, 0.99, (1000, 2)), np.ones(1000)]) + 1e5
    for tier in tiers(device):
        hits = scene.intersect(origins, [0, 0, -1], precision=tier)
        assert np.isin(hits.prim_id, [2, 3]).all(), tier


@pytest.mark.parametrize("offset", [0.0, 1e5])
@pytest.mark.parametrize("surface", ["bunny", "plane"])
def test_secondary_rays_never_hit_their_own_surface(device, offset, surface):
    """Shadow and bounce rays leaving a surface from `offset_origins` must not hit the triangle
    they leave (a flat triangle cannot be met again by a ray leaving it): zero self-hits."""
    if surface == "bunny":
        v, f = load_mesh("stanford-bunny")
    else:  # an axis-aligned plane, the classic failure case
        g = np.linspace(-1, 1, 21)
        x, y = np.meshgrid(g, g)
        v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
        at = lambda i, j: j * 21 + i  # noqa: E731
        f = np.array([[at(i, j), at(i + 1, j), at(i + 1, j + 1)] for j in range(20) for i in range(20)]
                     + [[at(i, j), at(i + 1, j + 1), at(i, j + 1)] for j in range(20) for i in range(20)])
    v = v + offset
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 20000, seed=9)
    rng = np.random.default_rng(10)
    for tier in tiers(device):
        first = scene.intersect(origins, directions, precision=tier, outputs=["prim_id", "normal", "position"])
        hit = first.hit
        bounce = rng.normal(size=(int(hit.sum()), 3))
        for towards in (bounce, -bounce):  # both sides: reflection and transmission
            start = vkray.offset_origins(first.position[hit], first.normal[hit], towards, precision=tier)
            second = scene.intersect(start, towards, precision=tier, outputs=["prim_id"])
            self_hits = int(np.sum(second.prim_id == first.prim_id[hit]))
            assert self_hits == 0, f"{tier}: {self_hits} self-hits"
