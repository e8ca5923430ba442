"""Every hit along a ray (`Scene.intersect_all`), hit counts (`Scene.count`), inside tests
(`Scene.contains`) and `Mesh.is_closed`, in the CPU-exact tier (``precision="reference"``).

Each answer is checked against an independent one: a brute-force f64 test of every ray against
every triangle (oracle.all_hits_brute), the generalized winding number summed in numpy
(oracle.winding_numbers), or the analytic answer of a hand-built case (shared vertices and edges,
rays along edges and in faces' planes, coplanar copies, hits exactly at tmin and tmax, lattices of
points in line with a box's vertices and edges). The rule behind every hard case: each crossing of
a surface is reported exactly once, and distinct triangles at the same t are all reported.
"""

import functools
import threading

import numpy as np
import pytest

import vkray
from oracle import (
    all_hits_brute,
    bipyramid,
    bounds,
    box,
    directed_edges_closed,
    fan,
    heightfield,
    load_mesh,
    random_rays,
    rays_into_bipyramid,
    rays_through,
    shared_targets,
    surface_distance,
    triangle_normals,
    triangle_soup,
    voxel_surface,
    winding_numbers,
)

REF = "reference"
ALL_TIERS = ("fast", "refined", "exact", "reference")
SMALL_MESHES = ("spot", "cow", "fandisk")


@pytest.fixture(params=["reference", "exact"])
def tier(request, any_device):
    """The exact tiers, whose answers are the same: f64 on the CPU, and on the GPU (where the
    device runs the exact tier's intersection shaders)."""
    if request.param == "exact" and not _exact_on(any_device):
        pytest.skip("this device does not answer precision='exact'")
    return request.param


@functools.cache
def _mesh_data(name):
    if name == "soup":
        return triangle_soup(150, seed=31)
    return load_mesh(name)


def mesh_data(name):
    v, f = _mesh_data(name)
    return v.copy(), f.copy()


def field(hits, name):
    """A field of `AllHits[i]`, which may be a Hits-like object or a dict."""
    return hits[name] if isinstance(hits, dict) else getattr(hits, name)


def ray_slices(all_hits):
    off = all_hits.offsets
    return [slice(int(off[i]), int(off[i + 1])) for i in range(len(off) - 1)]


def check_structure(all_hits, shape):
    """The layout the spec promises: offsets, counts, ray_index; hits sorted by t then by
    (instance_id, geometry_id, prim_id); no triangle of an instance reported twice for one ray."""
    n = int(np.prod(shape, dtype=np.int64))
    off = all_hits.offsets
    assert off.dtype == np.int64 and off.shape == (n + 1,)
    assert off[0] == 0 and (np.diff(off) >= 0).all()
    h = int(off[-1])
    assert all_hits.counts.dtype == np.int64 and all_hits.counts.shape == tuple(shape)
    np.testing.assert_array_equal(all_hits.counts.reshape(-1), np.diff(off))
    assert all_hits.ray_index.dtype == np.int64 and all_hits.ray_index.shape == (h,)
    np.testing.assert_array_equal(all_hits.ray_index, np.repeat(np.arange(n), np.diff(off)))
    assert len(all_hits) == n
    real = np.float32 if all_hits.precision == "fast" else np.float64
    for name, dtype, tail in (
        ("t", real, ()),
        ("prim_id", np.int32, ()),
        ("instance_id", np.int32, ()),
        ("custom_index", np.int32, ()),
        ("geometry_id", np.int32, ()),
        ("uv", real, (2,)),
        ("normal", np.float32, (3,)),
        ("position", real, (3,)),
    ):
        array = getattr(all_hits, name)
        if array is not None:
            assert array.dtype == dtype and array.shape == (h,) + tail, name
    t = all_hits.t
    keys = [x for x in (all_hits.instance_id, all_hits.geometry_id, all_hits.prim_id) if x is not None]
    if t is not None and h:
        same_ray = all_hits.ray_index[1:] == all_hits.ray_index[:-1]
        assert (t[1:][same_ray] >= t[:-1][same_ray]).all(), "hits of a ray not sorted by t"
        tied = same_ray & (t[1:] == t[:-1])
        if keys and tied.any():
            a = np.stack([k[:-1][tied] for k in keys], axis=1).tolist()
            b = np.stack([k[1:][tied] for k in keys], axis=1).tolist()
            assert all(x < y for x, y in zip(a, b)), "ties at one t not ordered by (instance, geometry, prim)"
    if keys and h:
        rows = np.stack([all_hits.ray_index] + [k.astype(np.int64) for k in keys], axis=1)
        assert len(np.unique(rows, axis=0)) == h, "a triangle reported twice for one ray"


def placed_triangles(items):
    """World-space triangles of (vertices, faces, transform or None, parts) items in tie order,
    with their (instance_id, geometry_id, prim_id) keys. `parts` lists each part's triangle count
    (None: one part)."""
    tris, keys = [], []
    for instance, (v, f, m, parts) in enumerate(items):
        w = v if m is None else v @ m[:3, :3].T + m[:3, 3]
        tris.append(w[f])
        parts = parts or [len(f)]
        geometry = np.repeat(np.arange(len(parts)), parts)
        prim = np.concatenate([np.arange(p) for p in parts])
        keys.append(np.column_stack([np.full(len(f), instance), geometry, prim]))
    return np.concatenate(tris), np.concatenate(keys)


# Tolerances by tier: (how near an edge, the plane or tmin/tmax rounding decides, relative to the
# scene's size; t and position; uv). The f32 tiers decide which triangles are hit in f32, the
# refined tier then computes where in f64.
TOLERANCES = {
    "exact": (1e-9, 1e-12, 1e-9),
    "reference": (1e-9, 1e-12, 1e-9),
    "refined": (1e-5, 1e-12, 1e-9),
    "fast": (1e-5, 2e-6, 2e-4),
}


def compare_with_brute(all_hits, tris, keys, origins, directions, size, tmin=0.0, tmax=np.inf, keep=None):
    """Asserts that `all_hits` lists the oracle's hits ray for ray: the same triangles in the same
    order, t within 1e-12 of the scene's size, uv, normal and position alike (in the f64 tiers;
    `TOLERANCES` for the others). Rays with a hit that rounding could decide either way (within
    1e-9 of an edge, of the plane, or of tmin/tmax; 1e-5 where f32 decides) are left out; fewer
    than 2% may be. `keep` filters the oracle's hits (culling, masks)."""
    near_edge, t_tol, uv_tol = TOLERANCES[all_hits.precision]
    n = len(origins)
    ref = all_hits_brute(tris, origins, directions, tmin, tmax)
    if keep is not None:
        ref = {k: x[keep(ref)] for k, x in ref.items()}
    length = np.linalg.norm(directions, axis=1)
    lo = np.broadcast_to(np.asarray(tmin, float), (n,))
    hi = np.broadcast_to(np.asarray(tmax, float), (n,))
    everything = all_hits_brute(tris, origins, directions, np.maximum(lo - 1e-6, 0), hi + 1e-6)
    near = everything["margin"] < near_edge
    span = np.abs(everything["t"] - lo[everything["ray"]]) * length[everything["ray"]] < near_edge * size
    span |= np.abs(everything["t"] - hi[everything["ray"]]) * length[everything["ray"]] < near_edge * size
    ambiguous = np.zeros(n, bool)
    ambiguous[everything["ray"][near | span]] = True
    assert ambiguous.mean() < 0.03, f"{ambiguous.sum()} of {n} rays too near an edge for the test"
    ref_off = np.searchsorted(ref["ray"], np.arange(n + 1))
    zeros = np.zeros_like(all_hits.prim_id)
    key_fields = [zeros if x is None else x for x in (all_hits.instance_id, all_hits.geometry_id, all_hits.prim_id)]
    checked = 0
    for i, got in enumerate(ray_slices(all_hits)):
        if ambiguous[i]:
            continue
        want = slice(ref_off[i], ref_off[i + 1])
        want_keys = keys[ref["tri"][want]]
        got_keys = np.column_stack([k[got] for k in key_fields])
        t_ref, t_got = ref["t"][want], all_hits.t[got]
        assert len(got_keys) == len(want_keys), f"ray {i}: {len(got_keys)} hits, the oracle has {len(want_keys)}"
        # Two hits whose t differ by less than rounding may come in either order: compare in
        # key order then (a ray crossing where two soup triangles cross each other).
        close = np.diff(t_ref) * length[i] < max(near_edge, 1e-9) * size
        if close.any():
            a, b = np.lexsort(want_keys.T[::-1]), np.lexsort(got_keys.T[::-1])
        else:
            a = b = slice(None)
        np.testing.assert_array_equal(got_keys[b], want_keys[a], err_msg=f"ray {i}")
        np.testing.assert_allclose(t_got[b] * length[i], t_ref[a] * length[i], rtol=0, atol=t_tol * size)
        tri = tris[ref["tri"][want]][a]
        if all_hits.uv is not None:
            uv_ref = np.column_stack([ref["u"][want], ref["v"][want]])[a]
            np.testing.assert_allclose(all_hits.uv[got][b], uv_ref, rtol=0, atol=uv_tol, err_msg=f"ray {i}")
        if all_hits.normal is not None:
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            np.testing.assert_allclose(all_hits.normal[got][b], normal, rtol=0, atol=1e-6, err_msg=f"ray {i}")
        if all_hits.position is not None:
            position = origins[i] + np.outer(t_ref[a], directions[i])
            np.testing.assert_allclose(all_hits.position[got][b], position, rtol=0, atol=max(t_tol, 1e-9) * size)
        checked += len(t_ref)
    return checked


# --- 1. Against the brute-force oracle ----------------------------------------------------------


@pytest.mark.parametrize("name", SMALL_MESHES + ("soup",))
def test_every_hit_matches_brute_force(any_device, tier, name):
    v, f = mesh_data(name)
    scene = any_device.scene(any_device.mesh(v, f))
    centre, radius = bounds(v)
    origins, directions = random_rays(v, 200, seed=41)
    # Half the rays with their own interval, which cuts hits off at both ends.
    rng = np.random.default_rng(42)
    tmin = np.where(np.arange(200) % 2 == 0, 0.0, rng.uniform(0.0, 0.8, 200))
    tmax = np.where(np.arange(200) % 2 == 0, np.inf, tmin + rng.uniform(0.1, 1.0, 200))
    hits = scene.intersect_all(origins, directions, tmin=tmin, tmax=tmax, precision=tier, outputs=vkray.HIT_FIELDS)
    check_structure(hits, (200,))
    tris, keys = placed_triangles([(v, f, None, None)])
    checked = compare_with_brute(hits, tris, keys, origins, directions, radius, tmin, tmax)
    assert checked > 100  # most rays cross the mesh, several times
    assert (hits.custom_index == 0).all() and (hits.instance_id == 0).all() and (hits.geometry_id == 0).all()
    counts = scene.count(origins, directions, tmin=tmin, tmax=tmax, precision=tier)
    assert counts.dtype == np.int32 and counts.shape == (200,)
    np.testing.assert_array_equal(counts, hits.counts)
    # Default outputs are intersect's: no geometry_id, no position.
    default = scene.intersect_all(origins, directions, tmin=tmin, tmax=tmax, precision=tier)
    for name_ in vkray.DEFAULT_FIELDS:
        np.testing.assert_array_equal(getattr(default, name_), getattr(hits, name_))
    assert default.geometry_id is None and default.position is None
    np.testing.assert_array_equal(default.offsets, hits.offsets)


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _affine(linear=None, shift=(0, 0, 0)):
    m = np.eye(4)
    m[:3, :3] = np.eye(3) if linear is None else linear
    m[:3, 3] = shift
    return m


@pytest.mark.parametrize("n", [1, 13, 203])
def test_fast_every_hit_at_any_ray_count_and_mask(device, n):
    """Counts and all hits in the fast tier for ray counts that fill no whole packet (the CPU
    engine traces them in Embree's packets of 8 or 16, each hit filed under its lane), a mask a
    ray that varies lane to lane, against the brute-force oracle."""
    (v, f), (sv, sf) = mesh_data("spot"), mesh_data("soup")
    spot, soup = device.mesh(v, f), device.mesh(sv, sf)
    scene = device.scene([vkray.Instance(spot, None, mask=0x1), vkray.Instance(soup, None, mask=0x2)])
    tris, keys = placed_triangles([(v, f, None, None), (sv, sf, None, None)])
    world = tris.reshape(-1, 3)
    _, radius = bounds(world)
    origins, directions = random_rays(world, n, seed=45)
    masks = np.array([0x3, 0x1, 0x2, 0x3, 0x0, 0x2, 0x1][:n] * (n // 7 + 1), np.uint32)[:n]
    instance_masks = np.array([0x1, 0x2])
    hits = scene.intersect_all(origins, directions, precision="fast", mask=masks, outputs=vkray.HIT_FIELDS)
    check_structure(hits, (n,))
    seen = lambda r: (masks[r["ray"]] & instance_masks[keys[r["tri"], 0]]) != 0  # noqa: E731
    checked = compare_with_brute(hits, tris, keys, origins, directions, radius, keep=seen)
    assert checked >= (n // 2 if n > 1 else 0)
    np.testing.assert_array_equal(scene.count(origins, directions, precision="fast", mask=masks), hits.counts)
    assert (hits.counts[masks == 0] == 0).all()


@pytest.mark.parametrize("tier", ALL_TIERS)
def test_instances_match_brute_force(device, tier):
    """Every tier on both backends: instances moved, rotated, scaled and mirrored, a mesh of two
    parts (geometry_id), custom indices, an instance's mask, and culling: the oracle works on the
    triangles placed in the world (a mirror reverses their winding, so their normal and front side
    flip, as vkray's do)."""
    if tier == "exact" and not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    any_device = device
    v, f = mesh_data("spot")
    sv, sf = mesh_data("soup")
    pv, pf = triangle_soup(40, seed=43)
    spot = any_device.mesh(v, f)
    soup = any_device.mesh(sv, sf)
    parts = any_device.mesh_from_parts([(pv, pf[:25]), (pv, pf[25:])])
    transforms = [
        None,
        _affine(1.3 * _rotation([1, 2, 3], 0.7), [1.5, 0.2, -0.4]),
        _affine(np.diag([-1.0, 1.0, 1.0]), [-1.2, 0.0, 0.3]),  # a mirror
        _affine(_rotation([0, 1, 0], 2.0) @ np.diag([0.5, 2.0, 1.0]), [0.3, -1.0, 0.5]),
        _affine(np.eye(3), [0.0, 1.0, 1.0]),
    ]
    instances = [
        vkray.Instance(spot, transforms[0], custom_index=5),
        vkray.Instance(spot, transforms[1], custom_index=6),
        vkray.Instance(spot, transforms[2], custom_index=7),
        vkray.Instance(soup, transforms[3], custom_index=8),
        vkray.Instance(parts, transforms[4], custom_index=9, mask=0x2),
    ]
    scene = any_device.scene(instances)
    items = [(v, f, transforms[0], None), (v, f, transforms[1], None), (v, f, transforms[2], None),
             (sv, sf, transforms[3], None), (pv, pf, transforms[4], [25, 15])]
    tris, keys = placed_triangles(items)
    world = tris.reshape(-1, 3)
    centre, radius = bounds(world)
    origins, directions = random_rays(world, 200, seed=44)
    custom = np.array([5, 6, 7, 8, 9])
    for kwargs, keep in (
        ({}, None),
        ({"mask": 0x1}, lambda r: keys[r["tri"], 0] != 4),
        ({"cull": "back"}, lambda r: r["front"]),
        ({"cull": "front"}, lambda r: ~r["front"]),
    ):
        hits = scene.intersect_all(origins, directions, precision=tier, outputs=vkray.HIT_FIELDS, **kwargs)
        check_structure(hits, (200,))
        checked = compare_with_brute(hits, tris, keys, origins, directions, radius, keep=keep)
        assert checked > (100 if "cull" not in kwargs else 50), kwargs
        np.testing.assert_array_equal(hits.custom_index, custom[hits.instance_id])
        np.testing.assert_array_equal(scene.count(origins, directions, precision=tier, **kwargs), hits.counts)
    assert set(np.unique(hits.instance_id)) >= {0, 1, 2, 3}
    full = scene.intersect_all(origins, directions, precision=tier, outputs=["instance_id", "geometry_id"])
    assert set(np.unique(full.geometry_id[full.instance_id == 4])) == {0, 1}
    # Fields that need no vertices are written in one pass over the hits; with normals asked, field
    # by field (the path checked against brute force above): the same values.
    every = scene.intersect_all(origins, directions, precision=tier, outputs=vkray.HIT_FIELDS)
    lean_fields = [name for name in vkray.HIT_FIELDS if name not in ("normal", "position")]
    lean = scene.intersect_all(origins, directions, precision=tier, outputs=lean_fields)
    for name in ["offsets", "counts", "ray_index"] + lean_fields:
        np.testing.assert_array_equal(getattr(lean, name), getattr(every, name), err_msg=name)
        assert getattr(lean, name).dtype == getattr(every, name).dtype, name


def test_both_backends_give_the_reference_answer(device):
    """The reference tier runs on the CPU: the device's backend changes nothing."""
    v, f = mesh_data("cow")
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 100, seed=45)
    hits = scene.intersect_all(origins, directions, precision=REF)
    check_structure(hits, (100,))
    tris, keys = placed_triangles([(v, f, None, None)])
    compare_with_brute(hits, tris, keys, origins, directions, bounds(v)[1])


def test_batch_shapes_and_indexing(any_device, tier):
    """Rays broadcast like numpy: counts take the batch shape S, offsets and hits[i] index the
    flattened rays in C order; no rays, no hits and a single ray work too."""
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    origin = np.array([0.3, 0.4, -1.0])
    rng = np.random.default_rng(46)
    away = rng.uniform([-1.0, -1.0, -3.0], [1.0, 1.0, -2.0], (2, 1, 3))  # below the origin: a miss
    targets = np.concatenate([rng.uniform(0.05, 0.95, (2, 3, 3)), away], axis=1)
    directions = targets - origin  # (2, 4, 3): the last column misses the box
    hits = scene.intersect_all(origin, directions, precision=tier)
    check_structure(hits, (2, 4))
    np.testing.assert_array_equal(hits.counts, [[2, 2, 2, 0], [2, 2, 2, 0]])
    counts = scene.count(origin, directions, precision=tier)
    assert counts.shape == (2, 4) and counts.dtype == np.int32
    np.testing.assert_array_equal(counts, hits.counts)
    flat = directions.reshape(-1, 3)
    for i, s in enumerate(ray_slices(hits)):
        one = hits[i]
        np.testing.assert_array_equal(field(one, "t"), hits.t[s])
        np.testing.assert_array_equal(field(one, "prim_id"), hits.prim_id[s])
        alone = scene.intersect_all(origin, flat[i], precision=tier)
        np.testing.assert_array_equal(alone.t, hits.t[s])
    assert hits[3] is not None and len(field(hits[3], "t")) == 0
    # One ray: a 0-d batch.
    single = scene.intersect_all(origin, flat[0], precision=tier)
    assert single.counts.shape == () and single.offsets.tolist() == [0, 2]
    assert scene.count(origin, flat[0], precision=tier).shape == ()
    # No rays at all, and rays that all miss.
    empty = scene.intersect_all(np.zeros((0, 3)), [0, 0, 1], precision=tier)
    assert empty.counts.shape == (0,) and empty.offsets.tolist() == [0] and empty.t.shape == (0,)
    assert len(empty) == 0 and scene.count(np.zeros((0, 3)), [0, 0, 1], precision=tier).shape == (0,)
    miss = scene.intersect_all(np.full((5, 3), 5.0), [0, 0, 1], precision=tier, outputs=vkray.HIT_FIELDS)
    check_structure(miss, (5,))
    assert miss.offsets.tolist() == [0] * 6 and miss.t.shape == (0,) and miss.uv.shape == (0, 2)


def test_counts_are_made_from_the_offsets_at_first_use():
    """`AllHits.counts` comes from the offsets when first read (the core's difference on all
    cores): numpy's diff, at every length about the core's blocks, in the batch's shape."""
    rng = np.random.default_rng(9)
    for n in (0, 1, 2, 16383, 16384, 16385, 100_003):
        offsets = np.concatenate([[0], np.cumsum(rng.integers(0, 40, n))]).astype(np.int64)
        np.testing.assert_array_equal(vkray._core.counts_of_offsets(offsets), np.diff(offsets))
    offsets = np.array([0, 2, 2, 7, 9, 9, 12], dtype=np.int64)
    hits = vkray.AllHits((2, 3), {"offsets": offsets, "ray_index": np.repeat(np.arange(6), np.diff(offsets))}, "fast")
    assert hits.counts.dtype == np.int64 and hits.counts.tolist() == [[2, 0, 5], [2, 0, 3]]


def test_ray_indices_are_made_from_the_offsets_at_first_use(device):
    """A numpy answer comes without each hit's ray: `AllHits.ray_index` makes it from the offsets
    when first read (the core's on all cores: numpy's repeat, at every length about its blocks of
    4,096 rays), the same from several threads at once, and through pickling, old pickles too."""
    import pickle

    rng = np.random.default_rng(3)
    for n in (0, 1, 4095, 4096, 4097, 100_003):
        offsets = np.concatenate([[0], np.cumsum(rng.integers(0, 5, n))]).astype(np.int64)
        expected = np.repeat(np.arange(n, dtype=np.int64), np.diff(offsets))
        np.testing.assert_array_equal(vkray._core.ray_index_of_offsets(offsets), expected)
    for bad in ([1, 2], [0, 3, 2], []):
        with pytest.raises(ValueError, match="offsets"):
            vkray._core.ray_index_of_offsets(np.array(bad, dtype=np.int64))
    v, f = box()
    scene = device.scene(device.mesh(v, f))
    origins = np.column_stack([rng.uniform(-0.5, 1.5, (3000, 2)), np.full(3000, -1.0)])
    hits = scene.intersect_all(origins, [0, 0, 1], outputs=["t"])
    assert hits._ray_index is None
    inside = ((origins[:, :2] > 0) & (origins[:, :2] < 1)).all(axis=1)
    expected = np.repeat(np.arange(3000), np.where(inside, 2, 0))
    assert 1000 < expected.size < 6000
    made = []
    threads = [threading.Thread(target=lambda: made.append(hits.ray_index)) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for rays in made:
        np.testing.assert_array_equal(rays, expected)
    again = pickle.loads(pickle.dumps(hits))
    np.testing.assert_array_equal(again.ray_index, expected)
    old = hits.__getstate__()
    old["ray_index"] = old.pop("_ray_index") if old["_ray_index"] is not None else expected
    revived = vkray.AllHits.__new__(vkray.AllHits)
    revived.__setstate__(old)
    np.testing.assert_array_equal(revived.ray_index, expected)
    assert f"hits={expected.size}" in repr(again)


def test_outputs_ask_for_fields(any_device, tier):
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    hits = scene.intersect_all([0.3, 0.4, -1.0], [0, 0, 1], precision=tier, outputs=["t", "position", "geometry_id"])
    assert hits.uv is None and hits.normal is None and hits.custom_index is None
    np.testing.assert_allclose(hits.t, [1.0, 2.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(hits.position, [[0.3, 0.4, 0.0], [0.3, 0.4, 1.0]], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(hits.geometry_id, [0, 0])
    with pytest.raises(ValueError, match="unknown hit fields"):
        scene.intersect_all([0.3, 0.4, -1.0], [0, 0, 1], precision=tier, outputs=["t", "colour"])


# --- 2. Hard cases ------------------------------------------------------------------------------

OFFSETS = [0.0, 1e3, 1e5, 1e7]


def _ray_rounding(offset, directions):
    """How far rounding of the ray's own f64 origin and direction can move t (as in
    test_precision.py): a few ulps of the offset, over the direction's length."""
    return 8 * np.spacing(max(offset, 1.0)) / np.linalg.norm(directions, axis=-1)


@pytest.mark.parametrize("offset", OFFSETS)
def test_heightfield_vertices_and_edges_are_crossed_once(any_device, tier, offset):
    """Vertical rays (down from above and up from below) through every interior vertex and the
    midpoint of every interior edge (axis-aligned and diagonal) of a random heightfield: the surface
    covers each such point once, so exactly one hit, at the surface's height there. Then tilted
    rays through the same points: one hit each, at t = 1."""
    n = 10
    v, f, _ = heightfield(n, seed=47, offset=offset)
    scene = any_device.scene(any_device.mesh(v, f))
    targets = shared_targets(v, f, n)
    top = offset + 5.0
    for sign in (-1.0, 1.0):
        origins = targets.copy()
        origins[:, 2] = top if sign < 0 else offset - 5.0
        directions = np.broadcast_to([0.0, 0.0, sign], origins.shape)
        hits = scene.intersect_all(origins, directions, precision=tier, outputs=["t", "prim_id"])
        check_structure(hits, (len(targets),))
        bad = np.nonzero(hits.counts != 1)[0]
        assert len(bad) == 0, f"{len(bad)} of {len(targets)} vertical rays with counts {hits.counts[bad][:10]}"
        expected = np.abs(origins[:, 2] - targets[:, 2])
        np.testing.assert_allclose(hits.t, expected, rtol=0, atol=8 * np.spacing(max(offset, 8.0)))
        np.testing.assert_array_equal(scene.count(origins, directions, precision=tier), 1)
    origins, directions = rays_through(targets, seed=48)
    hits = scene.intersect_all(origins, directions, precision=tier, outputs=["t"])
    assert (hits.counts == 1).all(), f"{np.sum(hits.counts == 0)} misses, {np.sum(hits.counts > 1)} double hits"
    assert (np.abs(hits.t - 1.0) <= 1e-9 + _ray_rounding(offset, directions)).all()


@pytest.mark.parametrize("offset", OFFSETS)
def test_closed_fans_are_crossed_once(any_device, tier, offset):
    """A closed fan (as in test_precision.py), rays through its centre and every spoke's midpoint
    from random directions above: one hit each."""
    v, f = fan(offset)
    targets = np.repeat(np.vstack([v[0], 0.5 * (v[0] + v[1:])]), 20, axis=0)
    origins, directions = rays_through(targets, seed=50)
    scene = any_device.scene(any_device.mesh(v, f))
    hits = scene.intersect_all(origins, directions, precision=tier, outputs=["t", "prim_id"])
    assert (hits.counts == 1).all(), f"{np.sum(hits.counts == 0)} misses, {np.sum(hits.counts > 1)} double hits"
    assert (np.abs(hits.t - 1.0) <= 1e-9 + _ray_rounding(offset, directions)).all()
    np.testing.assert_array_equal(scene.count(origins, directions, precision=tier), 1)


@pytest.mark.parametrize("offset", OFFSETS)
def test_closed_solid_entered_through_vertices_and_edges(any_device, tier, offset):
    """Rays from outside a closed convex solid through its vertices and the midpoints of its edges,
    aimed at random points inside: they enter once (at t = 1) and leave once: exactly two hits."""
    v, f = bipyramid(offset)
    assert directed_edges_closed(f)
    origins, directions = rays_into_bipyramid(v, f, offset, per_target=8)
    scene = any_device.scene(any_device.mesh(v, f))
    hits = scene.intersect_all(origins, directions, precision=tier, outputs=["t", "prim_id"])
    bad = np.nonzero(hits.counts != 2)[0]
    assert len(bad) == 0, f"{len(bad)} of {len(origins)} rays, counts {hits.counts[bad][:10]}"
    first = hits.t[hits.offsets[:-1]]
    assert (np.abs(first - 1.0) <= 1e-9 + _ray_rounding(offset, directions)).all()
    np.testing.assert_array_equal(scene.count(origins, directions, precision=tier), 2)


def _in_plane(tris, origins, directions):
    """(N, F) bool: whether ray n lies in the plane of triangle f."""
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    parallel = np.abs(directions @ normal.T) == 0
    on = np.abs(np.einsum("fk,nfk->nf", normal, origins[:, None, :] - tris[None, :, 0])) == 0
    return parallel & on


def test_rays_in_a_faces_plane(any_device, tier):
    """A ray in a triangle's plane meets it in a segment: no hit from that triangle (what
    intersect(precision="reference") says too, checked here). Along the edges of a single
    triangle: no hit at all. Along the edges of a box and across its faces in their planes: no hit
    from the faces whose plane holds the ray; the ray only touches the closed box, so it meets it
    an even number of times (0 or 2: a touch is not a crossing, and an odd count would break the
    parity of `contains`); the first hit is intersect's."""
    tri_v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    scene = any_device.scene(any_device.mesh(tri_v, [[0, 1, 2]]))
    origins = np.array([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [2.0, -1.0, 0.0], [-1.0, 0.25, 0.0], [-1.0, -1.0, 0.0]])
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    assert not scene.intersect(origins, directions, precision=tier).hit.any()
    hits = scene.intersect_all(origins, directions, precision=tier)
    assert hits.counts.tolist() == [0] * 5 and hits.t.shape == (0,)
    np.testing.assert_array_equal(scene.count(origins, directions, precision=tier), 0)

    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    rays = []
    for lo in np.array(np.meshgrid([0.0, 1.0], [0.0, 1.0], indexing="ij")).reshape(2, -1).T:
        for axis in range(3):  # the 12 edges, from beyond either end
            others = [a for a in range(3) if a != axis]
            for start, step in ((-1.0, 1.0), (2.0, -1.0)):
                o, d = np.zeros(3), np.zeros(3)
                o[others], o[axis], d[axis] = lo, start, step
                rays.append((o, d))
    for axis in range(3):  # across each face's plane, along and diagonally to the other axes
        for level in (0.0, 1.0):
            for along in range(3):
                if along == axis:
                    continue
                across = 3 - axis - along
                for x in (0.3, 0.5):
                    o, d = np.zeros(3), np.zeros(3)
                    o[axis], o[across], o[along], d[along] = level, x, -1.0, 1.0
                    rays.append((o, d))
                o, d = np.zeros(3), np.zeros(3)
                o[axis], o[across], o[along] = level, -1.0, -1.0
                d[across], d[along] = 1.0, 1.0  # the face's diagonal direction, through its corners
                rays.append((o, d))
    origins = np.array([o for o, _ in rays])
    directions = np.array([d for _, d in rays])
    hits = scene.intersect_all(origins, directions, precision=tier)
    check_structure(hits, (len(rays),))
    assert (hits.counts % 2 == 0).all(), f"odd counts for rays {np.nonzero(hits.counts % 2)[0]}"
    in_plane = _in_plane(v[f], origins, directions)
    assert in_plane.any(axis=1).all()
    assert not in_plane[hits.ray_index, hits.prim_id].any(), "a face hit by a ray in its own plane"
    closest = scene.intersect(origins, directions, precision=tier)
    np.testing.assert_array_equal(hits.counts > 0, closest.hit)
    first = hits.offsets[:-1][hits.counts > 0]
    np.testing.assert_array_equal(hits.prim_id[first], closest.prim_id[closest.hit])
    np.testing.assert_array_equal(hits.t[first], closest.t[closest.hit])


def test_rays_along_the_faces_of_the_bounding_box(any_device, tier):
    """Rays with a zero direction component whose origin lies on a face of the scene's bounding
    box (after re-centring): the crossing they make is reported, in every exact tier alike (the
    CPU's boxes once lost it: 0 * inf is NaN)."""
    scene = any_device.scene(any_device.mesh([[0.0, 0, 1], [1, 0, 1], [1, 1, 1]], [[0, 1, 2]]))
    o = [[0.5, 0.0, 2.0], [0.5, 1e-17, 2.0], [0.5, -1.0, 2.0]]
    d = [[0.0, 0, -1], [0.0, 0, -1], [0.0, 1, -1]]
    np.testing.assert_array_equal(scene.count(o, d, precision=tier), [1, 1, 1])
    cube = any_device.scene(any_device.mesh(*box()))
    xs = np.linspace(0.1, 0.9, 9)
    for plane in ([xs, np.zeros(9)], [np.zeros(9), xs], [xs, np.ones(9)], [np.ones(9), xs]):
        origins = np.column_stack(plane + [np.full(9, 2.0)])
        counts = cube.count(origins, [0.0, 0.0, -1.0], precision=tier)
        np.testing.assert_array_equal(counts, cube.count(origins, [0.0, 0.0, -1.0], precision="exact"
                                                         if _exact_on(any_device) else tier))
        assert set(counts.tolist()) <= {0, 2}, counts


def test_coplanar_copies_are_all_reported(any_device, tier):
    """The same triangle four times (copied, its corners rotated, its winding reversed): four hits
    at one t, by prim_id. Two copies of a split square (the second with reversed winding), a ray
    through the shared diagonal: one hit per copy."""
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    f = np.array([[0, 1, 2], [0, 1, 2], [1, 2, 0], [0, 2, 1]])
    scene = any_device.scene(any_device.mesh(v, f))
    hits = scene.intersect_all([0.2, 0.3, 1.0], [0, 0, -1], precision=tier, outputs=vkray.HIT_FIELDS)
    assert hits.prim_id.tolist() == [0, 1, 2, 3]
    assert hits.t.tolist() == [1.0] * 4
    np.testing.assert_allclose(hits.normal[:, 2], [1, 1, 1, -1])
    square = np.array([[0, 1, 3], [0, 3, 2], [0, 3, 1], [0, 2, 3]])
    scene = any_device.scene(any_device.mesh(v, square))
    rng = np.random.default_rng(53)
    s = rng.uniform(0.05, 0.95, 50)
    origins = np.column_stack([s, s, np.ones(50)])
    hits = scene.intersect_all(origins, [0, 0, -1], precision=tier)
    assert (hits.counts == 2).all()
    layer = hits.prim_id.reshape(-1, 2) // 2
    assert (layer == [0, 1]).all() and (hits.t == 1.0).all()


def test_ties_order_by_instance_geometry_prim(any_device, tier):
    """Distinct triangles at one t come in (instance_id, geometry_id, prim_id) order: a mesh of two
    parts, each holding the triangle (part 0 twice), placed twice in one place, then a mesh whose
    only copy is prim 0 and another whose copy is prim 1: 8 hits, all at t = 1."""
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    elsewhere = tri + [5.0, 5.0, 0.0]
    parts = any_device.mesh_from_parts([(tri, [[0, 1, 2], [0, 1, 2]]), (tri, [[0, 2, 1]])])
    second = any_device.mesh(np.vstack([elsewhere, tri]), [[0, 1, 2], [3, 4, 5]])
    first = any_device.mesh(tri, [[0, 1, 2]])
    scene = any_device.scene([second, parts, parts, first])
    hits = scene.intersect_all([0.2, 0.3, 1.0], [0, 0, -1], precision=tier, outputs=vkray.HIT_FIELDS)
    got = list(zip(hits.instance_id.tolist(), hits.geometry_id.tolist(), hits.prim_id.tolist()))
    assert got == [(0, 0, 1), (1, 0, 0), (1, 0, 1), (1, 1, 0), (2, 0, 0), (2, 0, 1), (2, 1, 0), (3, 0, 0)]
    assert (hits.t == 1.0).all()
    closest = scene.intersect([0.2, 0.3, 1.0], [0, 0, -1], precision=tier, outputs=vkray.HIT_FIELDS)
    assert (closest.instance_id, closest.geometry_id, closest.prim_id) == (0, 0, 1)
    for k in (1, 3, 8, 20):
        some = scene.intersect_all([0.2, 0.3, 1.0], [0, 0, -1], precision=tier, max_hits=k, outputs=vkray.HIT_FIELDS)
        kept = list(zip(some.instance_id.tolist(), some.geometry_id.tolist(), some.prim_id.tolist()))
        assert kept == got[:k]


def test_rays_starting_on_a_surface(any_device, tier):
    """tmin = 0 is inclusive: an origin on a surface hits it at t = 0, in both directions. From the
    centre of a box's face (on the diagonal that splits it: one of its two triangles), inwards:
    that face at t = 0, then the opposite one; outwards: that face only. Not once tmin > 0."""
    scene = any_device.scene(any_device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    hits = scene.intersect_all([[0.25, 0.25, 0.0]] * 2, [[0, 0, 1], [0, 0, -1]], precision=tier)
    assert hits.counts.tolist() == [1, 1] and hits.t.tolist() == [0.0, 0.0]
    assert scene.count([0.25, 0.25, 0.0], [0, 0, 1], tmin=1e-9, precision=tier) == 0
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    hits = scene.intersect_all([[0.5, 0.5, 0.0]] * 2, [[0, 0, 1], [0, 0, -1]], precision=tier)
    assert hits.counts.tolist() == [2, 1] and hits.t.tolist() == [0.0, 1.0, 0.0]
    assert scene.count([0.5, 0.5, 0.0], [0, 0, 1], tmin=1e-9, precision=tier) == 1
    # A corner and an edge of the box, looking in: 2 hits (out through the far side).
    hits = scene.intersect_all([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]], [[1, 1, 1], [0, 1, 1]], precision=tier)
    assert hits.counts.tolist() == [2, 2]
    np.testing.assert_allclose(hits.t, [0.0, 1.0, 0.0, 1.0], rtol=0, atol=1e-15)


def test_rays_from_anywhere_on_a_face_report_t0_or_not_at_all(any_device, tier):
    """Rays starting exactly on a box's faces (one coordinate 0 or 1) or on the slanted triangle
    x + y + z = 1 (dyadic coordinates, so the sum is exact), in random directions. The exact t of
    the surface they start on is 0, but the f64 test computes it within rounding of 0 (~1e-17),
    and the closed interval [0, inf) keeps it only where it rounds to >= 0: the documented answer
    is that the starting surface is reported at |t| <= 1e-15 or not at all, and every other
    crossing is reported (use `offset_origins`, or `contains` for points on a surface). Before
    this was decided, 68 of 300 rays into the box lost the t = 0 hit."""
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    rng = np.random.default_rng(61)
    n = 300
    origins = rng.uniform(0.0, 1.0, (n, 3))
    axis = rng.integers(0, 3, n)
    level = rng.integers(0, 2, n).astype(float)
    origins[np.arange(n), axis] = level
    directions = rng.normal(size=(n, 3))
    inwards = np.where(level == 0, 1.0, -1.0)
    directions[np.arange(n), axis] = np.abs(directions[np.arange(n), axis]) * inwards
    for sign, count in ((1.0, 2), (-1.0, 1)):  # into the box, then out of it
        d = directions.copy()
        d[np.arange(n), axis] *= sign
        hits = scene.intersect_all(origins, d, precision=tier, outputs=["t"])
        at_origin = np.zeros(n, int)
        np.add.at(at_origin, hits.ray_index, np.abs(hits.t) <= 1e-15)
        assert at_origin.max() <= 1
        np.testing.assert_array_equal(hits.counts - at_origin, count - 1)
    scene = any_device.scene(any_device.mesh(np.eye(3), [[0, 1, 2]]))
    xy = rng.integers(1, 512, (n, 2)) / 1024.0
    origins = np.column_stack([xy, 1.0 - xy.sum(axis=1)])
    assert (origins.sum(axis=1) == 1.0).all()
    hits = scene.intersect_all(origins, rng.normal(size=(n, 3)), precision=tier, outputs=["t"])
    assert (hits.counts <= 1).all()
    assert np.abs(hits.t).max() <= 1e-12  # rounding grows as directions graze the plane


def test_hits_exactly_at_tmin_and_tmax(any_device, tier):
    """Four stacked squares at z = 0, 1, 2, 3, a ray down from z = 4: hits at t = 1, 2, 3, 4.
    [1, 3] holds three of them (both ends included), one f64 ulp inside either end drops them,
    [2, 2] holds one."""
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    v = np.vstack([np.column_stack([square, np.full(4, z)]) for z in range(4)])
    f = np.vstack([[[4 * z, 4 * z + 1, 4 * z + 2], [4 * z, 4 * z + 2, 4 * z + 3]] for z in range(4)])
    scene = any_device.scene(any_device.mesh(v, f))
    o, d = [0.25, 0.6, 4.0], [0.0, 0.0, -1.0]
    cases = [
        (0.0, np.inf, [1, 2, 3, 4]),
        (1.0, 3.0, [1, 2, 3]),
        (float(np.nextafter(1.0, 2.0)), float(np.nextafter(3.0, 0.0)), [2]),
        (2.0, 2.0, [2]),
        (4.0, 10.0, [4]),
        (float(np.nextafter(4.0, 5.0)), 10.0, []),
    ]
    tmin = np.array([c[0] for c in cases])
    tmax = np.array([c[1] for c in cases])
    hits = scene.intersect_all(np.broadcast_to(o, (len(cases), 3)), d, tmin=tmin, tmax=tmax, precision=tier)
    for i, (lo, hi, expected) in enumerate(cases):
        assert field(hits[i], "t").tolist() == expected, (lo, hi)
    np.testing.assert_array_equal(scene.count(np.broadcast_to(o, (len(cases), 3)), d, tmin=tmin, tmax=tmax,
                                              precision=tier), [len(c[2]) for c in cases])


# --- 3. max_hits --------------------------------------------------------------------------------


def test_max_hits_keeps_the_nearest(any_device, tier):
    """max_hits=k: each ray's first k hits of the full list (counts min(count, k)); max_hits=1 is
    intersect(precision="reference") hit for hit, and a ray without hits has none."""
    v, f = mesh_data("spot")
    mesh = any_device.mesh(v, f)
    move = _affine(np.eye(3), [0.3, 0.1, 0.0])
    scene = any_device.scene([mesh, vkray.Instance(mesh, move)])  # overlapping copies: many hits
    origins, directions = random_rays(v, 300, seed=54)
    full = scene.intersect_all(origins, directions, precision=tier)
    assert full.counts.max() >= 4
    for k in (1, 2, 3, np.int64(4), 10**9):
        part = scene.intersect_all(origins, directions, precision=tier, max_hits=k)
        check_structure(part, (300,))
        np.testing.assert_array_equal(part.counts, np.minimum(full.counts, int(k)))
        keep = np.concatenate([np.arange(s.start, min(s.stop, s.start + int(k))) for s in ray_slices(full)])
        for name in vkray.DEFAULT_FIELDS:
            np.testing.assert_array_equal(getattr(part, name), getattr(full, name)[keep], err_msg=f"{name}, k={k}")
    one = scene.intersect_all(origins, directions, precision=tier, max_hits=1)
    closest = scene.intersect(origins, directions, precision=tier)
    np.testing.assert_array_equal(one.counts, closest.hit.astype(np.int64))
    for name in ("t", "prim_id", "instance_id"):
        np.testing.assert_array_equal(getattr(one, name), getattr(closest, name)[closest.hit], err_msg=name)
    assert not closest.hit.all()  # some rays miss


# --- 4. contains --------------------------------------------------------------------------------


def _points_around(v, f, n_box, n_surface, seed):
    """Uniform points in the bounding box grown by 10%, and points 1e-4 of the mesh's size off
    random surface points, on either side."""
    rng = np.random.default_rng(seed)
    lo, hi = v.min(axis=0), v.max(axis=0)
    pad = 0.1 * (hi - lo)
    box_points = rng.uniform(lo - pad, hi + pad, (n_box, 3))
    prim = rng.integers(0, len(f), n_surface)
    uv = rng.dirichlet([1, 1, 1], n_surface)
    tri = v[f[prim]]
    on = np.einsum("nk,nkd->nd", uv, tri)
    side = np.where(rng.random(n_surface) < 0.5, -1.0, 1.0)
    near = on + (side * 1e-4 * bounds(v)[1])[:, None] * triangle_normals(v, f, prim)
    return np.vstack([box_points, near])


@pytest.mark.parametrize("name", SMALL_MESHES)
def test_contains_matches_the_winding_number_on_closed_meshes(any_device, tier, name):
    v, f = mesh_data(name)
    mesh = any_device.mesh(v, f)
    assert mesh.is_closed
    scene = any_device.scene(mesh)
    points = _points_around(v, f, 200, 100, seed=55)
    w = winding_numbers(v, f, points)
    far = surface_distance(v, f, points) > 1e-9
    assert far.mean() > 0.99
    # The oracle itself: a closed mesh's winding number is an integer away from its surface.
    assert np.abs(w - np.round(w))[far].max() < 1e-6
    parity = np.round(w).astype(int) % 2 == 1
    winding = w >= 0.5
    assert 0.2 < parity.mean() < 0.8
    for method, expected in (("parity", parity), ("winding", winding)):
        inside = scene.contains(points, precision=tier, method=method)
        assert inside.dtype == np.bool_ and inside.shape == (len(points),)
        wrong = np.nonzero((inside != expected) & far)[0]
        assert len(wrong) == 0, f"{method}: {len(wrong)} wrong, e.g. points {points[wrong[:3]]}, w {w[wrong[:3]]}"
    np.testing.assert_array_equal(scene.contains(points), scene.contains(points, precision=tier, method="parity"))


def _lattice(values):
    return np.array(np.meshgrid(values, values, values, indexing="ij")).reshape(3, -1).T


def _check_contains(scene, points, expected, on_surface):
    """contains == expected for both methods; every method's wrong points are reported (and how
    many lie on the surface) before failing. Points on the surface are judged by parity only: the
    spec puts "points exactly on the surface count as inside" with the parity method (the winding
    number is exactly 1/2 on a face, less at a convex edge or vertex); the winding number on the
    surface has its own test below."""
    problems = []
    for method in ("parity", "winding"):
        inside = scene.contains(points, precision=REF, method=method)
        judged = np.ones(len(points), bool) if method == "parity" else ~on_surface
        wrong = np.nonzero((inside != expected) & judged)[0]
        if len(wrong):
            problems.append(
                f"{method}: {len(wrong)} of {judged.sum()} wrong ({on_surface[wrong].sum()} of them on the "
                f"surface), e.g. {points[wrong[:6]].tolist()} (expected {expected[wrong[:6]].tolist()})"
            )
    assert not problems, "; ".join(problems)


@pytest.mark.parametrize("offset", [0.0, 1e5])
def test_contains_on_a_lattice_around_a_box(any_device, offset):
    """A unit box and the points of a half-unit lattice from -1 to 2: each is in line with the box's
    vertices, edges and faces along the axes and the diagonals, whatever ray direction `contains`
    takes. Inside exactly when every coordinate is in [0, 1] (points on the surface are inside)."""
    v, f = box()
    scene = any_device.scene(any_device.mesh(v + offset, f))
    local = _lattice(np.arange(-1.0, 2.01, 0.5))
    expected = ((local >= 0) & (local <= 1)).all(axis=1)
    interior = ((local > 0) & (local < 1)).all(axis=1)
    _check_contains(scene, local + offset, expected, expected & ~interior)


def _solids():
    occupied = np.ones((2, 2, 2), bool)
    occupied[1, 1, 1] = False
    ov, of = box((0, 0, 0), (3, 3, 3))
    iv, inner = box((1, 1, 1), (2, 2, 2))
    return {
        "box": (*box(), lambda p: ((p >= 0) & (p <= 1)).all(axis=1), np.arange(-1.0, 2.01, 0.5)),
        "seven eighths": (
            *voxel_surface(occupied),
            lambda p: ((p >= 0) & (p <= 2)).all(axis=1) & ~(p > 1).all(axis=1),
            np.arange(-0.5, 2.51, 0.5),
        ),
        "cavity": (np.vstack([ov, iv]), np.vstack([of, inner[:, ::-1] + 8]),
                   lambda p: ((p >= 0) & (p <= 3)).all(axis=1) & ~((p > 1) & (p < 2)).all(axis=1),
                   np.arange(-0.5, 3.51, 0.5)),
    }


@pytest.mark.parametrize("solid", ["box", "seven eighths", "cavity"])
def test_crossings_along_axes_and_diagonals_have_the_right_parity(any_device, tier, solid):
    """Whatever direction `contains` picks, the crossings it counts must be right along every
    direction: from every lattice point off the surface, rays along the 26 axis, face-diagonal and
    space-diagonal directions run through the solid's vertices and edges and along its faces. A
    ray from inside crosses the surface an odd number of times, from outside an even number."""
    v, f, inside, values = _solids()[solid]
    scene = any_device.scene(any_device.mesh(v, f))
    points = _lattice(values)
    directions = _lattice([-1.0, 0.0, 1.0])
    directions = directions[np.abs(directions).sum(axis=1) > 0]
    # On the surface: inside, with a neighbour a hair away outside.
    on_surface = inside(points) & np.any([~inside(points + 1e-6 * e) for e in directions], axis=0)
    points = points[~on_surface]
    o = np.repeat(points, len(directions), axis=0)
    d = np.tile(directions, (len(points), 1))
    counts = scene.count(o, d, precision=tier)
    expected = np.repeat(inside(points), len(directions))
    wrong = np.nonzero(counts % 2 != expected)[0]
    example = f"from {o[wrong[:4]].tolist()} along {d[wrong[:4]].tolist()}"
    assert len(wrong) == 0, f"{len(wrong)} of {len(o)} rays, e.g. {example}"


def test_contains_counts_points_on_the_surface_as_inside(any_device, tier):
    """Random points exactly on the box's faces, its face centres, edge midpoints and vertices:
    inside, by parity. Points 1e-12 off the surface, outside: inside, by either method."""
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    points = _box_surface_points(seed=56)
    inside = scene.contains(points, precision=tier, method="parity")
    assert inside.all(), f"parity: {np.sum(~inside)} of {len(points)} outside, e.g. {points[~inside][:6].tolist()}"
    eps = 1e-12
    outside = np.array([[-eps, 0.5, 0.5], [0.5, 1 + eps, 0.5], [0.5, 0.5, -eps], [1 + eps, 1 + eps, 1 + eps],
                        [0.3, -eps, 0.2], [1 + eps, 0.5, 0.0]])
    for method in ("parity", "winding"):
        assert not scene.contains(outside, precision=tier, method=method).any(), method


def _box_surface_points(seed):
    rng = np.random.default_rng(seed)
    faces = []
    for axis in range(3):
        for level in (0.0, 1.0):
            p = rng.uniform(0.0, 1.0, (20, 3))
            p[:, axis] = level
            faces.append(p)
    centres = _lattice([0.0, 0.5, 1.0])
    centres = centres[(centres == 0.5).sum(axis=1) <= 2]  # face centres, edge midpoints, vertices
    return np.vstack(faces + [centres])


def test_winding_counts_points_on_the_surface_as_inside(any_device, tier):
    """Spec ambiguity, resolved as "contains means the closed solid whatever the method": points
    exactly on the surface count as inside by the winding number too (the box's faces, edges and
    vertices; the bunny's vertices). The raw winding number there is 1/2 on a face (either side of
    1/2 by rounding), 1/4 on the box's edges and 1/8 at its corners."""
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    points = _box_surface_points(seed=59)
    inside = scene.contains(points, precision=tier, method="winding")
    problems = [] if inside.all() else [f"box: {np.sum(~inside)} of {len(points)} outside, e.g. "
                                        f"{points[~inside][:6].tolist()}"]
    bv, bf = mesh_data("stanford-bunny")
    bunny = any_device.scene(any_device.mesh(bv, bf))
    on = bv[bf[np.random.default_rng(60).integers(0, len(bf), 20), 0]]  # vertices: exactly on the surface
    inside = bunny.contains(on, precision=tier, method="winding")
    if not inside.all():
        problems.append(f"bunny: {np.sum(~inside)} of {len(on)} vertices outside")
    assert not problems, "; ".join(problems)


def test_contains_with_a_cavity(any_device):
    """An outer box with an inner box of reversed winding (the cavity's walls face into it): the
    cavity is outside (parity: two walls crossed; winding number 1 - 1 = 0); its walls count as
    inside."""
    ov, of = box((0, 0, 0), (3, 3, 3))
    iv, inner = box((1, 1, 1), (2, 2, 2))
    v = np.vstack([ov, iv])
    f = np.vstack([of, inner[:, ::-1] + len(ov)])
    mesh = any_device.mesh(v, f)
    assert mesh.is_closed
    scene = any_device.scene(mesh)
    points = _lattice(np.arange(-0.5, 3.51, 0.5))
    in_outer = ((points >= 0) & (points <= 3)).all(axis=1)
    in_cavity = ((points > 1) & (points < 2)).all(axis=1)
    expected = in_outer & ~in_cavity
    interior = ((points > 0) & (points < 3)).all(axis=1) & ~((points >= 1) & (points <= 2)).all(axis=1)
    assert in_cavity.sum() == 1 and expected.sum() > 100
    off_walls = ~np.isin(points, [0.0, 1.0, 2.0, 3.0]).any(axis=1)
    w = winding_numbers(v, f, points[off_walls])  # the oracle agrees away from the walls
    np.testing.assert_array_equal(w >= 0.5, expected[off_walls])
    _check_contains(scene, points, expected, expected & ~interior)


def test_contains_in_a_box_missing_an_octant(any_device):
    """Seven eighths of a 2-unit box (a closed, non-convex mesh of unit squares): inside where
    every coordinate is in [0, 2] and not all are above 1 (the missing octant's walls are inside)."""
    occupied = np.ones((2, 2, 2), bool)
    occupied[1, 1, 1] = False
    v, f = voxel_surface(occupied)
    assert directed_edges_closed(f)
    mesh = any_device.mesh(v, f)
    assert mesh.is_closed
    scene = any_device.scene(mesh)
    points = _lattice(np.arange(-0.5, 2.51, 0.5))
    expected = ((points >= 0) & (points <= 2)).all(axis=1) & ~(points > 1).all(axis=1)
    interior = ((points > 0) & (points < 2)).all(axis=1) & ~(points >= 1).all(axis=1)
    _check_contains(scene, points, expected, expected & ~interior)


def test_open_meshes_need_the_winding_number(any_device, tier):
    """The bunny has holes: parity would depend on the ray's direction, so it is refused with a
    message naming both the problem and the way out; the winding number answers as numpy's does."""
    v, f = mesh_data("stanford-bunny")
    bunny = any_device.mesh(v, f)
    assert bunny.is_closed is False
    cube = any_device.mesh(*box())
    scale = _affine(10.0 * np.eye(3), [1.0, -2.0, 0.5])
    for scene in (any_device.scene(bunny), any_device.scene([cube, vkray.Instance(bunny, scale)])):
        for kwargs in ({}, {"method": "parity"}, {"precision": REF, "method": "parity"}):
            with pytest.raises(ValueError) as error:
                scene.contains([[0.0, 0.1, 0.0]], **kwargs)
            message = str(error.value)
            assert "closed" in message and "winding" in message, message
    points = _points_around(v, f, 60, 40, seed=58)
    w = winding_numbers(v, f, points)
    sure = (surface_distance(v, f, points) > 1e-9) & (np.abs(w - 0.5) > 1e-6)
    assert sure.mean() > 0.95
    scene = any_device.scene(bunny)
    inside = scene.contains(points, precision=tier, method="winding")
    np.testing.assert_array_equal(inside[sure], (w >= 0.5)[sure])
    # Placed by an instance (scaled 10 times, moved): the same answers at the moved points.
    placed = any_device.scene([vkray.Instance(bunny, scale)])
    moved = points @ scale[:3, :3].T + scale[:3, 3]
    np.testing.assert_array_equal(placed.contains(moved, precision=tier, method="winding")[sure], (w >= 0.5)[sure])


def _inside_boxes(points, transforms, tolerance=0.0):
    """Whether each point is in any of the unit boxes that the transforms place (closed), whether
    it is strictly inside one, and whether it is within `tolerance` (in box units) of a box's
    surface."""
    inside = np.zeros(len(points), bool)
    strictly = np.zeros(len(points), bool)
    near = np.zeros(len(points), bool)
    for m in transforms:
        local = (points - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T
        inside |= ((local >= 0) & (local <= 1)).all(axis=1)
        strictly |= ((local > 0) & (local < 1)).all(axis=1)
        within = ((local >= -tolerance) & (local <= 1 + tolerance)).all(axis=1)
        near |= within & ~((local > tolerance) & (local < 1 - tolerance)).all(axis=1)
    return inside, strictly, near


def test_contains_in_any_of_several_instances(any_device):
    """Boxes apart, overlapping (a point in two boxes is inside: per instance, not the parity of the
    whole scene's crossings), moved, rotated and scaled, and mirrored."""
    cube = any_device.mesh(*box())
    transforms = [
        _affine(),
        _affine(np.eye(3), [3.0, 0.0, 0.0]),
        _affine(np.eye(3), [0.5, 0.5, 0.5]),  # overlaps the first
        _affine(2.0 * _rotation([0, 0, 1], np.pi / 4), [0.0, 5.0, 0.0]),
        _affine(np.diag([-1.0, 1.0, 1.0]), [-2.0, 0.0, 0.0]),  # a mirror: x in [-3, -2]
    ]
    points = np.array(np.meshgrid(np.arange(-3.5, 4.51, 0.25), np.arange(-0.5, 8.01, 0.25),
                                  np.arange(-0.5, 2.01, 0.25), indexing="ij")).reshape(3, -1).T
    _, _, near_rotated = _inside_boxes(points, transforms[3:4], tolerance=1e-9)
    points = points[~near_rotated]  # rounding decides those
    both = ((points >= 0.5) & (points <= 1)).all(axis=1)
    assert both.sum() > 5
    for count in (5, 4):  # with the mirror, then without it
        expected, strictly, _ = _inside_boxes(points, transforms[:count])
        assert expected.sum() > 200 and expected[both].all()
        scene = any_device.scene([vkray.Instance(cube, m) for m in transforms[:count]])
        _check_contains(scene, points, expected, expected & ~strictly)


def test_contains_in_a_mirrored_instance_by_winding_number(any_device, tier):
    """A mirrored instance of a closed mesh is the mirrored solid; "inside any of the instances"
    means inside it, by either method. (The winding number summed in world space is -1 there,
    since the mirror reverses the winding: it must be taken per instance, in the mesh's own
    orientation.)"""
    cube = any_device.mesh(*box())
    mirror = _affine(np.diag([-1.0, 1.0, 1.0]), [-2.0, 0.0, 0.0])  # x in [-3, -2]
    scene = any_device.scene([vkray.Instance(cube, mirror)])
    points = np.array([[-2.5, 0.5, 0.5], [-2.1, 0.2, 0.9], [-1.5, 0.5, 0.5], [-2.5, 0.5, 1.5]])
    for method in ("parity", "winding"):
        np.testing.assert_array_equal(
            scene.contains(points, precision=tier, method=method), [True, True, False, False], err_msg=method
        )


def test_contains_batch_shapes(any_device, tier):
    v, f = box()
    scene = any_device.scene(any_device.mesh(v, f))
    points = np.full((2, 5, 3), 0.5)
    points[1] += 2.0
    inside = scene.contains(points, precision=tier)
    assert inside.shape == (2, 5) and inside.dtype == np.bool_
    assert inside[0].all() and not inside[1].any()
    assert scene.contains([0.5, 0.5, 0.5]).shape == ()
    assert scene.contains(np.zeros((0, 3))).shape == (0,)


# --- 5. Mesh.is_closed --------------------------------------------------------------------------


@pytest.mark.parametrize("name, closed", [("fandisk", True), ("spot", True), ("cow", True),
                                          ("stanford-bunny", False), ("teapot", False)])
def test_is_closed_on_shipped_meshes(any_device, name, closed):
    v, f = mesh_data(name)
    assert directed_edges_closed(f) is closed  # what vkray.data says of them
    value = any_device.mesh(v, f).is_closed
    assert isinstance(value, bool) and value is closed


def _hand_made_meshes():
    bv, bf = box()
    flipped = bf.copy()
    flipped[3] = flipped[3, ::-1]
    unwelded_v = bv[bf].reshape(-1, 3)
    unwelded_f = np.arange(len(unwelded_v)).reshape(-1, 3)
    tri_v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    occupied = np.ones((2, 2, 2), bool)
    occupied[1, 1, 1] = False
    # Two boxes sharing one edge: that edge's directed edges appear twice.
    two = np.zeros((2, 2, 1), bool)
    two[0, 0, 0] = two[1, 1, 0] = True
    return [
        ("box", bv, bf, True),
        ("box with a flipped triangle", bv, flipped, False),
        ("box missing a triangle", bv, bf[1:], False),
        ("box with a duplicated triangle", bv, np.vstack([bf, bf[:1]]), False),
        ("unwelded box", unwelded_v, unwelded_f, False),
        ("single triangle", tri_v, np.array([[0, 1, 2]]), False),
        ("two-sided triangle", tri_v, np.array([[0, 1, 2], [0, 2, 1]]), True),
        ("seven eighths of a box", *voxel_surface(occupied), True),
        ("boxes sharing an edge", *voxel_surface(two), False),
        ("box as uint16", bv, bf.astype(np.uint16), True),
    ]


@pytest.mark.parametrize("label, v, f, closed", _hand_made_meshes(), ids=lambda x: x if isinstance(x, str) else None)
def test_is_closed_on_hand_made_meshes(any_device, label, v, f, closed):
    assert directed_edges_closed(f) is closed, label
    assert any_device.mesh(v, f).is_closed is closed, label


# --- 6. Bad input -------------------------------------------------------------------------------


def _scene(device):
    return device.scene(device.mesh(*box()))


@pytest.mark.parametrize("max_hits", [0, -1, np.int64(0), 1.5, 2.0, "2", True, [2]])
def test_bad_max_hits(any_device, max_hits):
    """max_hits <= 0 is a ValueError; a value that is not an integer (a float, even 2.0; a string;
    a bool, as the project's other integer arguments refuse them) a TypeError or a ValueError:
    either names the argument."""
    scene = _scene(any_device)
    error = ValueError if isinstance(max_hits, (int, np.integer)) and not isinstance(max_hits, bool) else (
        TypeError, ValueError)
    with pytest.raises(error, match="max_hits"):
        scene.intersect_all([0.5, 0.5, -1], [0, 0, 1], precision=REF, max_hits=max_hits)


def test_bad_input_names_the_argument(any_device):
    scene = _scene(any_device)
    o, d = np.array([[0.5, 0.5, -1.0]]), np.array([[0.0, 0.0, 1.0]])
    for query in (scene.intersect_all, scene.count):
        with pytest.raises(ValueError, match="origins"):
            query(o[:, :2], d, precision=REF)
        with pytest.raises(ValueError, match="directions"):
            query(o, d[:, :2], precision=REF)
        with pytest.raises(ValueError, match="broadcast"):
            query(np.zeros((2, 3)), np.ones((3, 3)), precision=REF)
        with pytest.raises(ValueError, match="directions"):
            query(o, np.zeros((1, 3)), precision=REF)
        with pytest.raises(ValueError, match="tmax"):
            query(o, d, tmin=2.0, tmax=1.0, precision=REF)
        with pytest.raises(ValueError, match="origins"):
            query(np.full((1, 3), np.nan), d, precision=REF)
        with pytest.raises(ValueError, match="precision must be"):
            query(o, d, precision="double")
        with pytest.raises(ValueError, match="cull must be"):
            query(o, d, precision=REF, cull="sideways")
        with pytest.raises(ValueError, match="mask"):
            query(o, d, precision=REF, mask=256)
    with pytest.raises(ValueError, match="points"):
        scene.contains(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="points"):
        scene.contains([[0.5, 0.5, 0.5], [np.inf, 0.0, 0.0]])
    with pytest.raises(TypeError, match="points"):
        scene.contains(np.zeros((2, 3), complex))
    with pytest.raises(ValueError, match="method") as error:
        scene.contains([[0.5, 0.5, 0.5]], method="ray_casting")
    assert "parity" in str(error.value) and "winding" in str(error.value)
    with pytest.raises(ValueError, match="precision must be"):
        scene.contains([[0.5, 0.5, 0.5]], precision="double")
    # The device still answers.
    assert scene.count(o, d, precision=REF).tolist() == [2]


@pytest.mark.parametrize("tier", ["fast", "refined"])
def test_contains_refuses_the_f32_tiers(any_device, tier):
    """f32 traversal may count a crossing at an edge twice or not at all: parity needs an exact
    tier."""
    with pytest.raises(vkray.UnsupportedError, match="exact"):
        _scene(any_device).contains([0.5, 0.5, 0.5], precision=tier)


def test_a_sphere_is_met_twice(any_device):
    """A ray through a sphere meets it where it enters and where it leaves (test_spheres.py
    checks every tier against the analytic roots); a point inside is inside by either method."""
    spheres = any_device.spheres([[0.0, 0.0, 0.0]], [1.0])
    scene = any_device.scene([spheres])
    assert scene.count([0.0, 0.0, -5.0], [0, 0, 1]).tolist() == 2
    assert scene.intersect_all([0.0, 0.0, -5.0], [0, 0, 1]).t.tolist() == [4.0, 6.0]
    assert scene.contains([0.0, 0.0, 0.0], method="winding") and scene.contains([0.0, 0.0, 0.5])


def test_defaults(any_device):
    """intersect_all and count default to the fast tier (as intersect does), contains to exact."""
    scene = _scene(any_device)
    o, d = [[0.3, 0.6, -1.0]], [[0.0, 0.0, 1.0]]  # off the faces' diagonals
    hits = scene.intersect_all(o, d)
    assert hits.precision == "fast" and hits.t.dtype == np.float32
    np.testing.assert_array_equal(hits.t, scene.intersect_all(o, d, precision="fast").t)
    np.testing.assert_array_equal(scene.count(o, d), [2])
    points = [[0.5, 0.5, 0.5], [2.0, 0.5, 0.5]]
    if _exact_on(any_device):
        np.testing.assert_array_equal(scene.contains(points), scene.contains(points, precision="exact"))
    np.testing.assert_array_equal(scene.contains(points), [True, False])


# --- 7. Threads ---------------------------------------------------------------------------------


def test_threads_share_a_scene(any_device, tier):
    """4 threads × 20 calls mixing intersect_all, count and contains on one scene: the answers of
    one thread alone. A hang fails (join timeout) instead of stopping the suite."""
    threads_share_a_scene(any_device, tier)


def test_threads_share_a_scene_in_the_fast_tier(device):
    """As above, in the fast tier (contains: exact), on both backends."""
    threads_share_a_scene(device, "fast")


def threads_share_a_scene(any_device, tier):
    contains_tier = "exact" if tier == "fast" else tier
    v, f = mesh_data("spot")
    mesh = any_device.mesh(v, f)
    scene = any_device.scene([mesh, vkray.Instance(mesh, _affine(np.eye(3), [0.2, 0.0, 0.1]))])
    batches = [random_rays(v, 150, seed=60 + k) for k in range(3)]
    points = [_points_around(v, f, 80, 20, seed=70 + k) for k in range(3)]
    expected = []
    for k in range(3):
        o, d = batches[k]
        hits = scene.intersect_all(o, d, precision=tier)
        expected.append(("all", (hits.offsets, hits.t, hits.prim_id, hits.instance_id)))
        expected.append(("count", scene.count(o, d, precision=tier)))
        expected.append(("contains", scene.contains(points[k], precision=contains_tier)))
    failures, done = [], []

    def work(seed):
        rng = np.random.default_rng(seed)
        try:
            for _ in range(20):
                job = int(rng.integers(0, len(expected)))
                kind, want = expected[job]
                k = job // 3
                o, d = batches[k]
                if kind == "all":
                    hits = scene.intersect_all(o, d, precision=tier)
                    got = (hits.offsets, hits.t, hits.prim_id, hits.instance_id)
                    ok = all(np.array_equal(a, b) for a, b in zip(got, want))
                elif kind == "count":
                    ok = np.array_equal(scene.count(o, d, precision=tier), want)
                else:
                    ok = np.array_equal(scene.contains(points[k], precision=contains_tier), want)
                if not ok:
                    failures.append((seed, kind, k))
            done.append(seed)
        except BaseException as exc:  # noqa: B036 - reported to the main thread
            failures.append((seed, repr(exc)))

    threads = [threading.Thread(target=work, args=(seed,), daemon=True) for seed in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert not any(thread.is_alive() for thread in threads), "a query thread hung"
    assert not failures, failures
    assert sorted(done) == [0, 1, 2, 3]


def _exact_on(device) -> bool:
    """Whether this device answers the exact tier (shaderFloat64, and a pipeline driver that runs
    intersection shaders: vkray probes it and raises UnsupportedError if not)."""
    scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    try:
        scene.count([0.2, 0.2, 1.0], [0, 0, -1], precision="exact")
        return True
    except vkray.UnsupportedError:
        return False


@pytest.mark.parametrize("name", ["spot", "fandisk", "stanford-bunny"])
def test_exact_count_on_the_gpu_equals_the_reference(device, name):
    """The GPU's exact count (f32 traversal of per-triangle boxes, every candidate decided by the
    f64 watertight test, none committed) counts what the CPU's does, ray for ray, with a
    mirrored instance, culling and per-ray intervals."""
    if not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    v, f = load_mesh(name)
    mesh = device.mesh(v, f)
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    scene = device.scene([vkray.Instance(mesh), vkray.Instance(mesh, mirror, custom_index=3)])
    rng = np.random.default_rng(17)
    size = np.ptp(v, axis=0).max()
    origins = v.mean(axis=0) + rng.normal(size=(5000, 3)) * size
    directions = rng.normal(size=(5000, 3))
    tmax = rng.uniform(0.5, 4.0, 5000) * size
    for cull in (None, "back"):
        want = scene.count(origins, directions, tmax=tmax, cull=cull, precision="reference")
        got = scene.count(origins, directions, tmax=tmax, cull=cull, precision="exact")
        assert want.sum() > 100
        np.testing.assert_array_equal(got, want, err_msg=str(cull))


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e5, 1e7])
def test_exact_count_through_shared_vertices_and_edges(device, offset):
    """Rays through the vertices and edges a heightfield's triangles share cross it once: the
    GPU's exact count says 1 for every one of them, at every offset."""
    if not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    n = 10
    v, f, _ = heightfield(n, seed=3, offset=offset)
    origins, directions = rays_through(shared_targets(v, f, n), seed=4)
    scene = device.scene(device.mesh(v, f))
    counts = scene.count(origins, directions, precision="exact")
    assert (counts == 1).all(), f"{np.sum(counts == 0)} misses, {np.sum(counts > 1)} double counts"


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e5, 1e7])
def test_exact_tier_of_f32_rays_equals_the_reference(device, offset):
    """f32 rays of one interval go to the GPU's exact tier as given (24 bytes a ray, 12 from one
    origin) and are moved into the scene's frame there in f64: closest hits, occlusion, counts
    and all hits equal the reference tier's on the same f32 rays, through the vertices and edges
    a heightfield's triangles share, far from the origin, with per-ray masks, from one origin,
    and with an interval of their own."""
    if not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    n = 10
    v, f, _ = heightfield(n, seed=3, offset=offset)
    origins, directions = rays_through(shared_targets(v, f, n), seed=4)
    origins, directions = origins.astype(np.float32), directions.astype(np.float32)
    scene = device.scene(device.mesh(v, f))
    # One origin above the field's middle, aimed at the same targets.
    apex = (v.min(axis=0) + v.max(axis=0)) / 2 + [0.0, 0.0, 2.0]
    camera = np.float32(apex), (shared_targets(v, f, n) - apex).astype(np.float32)
    masks = np.where(np.arange(len(origins)) % 3 == 0, 0, 0xFF).astype(np.uint8)
    for label, (o, d), keywords in [
        ("rays", (origins, directions), {}),
        ("masks", (origins, directions), {"mask": masks}),
        ("camera", camera, {}),
        ("interval", (origins, directions), {"tmin": 0.5, "tmax": 50.0}),
    ]:
        for query in ("intersect", "occluded", "count", "intersect_all"):
            got = getattr(scene, query)(o, d, precision="exact", **keywords)
            want = getattr(scene, query)(o, d, precision="reference", **keywords)
            if query in ("intersect", "intersect_all"):
                for name in ("t", "prim_id", "uv") + (("offsets",) if query == "intersect_all" else ()):
                    what = f"{label} {query} {name}"
                    np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=what)
            else:
                np.testing.assert_array_equal(got, want, err_msg=f"{label} {query}")
    assert (scene.count(origins, directions, precision="exact") == 1).all()


@pytest.mark.parametrize("name", ["fandisk", "spot", "cow"])
def test_exact_contains_equals_the_reference(device, name):
    """contains(precision="exact") counts each point's crossings on the GPU (one instance) or on
    the CPU (several): the same answers as the reference tier, points on a lattice through the
    mesh's own vertices and on its surface included."""
    if not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    v, f = load_mesh(name)
    mesh = device.mesh(v, f)
    rng = np.random.default_rng(23)
    lo, hi = v.min(axis=0), v.max(axis=0)
    points = np.vstack([rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (3000, 3)), v[::7]])
    mirrored = vkray.Instance(mesh, np.diag([-1.0, 1, 1, 1]))
    for scene in (device.scene(mesh), device.scene([vkray.Instance(mesh), mirrored])):
        want = scene.contains(points, precision="reference")
        got = scene.contains(points, precision="exact")
        assert want[-len(v[::7]):].all()  # vertices are on the surface: inside
        np.testing.assert_array_equal(got, want)


# --- 8. The GPU tiers against intersect and against each other -----------------------------------


@pytest.mark.parametrize("tier", ALL_TIERS)
def test_nearest_hits_are_intersects(device, tier):
    """intersect_all(max_hits=1) is intersect hit for hit (the same triangle, t and uv), and
    max_hits=k keeps the first k of the full lists, in every tier and both backends."""
    if tier == "exact" and not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    v, f = mesh_data("spot")
    mesh = device.mesh(v, f)
    moved = _affine(_rotation([1, 1, 0], 0.4), [0.15, 0.05, -0.1])
    scene = device.scene([vkray.Instance(mesh), vkray.Instance(mesh, moved)])
    origins, directions = random_rays(v, 400, seed=47)
    fields = ["t", "prim_id", "instance_id", "uv"]
    one = scene.intersect_all(origins, directions, max_hits=1, precision=tier, outputs=fields)
    closest = scene.intersect(origins, directions, precision=tier, outputs=fields)
    hit = closest.prim_id >= 0
    assert hit.sum() > 200
    np.testing.assert_array_equal(one.counts, hit.astype(np.int64))
    for name in ("prim_id", "instance_id"):
        np.testing.assert_array_equal(getattr(one, name), getattr(closest, name)[hit], err_msg=name)
    np.testing.assert_array_equal(one.t, closest.t[hit])
    np.testing.assert_allclose(one.uv, closest.uv[hit], rtol=0, atol=1e-6 if tier == "fast" else 1e-12)
    full = scene.intersect_all(origins, directions, precision=tier, outputs=fields)
    for k in (2, 3):
        some = scene.intersect_all(origins, directions, max_hits=k, precision=tier, outputs=fields)
        np.testing.assert_array_equal(some.counts, np.minimum(full.counts, k))
        keep = np.concatenate([np.arange(a, a + c) for a, c in zip(full.offsets[:-1], some.counts)]).astype(np.int64)
        for name in fields:
            np.testing.assert_array_equal(getattr(some, name), getattr(full, name)[keep], err_msg=name)


def test_fast_tier_far_from_the_scene(device):
    """Rays starting 1e5 scene sizes away (their origins advanced in f64 before they become f32):
    the fast tier's hits are the reference's, t measured from the rays' own origins."""
    v, f = mesh_data("fandisk")
    scene = device.scene(device.mesh(v, f))
    centre, radius = bounds(v)
    origins, directions = random_rays(v, 300, seed=48)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    far = origins - 1e5 * radius * directions
    fast = scene.intersect_all(far, directions, outputs=["t", "prim_id"])
    ref = scene.intersect_all(far, directions, precision="reference", outputs=["t", "prim_id"])
    assert fast.t.dtype == np.float32 and int(ref.counts.sum()) > 300
    same = fast.counts == ref.counts
    assert same.mean() > 0.97, f"{(~same).sum()} rays differ"
    rows = np.repeat(same, ref.counts.reshape(-1))
    fast_rows = np.repeat(same, fast.counts.reshape(-1))
    np.testing.assert_array_equal(fast.prim_id[fast_rows], ref.prim_id[rows])
    # f32 at 1e5 sizes: a few ulps of the distance.
    np.testing.assert_allclose(fast.t[fast_rows], ref.t[rows], rtol=1e-6, atol=0)


@pytest.mark.parametrize("tier", ["fast", "exact"])
def test_gpu_count_does_not_depend_on_chunks(device, tier):
    """Counts and all hits over several chunks (a chunk of 64 rays, lists of every length) are the
    ones of a single chunk."""
    if tier == "exact" and not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    v, f = mesh_data("cow")
    scene = device.scene(device.mesh(v, f))
    origins, directions = random_rays(v, 1000, seed=49)
    whole = scene.intersect_all(origins, directions, precision=tier, outputs=["t", "prim_id"])
    counts = scene.count(origins, directions, precision=tier)
    previous = device.chunk_rays
    try:
        device.chunk_rays = 64
        chunked = scene.intersect_all(origins, directions, precision=tier, outputs=["t", "prim_id"])
        np.testing.assert_array_equal(scene.count(origins, directions, precision=tier), counts)
    finally:
        device.chunk_rays = previous
    np.testing.assert_array_equal(whole.counts, counts)
    for name in ("offsets", "t", "prim_id"):
        np.testing.assert_array_equal(getattr(chunked, name), getattr(whole, name), err_msg=name)


@pytest.mark.parametrize("tier", ["fast", "exact"])
def test_all_hits_in_records_smaller_than_a_chunk(device, tier, monkeypatch):
    """Room for 8 hit records a chunk (VKRAY_HIT_RECORD_BYTES, the storing pass's budget): each
    chunk stores only the rays whose lists fit and the next starts after them, and a ray of more
    hits than that (through twelve boxes) gets records of its own. With room for a few of each
    ray's hits, the counting pass keeps them, and only the rays with more are traced again. The
    hits (all, and the nearest 1, 3 or 30) are those of one chunk with room for all."""
    if tier == "exact" and not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    v, f = mesh_data("cow")
    cow = device.mesh(v, f)
    boxes = device.mesh(*box())
    far = [vkray.Instance(boxes, _affine(np.eye(3), [50.0, 0.0, 1.5 * k])) for k in range(12)]
    scene = device.scene([vkray.Instance(cow)] + far)
    origins, directions = random_rays(v, 300, seed=52)
    # Every 50th ray through the twelve boxes (24 hits).
    origins[::50] = [50.3, 0.6, -1.0]
    directions[::50] = [0.0, 0.0, 1.0]
    fields = ["t", "prim_id", "instance_id"]
    whole = scene.intersect_all(origins, directions, precision=tier, outputs=fields)
    assert whole.counts[::50].tolist() == [24] * 6 and whole.counts.sum() > 300
    # 8 records; then room for 2 and for 8 of each ray's nearest hits as they are counted (the
    # rays with more, and those past the room, traced again to store them).
    for records in (8, 2 * 300, 8 * 300):
        monkeypatch.setenv("VKRAY_HIT_RECORD_BYTES", str(records * 32))
        small = scene.intersect_all(origins, directions, precision=tier, outputs=fields)
        for name in ("offsets", "counts", "ray_index") + tuple(fields):
            np.testing.assert_array_equal(getattr(small, name), getattr(whole, name), err_msg=f"{records}: {name}")
        for max_hits in (1, 3, 30):
            kept = scene.intersect_all(origins, directions, precision=tier, outputs=fields, max_hits=max_hits)
            np.testing.assert_array_equal(kept.counts, np.minimum(whole.counts, max_hits))
            rows = np.concatenate([np.arange(a, a + c) for a, c in zip(whole.offsets[:-1], kept.counts)])
            np.testing.assert_array_equal(kept.prim_id, whole.prim_id[rows])
            np.testing.assert_array_equal(kept.t, whole.t[rows])


@pytest.mark.parametrize("tier", ["fast", "exact"])
def test_long_lists(device, tier):
    """Rays through 40 boxes in a row (80 hits each, in lists long enough that the GPU appends
    them and the host sorts them), some with max_hits=50 (kept sorted on the GPU): the reference
    tier's hits, in its order."""
    if tier == "exact" and not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    mesh = device.mesh(*box())
    scene = device.scene([vkray.Instance(mesh, _affine(np.eye(3), [0.0, 0.0, 1.5 * k])) for k in range(40)[::-1]])
    rng = np.random.default_rng(50)
    origins = np.column_stack([rng.uniform(0.2, 0.8, (64, 2)), np.full(64, -1.0)])
    directions = np.column_stack([rng.uniform(-0.002, 0.002, (64, 2)), np.ones(64)])
    fields = ["t", "prim_id", "instance_id"]
    for max_hits in (None, 50):
        got = scene.intersect_all(origins, directions, precision=tier, max_hits=max_hits, outputs=fields)
        want = scene.intersect_all(origins, directions, precision="reference", max_hits=max_hits, outputs=fields)
        check_structure(got, (64,))
        np.testing.assert_array_equal(got.counts, np.full(64, 80 if max_hits is None else 50))
        np.testing.assert_array_equal(got.instance_id, want.instance_id)
        np.testing.assert_array_equal(got.prim_id, want.prim_id)
        np.testing.assert_allclose(got.t, want.t, rtol=0, atol=2e-6 * 60 if tier == "fast" else 0)


@pytest.mark.parametrize("tier", ["fast", "exact"])
@pytest.mark.parametrize("parts", [1, 2])
def test_columns_written_on_the_gpu_equal_the_hosts(device, tier, parts, monkeypatch):
    """The GPU writes the answer's columns (t, uv, prim_id, instance_id, geometry_id and each
    hit's ray) from its hit records; asking for positions too sends the answer through the host,
    which writes them from the records instead. Both are the same, bit for bit: the cow (in one
    part or two) beside 40 boxes in a row, in chunks of 64 rays (the first holding rays through
    the boxes, whose 80-hit lists the host sorts: that chunk's columns are the host's), far rays
    among them (their t advanced back in the fast tier), with records for the whole query and
    for 100 hits a chunk; and no rays. The CPU engine writes every answer's columns on the host."""
    if tier == "exact" and not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    v, f = mesh_data("cow")
    half = len(f) // 2
    cow = device.mesh(v, f) if parts == 1 else device.mesh_from_parts([(v, f[:half]), (v, f[half:])])
    boxes = device.mesh(*box())
    row = [vkray.Instance(boxes, _affine(np.eye(3), [50.0, 0.0, 1.5 * k])) for k in range(40)]
    scene = device.scene([vkray.Instance(cow)] + row)
    origins, directions = random_rays(v, 400, seed=53)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    _, radius = bounds(v)
    origins[200::20] -= 1e5 * radius * directions[200::20]
    origins[[5, 40]] = [50.3, 0.6, -1.0]
    directions[[5, 40]] = [0.0, 0.0, 1.0]
    fields = ["t", "uv", "prim_id", "instance_id", "geometry_id"]
    # The exact tier's records name a triangle among all parts: the GPU writes one-part meshes'.
    on_gpu = device.info.engine == "vulkan" and (parts == 1 or tier == "fast")
    previous = device.chunk_rays
    try:
        device.chunk_rays = 64
        for records in (None, 100):
            if records is not None:
                monkeypatch.setenv("VKRAY_HIT_RECORD_BYTES", str(records * 32))
            gpu = scene.intersect_all(origins, directions, precision=tier, outputs=fields)
            written = device.last_trace_profile["gpu_columns"]
            host = scene.intersect_all(origins, directions, precision=tier, outputs=fields + ["position"])
            assert device.last_trace_profile["gpu_columns"] == 0
            assert (written > 0) == on_gpu
            assert gpu.counts[[5, 40]].tolist() == [80, 80] and gpu.counts.sum() > 400
            for name in ("offsets", "counts", "ray_index") + tuple(fields):
                got, want = getattr(gpu, name), getattr(host, name)
                assert got.dtype == want.dtype, name
                np.testing.assert_array_equal(got, want, err_msg=f"{records}: {name}")
    finally:
        device.chunk_rays = previous
    # No rays: every asked column, empty.
    none = scene.intersect_all(np.zeros((0, 3)), [0.0, 0.0, 1.0], precision=tier, outputs=fields)
    for name in fields:
        column = getattr(none, name)
        assert column is not None and len(column) == 0 and column.dtype == getattr(host, name).dtype, name


@pytest.mark.parametrize("offset", [0.0, 1e5])
def test_gpu_tells_points_on_the_surface(device, offset):
    """contains(precision="exact") on one instance tests on the GPU whether each point lies on the
    surface (the CPU's 8-ulp test, same operations): the fandisk's vertices are inside, and on
    edge midpoints and points inside faces (computed in f64, so a few ulps off the surface, some
    beyond the 8 the test allows) and 1e-6 off the surface on either side, the reference tier
    agrees point for point."""
    if not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    v, f = load_mesh("fandisk")
    v = v + offset
    scene = device.scene(device.mesh(v, f))
    rng = np.random.default_rng(57)
    tri = v[f[rng.integers(0, len(f), 400)]]
    w = rng.dirichlet([1.0, 1.0, 1.0], 400)
    on = np.vstack([v[::5], (tri[:, 0] + tri[:, 1]) / 2, np.einsum("nk,nkd->nd", w, tri)])
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    centres = tri.mean(axis=1)
    near = np.vstack([centres + 1e-6 * normal, centres - 1e-6 * normal])
    inside = scene.contains(on)
    assert inside[: len(v[::5])].all(), "a vertex called outside"
    assert inside.mean() > (0.95 if offset == 0 else 0.5)
    np.testing.assert_array_equal(inside, scene.contains(on, precision="reference"))
    np.testing.assert_array_equal(scene.contains(near), scene.contains(near, precision="reference"))
    assert scene.contains(near).sum() == len(centres)  # one side of each face is inside


def test_contacts_close_the_triangles(device):
    """The exact tier's contacts (the trimesh drop-in's second look at rays that cross nothing):
    a ray through a shared edge meets both triangles there, one down a face's boundary plane
    meets its edge; crossings give one and none. Other tiers refuse contacts."""
    if not _exact_on(device):
        pytest.skip("this device does not answer precision='exact'")
    scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]]))
    o = np.array([[0.5, 0.5, 1.0], [1.0, 0.5, 1.0], [2.0, 0.5, 1.0]])  # the diagonal; the x=1 border; outside
    d = np.array([[0.0, 0.0, -1.0]] * 3)
    core = scene._core
    crossings = core.trace_all(o, d, 0.0, np.inf, ["prim_id"], "exact")
    contacts = core.trace_all(o, d, 0.0, np.inf, ["prim_id"], "exact", None, None, None, True)
    assert np.diff(crossings["offsets"]).tolist()[0] == 1
    assert np.diff(contacts["offsets"]).tolist() == [2, 1, 0]
    first = core.trace(o, d, 0.0, np.inf, "closest", ["prim_id"], "exact", None, None, True)["prim_id"]
    assert (first[:2] >= 0).all() and first[2] == -1
    for tier in ("fast", "refined", "reference"):
        with pytest.raises(vkray.UnsupportedError, match="contacts"):
            core.trace(o, d, 0.0, np.inf, "closest", ["prim_id"], tier, None, None, True)
