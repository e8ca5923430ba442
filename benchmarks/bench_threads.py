"""One device, one scene, many rays: one call for all of them, or calls of one chunk each (as a Dask
worker traces its chunks) from 1, 2, 3, 4 or 8 Python threads at once. What chunking and threads
cost or gain on one GPU, without Dask; and what the device keeps between queries
(`Device.idle_memory`).

    python benchmarks/bench_threads.py --rays 64e6 --chunk 4e6

Bunny (vkray.data), float32 random rays (tests/oracle.py's random_rays, seed 1), lean
`intersect` (`t`, `prim_id`) and `occluded`; best of --repeat; each line also shows the device's
`last_trace_profile` (milliseconds) and `idle_memory` after the run.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import threading
from typing import Any, Callable, Dict, List, Tuple

import numpy as np
from _timing import best_of

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
from oracle import load_mesh, random_rays  # noqa: E402

LEAN = ["t", "prim_id"]
OPTIONS: Dict[str, Dict[str, Any]] = {"intersect": {"outputs": LEAN}, "occluded": {}}


def profile(device: vkray.Device) -> str:
    shown = {k: v for k, v in device.last_trace_profile.items() if v not in (None, 0, 0.0)}
    return " ".join(f"{k}={v * 1e3:.2f}" if isinstance(v, float) else f"{k}={v}" for k, v in shown.items())


def in_threads(scene: vkray.Scene, query: str, chunks: List[Tuple[np.ndarray, np.ndarray]], k: int) -> Callable[[], None]:
    """Every chunk traced once, thread j taking chunks j, j + k, ..."""

    def run() -> None:
        def work(j: int) -> None:
            for o, d in chunks[j::k]:
                getattr(scene, query)(o, d, **OPTIONS[query])

        threads = [threading.Thread(target=work, args=(j,)) for j in range(k)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rays", type=float, default=64e6)
    parser.add_argument("--chunk", type=float, default=4e6, help="rays per call in the chunked runs")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2, 3, 4, 8])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--device", default=None, help="index or name (default: vkray.Device()'s choice)")
    args = parser.parse_args()
    n, c = int(args.rays), int(args.chunk)
    v, f = load_mesh("stanford-bunny")
    device = vkray.Device(args.device) if args.device is not None else vkray.Device()
    scene = device.scene(device.mesh(v, f))
    o, d = (a.astype(np.float32) for a in random_rays(v, n, seed=1))
    chunks = [(np.ascontiguousarray(o[s : s + c]), np.ascontiguousarray(d[s : s + c])) for s in range(0, n, c)]
    print(f"{device.name}: {n:,} rays, calls of {c:,}, best of {args.repeat}")
    for query in OPTIONS:
        getattr(scene, query)(o[:1024], d[:1024], **OPTIONS[query])  # compiles the pipeline
        runs = [(f"one call of {n:,}", lambda q=query: getattr(scene, q)(o, d, **OPTIONS[q]))]
        runs += [(f"{len(chunks)} calls on {k} threads", in_threads(scene, query, chunks, k)) for k in args.threads]
        for label, run in runs:
            seconds = best_of(args.repeat, run)
            print(f"{query} {label}: {seconds * 1e3:.1f} ms, {n / seconds / 1e6:.1f} M rays/s | last call: "
                  f"{profile(device)} | idle {device.idle_memory}", flush=True)


if __name__ == "__main__":
    main()
