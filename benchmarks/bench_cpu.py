"""The CPU engine (``vkray.Device("cpu")``: Embree on the host's cores) against what users of a
machine without a ray-tracing GPU have today, on the same rays and points in one run (issue 32):
Open3D's RaycastingScene (Embree 4, all cores) on tensors it built beforehand, trimesh+embreex
(Embree, one core), and vkray on Mesa's lavapipe where this machine has it. Prints a Markdown
report (``--out`` writes it too).

    python benchmarks/bench_cpu.py                      # 1M rays and points, bunny, fandisk, bunny x16
    python benchmarks/bench_cpu.py --rays 200000 --points 100000 --repeat 3

Rays: a 1000 x 1000 pinhole camera looking at the mesh (``oracle.camera_rays``), and
``oracle.random_rays(v, n, seed=5)``; points uniform in the mesh's bounding box grown by 10%
(seed 1). Every engine gets the same float32 arrays; vkray answers numpy in, numpy out, in its
fast tier (f32, Embree's robust watertight test) for rays, and for points in its exact tier
(contains: winding numbers, exact) and at the distances' f32 tier. Open3D: ``cast_rays``,
``test_occlusions``, ``count_intersections``, ``list_intersections``, ``compute_occupancy
(nsamples=1)``, ``compute_distance``, ``compute_signed_distance``. trimesh+embreex:
``intersects_first`` and ``intersects_any`` on one core. Times are the best of ``--repeat``
after a warm-up call; "× Open3D" is Open3D's time over vkray's (above 1: vkray is faster).
Builds: vkray's ``Device.mesh`` + ``scene`` against Open3D's ``add_triangles`` and its first query
(which builds its BVH), and vkray's ``Mesh.stats`` bytes a triangle.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import sys
from typing import Any, Callable, Dict, List, Optional

import numpy as np
from _report import Report, table_head
from _timing import best_run

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
from oracle import camera_rays, random_rays  # noqa: E402

# The column of the vkray device timed (`--device`): the CPU engine unless named otherwise.
VKRAY = "vkray cpu"
DEVICE = "cpu"
PRECISION = "reference"


def big_mesh(vertices: np.ndarray, faces: np.ndarray, times: int) -> Any:
    """The mesh with every triangle split into four, `times` times (bunny x16: 1.1M triangles)."""
    import trimesh

    for _ in range(times):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32)


def rates(n: int, seconds: Dict[str, float]) -> Dict[str, float]:
    return {name: n / s / 1e6 for name, s in seconds.items()}


class Engines:
    """One mesh's scenes in every engine, built before any timing."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, lavapipe: bool) -> None:
        import open3d as o3d
        import trimesh

        self.o3d = o3d
        cpu = vkray.Device() if DEVICE == "default" else vkray.Device(DEVICE)
        self.mesh_seconds, self.mesh = best_run(1, lambda: cpu.mesh(vertices, faces))
        self.cpu = cpu.scene([self.mesh])
        self.vulkan = None
        if lavapipe:
            software = [d for d in vkray.devices() if d.engine == "vulkan"]
            if software:
                device = vkray.Device(software[0].index)
                self.vulkan = device.scene([device.mesh(vertices, faces)])
        self.o3d_build_seconds, self.o3d_scene = best_run(1, lambda: self.open3d_scene(vertices, faces))
        self.trimesh = trimesh.Trimesh(vertices, faces, process=False).ray  # embreex's where installed

    def open3d_scene(self, vertices: np.ndarray, faces: np.ndarray) -> Any:
        o3d = self.o3d
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor.from_numpy(vertices), o3d.core.Tensor.from_numpy(faces.astype(np.uint32)))
        scene.count_intersections(o3d.core.Tensor(np.array([[0, 0, 0, 1, 1, 1]], np.float32)))  # builds
        return scene


def ray_table(report: Report, name: str, engines: Engines, origins: np.ndarray, dirs: np.ndarray, repeat: int) -> List[Dict[str, Any]]:
    o3d = engines.o3d
    n = len(dirs)
    origins = np.ascontiguousarray(np.broadcast_to(origins, dirs.shape), np.float32)
    dirs = np.ascontiguousarray(dirs, np.float32)
    rays = o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.hstack([origins, dirs])))
    cpu, vulkan, o3s, tm = engines.cpu, engines.vulkan, engines.o3d_scene, engines.trimesh
    queries: Dict[str, Dict[str, Callable[[], Any]]] = {
        "closest hit": {
            VKRAY: lambda: cpu.intersect(origins, dirs),
            "open3d": lambda: o3s.cast_rays(rays),
            "lavapipe": (lambda: vulkan.intersect(origins, dirs)) if vulkan else None,
            "embreex 1 core": lambda: tm.intersects_first(origins, dirs),
        },
        "occlusion": {
            VKRAY: lambda: cpu.occluded(origins, dirs),
            "open3d": lambda: o3s.test_occlusions(rays),
            "lavapipe": (lambda: vulkan.occluded(origins, dirs)) if vulkan else None,
            "embreex 1 core": lambda: tm.intersects_any(origins, dirs),
        },
        "count": {
            VKRAY: lambda: cpu.count(origins, dirs),
            "open3d": lambda: o3s.count_intersections(rays),
            "lavapipe": (lambda: vulkan.count(origins, dirs)) if vulkan else None,
        },
        "intersect_all": {
            VKRAY: lambda: cpu.intersect_all(origins, dirs, outputs=("t", "prim_id")),
            "open3d": lambda: o3s.list_intersections(rays),
            "lavapipe": (lambda: vulkan.intersect_all(origins, dirs, outputs=("t", "prim_id"))) if vulkan else None,
        },
    }
    rows = []
    for query, runs in queries.items():
        seconds = {}
        for engine, run in runs.items():
            if run is None:
                continue
            if engine.startswith("embreex"):
                os.environ["OMP_NUM_THREADS"] = "1"  # embreex's calls are single-threaded anyway
            seconds[engine] = best_run(repeat, run, warm=True)[0]
        r = rates(n, seconds)
        cores = os.cpu_count() or 1
        row = {
            "rays": name,
            "query": query,
            **{f"{e} (M/s)": round(v, 2) for e, v in r.items()},
            "× open3d": round(seconds["open3d"] / seconds[VKRAY], 2),
        }
        if "lavapipe" in seconds:
            row["× lavapipe"] = round(seconds["lavapipe"] / seconds[VKRAY], 2)
        if "embreex 1 core" in seconds:
            row["× embreex per core"] = round(seconds["embreex 1 core"] / seconds[VKRAY] / cores, 2)
        rows.append(row)
        report(f"- {name} rays, {query}: " + ", ".join(f"{k} {v}" for k, v in row.items() if k not in ("rays", "query")))
    return rows


def point_table(report: Report, engines: Engines, points: np.ndarray, repeat: int) -> List[Dict[str, Any]]:
    o3d = engines.o3d
    tensor = o3d.core.Tensor.from_numpy(points)
    cpu, vulkan, o3s = engines.cpu, engines.vulkan, engines.o3d_scene
    queries: Dict[str, Dict[str, Optional[Callable[[], Any]]]] = {
        "contains (exact) / occupancy nsamples=1": {
            VKRAY: lambda: cpu.contains(points, method="winding" if not engines.mesh.is_closed else "parity"),
            "open3d": lambda: o3s.compute_occupancy(tensor, nsamples=1),
            "lavapipe": (lambda: vulkan.contains(points, method="winding" if not engines.mesh.is_closed else "parity")) if vulkan else None,
        },
        "distance": {
            VKRAY: lambda: cpu.distance(points, precision=PRECISION),
            "open3d": lambda: o3s.compute_distance(tensor),
            "lavapipe": (lambda: vulkan.distance(points)) if vulkan else None,
        },
        "signed distance": {
            VKRAY: lambda: cpu.signed_distance(points, precision=PRECISION),
            "open3d": lambda: o3s.compute_signed_distance(tensor),
            "lavapipe": (lambda: vulkan.signed_distance(points)) if vulkan else None,
        },
    }
    if PRECISION != "exact":
        # The exact tier's signs come through the scene's inside grid (the reference tier's, each
        # point's own test), its distances from the same search: the same answers, checked here.
        same = np.array_equal(cpu.signed_distance(points, precision="exact"), cpu.signed_distance(points, precision=PRECISION))
        queries[f"signed distance, exact tier ({'the same answers' if same else 'ANSWERS DIFFER'})"] = {
            VKRAY: lambda: cpu.signed_distance(points, precision="exact"),
            "open3d": lambda: o3s.compute_signed_distance(tensor),
        }
    rows = []
    for query, runs in queries.items():
        seconds = {e: best_run(repeat, run, warm=True)[0] for e, run in runs.items() if run is not None}
        r = rates(len(points), seconds)
        row = {"query": query, **{f"{e} (M/s)": round(v, 2) for e, v in r.items()}}
        row["× open3d"] = round(seconds["open3d"] / seconds[VKRAY], 2)
        if "lavapipe" in seconds:
            row["× lavapipe"] = round(seconds["lavapipe"] / seconds[VKRAY], 2)
        rows.append(row)
        report(f"- points, {query}: " + ", ".join(f"{k} {v}" for k, v in row.items() if k != "query"))
    return rows


def markdown(rows: List[Dict[str, Any]]) -> str:
    columns: List[str] = []
    for row in rows:
        columns += [c for c in row if c not in columns]
    lines = [table_head(columns)]
    lines += ["| " + " | ".join(str(row.get(c, "")) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rays", type=int, default=1_000_000)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--meshes", default="stanford-bunny,fandisk,bunny-x16")
    parser.add_argument("--no-lavapipe", action="store_true", help="skip vkray on lavapipe (slow)")
    parser.add_argument("--no-rays", action="store_true", help="only the point queries")
    parser.add_argument("--no-points", action="store_true", help="only the ray queries")
    parser.add_argument("--out", default=None)
    parser.add_argument("--device", default="cpu", help="the vkray device timed: 'cpu' (default), 'default' (vkray.Device()) or a name")
    parser.add_argument("--distance-precision", default="reference", help="the tier of distances (default 'reference')")
    args = parser.parse_args()
    global VKRAY, DEVICE, PRECISION
    DEVICE, PRECISION = args.device, args.distance_precision
    VKRAY = "vkray cpu" if DEVICE == "cpu" else "vkray"
    report = Report()
    cpu_name = (vkray.Device() if DEVICE == "default" else vkray.Device(DEVICE)).name
    report(f"# bench_cpu: {platform.node()}, {os.cpu_count()} cores, {cpu_name}")
    report(f"`python benchmarks/bench_cpu.py {' '.join(sys.argv[1:])}`")
    side = int(round(args.rays**0.5))
    for mesh_name in args.meshes.split(","):
        if mesh_name == "bunny-x16":
            vertices, faces = big_mesh(*vkray.data.load_mesh("stanford-bunny"), 2)
        else:
            vertices, faces = vkray.data.load_mesh(mesh_name)
            vertices, faces = np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32)
        report(f"\n## {mesh_name}: {len(faces)} triangles")
        engines = Engines(vertices, faces, lavapipe=not args.no_lavapipe)
        stats = engines.mesh.stats
        report(
            f"- build: {VKRAY} {engines.mesh_seconds * 1e3:.1f} ms ({stats['bytes'] / len(faces):.0f} bytes a triangle), "
            f"Open3D {engines.o3d_build_seconds * 1e3:.1f} ms (add_triangles and its first query)"
        )
        rows: List[Dict[str, Any]] = []
        if not args.no_rays:
            origin, dirs = camera_rays(vertices.astype(np.float64), width=side, height=side)
            rows += ray_table(report, "camera", engines, origin[None, :], dirs, args.repeat)
            o, d = random_rays(vertices.astype(np.float64), args.rays, seed=5)
            rows += ray_table(report, "random", engines, o, d, args.repeat)
        lo, hi = vertices.min(0), vertices.max(0)
        grow = 0.1 * (hi - lo)
        points = np.random.default_rng(1).uniform(lo - grow, hi + grow, (args.points, 3)).astype(np.float32)
        prows = [] if args.no_points else point_table(report, engines, points, args.repeat)
        if rows:
            report("")
            report(markdown(rows))
        if prows:
            report("")
            report(markdown(prows))
    report.save(args.out)


if __name__ == "__main__":
    main()
