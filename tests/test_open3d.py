"""vkray as Open3D's ray-casting scene (`vkray.open3d`): Open3D's ``RaycastingScene`` is the oracle,
on the same scenes, rays and points, for every method and keyword. Where the two differ by design
(the module's docstring lists each difference), the drop-in's side is checked against an
independent answer (analytic, brute force, winding numbers) and Open3D's side is shown."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

if os.environ.get("VKRAY_REQUIRE_OPEN3D") == "1":  # CI (.ci/run): Open3D must be there to compare with
    import open3d as o3d
else:
    o3d = pytest.importorskip("open3d")
if not hasattr(o3d, "t"):  # pragma: no cover - a package named open3d that is not Open3D
    pytest.skip("open3d lacks open3d.t (Open3D >= 0.14 is needed)", allow_module_level=True)
import vkray  # noqa: E402
import vkray.open3d as vo3d  # noqa: E402
from oracle import box, in_threads, triangle_soup, winding_numbers  # noqa: E402

O3DScene = o3d.t.geometry.RaycastingScene
INVALID = O3DScene.INVALID_ID
CUDA = o3d.core.cuda.is_available()


def numpy(value):
    """An Open3D tensor's or numpy array's values as numpy."""
    return value.cpu().numpy() if isinstance(value, o3d.core.Tensor) else np.asarray(value)


def both(device, meshes, **kwargs):
    """Open3D's scene and the drop-in's, the same (vertices, faces) added to each in order."""
    theirs, ours = O3DScene(), vo3d.RaycastingScene(vkray_device=device, **kwargs)
    for v, f in meshes:
        a = theirs.add_triangles(o3d.core.Tensor(np.asarray(v, np.float32)), o3d.core.Tensor(np.asarray(f, np.uint32)))
        b = ours.add_triangles(np.asarray(v, np.float32), np.asarray(f, np.uint32))
        assert a == b
    return theirs, ours


def closed_meshes():
    """Closed meshes that do not overlap: a box, a sphere and a torus (Open3D's own factories)."""
    meshes = [box((0.0, 0.0, 0.0), (1.0, 0.7, 0.9))]
    sphere = o3d.t.geometry.TriangleMesh.create_sphere(0.5, 24).translate([2.0, 0.3, 0.4])
    torus = o3d.t.geometry.TriangleMesh.create_torus(0.6, 0.2, 24, 12).translate([0.6, 2.2, 0.5])
    for mesh in (sphere, torus):
        meshes.append((mesh.vertex.positions.numpy(), mesh.triangle.indices.numpy()))
    return meshes


def scene_rays(n, seed, lo=(-0.5, -0.5, -0.5), hi=(3.0, 3.0, 1.5)):
    """Rays from around the scene's box towards points inside it (most hit), float32 (n, 6),
    directions of random lengths."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo), np.asarray(hi)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo)
    u = rng.normal(size=(n, 3))
    origins = centre + radius * u / np.linalg.norm(u, axis=1, keepdims=True)
    directions = (rng.uniform(lo, hi, (n, 3)) - origins) * rng.uniform(0.2, 3.0, (n, 1))
    return np.concatenate([origins, directions], axis=1).astype(np.float32)


def scene_points(n, seed, lo=(-0.5, -0.5, -0.5), hi=(3.0, 3.0, 1.5)):
    return np.random.default_rng(seed).uniform(lo, hi, (n, 3)).astype(np.float32)


def by_ray(listed, rays):
    """Open3D's or the drop-in's list_intersections as per-ray lists of (t, geometry, triangle)
    sorted by t (Open3D lists a ray's hits in Embree's order)."""
    splits = numpy(listed["ray_splits"]).astype(np.int64)
    t, g, p = (numpy(listed[k]) for k in ("t_hit", "geometry_ids", "primitive_ids"))
    assert len(splits) == len(rays) + 1
    return [sorted(zip(t[a:b].tolist(), g[a:b].tolist(), p[a:b].tolist())) for a, b in zip(splits[:-1], splits[1:])]


# --- every method against Open3D's, on random scenes --------------------------------------------


def test_ray_queries_match_open3d(device):
    meshes = closed_meshes() + [triangle_soup(40, seed=3)]
    meshes[-1] = (meshes[-1][0] * 2.5, meshes[-1][1])
    theirs, ours = both(device, meshes)
    rays = scene_rays(3000, seed=1)
    a, b = theirs.cast_rays(rays, nthreads=1), ours.cast_rays(rays, nthreads=3)  # nthreads: accepted
    assert set(a) == set(b)
    for key in a:
        assert b[key].dtype == numpy(a[key]).dtype and b[key].shape == tuple(a[key].shape), key
    hit = numpy(a["geometry_ids"]) != INVALID
    np.testing.assert_array_equal(b["geometry_ids"] != INVALID, hit)
    assert hit.mean() > 0.5
    np.testing.assert_allclose(b["t_hit"], numpy(a["t_hit"]), rtol=1e-4)
    np.testing.assert_array_equal(b["geometry_ids"], numpy(a["geometry_ids"]))
    np.testing.assert_array_equal(b["primitive_ids"], numpy(a["primitive_ids"]))
    np.testing.assert_allclose(b["primitive_uvs"][hit], numpy(a["primitive_uvs"])[hit], atol=2e-4)
    np.testing.assert_allclose(b["primitive_normals"][hit], numpy(a["primitive_normals"])[hit], atol=1e-5)
    # Misses: NaN uvs and normals where Open3D writes 0 (the module's docstring says why).
    assert np.isnan(b["primitive_uvs"][~hit]).all() and np.isnan(b["primitive_normals"][~hit]).all()
    assert not numpy(a["primitive_normals"])[~hit].any()

    np.testing.assert_array_equal(ours.test_occlusions(rays), numpy(theirs.test_occlusions(rays)))
    t = numpy(a["t_hit"])
    for tnear, tfar in ((0.0, 0.5), (0.3, 0.9), (1.0, np.inf), (-2.0, 0.2), (0.7, 0.2), (0.4, 0.4)):
        want = numpy(theirs.test_occlusions(rays, tnear=tnear, tfar=tfar))
        got = ours.test_occlusions(rays, tnear=tnear, tfar=tfar, nthreads=2)
        # Open3D's f32 interval ends and vkray's differ for hits within rounding of tnear or tfar.
        near_end = np.isclose(t, tnear, rtol=1e-4) | np.isclose(t, tfar, rtol=1e-4)
        np.testing.assert_array_equal(got[~near_end], want[~near_end], err_msg=f"tnear={tnear} tfar={tfar}")
        assert got.any() == (tnear <= tfar and want.any())

    counts = ours.count_intersections(rays)
    assert counts.dtype == np.int32
    np.testing.assert_array_equal(counts, numpy(theirs.count_intersections(rays)))
    listed = ours.list_intersections(rays, nthreads=2)
    want = theirs.list_intersections(rays, nthreads=2)
    assert {k: numpy(v).dtype for k, v in want.items()} == {k: v.dtype for k, v in listed.items()}
    np.testing.assert_array_equal(listed["ray_splits"], numpy(want["ray_splits"]))
    np.testing.assert_array_equal(listed["ray_ids"], numpy(want["ray_ids"]))
    for k, (got_hits, want_hits) in enumerate(zip(by_ray(listed, rays), by_ray(want, rays))):
        assert [h[1:] for h in got_hits] == [h[1:] for h in want_hits], k
        np.testing.assert_allclose([h[0] for h in got_hits], [h[0] for h in want_hits], rtol=1e-4)
    # Nearest first, and each hit's uv as cast_rays gives the first one.
    t_hit, splits = listed["t_hit"], listed["ray_splits"].astype(np.int64)
    assert all((np.diff(t_hit[a:b]) >= 0).all() for a, b in zip(splits[:-1], splits[1:]))
    first = splits[:-1][counts > 0]
    np.testing.assert_allclose(listed["primitive_uvs"][first], b["primitive_uvs"][counts > 0], atol=2e-4)


def test_point_queries_match_open3d(any_device):
    theirs, ours = both(any_device, closed_meshes())
    points = scene_points(1500, seed=2)
    a, b = theirs.compute_closest_points(points), ours.compute_closest_points(points, nthreads=4)
    assert set(a) == set(b)
    for key in a:
        assert b[key].dtype == numpy(a[key]).dtype and b[key].shape == tuple(a[key].shape), key
    # As near as Open3D's nearest point; the same point but where several lie at one distance
    # (within float32's rounding: points near the torus's axis have a ring of them).
    ours_away = np.linalg.norm(b["points"] - points, axis=1)
    np.testing.assert_allclose(ours_away, np.linalg.norm(numpy(a["points"]) - points, axis=1), rtol=1e-5, atol=1e-6)
    same = np.abs(b["points"] - numpy(a["points"])).max(axis=1) <= 2e-6
    assert same.mean() > 0.99
    # The point lies on the triangle named, where its uvs say.
    meshes = closed_meshes()
    corners = np.stack([meshes[g][0][meshes[g][1][p]] for g, p in zip(b["geometry_ids"], b["primitive_ids"])])
    u, v = b["primitive_uvs"][:, :1], b["primitive_uvs"][:, 1:]
    on_triangle = corners[:, 0] * (1 - u - v) + corners[:, 1] * u + corners[:, 2] * v
    np.testing.assert_allclose(on_triangle, b["points"], atol=1e-5)
    # The nearest triangle is one answer where the nearest point lies inside it; at an edge or
    # vertex, several triangles are nearest and either may be named.
    uv = numpy(a["primitive_uvs"])
    inner = (uv.min(axis=1) > 1e-3) & (uv.sum(axis=1) < 1 - 1e-3) & same
    assert inner.mean() > 0.25
    for key in ("geometry_ids", "primitive_ids"):
        np.testing.assert_array_equal(b[key][inner], numpy(a[key])[inner])
    np.testing.assert_allclose(b["primitive_uvs"][inner], uv[inner], atol=1e-4)
    np.testing.assert_allclose(b["primitive_normals"][inner], numpy(a["primitive_normals"])[inner], atol=1e-5)

    distance = ours.compute_distance(points, nthreads=0)
    assert distance.dtype == np.float32
    np.testing.assert_allclose(distance, numpy(theirs.compute_distance(points)), rtol=1e-5, atol=1e-6)
    # Signs and occupancy: the same wherever a point is not within rounding of a surface.
    away = distance > 1e-4
    for nsamples in (1, 3):
        signed = ours.compute_signed_distance(points, nsamples=nsamples)
        want = numpy(theirs.compute_signed_distance(points, nsamples=nsamples))
        np.testing.assert_allclose(signed[away], want[away], rtol=1e-5, atol=1e-6)
        occupancy = ours.compute_occupancy(points, nthreads=1, nsamples=nsamples)
        assert occupancy.dtype == np.float32
        np.testing.assert_array_equal(occupancy[away], numpy(theirs.compute_occupancy(points, nsamples=nsamples))[away])
        assert 0.05 < occupancy.mean() < 0.9


def test_every_method_keeps_leading_dimensions_and_open3d_dtypes(any_device):
    theirs, ours = both(any_device, closed_meshes())
    methods = ("cast_rays", "test_occlusions", "count_intersections", "list_intersections",
               "compute_closest_points", "compute_distance", "compute_signed_distance", "compute_occupancy")

    def call(scene, method, shape, seed):
        n = int(np.prod(shape, dtype=int))
        rays = scene_rays(max(n, 1), seed)[:n].reshape(shape + (6,))
        points = scene_points(max(n, 1), seed)[:n].reshape(shape + (3,))
        arg = rays if method in methods[:4] else points
        answer = getattr(scene, method)(arg if scene is ours else o3d.core.Tensor(arg))
        return answer if isinstance(answer, dict) else {"": answer}

    def shapes(answer):
        return {key: (tuple(value.shape), numpy(value).dtype) for key, value in answer.items()}

    for method in methods:
        for shape in ((5,), (2, 3, 4)):
            assert shapes(call(ours, method, shape, 4)) == shapes(call(theirs, method, shape, 4)), (method, shape)
        # Open3D refuses a single ray (6,) and crashes on none (0, 6): the drop-in answers as
        # for (1, 6), less the leading axis, and (0, ...) arrays.
        one = shapes(call(ours, method, (1,), 5))
        for shape in ((), (0,)):
            got = shapes(call(ours, method, shape, 5))
            if method == "list_intersections":  # flat: ray_splits has rays + 1 entries
                assert got["ray_splits"] == ((int(np.prod(shape)) + 1,), np.dtype(np.uint32))
                continue
            assert got == {k: (shape + s[1:], dtype) for k, (s, dtype) in one.items()}, (method, shape)


# --- inputs and results ---------------------------------------------------------------------------


def test_open3d_tensors_in_give_open3d_tensors_out(any_device):
    ours = vo3d.RaycastingScene(vkray_device=any_device)
    cube = o3d.t.geometry.TriangleMesh.create_box()
    assert ours.add_triangles(cube) == 0
    rays = scene_rays(50, seed=6)
    points = scene_points(50, seed=7)
    from_numpy = ours.cast_rays(rays)
    from_tensor = ours.cast_rays(o3d.core.Tensor(rays))
    for key, value in from_tensor.items():
        assert isinstance(value, o3d.core.Tensor) and value.device == o3d.core.Device("CPU:0")
        assert isinstance(from_numpy[key], np.ndarray)
        np.testing.assert_array_equal(value.numpy(), from_numpy[key])
    for method, arg in (("test_occlusions", rays), ("count_intersections", rays), ("compute_distance", points),
                        ("compute_signed_distance", points), ("compute_occupancy", points)):
        tensor = getattr(ours, method)(o3d.core.Tensor(arg))
        assert isinstance(tensor, o3d.core.Tensor)
        np.testing.assert_array_equal(tensor.numpy(), getattr(ours, method)(arg))
    for method, arg in (("list_intersections", rays), ("compute_closest_points", points)):
        assert all(isinstance(v, o3d.core.Tensor) for v in getattr(ours, method)(o3d.core.Tensor(arg)).values())
    # Strided Open3D tensors (views) and float64 arrays are read as they are.
    wide = o3d.core.Tensor(np.concatenate([rays, np.zeros((50, 2), np.float32)], axis=1))
    np.testing.assert_array_equal(ours.cast_rays(wide[:, :6])["t_hit"].numpy(), from_numpy["t_hit"])
    np.testing.assert_allclose(ours.cast_rays(rays.astype(np.float64))["t_hit"], from_numpy["t_hit"], rtol=1e-6)
    # results="open3d": Open3D tensors for numpy inputs too, on the scene's device.
    as_open3d = vo3d.RaycastingScene(vkray_device=any_device, results="open3d", device=o3d.core.Device("CPU:0"))
    as_open3d.add_triangles(cube)
    assert isinstance(as_open3d.compute_distance(points), o3d.core.Tensor)
    assert isinstance(as_open3d.cast_rays(rays)["t_hit"], o3d.core.Tensor)


def test_add_triangles_in_every_form_numbers_geometries_as_open3d(any_device):
    cube = o3d.t.geometry.TriangleMesh.create_box()
    legacy = o3d.geometry.TriangleMesh.create_box().translate([2.0, 0.0, 0.0])
    v, f = box((0.0, 2.0, 0.0), (1.0, 3.0, 1.0))
    theirs, ours = O3DScene(), vo3d.RaycastingScene(vkray_device=any_device)
    empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32))
    added = [
        (theirs.add_triangles(cube), ours.add_triangles(cube)),
        (theirs.add_triangles(*empty), ours.add_triangles(*empty)),
        (theirs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(legacy)), ours.add_triangles(legacy)),
    ]
    rays = np.array([[0.5, 0.3, -1, 0, 0, 1], [2.5, 0.3, -1, 0, 0, 1], [0.5, 2.3, -1, 0, 0, 1]], np.float32)
    np.testing.assert_array_equal(ours.cast_rays(rays)["geometry_ids"], [0, 2, INVALID])
    # Adding after a query rebuilds the scene at the next one; every geometry keeps its id.
    added.append(
        (theirs.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32))),
         ours.add_triangles(v, f))  # float64 and int64 are taken as they are
    )
    assert [a for a, _ in added] == [b for _, b in added] == [0, 1, 2, 3]
    np.testing.assert_array_equal(ours.cast_rays(rays)["geometry_ids"], numpy(theirs.cast_rays(rays)["geometry_ids"]))
    np.testing.assert_array_equal(ours.cast_rays(rays)["geometry_ids"], [0, 2, 3])
    np.testing.assert_array_equal(ours.count_intersections(rays), [2, 2, 2])
    assert "4 geometries" in repr(ours)


def test_create_rays_pinhole_in_both_forms_matches_open3d():
    rng = np.random.default_rng(8)
    intrinsic = np.array([[300.0, 2.0, 70.0], [0.0, 280.0, 45.0], [0.0, 0.0, 1.0]])
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    extrinsic = np.eye(4)
    extrinsic[:3, :3] = rotation * np.sign(np.linalg.det(rotation))
    extrinsic[:3, 3] = [0.3, -1.0, 2.0]
    want = numpy(O3DScene.create_rays_pinhole(o3d.core.Tensor(intrinsic), o3d.core.Tensor(extrinsic), 13, 7))
    got = vo3d.RaycastingScene.create_rays_pinhole(intrinsic, extrinsic, 13, 7)
    assert isinstance(got, np.ndarray) and got.dtype == np.float32 and got.shape == (7, 13, 6)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    tensor = vo3d.RaycastingScene.create_rays_pinhole(
        intrinsic_matrix=o3d.core.Tensor(intrinsic), extrinsic_matrix=o3d.core.Tensor(extrinsic), width_px=13,
        height_px=7
    )
    assert isinstance(tensor, o3d.core.Tensor)
    np.testing.assert_array_equal(tensor.numpy(), got)
    for fov, center, eye, up, w, h in ((60.0, [0.5, 0.5, 0.5], [-1, -1, -1], [0, 0, 1], 32, 24),
                                       (25.0, [1, 2, 3], [-1, 0.5, 2], [0.3, 1, 0.2], 9, 17)):
        want = numpy(O3DScene.create_rays_pinhole(fov_deg=fov, center=center, eye=eye, up=up, width_px=w, height_px=h))
        got = vo3d.RaycastingScene.create_rays_pinhole(fov, center, eye, up, w, h)
        assert got.shape == (h, w, 6)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # A camera's rays through the scene: the same depth image as Open3D's.
    theirs, ours = O3DScene(), vo3d.RaycastingScene()
    cube = o3d.t.geometry.TriangleMesh.create_box()
    theirs.add_triangles(cube), ours.add_triangles(cube)
    rays = ours.create_rays_pinhole(fov_deg=60, center=[0.5, 0.5, 0.5], eye=[-1, -1.3, -1.1], up=[0, 0, 1],
                                    width_px=40, height_px=30)
    depth = ours.cast_rays(rays)["t_hit"]
    assert depth.shape == (30, 40) and np.isfinite(depth).mean() > 0.2
    np.testing.assert_allclose(depth, numpy(theirs.cast_rays(rays)["t_hit"]), rtol=1e-5)


# --- where the two differ, by design ------------------------------------------------------------


def test_list_order_and_shared_edges(any_device):
    """Two overlapping unit boxes, and a ray through the diagonal edges of their faces: four
    crossings. The drop-in lists them once each, nearest first; Open3D lists 8 (both triangles at
    each edge, as its count's filter keeps only one geometry's last hit), in traversal order."""
    first = o3d.t.geometry.TriangleMesh.create_box()
    second = o3d.t.geometry.TriangleMesh.create_box().translate([0.0, 0.0, -0.5])
    theirs, ours = O3DScene(), vo3d.RaycastingScene(vkray_device=any_device)
    for mesh in (first, second):
        assert theirs.add_triangles(mesh) == ours.add_triangles(mesh)
    ray = np.array([[0.5, 0.5, -1.0, 0.0, 0.0, 1.0]], np.float32)
    listed = ours.list_intersections(ray)
    np.testing.assert_allclose(listed["t_hit"], [0.5, 1.0, 1.5, 2.0])
    np.testing.assert_array_equal(listed["geometry_ids"], [1, 0, 1, 0])
    np.testing.assert_array_equal(ours.count_intersections(ray), [4])
    # Open3D's answer, as the module's docstring describes it.
    assert numpy(theirs.count_intersections(ray)).tolist() == [8]
    assert len(numpy(theirs.list_intersections(ray)["t_hit"])) == 8


def test_points_on_the_surface_are_inside(any_device):
    """Faces, vertices and edges of a box: occupancy 1 and signed distance 0 (Open3D's jittered
    rays put such points on either side)."""
    ours = vo3d.RaycastingScene(vkray_device=any_device)
    ours.add_triangles(*box())
    v, _ = box()
    on_faces = np.array([[0.5, 0.5, 0.0], [1.0, 0.2, 0.7], [0.3, 1.0, 0.3], [0.25, 0.25, 1.0]])
    edges = (v[[0, 1, 2, 4]] + v[[1, 3, 6, 5]]) / 2
    points = np.concatenate([on_faces, v, edges]).astype(np.float32)
    np.testing.assert_array_equal(ours.compute_occupancy(points), 1.0)
    # At float32's rounding in the default tier (never outside), exactly 0 in the exact tier.
    signed = ours.compute_signed_distance(points)
    assert (signed <= 0).all() and (signed >= -1e-6).all()
    exact = vo3d.RaycastingScene(vkray_device=any_device, precision="exact")
    exact.add_triangles(*box())
    np.testing.assert_array_equal(exact.compute_signed_distance(points), 0.0)
    np.testing.assert_array_equal(exact.compute_distance(points), 0.0)


def test_occupancy_is_exact_whatever_nsamples(any_device):
    """A sphere's grid of points (Open3D's own test's grid, finer): every nsamples gives the
    exact answer, the winding number of the mesh (1 inside, 0 outside)."""
    sphere = o3d.t.geometry.TriangleMesh.create_sphere(0.8, 12)
    ours = vo3d.RaycastingScene(vkray_device=any_device)
    ours.add_triangles(sphere)
    grid = np.stack(np.meshgrid(*[np.linspace(-0.9, 0.9, 13)] * 3, indexing="ij"), axis=-1).astype(np.float32)
    v, f = sphere.vertex.positions.numpy(), sphere.triangle.indices.numpy()
    exact = (winding_numbers(v, f, grid) > 0.5).reshape(grid.shape[:-1])
    on_surface = ours.compute_distance(grid) < 1e-6
    for nsamples in (1, 3, 7):
        occupancy = ours.compute_occupancy(grid, nsamples=nsamples)
        assert occupancy.shape == grid.shape[:-1]
        np.testing.assert_array_equal(occupancy[~on_surface], exact[~on_surface])
        np.testing.assert_array_equal(occupancy[on_surface], 1.0)
    for bad in (0, 2, -1):
        with pytest.raises(ValueError, match="odd"):
            ours.compute_occupancy(grid, nsamples=bad)
        with pytest.raises(ValueError, match="odd"):
            ours.compute_signed_distance(grid, nsamples=bad)
        with pytest.raises(RuntimeError, match="odd"):  # Open3D refuses them too
            O3DScene().compute_occupancy(grid, nsamples=bad)


def test_open_meshes_are_signed_by_the_winding_number(any_device):
    """A box without its top: points inside it are inside (winding number >= 1/2), whichever way
    a ray from them would leave; Open3D's parity of jittered rays is no answer there."""
    v, f = box()
    top = np.all(v[f][:, :, 2] == 1.0, axis=1)
    f = f[~top]
    ours = vo3d.RaycastingScene(vkray_device=any_device)
    ours.add_triangles(v, f)
    points = scene_points(400, seed=9, lo=(-0.3, -0.3, -0.3), hi=(1.3, 1.3, 1.3))
    signed = ours.compute_signed_distance(points)
    inside = winding_numbers(v, f, points) >= 0.5
    assert 0.1 < inside.mean() < 0.9
    np.testing.assert_array_equal(signed < 0, inside)
    np.testing.assert_array_equal(ours.compute_occupancy(points), inside)
    np.testing.assert_allclose(np.abs(signed), ours.compute_distance(points))


def test_a_point_inside_any_mesh_is_inside(any_device):
    """Overlapping closed boxes: a point in both is inside (Open3D's parity says outside: two
    crossings; its documentation assumes meshes that do not overlap)."""
    theirs, ours = both(any_device, [box((0, 0, 0), (1, 1, 1)), box((0.5, 0.5, 0.5), (1.5, 1.5, 1.5))])
    points = np.array([[0.75, 0.75, 0.75], [0.25, 0.2, 0.3], [1.3, 1.2, 1.4], [2.0, 2.0, 2.0]], np.float32)
    np.testing.assert_array_equal(ours.compute_occupancy(points), [1, 1, 1, 0])
    assert ours.compute_signed_distance(points)[0] < 0
    assert numpy(theirs.compute_occupancy(points)).tolist() == [0, 1, 1, 0]


def test_an_empty_scene_answers_misses(any_device):
    ours = vo3d.RaycastingScene(vkray_device=any_device)
    rays, points = scene_rays(4, seed=10), scene_points(4, seed=11)
    hits = ours.cast_rays(rays)
    np.testing.assert_array_equal(hits["t_hit"], np.inf)
    np.testing.assert_array_equal(hits["geometry_ids"], INVALID)
    assert np.isnan(hits["primitive_uvs"]).all()
    assert not ours.test_occlusions(rays).any() and not ours.count_intersections(rays).any()
    np.testing.assert_array_equal(ours.list_intersections(rays)["ray_splits"], np.zeros(5))
    np.testing.assert_array_equal(ours.compute_distance(points), np.inf)
    np.testing.assert_array_equal(ours.compute_signed_distance(points), np.inf)
    np.testing.assert_array_equal(ours.compute_occupancy(points), 0.0)
    closest = ours.compute_closest_points(points)
    np.testing.assert_array_equal(closest["primitive_ids"], INVALID)
    assert np.isnan(closest["points"]).all()


# --- several threads, Open3D's place, bad input, precision ---------------------------------------


def test_several_threads_query_one_scene_at_once(any_device):
    theirs, ours = both(any_device, closed_meshes())
    rays, points = scene_rays(800, seed=12), scene_points(300, seed=13)
    want_t = numpy(theirs.cast_rays(rays)["t_hit"])
    want_counts = numpy(theirs.count_intersections(rays))
    want_distance = numpy(theirs.compute_distance(points))

    def work(k):
        # The first queries of all threads race to build the scene (built lazily, once needed).
        if k % 3 == 0:
            np.testing.assert_allclose(ours.cast_rays(rays[k:])["t_hit"], want_t[k:], rtol=1e-4)
        elif k % 3 == 1:
            np.testing.assert_array_equal(ours.count_intersections(rays), want_counts)
        else:
            np.testing.assert_allclose(ours.compute_distance(points), want_distance, rtol=1e-5, atol=1e-6)
        return k

    assert in_threads(6, work) == list(range(6))
    # A geometry added while other threads query: each query sees the scene before or after it.
    extra = box((-3.0, -3.0, -3.0), (-2.0, -2.0, -2.0))
    probe = np.array([[-2.5, -2.5, -5.0, 0.0, 0.0, 1.0]], np.float32)

    def adding(k):
        if k == 0:
            return ours.add_triangles(*extra)
        return [int(ours.count_intersections(probe)[0]) for _ in range(3)]

    results = in_threads(4, adding)
    assert results[0] == 3
    assert all(set(r) <= {0, 2} for r in results[1:])
    assert ours.count_intersections(probe).tolist() == [2]


def test_enable_puts_the_drop_in_in_open3d_s_place():
    original = o3d.t.geometry.RaycastingScene
    try:
        vo3d.enable()
        assert vo3d.enabled() and o3d.t.geometry.RaycastingScene is not original
        scene = o3d.t.geometry.RaycastingScene(device=o3d.core.Device("CPU:0"))
        assert isinstance(scene, vo3d.RaycastingScene)
        assert scene.add_triangles(o3d.t.geometry.TriangleMesh.create_box()) == 0
        # As Open3D's class: Open3D tensors for numpy inputs too.
        t = scene.cast_rays(np.array([[0.5, 0.3, -1, 0, 0, 1]], np.float32))["t_hit"]
        # Embree's f32 t, within an ulp of 1 (its AVX2 and AVX-512 kernels round differently).
        assert isinstance(t, o3d.core.Tensor) and np.allclose(t.numpy(), [1.0], rtol=2**-23, atol=0)
        assert isinstance(o3d.t.geometry.RaycastingScene.create_rays_pinhole(60.0, [0, 0, 1], [0, 0, 0], [0, 1, 0],
                                                                             4, 3), o3d.core.Tensor)
        assert o3d.t.geometry.RaycastingScene.INVALID_ID == INVALID
    finally:
        vo3d.disable()
    assert o3d.t.geometry.RaycastingScene is original and not vo3d.enabled()


def test_bad_input_is_refused_clearly(any_device):
    ours = vo3d.RaycastingScene(vkray_device=any_device)
    ours.add_triangles(*box())
    with pytest.raises(ValueError, match=r"rays must have shape \(\.\.\., 6\)"):
        ours.cast_rays(np.zeros((4, 3), np.float32))
    with pytest.raises(ValueError, match=r"query_points must have shape \(\.\.\., 3\)"):
        ours.compute_distance(np.zeros((4, 6), np.float32))
    with pytest.raises(TypeError, match="nthreads"):
        ours.count_intersections(np.zeros((1, 6), np.float32), nthreads=1.5)
    with pytest.raises(TypeError, match="tnear"):
        ours.test_occlusions(np.zeros((1, 6), np.float32), tnear="near")
    with pytest.raises(TypeError, match="TriangleMesh"):
        ours.add_triangles("a mesh")
    with pytest.raises(ValueError, match="triangle_indices must have shape"):
        ours.add_triangles(np.zeros((3, 3)), np.zeros((1, 4), np.int64))
    with pytest.raises(ValueError):  # an index beyond the vertices (Open3D reads past them)
        ours.add_triangles(np.zeros((3, 3)), np.array([[0, 1, 5]], np.uint32))
    with pytest.raises(ValueError, match="device"):
        vo3d.RaycastingScene(device="GPU:7")
    with pytest.raises(ValueError, match="precision"):
        vo3d.RaycastingScene(precision="approximate")
    with pytest.raises(TypeError, match="missing height_px"):
        vo3d.RaycastingScene.create_rays_pinhole(np.eye(3), np.eye(4), 4)
    with pytest.raises(ValueError, match="parallel"):
        vo3d.RaycastingScene.create_rays_pinhole(60.0, [0, 0, 1], [0, 0, 0], [0, 0, 2], 4, 3)
    # The scene still answers.
    assert ours.count_intersections(np.array([[0.5, 0.5, -1, 0, 0, 1]], np.float32)).tolist() == [2]


def test_one_precision_for_every_query(any_device):
    theirs, ours = both(any_device, closed_meshes(), precision="reference")
    rays, points = scene_rays(300, seed=14), scene_points(200, seed=15)
    hits = ours.cast_rays(rays)
    assert hits["t_hit"].dtype == np.float32  # float64 in the reference tier, float32 as Open3D's
    np.testing.assert_allclose(hits["t_hit"], numpy(theirs.cast_rays(rays)["t_hit"]), rtol=1e-4)
    np.testing.assert_array_equal(ours.count_intersections(rays), numpy(theirs.count_intersections(rays)))
    want = numpy(theirs.compute_distance(points))
    np.testing.assert_allclose(ours.compute_distance(points), want, rtol=1e-5, atol=1e-6)


def test_the_module_imports_without_open3d():
    """Without Open3D, numpy in and out works; asking for Open3D tensors says what to install."""
    code = textwrap.dedent(
        """
        import sys
        sys.modules["open3d"] = None  # import open3d raises ImportError
        import numpy as np
        import vkray.open3d as vo3d
        scene = vo3d.RaycastingScene()
        scene.add_triangles(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]))
        # Embree's f32 t, within an ulp of 1 (its AVX2 and AVX-512 kernels round differently).
        print(np.round(scene.cast_rays(np.array([[0.2, 0.2, 1, 0, 0, -1]], np.float32))["t_hit"], 6).tolist())
        try:
            vo3d.RaycastingScene(results="open3d").compute_distance(np.zeros((1, 3)))
        except ImportError as exc:
            print(exc)
        try:
            vo3d.enable()
        except ImportError as exc:
            print(exc)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "[1.0]"
    assert len(lines) == 3 and all('pip install "vkray[open3d]"' in line for line in lines[1:])


# --- CUDA (the H200): Open3D's CUDA tensors stay on the GPU ---------------------------------------


def _cuda_scene():
    if not CUDA:
        pytest.skip("Open3D without CUDA, or no CUDA GPU")
    device = vkray.Device()
    if device.cuda_device is None:
        pytest.skip("the vkray device is no CUDA GPU")
    theirs, ours = both(device, closed_meshes())
    return theirs, ours, o3d.core.Device(f"CUDA:{device.cuda_device}")


def test_open3d_cuda_tensors_stay_on_their_gpu():
    theirs, ours, gpu = _cuda_scene()
    rays, points = scene_rays(2000, seed=16), scene_points(500, seed=17)
    on_gpu = o3d.core.Tensor(rays.reshape(40, 50, 6)).to(gpu)
    hits = ours.cast_rays(on_gpu)
    want = theirs.cast_rays(rays)
    for key, value in hits.items():
        assert value.device == gpu and value.dtype == want[key].dtype, key
        assert tuple(value.shape)[:2] == (40, 50)
    np.testing.assert_allclose(hits["t_hit"].cpu().numpy().reshape(-1), want["t_hit"].numpy(), rtol=1e-4)
    np.testing.assert_array_equal(hits["primitive_ids"].cpu().numpy().reshape(-1), want["primitive_ids"].numpy())
    np.testing.assert_array_equal(np.isnan(hits["primitive_normals"].cpu().numpy()).any(axis=-1).reshape(-1),
                                  want["geometry_ids"].numpy() == INVALID)
    occluded = ours.test_occlusions(on_gpu, tfar=1.0)
    assert occluded.device == gpu and occluded.dtype == o3d.core.bool
    np.testing.assert_array_equal(occluded.cpu().numpy().reshape(-1), theirs.test_occlusions(rays, tfar=1.0).numpy())
    # The other queries copy through the host for now; their results go back to the GPU.
    counts = ours.count_intersections(on_gpu)
    assert counts.device == gpu
    np.testing.assert_array_equal(counts.cpu().numpy().reshape(-1), theirs.count_intersections(rays).numpy())
    distance = ours.compute_distance(o3d.core.Tensor(points).to(gpu))
    assert distance.device == gpu
    np.testing.assert_allclose(distance.cpu().numpy(), theirs.compute_distance(points).numpy(), rtol=1e-5, atol=1e-6)


def test_torch_cuda_rays_counted_on_their_gpu(monkeypatch):
    """count_intersections of torch CUDA rays runs vkray's GPU-resident exact count: neither the
    drop-in nor vkray copies the rays to the host, and the counts are Open3D's (numpy out)."""
    torch = pytest.importorskip("torch")
    device = vkray.Device()
    if device.cuda_device is None or not torch.cuda.is_available():
        pytest.skip("the vkray device is no CUDA GPU torch sees")
    theirs, ours = both(device, closed_meshes())

    def refuse(*args, **kwargs):
        raise AssertionError("CUDA rays went through the host")

    monkeypatch.setattr(vo3d, "_host", refuse)
    monkeypatch.setattr(vkray._device.Scene, "_through_host", refuse)
    rays = scene_rays(3000, seed=19)
    counts = ours.count_intersections(torch.from_numpy(rays).to(f"cuda:{device.cuda_device}"))
    assert isinstance(counts, np.ndarray) and counts.dtype == np.int32
    np.testing.assert_array_equal(counts, theirs.count_intersections(rays).numpy())
    assert counts.max() >= 2


def test_torch_cuda_rays_give_numpy():
    torch = pytest.importorskip("torch")
    theirs, ours, gpu = _cuda_scene()
    rays = scene_rays(1000, seed=18)
    hits = ours.cast_rays(torch.from_numpy(rays).to(f"cuda:{gpu.get_id()}"))
    assert isinstance(hits["t_hit"], np.ndarray)
    np.testing.assert_allclose(hits["t_hit"], theirs.cast_rays(rays)["t_hit"].numpy(), rtol=1e-4)
    assert isinstance(ours.compute_distance(torch.zeros((3, 3), device="cuda")), np.ndarray)
