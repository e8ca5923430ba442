"""`contains` at the exact tier with and without the scene's inside grid (src/scene/inside_grid.rs)
against Open3D's ``compute_occupancy(nsamples=1)`` on tensors it built beforehand: the same points
(uniform in each mesh's bounding box grown by 10% per side, seed 1), one process, on the device
named (default: the CPU engine). Prints a Markdown table; the answers with and without the grid
must be equal (the row says so).

    python benchmarks/bench_contains_grid.py                          # CPU engine, 1M points
    python benchmarks/bench_contains_grid.py --device default         # vkray.Device(): the GPU

"Without": ``VKRAY_CONTAINS_GRID=off`` while that scene is asked (no grid is built or used).
"Grid build": the grid's build (once a scene, by its first query of 32,768 points or more on the
engines of the host's cores, by its second on a GPU), `Scene`'s ``inside_grid`` record. Times are the best of ``--repeat``
after a warm-up; "× open3d" is Open3D's time over vkray's (above 1: vkray is faster).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys

import numpy as np
from _timing import best_of, open3d_scene

import vkray


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--meshes", default="stanford-bunny,fandisk,spot,cow")
    parser.add_argument("--device", default="cpu", help="'cpu' (default), 'default' (vkray.Device()) or a name")
    args = parser.parse_args()
    import open3d as o3d

    device = vkray.Device() if args.device == "default" else vkray.Device(args.device)
    print(f"# bench_contains_grid: {platform.node()}, {os.cpu_count()} cores, {device.name}")
    print(f"`python benchmarks/bench_contains_grid.py {' '.join(sys.argv[1:])}`\n")
    print("| mesh | method | without grid (M/s) | grid build (ms) | with grid (M/s) | open3d (M/s) | × without | × open3d | equal |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.meshes.split(","):
        v, f = vkray.data.load_mesh(name)
        v, f = np.ascontiguousarray(v, np.float32), np.ascontiguousarray(f, np.int32)
        lo, hi = v.min(0), v.max(0)
        grow = 0.1 * (hi - lo)
        points = np.random.default_rng(1).uniform(lo - grow, hi + grow, (args.points, 3)).astype(np.float32)
        mesh = device.mesh(v, f)
        method = "parity" if mesh.is_closed else "winding"
        os.environ["VKRAY_CONTAINS_GRID"] = "off"
        plain = device.scene([mesh])
        without = plain.contains(points, method=method)
        t_without = best_of(args.repeat, lambda: plain.contains(points, method=method))
        del os.environ["VKRAY_CONTAINS_GRID"]
        gridded = device.scene([mesh])
        for _ in range(3):  # until a query built the grid (a GPU builds it at the second)
            with_grid = gridded.contains(points, method=method)
            grid = gridded._core.inside_grid(method == "winding")
            if grid is not None:
                break
        build = grid["build_seconds"] if grid is not None else float("nan")
        t_with = best_of(args.repeat, lambda: gridded.contains(points, method=method))
        scene = open3d_scene(o3d, v, f)
        tensor = o3d.core.Tensor.from_numpy(points)
        scene.compute_occupancy(tensor, nsamples=1)
        t_o3d = best_of(args.repeat, lambda: scene.compute_occupancy(tensor, nsamples=1))
        rate = lambda s: f"{args.points / s / 1e6:.2f}"  # noqa: E731
        equal = bool(np.array_equal(without, with_grid))
        print(
            f"| {name} | {method} | {rate(t_without)} | {build * 1e3:.0f} | {rate(t_with)} | {rate(t_o3d)} "
            f"| {t_without / t_with:.2f} | {t_o3d / t_with:.2f} | {'yes' if equal else 'NO'} |"
        )


if __name__ == "__main__":
    main()
