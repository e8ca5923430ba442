"""Rays that stay on the GPU against numpy in and out, and the peers, on the same rays; prints a
Markdown table (issue 14's figures).

    python benchmarks/bench_resident.py --rays 1e6 16e6 --big            # vkray (torch and numpy) + Embree
    python benchmarks/bench_resident.py --rays 1e6 16e6 --big --only open3d   # Open3D, in its own venv
    python benchmarks/bench_resident.py --rays 1e6 16e6 --big --only mitsuba  # Mitsuba 3 (cuda_ad_rgb)

Per mesh (the bunny; with --big the bunny subdivided twice, 1.1M triangles) and rays (camera and
random, the same seeds everywhere): vkray with torch CUDA tensors in and `vkray.CudaArray` out
(read as torch tensors, timed to torch.cuda.synchronize()), vkray numpy in and out with the
caller's arrays imported and the rays packed by the GPU (VKRAY_PACK=gpu) and packed by the host
(the default), each
asking t and prim_id (lean) and the default fields, and the host path writing into the arrays
of an earlier call (``out=``); Embree in N processes; Open3D's
RaycastingScene.cast_rays on numpy and on its own tensors; Mitsuba 3 (OptiX, the cuda_ad_rgb
variant) on rays it holds on the GPU, `ray_intersect_preliminary` (t and the primitive: lean) and
`ray_intersect` (a whole surface interaction: default), evaluated and synchronized. Best of
--repeat after a warm-up.
"""

from __future__ import annotations

import argparse
import functools
import os
import pathlib
import sys

import _timing
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from oracle import camera_rays, load_mesh, random_rays  # noqa: E402

LEAN = ["t", "prim_id"]


# Each timing runs its call once first, untimed (pipelines compiled, memory faulted in).
best_of = functools.partial(_timing.best_of, warm=True)


def subdivided(vertices, faces, times):
    for _ in range(times):
        a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
        n = len(vertices)
        mids = np.concatenate([(vertices[a] + vertices[b]) / 2, (vertices[b] + vertices[c]) / 2,
                               (vertices[c] + vertices[a]) / 2])
        m = len(faces)
        ab, bc, ca = n + np.arange(m), n + m + np.arange(m), n + 2 * m + np.arange(m)
        vertices = np.concatenate([vertices, mids])
        faces = np.concatenate([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return vertices, faces


def rays_for(vertices, kind, n):
    if kind == "camera":
        side = int(round(np.sqrt(n)))
        o, d = camera_rays(vertices, side, side)
        o = np.broadcast_to(o, d.shape)  # every peer gets whole arrays
    else:
        o, d = random_rays(vertices, n, seed=1)
    return np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32)


def vkray_rows(name, v, f, kind, n, repeat, processes):
    import torch

    import vkray

    o, d = rays_for(v, kind, n)
    rows = {}
    os.environ["VKRAY_PACK"] = "gpu"  # import the caller's arrays, the GPU packs (not the default)
    devices = {"gpu": vkray.Device()}
    os.environ["VKRAY_PACK"] = "host"  # the default
    devices["host"] = vkray.Device()
    del os.environ["VKRAY_PACK"]
    scenes = {k: dev.scene([dev.mesh(v, f)]) for k, dev in devices.items()}
    to, td = torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda()
    for label, fields in (("lean", LEAN), ("default", None)):
        def resident():
            hits = scenes["gpu"].intersect(to, td, outputs=fields)
            torch.from_dlpack(hits.t)
            torch.cuda.synchronize()

        rows[f"torch {label}"] = best_of(repeat, resident)
        for packing in ("gpu", "host"):
            rows[f"numpy {label} ({packing} packs)"] = best_of(
                repeat, lambda: scenes[packing].intersect(o, d, outputs=fields))
            if label == "lean":
                rows[f"profile {packing}"] = devices[packing].last_trace_profile
        reused = scenes["host"].intersect(o, d, outputs=fields)
        rows[f"numpy {label} (host packs, out=)"] = best_of(
            repeat, lambda: scenes["host"].intersect(o, d, outputs=fields, out=reused))
        if label == "lean":
            rows["profile host out="] = devices["host"].last_trace_profile
    if processes:
        import bench_core

        rows["embree"] = embree_seconds(bench_core, v, f, o, d, processes, repeat)
    return rows


def embree_seconds(bench_core, v, f, o, d, processes, repeat):
    import multiprocessing as mp

    bench_core._worker["rays"] = (o, d)
    n = len(o)
    jobs = [(k * n // processes, (k + 1) * n // processes, False) for k in range(processes)]
    with mp.get_context("fork").Pool(processes, bench_core._embree_init, (v, f)) as pool:
        return best_of(repeat, lambda: pool.map(bench_core._embree_part, jobs))


def open3d_rows(v, f, kind, n, repeat):
    import open3d as o3d

    o, d = rays_for(v, kind, n)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    rays = o3d.core.Tensor(np.hstack([o, d]))

    def from_numpy():
        result = scene.cast_rays(o3d.core.Tensor(np.hstack([o, d])))
        return result["t_hit"].numpy(), result["primitive_ids"].numpy()

    return {"open3d numpy": best_of(repeat, from_numpy), "open3d tensors": best_of(repeat, lambda: scene.cast_rays(rays))}


def mitsuba_rows(v, f, kind, n, repeat):
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("cuda_ad_rgb")
    o, d = rays_for(v, kind, n)
    mesh = mi.Mesh("mesh", vertex_count=len(v), face_count=len(f), has_vertex_normals=False,
                   has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(v, np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(f, np.uint32).ravel())
    params.update()
    scene = mi.load_dict({"type": "scene", "mesh": mesh})

    def vec(a, kind_of):
        return kind_of(*(mi.Float(np.ascontiguousarray(a[:, k])) for k in range(3)))

    ray = mi.Ray3f(o=vec(o, mi.Point3f), d=vec(d, mi.Vector3f))
    dr.eval(ray)
    dr.sync_thread()

    def lean():
        hit = scene.ray_intersect_preliminary(ray)
        dr.eval(hit.t, hit.prim_index)
        dr.sync_thread()
        return hit

    def default():
        si = scene.ray_intersect(ray)
        dr.eval(si.t, si.prim_index, si.p, si.uv, si.n, si.sh_frame.n)
        dr.sync_thread()

    rows = {"mitsuba lean": best_of(repeat, lean), "mitsuba default": best_of(repeat, default)}
    t = lean().t.numpy()
    print(f"|   | mitsuba hits | {int(np.isfinite(t).sum()):,} of {n:,} |", flush=True)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rays", type=float, nargs="+", default=[1e6])
    parser.add_argument("--big", action="store_true")
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--embree-processes", type=int, default=0)
    parser.add_argument("--only", choices=["vkray", "open3d", "mitsuba"], default="vkray")
    args = parser.parse_args()
    v, f = load_mesh("stanford-bunny")
    meshes = [("bunny", v, f)] + ([("bunny x16 (subdivided)", *subdivided(v, f, 2))] if args.big else [])
    for name, vv, ff in meshes:
        for kind in ("camera", "random"):
            for n in (int(r) for r in args.rays):
                if args.only == "open3d":
                    rows = open3d_rows(vv, ff, kind, n, args.repeat)
                elif args.only == "mitsuba":
                    rows = mitsuba_rows(vv, ff, kind, n, args.repeat)
                else:
                    rows = vkray_rows(name, vv, ff, kind, n, args.repeat, args.embree_processes)
                speeds = " | ".join(f"{k}: {n / s / 1e6:.0f}" for k, s in rows.items() if not k.startswith("profile"))
                print(f"| {name} | {kind} | {n:,} | {speeds} |", flush=True)
                for k, p in rows.items():
                    if k.startswith("profile"):
                        split = ", ".join(f"{key} {value:.4f}" for key, value in p.items()
                                          if isinstance(value, float) and value)
                        print(f"|   | {k} | {split} |", flush=True)


if __name__ == "__main__":
    main()
