"""Issue 15: rays per second on 1, 2, 4 ... devices. `vkray.DeviceGroup` (one process, a thread per
device, numpy in and numpy out), and with --dask `vkray.dask` on a local cluster of one worker
process per device (`vkray.dask.local_cluster`: VKRAY_DEVICE per worker). Prints Markdown; `--json`
keeps every figure. Progress lines (each step, each timed run, with the seconds since the start) go
to stderr as they happen, so that a run cut short shows where it stopped.

    python benchmarks/bench_scaling.py --rays 64e6 --json $OUT/scaling.json          # every GPU of the machine
    python benchmarks/bench_scaling.py --rays 256e6 --dask --gather --json $OUT/scaling-dask.json
    python benchmarks/bench_scaling.py --rays 2e5 --same-device 2 --dask --gather     # lavapipe smoke test
    python benchmarks/bench_scaling.py --rays 64e6 --resident --json $OUT/resident.json  # torch CUDA rays

Rays: the bunny (vkray.data). Queries: `intersect` with `outputs=["t", "prim_id"]` (8 bytes a
ray out: the lean closest hit) and `occluded`.

Group: float32 rays from a sphere of twice the bunny's bounding radius towards uniform points of its
bounding box (tests/oracle.py's random_rays, seed 1). For each device count k, a `DeviceGroup` of
the first k devices (--devices, default every hardware device; --same-device K opens device 0 K
times) builds the scene; one query of each kind on all the rays sizes the pieces by the devices'
measured speeds, then the figure is the best of --repeat. k = 1 is also timed on a plain `Scene`.
Every answer is compared with that `Scene`'s.

Dask (--dask): the same kind of rays without random_rays' quarter of wild directions, drawn in
float32, each chunk of --chunk rays from its own seed. For each k, a cluster of k worker processes
(--threads-per-worker threads each: 3 by default, as `local_cluster`'s); the rays are made on the
workers and kept there (`Client.persist`), outside the timing, so that no ray crosses the network
and the figure is the tracing. "dask": the best of
--repeat of tracing every chunk where its rays are, the answers kept in the workers' memory
(`Client.persist`, numpy out on the workers), after one warm-up (each worker builds its scene and
compiles its pipelines); the answers' chunks are compared with one `Scene`'s in this process by
digest (blake2b of each chunk, computed where the chunk is), so that nothing but the digests
crosses to this process. "dask gathered" (--gather): the best of --repeat of `dask.compute`
gathering every answer into this process (numpy out here: 8 bytes a ray for intersect, 1 for
occluded, through the network), compared whole. Until this revision the dask figure was the
gathered one and included making the rays on the workers, in float64, each chunk twice (vkray.dask
took each array's blocks from its own optimized graph): 20 s a computation for 64M rays on one
worker of the 2-core test machine, in each of the 8 computations per device count.
Resident (--resident, torch with CUDA): the group's rays as float32 CUDA tensors, each of k GPUs'
share (contiguous, in proportion to equal weights) already on that GPU; one thread per GPU calls
`intersect` (lean) or `occluded` on its share through that GPU's member of the group
(`GroupScene.per_device[j]`: rays already spread over the GPUs, nothing copied between them), the
hits left there; timed to `torch.cuda.synchronize` of every GPU. Every answer
is compared with one `Scene`'s numpy answer on the same rays. Then "on one GPU, split": all the
rays as one tensor pair on the first GPU, one call of the group, which splits them (each member
copies its rows over NVLink or PCIe and its hits back; shares by measured speed, the first call
untimed), the hits on that GPU, timed to the synchronization of every GPU.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import platform
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Dict, List, Sequence

import numpy as np
from _timing import best_of

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
from oracle import bounds, load_mesh, random_rays  # noqa: E402

QUERIES = ("intersect", "occluded")
LEAN = ["t", "prim_id"]
STARTED = time.perf_counter()


def log(message: str) -> None:
    """A progress line on stderr, at once: where a run that times out stopped."""
    print(f"[{time.perf_counter() - STARTED:7.1f} s] {message}", file=sys.stderr, flush=True)


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
    log(f"building the Scene on device {devices[0]!r}")
    first = vkray.Device(devices[0])
    scene = first.scene(first.mesh(*mesh))
    reference = {}
    rows = []
    for query in QUERIES:
        answer(scene, query, o[:1024], d[:1024])  # compiles the pipeline
        reference[query] = answer(scene, query, o, d)
        seconds = best_of(repeat, lambda: answer(scene, query, o, d))
        log(f"Scene {query}: {seconds:.3f} s ({n / seconds / 1e6:.1f} M rays/s)")
        rows.append(dict(mode="Scene", devices=1, query=query, rays=n, seconds=seconds, same=True))
    for k in device_counts(len(devices)):
        log(f"{k} devices: opening them, building the scene on each")
        group = vkray.DeviceGroup(devices[:k])
        group_scene = group.scene(group.mesh(*mesh))
        for query in QUERIES:
            answer(group_scene, query, o[: 1024 * k], d[: 1024 * k])
            answer(group_scene, query, o, d)  # measures the devices' speeds
            log(f"{k} devices: {query} warmed up and the devices' speeds measured")
            seconds = best_of(repeat, lambda: answer(group_scene, query, o, d))
            ok = same(answer(group_scene, query, o, d), reference[query])
            weights = group.weights(f"{query}/fast")
            shares = [round(w / sum(weights), 3) for w in weights]
            log(f"{k} devices: {query}: {seconds:.3f} s ({n / seconds / 1e6:.1f} M rays/s), shares {shares}, "
                f"answers {'equal' if ok else 'DIFFER FROM'} one Scene's")
            rows.append(dict(mode="DeviceGroup", devices=k, query=query, rays=n, seconds=seconds, same=ok, shares=shares))
    return rows


def bench_resident(devices: List[Any], mesh: Any, o: np.ndarray, d: np.ndarray, repeat: int) -> List[Dict[str, Any]]:
    import threading

    import torch

    n = len(o)
    log(f"building the Scene on device {devices[0]!r}")
    first = vkray.Device(devices[0])
    reference = {query: answer(first.scene(first.mesh(*mesh)), query, o, d) for query in QUERIES}
    rows = []
    for k in device_counts(len(devices)):
        log(f"{k} devices: opening them, building the scene on each, the rays onto their GPUs")
        group = vkray.DeviceGroup(devices[:k])
        scene = group.scene(group.mesh(*mesh))
        gpus = [f"cuda:{device.cuda_device}" for device in group.devices]
        parts = np.array_split(np.arange(n), k)
        shares = [(torch.from_numpy(o[p]).to(g), torch.from_numpy(d[p]).to(g)) for p, g in zip(parts, gpus)]

        def run(query: str) -> List[Any]:
            answers: List[Any] = [None] * k

            def one(j: int) -> None:
                answers[j] = answer(scene.per_device[j], query, *shares[j])

            threads = [threading.Thread(target=one, args=(j,)) for j in range(k)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            for g in gpus:
                torch.cuda.synchronize(g)
            return answers

        for query in QUERIES:
            answers = run(query)  # warm-up: pipelines, CUDA leases
            seconds = best_of(repeat, lambda: run(query))
            got = {
                name: np.concatenate([torch.from_dlpack(a[name]).cpu().numpy() for a in answers])
                for name in answers[0]
            }
            if query == "occluded":  # CUDA rays: the blocking triangle, -1 where none
                got["occluded"] = got["occluded"] >= 0
            ok = same(got, reference[query])
            log(f"{k} devices: resident {query}: {seconds:.3f} s ({n / seconds / 1e6:.1f} M rays/s), answers "
                f"{'equal' if ok else 'DIFFER FROM'} one Scene's")
            rows.append(dict(mode="DeviceGroup, CUDA rays", devices=k, query=query, rays=n, seconds=seconds, same=ok))
        whole = (torch.from_numpy(o).to(gpus[0]), torch.from_numpy(d).to(gpus[0]))

        def run_split(query: str) -> Dict[str, Any]:
            result = answer(scene, query, *whole)
            for g in gpus:
                torch.cuda.synchronize(g)
            return result

        for query in QUERIES:
            result = run_split(query)  # warm-up, and the first split by measured speeds
            seconds = best_of(repeat, lambda: run_split(query))
            got = {name: torch.from_dlpack(a).cpu().numpy() for name, a in result.items()}
            if query == "occluded":
                got["occluded"] = got["occluded"] >= 0
            ok = same(got, reference[query])
            shares = [round(w / sum(group.weights(f"{query}/cuda")), 3) for w in group.weights(f"{query}/cuda")]
            log(f"{k} devices: one GPU's tensor split, {query}: {seconds:.3f} s ({n / seconds / 1e6:.1f} M rays/s), "
                f"shares {shares}, answers {'equal' if ok else 'DIFFER FROM'} one Scene's")
            rows.append(dict(mode="DeviceGroup, CUDA rays on one GPU, split", devices=k, query=query, rays=n,
                             seconds=seconds, same=ok, shares=shares))
    return rows


def _ray_block(centre: np.ndarray, radius: float, lo: np.ndarray, hi: np.ndarray, block_info: Any = None) -> np.ndarray:
    """One chunk of rays as (k, 6) float32 (origins, directions), from its own seed (the chunk's
    index): origins uniform on the sphere of twice the bounding radius, towards uniform points of
    the bounding box. Drawn in float32: 0.2 s for 4M rays on one core of the 2-core test
    machine, against 1.4 s for the same formula in float64 (this benchmark's earlier version)."""
    k = block_info[None]["chunk-shape"][0]
    rng = np.random.default_rng([1, block_info[None]["chunk-location"][0]])
    rays = np.empty((k, 6), np.float32)
    u = rng.standard_normal((k, 3), dtype=np.float32)
    u *= np.float32(2.0 * radius) / np.sqrt(np.einsum("ij,ij->i", u, u))[:, None]
    rays[:, :3] = u + centre.astype(np.float32)
    targets = rng.random((k, 3), dtype=np.float32)
    targets *= (hi - lo).astype(np.float32)
    targets += lo.astype(np.float32)
    rays[:, 3:] = targets - rays[:, :3]
    return rays


def dask_rays(mesh: Any, n: int, chunk: int) -> Any:
    """Rays as dask arrays (origins, directions), each chunk made on a worker, C-contiguous."""
    import dask.array as da

    v, _ = mesh
    centre, radius = bounds(v)
    lengths = (chunk,) * (n // chunk) + ((n % chunk,) if n % chunk else ())
    meta = np.empty((0, 6), np.float32)
    rays = da.map_blocks(_ray_block, centre, radius, v.min(axis=0), v.max(axis=0), chunks=(lengths, (6,)), meta=meta)
    origins = rays[:, :3].map_blocks(np.ascontiguousarray, meta=meta[:, :3])
    directions = rays[:, 3:].map_blocks(np.ascontiguousarray, meta=meta[:, :3])
    return origins, directions


def digest(array: np.ndarray) -> str:
    """An array's dtype, shape and bytes, hashed: equal digests, equal arrays."""
    h = hashlib.blake2b(f"{array.dtype.str}{array.shape}".encode(), digest_size=16)
    h.update(np.ascontiguousarray(array).data)
    return h.hexdigest()


def block_digests(answers: Dict[str, np.ndarray], lengths: Sequence[int]) -> Dict[str, List[str]]:
    """`digest` of each chunk of each answer (the chunks of dask arrays chunked by ``lengths``),
    on this process's threads (hashlib lets go of the GIL)."""
    bounds_ = np.cumsum((0,) + tuple(lengths))
    with ThreadPoolExecutor(os.cpu_count()) as pool:
        return {
            name: list(pool.map(lambda ab, a=array: digest(a[ab[0] : ab[1]]), zip(bounds_[:-1], bounds_[1:])))
            for name, array in answers.items()
        }


def dask_digests(answers: Dict[str, Any]) -> Dict[str, List[str]]:
    """`digest` of each chunk of each dask array, computed where the chunk is (the default client)."""
    import dask

    names = sorted(answers)
    per_block = {name: [dask.delayed(digest)(b) for b in answers[name].to_delayed(optimize_graph=False).ravel()]
                 for name in names}
    (found,) = dask.compute(per_block)
    return {name: list(found[name]) for name in names}


def _count_known(keys: Sequence[str], dask_scheduler: Any = None) -> int:
    """How many of ``keys`` (as str) the scheduler still knows."""
    wanted = set(keys)
    return sum(str(key) in wanted for key in dask_scheduler.tasks)


def forget(client: Any, collections: List[Any]) -> None:
    """Releases persisted collections and waits until the scheduler has forgotten their keys, so
    that persisting the same graph again computes it again (its keys are the same)."""
    from dask.distributed import futures_of

    keys = [str(f.key) for f in futures_of(collections)]
    collections.clear()
    deadline = time.monotonic() + 60
    while client.run_on_scheduler(_count_known, keys):
        if time.monotonic() > deadline:
            log("warning: the scheduler still holds answers released 60 s ago: the next run may reuse them")
            return
        time.sleep(0.01)


def task_times(tasks: List[Dict[str, Any]], query: str, threads: int) -> str:
    """Where the workers' time went, from Dask's task stream: the vkray tasks' count and mean
    compute time, and the share of each worker's threads' time from its first task's start to
    its last task's end that the vkray tasks computed (``threads`` threads a worker; the rest:
    Dask's work between tasks, the other tasks, idle threads)."""
    traced = [t for t in tasks if f"vkray-{query}-" in str(t["key"])]
    computed = [(t["worker"], ss["start"], ss["stop"]) for t in traced for ss in t["startstops"] if ss["action"] == "compute"]
    if not computed:
        return "no vkray tasks in the task stream"
    busy = []
    for worker in sorted({w for w, _, _ in computed}):
        mine = [(a, b) for w, a, b in computed if w == worker]
        span = max(b for _, b in mine) - min(a for a, _ in mine)
        busy.append(sum(b - a for a, b in mine) / (span * threads) if span > 0 else 1.0)
    mean = sum(b - a for _, a, b in computed) / len(computed)
    shares = ", ".join(f"{x:.2f}" for x in busy)
    return f"{len(computed)} vkray tasks, {mean * 1e3:.1f} ms each, computing {shares} of each worker's threads' span"


def bench_dask(
    devices: List[Any], mesh: Any, n: int, chunk: int, repeat: int, gather: bool, threads: int
) -> List[Dict[str, Any]]:
    import dask
    from dask.distributed import Client, futures_of, get_task_stream, wait

    import vkray.dask as vkray_dask

    spec = vkray_dask.SceneSpec([mesh])
    origins, directions = dask_rays(mesh, n, chunk)
    lengths = origins.chunks[0]
    log(f"making {n:,} rays in this process (the reference), {len(lengths)} chunks")
    o, d = dask.compute(origins, directions, scheduler="threads")
    log(f"building the reference Scene on device {devices[0]!r}")
    scene = spec.build(vkray.Device(devices[0]))
    reference = {}
    for query in QUERIES:
        answer(scene, query, o[:1024], d[:1024])  # compiles the pipeline
        start = time.perf_counter()
        want = answer(scene, query, o, d)
        seconds = time.perf_counter() - start
        reference[query] = (want, block_digests(want, lengths))
        log(f"reference {query}: {seconds:.2f} s on one Scene in this process")
    del o, d, scene

    rows = []
    for k in device_counts(len(devices)):
        log(f"{k} devices: starting a local cluster of {k} workers")
        with vkray_dask.local_cluster(devices[:k], threads_per_worker=threads) as cluster, Client(cluster) as client:
            client.wait_for_workers(k, timeout=300)
            limits = sorted({w["memory_limit"] for w in client.scheduler_info()["workers"].values()})
            log(f"{k} devices: {k} workers up (memory limit each: {[f'{x / 2**30:.0f} GiB' for x in limits]})")
            start = time.perf_counter()
            rays = client.persist([origins, directions])
            wait(futures_of(rays))
            log(f"{k} devices: rays made on the workers and kept there in {time.perf_counter() - start:.1f} s")
            o_kept, d_kept = rays
            lazy = {
                "intersect": lambda: vkray_dask.intersect(spec, o_kept, d_kept, outputs=LEAN),
                "occluded": lambda: {"occluded": vkray_dask.occluded(spec, o_kept, d_kept)},
            }
            for query in QUERIES:
                graph = lazy[query]()
                names = sorted(graph)
                times = []
                for run in range(repeat + 1):  # run 0: each worker builds the scene, compiles its pipeline
                    with get_task_stream(client) as stream:
                        start = time.perf_counter()
                        kept = client.persist([graph[name] for name in names])
                        wait(futures_of(kept))
                        seconds = time.perf_counter() - start
                    what = "warm-up" if run == 0 else f"run {run}/{repeat}"
                    log(f"{k} devices: {query} {what}: {seconds:.3f} s ({n / seconds / 1e6:.1f} M rays/s), answers kept;"
                        f" {task_times(stream.data, query, threads)}")
                    if run > 0:
                        times.append(seconds)
                    if run == repeat:
                        ok = dask_digests(dict(zip(names, kept))) == reference[query][1]
                        log(f"{k} devices: {query} answers {'equal' if ok else 'DIFFER FROM'} one Scene's")
                    forget(client, kept)
                rows.append(dict(mode="dask", devices=k, query=query, rays=n, seconds=min(times), same=ok, chunk=chunk,
                                 threads_per_worker=threads))
                if not gather:
                    continue
                times = []
                for run in range(repeat):
                    start = time.perf_counter()
                    (got,) = dask.compute(graph)
                    times.append(time.perf_counter() - start)
                    log(f"{k} devices: {query} gathered, run {run + 1}/{repeat}: {times[-1]:.3f} s")
                ok = same(got, reference[query][0])
                del got
                rows.append(dict(mode="dask gathered", devices=k, query=query, rays=n, seconds=min(times), same=ok,
                                 chunk=chunk))
            log(f"{k} devices: closing the cluster")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rays", type=float, default=64e6)
    parser.add_argument("--devices", nargs="+", help="device indices or names (default: every hardware device)")
    parser.add_argument("--same-device", type=int, metavar="K", help="device 0, opened K times (lavapipe)")
    parser.add_argument("--dask", action="store_true", help="vkray.dask on a local cluster, instead of DeviceGroup")
    parser.add_argument("--resident", action="store_true", help="torch CUDA rays, each GPU's share on it")
    parser.add_argument("--gather", action="store_true", help="with --dask: also time gathering the answers here")
    parser.add_argument("--chunk", type=float, default=4e6, help="rays per dask chunk")
    parser.add_argument("--threads-per-worker", type=int, default=3, help="with --dask: each worker's threads")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--mesh", default="stanford-bunny")
    parser.add_argument("--json", type=pathlib.Path)
    args = parser.parse_args()

    from vkray._device_group import default_devices

    devices: List[Any] = [0] * args.same_device if args.same_device else (args.devices or default_devices())
    n = int(args.rays)
    mesh = load_mesh(args.mesh)
    if args.dask:
        rows = bench_dask(devices, mesh, n, int(args.chunk), args.repeat, args.gather, args.threads_per_worker)
    else:
        log(f"making {n:,} rays (random_rays)")
        o, d = (a.astype(np.float32) for a in random_rays(mesh[0], n, seed=1))
        bench = bench_resident if args.resident else bench_group
        rows = bench(devices, mesh, o, d, args.repeat)
    log("done")

    names = [vkray.devices()[x].name if isinstance(x, int) else str(x) for x in devices]
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
