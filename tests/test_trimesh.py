"""vkray as trimesh's ray engine (`vkray.trimesh`): trimesh's interface, answered exactly.

Each behaviour is checked against an independent answer: the analytic one of a box or sphere,
trimesh's own geometry (face normals, bounds), or trimesh's embree engine where both must agree.
"""

import copy
import pickle
import threading

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")
import vkray  # noqa: E402
import vkray.trimesh as vt  # noqa: E402


@pytest.fixture
def box(any_device):
    mesh = trimesh.creation.box(extents=[2.0, 2.0, 2.0])
    return mesh, vt.RayMeshIntersector(mesh, device=any_device)


def test_interface_types_and_shapes(box):
    mesh, ray = box
    o = np.array([[0.3, 0.2, -5.0], [5.0, 5.0, 5.0], [0.1, -0.4, 5.0]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -3.0]])  # raw lengths are fine
    tri, ray_index = ray.intersects_id(o, d)
    assert tri.dtype == np.int64 and ray_index.dtype == np.int64
    assert sorted(ray_index.tolist()) == [0, 0, 2, 2]
    tri, ray_index, loc = ray.intersects_id(o, d, return_locations=True)
    assert loc.dtype == np.float64 and loc.shape == (4, 3)
    # Hit points lie on the box's faces, under the rays' origins.
    np.testing.assert_allclose(np.abs(loc[:, 2]), 1.0, atol=1e-12)
    np.testing.assert_allclose(loc[:, :2], o[ray_index, :2], atol=1e-12)
    # ... on the faces whose normal says so.
    np.testing.assert_allclose(np.abs(mesh.face_normals[tri, 2]), 1.0)
    loc2, ray2, tri2 = ray.intersects_location(o, d)
    np.testing.assert_array_equal(ray2, ray_index)
    np.testing.assert_array_equal(tri2, tri)
    np.testing.assert_array_equal(loc2, loc)
    first = ray.intersects_first(o, d)
    assert first.dtype == np.int64 and first[1] == -1 and (first[[0, 2]] >= 0).all()
    any_hit = ray.intersects_any(o, d)
    assert any_hit.dtype == bool and any_hit.tolist() == [True, False, True]
    assert ray.mesh is mesh


def test_first_hit_and_max_hits(box):
    _, ray = box
    o, d = [[0.3, 0.2, -5.0]], [[0.0, 0.0, 1.0]]
    tri, idx, loc = ray.intersects_id(o, d, multiple_hits=False, return_locations=True)
    assert len(tri) == 1 and loc[0, 2] == pytest.approx(-1.0)
    tri, idx, loc = ray.intersects_id(o, d, max_hits=1, return_locations=True)
    assert len(tri) == 1 and loc[0, 2] == pytest.approx(-1.0)
    assert len(ray.intersects_id(o, d)[0]) == 2


def test_zero_and_non_finite_directions_hit_nothing(box):
    _, ray = box
    o = np.array([[0.0, 0.0, -5.0]] * 3)
    d = np.array([[0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [0.0, 0.0, 1.0]])
    tri, idx = ray.intersects_id(o, d)
    assert set(idx.tolist()) == {2}
    assert ray.intersects_first(o, d).tolist()[:2] == [-1, -1]
    assert ray.intersects_any(o, d).tolist() == [False, False, True]
    with pytest.raises(ValueError, match="differ"):
        ray.intersects_id(o, d[:2])


def test_rays_through_vertices_and_edges_hit_once(any_device):
    """From the box's centre through each vertex and each edge midpoint: exactly one hit each
    (trimesh's engines may report two or none there)."""
    mesh = trimesh.creation.box()
    ray = vt.RayMeshIntersector(mesh, device=any_device)
    edges = mesh.vertices[mesh.edges_unique].mean(axis=1)
    targets = np.vstack([mesh.vertices, edges])
    _, idx = ray.intersects_id(np.zeros_like(targets), targets)
    np.testing.assert_array_equal(np.bincount(idx, minlength=len(targets)), 1)
    # From outside through two opposite edges: two crossings, once each.
    o = -3 * targets
    _, idx = ray.intersects_id(o, targets - o)
    np.testing.assert_array_equal(np.bincount(idx, minlength=len(targets)), 2)


def test_rays_in_a_faces_plane_hit_nothing_there(any_device):
    mesh = trimesh.creation.box()  # faces at +-0.5
    ray = vt.RayMeshIntersector(mesh, device=any_device)
    o = np.array([[-2.0, 0.1, 0.5], [-2.0, 0.5, 0.5]])  # in the top face's plane; along an edge
    tri, idx = ray.intersects_id(o, [[1.0, 0.0, 0.0]] * 2)
    assert not np.isin(tri, np.nonzero(mesh.face_normals[:, 2] > 0.5)[0]).any()


def test_grazing_rays_touch_once_per_point(box):
    """Rays down the box's side faces (through a top edge, or down a vertical edge through a
    corner) cross nothing but touch it: they hit where they touch, once per point (the triangles
    sharing that edge or corner meet the ray there together), at the top and at the bottom."""
    mesh, ray = box
    o = np.array([[1, 0, 5], [-1, 0, 5], [0, 1, 5], [0, -1, 5], [1, 1, 5], [-1, -1, 5], [1, -1, 5], [-1, 1, 5]], float)
    d = np.tile([[0.0, 0.0, -1.0]], (len(o), 1))
    assert ray.intersects_any(o, d).all()
    first = ray.intersects_id(o, d, multiple_hits=False, return_locations=True)
    np.testing.assert_allclose(first[2][:, 2], 1.0)
    tri, idx, loc = ray.intersects_id(o, d, return_locations=True)
    np.testing.assert_array_equal(np.bincount(idx, minlength=len(o)), 2)
    np.testing.assert_allclose(np.sort(loc[:, 2].reshape(-1, 2), axis=1), [[-1.0, 1.0]] * len(o))
    np.testing.assert_allclose(loc[:, :2], o[idx, :2], atol=4 * vt.GRAZE_TOLERANCE * mesh.scale)
    # One ray grazing, one crossing: the crossing ray reports its crossings only.
    tri, idx = ray.intersects_id([[1.0, 0.0, 5.0], [0.0, 0.0, 5.0]], [[0, 0, -1.0]] * 2)
    assert np.bincount(idx).tolist() == [2, 2]


def test_contains_points(any_device):
    """Closed: parity, exact (vertices and surface points inside); open: the winding number."""
    mesh = trimesh.creation.box()
    ray = vt.RayMeshIntersector(mesh, device=any_device)
    assert ray.contains_points(mesh.vertices).all()
    assert ray.contains_points(mesh.vertices / 1.5).all()
    assert not ray.contains_points(mesh.vertices * 1.5).any()
    assert ray.contains_points(np.zeros((0, 3))).shape == (0,)
    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, (2000, 3))
    np.testing.assert_array_equal(ray.contains_points(points), (np.abs(points) <= 0.5).all(axis=1))
    # A box without its top: not closed, so the winding number decides (1/2 at the centre).
    open_box = trimesh.Trimesh(mesh.vertices, mesh.faces[mesh.face_normals[:, 2] < 0.5], process=False)
    inside = vt.RayMeshIntersector(open_box, device=any_device).contains_points([[0, 0, -0.3], [0, 0, 3.0]])
    assert inside.tolist() == [True, False]


def test_the_scene_follows_the_mesh(any_device):
    mesh = trimesh.creation.box()
    ray = vt.RayMeshIntersector(mesh, device=any_device)
    o, d = [[0.0, 0.0, -5.0]], [[0.0, 0.0, 1.0]]
    assert ray.intersects_location(o, d)[0][0, 2] == pytest.approx(-0.5)
    mesh.apply_scale(4.0)
    assert ray.intersects_location(o, d)[0][0, 2] == pytest.approx(-2.0)
    mesh.vertices = mesh.vertices + [0.0, 0.0, 1.0]
    assert ray.intersects_location(o, d)[0][0, 2] == pytest.approx(-1.0)


def test_pickle_and_copy(any_device):
    mesh = trimesh.creation.icosphere()
    ray = vt.RayMeshIntersector(mesh, device=any_device, precision="exact")
    o, d = [[0.0, 0.0, -5.0]], [[0.0, 0.0, 1.0]]
    want = ray.intersects_location(o, d)[0]
    for other in (pickle.loads(pickle.dumps(ray)), copy.copy(ray), copy.deepcopy(ray)):
        assert other.precision == "exact"
        np.testing.assert_allclose(other.intersects_location(o, d)[0], want)


def test_enable_disable_and_use(any_device):
    embree_or_triangle = type(trimesh.creation.box().ray)
    vt.enable(device=any_device)
    try:
        mesh = trimesh.creation.icosphere(subdivisions=3)
        assert isinstance(mesh.ray, vt.RayMeshIntersector)
        # trimesh's own helpers now run on vkray.
        assert mesh.contains([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]).tolist() == [True, False]
        sd = trimesh.proximity.signed_distance(mesh, [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
        assert sd[0] > 0.9 and sd[1] < -0.9
        longest = trimesh.proximity.longest_ray(mesh, [[0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]])
        assert longest[0] == pytest.approx(1.0, abs=0.01)
    finally:
        vt.disable()
    assert type(trimesh.creation.box().ray) is embree_or_triangle
    mesh = vt.use(trimesh.creation.box(), device=any_device)
    assert isinstance(mesh.ray, vt.RayMeshIntersector)


def test_agrees_with_embree_away_from_edges(any_device):
    """Random rays at a subdivided sphere: the same triangles as trimesh's embree engine where no
    hit is near an edge (embree runs in float32)."""
    pytest.importorskip("embreex")
    from trimesh.ray import ray_pyembree

    mesh = trimesh.creation.icosphere(subdivisions=3)
    ours = vt.RayMeshIntersector(mesh, device=any_device)
    theirs = ray_pyembree.RayMeshIntersector(mesh)
    rng = np.random.default_rng(9)
    o = rng.normal(size=(500, 3))
    o = 3 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.6, 0.6, (500, 3)) - o
    np.testing.assert_array_equal(ours.intersects_first(o, d), theirs.intersects_first(o, d))
    a_tri, a_ray = ours.intersects_id(o, d)
    b_tri, b_ray = theirs.intersects_id(o, d)
    assert sorted(zip(a_ray.tolist(), a_tri.tolist())) == sorted(zip(b_ray.tolist(), b_tri.tolist()))


def test_device_mesh_takes_a_trimesh(any_device):
    mesh = trimesh.creation.box()
    scene = any_device.scene(any_device.mesh(mesh))
    assert scene.intersect([0.0, 0.0, -5.0], [0.0, 0.0, 1.0]).t == pytest.approx(4.5)
    with pytest.raises(TypeError, match="faces"):
        any_device.mesh(np.eye(3))


def test_device_scene_takes_trimeshes(any_device):
    """Device.scene takes a trimesh mesh, or a list mixing them with vkray meshes and instances,
    as Device.mesh takes one: instance ids in the list's order."""
    box = trimesh.creation.box()  # faces at +-0.5
    far = trimesh.creation.box().apply_translation([0.0, 0.0, 3.0])
    assert any_device.scene(box).intersect([0.0, 0.0, -5.0], [0.0, 0.0, 1.0]).t == pytest.approx(4.5)
    scene = any_device.scene([far, vkray.Instance(any_device.mesh(box), custom_index=7)])
    hits = scene.count([0.0, 0.0, -5.0], [0.0, 0.0, 1.0], precision="reference")
    assert int(hits) == 4
    first = scene.intersect([0.0, 0.0, 5.0], [0.0, 0.0, -1.0])
    assert (int(first.instance_id), float(first.t)) == (0, pytest.approx(1.5))
    with pytest.raises(TypeError, match=r"scene item 1 must be a Mesh, an Instance or a mesh object"):
        any_device.scene([box, "box"])
    with pytest.raises(TypeError, match="scene\\(\\) takes a Mesh, an Instance or a list of them, got int"):
        any_device.scene(3)


def _touching_rays(mesh, rng):
    """Rays that only touch a convex mesh: through each vertex and the midpoint of each edge
    between faces that are not coplanar (a face's diagonal is no silhouette), in the plane
    through it whose normal is a sum of the normals of the faces there (a supporting plane)."""
    crease = mesh.face_adjacency_angles > 1e-3
    points = np.vstack([mesh.vertices, mesh.vertices[mesh.face_adjacency_edges[crease]].mean(axis=1)])
    outward = np.vstack([mesh.vertex_normals, mesh.face_normals[mesh.face_adjacency[crease]].sum(axis=1)])
    along = np.cross(outward, rng.normal(size=points.shape))
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    return points - 3 * along, along, points


@pytest.mark.parametrize("precision", vkray.PRECISIONS)
@pytest.mark.parametrize("name", ["icosphere", "box", "capsule"])
def test_touching_rays_hit_where_trimesh_triangle_engine_says(any_device, name, precision):
    """Rays aimed through vertices and edge midpoints of convex meshes, touching them only: in
    every precision each hits (as trimesh's triangle engine answers, with its tolerance), where it
    touches. On the float32 surface a touching ray may also cross it, entering and leaving close
    by (a chord as long as the square root of float32's rounding allows): each hit is near the
    touched point, one per point in the exact tiers (a chord's two ends at most); the f32 tiers
    may meet each triangle around a vertex (README: precision tiers)."""
    from trimesh.ray.ray_triangle import RayMeshIntersector as TriangleEngine

    mesh = {"icosphere": lambda: trimesh.creation.icosphere(subdivisions=1),
            "box": lambda: trimesh.creation.box(extents=[1.0, 2.0, 3.0]),
            "capsule": lambda: trimesh.creation.capsule(height=1.0, radius=0.5, count=[6, 6])}[name]()
    assert mesh.is_convex
    o, d, touched = _touching_rays(mesh, np.random.default_rng(5))
    theirs = TriangleEngine(mesh)
    ours = vt.RayMeshIntersector(mesh, device=any_device, precision=precision)
    assert theirs.intersects_any(o, d).all()
    np.testing.assert_array_equal(ours.intersects_any(o, d), True)
    near = 1e-3 * mesh.scale  # float32 chords: sqrt(6e-8) of the size, with room
    tri, ray, loc = ours.intersects_id(o, d, multiple_hits=False, return_locations=True)
    np.testing.assert_array_equal(ray, np.arange(len(o)))
    assert np.linalg.norm(loc - touched, axis=1).max() < near
    # The triangle named holds the point hit (trimesh's barycentric test, a float32 tolerance).
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], loc)
    assert (bary > -1e-3).all()
    tri, ray, loc = ours.intersects_id(o, d, multiple_hits=True, return_locations=True)
    assert np.linalg.norm(loc - touched[ray], axis=1).max() < near
    counts = np.bincount(ray, minlength=len(o))
    assert counts.min() >= 1
    if precision in ("exact", "reference"):
        assert counts.max() <= 2


def test_scale_to_box_is_accepted_and_changes_nothing(any_device):
    """trimesh's embree engine's `scale_to_box` (positional or keyword): the same answers."""
    mesh = trimesh.creation.icosphere(subdivisions=2).apply_scale(1e-3)
    rng = np.random.default_rng(6)
    o = rng.uniform(-2e-3, 2e-3, (200, 3))
    d = -o + rng.normal(scale=1e-4, size=o.shape)
    answers = [vt.RayMeshIntersector(mesh, *args, device=any_device, **kwargs).intersects_id(o, d)
               for args, kwargs in (((), {}), ((False,), {}), ((), {"scale_to_box": True}))]
    for a, b in zip(answers[0], answers[1]):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(answers[0], answers[2]):
        np.testing.assert_array_equal(a, b)
    assert len(answers[0][0]) > 100
    assert copy.copy(vt.RayMeshIntersector(mesh, False))._scale_to_box is False


def test_threads_share_an_intersector(any_device):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    ray = vt.RayMeshIntersector(mesh, device=any_device)
    rng = np.random.default_rng(4)
    o = rng.uniform(-2, 2, (300, 3))
    d = -o
    want = ray.intersects_id(o, d)
    failures = []

    def work():
        for _ in range(10):
            got = ray.intersects_id(o, d)
            if not all(np.array_equal(a, b) for a, b in zip(got, want)):
                failures.append("differs")

    threads = [threading.Thread(target=work, daemon=True) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not any(t.is_alive() for t in threads) and not failures


def test_bad_precision():
    with pytest.raises(ValueError, match="precision"):
        vt.RayMeshIntersector(trimesh.creation.box(), precision="double")


def test_default_device_is_shared():
    assert vt.default_device() is vt.default_device() is vkray.default_device()
    assert isinstance(vt.default_device(), vkray.Device)


def test_default_device_from_several_threads_at_once():
    """Threads asking for the shared device at once all get one and the same (opened outside the
    lock: none waits on another's driver call holding it)."""
    import vkray._device as device_module

    got = []
    previous = device_module._default
    device_module._default = None  # as in a fresh process
    try:
        threads = [threading.Thread(target=lambda: got.append(vkray.default_device())) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=120)
        assert len(got) == 4 and all(d is got[0] for d in got)
        assert vkray.default_device() is got[0]
    finally:
        device_module._default = previous
