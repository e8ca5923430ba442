"""Independent references for the tests: OBJ loading, Embree (embreex) and plain numpy geometry."""

from __future__ import annotations

import functools
import hashlib

import numpy as np

from vkray.data import MESH_NAMES, load_mesh  # noqa: F401  (the tests' meshes, shipped with vkray)

EMBREE_MISS_T = 1e37


def _key(value):
    """A hashable stand-in of an argument: arrays by shape, dtype and a digest of their bytes."""
    if isinstance(value, (list, tuple)):
        return tuple(_key(v) for v in value)
    if isinstance(value, np.ndarray) or hasattr(value, "__array__"):
        a = np.ascontiguousarray(value)
        return (a.shape, a.dtype.str, hashlib.blake2b(a.tobytes(), digest_size=16).digest())
    return repr(value)


def _remembered(oracle):
    """The brute-force oracles run once per distinct input in a session: a test parametrized over
    devices and tiers asks the same question of each (the bunny's winding numbers took 11 s a
    call on CI's machine). Each caller gets its own copy of the answer."""
    answers = {}

    @functools.wraps(oracle)
    def remembered(*args, **kwargs):
        key = (_key(args), tuple(sorted((k, _key(v)) for k, v in kwargs.items())))
        if key not in answers:
            answers[key] = oracle(*args, **kwargs)
        answer = answers[key]
        if isinstance(answer, dict):
            return {k: np.copy(v) for k, v in answer.items()}
        return np.copy(answer)

    return remembered


def embree(triangle_sets, origins, directions, tmax=None, query="INTERSECT"):
    """Embree's answer for rays against meshes given as (vertices, faces) pairs (geomID = order)."""
    # Imported here: the benchmarks use this module's loaders and rays where embreex is absent.
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    for vertices, faces in triangle_sets:
        TriangleMesh(scene, np.ascontiguousarray(vertices[faces], dtype=np.float32))
    o = np.ascontiguousarray(origins, dtype=np.float32)
    d = np.ascontiguousarray(directions, dtype=np.float32)
    dists = None if tmax is None else np.ascontiguousarray(tmax, dtype=np.float32)
    if query == "OCCLUDED":
        return scene.run(o, d, dists=dists, query="OCCLUDED") >= 0
    return scene.run(o, d, dists=dists, output=1)


def bounds(vertices):
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2


def camera_rays(vertices, width=256, height=256, direction=(0.3, -0.4, -1.0)):
    """A pinhole camera looking at the mesh's centre from 2.5 radii away: (origin (3,), dirs (H*W, 3))."""
    centre, radius = bounds(vertices)
    forward = np.asarray(direction, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    origin = centre - 2.5 * radius * forward
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    ys, xs = np.meshgrid(np.linspace(0.5, -0.5, height), np.linspace(-0.5, 0.5, width), indexing="ij")
    dirs = forward + xs[..., None] * right + ys[..., None] * up
    return origin, dirs.reshape(-1, 3)


def random_rays(vertices, n, seed=0):
    """Rays from a sphere around the mesh towards random points of its bounding box, plus a
    quarter in uniformly random directions (many of which miss)."""
    rng = np.random.default_rng(seed)
    centre, radius = bounds(vertices)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    u = rng.normal(size=(n, 3))
    origins = centre + 2.0 * radius * u / np.linalg.norm(u, axis=1, keepdims=True)
    targets = rng.uniform(lo, hi, size=(n, 3))
    directions = targets - origins
    wild = rng.random(n) < 0.25
    directions[wild] = rng.normal(size=(int(wild.sum()), 3))
    return origins, directions


def triangle_normals(vertices, faces, prim):
    tri = vertices[faces[prim]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def barycentric_points(vertices, faces, prim, uv):
    tri = vertices[faces[prim]]
    u, v = uv[:, :1].astype(np.float64), uv[:, 1:].astype(np.float64)
    return (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]


def transform_points(matrix, points):
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def heightfield(n: int, seed: int, offset: float = 0.0):
    """A random heightfield of (n-1)^2 quads, two triangles each, translated by `offset` along
    every axis (baked into the float64 vertices): (vertices, faces, color) where `color` gives
    every triangle one of 18 classes such that triangles sharing a vertex never share a class."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64), indexing="xy")
    z = rng.uniform(0.0, 0.5, (n, n))
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3) + offset
    at = lambda i, j: j * n + i  # noqa: E731
    faces, color = [], []
    for j in range(n - 1):
        for i in range(n - 1):
            faces += [[at(i, j), at(i + 1, j), at(i + 1, j + 1)], [at(i, j), at(i + 1, j + 1), at(i, j + 1)]]
            color += [((i % 3) * 3 + j % 3) * 2, ((i % 3) * 3 + j % 3) * 2 + 1]
    return vertices, np.array(faces, dtype=np.int64), np.array(color)


def shared_targets(vertices, faces, n: int):
    """Points of a heightfield that several triangles share: interior vertices and the midpoints
    of interior edges (axis-aligned and diagonal)."""
    grid = vertices.reshape(n, n, 3)
    inner = grid[1:-1, 1:-1].reshape(-1, 3)
    right = 0.5 * (grid[1:-1, 1:-2] + grid[1:-1, 2:-1])
    up = 0.5 * (grid[1:-2, 1:-1] + grid[2:-1, 1:-1])
    diagonal = 0.5 * (grid[1:-2, 1:-2] + grid[2:-1, 2:-1])
    return np.concatenate([inner, right.reshape(-1, 3), up.reshape(-1, 3), diagonal.reshape(-1, 3)])


def rays_through(targets, seed: int, distance: float = 5.0):
    """Rays from above (random tilts up to 45 degrees) that pass through `targets` at t = 1."""
    rng = np.random.default_rng(seed)
    tilt = rng.uniform(-1.0, 1.0, (len(targets), 2))
    away = np.column_stack([tilt, np.ones(len(targets))])
    away *= distance / np.linalg.norm(away, axis=1, keepdims=True)
    origins = targets + away
    return origins, targets - origins


# --- Added for tests/test_all_hits.py: pure-numpy oracles (every hit along a ray, generalized
# --- winding numbers, distances to a surface, closedness) and closed test solids. No vkray here.


@_remembered
def all_hits_brute(triangles, origins, directions, tmin=0.0, tmax=np.inf, rays_per_chunk=None):
    """Every hit of every ray on every triangle (Möller–Trumbore in f64, closed triangles, no
    tie-break), brute force. triangles: (F, 3, 3) world-space corners; origins, directions: (N, 3);
    tmin, tmax: scalars or (N,). Returns a dict of flat arrays sorted by (ray, t, triangle):
    ``ray``, ``tri``, ``t``, ``u``, ``v`` (weights of corners 1 and 2), ``front`` (the ray meets the
    side ``cross(b - a, c - a)`` points to) and ``margin``: how near the hit is to being decided
    otherwise by rounding (the smallest barycentric weight, and the sine of the angle between the
    ray and the plane, whichever is smaller)."""
    tri = np.asarray(triangles, dtype=np.float64)
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    n = len(o)
    lo = np.broadcast_to(np.asarray(tmin, dtype=np.float64), (n,))
    hi = np.broadcast_to(np.asarray(tmax, dtype=np.float64), (n,))
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    normal = np.cross(e1, e2)
    area2 = np.linalg.norm(normal, axis=1)
    # Component by component on (rays, faces) arrays of about 64k pairs, which stay in the cache.
    (ax, ay, az), (e1x, e1y, e1z), (e2x, e2y, e2z) = a.T, e1.T, e2.T
    step = rays_per_chunk or max(1, 65_536 // max(1, len(tri)))
    out = {k: [] for k in ("ray", "tri", "t", "u", "v", "front", "margin")}
    for start in range(0, n, step):
        dx, dy, dz = (d[start : start + step, k, None] for k in range(3))
        px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
        det = px * e1x + py * e1y + pz * e1z
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            sx, sy, sz = (o[start : start + step, k, None] - corner for k, corner in enumerate((ax, ay, az)))
            u = (sx * px + sy * py + sz * pz) * inv
            qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
            v = (dx * qx + dy * qy + dz * qz) * inv
            t = (qx * e2x + qy * e2y + qz * e2z) * inv
            r_lo, r_hi = lo[start : start + step, None], hi[start : start + step, None]
            hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= r_lo) & (t <= r_hi)
        r, f = np.nonzero(hit)
        length = np.linalg.norm(d[start + r], axis=1)
        sine = np.abs(det[r, f]) / (length * area2[f])
        out["ray"].append(start + r)
        out["tri"].append(f)
        out["t"].append(t[r, f])
        out["u"].append(u[r, f])
        out["v"].append(v[r, f])
        out["front"].append(det[r, f] > 0)
        out["margin"].append(np.minimum.reduce([u[r, f], v[r, f], 1 - u[r, f] - v[r, f], sine]))
    hits = {k: np.concatenate(x) if x else np.zeros(0) for k, x in out.items()}
    order = np.lexsort((hits["tri"], hits["t"], hits["ray"]))
    return {k: x[order] for k, x in hits.items()}


@_remembered
def winding_numbers(vertices, faces, points, points_per_chunk=None):
    """Generalized winding numbers (Jacobson, Kavan and Sorkine-Hornung 2013) of points with
    respect to a triangle mesh: the sum of the triangles' signed solid angles over 4 pi, each by Van
    Oosterom and Strackee's formula. 1 inside and 0 outside a closed outward-oriented mesh. The
    arithmetic runs component by component on (points, faces) arrays of about 64k pairs, which stay
    in the cache (5x faster than on stacked vectors)."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    corners = [tri[:, k].T.copy() for k in range(3)]  # each corner's x, y, z rows, (3, F)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    step = points_per_chunk or max(1, 65_536 // max(1, len(tri)))
    total = np.zeros(len(p))
    for start in range(0, len(p), step):
        q = p[start : start + step]
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = ([c[k][None, :] - q[:, k, None] for k in range(3)] for c in corners)
        la, lb, lc = (np.sqrt(x * x + y * y + z * z) for x, y, z in ((ax, ay, az), (bx, by, bz), (cx, cy, cz)))
        numerator = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        ab, bc, ca = ax * bx + ay * by + az * bz, bx * cx + by * cy + bz * cz, cx * ax + cy * ay + cz * az
        denominator = la * lb * lc + ab * lc + bc * la + ca * lb
        total[start : start + step] = 2.0 * np.arctan2(numerator, denominator).sum(axis=1)
    return total / (4.0 * np.pi)


def _segment_distance(px, py, pz, a, ab, ab_ab):
    """Distances of points (components, (P, 1) each) to segments from corners `a` along `ab`
    (components, (F,) each; `ab_ab` their squared lengths), (P, F)."""
    wx, wy, wz = px - a[0], py - a[1], pz - a[2]
    w = np.clip((wx * ab[0] + wy * ab[1] + wz * ab[2]) / ab_ab, 0.0, 1.0)
    dx, dy, dz = wx - w * ab[0], wy - w * ab[1], wz - w * ab[2]
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@_remembered
def surface_distance(vertices, faces, points, points_per_chunk=None):
    """Each point's distance to the nearest point of the mesh's (closed) triangles, brute force
    (component by component on (points, faces) arrays of about 64k pairs, which stay in the cache)."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    nx, ny, nz = normal.T
    sides = [(x.T, (y - x).T, np.einsum("fk,fk->f", y - x, y - x)) for x, y in ((a, b), (b, c), (c, a))]
    step = points_per_chunk or max(1, 65_536 // max(1, len(tri)))
    out = np.empty(len(p))
    for start in range(0, len(p), step):
        px, py, pz = (p[start : start + step, k, None] for k in range(3))
        height = (px - a[:, 0]) * nx + (py - a[:, 1]) * ny + (pz - a[:, 2]) * nz
        fx, fy, fz = px - height * nx, py - height * ny, pz - height * nz  # the foot on the plane
        inside = np.ones(height.shape, bool)
        for (xx, xy, xz), (ex, ey, ez), _ in sides:
            gx, gy, gz = fx - xx, fy - xy, fz - xz
            inside &= (ey * gz - ez * gy) * nx + (ez * gx - ex * gz) * ny + (ex * gy - ey * gx) * nz >= 0
        edges = np.minimum.reduce([_segment_distance(px, py, pz, x, e, ee) for x, e, ee in sides])
        out[start : start + step] = np.where(inside, np.abs(height), edges).min(axis=1)
    return out


def directed_edges_closed(faces) -> bool:
    """Whether every directed edge (a, b) of the faces appears exactly once and (b, a) exactly once."""
    f = np.asarray(faces, dtype=np.int64)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    pairs = {tuple(e) for e in edges.tolist()}
    return len(pairs) == len(edges) and all((b, a) in pairs for a, b in pairs)


def voxel_surface(occupied, size=1.0, offset=0.0):
    """The boundary of a union of unit voxels (a bool (X, Y, Z) array; voxel (i, j, k) spans
    [i, i+1] x [j, j+1] x [k, k+1]), two outward triangles per exposed unit square, sharing the grid's
    vertices: a closed mesh without T-junctions, scaled by `size` and moved by `offset`."""
    occupied = np.asarray(occupied, dtype=bool)
    index, vertices, faces = {}, [], []

    def vertex(corner):
        if corner not in index:
            index[corner] = len(vertices)
            vertices.append(corner)
        return index[corner]

    padded = np.pad(occupied, 1)
    for i, j, k in zip(*np.nonzero(occupied)):
        for axis in range(3):
            for side in (0, 1):
                step = [0, 0, 0]
                step[axis] = 1 if side else -1
                if padded[i + 1 + step[0], j + 1 + step[1], k + 1 + step[2]]:
                    continue
                b, c = (axis + 1) % 3, (axis + 2) % 3  # cyclic: cross(e_b, e_c) = e_axis
                quad = []
                for db, dc in ((0, 0), (1, 0), (1, 1), (0, 1)):
                    corner = [i, j, k]
                    corner[axis] += side
                    corner[b] += db
                    corner[c] += dc
                    quad.append(vertex(tuple(corner)))
                if not side:  # outward is -axis: reverse the winding, keeping the diagonal q0-q2
                    quad = [quad[0], quad[3], quad[2], quad[1]]
                faces += [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]]
    v = np.array(vertices, dtype=np.float64) * size + offset
    return v, np.array(faces, dtype=np.int64)


def box(lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)):
    """An axis-aligned box as 12 outward triangles over 8 vertices (closed)."""
    v, f = voxel_surface(np.ones((1, 1, 1), bool))
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    return lo + v * (hi - lo), f


def triangle_soup(n: int, seed: int):
    """`n` random triangles of random sizes in the unit cube (they cross each other freely)."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0.0, 1.0, (n, 1, 3))
    corners = centres + rng.normal(size=(n, 3, 3)) * rng.uniform(0.02, 0.3, (n, 1, 1))
    return corners.reshape(-1, 3), np.arange(3 * n, dtype=np.int64).reshape(n, 3)


def in_threads(count, work):
    """``[work(0), ..., work(count - 1)]``, each called in a thread of its own, all at once; the
    first error raised by any of them is raised here once all are done."""
    import threading

    results = [None] * count
    errors = []

    def run(k):
        try:
            results[k] = work(k)
        except BaseException as exc:  # raised below, in the caller's thread
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(k,)) for k in range(count)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        raise errors[0]
    return results


def fan(offset, seed=49, k=11):
    """A closed fan: k triangles around a centre vertex, an irregular ring."""
    rng = np.random.default_rng(seed)
    angles = 2 * np.pi * np.arange(k) / k + rng.uniform(-0.2, 0.2, k)
    ring = np.column_stack([np.cos(angles), np.sin(angles), rng.uniform(-0.2, 0.2, k)])
    v = np.vstack([[0.0, 0.0, 0.3], ring]) + offset
    f = np.array([[0, 1 + i, 1 + (i + 1) % k] for i in range(k)])
    return v, f


def bipyramid(offset, seed=51, k=9):
    """A closed convex solid: two fans on one irregular ring, apexes above and below."""
    rng = np.random.default_rng(seed)
    angles = 2 * np.pi * np.arange(k) / k + rng.uniform(-0.25, 0.25, k)
    ring = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(k)])
    v = np.vstack([[0.0, 0.0, 1.0], [0.0, 0.0, -0.8], ring]) + offset
    top = [[0, 2 + i, 2 + (i + 1) % k] for i in range(k)]
    bottom = [[1, 2 + (i + 1) % k, 2 + i] for i in range(k)]
    return v, np.array(top + bottom)


def undirected_edges(faces):
    """Every edge of the faces once, as a sorted vertex pair, in sorted order."""
    return sorted({tuple(sorted(e)) for a, b, c in np.asarray(faces).tolist() for e in ((a, b), (b, c), (c, a))})


def rays_into_bipyramid(vertices, faces, offset, per_target: int, seed: int = 52):
    """Rays from outside `bipyramid(offset)` through each of its vertices, then each midpoint of its
    edges (in `undirected_edges` order), `per_target` rays a target, aimed at random points inside:
    each enters at t = 1 and leaves once. Returns (origins, directions)."""
    targets = np.vstack([vertices, [0.5 * (vertices[a] + vertices[b]) for a, b in undirected_edges(faces)]])
    targets = np.repeat(targets, per_target, axis=0)
    rng = np.random.default_rng(seed)
    inner = offset + np.column_stack([rng.uniform(-0.3, 0.3, (len(targets), 2)), rng.uniform(-0.2, 0.3, len(targets))])
    directions = inner - targets
    directions *= 2.0 / np.linalg.norm(directions, axis=1, keepdims=True)
    return targets - directions, directions
