"""vkray against Embree (embreex) on the shared meshes and on instanced scenes."""

import numpy as np
import pytest

import vkray
from oracle import (
    MESH_NAMES,
    barycentric_points,
    bounds,
    camera_rays,
    embree,
    load_mesh,
    random_rays,
    transform_points,
    triangle_normals,
)

_meshes = {}


def mesh_data(name):
    if name not in _meshes:
        _meshes[name] = load_mesh(name)
    return _meshes[name]


def rays_for(kind, vertices):
    if kind == "camera":
        origin, directions = camera_rays(vertices)
        return np.broadcast_to(origin, directions.shape).copy(), directions
    return random_rays(vertices, 65536, seed=1)


def assert_agrees_with_embree(hits, reference, vertices, faces, origins, directions):
    """The issue's bar: hit/miss agreement >= 99.99 %, the same triangle on >= 99.9 % of rays both
    hit, t within 1e-5 relative where both hit that triangle, uv and normal true to the triangle hit.
    (Where the two f32 tracers disagree on a ray grazing a shared edge, one may slip through a crack
    to a farther surface: those rays are the 0.1 % the triangle bar allows, and issue 4's exact
    tiers are the cure.)"""
    n = len(origins)
    embree_hit = reference["primID"] >= 0
    assert (hits.hit == embree_hit).mean() >= 0.9999, f"hit/miss differ on {(hits.hit != embree_hit).sum()} of {n}"
    both = hits.hit & embree_hit
    assert both.sum() > n // 10, "the rays must actually hit the mesh"
    same = both & (hits.prim_id == reference["primID"])
    assert same.sum() >= 0.999 * both.sum()
    # Both are f32 traversals: t agrees to a few f32 ulps of the mesh's size along the ray, but for
    # rays grazing their triangle, where f32 rounding of either is amplified (a handful of rays).
    _, radius = bounds(vertices)
    error = np.abs(hits.t[same] - reference["tfar"][same]) * np.linalg.norm(directions[same], axis=1)
    assert np.mean(error <= 1e-5 * radius) >= 0.999 and error.max() <= 1e-3 * radius
    assert np.all(np.isinf(hits.t[~hits.hit])) and np.all(hits.prim_id[~hits.hit] == -1)

    # uv: the barycentric point of the reported triangle is where the ray is at t.
    prim = hits.prim_id[both]
    at_t = origins[both] + hits.t[both, None].astype(np.float64) * directions[both]
    on_triangle = barycentric_points(vertices, faces, prim, hits.uv[both])
    assert np.abs(on_triangle - at_t).max() <= 1e-4 * radius
    assert np.all(hits.uv[both] >= -1e-6) and np.all(hits.uv[both].sum(axis=1) <= 1 + 1e-6)
    # normal: the unit normal of the reported triangle in its winding, and Embree's Ng direction.
    expected = triangle_normals(vertices, faces, prim)
    np.testing.assert_allclose(hits.normal[both], expected, atol=2e-4)
    ng = reference["Ng"][same].astype(np.float64)
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    np.testing.assert_allclose(hits.normal[same], ng, atol=2e-3)


@pytest.mark.parametrize("kind", ["camera", "random"])
@pytest.mark.parametrize("name", MESH_NAMES)
def test_shared_mesh_matches_embree(device, name, kind):
    vertices, faces = mesh_data(name)
    origins, directions = rays_for(kind, vertices)
    scene = device.scene(device.mesh(vertices, faces))
    hits = scene.intersect(origins, directions)
    reference = embree([(vertices, faces)], origins, directions)
    assert_agrees_with_embree(hits, reference, vertices, faces, origins, directions)
    assert np.all(hits.instance_id[hits.hit] == 0) and np.all(hits.custom_index[hits.hit] == 0)
    # The tests' own camera agrees with the broadcast form users write (one origin, many rays).
    if kind == "camera":
        again = scene.intersect(origins[0], directions, outputs=["t"])
        np.testing.assert_array_equal(again.t, hits.t)


def rotation(axis, angle):
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def affine(linear, translation):
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = translation
    return m


INSTANCE_TRANSFORMS = [
    affine(np.eye(3), [0.0, 0.0, 0.0]),
    affine(rotation([1, 2, 3], 0.7), [3.0, -1.0, 0.5]),
    affine(np.diag([2.0, 0.5, 1.3]), [-3.0, 1.0, -2.0]),  # non-uniform scale
    affine(np.diag([-1.0, 1.0, 1.0]) @ rotation([0, 1, 0], 1.1), [0.0, 3.0, 1.0]),  # mirrored
    affine(rotation([0, 0, 1], -0.4) @ np.diag([0.7, 1.6, 0.9]), [2.0, 2.5, -3.0]),
]


def test_instances_match_embree_on_baked_meshes(device):
    parts = [mesh_data("spot"), mesh_data("cow")]
    meshes = [device.mesh(v, f) for v, f in parts]
    scale = [1 / bounds(v)[1] for v, _ in parts]  # both meshes about unit size
    items, baked = [], []
    for i, m in enumerate(INSTANCE_TRANSFORMS):
        which = i % 2
        transform = m @ np.diag([scale[which]] * 3 + [1.0])
        items.append(vkray.Instance(meshes[which], transform, custom_index=1000 + i))
        v, f = parts[which]
        baked.append((transform_points(transform, v), f))
    scene = device.scene(items)
    all_vertices = np.concatenate([v for v, _ in baked])
    origins, directions = random_rays(all_vertices, 65536, seed=2)
    hits = scene.intersect(origins, directions)
    reference = embree(baked, origins, directions)

    embree_hit = reference["primID"] >= 0
    assert (hits.hit == embree_hit).mean() >= 0.9999
    both = hits.hit & embree_hit
    assert both.sum() > 4000
    same = both & (hits.instance_id == reference["geomID"]) & (hits.prim_id == reference["primID"])
    assert same.sum() >= 0.999 * both.sum()
    np.testing.assert_allclose(hits.t[same], reference["tfar"][same], rtol=1e-5)
    assert np.all(hits.custom_index[hits.hit] == 1000 + hits.instance_id[hits.hit])
    # Normals follow the transformed triangle, mirrored instances included.
    for i, (v, f) in enumerate(baked):
        rows = same & (hits.instance_id == i)
        assert rows.sum() > 100
        np.testing.assert_allclose(hits.normal[rows], triangle_normals(v, f, hits.prim_id[rows]), atol=2e-4)


def test_instance_mask_zero_hides_the_instance(device):
    v, f = mesh_data("spot")
    mesh = device.mesh(v, f)
    shift = affine(np.eye(3), [5.0, 0.0, 0.0])
    scene = device.scene([vkray.Instance(mesh, mask=0), vkray.Instance(mesh, shift, custom_index=7)])
    baked = [(transform_points(shift, v), f)]
    origins, directions = random_rays(np.concatenate([v, baked[0][0]]), 20000, seed=3)
    hits = scene.intersect(origins, directions)
    reference = embree(baked, origins, directions)
    assert (hits.hit == (reference["primID"] >= 0)).mean() >= 0.9999
    assert set(np.unique(hits.instance_id[hits.hit])) == {1}
    assert set(np.unique(hits.custom_index[hits.hit])) == {7}


def test_transform_3x4_equals_4x4(device):
    v, f = mesh_data("cow")
    mesh = device.mesh(v, f)
    m = INSTANCE_TRANSFORMS[1]
    origins, directions = random_rays(transform_points(m, v), 4096, seed=4)
    a = device.scene(vkray.Instance(mesh, m)).intersect(origins, directions)
    b = device.scene(vkray.Instance(mesh, m[:3])).intersect(origins, directions)
    np.testing.assert_array_equal(a.t, b.t)
    assert a.hit.sum() > 500
