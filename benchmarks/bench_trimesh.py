"""vkray.trimesh's ``RayMeshIntersector`` at precision "exact" (the default) and "fast" against
trimesh's own engines (embreex: ``trimesh.ray.ray_pyembree``; numpy: ``trimesh.ray.ray_triangle``)
on the same rays and points in one run: speed, agreement on random rays, and rays with a known
answer (issue 11: is "exact" cheap enough to be the default?). Prints a Markdown report.

    python benchmarks/bench_trimesh.py                                    # H100: 100k and 1M rays
    python benchmarks/bench_trimesh.py --sizes 10000 100000 --winding-points 1000   # lavapipe

The figures in docs/benchmarks.md (issue 11) came from exactly these two commands, each with
``--out FILE`` added (the first on the NVIDIA H100 through the device tool, ~2 minutes, most of it
the bunny's winding numbers on 16 cores; the second on lavapipe's 2 cores, ~1.5 minutes).

Calls, as trimesh's users make them: ``intersects_id(o, d, multiple_hits=True)`` ("all hits"),
``intersects_id(o, d, multiple_hits=False)`` ("first hit"), ``intersects_any(o, d)`` ("any") and
``contains_points(p)`` ("contains"). Rays: ``oracle.random_rays(v, n, seed=5)``; points: uniform in
the mesh's bounding box (seed 1). The bunny is open: vkray answers ``contains_points`` there with
the generalized winding number (on the CPU cores), so it is timed on ``--winding-points`` points
only; trimesh's engines use their ray parity on both meshes. vkray's "fast" intersector answers
``contains_points`` in the exact tier too (the f32 tiers cannot decide parity).

Speed: numpy in, numpy out, best of ``--repeat`` after one warm-up call on the whole batch (scene
builds are not timed). trimesh's numpy engine is slow and memory-hungry on random rays (each ray's
box holds most triangles: about 3 GB for 1,000 rays on the bunny), so it runs on the first
``--triangle-rays`` rays and points of the smallest size only, best of ``--triangle-repeat``; it
needs ``rtree`` (skipped without it; on the H100 its wheel travelled with numpy's and embreex's).

Agreement ("≠ exact"): per call, the rays whose number of hits (all hits), hit-or-miss (first
hit, any) or inside-or-outside (contains) differs from vkray exact's answer on the same rays.

Hard cases: rays from outside through each vertex and each edge midpoint of ``trimesh.creation.box()``
(12 triangles) and ``trimesh.creation.icosphere(subdivisions=3)`` (1,280 triangles) and through
the centre: by symmetry each crosses the closed surface exactly twice, both times at a vertex or
an edge. Counted per engine: rays reported with fewer than two crossings (a lost crossing), with
more than two (a duplicated one), and rays whose first hit is a miss.
"""

from __future__ import annotations

import argparse
import importlib.util
import pathlib
import platform
import sys
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import trimesh
from _report import Report
from _timing import best_run as best

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
import vkray.trimesh as vkt  # noqa: E402
from oracle import load_mesh, random_rays  # noqa: E402

CALLS = ("all hits", "first hit", "any", "contains")


def engines(mesh: trimesh.Trimesh) -> Dict[str, Any]:
    out: Dict[str, Any] = {
        "exact": vkt.RayMeshIntersector(mesh, precision="exact"),
        "fast": vkt.RayMeshIntersector(mesh, precision="fast"),
    }
    if trimesh.ray.has_embree:
        out["embree"] = trimesh.ray.ray_pyembree.RayMeshIntersector(mesh)
    if importlib.util.find_spec("rtree") is not None:
        out["numpy"] = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    return out


def call(engine: Any, name: str, o: np.ndarray, d: np.ndarray, p: np.ndarray) -> Callable[[], Any]:
    if name == "all hits":
        return lambda: engine.intersects_id(o, d, multiple_hits=True)
    if name == "first hit":
        return lambda: engine.intersects_id(o, d, multiple_hits=False)
    if name == "any":
        return lambda: engine.intersects_any(o, d)
    return lambda: engine.contains_points(p)


def per_ray(name: str, answer: Any, n: int) -> np.ndarray:
    """The answer as one value a ray (or point): hit count, hit-or-miss, inside-or-outside."""
    if name == "all hits":
        return np.bincount(np.asarray(answer[1], dtype=np.int64), minlength=n)
    if name == "first hit":
        hit = np.zeros(n, dtype=bool)
        hit[np.asarray(answer[1], dtype=np.int64)] = True
        return hit
    return np.asarray(answer, dtype=bool)


def hard_rays(mesh: trimesh.Trimesh) -> Tuple[np.ndarray, np.ndarray]:
    """Rays from 3x outside through each vertex and each edge midpoint and through the centre."""
    centre = mesh.bounds.mean(axis=0)
    through = np.vstack([mesh.vertices, mesh.vertices[mesh.edges_unique].mean(axis=1)])
    origins = centre + 3.0 * (through - centre)
    return origins, centre - origins


def mrate(rate: float) -> str:
    """Millions a second: two decimals from 1 M/s, three from 0.1 M/s, else three significant digits."""
    return f"{rate / 1e6:.2f}" if rate >= 1e6 else f"{rate / 1e6:.3f}" if rate >= 1e5 else f"{rate / 1e6:.3g}"


def ratio(a: Optional[float], b: Optional[float]) -> str:
    return "-" if a is None or b is None else f"{a / b:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", nargs="+", default=["stanford-bunny", "fandisk"])
    parser.add_argument("--sizes", nargs="+", type=int, default=[100_000, 1_000_000])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--triangle-rays", type=int, default=1_000)
    parser.add_argument("--triangle-repeat", type=int, default=1)
    parser.add_argument("--winding-points", type=int, default=10_000)
    parser.add_argument("--out", default=None, help="also write the report here")
    args = parser.parse_args()

    emit = Report()

    device = vkt.default_device()
    emit(
        f"Device: {device.name} ({device.backend}); vkray {getattr(vkray, '__version__', '?')}; "
        f"trimesh {trimesh.__version__}; numpy {np.__version__}; Python {platform.python_version()}; "
        f"{platform.machine()}, {len(__import__('os').sched_getaffinity(0))} CPUs"
    )
    emit(f"Command: python benchmarks/bench_trimesh.py {' '.join(sys.argv[1:])}")
    emit()

    speed_rows: List[str] = []
    agree_rows: List[str] = []
    smallest = min(args.sizes)
    for mesh_name in args.meshes:
        v, f = load_mesh(mesh_name)
        mesh = trimesh.Trimesh(v, f, process=False)
        closed = bool(mesh.is_watertight)
        eng = engines(mesh)
        for n in args.sizes:
            o, d = random_rays(v, n, seed=5)
            n_points = n if closed else min(n, args.winding_points)
            p = np.random.default_rng(1).uniform(v.min(axis=0), v.max(axis=0), size=(n_points, 3))
            k = min(args.triangle_rays, n)
            for c in CALLS:
                count = n_points if c == "contains" else n
                times: Dict[str, float] = {}
                answers: Dict[str, np.ndarray] = {}
                for e, engine in eng.items():
                    if e == "numpy":
                        if n != smallest:
                            continue
                        kp = min(k, n_points)
                        run = call(engine, c, o[:k], d[:k], p[:kp])
                        call(engine, c, o[:10], d[:10], p[:10])()
                        t, a = best(args.triangle_repeat, run)
                        times[e] = (kp if c == "contains" else k) / t
                        answers[e] = per_ray(c, a, kp if c == "contains" else k)
                        continue
                    run = call(engine, c, o, d, p)
                    run()  # warm-up: the scene, the pipelines, the allocations
                    t, a = best(args.repeat, run)
                    times[e] = count / t
                    answers[e] = per_ray(c, a, count)
                label = c if c != "contains" else ("contains (parity)" if closed else "contains (vkray: winding)")
                shown = f"{count:,}"
                tri = "-"
                if "numpy" in times:
                    tri = f"{mrate(times['numpy'])} ({len(answers['numpy']):,})"
                speed_rows.append(
                    f"| {mesh_name} | {label} | {shown} | {mrate(times['exact'])} | "
                    f"{mrate(times['fast'])} | "
                    f"{mrate(times['embree']) if 'embree' in times else '-'} | {tri} | "
                    f"{ratio(times['fast'], times['exact'])} | {ratio(times['exact'], times.get('embree'))} | "
                    f"{ratio(times['fast'], times.get('embree'))} |"
                )
                ex = answers["exact"]

                def differ(e: str, ex: np.ndarray = ex, answers: Dict[str, np.ndarray] = answers) -> str:
                    if e not in answers:
                        return "-"
                    other = answers[e]
                    return f"{int(np.count_nonzero(other != ex[: len(other)])):,}"

                extra = ""
                if c == "all hits":
                    extra = f"{int(ex.sum()):,}"
                elif c in ("first hit", "any"):
                    extra = f"{int(ex.sum()):,} hit"
                else:
                    extra = f"{int(ex.sum()):,} inside"
                agree_rows.append(
                    f"| {mesh_name} | {label} | {shown} | {extra} | {differ('fast')} | {differ('embree')} | "
                    f"{differ('numpy')} |"
                )

    emit(
        "Speed (M rays or points per second; numpy engine on the first rays/points, count in brackets; "
        "exact cost = fast rate / exact rate, the default's price; × embree = vkray rate / embree rate):"
    )
    emit()
    emit(
        "| mesh | call | rays | vkray exact | vkray fast | trimesh+embreex | trimesh numpy | exact cost | "
        "× embree, exact | × embree, fast |"
    )
    emit("|---|---|---|---|---|---|---|---|---|---|")
    for row in speed_rows:
        emit(row)
    emit()
    emit(
        "Agreement on the same rays (vkray exact's answer, then how many rays or points each engine "
        "answers differently: hit count, hit-or-miss, inside-or-outside):"
    )
    emit()
    emit(
        "| mesh | call | rays | exact: hits / hit / inside | ≠ exact: vkray fast | ≠ exact: embreex | "
        "≠ exact: numpy (its rays) |"
    )
    emit("|---|---|---|---|---|---|---|")
    for row in agree_rows:
        emit(row)
    emit()

    emit(
        "Hard cases (each ray crosses the closed surface exactly twice, both times at a vertex or an "
        "edge): rays reported with fewer than 2 crossings / more than 2 / a first hit that misses:"
    )
    emit()
    shapes = {
        "box (12 triangles)": trimesh.creation.box(),
        "icosphere, 3 subdivisions (1,280 triangles)": trimesh.creation.icosphere(subdivisions=3),
    }
    names = ["exact", "fast", "embree", "numpy"]
    emit(
        "| shape | rays | "
        + " | ".join(
            f"vkray {e}" if e in ("exact", "fast") else ("trimesh+embreex" if e == "embree" else "trimesh numpy")
            for e in names
        )
        + " |"
    )
    emit("|---|---|" + "---|" * len(names))
    for label, shape in shapes.items():
        o, d = hard_rays(shape)
        eng = engines(shape)
        cells = []
        for e in names:
            if e not in eng:
                cells.append("-")
                continue
            _, ray = eng[e].intersects_id(o, d, multiple_hits=True)
            counts = np.bincount(np.asarray(ray, dtype=np.int64), minlength=len(o))
            _, first_ray = eng[e].intersects_id(o, d, multiple_hits=False)
            misses = len(o) - len(np.unique(first_ray))
            cells.append(f"{int((counts < 2).sum())} / {int((counts > 2).sum())} / {misses}")
        emit(f"| {label} | {len(o):,} | " + " | ".join(cells) + " |")

    emit.save(args.out)


if __name__ == "__main__":
    main()
