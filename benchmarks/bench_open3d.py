"""vkray.open3d's ``RaycastingScene`` against Open3D's own (``open3d.t.geometry.RaycastingScene``,
Embree on the host's cores) on the same calls and tensors, and against vkray's native call on the
same inputs (issue 35: the conversion to and from Open3D's conventions must cost nothing
measurable). Prints a Markdown report.

    python benchmarks/bench_open3d.py                                  # H200: 1M rays and points
    python benchmarks/bench_open3d.py --rays 20000 --points 5000       # lavapipe (2 cores)

Every method, as Open3D's users call it: ``cast_rays``, ``test_occlusions``,
``count_intersections``, ``list_intersections`` on rays of ``oracle.random_rays(v, n, seed=5)``
as one float32 (n, 6) tensor, and ``compute_closest_points``, ``compute_distance``,
``compute_signed_distance``, ``compute_occupancy`` on float32 points uniform in the mesh's
bounding box (seed 1). Columns, in ms (best of ``--repeat`` after one warm-up call on the whole
batch; scene builds not timed):

- Open3D: Open3D's scene, Open3D CPU tensors in and out (Open3D has no CUDA path for this class).
- drop-in, o3d CPU: vkray.open3d, the same Open3D tensors in, Open3D tensors out.
- drop-in, numpy: the same arrays as numpy, numpy out.
- native: the vkray call the drop-in makes (``Scene.intersect``, ``occluded``, ``count``,
  ``intersect_all``, ``closest_points``, ``distance``, ``signed_distance``, ``contains``) with the
  same tier and fields, on views of the same numpy arrays (origins ``rays[:, :3]``, directions
  ``rays[:, 3:]``), vkray's own dtypes out.
- ÷ native: drop-in time / native time: the conversion's cost (1.00: none), for Open3D CPU
  tensors and for numpy; and the same for Open3D tensors in CPU time (this process's, all its
  threads: on lavapipe the "GPU" is this process's threads too), which other jobs on the
  machine disturb less than the wall clock.
- × Open3D: Open3D time / drop-in (o3d CPU) time.
- With CUDA (Open3D built with CUDA, a CUDA GPU as the vkray device): drop-in on Open3D CUDA
  tensors (results as Open3D tensors on the GPU), native on views of the same GPU memory for the
  two queries whose vkray call takes CUDA rays (cast_rays, test_occlusions; the drop-in copies
  the others' inputs through the host), vkray's CUDA arrays out, and their ratio.
- ≠ Open3D: the rays or points where Open3D's answer and the drop-in's differ: hit or miss
  (cast_rays, test_occlusions), the count, the number listed, the nearest point (more than
  1e-4 of the mesh's size apart), the distance (likewise), the sign, the occupancy.

The bunny is open: Open3D's occupancy and signs vote with jittered rays, the drop-in takes the
winding number (vkray.open3d's docstring), so they differ there by design.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import sys
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import open3d as o3d
from _report import Report

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
import vkray.open3d as vo3d  # noqa: E402

try:
    from oracle import load_mesh  # noqa: E402
except ImportError:  # the meshes before they moved into vkray.data
    from oracle import load_obj as load_mesh  # noqa: E402
from oracle import random_rays  # noqa: E402

RAY_METHODS = ("cast_rays", "test_occlusions", "count_intersections", "list_intersections")
POINT_METHODS = ("compute_closest_points", "compute_distance", "compute_signed_distance", "compute_occupancy")


def best(repeat: int, runs: Dict[str, Callable[[], Any]]) -> Dict[str, Tuple[float, float, Any]]:
    """Each run's best wall time and best CPU time (this process's, all its threads) of
    ``repeat`` calls after one warm-up call, and its last answer. The runs take turns, so that a
    burst of load on the machine falls on all of them alike."""
    answers = {name: run() for name, run in runs.items()}
    wall: Dict[str, List[float]] = {name: [] for name in runs}
    cpu: Dict[str, List[float]] = {name: [] for name in runs}
    for _ in range(repeat):
        for name, run in runs.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            answers[name] = run()
            wall[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
    return {name: (min(wall[name]), min(cpu[name]), answers[name]) for name in runs}


def sync_cuda() -> None:
    if o3d.core.cuda.is_available():
        o3d.core.cuda.synchronize()


def native_calls(scene: vkray.Scene, closed: bool, rays: Any, points: Any) -> Dict[str, Callable[[], Any]]:
    """The vkray call each drop-in method makes, with its tier and fields (vkray.open3d's
    defaults), on views of the same rays and points."""
    o, d = rays[:, :3], rays[:, 3:]
    method = "parity" if closed else "winding"
    return {
        "cast_rays": lambda: scene.intersect(o, d, outputs=["t", "prim_id", "custom_index", "uv", "normal"]),
        "test_occlusions": lambda: scene.occluded(o, d),
        "count_intersections": lambda: scene.count(o, d, precision="exact"),
        "list_intersections": lambda: scene.intersect_all(
            o, d, outputs=["t", "prim_id", "custom_index", "uv"], precision="exact"
        ),
        "compute_closest_points": lambda: scene.closest_points(
            points, outputs=["position", "prim_id", "custom_index", "uv", "normal"], precision="fast"
        ),
        "compute_distance": lambda: scene.distance(points, precision="fast"),
        "compute_signed_distance": lambda: scene.signed_distance(points, precision="fast"),
        "compute_occupancy": lambda: scene.contains(points, precision="exact", method=method),
    }


def host(answer: Any) -> Any:
    """An answer (a dict of tensors, a tensor or an array) as numpy."""
    if isinstance(answer, dict):
        return {k: host(v) for k, v in answer.items()}
    if isinstance(answer, o3d.core.Tensor):
        return answer.cpu().numpy()
    return np.asarray(answer)


def differ(method: str, theirs: Any, ours: Any, size: float) -> int:
    """How many rays or points Open3D's answer and the drop-in's differ on (see the module)."""
    a, b = host(theirs), host(ours)
    if method == "cast_rays":
        return int(np.count_nonzero((a["geometry_ids"] == vo3d.INVALID_ID) != (b["geometry_ids"] == vo3d.INVALID_ID)))
    if method == "list_intersections":
        return int(np.count_nonzero(np.diff(a["ray_splits"].astype(np.int64)) != np.diff(b["ray_splits"].astype(np.int64))))
    if method == "compute_closest_points":
        return int(np.count_nonzero(np.linalg.norm(a["points"] - b["points"], axis=-1) > 1e-4 * size))
    if method == "compute_distance":
        return int(np.count_nonzero(np.abs(a - b) > 1e-4 * size))
    if method == "compute_signed_distance":
        return int(np.count_nonzero((a < 0) != (b < 0)))
    return int(np.count_nonzero(a != b))


class CudaRows:
    """An Open3D CUDA tensor as any DLPack array (the same memory), for vkray's native CUDA path:
    Open3D's ``__dlpack_device__`` names the device type by an enum, where DLPack wants ints."""

    def __init__(self, tensor: Any) -> None:
        self.tensor = tensor
        self.shape = tuple(int(n) for n in tensor.shape)

    def __dlpack_device__(self) -> Tuple[int, int]:
        kind, index = self.tensor.__dlpack_device__()
        return int(getattr(kind, "value", kind)), int(index)

    def __dlpack__(self, *, stream: Optional[int] = None, **_: Any) -> Any:
        return self.tensor.__dlpack__(stream=stream)


def ms(seconds: Optional[float]) -> str:
    return "-" if seconds is None else f"{seconds * 1e3:.2f}"


def ratio(a: Optional[float], b: Optional[float]) -> str:
    return "-" if a is None or b is None or b == 0 else f"{a / b:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", nargs="+", default=["stanford-bunny", "fandisk"])
    parser.add_argument("--rays", type=int, default=1_000_000)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--no-cuda", action="store_true", help="skip the CUDA columns where they could run")
    parser.add_argument("--out", default=None, help="also write the report here")
    args = parser.parse_args()

    emit = Report()

    device = vkray.Device()
    gpu = None
    if not args.no_cuda and o3d.core.cuda.is_available() and device.cuda_device is not None:
        gpu = o3d.core.Device(f"CUDA:{device.cuda_device}")
    emit(
        f"Device: {device.name} ({device.backend}); vkray {vkray.__version__}; Open3D {o3d.__version__} "
        f"(CUDA: {'yes, ' + str(gpu) if gpu is not None else 'not used'}); numpy {np.__version__}; "
        f"Python {platform.python_version()}; {platform.machine()}, {len(os.sched_getaffinity(0))} CPUs"
    )
    emit(f"Command: python benchmarks/bench_open3d.py {' '.join(sys.argv[1:])}")
    emit()

    rows: List[str] = []
    for mesh_name in args.meshes:
        v, f = load_mesh(mesh_name)
        vertices = o3d.core.Tensor(np.ascontiguousarray(v, dtype=np.float32))
        faces = o3d.core.Tensor(np.ascontiguousarray(f, dtype=np.uint32))
        theirs = o3d.t.geometry.RaycastingScene()
        theirs.add_triangles(vertices, faces)
        ours = vo3d.RaycastingScene(vkray_device=device)
        ours.add_triangles(vertices, faces)
        mesh = device.mesh(vertices.numpy(), faces.numpy())
        scene = device.scene([vkray.Instance(mesh, custom_index=0)])
        size = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))

        o, d = random_rays(v, args.rays, seed=5)
        rays = np.ascontiguousarray(np.concatenate([o, d], axis=1), dtype=np.float32)
        lo, hi = v.min(axis=0), v.max(axis=0)
        points = np.random.default_rng(1).uniform(lo, hi, size=(args.points, 3)).astype(np.float32)
        tensors = {"rays": o3d.core.Tensor(rays), "points": o3d.core.Tensor(points)}
        natives = native_calls(scene, mesh.is_closed, rays, points)
        on_gpu = {k: t.to(gpu) for k, t in tensors.items()} if gpu is not None else {}
        gpu_natives = {}
        if gpu is not None:
            go, gd = CudaRows(on_gpu["rays"][:, :3]), CudaRows(on_gpu["rays"][:, 3:])
            gpu_natives = {
                "cast_rays": lambda: scene.intersect(go, gd, outputs=["t", "prim_id", "custom_index", "uv", "normal"]),
                "test_occlusions": lambda: scene.occluded(go, gd),
            }

        for method in RAY_METHODS + POINT_METHODS:
            kind = "rays" if method in RAY_METHODS else "points"
            count = args.rays if kind == "rays" else args.points
            print(f"{mesh_name} {method} ({count:,} {kind})", file=sys.stderr, flush=True)
            runs: Dict[str, Callable[[], Any]] = {
                "open3d": lambda: getattr(theirs, method)(tensors[kind]),
                "o3d": lambda: getattr(ours, method)(tensors[kind]),
                "numpy": lambda: getattr(ours, method)(rays if kind == "rays" else points),
                "native": natives[method],
            }
            if gpu is not None:

                def on_cuda() -> Any:
                    answer = getattr(ours, method)(on_gpu[kind])
                    sync_cuda()
                    return answer

                runs["gpu"] = on_cuda
                if method in gpu_natives:

                    def native_cuda() -> Any:
                        answer = gpu_natives[method]()
                        sync_cuda()
                        return answer

                    runs["gpu native"] = native_cuda
            timed = best(args.repeat, runs)
            t_theirs, _, a_theirs = timed["open3d"]
            t_o3d, cpu_o3d, a_ours = timed["o3d"]
            t_numpy, t_native, cpu_native = timed["numpy"][0], timed["native"][0], timed["native"][1]
            t_gpu = timed["gpu"][0] if "gpu" in timed else None
            t_gpu_native = timed["gpu native"][0] if "gpu native" in timed else None
            gpu_cells = ""
            if gpu is not None:
                gpu_cells = (
                    f" {ms(t_gpu)} | {ms(t_gpu_native)} | {ratio(t_gpu, t_gpu_native)} | {ratio(t_theirs, t_gpu)} |"
                )
            rows.append(
                f"| {mesh_name} | {method} | {count:,} | {ms(t_theirs)} | {ms(t_o3d)} | {ms(t_numpy)} | "
                f"{ms(t_native)} | {ratio(t_o3d, t_native)} | {ratio(t_numpy, t_native)} | {ratio(cpu_o3d, cpu_native)} | "
                f"{ratio(t_theirs, t_o3d)} |{gpu_cells} {differ(method, a_theirs, a_ours, size):,} |"
            )

    header = (
        "| mesh | method | rays or points | Open3D | drop-in, o3d CPU | drop-in, numpy | native | "
        "÷ native (o3d) | ÷ native (numpy) | ÷ native (o3d), CPU time | × Open3D |"
    )
    rule = "|---|---|---|---|---|---|---|---|---|---|---|"
    if gpu is not None:
        header += " drop-in, o3d CUDA | native, CUDA | ÷ native (CUDA) | × Open3D (CUDA) |"
        rule += "---|---|---|---|"
    emit("Times in ms (best of the runs); ÷ native: the drop-in's time over vkray's native call's; "
         "× Open3D: Open3D's time over the drop-in's; ≠ Open3D: rays or points answered otherwise.")
    emit()
    emit(header + " ≠ Open3D |")
    emit(rule + "---|")
    for row in rows:
        emit(row)
    emit.save(args.out)


if __name__ == "__main__":
    main()
