"""Every vkray query on one device, with numpy arrays in and out and with torch CUDA tensors in and
`vkray.CudaArray` out, against Open3D's ``RaycastingScene`` on tensors it built beforehand, in one
run that writes one Markdown table (issue 33: every query on GPU arrays).

    python benchmarks/bench_queries.py                                # 1M rays and points: bunny, fandisk, bunny x16
    python benchmarks/bench_queries.py --rays 1e6 16e6 --out /tmp/bench_queries.md
    python benchmarks/bench_queries.py --queries count,intersect_all --meshes bunny-x16
    python benchmarks/bench_queries.py --rays 2e4 --points 2e4 --repeat 1 --meshes stanford-bunny   # a laptop
    python benchmarks/bench_queries.py --device cpu --no-cuda         # the CPU engine

Meshes: vkray's shipped meshes (``vkray.data.load_mesh``) and ``bunny-x16``, the bunny with every
triangle split into four twice (1.1M triangles, as bench_cpu.py's). Rays (float32, the same arrays
for every engine): a pinhole camera of round(sqrt(n))^2 rays looking at the mesh
(``oracle.camera_rays``, its origin repeated for every ray) and ``oracle.random_rays(v, n, seed=5)``;
points uniform in the mesh's bounding box grown by 10% per side (seed 1).

Rows: one per mesh, ray (or point) set, query and tier. Queries and their Open3D peers: intersect
(fast, t and prim_id) / ``cast_rays``; occluded (fast) / ``test_occlusions``; count (fast, exact) /
``count_intersections``; intersect_all (fast, exact; t and prim_id) / ``list_intersections``;
transmittance (fast; no peer); contains (exact; parity on closed meshes, else the winding number) /
``compute_occupancy(nsamples=1)``; distance, signed_distance / ``compute_distance``,
``compute_signed_distance``, and closest_points (default fields) / ``compute_closest_points``, at the
distances' default tier (``--distance-precision`` picks another).

Columns: seconds (best of ``--repeat``, after one untimed call) and millions of rays (points) a
second of Open3D (its call alone, on its own tensors), of vkray numpy in and out, and of vkray with
torch CUDA tensors in and `vkray.CudaArray` out (each array read with ``torch.from_dlpack``, timed to
``torch.cuda.synchronize()``); "numpy × open3d" and "cuda × open3d" are Open3D's time over vkray's
(above 1: vkray is faster); "× own count" (intersect_all) is its rate over count's on the same rays
and tier (numpy, cuda). A query the device refuses with CUDA inputs says "refused"; a peer or a
path that did not run says "—". "agrees": the CUDA answers equal the numpy answers bit for bit
("cuda"), and the exact tier's counts, all hits (CSR offsets, prim_id; t within 1e-12) and contains
equal the CPU engine's reference tier on the first ``--check`` rays or points ("ref"); a "no" gives
the number of rays or points that differ. Targets (issue 33) are checked under the table. Before
any timing each scene traces about a second of closest-hit queries (the GPU's clocks up).
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import os
import pathlib
import platform
import shlex
import sys
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
from _report import Report, table_head
from _timing import best_run

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
from oracle import camera_rays, random_rays  # noqa: E402

RAY_QUERIES = ("intersect", "occluded", "count", "intersect_all", "transmittance")
POINT_QUERIES = ("contains", "distance", "signed_distance", "closest_points")
LEAN = ("t", "prim_id")
REFUSALS = (TypeError, ValueError, vkray.UnsupportedError)
COLUMNS = (
    "mesh", "set", "n", "query", "tier", "open3d (s)", "numpy (s)", "cuda (s)", "open3d (M/s)", "numpy (M/s)",
    "cuda (M/s)", "numpy × open3d", "cuda × open3d", "× own count (numpy, cuda)", "agrees",
)  # fmt: skip
NONE = "—"


@dataclasses.dataclass(frozen=True)
class Job:
    """One row's query: ``run(scene, inputs, precision)`` answers it (inputs: (origins, directions)
    or (points,)); ``peer`` is Open3D's method and its keywords; ``reference``: check the tier's
    answers against the CPU engine's reference tier."""

    query: str
    tier: str
    run: Callable[[Any, Tuple[Any, ...], str], Any]
    peer: Optional[Tuple[str, Dict[str, Any]]] = None
    reference: bool = False


def default_precision(query: str) -> str:
    """The tier a query answers unless told (read from its signature: it follows the package)."""
    return str(inspect.signature(getattr(vkray.SceneLike, query)).parameters["precision"].default)


def jobs_for(selected: Sequence[str], closed: bool, distance_tier: str) -> List[Job]:
    """The rows of one mesh, in the order run (count before intersect_all: its rate is compared)."""
    method = "parity" if closed else "winding"
    every = [
        Job("intersect", "fast", lambda s, a, p: s.intersect(*a, outputs=LEAN, precision=p), ("cast_rays", {})),
        Job("occluded", "fast", lambda s, a, p: s.occluded(*a, precision=p), ("test_occlusions", {})),
        Job("count", "fast", lambda s, a, p: s.count(*a, precision=p), ("count_intersections", {})),
        Job("count", "exact", lambda s, a, p: s.count(*a, precision=p), ("count_intersections", {}), True),
        Job("intersect_all", "fast", lambda s, a, p: s.intersect_all(*a, outputs=LEAN, precision=p),
            ("list_intersections", {})),
        Job("intersect_all", "exact", lambda s, a, p: s.intersect_all(*a, outputs=LEAN, precision=p),
            ("list_intersections", {}), True),
        Job("transmittance", "fast", lambda s, a, p: s.transmittance(*a, precision=p)),
        Job("contains", "exact", lambda s, a, p: s.contains(*a, precision=p, method=method),
            ("compute_occupancy", {"nsamples": 1}), True),
        Job("distance", distance_tier, lambda s, a, p: s.distance(*a, precision=p), ("compute_distance", {})),
        Job("signed_distance", distance_tier, lambda s, a, p: s.signed_distance(*a, precision=p),
            ("compute_signed_distance", {})),
        Job("closest_points", distance_tier, lambda s, a, p: s.closest_points(*a, precision=p),
            ("compute_closest_points", {})),
    ]  # fmt: skip
    return [job for job in every if job.query in selected]


def subdivided(vertices: np.ndarray, faces: np.ndarray, times: int) -> Tuple[np.ndarray, np.ndarray]:
    """Every triangle split into four at its edges' midpoints, ``times`` times; triangles sharing an
    edge share its midpoint (a closed mesh stays closed), as trimesh.remesh.subdivide splits them."""
    for _ in range(times):
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
        edges = np.sort(np.concatenate([np.stack(e, 1) for e in ((a, b), (b, c), (c, a))]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = len(vertices) + inverse.reshape(3, len(faces))
        vertices = np.concatenate([vertices, (vertices[unique[:, 0]] + vertices[unique[:, 1]]) / 2])
        ab, bc, ca = mid
        faces = np.concatenate([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return vertices, faces


def load(name: str) -> Tuple[np.ndarray, np.ndarray]:
    if name == "bunny-x16":
        vertices, faces = subdivided(*vkray.data.load_mesh("stanford-bunny"), 2)
    else:
        vertices, faces = vkray.data.load_mesh(name)
    return np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32)


def ray_sets(vertices: np.ndarray, counts: Sequence[int]) -> List[Tuple[str, np.ndarray, np.ndarray]]:
    """(name, origins, directions): float32, whole arrays (the camera's origin repeated)."""
    v = vertices.astype(np.float64)
    sets = []
    for n in counts:
        side = max(1, int(round(n**0.5)))
        origin, dirs = camera_rays(v, width=side, height=side)
        sets.append(("camera", np.broadcast_to(origin, dirs.shape), dirs))
    for n in counts:
        sets.append(("random", *random_rays(v, n, seed=5)))
    return [(name, np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32)) for name, o, d in sets]


def point_sets(vertices: np.ndarray, counts: Sequence[int]) -> List[np.ndarray]:
    lo, hi = vertices.min(0), vertices.max(0)
    grow = 0.1 * (hi - lo)
    return [np.random.default_rng(1).uniform(lo - grow, hi + grow, (n, 3)).astype(np.float32) for n in counts]


# --- answers: the arrays of a query's result, on the host, and how many rays or points differ ----


def arrays_of(answer: Any) -> Dict[str, Any]:
    """The arrays of a result: itself for a plain array (numpy or CudaArray), else the fields of its
    Hits, AllHits or Closest that it holds (CSR ``offsets`` and ``ray_index`` too)."""
    if isinstance(answer, np.ndarray) or hasattr(answer, "__dlpack__"):
        return {"value": answer}
    names = ("offsets", "ray_index") + tuple(vkray.HIT_FIELDS) + tuple(vkray.CLOSEST_FIELDS)
    return {name: getattr(answer, name) for name in dict.fromkeys(names) if getattr(answer, name, None) is not None}


def on_host(answer: Any, torch: Any) -> Dict[str, np.ndarray]:
    """A result's arrays as numpy (CUDA arrays copied through torch, else through __array__)."""
    out = {}
    for name, array in arrays_of(answer).items():
        if not isinstance(array, np.ndarray):
            array = torch.from_dlpack(array).cpu().numpy() if torch is not None else np.asarray(array)
        out[name] = array
    return out


def first_rows(arrays: Dict[str, np.ndarray], k: int) -> Dict[str, np.ndarray]:
    """The arrays of the first ``k`` rays or points (of all hits: the CSR rows of the first k rays)."""
    if "offsets" not in arrays:
        return {name: a[:k] for name, a in arrays.items()}
    end = int(arrays["offsets"][k])
    return {name: a[: k + 1] if name == "offsets" else a[:end] for name, a in arrays.items()}


def differing(a: Dict[str, np.ndarray], b: Dict[str, np.ndarray], rtol: float = 0.0) -> int:
    """How many rays (points) the two results disagree on: all hits by their counts first, then by
    the hits' fields (a hit counted once); floats equal (NaN and inf alike), or within ``rtol``."""
    if "offsets" in a and "offsets" in b:
        ca, cb = np.diff(a["offsets"]), np.diff(b["offsets"])
        if ca.shape != cb.shape:
            return max(len(ca), len(cb))
        if (ca != cb).any():
            return int((ca != cb).sum())
    worst = 0
    for name in a.keys() & b.keys():
        x, y = a[name], b[name]
        if x.dtype == np.bool_ and y.dtype != np.bool_:  # occluded: CUDA gives the hit triangle (-1: none)
            y = y >= 0
        elif y.dtype == np.bool_ and x.dtype != np.bool_:
            x = x >= 0
        if x.shape != y.shape:
            return max(len(x), len(y))
        if x.size == 0:
            continue
        if x.dtype.kind == "f" or y.dtype.kind == "f":
            x, y = x.astype(np.float64), y.astype(np.float64)
            same = (
                np.isclose(x, y, rtol=rtol, atol=0.0, equal_nan=True)
                if rtol
                else (x == y) | (np.isnan(x) & np.isnan(y))
            )
        else:
            same = x == y
        bad = ~same.reshape(len(same), -1).all(axis=1) if same.ndim else ~same
        worst = max(worst, int(np.sum(bad)))
    return worst


# --- timing ---------------------------------------------------------------------------------------


def describe(error: BaseException) -> str:
    return f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"[:160]


def warm_up(scene: Any, origins: np.ndarray, directions: np.ndarray, seconds: float = 1.0) -> int:
    """Closest-hit queries for about ``seconds`` (at least one): clocks up, pipelines compiled."""
    m = min(len(origins), 1_000_000)
    began, calls = time.perf_counter(), 0
    while calls == 0 or time.perf_counter() - began < seconds:
        scene.intersect(origins[:m], directions[:m], outputs=LEAN)
        calls += 1
    return calls


class Runner:
    """Times one mesh's queries on every path, and keeps the notes said under the table."""

    def __init__(self, args: argparse.Namespace, device: Any, torch: Any, o3d: Any) -> None:
        self.args, self.device, self.torch, self.o3d = args, device, torch, o3d
        self.notes: Dict[str, List[str]] = {}  # what was said: the rows it was said of
        self.cuda = None if torch is None else f"cuda:{device.cuda_device}"
        self.reference_device: Any = None
        # The mesh's warm-up rays: each path's timing starts after `--rewarm` seconds of GPU work
        # (Open3D's runs and the reference tier's checks leave the GPU idle, and its clocks fall).
        self.warm_rays: Optional[Tuple[np.ndarray, np.ndarray]] = None

    def rewarm(self, scene: Any) -> None:
        if self.warm_rays is not None and self.args.rewarm > 0:
            warm_up(scene, *self.warm_rays, seconds=self.args.rewarm)

    def note(self, where: str, text: str) -> None:
        print(f"  note: {where}: {text}", file=sys.stderr, flush=True)
        self.notes.setdefault(text, []).append(where)

    def numpy_time(self, job: Job, scene: Any, inputs: Tuple[Any, ...], where: str) -> Tuple[Any, Any]:
        """(seconds or a cell's word, the answer or None)."""
        try:
            self.rewarm(scene)
            seconds, answer = best_run(self.args.repeat, lambda: job.run(scene, inputs, job.tier), warm=True)
            return seconds, answer
        except REFUSALS as error:
            self.note(where, f"numpy refused: {describe(error)}")
            return "refused", None
        except Exception as error:  # a path that broke is a cell that says so, not a lost run
            self.note(where, f"numpy failed: {describe(error)}")
            return "error", None

    def cuda_time(self, job: Job, scene: Any, inputs: Tuple[Any, ...], where: str) -> Tuple[Any, Any]:
        torch = self.torch
        if torch is None:
            return NONE, None

        def resident() -> Any:
            answer = job.run(scene, inputs, job.tier)
            for array in arrays_of(answer).values():
                if not isinstance(array, np.ndarray):
                    torch.from_dlpack(array)  # read where it lies (zero-copy, stream-ordered)
            torch.cuda.synchronize()
            return answer

        try:
            torch.cuda.synchronize()
            first = resident()  # the untimed call; a refusal shows here
        except REFUSALS as error:
            self.note(where, f"CUDA inputs refused: {describe(error)}")
            return "refused", None
        except Exception as error:
            self.note(where, f"CUDA inputs failed: {describe(error)}")
            return "error", None
        if all(isinstance(a, np.ndarray) for a in arrays_of(first).values()):
            self.note(where, "CUDA inputs answered with numpy arrays (not CudaArray)")
        self.rewarm(scene)
        seconds, answer = best_run(self.args.repeat, resident)
        return seconds, answer

    def peer_time(self, o3d_scene: Any, job: Job, tensor: Any, cache: Dict[str, Any], where: str) -> Any:
        """Open3D's seconds for the job's peer on these tensors (once per peer and set)."""
        if job.peer is None or o3d_scene is None:
            return NONE
        name, keywords = job.peer
        if name not in cache:
            call = getattr(o3d_scene, name, None)
            if call is None:
                self.note(where, f"Open3D has no {name}")
                cache[name] = NONE
            else:
                try:
                    cache[name] = best_run(self.args.repeat, lambda: call(tensor, **keywords), warm=True)[0]
                except Exception as error:
                    self.note(where, f"Open3D {name} failed: {describe(error)}")
                    cache[name] = "error"
        return cache[name]

    def reference_check(self, job: Job, answer: Any, inputs: Tuple[np.ndarray, ...], ref_scene: Any) -> Optional[int]:
        k = min(self.args.check, len(inputs[0]))
        if not job.reference or answer is None or k == 0:
            return None
        sub = tuple(np.ascontiguousarray(a[:k]) for a in inputs)
        reference = on_host(job.run(ref_scene, sub, "reference"), self.torch)
        return differing(first_rows(on_host(answer, self.torch), k), reference, rtol=1e-12)


def fmt(value: Any, digits: int = 3) -> str:
    """A cell: floats to ``digits`` significant digits (whole numbers from 10**digits up)."""
    if not isinstance(value, float):
        return str(value)
    return f"{value:.0f}" if value >= 10**digits else f"{value:.{digits}g}"


def rate(n: int, seconds: Any) -> Any:
    return n / seconds / 1e6 if isinstance(seconds, float) else NONE


def ratio(a: Any, b: Any) -> Any:
    return a / b if isinstance(a, float) and isinstance(b, float) else NONE


def agreement(cuda: Optional[int], reference: Optional[int]) -> str:
    said = [f"{label} {'yes' if bad == 0 else f'no ({bad:,})'}" for label, bad in (("cuda", cuda), ("ref", reference))
            if bad is not None]  # fmt: skip
    return ", ".join(said) or NONE


def targets(rows: List[Dict[str, Any]]) -> Tuple[int, List[str], int]:
    """Issue 33's targets on these rows: (how many were met, a line for each missed, how many
    could not be checked: their peer, path or check did not run)."""
    met, misses, unchecked = 0, [], 0
    refused: Dict[str, List[str]] = {}
    floors = {"intersect_all": 10.0, "count": 10.0, "contains": 10.0, "distance": 50.0, "signed_distance": 50.0}
    for row in rows:
        where = f"{row['mesh']} {row['set']} {row['n']:,} {row['query']} ({row['tier']})"
        checks: List[Tuple[str, Any, float]] = []  # (what, value, its floor)
        if row["query"] in floors:
            checks.append(("numpy × open3d", row["numpy × open3d"], floors[row["query"]]))
        if row["query"] != "transmittance":  # no Open3D peer
            checks.append(("cuda × open3d", row["cuda × open3d"], 20.0))
        if row["query"] == "intersect_all":
            checks.append(("intersect_all rate / count rate (numpy)", row["own count numpy"], 0.5))
        if row["cuda (s)"] in ("refused", "error"):  # every query takes CUDA arrays
            refused.setdefault(f"{row['query']} ({row['tier']})", []).append(where)
        for what, value, floor in checks:
            if not isinstance(value, float):
                unchecked += 1
            elif value < floor:
                misses.append(f"{where}: {what} {value:.2f} < {floor:g}")
            else:
                met += 1
        if row["agrees"] == NONE:
            unchecked += 1
        elif "no (" in row["agrees"]:
            misses.append(f"{where}: answers differ ({row['agrees']})")
        else:
            met += 1
    misses += [f"CUDA inputs refused or failed: {query}, {len(where)} rows" for query, where in refused.items()]
    return met, misses, unchecked


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--meshes", default="stanford-bunny,fandisk,bunny-x16", help="comma-separated (bunny-x16: 1.1M triangles)"
    )
    parser.add_argument("--rays", type=float, nargs="+", default=[1e6], help="ray counts, each a row (e.g. 1e6 16e6)")
    parser.add_argument("--points", type=float, nargs="+", default=[1e6], help="point counts, each a row")
    parser.add_argument("--repeat", type=int, default=3, help="best of this many timed runs (after one untimed)")
    parser.add_argument("--rewarm", type=float, default=0.3,
                        help="seconds of closest hits before each path's timing (0: none; the mesh's first second always)")
    parser.add_argument(
        "--device", default=None, help="vkray device: an index, a name or 'cpu' (default: vkray.Device())"
    )
    parser.add_argument("--queries", default=",".join(RAY_QUERIES + POINT_QUERIES), help="comma-separated subset")
    parser.add_argument(
        "--distance-precision", default=None, help="tier of distance, signed_distance, closest_points (default: theirs)"
    )
    parser.add_argument(
        "--check", type=int, default=20_000, help="rays (points) checked against the CPU reference tier"
    )
    parser.add_argument("--no-cuda", action="store_true", help="skip torch CUDA tensors in, CudaArray out")
    parser.add_argument("--no-open3d", action="store_true", help="skip Open3D")
    parser.add_argument("--out", default=None, help="also write the Markdown report here")
    args = parser.parse_args()
    selected = [q.strip() for q in args.queries.split(",") if q.strip()]
    unknown = [q for q in selected if q not in RAY_QUERIES + POINT_QUERIES]
    if unknown:
        parser.error(f"unknown queries {unknown}; choose from {', '.join(RAY_QUERIES + POINT_QUERIES)}")
    distance_tier = args.distance_precision or default_precision("distance")

    device = vkray.Device() if args.device in (None, "default") else vkray.Device(args.device)
    torch: Any = None
    torch_line = "torch: not used (--no-cuda)"
    if not args.no_cuda:
        try:
            import torch

            if not torch.cuda.is_available():
                torch_line, torch = f"torch {torch.__version__}: no CUDA device", None
            elif device.cuda_device is None:
                torch_line, torch = f"torch {torch.__version__}: the vkray device is no CUDA device", None
            else:
                gpu = torch.cuda.get_device_name(device.cuda_device)
                torch_line = f"torch {torch.__version__} (CUDA {torch.version.cuda}), cuda:{device.cuda_device} {gpu}"
        except ImportError:
            torch_line, torch = "torch: not installed", None
    o3d: Any = None
    o3d_line = "Open3D: not used (--no-open3d)"
    if not args.no_open3d:
        try:
            import open3d as o3d

            o3d_line = f"Open3D {o3d.__version__} RaycastingScene ({os.cpu_count()} cores)"
        except ImportError:
            o3d_line = "Open3D: not installed"

    report = Report()
    report(
        f"# bench_queries: {platform.node()}, {os.cpu_count()} CPU cores ({platform.processor() or platform.machine()})"
    )
    report(f"`python {shlex.join(sys.argv)}`\n")
    info = device.info
    report(f"- vkray {vkray.__version__}: {device.name} ({device.engine}, {device.backend}, {info.driver})")
    report(f"- {torch_line}")
    report(f"- {o3d_line}")
    report(f"- numpy {np.__version__}, Python {platform.python_version()}, best of {args.repeat}")
    meshes = []
    for name in args.meshes.split(","):
        vertices, faces = load(name.strip())
        meshes.append((name.strip(), vertices, faces))
    report("- meshes: " + ", ".join(f"{name} {len(f):,} triangles" for name, _, f in meshes))
    report("")
    report(table_head(COLUMNS))

    rows: List[Dict[str, Any]] = []
    runner = Runner(args, device, torch, o3d)
    ray_counts = [int(r) for r in args.rays]
    point_counts = [int(p) for p in args.points]
    for name, vertices, faces in meshes:
        mesh = device.mesh(vertices, faces)
        scene = device.scene([mesh])
        jobs = jobs_for(selected, mesh.is_closed, distance_tier)
        if device.engine == "cpu":
            ref_scene = scene
        else:
            runner.reference_device = runner.reference_device or vkray.Device("cpu")
            ref_scene = runner.reference_device.scene([runner.reference_device.mesh(vertices, faces)])
        o3d_scene = None
        if o3d is not None:
            o3d_scene = o3d.t.geometry.RaycastingScene()
            o3d_scene.add_triangles(
                o3d.core.Tensor.from_numpy(vertices), o3d.core.Tensor.from_numpy(faces.astype(np.uint32))
            )
            o3d_scene.count_intersections(o3d.core.Tensor(np.array([[0, 0, 0, 1, 1, 1]], np.float32)))  # builds
        sets: List[Tuple[str, Tuple[np.ndarray, ...]]] = []
        if any(job.query in RAY_QUERIES for job in jobs):
            sets += [(kind, (o, d)) for kind, o, d in ray_sets(vertices, ray_counts)]
        if any(job.query in POINT_QUERIES for job in jobs):
            sets += [("points", (p,)) for p in point_sets(vertices, point_counts)]
        if not sets:
            continue
        warm = random_rays(vertices.astype(np.float64), min(min(ray_counts), 1_000_000), seed=5)
        runner.warm_rays = (np.ascontiguousarray(warm[0], np.float32), np.ascontiguousarray(warm[1], np.float32))
        calls = warm_up(scene, *runner.warm_rays)
        if torch is not None:
            torch.zeros(1, device=runner.cuda).add_(1)
            torch.cuda.synchronize()
        print(f"[{name}] warmed up: {calls} closest-hit queries", file=sys.stderr, flush=True)
        for kind, inputs in sets:
            n = len(inputs[0])
            tensor = None
            if o3d_scene is not None:
                tensor = o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.hstack(inputs)))
            on_gpu = None if torch is None else tuple(torch.from_numpy(a).to(runner.cuda) for a in inputs)
            peers: Dict[str, Any] = {}
            counts: Dict[str, Tuple[Any, Any]] = {}
            for job in jobs:
                if (job.query in RAY_QUERIES) != (kind != "points"):
                    continue
                where = f"{name} {kind} {n:,} {job.query} ({job.tier})"
                print(f"[{where}]", file=sys.stderr, flush=True)
                open3d_s = runner.peer_time(o3d_scene, job, tensor, peers, where)
                numpy_s, answer = runner.numpy_time(job, scene, inputs, where)
                cuda_s, cuda_answer = NONE, None
                if on_gpu is not None:
                    cuda_s, cuda_answer = runner.cuda_time(job, scene, on_gpu, where)
                cuda_bad = None
                if answer is not None and cuda_answer is not None:
                    cuda_bad = differing(on_host(answer, torch), on_host(cuda_answer, torch))
                try:
                    ref_bad = runner.reference_check(job, answer, inputs, ref_scene)
                except Exception as error:
                    runner.note(where, f"reference tier failed: {describe(error)}")
                    ref_bad = None
                del answer, cuda_answer
                if job.query == "count":
                    counts[job.tier] = (numpy_s, cuda_s)
                own: Tuple[Any, Any] = (NONE, NONE)
                if job.query == "intersect_all" and job.tier in counts:
                    own = (ratio(counts[job.tier][0], numpy_s), ratio(counts[job.tier][1], cuda_s))
                row = {
                    "mesh": name, "set": kind, "n": n, "query": job.query, "tier": job.tier,
                    "open3d (s)": open3d_s, "numpy (s)": numpy_s, "cuda (s)": cuda_s,
                    "open3d (M/s)": rate(n, open3d_s), "numpy (M/s)": rate(n, numpy_s), "cuda (M/s)": rate(n, cuda_s),
                    "numpy × open3d": ratio(open3d_s, numpy_s), "cuda × open3d": ratio(open3d_s, cuda_s),
                    "× own count (numpy, cuda)": NONE if job.query != "intersect_all" else f"{fmt(own[0], 2)}, {fmt(own[1], 2)}",
                    "agrees": agreement(cuda_bad, ref_bad), "own count numpy": own[0],
                }  # fmt: skip
                rows.append(row)
                cells = [f"{row['n']:,}" if c == "n" else fmt(row[c]) for c in COLUMNS]
                report("| " + " | ".join(cells) + " |")
    report("")
    met, misses, unchecked = targets(rows)
    report(
        f"Targets (issue 33) in {len(rows)} rows: {met} met, {len(misses)} missed, {unchecked} not checked (a peer or path absent)."
    )
    for miss in misses:
        report(f"- {miss}")
    if runner.notes:
        report("\nNotes:")
        for text, where in runner.notes.items():
            report(f"- {text} ({len(where)} rows: {where[0]}{', ...' if len(where) > 1 else ''})")
    report.save(args.out)


if __name__ == "__main__":
    main()
