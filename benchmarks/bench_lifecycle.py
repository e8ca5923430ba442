"""Acceleration-structure lifecycle figures in one run; prints Markdown.

    python benchmarks/bench_lifecycle.py                          # the shipped meshes, 1k..100k instances
    python benchmarks/bench_lifecycle.py --big --instances 1000 100000 1000000   # the GPU run

- BLAS build speed (Mtris/s) per build preference against Embree's scene build;
- compaction: bytes before and after, on every shipped mesh (vkray.data);
- trace speed per build preference (1M random rays, closest hit, t and prim_id);
- refit (`Mesh.update`) against a rebuild of the same vertices;
- TLAS build and refit (`Scene.update`) for many instances of the bunny;
- quantized vertex formats: memory saved and accuracy lost against float32, on every shipped mesh (vkray.data).
Times are best of `--repeat`, wall clock around the Python call unless marked as the device's own.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np
from _timing import best_run

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
from oracle import MESH_NAMES, load_mesh, random_rays  # noqa: E402

BUILDS = ("fast_trace", "fast_build", "low_memory")


def embree_build(v, f):
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(v[f], dtype=np.float32))
    scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))  # commits the build
    return scene


def meshes(big):
    out = [(name, *load_mesh(name)) for name in MESH_NAMES]
    if big:
        import trimesh.remesh

        v, f = load_mesh("stanford-bunny")
        for _ in range(2):
            v, f = trimesh.remesh.subdivide(v, f)
        out.append(("bunny x16 (subdivided)", v, f))
    return out


def random_transforms(n, spread, seed):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    t = np.zeros((n, 4, 4))
    t[:, 0, :3] = np.column_stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)])
    t[:, 1, :3] = np.column_stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)])
    t[:, 2, :3] = np.column_stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)])
    t[:, :3, 3] = rng.uniform(-spread, spread, (n, 3))
    t[:, 3, 3] = 1
    return t


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--big", action="store_true", help="add the bunny subdivided twice (1.1M triangles)")
    parser.add_argument("--instances", type=int, nargs="+", default=[1000, 100_000])
    parser.add_argument("--rays", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    device = vkray.Device()
    print(f"Command: `python {' '.join(sys.argv)}`\n")
    print(f"Device: {device.name} ({device.info.device_type}), driver {device.info.driver}, backend `{device.backend}`.\n")

    print("BLAS builds and traces per build preference (build: device time from submission to a usable BLAS, "
          "uploads included; trace: 1M random rays, closest hit with t and prim_id, end to end and the device's "
          "trace alone):\n")
    print("| mesh | triangles | build | BLAS build s | Mtris/s | Embree build s | Mtris/s | bytes | compacted bytes | saved | trace Mrays/s | trace alone Mrays/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, v, f in meshes(args.big):
        embree_s, _ = best_run(args.repeat, lambda: embree_build(v, f))
        origins, directions = random_rays(v, args.rays, seed=41)
        for build in BUILDS:
            seconds = min(device.mesh(v, f, build=build).stats["build_seconds"] for _ in range(args.repeat))
            compacted = device.mesh(v, f, build=build, compact=True)
            scene = device.scene(compacted)
            scene.intersect(origins[:10], directions[:10], outputs=["t", "prim_id"])
            trace_s, _ = best_run(args.repeat, lambda: scene.intersect(origins, directions, outputs=["t", "prim_id"]))
            gpu = device.last_trace_profile["gpu_trace"]
            s = compacted.stats
            print(f"| {name} | {len(f):,} | {build} | {seconds:.4f} | {len(f) / seconds / 1e6:.1f} | {embree_s:.4f} | "
                  f"{len(f) / embree_s / 1e6:.1f} | {s['built_bytes']:,} | {s['bytes']:,} | "
                  f"{1 - s['bytes'] / s['built_bytes']:.0%} | {len(origins) / trace_s / 1e6:.1f} | "
                  f"{'n/a' if not gpu else f'{len(origins) / gpu / 1e6:.0f}'} |")

    print("\nRefit (`Mesh.update`, UPDATE mode in place) against a rebuild of the same moved vertices "
          "(wall clock of the Python call, upload included):\n")
    print("| mesh | triangles | rebuild s | refit s | refit / rebuild | trace after refit / after rebuild |")
    print("|---|---|---|---|---|---|")
    for name, v, f in meshes(args.big)[:1] + meshes(args.big)[-1:]:
        size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
        moved = v + 0.02 * size * np.sin(7 * v[:, [1, 2, 0]] / size)
        rebuild_s, fresh = best_run(args.repeat, lambda: device.mesh(moved, f, allow_update=True))
        mesh = device.mesh(v, f, allow_update=True)
        refit_s, _ = best_run(args.repeat, lambda: mesh.update(moved))
        origins, directions = random_rays(moved, args.rays, seed=42)
        times = []
        for m in (mesh, fresh):
            scene = device.scene(m)
            scene.intersect(origins[:10], directions[:10], outputs=["t"])
            times.append(best_run(args.repeat, lambda: scene.intersect(origins, directions, outputs=["t"]))[0])
        print(f"| {name} | {len(f):,} | {rebuild_s:.4f} | {refit_s:.4f} | {refit_s / rebuild_s:.2f} | {times[0] / times[1]:.2f} |")

    print("\nQuantized vertices (`vertex_format=`): bytes of the vertex buffer and of the BLAS, and how far hits "
          "move against the float32 mesh (reference tier on both, 100k random rays; |Δt| along the ray over the "
          "mesh's bounding-box diagonal):\n")
    print("| mesh | format | vertex bytes | BLAS bytes | hit/miss changed | p50 \\|Δt\\| | p99 \\|Δt\\| | max \\|Δt\\| |")
    print("|---|---|---|---|---|---|---|---|")
    for name, v, f in meshes(False):
        size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
        origins, directions = random_rays(v, 100_000, seed=43)
        length = np.linalg.norm(directions, axis=1)
        full = device.scene(device.mesh(v, f)).intersect(origins, directions, precision="reference", outputs=["t"])
        for fmt in ("float32", "float16", "snorm16"):
            if fmt not in device.limits["vertex_formats"]:
                continue
            mesh = device.mesh(v, f, vertex_format=fmt)
            hits = device.scene(mesh).intersect(origins, directions, precision="reference", outputs=["t"])
            both = hits.hit & full.hit
            moved = np.abs(hits.t[both] - full.t[both]) * length[both] / size
            p50, p99 = np.percentile(moved, [50, 99])
            print(f"| {name} | {fmt} | {mesh.stats['vertex_bytes']:,} | {mesh.stats['bytes']:,} | "
                  f"{np.mean(hits.hit != full.hit):.3%} | {p50:.1e} | {p99:.1e} | {moved.max():.1e} |")

    print("\nTLAS over many instances of the bunny (random rotations and translations): build and refit "
          "(`Scene.update(transforms=...)`), wall clock of the Python call and the device's build time:\n")
    print("| instances | build s (call) | TLAS build s (device) | refit s (call) | TLAS bytes |")
    print("|---|---|---|---|---|")
    v, f = load_mesh("stanford-bunny")
    bunny = device.mesh(v, f)
    for n in args.instances:
        spread = 0.2 * n ** (1 / 3)
        first, moved = random_transforms(n, spread, 1), random_transforms(n, spread, 2)
        instances = [vkray.Instance(bunny, t) for t in first]
        build_s, scene = best_run(1, lambda: device.scene(instances, allow_update=True))
        refit_s, _ = best_run(args.repeat, lambda: scene.update(transforms=moved))
        print(f"| {n:,} | {build_s:.3f} | {scene.stats['build_seconds']:.4f} | {refit_s:.3f} | {scene.stats['bytes']:,} |")


if __name__ == "__main__":
    main()
