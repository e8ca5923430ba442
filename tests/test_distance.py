"""How far to the surface: `Scene.closest_points`, `distance` and `signed_distance`, against a
brute-force numpy oracle (every point against every triangle) and numpy's own geometry."""

import threading

import numpy as np
import pytest

import oracle
import vkray


@pytest.fixture(scope="module")
def bunny():
    return oracle.load_mesh("stanford-bunny")


def points_around(vertices, n, seed, spread=0.3):
    """Points in the mesh's bounding box grown by `spread` of its size, a few far away."""
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(0), vertices.max(0)
    pad = spread * (hi - lo)
    points = rng.uniform(lo - pad, hi + pad, (n, 3))
    points[: n // 20] *= 40.0
    return points


def world_triangles(vertices, faces, transform=None):
    tri = vertices[faces]
    return tri if transform is None else tri @ transform[:3, :3].T + transform[:3, 3]


def check_tiers_in_threads(query, tiers=("reference", "exact"), threads=4):
    """`query(tier)` for each tier in several threads at once gives each tier's answer alone."""
    want = {tier: query(tier) for tier in tiers}
    results, errors = [], []

    def work():
        try:
            for tier in tiers:
                results.append((tier, query(tier)))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    started = [threading.Thread(target=work) for _ in range(threads)]
    for t in started:
        t.start()
    for t in started:
        t.join()
    assert not errors and len(results) == threads * len(tiers)
    for tier, got in results:
        np.testing.assert_array_equal(got, want[tier])


def check_refuses_bad_points(query):
    """A point query refuses, with a ValueError naming the fault: a point not finite, a negative
    max_distance, and points not shaped (..., 3)."""
    with pytest.raises(ValueError, match="not finite"):
        query([[0.0, np.nan, 0.0]])
    with pytest.raises(ValueError, match="max_distance"):
        query([[0.0, 0.0, 0.0]], max_distance=-1.0)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        query(np.zeros((4, 2)))


def check_against_brute_force(found, points, tri):
    """distance equals the brute-force minimum; position lies on the reported triangle at that
    distance, at the reported barycentrics."""
    v = tri.reshape(-1, 3)
    f = np.arange(len(v)).reshape(-1, 3)
    expected = oracle.surface_distance(v, f, points)
    scale = np.abs(tri).max()
    np.testing.assert_allclose(found.distance, expected, rtol=1e-12, atol=1e-14 * scale)
    np.testing.assert_allclose(
        np.linalg.norm(found.position - points, axis=1), found.distance, rtol=1e-12, atol=1e-14 * scale
    )
    a, b, c = (tri[found.prim_id, k] for k in range(3))
    u, w = found.uv[:, :1], found.uv[:, 1:]
    np.testing.assert_allclose((1 - u - w) * a + u * b + w * c, found.position, atol=1e-12 * scale)
    assert ((found.uv >= -1e-12) & (found.uv.sum(axis=1, keepdims=True) <= 1 + 1e-12)).all()


TIERS = ("exact", "reference")


@pytest.mark.parametrize("precision", TIERS)
def test_closest_points_match_brute_force_on_the_bunny(device, bunny, precision):
    v, f = bunny
    scene = device.scene([device.mesh(v, f)])
    near = v[::350][:50] + 1e-3 * np.random.default_rng(9).normal(size=(50, 3))
    points = np.vstack([points_around(v, 150, seed=0), near])
    found = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS, precision=precision)
    assert found.distance.dtype == np.float64 and found.position.shape == (len(points), 3)
    check_against_brute_force(found, points, v[f])
    assert (found.instance_id == 0).all() and (found.geometry_id == 0).all()
    normals = oracle.triangle_normals(v, f, found.prim_id)
    np.testing.assert_allclose(found.normal, normals, atol=1e-6)
    np.testing.assert_array_equal(scene.distance(points, precision=precision), found.distance)
    if precision == "exact":
        # The GPU's f64 search and the CPU's compute the same operations in the same order: the
        # same answers to f64 rounding (bit for bit on lavapipe; NVIDIA's f64 division and square
        # root round otherwise), the same triangles but for near-ties.
        reference = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS, precision="reference")
        np.testing.assert_allclose(found.distance, reference.distance, rtol=1e-12, atol=1e-18)
        assert np.mean(found.prim_id == reference.prim_id) > 0.98


@pytest.mark.parametrize("precision", TIERS)
def test_random_triangle_soups_match_brute_force(device, precision):
    """Random triangles of random sizes crossing each other freely, points inside and around."""
    for seed in (11, 12):
        v, f = oracle.triangle_soup(300, seed)
        scene = device.scene([device.mesh(v, f)])
        points = np.random.default_rng(seed).uniform(-0.5, 1.5, (400, 3))
        found = scene.closest_points(points, precision=precision)
        check_against_brute_force(found, points, v[f])


@pytest.mark.parametrize("precision", TIERS)
def test_points_on_the_surface_are_at_distance_zero_with_one_triangle_chosen(device, precision):
    """Vertices and edge midpoints of a heightfield lie on several triangles: distance 0 (to f64
    rounding of an edge's midpoint) on one of them; at a vertex, every triangle that has it is at
    exactly 0, and the lowest-numbered wins (the tie-break every tier shares)."""
    vertices, faces, _ = oracle.heightfield(8, seed=1)
    scene = device.scene([device.mesh(vertices, faces)])
    targets = oracle.shared_targets(vertices, faces, 8)
    found = scene.closest_points(targets, precision=precision)
    assert (found.distance <= 1e-15).all()
    per_triangle = np.stack([oracle.surface_distance(vertices, faces[k : k + 1], targets) for k in range(len(faces))])
    holders = per_triangle <= 1e-15
    assert (holders.sum(axis=0) >= 2).all()  # every target is shared
    assert holders[found.prim_id, np.arange(len(targets))].all()
    vertex = np.arange(len(targets)) < 36  # shared_targets lists the 6x6 inner vertices first
    np.testing.assert_array_equal(found.prim_id[vertex], holders.argmax(axis=0)[vertex])


@pytest.mark.parametrize("precision", TIERS)
@pytest.mark.parametrize("offset", [0.0, 1e6])
def test_instances_rotated_stretched_and_mirrored_keep_world_distances(device, offset, precision):
    v, f = oracle.load_mesh("spot")
    v = 0.1 * (v - v.mean(0))
    mesh = device.mesh(v, f)
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1.0]])
    transforms = [
        np.eye(4),
        np.block([[rotation @ np.diag([3.0, 0.5, 1.0]), np.array([[0.4], [0.0], [0.1]])], [np.zeros((1, 3)), 1.0]]),
        np.block([[np.diag([1.0, -1.0, 2.0]), np.array([[-0.4], [0.2], [0.0]])], [np.zeros((1, 3)), 1.0]]),
    ]
    for t in transforms:
        t[:3, 3] += offset
    scene = device.scene([vkray.Instance(mesh, t) for t in transforms])
    points = points_around(np.vstack([world_triangles(v, f, t).reshape(-1, 3) for t in transforms]), 500, seed=2)
    found = scene.closest_points(points, precision=precision)
    tri = np.concatenate([world_triangles(v, f, t) for t in transforms])
    v_all = tri.reshape(-1, 3)
    expected = oracle.surface_distance(v_all, np.arange(len(v_all)).reshape(-1, 3), points)
    scale = np.abs(tri).max()
    np.testing.assert_allclose(found.distance, expected, rtol=1e-11, atol=1e-13 * scale)
    instance_tri = np.stack([world_triangles(v, f, t) for t in transforms])
    a, b, c = (instance_tri[found.instance_id, found.prim_id, k] for k in range(3))
    u, w = found.uv[:, :1], found.uv[:, 1:]
    np.testing.assert_allclose((1 - u - w) * a + u * b + w * c, found.position, atol=1e-11 * scale)


@pytest.mark.parametrize("precision", TIERS)
def test_max_distance_cuts_off_with_misses(device, bunny, precision):
    v, f = bunny
    scene = device.scene([device.mesh(v, f)])
    points = points_around(v, 500, seed=3)
    full = scene.closest_points(points, precision=precision)
    limit = float(np.median(full.distance))
    cut = scene.closest_points(points, max_distance=limit, outputs=vkray.CLOSEST_FIELDS, precision=precision)
    near = full.distance <= limit
    np.testing.assert_array_equal(cut.distance[near], full.distance[near])
    assert np.isinf(cut.distance[~near]).all() and (cut.prim_id[~near] == -1).all()
    assert (cut.instance_id[~near] == -1).all() and np.isnan(cut.position[~near]).all()
    assert np.isnan(cut.uv[~near]).all() and np.isnan(cut.normal[~near]).all()
    np.testing.assert_array_equal(cut.hit, near)
    assert scene.closest_points(points, max_distance=0.0, precision=precision).hit.sum() == 0


def test_signed_distance_is_negative_inside(any_device, bunny):
    """Closed meshes take their sign from the exact parity; open ones from the winding number."""
    box_v, box_f = oracle.box((0, 0, 0), (1, 2, 3))
    closed = any_device.scene([any_device.mesh(box_v, box_f)])
    points = np.random.default_rng(4).uniform(-1, 4, (2000, 3))
    inside = (points >= 0).all(1) & (points <= [1, 2, 3]).all(1)
    outside_gap = np.linalg.norm(np.maximum(0, np.maximum(-points, points - [1, 2, 3])), axis=1)
    inside_gap = np.min(np.concatenate([points, [1, 2, 3] - points], axis=1), axis=1)
    expected = np.where(inside, -inside_gap, outside_gap)
    np.testing.assert_allclose(closed.signed_distance(points), expected, atol=1e-14)
    v, f = bunny
    open_scene = any_device.scene([any_device.mesh(v, f)])
    probe = points_around(v, 300, seed=5, spread=0.05)
    winding = oracle.winding_numbers(v, f, probe)
    signed = open_scene.signed_distance(probe)
    clear = np.abs(winding - 0.5) > 0.1
    np.testing.assert_array_equal(signed[clear] < 0, winding[clear] > 0.5)
    with pytest.raises(ValueError, match="winding"):
        open_scene.signed_distance(probe, method="parity")
    # Batches of any shape; the fast tier in float32; beyond max_distance, +-inf by the side.
    whole = closed.signed_distance(points, precision="exact")
    np.testing.assert_array_equal(closed.signed_distance(points.reshape(10, 200, 3)), whole.reshape(10, 200))
    fast = closed.signed_distance(points, precision="fast")
    assert fast.dtype == np.float32
    np.testing.assert_allclose(fast, expected, atol=1e-6)
    cut = closed.signed_distance(points, max_distance=0.25)
    far = np.abs(expected) > 0.25 + 1e-9
    assert far.sum() > 100 and np.isinf(cut[far]).all()
    np.testing.assert_array_equal(np.sign(cut[far]), np.sign(expected[far]))
    np.testing.assert_array_equal(cut[~far], whole[~far])
    # Several threads at once, each tier: the same answers.
    check_tiers_in_threads(lambda tier: open_scene.signed_distance(probe, precision=tier))
    check_refuses_bad_points(closed.signed_distance)
    with pytest.raises(ValueError, match="method"):
        closed.signed_distance([[0.0, 0.0, 0.0]], method="vote")


def test_the_fast_tier_is_the_nearest_to_float32_rounding(device, bunny):
    v, f = bunny
    scene = device.scene([device.mesh(v, f)])
    near = v[::200] + 1e-3 * np.random.default_rng(13).normal(size=(len(v[::200]), 3))
    points = np.vstack([points_around(v, 300, seed=14), near])
    fast = scene.closest_points(points, precision="fast", outputs=vkray.CLOSEST_FIELDS)
    exact = scene.closest_points(points, precision="exact", outputs=vkray.CLOSEST_FIELDS)
    assert fast.distance.dtype == np.float32 and fast.uv.dtype == np.float32
    scale = float(np.abs(v).max())
    np.testing.assert_allclose(fast.distance, exact.distance, rtol=1e-5, atol=1e-6 * scale)
    same = fast.prim_id == exact.prim_id
    assert same.mean() > 0.98
    # Where f32 picks another triangle (a point nearly equidistant from two), its point is as near.
    np.testing.assert_allclose(fast.position[same], exact.position[same], atol=1e-5 * scale)
    reached = np.linalg.norm(fast.position.astype(np.float64) - points, axis=1)
    np.testing.assert_allclose(reached, exact.distance, rtol=1e-5, atol=1e-6 * scale)


def test_shapes_threads_and_bad_input(any_device, bunny):
    v, f = bunny
    scene = any_device.scene([any_device.mesh(v, f)])
    grid = points_around(v, 24, seed=6).reshape(2, 3, 4, 3)
    found = scene.closest_points(grid, outputs=["distance", "uv"])
    assert found.distance.shape == (2, 3, 4) and found.uv.shape == (2, 3, 4, 2) and found.position is None
    assert scene.closest_points(np.zeros((0, 3))).distance.shape == (0,)
    points = points_around(v, 3000, seed=7)
    check_tiers_in_threads(lambda tier: scene.distance(points, precision=tier))
    check_refuses_bad_points(scene.closest_points)
    with pytest.raises(ValueError, match="max_distance"):
        scene.closest_points([[0.0, 0.0, 0.0]], max_distance=np.nan)
    with pytest.raises(ValueError, match="unknown fields"):
        scene.closest_points([[0.0, 0.0, 0.0]], outputs=["t"])
    spheres = any_device.scene([any_device.spheres([[0, 0, 0]], 1.0)])
    ball = spheres.closest_points([[0.0, 0.0, 5.0]])
    assert ball.distance[0] == 4.0 and ball.position[0].tolist() == [0.0, 0.0, 1.0]
    with pytest.raises(vkray.UnsupportedError, match="'refined' would be 'exact'"):
        scene.closest_points([[0.0, 0.0, 0.0]], precision="refined")


def test_winding_numbers_on_the_gpu_decide_as_the_cpu(device, bunny):
    """contains(method="winding") at "exact" (winding numbers on the GPU, f64 terms and f32
    arctangents, points near 1/2 and points on a surface decided on the CPU) equals "reference"
    (the CPU, f64) and the numpy oracle, for an open mesh under rotated, stretched and mirrored
    instances; several threads at once give the same answers."""
    v, f = bunny
    mesh = device.mesh(v, f)
    rotate = np.eye(4)
    c, s = np.cos(0.7), np.sin(0.7)
    rotate[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    rotate[:3, 3] = [0.3, 0.0, 0.0]
    mirror = np.diag([-1.5, 1.0, 0.8, 1.0])
    mirror[:3, 3] = [-0.3, 0.05, 0.0]
    scene = device.scene([mesh, vkray.Instance(mesh, rotate), vkray.Instance(mesh, mirror)])
    rng = np.random.default_rng(21)
    tri = v[f[rng.integers(0, len(f), 300)]]
    on_surface = tri.mean(axis=1)  # centroids: on the surface
    near = tri[:, 0] + 1e-4 * rng.normal(size=(300, 3))
    lo, hi = v.min(0) - 0.4, v.max(0) + 0.4
    points = np.vstack([rng.uniform(lo, hi, (600, 3)), on_surface, near, v[:50]])
    exact = scene.contains(points, method="winding", precision="exact")
    reference = scene.contains(points, method="winding", precision="reference")
    np.testing.assert_array_equal(exact, reference)
    assert exact[600:900].all()  # on a surface: inside
    world = [v, v @ rotate[:3, :3].T + rotate[:3, 3], v @ mirror[:3, :3].T + mirror[:3, 3]]
    w = np.stack([oracle.winding_numbers(x, f, points[:600]) for x in world])
    w[2] *= -1  # a mirror turns its triangles inside out
    clear = np.abs(w.max(axis=0) - 0.5) > 1e-6
    np.testing.assert_array_equal(exact[:600][clear], (w.max(axis=0) >= 0.5)[clear])
    check_tiers_in_threads(lambda tier: scene.contains(points, method="winding", precision=tier), ("exact",), 4)


def boundary_edges(faces):
    """The directed edges a -> b of the faces that no face runs b -> a (an oriented mesh's holes)."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    forward = {tuple(e) for e in edges.tolist()}
    return np.array([e for e in edges.tolist() if (e[1], e[0]) not in forward])


def boundary_loops(edges):
    """The boundary's edges grouped by connected component (each a hole's loop), as the caps
    group them (geometry/winding.rs `boundary_loops`)."""
    parent = {}

    def root(x):
        while parent.setdefault(x, x) != x:
            x = parent[x]
        return x

    for a, b in edges.tolist():
        parent[root(a)] = root(b)
    groups = {}
    for e in edges.tolist():
        groups.setdefault(root(e[0]), []).append(e)
    return [np.array(g) for g in groups.values()]


def points_on_the_cap(vertices, faces, transform, n, seed):
    """Points where the exact tier's winding query is least sure: on the caps that close the
    mesh's holes (per hole, the fan from the mean of its corners over its boundary edges), on the
    fans' inner edges, on the boundary, and the apexes themselves, placed by `transform`."""
    rng = np.random.default_rng(seed)
    loops = boundary_loops(boundary_edges(faces))
    edges = np.concatenate(loops)
    apexes = np.concatenate([np.repeat(vertices[g[:, 0]].mean(axis=0)[None], len(g), axis=0) for g in loops])
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    k = rng.integers(0, len(edges), n)
    apex = apexes[k]
    s, t = rng.uniform(0, 1, (2, n, 1))
    s, t = np.where(s + t > 1, 1 - s, s), np.where(s + t > 1, 1 - t, t)
    on_fan = apex + s * (a[k] - apex) + t * (b[k] - apex)
    on_spokes = apex + s * (a[k] - apex)
    on_boundary = a[k] + s * (b[k] - a[k])
    local = np.vstack([np.unique(apexes, axis=0), on_fan, on_spokes, on_boundary, a])
    return local @ transform[:3, :3].T + transform[:3, 3]


def open_tube(radius, length, sides, rings=8):
    """A tube along z from 0 to `length` in `rings` rings, open at both ends (two holes of `sides`
    edges each, fewer edges than triangles: the caps' case), faces outward."""
    angle = 2 * np.pi * np.arange(sides) / sides
    circle = np.stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(sides)], axis=1)
    vertices = np.vstack([circle + [0, 0, length * r / rings] for r in range(rings + 1)])
    k = np.arange(sides)
    n = (k + 1) % sides
    faces = []
    for r in range(rings):
        lo, hi = r * sides, (r + 1) * sides
        faces += [np.stack([lo + k, lo + n, hi + n], axis=1), np.stack([lo + k, hi + n, hi + k], axis=1)]
    return vertices, np.concatenate(faces).astype(np.int32)


def test_winding_caps_passed_over_are_summed_near_one_half(device):
    """A ray of the exact winding query passes over a hole's cap that it cannot cross and whose
    winding number is bounded small (far from the point), unless the bound could bring the sum
    within the band about 1/2. Near one end of a long tube open at both, the winding number
    crosses 1/2 a little inside the end's plane, by about the far end's small share (0.0025),
    which a point passing the far cap over would lose: the points there must still be decided
    as the CPU decides them, and as numpy's oracle does where it is clear of 1/2."""
    v, f = open_tube(1.0, 10.0, 24)
    assert len(boundary_loops(boundary_edges(f))) == 2
    scene = device.scene(device.mesh(v, f))
    rng = np.random.default_rng(21)
    n = 4000
    # On and near the axis, from 0.02 outside the top end's plane to 0.02 inside it.
    points = np.stack(
        [rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), 10.0 + rng.uniform(-0.02, 0.02, n)], axis=1
    )
    w = oracle.winding_numbers(v, f, points)
    straddling = (w > 0.5 - 0.0025) & (w < 0.5)
    assert straddling.sum() > 50  # outside, but inside were the far cap passed over
    exact = scene.contains(points, method="winding", precision="exact")
    np.testing.assert_array_equal(exact, scene.contains(points, method="winding", precision="reference"))
    clear = np.abs(w - 0.5) > 1e-6
    np.testing.assert_array_equal(exact[clear], (w >= 0.5)[clear])
    signed = scene.signed_distance(points)
    np.testing.assert_array_equal(signed < 0, exact)  # every point clear of the wall
    check_tiers_in_threads(lambda tier: scene.contains(points, method="winding", precision=tier), ("exact",), 3)


@pytest.mark.parametrize("name", ["open box", "bunny"])
def test_winding_numbers_through_the_cap_decide_as_the_cpu(device, bunny, name):
    """With one instance, contains(method="winding") at "exact" counts one ray's signed crossings
    with the mesh less the cap that closes its holes, on the GPU, and adds the cap's winding
    number. It must equal "reference" (the CPU's winding number over the hierarchy, which knows no
    cap) where the two meet: on the cap, its inner edges and its apex (the box's centre), on the
    holes' edges, on a lattice whose points lie on the cap's planes, under a mirroring stretch and
    far from the origin; and numpy's oracle where the winding number is clear of 1/2. Several
    threads at once give the same answers."""
    if name == "bunny":
        v, f = bunny
    else:
        v, f = oracle.box()
        f = f[~(v[f][:, :, 2] == 1.0).all(axis=1)]  # no lid: a hole of 4 edges
    assert len(boundary_edges(f)) > 0
    transform = np.diag([-1.5, 1.0, 0.5, 1.0])
    transform[:3, 3] = [1e4, -2.0, 0.25]
    scene = device.scene([vkray.Instance(device.mesh(v, f), transform)])
    lo, hi = v.min(0), v.max(0)
    axes = [np.linspace(a - 0.25 * (b - a), b + 0.25 * (b - a), 13) for a, b in zip(lo, hi)]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(8)
    local = np.vstack([lattice, rng.uniform(lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo), (2000, 3))])
    placed = local @ transform[:3, :3].T + transform[:3, 3]
    points = np.vstack([placed, points_on_the_cap(v, f, transform, 300, seed=9)])
    exact = scene.contains(points, method="winding", precision="exact")
    reference = scene.contains(points, method="winding", precision="reference")
    np.testing.assert_array_equal(exact, reference)
    assert 0 < exact.sum() < len(exact)
    # The winding number in the scene's frame, negated: the mirror turns the triangles inside out
    # (numpy's oracle, over every triangle: on some of the points).
    world = v @ transform[:3, :3].T + transform[:3, 3]
    some = rng.choice(len(local), min(len(local), 400), replace=False)
    w = -oracle.winding_numbers(world, f, points[some])
    clear = (np.abs(w - 0.5) > 1e-6) & (oracle.surface_distance(world, f, points[some]) > 1e-9)
    assert clear.mean() > 0.9
    np.testing.assert_array_equal(exact[some][clear], (w >= 0.5)[clear])
    check_tiers_in_threads(lambda tier: scene.contains(points, method="winding", precision=tier), ("exact",), 3)


@pytest.mark.parametrize("name", ["closed box", "open box", "bunny"])
def test_signed_distance_in_one_pass_equals_two_queries(device, bunny, name, monkeypatch):
    """With one instance, signed_distance runs the distance search and the sign's rays (one exact
    ray from each point, read from the search's own points buffer) in one pass of the GPU and
    signs on the host, the rays cast in the search's grid order. It must equal distance and
    contains asked apart (VKRAY_SIGNED_DISTANCE=separate) and itself with the points as they
    come (VKRAY_POINT_ORDER=input) bit for bit at each tier, and take its sign from the
    reference tier's contains: over more than one chunk (262,144 points on a software device), on
    vertices, edges and faces, on the cap over the holes (points the GPU leaves to the CPU), under
    a mirroring stretch far from the origin; and in several threads at once."""
    if name == "bunny":
        v, f = bunny
    else:
        v, f = oracle.box()
        if name == "open box":
            f = f[~(v[f][:, :, 2] == 1.0).all(axis=1)]  # no lid: a hole of 4 edges
    method = "parity" if name == "closed box" else "winding"
    transform = np.diag([-1.5, 1.0, 0.5, 1.0])
    transform[:3, 3] = [1e4, -2.0, 0.25]
    scene = device.scene([vkray.Instance(device.mesh(v, f), transform)])
    lo, hi = v.min(0), v.max(0)
    rng = np.random.default_rng(21)
    tri = v[f]
    on_surface = np.vstack([v, 0.5 * (tri[:, 0] + tri[:, 1]), tri.mean(axis=1)])
    count = 10_000 if name == "bunny" else 270_000
    local = np.vstack([rng.uniform(lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo), (count, 3)), on_surface])
    points = local @ transform[:3, :3].T + transform[:3, 3]
    if method == "winding":
        points = np.vstack([points, points_on_the_cap(v, f, transform, 300, seed=22)])
    exact = scene.signed_distance(points, precision="exact")
    fast = scene.signed_distance(points, precision="fast")
    monkeypatch.setenv("VKRAY_SIGNED_DISTANCE", "separate")
    np.testing.assert_array_equal(exact, scene.signed_distance(points, precision="exact"))
    np.testing.assert_array_equal(fast, scene.signed_distance(points, precision="fast"))
    monkeypatch.delenv("VKRAY_SIGNED_DISTANCE")
    # The sign's rays cast as the points come, not in the search's grid order: the same rows.
    monkeypatch.setenv("VKRAY_POINT_ORDER", "input")
    np.testing.assert_array_equal(exact, scene.signed_distance(points, precision="exact"))
    monkeypatch.delenv("VKRAY_POINT_ORDER")
    np.testing.assert_array_equal(np.abs(exact), scene.distance(points, precision="exact"))
    # The sign is contains' (-0.0 on the surface, which is inside): checked on every point near
    # a surface or on the cap, and on a sample of the others.
    near = np.flatnonzero(np.abs(exact) < 1e-3 * float(np.abs(hi - lo).max()))
    some = np.union1d(near, rng.choice(len(points), 4000, replace=False))
    inside = scene.contains(points[some], method=method, precision="reference")
    assert 0 < inside.sum() < len(some)
    np.testing.assert_array_equal(np.signbit(exact[some]), inside)
    np.testing.assert_array_equal(np.signbit(fast[some]), inside)
    check_tiers_in_threads(lambda tier: scene.signed_distance(points[:5000], precision=tier), ("exact", "fast"), 3)


def test_points_searched_in_grid_order_answer_in_their_own_rows(device, bunny, monkeypatch):
    """A chunk of 4,096 points or more is searched cell by cell of a grid over the scene
    (point_order.comp's counting sort on the GPU); each answer must still land in its own row:
    the exact tier equals the reference tier bit for bit, and equals the same query with the
    points searched as they come (VKRAY_POINT_ORDER=input), for points inside the grid, far
    outside it (clamped to its border cells) and repeated ones; winding numbers likewise."""
    v, f = bunny
    scene = device.scene([device.mesh(v, f)])
    rng = np.random.default_rng(5)
    points = np.vstack([points_around(v, 9000, seed=3), np.repeat(v[:10], 100, axis=0), [[1e6, -1e6, 3e5]]])
    rng.shuffle(points)
    ordered = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS, precision="exact")
    reference = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS, precision="reference")
    monkeypatch.setenv("VKRAY_POINT_ORDER", "input")
    as_they_come = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS, precision="exact")
    for field in vkray.CLOSEST_FIELDS:
        np.testing.assert_array_equal(getattr(ordered, field), getattr(as_they_come, field), err_msg=field)
    if device.info.is_software:
        np.testing.assert_array_equal(ordered.distance, reference.distance)
        np.testing.assert_array_equal(ordered.position, reference.position)
    else:  # a GPU's f64 division and square root may round otherwise (to an ulp)
        np.testing.assert_allclose(ordered.distance, reference.distance, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(ordered.position, reference.position, rtol=1e-13, atol=1e-15)
    inside_as_they_come = scene.contains(points[:5000], method="winding")
    monkeypatch.delenv("VKRAY_POINT_ORDER")
    inside = scene.contains(points[:5000], method="winding")
    np.testing.assert_array_equal(inside, inside_as_they_come)
    np.testing.assert_array_equal(inside, scene.contains(points[:5000], method="winding", precision="reference"))
    # contains' rays cast in grid order (the default on software devices): the same rows, by the
    # winding number through the cap and by parity in a closed mesh.
    monkeypatch.setenv("VKRAY_POINT_ORDER", "grid")
    np.testing.assert_array_equal(scene.contains(points[:5000], method="winding"), inside)
    cube = device.scene([device.mesh(*oracle.box(v.min(0), v.max(0)))])
    in_the_box = ((points >= v.min(0)) & (points <= v.max(0))).all(axis=1)
    np.testing.assert_array_equal(cube.contains(points), in_the_box)
    monkeypatch.delenv("VKRAY_POINT_ORDER")
    # Several threads at once, each with its own chunks in grid order: the same answers.
    check_tiers_in_threads(lambda tier: scene.distance(points, precision=tier), ("exact",), 3)


def test_closest_points_in_chunks_land_in_their_rows(device, bunny, monkeypatch):
    """On a GPU each chunk's fields are written from its readback as it finishes (while the next
    chunk is searched): over five chunks, the last one short, every field of the exact tier lands
    in its own row and equals the reference tier's (to a GPU's f64 rounding)."""
    monkeypatch.setenv("VKRAY_POINT_CHUNK", "2500")
    v, f = bunny
    scene = device.scene([device.mesh(v, f)])
    points = points_around(v, 11000, seed=17)
    found = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS, precision="exact")
    reference = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS, precision="reference")
    exact = device.info.is_software or device.info.engine == "cpu"
    for name in ("distance", "position", "uv"):
        if exact:
            np.testing.assert_array_equal(getattr(found, name), getattr(reference, name), err_msg=name)
        else:
            np.testing.assert_allclose(getattr(found, name), getattr(reference, name), rtol=1e-9, atol=1e-12,
                                       err_msg=name)
    for name in ("prim_id", "instance_id", "custom_index", "geometry_id", "normal"):
        rows = (getattr(found, name) == getattr(reference, name)).reshape(len(points), -1)
        same = rows.all(axis=1)
        assert same.mean() >= (1.0 if exact else 0.98), f"{name}: {same.mean()}"


def test_host_search_from_a_neighbours_nearest_answers_each_point_alone(any_device, bunny):
    """The host's search takes points along a Morton curve, each from the previous point's nearest
    triangle: every point's answer must be its own search's, whatever its neighbours in the batch.
    Two identical instances (every distance a tie, settled by the lower instance) and a third moved
    and turned: the batch, the batch shuffled, and each point asked alone answer alike."""
    v, f = bunny
    mesh = any_device.mesh(v, f)
    turned = np.eye(4)
    turned[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    turned[:3, 3] = 0.05
    scene = any_device.scene([vkray.Instance(mesh), vkray.Instance(mesh), vkray.Instance(mesh, turned)])
    points = points_around(v, 3000, seed=11)
    batch = scene.closest_points(points, outputs=vkray.CLOSEST_FIELDS, precision="reference")
    order = np.random.default_rng(2).permutation(len(points))
    shuffled = scene.closest_points(points[order], outputs=vkray.CLOSEST_FIELDS, precision="reference")
    for field in vkray.CLOSEST_FIELDS:
        np.testing.assert_array_equal(getattr(shuffled, field), getattr(batch, field)[order], err_msg=field)
    assert set(np.unique(batch.instance_id)) <= {0, 2} and (batch.instance_id == 0).any()
    for i in range(0, len(points), 100):
        alone = scene.closest_points(points[i : i + 1], outputs=vkray.CLOSEST_FIELDS, precision="reference")
        for field in vkray.CLOSEST_FIELDS:
            np.testing.assert_array_equal(getattr(alone, field)[0], getattr(batch, field)[i], err_msg=f"{field} of {i}")


@pytest.mark.parametrize("chunk", [None, "1000"])
def test_float32_points_answer_as_their_float64_values(device, bunny, monkeypatch, chunk):
    """Points given as float32 reach a GPU as they are (12 bytes a point) and are widened there;
    every point query answers them exactly as it answers the same values given as float64 (numpy's
    widening): distances and closest points in both GPU tiers, signed distances (the sign's rays)
    and contains by winding number. One chunk of 6,000 points is searched in grid order, chunks of
    1,000 as they come."""
    if chunk is not None:
        monkeypatch.setenv("VKRAY_POINT_CHUNK", chunk)
    v, f = bunny
    scene = device.scene(device.mesh(v, f))
    p32 = points_around(v, 6000, seed=21).astype(np.float32)
    p64 = p32.astype(np.float64)
    for tier in ("fast", "exact"):
        np.testing.assert_array_equal(scene.distance(p32, precision=tier), scene.distance(p64, precision=tier))
        a, b = scene.closest_points(p32, precision=tier), scene.closest_points(p64, precision=tier)
        for name in ("distance", "position", "prim_id", "uv"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{tier} {name}")
    signed = scene.signed_distance(p32, precision="exact", method="winding")
    np.testing.assert_array_equal(signed, scene.signed_distance(p64, precision="exact", method="winding"))
    inside = scene.contains(p32, method="winding")
    np.testing.assert_array_equal(inside, scene.contains(p64, method="winding"))
    # Not a vacuous equality: points on both sides, and the distances themselves right.
    assert 0 < inside.sum() < len(inside) and (signed < 0).sum() == inside.sum()
    np.testing.assert_array_equal(np.abs(signed), scene.distance(p64, precision="exact"))


def test_float32_points_with_subnormal_coordinates_are_measured_as_given(device):
    """A float32 point whose coordinate is subnormal keeps it on a GPU (whose conversions may
    flush such inputs to zero): its distances equal those of the same values in float64, and the
    first point's, to a square through the origin in the plane x = 0, is that coordinate."""
    v = np.array([[0, -1, -1], [0, 1, -1], [0, 1, 1], [0, -1, 1]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    scene = device.scene(device.mesh(v, f))
    tiny = np.float32(1e-40)
    assert 0 < tiny < np.finfo(np.float32).tiny  # subnormal
    p32 = np.array([[tiny, 0.2, 0.3], [-tiny, -0.4, 0.1], [0.5, 0.25, 0.0]], dtype=np.float32)
    p64 = p32.astype(np.float64)
    for tier in ("exact", "reference"):
        got = scene.distance(p32, precision=tier)
        np.testing.assert_array_equal(got, scene.distance(p64, precision=tier), err_msg=tier)
        assert got[0] == np.float64(tiny), tier
        signed = scene.signed_distance(p32, precision=tier, method="winding")
        np.testing.assert_array_equal(signed, scene.signed_distance(p64, precision=tier, method="winding"))
