"""vkray against Embree (embreex) on the same rays in one run; prints a Markdown report.

    python benchmarks/bench_core.py                       # bunny, 1M rays, Embree on 1 process
    python benchmarks/bench_core.py --rays 1e6 16e6 --big --embree-processes 16   # the GPU run

Embree's `run()` holds the GIL, so `--embree-processes N` runs N processes, each with its own scene,
each casting its share of the rays (forked: the rays are shared, not copied in). Times are best of
`--repeat`, numpy in and numpy out, after one warm-up query (pipeline compilation).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import pathlib
import platform
import sys
import time

import numpy as np
from _timing import best_of

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
from oracle import camera_rays, load_mesh, random_rays  # noqa: E402

_worker = {}


def _embree_scene(vertices, faces):
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(vertices[faces], dtype=np.float32))
    return scene


def _embree_init(vertices, faces):
    _worker["scene"] = _embree_scene(vertices, faces)
    # Embree commits the scene lazily: build it now, not inside the timed queries.
    _worker["scene"].run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))


def _embree_part(job):
    lo, hi, occluded = job
    o, d = _worker["rays"]
    scene = _worker["scene"]
    if occluded:
        return scene.run(o[lo:hi], d[lo:hi], query="OCCLUDED")
    result = scene.run(o[lo:hi], d[lo:hi], output=1)
    return result["tfar"], result["primID"]


def bench_mesh(name, vertices, faces, device, ray_counts, processes, repeat, rows, splits, builds):
    o32 = None
    start = time.perf_counter()
    mesh = device.mesh(vertices, faces)
    scene = device.scene(mesh)
    vk_build = time.perf_counter() - start
    start = time.perf_counter()
    _embree_init(vertices, faces)
    embree_build = time.perf_counter() - start
    builds.append((name, len(faces), mesh.stats["build_seconds"], scene.stats["build_seconds"], vk_build, embree_build))

    ctx = mp.get_context("fork")
    for n in ray_counts:
        side = int(round(np.sqrt(n)))
        origin, cam = camera_rays(vertices, side, side)
        sets = {
            "camera": (np.broadcast_to(origin, cam.shape), cam),
            "random": random_rays(vertices, side * side, seed=11),
        }
        for kind, (o, d) in sets.items():
            o32 = np.ascontiguousarray(o, dtype=np.float32)
            d32 = np.ascontiguousarray(d, dtype=np.float32)
            count = len(d32)
            scene.intersect(o32[:1], d32[:1])  # warm-up: compile the variants
            scene.occluded(o32[:1], d32[:1])
            vk_closest = best_of(repeat, lambda: scene.intersect(o32, d32))
            profile = device.last_trace_profile
            vk_lean = best_of(repeat, lambda: scene.intersect(o32, d32, outputs=["t", "prim_id"]))
            vk_occluded = best_of(repeat, lambda: scene.occluded(o32, d32))
            _worker["rays"] = (o32, d32)
            bounds = np.linspace(0, count, processes + 1).astype(int)
            with ctx.Pool(processes, initializer=_embree_init, initargs=(vertices, faces)) as pool:
                for occluded in (False, True):  # warm the workers
                    pool.map(_embree_part, [(0, 1, occluded)] * processes)
                jobs = lambda occluded: [(lo, hi, occluded) for lo, hi in zip(bounds[:-1], bounds[1:])]
                em_closest = best_of(repeat, lambda: pool.map(_embree_part, jobs(False)))
                em_occluded = best_of(repeat, lambda: pool.map(_embree_part, jobs(True)))
            hits = float(scene.intersect(o32, d32, outputs=["t"]).hit.mean())
            rows.append((name, kind, count, hits, count / vk_closest, count / vk_lean, count / em_closest, count / vk_occluded, count / em_occluded))
            splits.append((name, kind, count, profile))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rays", type=float, nargs="+", default=[1e6])
    parser.add_argument("--big", action="store_true", help="add the bunny subdivided twice (1.1M triangles)")
    parser.add_argument("--embree-processes", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    device = vkray.Device()
    bunny = load_mesh("stanford-bunny")
    meshes = [("bunny", *bunny)]
    if args.big:
        import trimesh.remesh

        v, f = bunny
        for _ in range(2):
            v, f = trimesh.remesh.subdivide(v, f)
        meshes.append(("bunny x16 (subdivided)", v, f))
    rows, splits, builds = [], [], []
    for name, v, f in meshes:
        bench_mesh(name, v, f, device, [int(n) for n in args.rays], args.embree_processes, args.repeat, rows, splits, builds)

    print(f"Command: `python {' '.join(sys.argv)}`\n")
    print(f"Device: {device.name} ({device.info.device_type}), driver {device.info.driver}, backend `{device.backend}`; "
          f"host {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs; "
          f"Embree (embreex) in {args.embree_processes} process(es). Best of {args.repeat}.\n")
    print("Closest hit: vkray with its default fields (t, prim_id, instance_id, custom_index, uv, normal: 36 bytes a ray) "
          "and with `outputs=['t', 'prim_id']`; Embree `run(output=1)`. Ratios are vkray (default fields) / Embree.\n")
    print("| mesh | rays | count | hit | vkray closest Mrays/s | vkray closest (t, prim_id) Mrays/s | Embree closest Mrays/s | ratio | vkray occluded Mrays/s | Embree occluded Mrays/s | ratio |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, kind, n, hit, vc, vl, ec, vo, eo in rows:
        print(f"| {name} | {kind} | {n:,} | {hit:.0%} | {vc / 1e6:.2f} | {vl / 1e6:.2f} | {ec / 1e6:.2f} | {vc / ec:.2f}x | {vo / 1e6:.2f} | {eo / 1e6:.2f} | {vo / eo:.2f}x |")
    print("\nSplit of one vkray closest-hit query with default fields, in seconds. Host clock: pack (check + convert "
          "into staging), submit, wait (GPU time not hidden behind packing), unpack (copy hits out). GPU timestamps, "
          "summed over chunks: upload copy, trace alone, readback copy.\n")
    print("| mesh | rays | count | chunks | pack | submit | wait | unpack | total | GPU upload | GPU trace | GPU readback | trace alone Grays/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    gpu = lambda v: "n/a" if v is None else f"{v:.4f}"
    for name, kind, n, p in splits:
        rate = "n/a" if not p["gpu_trace"] else f"{n / p['gpu_trace'] / 1e9:.2f}"
        print(f"| {name} | {kind} | {n:,} | {p['chunks']} | {p['pack']:.4f} | {p['submit']:.4f} | {p['wait']:.4f} | "
              f"{p['unpack']:.4f} | {p['total']:.4f} | {gpu(p['gpu_upload'])} | {gpu(p['gpu_trace'])} | {gpu(p['gpu_readback'])} | {rate} |")
    print("\nBuilds (seconds):\n")
    print("| mesh | triangles | vkray BLAS | vkray TLAS | vkray total (upload + BLAS + TLAS) | Embree scene |")
    print("|---|---|---|---|---|---|")
    for name, tris, blas, tlas, total, embree in builds:
        print(f"| {name} | {tris:,} | {blas:.4f} | {tlas:.5f} | {total:.4f} | {embree:.4f} |")


if __name__ == "__main__":
    main()
