"""Issue 15: rays per second on 1, 2, 4 ... devices. `vkray.DeviceGroup` (one process, a thread per
device, numpy in and numpy out), and with --dask `vkray.dask` on a local cluster of one worker
process per device (`vkray.dask.local_cluster`: VKRAY_DEVICE per worker). Prints Markdown; `--json`
keeps every figure.

    python benchmarks/bench_scaling.py --rays 64e6 --json $OUT/scaling.json          # every GPU of the machine
    python benchmarks/bench_scaling.py --rays 64e6 --dask --json $OUT/scaling-dask.json
    python benchmarks/bench_scaling.py --rays 2e5 --same-device 2 --dask              # lavapipe smoke test

Rays: the bunny (../shared/meshes), float32 rays from a sphere of twice its bounding radius towards
uniform points of its bounding box (tests/oracle.py's random_rays, seed 1). Queries: `intersect`
with `outputs=["t", "prim_id"]` (8 bytes a ray out: the lean closest hit) and `occluded`.

Group: for each device count k, a `DeviceGroup` of the first k devices (--devices, default every
hardware device; --same-device K opens device 0 K times) builds the scene; one query of each kind
on all the rays sizes the pieces by the devices' measured speeds, then the figure is the best of
--repeat. k = 1 is also timed on a plain `Scene`. Every answer is compared with that `Scene`'s.

Dask (--dask): for each k, a cluster of k worker processes (one thread each); the rays are made on
the workers (the same formula without random_rays' quarter of wild directions, each chunk of
--chunk rays from its own seed), so that no ray crosses the network; the figure is the best of --repeat of `dask.compute` gathering every answer
into this process (numpy out), after one warm-up computation (each worker builds its scene and
compiles its pipelines). Answers compared with a `Scene` in this process on the same rays.
DeviceGroup does not split CUDA arrays (issue 14) yet: every figure is numpy in host memory.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import sys
import time
from typing import Any, Callable, Dict, List

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
from oracle import bounds, load_obj, random_rays  # noqa: E402

QUERIES = ("intersect", "occluded")
LEAN = ["t", "prim_id"]


def best_of(repeat: int, run: Callable[[], Any]) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def answer(scene: Any, query: str, o: np.ndarray, d: np.ndarray) -> Dict[str, np.ndarray]:
    """The query's arrays on a Scene or GroupScene."""
    if query == "intersect":
        hits = scene.intersect(o, d, outputs=LEAN)
        return {"t": hits.t, "prim_id": hits.prim_id}
    return {"occluded": scene.occluded(o, d)}


def same(got: Dict[str, np.ndarray], want: Dict[str, np.ndarray]) -> bool:
    return all(np.array_equal(got[k], want[k]) for k in want)


def device_counts(available: int) -> List[int]:
    """1, 2, 4 ... and every device."""
    counts = [k for k in (1, 2, 4, 8, 16, 32) if k < available]
    return counts + [available]


def bench_group(devices: List[Any], mesh: Any, o: np.ndarray, d: np.ndarray, repeat: int) -> List[Dict[str, Any]]:
    n = len(o)
    first = vkray.Device(devices[0])
    scene = first.scene(first.mesh(*mesh))
    reference = {}
    rows = []
    for query in QUERIES:
        answer(scene, query, o[:1024], d[:1024])  # compiles the pipeline
        reference[query] = answer(scene, query, o, d)
        seconds = best_of(repeat, lambda: answer(scene, query, o, d))
        rows.append(dict(mode="Scene", devices=1, query=query, rays=n, seconds=seconds, same=True))
    for k in device_counts(len(devices)):
        group = vkray.DeviceGroup(devices[:k])
        group_scene = group.scene(group.mesh(*mesh))
        for query in QUERIES:
            answer(group_scene, query, o[: 1024 * k], d[: 1024 * k])
            answer(group_scene, query, o, d)  # measures the devices' speeds
            seconds = best_of(repeat, lambda: answer(group_scene, query, o, d))
            ok = same(answer(group_scene, query, o, d), reference[query])
            weights = group.weights(f"{query}/fast")
            shares = [round(w / sum(weights), 3) for w in weights]
            rows.append(dict(mode="DeviceGroup", devices=k, query=query, rays=n, seconds=seconds, same=ok, shares=shares))
    return rows


def _ray_block(centre: np.ndarray, radius: float, lo: np.ndarray, hi: np.ndarray, block_info: Any = None) -> np.ndarray:
    """One chunk of rays as (k, 6) float32 (origins, directions): oracle.random_rays' formula,
    without its quarter of wild directions, seeded by the chunk's index."""
    k = block_info[None]["chunk-shape"][0]
    rng = np.random.default_rng([1, block_info[None]["chunk-location"][0]])
    u = rng.normal(size=(k, 3))
    origins = centre + 2.0 * radius * u / np.linalg.norm(u, axis=1, keepdims=True)
    targets = rng.uniform(lo, hi, size=(k, 3))
    return np.hstack([origins, targets - origins]).astype(np.float32)


def dask_rays(mesh: Any, n: int, chunk: int) -> Any:
    """Rays as dask arrays (origins, directions), each chunk made on a worker."""
    import dask.array as da

    v, _ = mesh
    centre, radius = bounds(v)
    lengths = (chunk,) * (n // chunk) + ((n % chunk,) if n % chunk else ())
    rays = da.map_blocks(_ray_block, centre, radius, v.min(axis=0), v.max(axis=0), chunks=(lengths, (6,)), dtype=np.float32)
    return rays[:, :3], rays[:, 3:]


def bench_dask(devices: List[Any], mesh: Any, n: int, chunk: int, repeat: int) -> List[Dict[str, Any]]:
    import dask
    from dask.distributed import Client

    import vkray.dask as vkray_dask

    spec = vkray_dask.SceneSpec([mesh])
    origins, directions = dask_rays(mesh, n, chunk)
    o, d = dask.compute(origins, directions)
    device = vkray.Device(devices[0])
    scene = spec.build(device)
    reference = {query: answer(scene, query, o, d) for query in QUERIES}
    lazy = {
        "intersect": lambda: vkray_dask.intersect(spec, origins, directions, outputs=LEAN),
        "occluded": lambda: {"occluded": vkray_dask.occluded(spec, origins, directions)},
    }
    rows = []
    for k in device_counts(len(devices)):
        with vkray_dask.local_cluster(devices[:k]) as cluster, Client(cluster) as client:
            client.wait_for_workers(k)
            for query in QUERIES:
                graph = lazy[query]()
                dask.compute(graph)  # each worker builds the scene, compiles its pipeline
                seconds = best_of(repeat, lambda: dask.compute(graph))
                (got,) = dask.compute(graph)
                rows.append(dict(mode="dask", devices=k, query=query, rays=n, seconds=seconds, same=same(got, reference[query]),
                                 chunk=chunk))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rays", type=float, default=64e6)
    parser.add_argument("--devices", nargs="+", help="device indices or names (default: every hardware device)")
    parser.add_argument("--same-device", type=int, metavar="K", help="device 0, opened K times (lavapipe)")
    parser.add_argument("--dask", action="store_true", help="vkray.dask on a local cluster, instead of DeviceGroup")
    parser.add_argument("--chunk", type=float, default=4e6, help="rays per dask chunk")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--mesh", default="stanford-bunny")
    parser.add_argument("--json", type=pathlib.Path)
    args = parser.parse_args()

    from vkray._group import default_devices

    devices: List[Any] = [0] * args.same_device if args.same_device else (args.devices or default_devices())
    n = int(args.rays)
    mesh = load_obj(args.mesh)
    if args.dask:
        rows = bench_dask(devices, mesh, n, int(args.chunk), args.repeat)
    else:
        o, d = (a.astype(np.float32) for a in random_rays(mesh[0], n, seed=1))
        rows = bench_group(devices, mesh, o, d, args.repeat)

    names = [vkray.Device(x).name for x in devices]
    host = f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}"
    print(f"Command: `python {' '.join(sys.argv)}`\n")
    print(f"Devices: {', '.join(names)}; host {host}; {args.mesh}, {n:,} rays, best of {args.repeat}.\n")
    print("| mode | devices | query | M rays/s | speed-up over 1 device | answers as one Scene's |")
    print("|---|---|---|---|---|---|")
    one = {(r["mode"], r["query"]): r["seconds"] for r in rows if r["devices"] == 1}
    for r in rows:
        r["rays_per_s"] = r["rays"] / r["seconds"]
        r["speedup"] = one[(r["mode"], r["query"])] / r["seconds"]
        shares = f" (shares {r['shares']})" if "shares" in r else ""
        print(f"| {r['mode']} | {r['devices']} | {r['query']} | {r['rays_per_s'] / 1e6:.1f} | {r['speedup']:.2f}x{shares} | {r['same']} |")
    if args.json:
        args.json.write_text(json.dumps({"command": sys.argv, "devices": names, "host": host, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
