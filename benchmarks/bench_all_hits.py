"""vkray's all-hits queries (`intersect_all`, `count`, `contains`) in every precision tier (fast,
refined, exact: the GPU, on each backend the device has; reference: f64 on the CPU) against trimesh
(embreex and its numpy engine) and Open3D's RaycastingScene, on the same rays and points in one run;
prints a Markdown report.

    python benchmarks/bench_all_hits.py                               # everything, ~2 minutes on lavapipe's 2 cores
    python benchmarks/bench_all_hits.py --o3d-python /tmp/o3d-venv/bin/python --out /tmp/bench_all_hits.md

Open3D lives in its own virtual environment (``python3 -m venv /tmp/o3d-venv &&
/tmp/o3d-venv/bin/pip install open3d-cpu numpy``; its wheel needs ``libusb-1.0.so.0``): this script
saves the rays and points to an .npz, runs itself with ``--o3d-worker`` under that interpreter, and
reads Open3D's timings and answers back. Without it (or with ``--o3d-python ''``) Open3D is skipped.
trimesh's numpy engine (``trimesh.ray.ray_triangle``) needs ``rtree``, which requirements-dev.txt
does not list; it is skipped without it (``pip install --target /tmp/bench-extra rtree`` and
``PYTHONPATH=/tmp/bench-extra`` keep it out of .venv).

Speed: numpy in, numpy out (conversions included), best of ``--repeat`` after one warm-up call
(scene builds are not timed). Correctness: hard cases with known answers (rays through shared
vertices and edges at offsets 0, 1e3, 1e5 and 1e7; points whose rays run through a solid's vertices
and edges, for the direction each engine casts), answers counted per engine and per vkray tier and
backend, not assumed. ``--backends`` picks vkray's Vulkan backends (default: ray_query and pipeline,
those the device supports).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np
from _timing import open3d_scene

# ------------------------------------------------------------------------------------------------
# The directions each engine casts for inside/outside tests (read from their sources):
#   vkray: src/trace/tiers.rs PARITY_DIRECTION (0.6, 0.48, 0.64), one ray per point.
#   trimesh: ray/ray_util.py contains_points, (0.4395064455, 0.617598629942, 0.652231566745), cast
#     forwards and backwards; where the two parities disagree and neither ray is free it recasts
#     along a random direction.
#   Open3D 0.20: RaycastingScene.cpp VoteInsideOutside, nsamples directions (1 + U(-0.001, 0.001))
#     per component from std::mt19937(42) and std::uniform_real_distribution<float>, filled column by
#     column (direction j is draws 3j, 3j+1, 3j+2); the parity of count_intersections, majority vote.
VKRAY_DIRECTION = np.array([0.6, 0.48, 0.64])
TRIMESH_DIRECTION = np.array([0.4395064455, 0.617598629942, 0.652231566745])

# vkray's precision tiers: the f64 ones (each crossing exactly once; exact on the GPU, reference on
# the CPU) and the f32 ones (the GPU's f32 traversal decides which triangles are hit; refined then
# re-intersects them in f64).
TIERS = ("reference", "exact", "fast", "refined")
GPU_TIERS = ("fast", "refined", "exact")
HARD_OFFSETS = (0.0, 1e3, 1e5, 1e7)


def open3d_directions(n):
    """Open3D's vote directions, as libstdc++'s generate_canonical<float, 24> and
    uniform_real_distribution<float> make them from mt19937(42) (numpy's legacy MT19937 seeding is
    mt19937's init_genrand)."""
    bits = np.random.MT19937(0)
    bits._legacy_seeding(42)
    raw = bits.random_raw(3 * n).astype(np.float32)
    canonical = raw / np.float32(2.0**32)
    canonical = np.where(canonical >= 1, np.nextafter(np.float32(1), np.float32(0)), canonical).astype(np.float32)
    lo, hi = np.float32(-0.001), np.float32(0.001)
    value = (canonical * (hi - lo) + lo).astype(np.float32)
    return (np.float32(1) + value).astype(np.float32).reshape(n, 3)


# ------------------------------------------------------------------------------------------------
# The Open3D worker: runs under the Open3D venv's interpreter (no vkray, no trimesh there).


def _best(repeat, fn):
    times, cpu = [], []
    result = None
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    k = int(np.argmin(times))
    return times[k], cpu[k], result


def o3d_worker(inp, outp):
    import open3d as o3d

    data = np.load(inp)
    tasks = json.loads(str(data["tasks"]))
    repeat = int(data["repeat"])
    scenes = {}

    def scene_of(key):
        if key not in scenes:
            scenes[key] = open3d_scene(o3d, data[f"mesh__{key}__v"], data[f"mesh__{key}__f"])
        return scenes[key]

    def as_rays(o, d):
        return o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.hstack([o, d]), dtype=np.float32))

    def as_points(p):
        return o3d.core.Tensor.from_numpy(np.ascontiguousarray(p, dtype=np.float32))

    out, timings = {}, {}
    for task in tasks:
        tid, scene = task["id"], scene_of(task["mesh"])
        if task["kind"] == "rays":
            o, d = data[task["rays"] + "__o"], data[task["rays"] + "__d"]

            def list_numpy():
                result = scene.list_intersections(as_rays(o, d))
                return {k: v.numpy() for k, v in result.items()}

            def count_numpy():
                return scene.count_intersections(as_rays(o, d)).numpy()

            if task.get("time"):
                rays_t = as_rays(o, d).contiguous()
                t, c, listed = _best(repeat, list_numpy)
                timings[f"{tid}__list_numpy"] = (t, c)
                t, c, _ = _best(repeat, lambda: scene.list_intersections(rays_t))
                timings[f"{tid}__list_tensor"] = (t, c)
                t, c, counted = _best(repeat, count_numpy)
                timings[f"{tid}__count_numpy"] = (t, c)
                t, c, _ = _best(repeat, lambda: scene.count_intersections(rays_t))
                timings[f"{tid}__count_tensor"] = (t, c)
                hits = len(listed["t_hit"])
                timings[f"{tid}__list_bytes"] = (
                    sum(v.nbytes for k, v in listed.items() if k != "ray_splits") / max(hits, 1),
                    listed["ray_splits"].nbytes / len(o),
                )
            else:
                listed, counted = list_numpy(), count_numpy()
            out[f"{tid}__splits"] = listed["ray_splits"].astype(np.int64)
            out[f"{tid}__t"] = listed["t_hit"]
            out[f"{tid}__prim"] = listed["primitive_ids"].astype(np.int64)
            out[f"{tid}__ray"] = listed["ray_ids"].astype(np.int64)
            out[f"{tid}__count"] = counted.astype(np.int64)
        elif task["kind"] == "points":
            p = data[task["points"]]
            variants = {"default": {}, "ns1": {"nsamples": 1}, "ns3": {"nsamples": 3}}
            for label, kwargs in variants.items():
                if task.get("time") and label != "default":
                    pts_t = as_points(p).contiguous()
                    t, c, answer = _best(repeat, lambda: scene.compute_occupancy(as_points(p), **kwargs).numpy())
                    timings[f"{tid}__{label}_numpy"] = (t, c)
                    t, c, _ = _best(repeat, lambda: scene.compute_occupancy(pts_t, **kwargs))
                    timings[f"{tid}__{label}_tensor"] = (t, c)
                else:
                    answer = scene.compute_occupancy(as_points(p), **kwargs).numpy()
                out[f"{tid}__{label}"] = answer > 0.5
            if task.get("check_directions"):
                # Whether Open3D casts the directions open3d_directions() computes: the parity of
                # count_intersections along them must give compute_occupancy's answers.
                dirs = open3d_directions(3)
                votes = []
                for j in range(3):
                    rays = np.hstack([p.astype(np.float32), np.broadcast_to(dirs[j], p.shape)])
                    votes.append(scene.count_intersections(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays))).numpy() % 2 == 1)
                out[f"{tid}__dircheck1"] = votes[0]
                out[f"{tid}__dircheck3"] = np.sum(votes, axis=0) >= 2
    out["timings"] = np.array(json.dumps(timings))
    out["version"] = np.array(o3d.__version__)
    import multiprocessing

    out["cpus"] = np.array(multiprocessing.cpu_count())
    np.savez(outp, **out)


# ------------------------------------------------------------------------------------------------
# Helpers on the main side.


def best_of(repeat, fn):
    return _best(repeat, fn)


def fmt_rate(n, seconds):
    return f"{n / seconds / 1e6:.3f}"


def crossings(ray, t_dist, n, tol):
    """Per ray: hits, and crossings (hits within `tol` of distance along the ray merged)."""
    ray = np.asarray(ray, np.int64)
    t_dist = np.asarray(t_dist, np.float64)
    order = np.lexsort((t_dist, ray))
    ray, t_dist = ray[order], t_dist[order]
    hits = np.bincount(ray, minlength=n)
    new = np.ones(len(ray), bool)
    if len(ray) > 1:
        same = ray[1:] == ray[:-1]
        new[1:] = ~same | (np.diff(t_dist) > tol)
    clusters = np.bincount(ray[new], minlength=n)
    return hits, clusters


def plane_distance(tris, origins, directions):
    """Distance along the unit direction from each origin to its triangle's plane (trimesh gives ids)."""
    a, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    normal = np.cross(e1, e2)
    unit = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    return np.einsum("ij,ij->i", a - origins, normal) / np.einsum("ij,ij->i", unit, normal)


# Hits within this many bounding radii of the point a touching ray is aimed at count as hits there:
# wide enough for the two crossings a float32-rounded ray (moved by up to ~0.004 at 1e5) makes of
# a ridge it only touched in float64, which lie a few hundredths apart.
TOUCH_WINDOW = 0.1


def classify_rays(all_hits_brute, crossings, v, f, o, d, target_t, expected, radius, shifts=4, seed=5):
    """The exact answer for rays aimed through a vertex or edge, from a brute-force f64 test of every
    triangle (tests/oracle.py), independent of every engine: (keep, touch, why).

    At the point aimed at (within 1% of a radius), parallel rays moved 1e-7 radii sideways (in
    `shifts` random directions) miss every edge: if each crosses the surface there exactly once, the
    ray crosses it (answer: one hit there); if each crosses it 0 or 2 times, the ray only touches it
    (0 or 2 hits are both right).
    Elsewhere along the ray: `keep` needs exactly `expected - 1` other crossings, none within 1e-9 of
    an edge (a tilted ray may clip a non-flat surface again)."""
    n = len(o)
    length = np.linalg.norm(d, axis=1)
    window = 1e-2 * radius / length
    rng = np.random.default_rng(seed)
    local = []
    for _ in range(shifts):
        e = rng.normal(size=(n, 3))
        e -= (np.einsum("ij,ij->i", e, d) / length**2)[:, None] * d
        e /= np.linalg.norm(e, axis=1, keepdims=True)
        ref = all_hits_brute(v[f], o + 1e-7 * radius * e, d, target_t - window, target_t + window)
        local.append(np.bincount(ref["ray"], minlength=n))
    local = np.array(local)
    crosses = (local == 1).all(axis=0)
    touch = (local % 2 == 0).all(axis=0)
    ref = all_hits_brute(v[f], o, d)
    r = ref["ray"]
    away = np.abs(ref["t"] - target_t[r]) > window[r]
    _, others = crossings(r[away], ref["t"][away] * length[r[away]], n, 1e-7 * radius)
    unclean = np.zeros(n, bool)
    unclean[r[away & (ref["margin"] < 1e-9)]] = True
    keep = crosses & (others == expected - 1) & ~unclean
    why = (f"{int(np.sum(~crosses))} touch there or are undecided, "
           f"{int(np.sum(crosses & ((others != expected - 1) | unclean)))} cross elsewhere too")
    # Touching rays count only where no other crossing comes within TOUCH_WINDOW radii of the point.
    close = np.zeros(n, bool)
    close[r[away & (np.abs(ref["t"] - target_t[r]) * length[r] < TOUCH_WINDOW * radius)]] = True
    return keep, touch & ~close, why


class Table:
    def __init__(self, *header):
        self.rows = [list(header), ["---"] * len(header)]

    def add(self, *cells):
        self.rows.append([str(c) for c in cells])

    def __str__(self):
        return "\n".join("| " + " | ".join(r) + " |" for r in self.rows)


# ------------------------------------------------------------------------------------------------


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rays", type=int, default=100_000, help="random rays per mesh for all hits and counts")
    parser.add_argument("--points", type=int, default=100_000, help="random points per mesh for contains")
    parser.add_argument("--native-rays", type=int, default=300, help="rays (and 3x points) for trimesh's numpy engine")
    parser.add_argument("--winding-points", type=int, default=2000, help="points timed for vkray's winding method")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--backends", default="ray_query,pipeline", help="vkray backends for the GPU tiers")
    parser.add_argument("--o3d-python", default="/tmp/o3d-venv/bin/python", help="interpreter with open3d ('' to skip)")
    parser.add_argument("--out", default=None, help="also write the report to this file")
    args = parser.parse_args()
    wall_start = time.perf_counter()
    load_before = os.getloadavg()[0]

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
    import trimesh
    from trimesh.ray import ray_pyembree

    import oracle  # tests/oracle.py: the geometry and the references the tests use too
    import vkray

    try:
        import rtree  # noqa: F401
        from trimesh.ray import ray_triangle

        native_ok, native_why = True, ""
    except ImportError as exc:
        ray_triangle, native_ok, native_why = None, False, f"skipped: {exc}"

    lines = []
    say = lines.append
    backends = []
    for b in args.backends.split(","):
        info = vkray.devices()[0]
        if (b == "ray_query" and info.ray_query) or (b == "pipeline" and info.ray_tracing_pipeline):
            backends.append(b)
    devices = {b: vkray.Device(backend=b) for b in backends}
    device = devices[backends[0]]  # holds the scenes of the reference tier
    repeat = args.repeat

    # ---- inputs -----------------------------------------------------------------------------
    meshes = {name: oracle.load_mesh(full) for name, full in (("bunny", "stanford-bunny"), ("fandisk", "fandisk"), ("spot", "spot"))}
    npz = {"repeat": np.array(repeat)}
    tasks = []

    def add_mesh(key, v, f):
        npz[f"mesh__{key}__v"] = v
        npz[f"mesh__{key}__f"] = f

    for key, (v, f) in meshes.items():
        add_mesh(key, v, f)
    speed_rays = {}
    for key in ("bunny", "fandisk"):
        v, _ = meshes[key]
        o, d = oracle.random_rays(v, args.rays, seed=7)
        speed_rays[key] = (o, d)
        npz[f"speed_{key}__o"], npz[f"speed_{key}__d"] = o, d
        tasks.append({"id": f"speed_{key}", "kind": "rays", "mesh": key, "rays": f"speed_{key}", "time": True})
    speed_points = {}
    for key in ("fandisk", "spot"):
        v, _ = meshes[key]
        lo, hi = v.min(axis=0), v.max(axis=0)
        pad = 0.1 * (hi - lo)
        p = np.random.default_rng(8).uniform(lo - pad, hi + pad, (args.points, 3))
        speed_points[key] = p
        npz[f"pts_{key}"] = p
        tasks.append({"id": f"pts_{key}", "kind": "points", "mesh": key, "points": f"pts_{key}", "time": True,
                      "check_directions": True})

    # (a) rays through shared vertices and edges, at every offset of HARD_OFFSETS
    hard_rays = []  # (label, offset, key, v, f, o, d, expected crossings, t of the crossing aimed at, radius, kinds)
    cube_v, cube_f = oracle.box()
    # The cube's face diagonals: the edges its coplanar triangle pairs share.
    face_normals = np.cross(cube_v[cube_f[:, 1]] - cube_v[cube_f[:, 0]], cube_v[cube_f[:, 2]] - cube_v[cube_f[:, 0]])
    diagonals = []
    for a, b in oracle.undirected_edges(cube_f):
        tris = [t for t in range(len(cube_f)) if a in cube_f[t] and b in cube_f[t]]
        if len(tris) == 2 and np.allclose(np.cross(face_normals[tris[0]], face_normals[tris[1]]), 0):
            diagonals.append((a, b, face_normals[tris[0]] / np.linalg.norm(face_normals[tris[0]])))
    for offset in HARD_OFFSETS:
        n = 16
        v, f, _ = oracle.heightfield(n, seed=47, offset=offset)
        key = f"hf_{offset:g}"
        add_mesh(key, v, f)
        targets = oracle.shared_targets(v, f, n)
        kinds = np.array(["vertex (6 triangles)"] * (n - 2) ** 2 + ["axis-aligned edge"] * (2 * (n - 2) * (n - 3))
                         + ["diagonal edge"] * (n - 3) ** 2)
        radius = oracle.bounds(v)[1]
        for sign, label in ((-1.0, "heightfield, vertical rays down"), (1.0, "heightfield, vertical rays up")):
            o = targets.copy()
            o[:, 2] = offset + 5.0 if sign < 0 else offset - 5.0
            d = np.broadcast_to([0.0, 0.0, sign], o.shape).copy()
            hard_rays.append((label, offset, key, v, f, o, d, 1, np.abs(o[:, 2] - targets[:, 2]), radius, kinds))
        o, d = oracle.rays_through(targets, seed=48)
        hard_rays.append(("heightfield, tilted rays", offset, key, v, f, o, d, 1, np.ones(len(o)), radius, kinds))
        v, f = oracle.fan(offset)
        key = f"fan_{offset:g}"
        add_mesh(key, v, f)
        targets = np.repeat(np.vstack([v[0], 0.5 * (v[0] + v[1:])]), 100, axis=0)
        kinds = np.array(["centre vertex (11 triangles)"] * 100 + ["spoke (edge)"] * (len(targets) - 100))
        o, d = oracle.rays_through(targets, seed=50)
        hard_rays.append(("closed fan (11 triangles), centre and spokes", offset, key, v, f, o, d, 1, np.ones(len(o)),
                          oracle.bounds(v)[1], kinds))
        v, f = oracle.bipyramid(offset)
        key = f"bip_{offset:g}"
        add_mesh(key, v, f)
        kinds = np.repeat(np.array(["vertex"] * len(v) + ["edge"] * len(oracle.undirected_edges(f))), 30)
        o, d = oracle.rays_into_bipyramid(v, f, offset, per_target=30)
        hard_rays.append(("closed bipyramid, entered through vertices and edges", offset, key, v, f, o, d, 2,
                          np.ones(len(o)), oracle.bounds(v)[1], kinds))
        # The unit cube entered through its faces' diagonals (the edge each face's two triangles
        # share): rays perpendicular to the face, and tilted towards random points inside. A convex
        # solid: every ray through its interior crosses it twice.
        v = cube_v + offset
        key = f"cubeh_{offset:g}"
        add_mesh(key, v, cube_f)
        w = np.array([0.1, 0.25, 0.5, 0.75, 0.9])
        targets = np.vstack([cube_v[a] + w[:, None] * (cube_v[b] - cube_v[a]) for a, b, _ in diagonals])
        normals = np.repeat(np.array([nrm for _, _, nrm in diagonals]), len(w), axis=0)
        rng = np.random.default_rng(53)
        inner = rng.uniform(0.2, 0.8, (len(targets), 10, 3))
        tilted = inner - targets[:, None, :]
        dirs = np.concatenate([-normals[:, None, :], tilted / np.linalg.norm(tilted, axis=2, keepdims=True)], axis=1)
        kinds = np.tile(np.array(["perpendicular to the face"] + ["tilted"] * 10), len(targets))
        targets = np.repeat(targets, 11, axis=0) + offset
        d = 2.0 * dirs.reshape(-1, 3)
        o = targets - d
        hard_rays.append(("unit cube (12 triangles), entered through its faces' diagonals", offset, key, v, cube_f, o, d,
                          2, np.ones(len(o)), oracle.bounds(v)[1], kinds))
    for i, case in enumerate(hard_rays):
        npz[f"hard{i}__o"], npz[f"hard{i}__d"] = case[5], case[6]
        tasks.append({"id": f"hard{i}", "kind": "rays", "mesh": case[2], "rays": f"hard{i}"})

    # (b) contains: points whose rays (for each engine's direction) run through vertices and edges
    o3d_dirs = open3d_directions(3).astype(np.float64)
    engine_dirs = [VKRAY_DIRECTION, TRIMESH_DIRECTION, *o3d_dirs]
    steps = np.array([0.25, 0.5, 0.75, 1.0, 1.5])
    steps = np.concatenate([steps, -steps])

    def lattice(values):
        return np.array(np.meshgrid(values, values, values, indexing="ij")).reshape(3, -1).T

    cube_v, cube_f = oracle.box()
    cube_targets = np.vstack(
        [cube_v]
        + [cube_v[a] + w * (cube_v[b] - cube_v[a]) for a, b in oracle.undirected_edges(cube_f)
           if np.count_nonzero(cube_v[a] != cube_v[b]) == 1 for w in (0.25, 0.5)]
        + [lattice([0.0, 0.5, 1.0])]  # face centres among them
    )
    cube_targets = np.unique(cube_targets, axis=0)
    cube_local = np.vstack(
        [lattice(np.arange(-1.0, 2.001, 0.25))]
        + [cube_targets - s * dirn for dirn in engine_dirs for s in steps]
    )
    cube_local = np.unique(cube_local, axis=0)
    # Points off the surface but within 0.01 of it (d ≈ (1, 1, 1) and a step equal to a coordinate)
    # are left out: float32 rounding at 1e5 (ulp 0.0078) puts them on the surface.
    gap = np.linalg.norm(np.maximum(0, np.maximum(-cube_local, cube_local - 1)), axis=1)
    depth = np.minimum(cube_local, 1 - cube_local).min(axis=1)
    distance = np.where(gap > 0, gap, np.maximum(depth, 0))
    cube_local = cube_local[(distance == 0) | (distance >= 0.01)]
    hard_points = []  # (label, key, v, f, points, expected or None, on_surface or None)
    for offset in (0.0, 1e5):
        key = f"cube_{offset:g}"
        add_mesh(key, cube_v + offset, cube_f)
        inside = ((cube_local >= 0) & (cube_local <= 1)).all(axis=1)
        interior = ((cube_local > 1e-12) & (cube_local < 1 - 1e-12)).all(axis=1)
        hard_points.append((f"unit cube at offset {offset:g}", key, cube_v + offset, cube_f, cube_local + offset,
                            inside, inside & ~interior))
    fv, ff = meshes["fandisk"]
    f_radius = oracle.bounds(fv)[1]
    rng = np.random.default_rng(9)
    fedges = np.array(oracle.undirected_edges(ff))
    ftargets = np.vstack([fv[rng.choice(len(fv), 150, replace=False)],
                          fv[fedges[rng.choice(len(fedges), 150, replace=False)]].mean(axis=1)])
    fsteps = f_radius * np.array([0.01, 0.05, 0.2, 0.5])
    fsteps = np.concatenate([fsteps, -fsteps])
    lo, hi = fv.min(axis=0), fv.max(axis=0)
    fpoints = np.vstack(
        [lattice(np.linspace(0, 1, 12)) * (1.2 * (hi - lo)) + lo - 0.1 * (hi - lo)]
        + [ftargets - s * dirn for dirn in engine_dirs for s in fsteps]
    )
    hard_points.append(("fandisk", "fandisk", fv, ff, fpoints, None, None))
    for i, case in enumerate(hard_points):
        npz[f"hpts{i}"] = case[4]
        tasks.append({"id": f"hpts{i}", "kind": "points", "mesh": case[1], "points": f"hpts{i}"})

    # ---- Open3D, in its own interpreter -------------------------------------------------------
    o3d = None
    o3d_note = "skipped: no --o3d-python"
    if args.o3d_python:
        if not os.path.exists(args.o3d_python):
            o3d_note = f"skipped: {args.o3d_python} does not exist"
        else:
            with tempfile.TemporaryDirectory() as tmp:
                inp, outp = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
                np.savez(inp, tasks=np.array(json.dumps(tasks)), **npz)
                start = time.perf_counter()
                proc = subprocess.run([args.o3d_python, os.path.abspath(__file__), "--o3d-worker", inp, outp],
                                      capture_output=True, text=True)
                o3d_wall = time.perf_counter() - start
                if proc.returncode != 0:
                    o3d_note = f"skipped: the worker failed ({proc.stderr.strip().splitlines()[-1:]})"
                else:
                    with np.load(outp) as z:
                        o3d = {k: z[k] for k in z.files}
                    o3d_timings = json.loads(str(o3d["timings"]))
                    o3d_note = (f"Open3D {o3d['version']} (own venv, {int(o3d['cpus'])} CPUs, nthreads=0: all), "
                                f"worker ran {o3d_wall:.1f} s")

    # ---- vkray and trimesh: speed ---------------------------------------------------------------
    t_mesh = {k: trimesh.Trimesh(v, f, process=False) for k, (v, f) in meshes.items()}
    env = f"PYTHONPATH={os.environ['PYTHONPATH']} " if os.environ.get("PYTHONPATH") else ""
    say(f"Command: `{env}{' '.join([os.path.basename(sys.executable)] + sys.argv)}`\n")
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), platform.machine())
    import embreex

    say(f"Host: {cpu}, {os.cpu_count()} CPUs; Python {platform.python_version()}, numpy {np.__version__}. "
        f"vkray {getattr(vkray, '__version__', '?')}: `precision=\"reference\"` f64 on all CPU cores, `\"fast\"`, "
        f"`\"refined\"` and `\"exact\"` on the Vulkan device {device.name} ({vkray.devices()[0].driver}), backends "
        f"{', '.join(backends)} (on lavapipe the \"GPU\" is the same CPU cores); trimesh {trimesh.__version__} with embreex "
        f"{getattr(embreex, '__version__', '?')} (Embree 4, float32; one thread: embreex casts in a loop "
        f"holding the GIL); trimesh numpy engine: {'rtree ' + __import__('rtree').__version__ if native_ok else native_why}; "
        f"{o3d_note}.\n")
    say(f"Times: best of {repeat}, after a warm-up call, numpy in (float64 arrays, as `oracle.random_rays` makes "
        "them) and numpy out, every conversion included (Open3D: stacking into an (N, 6) float32 array, "
        "`Tensor.from_numpy`, `.numpy()` of every output). \"Open3D tensors\" is the call alone on tensors "
        "built beforehand, outputs left as tensors. CPU/wall is process CPU time over wall time (how many "
        "cores the engine kept busy). vkray ÷ peer > 1: vkray (the reference tier, where not said otherwise) is "
        "faster.\n")

    say("## 1. Speed\n")
    say(f"### All hits along {args.rays:,} random rays (`oracle.random_rays`: from a sphere of 2 bounding radii "
        "towards random points of the bounding box, a quarter in random directions)\n")
    table = Table("mesh (triangles)", "engine and call", "rays", "best s", "CPU/wall", "Mrays/s", "hits",
                  "rays whose hit count ≠ vkray reference's", "vkray reference ÷ row")
    ctable = Table("mesh", "engine and call", "rays", "best s", "CPU/wall", "Mrays/s",
                   "rays whose count ≠ vkray reference's", "vkray reference ÷ row")
    bytes_rows = []
    disagreements = {}
    peer_counts = {}  # (mesh, engine) -> hit counts per ray (trimesh numpy: the first rays only)
    rates = {}
    for key in ("bunny", "fandisk"):
        v, f = meshes[key]
        o, d = speed_rays[key]
        n = len(o)
        scene = device.scene(device.mesh(v, f))
        scene.intersect_all(o[:10], d[:10], precision="reference")
        scene.count(o[:10], d[:10], precision="reference")
        t_all, c_all, hits = best_of(repeat, lambda: scene.intersect_all(o, d, precision="reference"))
        t_lean, c_lean, lean = best_of(repeat, lambda: scene.intersect_all(o, d, outputs=["t", "prim_id"],
                                                                           precision="reference"))
        t_cnt, c_cnt, counts = best_of(repeat, lambda: scene.count(o, d, precision="reference"))
        assert (counts == hits.counts).all()
        vk_rate = n / t_all
        vk_crate = n / t_cnt
        name = f"{key} ({len(f):,})"
        per_hit = [a for a in (hits.ray_index, hits.t, hits.prim_id, hits.instance_id, hits.custom_index,
                                hits.geometry_id, hits.uv, hits.normal, hits.position) if a is not None]
        h = int(hits.offsets[-1])
        bytes_rows.append((key, "vkray `intersect_all` default outputs (ray_index, t, prim_id, instance_id, "
                           "custom_index, uv, normal)", sum(a.nbytes for a in per_hit) / h,
                           (hits.offsets.nbytes + hits.counts.nbytes) / n))
        bytes_rows.append((key, "vkray `intersect_all(outputs=['t', 'prim_id'])` (ray_index, t, prim_id)",
                           sum(a.nbytes for a in (lean.ray_index, lean.t, lean.prim_id)) / h,
                           (lean.offsets.nbytes + lean.counts.nbytes) / n))
        table.add(name, "vkray reference `intersect_all` (default outputs)", f"{n:,}", f"{t_all:.3f}",
                  f"{c_all / t_all:.1f}", fmt_rate(n, t_all), f"{h:,}", "—", "—")
        table.add(name, "vkray reference `intersect_all(outputs=['t', 'prim_id'])`", f"{n:,}", f"{t_lean:.3f}",
                  f"{c_lean / t_lean:.1f}", fmt_rate(n, t_lean), f"{h:,}", "—", "—")
        ctable.add(name, "vkray reference `count`", f"{n:,}", f"{t_cnt:.3f}", f"{c_cnt / t_cnt:.1f}",
                   fmt_rate(n, t_cnt), "—", "—")
        vk_counts = hits.counts
        # Rates for the ratio table: (mesh, call) -> {engine: rays per second}.
        rates[(name, "all")] = {"vkray reference": n / t_lean}
        rates[(name, "count")] = {"vkray reference": n / t_cnt}

        # vkray's GPU tiers, on each backend: the hit lists lean (t and prim_id, as the peers' ids).
        for backend in backends:
            gdev = devices[backend]
            gscene = gdev.scene(gdev.mesh(v, f))
            for tier in GPU_TIERS:
                gscene.intersect_all(o[:10], d[:10], outputs=["t", "prim_id"], precision=tier)
                gscene.count(o[:10], d[:10], precision=tier)
                t_g, c_g, gh = best_of(repeat, lambda: gscene.intersect_all(o, d, outputs=["t", "prim_id"],
                                                                           precision=tier))
                t_gc, c_gc, gc = best_of(repeat, lambda: gscene.count(o, d, precision=tier))
                gdiff = np.nonzero(gh.counts != vk_counts)[0]
                disagreements[(key, f"vkray {tier}, {backend}")] = gdiff
                peer_counts[(key, f"vkray {tier}, {backend}")] = gh.counts
                same = "" if (gc == gh.counts).all() else f" (`count` ≠ `intersect_all`'s counts on {int(np.sum(gc != gh.counts))} rays)"
                label = f"vkray {tier}, {backend}"
                table.add(name, f"{label} `intersect_all(outputs=['t', 'prim_id'])`", f"{n:,}", f"{t_g:.3f}",
                          f"{c_g / t_g:.1f}", fmt_rate(n, t_g), f"{int(gh.offsets[-1]):,}", f"{len(gdiff):,}",
                          f"{vk_rate / (n / t_g):.2f}")
                ctable.add(name, f"{label} `count`{same}", f"{n:,}", f"{t_gc:.3f}", f"{c_gc / t_gc:.1f}",
                           fmt_rate(n, t_gc), f"{int(np.sum(gc != vk_counts)):,}", f"{vk_crate / (n / t_gc):.2f}")
                rates[(name, "all")][label] = n / t_g
                rates[(name, "count")][label] = n / t_gc

        # trimesh + embreex
        inter = ray_pyembree.RayMeshIntersector(t_mesh[key])
        inter.intersects_id(o[:10], d[:10], multiple_hits=True)
        t_e, c_e, (tri, ray) = best_of(repeat, lambda: inter.intersects_id(o, d, multiple_hits=True, return_locations=False))
        e_counts = np.bincount(ray, minlength=n)
        diff = np.nonzero(e_counts != vk_counts)[0]
        disagreements[(key, "trimesh+embreex")] = diff
        peer_counts[(key, "trimesh+embreex")] = e_counts
        rates[(name, "all")]["trimesh+embreex"] = n / t_e
        table.add(name, "trimesh+embreex `intersects_id(multiple_hits=True)`", f"{n:,}", f"{t_e:.3f}",
                  f"{c_e / t_e:.1f}", fmt_rate(n, t_e), f"{len(tri):,}", f"{len(diff):,}", f"{vk_rate / (n / t_e):.2f}")
        t_l, c_l, (loc, lray, ltri) = best_of(repeat, lambda: inter.intersects_location(o, d, multiple_hits=True))
        table.add(name, "trimesh+embreex `intersects_location`", f"{n:,}", f"{t_l:.3f}", f"{c_l / t_l:.1f}",
                  fmt_rate(n, t_l), f"{len(lray):,}", f"{int(np.sum(np.bincount(lray, minlength=n) != vk_counts)):,}",
                  f"{vk_rate / (n / t_l):.2f}")
        t_ec, c_ec, ec = best_of(repeat, lambda: np.bincount(
            inter.intersects_id(o, d, multiple_hits=True, return_locations=False)[1], minlength=n))
        ctable.add(name, "trimesh+embreex `intersects_id` + `np.bincount` (no count call)", f"{n:,}", f"{t_ec:.3f}",
                   f"{c_ec / t_ec:.1f}", fmt_rate(n, t_ec), f"{int(np.sum(ec != vk_counts)):,}",
                   f"{vk_crate / (n / t_ec):.2f}")
        rates[(name, "count")]["trimesh+embreex"] = n / t_ec
        bytes_rows.append((key, "trimesh `intersects_id` (index_tri, index_ray: int64)",
                           (tri.nbytes + ray.nbytes) / max(len(tri), 1), 0.0))
        bytes_rows.append((key, "trimesh `intersects_location` (+ locations float64)",
                           (loc.nbytes + lray.nbytes + ltri.nbytes) / max(len(lray), 1), 0.0))

        # trimesh's numpy engine, on the first rays only
        if native_ok:
            k = min(args.native_rays, n)
            nat = ray_triangle.RayMeshIntersector(t_mesh[key])
            nat.intersects_id(o[:2], d[:2], multiple_hits=True)  # builds the r-tree
            t_n, c_n, (ntri, nray) = best_of(repeat, lambda: nat.intersects_id(o[:k], d[:k], multiple_hits=True))
            n_counts = np.bincount(nray, minlength=k)
            ndiff = np.nonzero(n_counts != vk_counts[:k])[0]
            disagreements[(key, "trimesh numpy")] = ndiff
            peer_counts[(key, "trimesh numpy")] = n_counts
            table.add(name, f"trimesh numpy engine `intersects_id` (first {k} rays)", f"{k:,}", f"{t_n:.3f}",
                      f"{c_n / t_n:.1f}", fmt_rate(k, t_n), f"{len(ntri):,}", f"{len(ndiff):,} of {k}",
                      f"{vk_rate / (k / t_n):.0f}")
            ctable.add(name, f"trimesh numpy engine, same call + bincount (first {k} rays)", f"{k:,}", f"{t_n:.3f}",
                       f"{c_n / t_n:.1f}", fmt_rate(k, t_n), f"{len(ndiff):,} of {k}", f"{vk_crate / (k / t_n):.0f}")
        else:
            table.add(name, "trimesh numpy engine", "", "", "", "", "", native_why, "")

        # Open3D
        if o3d is not None:
            tid = f"speed_{key}"
            l_counts = np.diff(o3d[f"{tid}__splits"])
            c_counts = o3d[f"{tid}__count"]
            ldiff = np.nonzero(l_counts != vk_counts)[0]
            disagreements[(key, "Open3D list")] = ldiff
            peer_counts[(key, "Open3D list")] = l_counts
            for label, suffix in (("numpy in/out", "numpy"), ("tensors", "tensor")):
                t, c = o3d_timings[f"{tid}__list_{suffix}"]
                rates[(name, "all")][f"Open3D, {label}"] = n / t
                rates[(name, "count")][f"Open3D, {label}"] = n / o3d_timings[f"{tid}__count_{suffix}"][0]
                table.add(name, f"Open3D `list_intersections`, {label}", f"{n:,}", f"{t:.3f}", f"{c / t:.1f}",
                          fmt_rate(n, t), f"{int(l_counts.sum()):,}", f"{len(ldiff):,}", f"{vk_rate / (n / t):.2f}")
            for label, suffix in (("numpy in/out", "numpy"), ("tensors", "tensor")):
                t, c = o3d_timings[f"{tid}__count_{suffix}"]
                ctable.add(name, f"Open3D `count_intersections`, {label}", f"{n:,}", f"{t:.3f}", f"{c / t:.1f}",
                           fmt_rate(n, t), f"{int(np.sum(c_counts != vk_counts)):,}", f"{vk_crate / (n / t):.2f}")
            per_hit, per_ray = o3d_timings[f"{tid}__list_bytes"]
            bytes_rows.append((key, "Open3D `list_intersections` (ray_ids, geometry_ids, primitive_ids: uint32; "
                               "t_hit float32; primitive_uvs 2×float32)", per_hit, per_ray))

        # Who is right where the engines disagree: the brute-force f64 oracle on those rays, hits
        # at one point (t within 1e-9 radii: a shared edge or vertex) merged into one crossing.
        radius = oracle.bounds(v)[1]
        rays = np.unique(np.concatenate([x for (kk, _), x in disagreements.items() if kk == key] or [np.zeros(0, int)]))
        rays = rays[:300]
        if len(rays):
            ref = oracle.all_hits_brute(v[f], o[rays], d[rays])
            length = np.linalg.norm(d[rays], axis=1)
            _, brute = crossings(ref["ray"], ref["t"] * length[ref["ray"]], len(rays), 1e-9 * radius)
            ambiguous = np.zeros(len(rays), bool)
            ambiguous[ref["ray"][ref["margin"] < 1e-6]] = True
            disagreements[(key, "__brute")] = (rays, brute, ambiguous)
    say(str(table) + "\n")
    say(f"### Hit counts along the same rays\n\n{ctable}\n")

    # vkray's tiers against the peers: speed ratios.
    say("### vkray's tiers against the peers: speed ratios in this run\n")
    say("Rays per second of each vkray tier and backend over those of each peer, on the same rays in the same run "
        "(> 1: vkray faster). All hits: vkray `intersect_all(outputs=['t', 'prim_id'])` against trimesh+embreex "
        "`intersects_id(multiple_hits=True)` and Open3D `list_intersections`; counts: vkray `count` against "
        "`intersects_id` + `np.bincount` and Open3D `count_intersections`.\n")
    peers = ["vkray reference", "trimesh+embreex", "Open3D, numpy in/out", "Open3D, tensors"]
    rtable = Table("mesh", "query", "vkray tier, backend", "Mrays/s", *[f"÷ {p}" for p in peers])
    for (name, call), r in rates.items():
        for engine, rate in r.items():
            if not engine.startswith("vkray"):
                continue
            rtable.add(name, "all hits" if call == "all" else "count", engine, f"{rate / 1e6:.3f}",
                       *[f"{rate / r[p]:.2f}" if p in r else "n/a" for p in peers])
    say(str(rtable) + "\n")

    # Where engines disagree on random rays.
    say("Rays whose hit counts differ from vkray's reference tier, checked against a brute-force f64 test of every "
        "ray against every triangle (`oracle.all_hits_brute`, closed triangles; hits within 1e-9 radii along the ray "
        "merged into one crossing; \"near an edge\" = some hit within 1e-6 of a triangle's edge in barycentric terms, "
        "or a ray within 1e-6 of a triangle's plane; at most 300 rays per mesh checked):\n")
    dt = Table("mesh", "engine", "rays ≠ vkray reference", "of which vkray reference = brute force",
               "engine = brute force", "near an edge (either may be right)")
    for key in ("bunny", "fandisk"):
        if (key, "__brute") not in disagreements:
            continue
        rays, brute, ambiguous = disagreements[(key, "__brute")]
        pos = {r: i for i, r in enumerate(rays.tolist())}
        o, d = speed_rays[key]
        vk = device.scene(device.mesh(*meshes[key])).count(o[rays], d[rays], precision="reference")
        for (kk, engine), diffs in disagreements.items():
            if kk != key or engine.startswith("__") or not len(diffs):
                continue
            diff = [r for r in diffs.tolist() if r in pos]
            idx = np.array([pos[r] for r in diff], int)
            peer = peer_counts[(key, engine)][rays[idx]]
            dt.add(key, engine, f"{len(diffs)} (checked {len(idx)})", int(np.sum(vk[idx] == brute[idx])),
                   int(np.sum(peer == brute[idx])), int(ambiguous[idx].sum()))
    say((str(dt) if len(dt.rows) > 2 else "None: every engine's hit count equals vkray's on every ray.") + "\n")

    # contains
    say(f"### Inside or outside: {args.points:,} uniform random points in the bounding box grown by 10% per side\n")
    table = Table("mesh (triangles)", "engine and call", "points", "best s", "CPU/wall", "Mpoints/s",
                  "inside", "answers ≠ vkray reference parity", "vkray reference ÷ row")
    check_rows = []
    for key in ("fandisk", "spot"):
        v, f = meshes[key]
        p = speed_points[key]
        n = len(p)
        name = f"{key} ({len(f):,})"
        mesh = device.mesh(v, f)
        scene = device.scene(mesh)
        scene.contains(p[:10], precision="reference")
        t_p, c_p, inside = best_of(repeat, lambda: scene.contains(p, precision="reference"))
        vk_rate = n / t_p
        table.add(name, f"vkray reference `contains(precision='reference')` (parity; `is_closed`={mesh.is_closed})",
                  f"{n:,}", f"{t_p:.3f}", f"{c_p / t_p:.1f}", fmt_rate(n, t_p), f"{int(inside.sum()):,}", "—", "—")
        for backend in backends:
            gdev = devices[backend]
            gscene = gdev.scene(gdev.mesh(v, f))
            gscene.contains(p[:10])
            t_g, c_g, gin = best_of(repeat, lambda: gscene.contains(p))
            table.add(name, f"vkray exact, {backend} `contains` (the default: parity, exact)", f"{n:,}", f"{t_g:.3f}",
                      f"{c_g / t_g:.1f}", fmt_rate(n, t_g), f"{int(gin.sum()):,}", f"{int(np.sum(gin != inside)):,}",
                      f"{vk_rate / (n / t_g):.2f}")
        w = min(args.winding_points, n)
        t_w, c_w, wind = best_of(repeat, lambda: scene.contains(p[:w], method="winding"))
        table.add(name, f"vkray `contains(method='winding')` (first {w:,})", f"{w:,}", f"{t_w:.3f}", f"{c_w / t_w:.1f}",
                  fmt_rate(w, t_w), f"{int(wind.sum()):,}", f"{int(np.sum(wind != inside[:w]))} of {w}",
                  f"{vk_rate / (w / t_w):.0f}")
        answers = {}
        tm = trimesh.Trimesh(v, f, process=False)
        tm.contains(p[:10])
        t_t, c_t, tin = best_of(repeat, lambda: tm.contains(p))
        answers["trimesh+embreex"] = tin
        table.add(name, "trimesh+embreex `mesh.contains`", f"{n:,}", f"{t_t:.3f}", f"{c_t / t_t:.1f}", fmt_rate(n, t_t),
                  f"{int(tin.sum()):,}", f"{int(np.sum(tin != inside)):,}", f"{vk_rate / (n / t_t):.2f}")
        if native_ok:
            k = min(3 * args.native_rays, n)
            nat = ray_triangle.RayMeshIntersector(tm)
            nat.contains_points(p[:2])
            t_n, c_n, nin = best_of(repeat, lambda: nat.contains_points(p[:k]))
            table.add(name, f"trimesh numpy engine `contains_points` (first {k:,})", f"{k:,}", f"{t_n:.3f}",
                      f"{c_n / t_n:.1f}", fmt_rate(k, t_n), f"{int(nin.sum()):,}", f"{int(np.sum(nin != inside[:k]))} of {k}",
                      f"{vk_rate / (k / t_n):.0f}")
        if o3d is not None:
            tid = f"pts_{key}"
            for label, ns in (("nsamples=1 (= the default in 0.20)", "ns1"), ("nsamples=3", "ns3")):
                ans = o3d[f"{tid}__{ns}"]
                answers[f"Open3D {ns}"] = ans
                for io, suffix in (("numpy in/out", "numpy"), ("tensors", "tensor")):
                    t, c = o3d_timings[f"{tid}__{ns}_{suffix}"]
                    table.add(name, f"Open3D `compute_occupancy`, {label}, {io}", f"{n:,}", f"{t:.3f}", f"{c / t:.1f}",
                              fmt_rate(n, t), f"{int(ans.sum()):,}", f"{int(np.sum(ans != inside)):,}",
                              f"{vk_rate / (n / t):.2f}")
            assert (o3d[f"{tid}__default"] == o3d[f"{tid}__ns1"]).all()
            check_rows.append((key, int(np.sum(o3d[f"{tid}__dircheck1"] == o3d[f"{tid}__ns1"])),
                               int(np.sum(o3d[f"{tid}__dircheck3"] == o3d[f"{tid}__ns3"])), n))
        # Disagreements, judged by the generalized winding number in numpy (oracle.winding_numbers).
        bad = np.unique(np.concatenate([np.nonzero(a != inside)[0] for a in answers.values()] or [np.zeros(0, int)]))
        if len(bad):
            wn = oracle.winding_numbers(v, f, p[bad])
            truth = wn >= 0.5
            notes = [f"vkray parity right on {int(np.sum(inside[bad] == truth))} of {len(bad)}"]
            for label, a in answers.items():
                notes.append(f"{label} right on {int(np.sum(a[bad] == truth))}")
            say_line = (f"- {key}: {len(bad)} points where some engine differs from vkray; by the numpy winding number "
                        f"(min |w − ½| {np.abs(wn - 0.5).min():.3f}): " + ", ".join(notes) + ".")
            check_rows.append(("note", say_line))
    say(str(table) + "\n")
    for row in check_rows:
        if row[0] == "note":
            say(row[1])
    for row in check_rows:
        if row[0] != "note":
            key, a1, a3, n = row
            say(f"- Open3D's ray directions (computed here from mt19937(42), see the script): the parity of "
                f"`count_intersections` along direction 0 equals `compute_occupancy(nsamples=1)` on {a1:,} of {n:,} "
                f"{key} points, the majority over directions 0–2 equals `nsamples=3` on {a3:,} of {n:,}.")
    say("")

    # ---- 2. Correctness ----------------------------------------------------------------------
    say("## 2. Correctness on hard cases\n")
    say("### (a) Rays through shared vertices and edges: one hit per crossing\n")
    say("Heightfield (`oracle.heightfield(16, seed=47)`, 450 triangles): vertical rays down and up, and tilted rays "
        "(`oracle.rays_through`, up to 55° off vertical), through every interior vertex and the midpoint of every "
        "interior edge (axis-aligned and diagonal): the surface is crossed exactly once. Closed fan (11 triangles "
        "around a vertex, as in tests/test_all_hits.py): 100 random rays from above through the centre and through "
        "each spoke's midpoint: once. Closed bipyramid (18 triangles): rays from outside through each vertex and edge "
        "midpoint towards random points inside: twice (in and out). Unit cube (`oracle.box`, 12 triangles): rays "
        "through 5 points of each face's diagonal (the edge the face's two triangles share), one perpendicular to the "
        "face and 10 tilted towards random points inside: twice. Offsets (0, 1e3, 1e5, 1e7) are added to every "
        "coordinate in float64 (the engines in float32 get the rounded vertices and rays).\n")
    say("The exact answer is decided without any engine, by a brute-force f64 test of every triangle "
        "(`oracle.all_hits_brute`) on the offset-0 copy of the rays: at the point aimed at, 4 parallel rays moved "
        "1e-7 radii sideways (which miss every edge) must each cross the surface exactly once within 1% of a radius "
        "of it, and the ray must cross nowhere else (the bipyramid: exactly one exit, not within 1e-9 of an edge). "
        "A tilted ray can instead only touch the non-flat fan along a ridge or valley edge, or clip it again "
        "elsewhere: such rays are left out of this table (\"rays kept\"), and the touching ones get their own "
        "table below. The cube needs no such test: it is convex, so a ray through its inside crosses it twice.\n")
    say("Each engine's hits on a ray are sorted along it and hits within 2% of the mesh's bounding radius of each "
        "other merged into one crossing (distinct crossings here are ≥ 30% apart; float32 engines at 1e5 land within "
        "~0.01 of the true point). **missing**: fewer crossings than the exact answer; **dup**: some crossing reported "
        "by more than one hit; **extra**: more crossings than the answer. Cells: missing / dup / extra, in rays. "
        "vkray columns: `intersect_all(outputs=['t', 'prim_id'], precision=...)` on a scene of each backend's device; "
        "\"reference\" and \"exact\" ran on every backend and show one cell where all backends gave the same one "
        "(otherwise each backend's). \"vkray reference on f32 input\": vkray given the float32-rounded vertices and "
        "rays that Open3D gets, to tell rounding of the input from the engines' own misses (at 1e7 float32's spacing "
        "is 1, as large as the meshes themselves: the float32 engines get other meshes and rays there). Open3D's "
        "`count_intersections` is in the counts table below.\n")
    f64_tiers = ("reference", "exact")
    f32_tiers = ("fast", "refined")
    # Display columns: (title, engine keys whose cells it shows).
    vk_cols = [(f"vkray {t}", [f"vkray {t}, {b}" for b in backends]) for t in f64_tiers]
    vk_cols += [(f"vkray {t}, {b}", [f"vkray {t}, {b}"]) for t in f32_tiers for b in backends]
    peer_cols = [(c, [c]) for c in ("vkray reference on f32 input", "trimesh+embreex", "trimesh numpy", "Open3D list")]
    cols = vk_cols + peer_cols
    count_cols = vk_cols + [("Open3D count", ["Open3D count"])]
    consistency_cols = ["reference: backends differ", "exact: backends differ", "exact ≠ reference"]
    consistency_cols += [f"{t}: backends differ" for t in f32_tiers if len(backends) > 1]
    consistency_cols += [f"refined ≠ fast, {b}" for b in backends]
    consistency_cols += ["`count` ≠ `intersect_all(...).counts`"]

    def merged(keys, cells, fmt):
        shown = [fmt(cells[k]) for k in keys if k in cells]
        if not shown:
            return "n/a"
        if len(set(shown)) == 1:
            return shown[0]
        return "; ".join(f"{k.rsplit(', ', 1)[-1]}: {fmt(cells[k])}" for k in keys if k in cells)

    def triple(c):
        return "{} / {} / {}".format(*c)

    def pair(c):
        return "{} / {}".format(*c)

    def differing(a, b, t_rtol=None, as_sets=False):
        """Rays whose hit lists differ: other counts, other triangles (as_sets: in any order), or
        (t_rtol given) t apart."""
        bad = a.counts != b.counts
        ia, ib = np.repeat(~bad, a.counts), np.repeat(~bad, b.counts)
        if as_sets:
            pa = a.prim_id[ia][np.lexsort((a.prim_id[ia], a.ray_index[ia]))]
            pb = b.prim_id[ib][np.lexsort((b.prim_id[ib], b.ray_index[ib]))]
            bad = bad.copy()
            bad[np.sort(a.ray_index[ia])[pa != pb]] = True
            return bad
        diff = a.prim_id[ia] != b.prim_id[ib]
        if t_rtol is not None:
            ta, tb = a.t[ia].astype(np.float64), b.t[ib].astype(np.float64)
            diff |= np.abs(ta - tb) > t_rtol * np.maximum(1.0, np.abs(ta))
        bad = bad.copy()
        bad[a.ray_index[ia][diff]] = True
        return bad

    table = Table("case", "offset", "rays kept", *[c for c, _ in cols])
    ctable = Table("case", "offset", "rays kept", *[c for c, _ in count_cols])
    xtable = Table("case", "offset", "rays", *consistency_cols)
    totals = {}
    ctotals = {}
    left_out = []
    classes = {}
    touch_table = Table("case", "offset", "touching rays", *[c for c, _ in cols])
    touch_rows = 0
    f32_detail = []  # (label, offset, backend, tier, histogram of hits on the kept rays)
    for i, (label, offset, _key, v, f, o, d, expected, target_t, radius, kinds) in enumerate(hard_rays):
        built = len(o)
        if label not in classes:
            assert offset == 0.0
            if label.startswith("unit cube"):  # convex: two crossings for every ray through the interior
                classes[label] = (np.ones(built, bool), np.zeros(built, bool), "none (convex solid)")
            else:
                classes[label] = classify_rays(oracle.all_hits_brute, crossings, v, f, o, d, target_t, expected, radius)
        keep, touch, why = classes[label]
        length = np.linalg.norm(d, axis=1)
        tol = 0.02 * radius
        v32, o32, d32 = (x.astype(np.float32).astype(np.float64) for x in (v, o, d))
        length32 = np.linalg.norm(d32, axis=1)
        # Every engine's hits on every ray built: (ray, distance along it); counts where only counts.
        found, counted, runs = {}, {}, {}
        for backend in backends:
            dev = devices[backend]
            sc = dev.scene(dev.mesh(v, f))
            for tier in TIERS:
                ah = sc.intersect_all(o, d, outputs=["t", "prim_id"], precision=tier)
                runs[(tier, backend)] = (ah, sc.count(o, d, precision=tier))
                found[f"vkray {tier}, {backend}"] = (ah.ray_index, ah.t.astype(np.float64) * length[ah.ray_index])
                counted[f"vkray {tier}, {backend}"] = runs[(tier, backend)][1]
        ah = device.scene(device.mesh(v32, f)).intersect_all(o32, d32, outputs=["t"], precision="reference")
        found["vkray reference on f32 input"] = (ah.ray_index, ah.t * length32[ah.ray_index])
        tm = trimesh.Trimesh(v, f, process=False)
        tri, ray = ray_pyembree.RayMeshIntersector(tm).intersects_id(o, d, multiple_hits=True, return_locations=False)
        found["trimesh+embreex"] = (ray, plane_distance(v[f[tri]], o[ray], d[ray]))
        if native_ok:
            tri, ray = ray_triangle.RayMeshIntersector(tm).intersects_id(o, d, multiple_hits=True)
            found["trimesh numpy"] = (ray, plane_distance(v[f[tri]], o[ray], d[ray]))
        if o3d is not None:
            tid = f"hard{i}"
            ray = o3d[f"{tid}__ray"]
            found["Open3D list"] = (ray, o3d[f"{tid}__t"].astype(np.float64) * length32[ray])
            counted["Open3D count"] = o3d[f"{tid}__count"]
        cells, tcells, ccells = {}, {}, {}
        index = np.cumsum(keep) - 1  # kept rays, renumbered
        aimed = target_t * length
        for c, (ray, dist) in found.items():
            sel = keep[ray]
            hits, clusters = crossings(index[ray[sel]], dist[sel], int(keep.sum()), tol)
            cells[c] = np.array([np.sum(clusters < expected), np.sum(hits > clusters), np.sum(clusters > expected)])
            near = touch[ray] & (np.abs(dist - aimed[ray]) < TOUCH_WINDOW * radius)
            tcells[c] = int(np.sum(np.bincount(ray[near], minlength=built)[touch] % 2 == 1))
            if c.startswith("vkray ") and c.split(", ")[0].split()[1] in f32_tiers:
                for kind in dict.fromkeys(kinds):
                    f32_detail.append((label, kind, offset, c, np.bincount(hits[kinds[keep] == kind], minlength=8)))
        for c, cnt in counted.items():
            ccells[c] = np.array([np.sum(cnt[keep] < expected), np.sum(cnt[keep] > expected)])
        for c, cell in cells.items():
            totals[c] = totals.get(c, 0) + cell
        for c, cell in ccells.items():
            ctotals[c] = ctotals.get(c, 0) + cell
        table.add(label, f"{offset:g}", f"{int(keep.sum()):,} of {built:,}", *[merged(k, cells, triple) for _, k in cols])
        ctable.add(label, f"{offset:g}", f"{int(keep.sum()):,} of {built:,}",
                   *[merged(k, ccells, pair) for _, k in count_cols])
        if touch.any():
            touch_rows += 1
            touch_table.add(label, f"{offset:g}", f"{int(touch.sum())}", *[merged(k, tcells, str) for _, k in cols])
        # Consistency on every ray built (kept or not): backends, tiers, count against intersect_all.
        b0 = backends[0]
        xrow = []
        for tier in f64_tiers:
            xrow.append(sum(int(differing(runs[(tier, b0)][0], runs[(tier, b)][0], 0.0).sum()) for b in backends[1:]))
        xrow.append(", ".join(str(int(differing(runs[("exact", b)][0], runs[("reference", b0)][0], 0.0).sum()))
                              for b in backends))
        if len(backends) > 1:
            for tier in f32_tiers:
                xrow.append(sum(int(differing(runs[(tier, b0)][0], runs[(tier, b)][0]).sum()) for b in backends[1:]))
        for b in backends:
            xrow.append(int(differing(runs[("refined", b)][0], runs[("fast", b)][0], as_sets=True).sum()))
        mismatch = {f"{t}, {b}": int(np.sum(runs[(t, b)][1] != runs[(t, b)][0].counts)) for t in TIERS for b in backends}
        xrow.append(", ".join(f"{k} {n}" for k, n in mismatch.items() if n) or "0")
        xtable.add(label, f"{offset:g}", f"{built:,}", *xrow)
        if offset == 0.0:
            left_out.append(f"{label}: {why}")
    table.add("**total**", "", "", *[merged(k, totals, triple) for _, k in cols])
    ctable.add("**total**", "", "", *[merged(k, ctotals, pair) for _, k in count_cols])
    say(str(table) + "\n")
    say("Rays left out (the same at every offset): " + "; ".join(left_out) + ".\n")
    if touch_rows:
        say("Rays that touch the surface at the point aimed at without crossing it (a tilted ray along a ridge or "
            "valley edge of the fan or heightfield, found as above): there 0 or 2 hits are both consistent (what "
            "matters for counting crossings and parity is that the number is even: a float32-rounded ray, moved "
            "sideways by up to ~0.004 at 1e5, misses the ridge or crosses both of its faces a few hundredths apart); "
            "cells: rays with an odd number of hits within 10% of a radius of that point.\n")
        say(str(touch_table) + "\n")

    say("#### Counts: `count` against the analytic number of crossings\n")
    say("The same kept rays; vkray `count(precision=...)` per tier and backend, Open3D `count_intersections`. Cells: "
        "rays counted below / above the answer.\n")
    say(str(ctable) + "\n")

    say("#### Consistency between backends and tiers, on every ray built\n")
    say("Rays whose hit lists (`intersect_all(outputs=['t', 'prim_id'])`) differ: other counts or other triangles "
        "or any t not bit-equal (exact against reference: one number per backend). The f64 tiers must agree everywhere; fast and "
        "refined may differ between backends (each driver's f32 traversal decides), and refined must report fast's "
        "triangles. Last column: rays where `count` differs from `intersect_all(...).counts` at the same tier and "
        "backend.\n")
    say(str(xtable) + "\n")

    say("#### What the f32 tiers report where rays meet shared edges and vertices\n")
    say("Hits per kept ray (before merging), `intersect_all` in the fast and refined tiers, by what the ray is aimed "
        "through: how many rays got 0, 1, 2, … hits, and the most on one ray. The answer is 1 hit per ray (the "
        "bipyramid and the cube: 2; the bipyramid's exit and a tilted ray's exit from the cube lie away from any edge, "
        "while a ray perpendicular to a cube face leaves through the opposite face's diagonal, which runs the same "
        "way). Rows with the same counts at several offsets or for several tiers and backends are merged.\n")
    dtable = Table("case", "rays through", "offsets", "tiers, backends", "0 hits", "1", "2", "3", "4", "5", "6+",
                   "most")
    groups = {}  # (label, kind, offset, histogram) -> engines with that histogram
    order = {}
    for label, kind, offset, c, hist in f32_detail:
        row = (*[int(x) for x in hist[:6]], int(hist[6:].sum()), int(np.nonzero(hist)[0].max()))
        order.setdefault((label, kind), len(order))
        groups.setdefault((label, kind, offset, row), []).append(c.replace("vkray ", ""))
    by_offsets = {}  # (label, kind, engines, histogram) -> offsets
    for (label, kind, offset, row), names in groups.items():
        every = [f"{t}, {b}" for t in f32_tiers for b in backends]
        shown = "all: " + " and ".join(f32_tiers) + ", " + " and ".join(backends) if sorted(names) == sorted(every) \
            else "; ".join(names)
        by_offsets.setdefault((label, kind, shown, row), []).append(f"{offset:g}")
    for (label, kind, names, row), offsets in sorted(by_offsets.items(), key=lambda x: order[x[0][:2]]):
        dtable.add(label, kind, ", ".join(offsets), names, *[str(x) for x in row])
    say(str(dtable) + "\n")

    say("### (b) Inside or outside where rays run through vertices and edges\n")
    say("Points: a lattice, plus points placed on the lines through the solid's vertices and edge points along "
        "each engine's own ray direction (vkray (0.6, 0.48, 0.64); trimesh (0.4395, 0.6176, 0.6522), which it also "
        "casts backwards; Open3D's three vote directions, ≈ (1, 1, 1) ± 0.001 each, from mt19937(42)), at distances "
        "before and after the vertex or edge, so that each engine's ray from such a point passes through a vertex or "
        "an edge (to within the rounding of the point). Unit cube (12 triangles): a quarter-unit lattice from −1 to 2 "
        "and such points through its 8 vertices, 24 edge points and the face centres (leaving out those within 0.01 of "
        "the surface but not on it, which float32 rounding at 1e5 would put on it); the answer is analytic. "
        "Fandisk: a 12³ lattice over its bounding box grown by 10%, and such points through 150 random vertices and "
        "150 random edge midpoints; **the reference is vkray's `contains(method='winding')`** (generalized winding "
        "number in f64), itself checked against the numpy winding number of `tests/oracle.py` where any engine "
        "disagrees with it.\n")
    say("Cells: wrong answers among points off the surface (of all off-surface points). Points exactly on the "
        "surface (cube lattice points on a face, edge or vertex) have no single right answer: vkray counts them as "
        "inside (documented); the last column gives, per engine, how many of them it called inside. vkray: "
        "`contains(p)` (parity in the exact tier, the default) on each backend, `contains(p, precision='reference')`, "
        "`contains(p, method='winding')`; \"f32 points\": the default call on float32-rounded vertices and points. "
        "The f32 tiers have no `contains` (they raise `UnsupportedError`).\n")
    engines = [*[f"vkray parity exact, {b}" for b in backends], "vkray parity reference", "vkray winding",
               "vkray parity, f32 points", "trimesh+embreex", "trimesh numpy", "Open3D nsamples=1 (default)",
               "Open3D nsamples=3"]
    table = Table("solid", "points", *engines, "on-surface points called inside")
    fandisk_note = ""
    for i, (label, _key, v, f, p, expected, on_surface) in enumerate(hard_points):
        n = len(p)
        ans = {}
        for backend in backends:
            dev = devices[backend]
            ans[f"vkray parity exact, {backend}"] = dev.scene(dev.mesh(v, f)).contains(p)  # the default tier
        scene = device.scene(device.mesh(v, f))
        ans["vkray parity reference"] = scene.contains(p, precision="reference")
        ans["vkray winding"] = scene.contains(p, method="winding")
        s32 = device.scene(device.mesh(v.astype(np.float32).astype(np.float64), f))
        ans["vkray parity, f32 points"] = s32.contains(p.astype(np.float32).astype(np.float64))
        tm = trimesh.Trimesh(v, f, process=False)
        ans["trimesh+embreex"] = tm.contains(p)
        if native_ok:
            ans["trimesh numpy"] = ray_triangle.RayMeshIntersector(tm).contains_points(p)
        if o3d is not None:
            ans["Open3D nsamples=1 (default)"] = o3d[f"hpts{i}__ns1"]
            ans["Open3D nsamples=3"] = o3d[f"hpts{i}__ns3"]
            assert (o3d[f"hpts{i}__default"] == o3d[f"hpts{i}__ns1"]).all()
        if expected is None:  # fandisk: vkray's winding number is the reference
            expected = ans["vkray winding"]
            bad = np.unique(np.concatenate([np.nonzero(a != expected)[0] for a in ans.values()]))
            dist = oracle.surface_distance(v, f, p[bad]) if len(bad) else np.zeros(0)
            near = bad[dist < 1e-6 * f_radius]
            on_surface = np.zeros(n, bool)
            on_surface[near] = True
            if len(bad):
                wn = oracle.winding_numbers(v, f, p[bad])
                agree = int(np.sum((wn >= 0.5) == expected[bad]))
                fandisk_note = (f"Fandisk: {len(bad)} points where some engine differs from the reference; there the "
                                f"numpy winding number agrees with vkray's on {agree} of {len(bad)} "
                                f"(|w − round(w)| ≤ {np.abs(wn - np.round(wn)).max():.1e}); their distances to the "
                                f"surface: min {dist.min():.2e}, median {np.median(dist):.2e} (radius {f_radius:.2f}); "
                                f"{len(near)} within 1e-6 radii, treated as on the surface.")
        off = ~on_surface
        row = []
        for e in engines:
            if e in ans:
                row.append(f"{int(np.sum((ans[e] != expected) & off))} of {int(off.sum()):,}")
            else:
                row.append("n/a")
        onsurf = ", ".join(f"{e.split(' (')[0]} {int(np.sum(ans[e] & on_surface))}" for e in engines if e in ans)
        table.add(label, f"{n:,}", *row, f"{int(on_surface.sum())} points: {onsurf}" if on_surface.any() else "none")
    say(str(table) + "\n")
    if fandisk_note:
        say(fandisk_note + "\n")

    say("### (c) Bytes per stored hit\n")
    say("Measured from the returned numpy arrays on the 100k random rays above (per hit: arrays with one entry per "
        "hit; per ray: offsets and counts, or Open3D's ray_splits).\n")
    table = Table("mesh", "result", "bytes per hit", "bytes per ray")
    for key, label, per_hit, per_ray in bytes_rows:
        table.add(key, label, f"{per_hit:.1f}", f"{per_ray:.1f}")
    say(str(table) + "\n")
    say(f"Total wall time of this run: {time.perf_counter() - wall_start:.0f} s. 1-minute load average before the "
        f"run {load_before:.2f}, after it {os.getloadavg()[0]:.2f} (other work on the machine skews the times: "
        "the CPU/wall columns show whether an engine got the cores it asked for).")

    report = "\n".join(lines) + "\n"
    print(report)
    if args.out:
        pathlib.Path(args.out).write_text(report)


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--o3d-worker":
        o3d_worker(sys.argv[2], sys.argv[3])
    else:
        main()
