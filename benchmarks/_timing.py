"""The benchmarks' one timer: the best of several runs of a call (imported as a sibling module, as
the benchmarks run as scripts from this folder)."""

from __future__ import annotations

import time
from typing import Any, Callable, Tuple


def best_run(repeat: int, fn: Callable[[], Any], *, warm: bool = False) -> Tuple[float, Any]:
    """(the fastest of ``repeat`` runs of ``fn`` in seconds, that run's result); ``warm`` runs it
    once first, untimed (pipelines compiled, memory faulted in)."""
    if warm:
        fn()
    best, result = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        answer = fn()
        seconds = time.perf_counter() - start
        if seconds < best:
            best, result = seconds, answer
    return best, result


def best_of(repeat: int, fn: Callable[[], Any], *, warm: bool = False) -> float:
    """The fastest of ``repeat`` runs of ``fn``, in seconds (`best_run` without the result)."""
    return best_run(repeat, fn, warm=warm)[0]


def open3d_scene(o3d: Any, vertices: Any, faces: Any) -> Any:
    """An Open3D RaycastingScene of one mesh, its BVH built (by one query) before any timing starts;
    ``o3d`` is the open3d module (imported by the caller: it runs in the Open3D worker's interpreter)."""
    import numpy as np  # here, so that the timer above needs nothing but the standard library

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(faces, dtype=np.uint32)),
    )
    scene.count_intersections(o3d.core.Tensor(np.array([[0, 0, 0, 1, 1, 1]], np.float32)))  # commit (build)
    return scene
