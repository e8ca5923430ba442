"""Instances and what a query asks of them: facing and culling, instance flags, per-ray masks,
opacity. The answers follow from the geometry (which side a ray meets), in every tier."""

import numpy as np
import pytest

import vkray
from oracle import load_mesh, random_rays
from test_precision import tiers

TRIANGLE = ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])  # normal +z
FROM_ABOVE = ([0.2, 0.2, 1.0], [0.0, 0.0, -1.0])  # meets the front (the normal's side)
FROM_BELOW = ([0.2, 0.2, -1.0], [0.0, 0.0, 1.0])  # meets the back


def test_culling_follows_the_normal(device):
    scene = device.scene(device.mesh(*TRIANGLE))
    for tier in tiers(device):
        for cull, above, below in ((None, True, True), ("back", True, False), ("front", False, True)):
            assert scene.intersect(*FROM_ABOVE, cull=cull, precision=tier).hit == above, (tier, cull)
            assert scene.intersect(*FROM_BELOW, cull=cull, precision=tier).hit == below, (tier, cull)
            assert scene.occluded(*FROM_BELOW, cull=cull, precision=tier) == below, (tier, cull)
    with pytest.raises(ValueError, match="cull must be"):
        scene.intersect(*FROM_ABOVE, cull="both")


def test_instance_flags_flip_and_exempt(device):
    """x -> -x mirrors the triangle into x < 0 and reverses its winding: its normal becomes -z, so
    a ray from above meets its back. flip_facing swaps sides; cull_disable ignores culling."""
    mesh = device.mesh(*TRIANGLE)
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    cases = [
        (vkray.Instance(mesh), True),
        (vkray.Instance(mesh, flip_facing=True), False),
        (vkray.Instance(mesh, mirror), False),
        (vkray.Instance(mesh, mirror, flip_facing=True), True),
        (vkray.Instance(mesh, mirror, cull_disable=True), False),
    ]
    for instance, front_from_above in cases:
        scene = device.scene(instance)
        origin = [-0.2 if instance.transform is not None else 0.2, 0.2, 1.0]
        for tier in tiers(device):
            hits = scene.intersect(origin, FROM_ABOVE[1], cull="back", precision=tier)
            assert hits.hit == (front_from_above or instance.cull_disable), (tier, instance.flip_facing)
            if hits.hit and not instance.flip_facing:
                # The normal says which side is front: +z when the ray meets the front from above.
                assert np.sign(hits.normal[2]) == (1 if front_from_above else -1), tier


def test_per_ray_masks_select_instances(device):
    v, f = load_mesh("spot")
    mesh = device.mesh(v, f)
    size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    shifted = np.eye(4)
    shifted[0, 3] = 2 * size
    scene = device.scene([vkray.Instance(mesh, mask=0b01), vkray.Instance(mesh, shifted, mask=0b10)])
    origins, directions = random_rays(np.vstack([v, v + shifted[:3, 3]]), 4000, seed=51)
    masks = np.random.default_rng(52).integers(0, 4, len(origins)).astype(np.uint8)
    for tier in tiers(device):
        every = scene.intersect(origins, directions, precision=tier)
        # Masked rays see what the instances they may see would show alone.
        only = [device.scene([vkray.Instance(mesh)]), device.scene([vkray.Instance(mesh, shifted)])]
        alone = [s.intersect(origins, directions, precision=tier) for s in only]
        masked = scene.intersect(origins, directions, mask=masks, precision=tier)
        np.testing.assert_array_equal(masked.hit[masks == 0], False)
        np.testing.assert_array_equal(masked.prim_id[masks == 3], every.prim_id[masks == 3])
        for bit, hits in ((1, alone[0]), (2, alone[1])):
            np.testing.assert_array_equal(masked.prim_id[masks == bit], hits.prim_id[masks == bit])
        np.testing.assert_array_equal(scene.occluded(origins, directions, mask=masks, precision=tier), masked.hit)
        # One mask for every ray.
        one_mask = scene.intersect(origins, directions, mask=2, precision=tier)
        np.testing.assert_array_equal(one_mask.prim_id, alone[1].prim_id)
    with pytest.raises(ValueError, match="mask values"):
        scene.intersect(origins, directions, mask=256)
    with pytest.raises(ValueError, match="does not broadcast"):
        scene.intersect(origins, directions, mask=masks[:10])


def test_non_opaque_instances_are_still_hit(device):
    """Forcing an instance non-opaque sends its triangles through the shader's candidate path
    (ray query) or the any-hit slot (pipeline); with no any-hit program they are accepted, so
    the hits are those of the opaque instance."""
    v, f = load_mesh("cow")
    mesh = device.mesh(v, f)
    origins, directions = random_rays(v, 5000, seed=53)
    opaque = device.scene(vkray.Instance(mesh, opaque=True)).intersect(origins, directions)
    scene = device.scene(vkray.Instance(mesh, opaque=False))
    hits = scene.intersect(origins, directions)
    np.testing.assert_array_equal(hits.prim_id, opaque.prim_id)
    np.testing.assert_array_equal(hits.t, opaque.t)
    np.testing.assert_array_equal(scene.occluded(origins, directions), opaque.hit)
    with pytest.raises(TypeError, match="opaque must be"):
        vkray.Instance(mesh, opaque="yes")


def test_parts_of_one_mesh_are_told_apart(device):
    """Three parts in one BLAS (spot, the cow moved by a transform, the teapot): each hit names
    its part (geometry_id) and its triangle within the part, as the same parts placed as three
    instances do, in every tier."""
    parts = [load_mesh("spot"), load_mesh("cow"), load_mesh("teapot")]
    sizes = [np.linalg.norm(v.max(axis=0) - v.min(axis=0)) for v, _ in parts]
    moves = [np.eye(4) for _ in parts]
    for k in (1, 2):
        moves[k][0, 3] = 1.5 * sum(sizes[:k])
    moves[1][:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]  # and turned a quarter
    mesh = device.mesh_from_parts([(v, f, m) for (v, f), m in zip(parts, moves)])
    assert mesh.part_count == 3 and mesh.triangle_count == sum(len(f) for _, f in parts)
    placed = device.scene([vkray.Instance(device.mesh(v, f), m) for (v, f), m in zip(parts, moves)])
    scene = device.scene(mesh)
    origins, directions = random_rays(mesh.vertices, 20000, seed=54)
    for tier in tiers(device):
        a = scene.intersect(origins, directions, precision=tier, outputs=vkray.HIT_FIELDS)
        b = placed.intersect(origins, directions, precision=tier, outputs=vkray.HIT_FIELDS)
        assert set(np.unique(a.geometry_id[a.hit])) == {0, 1, 2}, tier
        assert (a.instance_id[a.hit] == 0).all() and (a.geometry_id[~a.hit] == -1).all()
        same = (a.geometry_id == b.instance_id) & (a.prim_id == b.prim_id)
        assert same.mean() > (0.999 if tier in ("fast", "refined") else 1 - 1e-12), tier
        hit = same & a.hit
        np.testing.assert_allclose(a.t[hit], b.t[hit], rtol=1e-5 if tier == "fast" else 1e-9)
        np.testing.assert_allclose(a.position[hit], b.position[hit], atol=1e-4 if tier == "fast" else 1e-9)
    with pytest.raises(vkray.UnsupportedError, match="single-part"):
        device.mesh_from_parts(parts, allow_update=True).update(mesh.vertices)
    with pytest.raises(ValueError, match="part 1: faces row 0"):
        device.mesh_from_parts([parts[0], (parts[1][0], [[0, 1, 10**6]])])
    with pytest.raises(TypeError, match="part 0 must be"):
        device.mesh_from_parts([parts[0][0]])
