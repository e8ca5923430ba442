"""How long Ctrl-C waits: a query through 200 stacked squares (200 hits a ray), SIGINT one second
in, the seconds until KeyboardInterrupt. Issue 34's measurement (docs/benchmarks.md).

    python benchmarks/bench_interrupt.py cpu 4000000 count_fast count_exact all_fast all_exact
    python benchmarks/bench_interrupt.py 1 1000000 count_fast count_exact all_fast all_exact

The first argument is the device (``cpu`` or an index of `vkray.devices()`), the second the rays,
then the queries: count_fast, count_exact, all_fast, all_exact, contains (winding number),
transmit."""

import os
import signal
import sys
import threading
import time

import numpy as np

import vkray


def stacked_squares(k: int = 200):
    z = np.repeat(np.linspace(0.0, 1.0, k), 4)
    corners = np.tile([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], (k, 1))
    base = 4 * np.arange(k)[:, None]
    return np.column_stack([corners, z]), np.vstack([base + [0, 1, 2], base + [0, 2, 3]])


def main() -> None:
    which, n = sys.argv[1], int(sys.argv[2])
    dev = vkray.Device(which if which == "cpu" else int(which))
    v, f = stacked_squares()
    scene = dev.scene([dev.mesh(v, f)])
    rng = np.random.default_rng(0)
    origins = np.column_stack([rng.uniform(0.01, 0.99, (n, 2)), np.full(n, -1.0)])
    up = np.array([0.0, 0.0, 1.0])
    queries = {
        "count_fast": lambda: scene.count(origins, up, precision="fast"),
        "count_exact": lambda: scene.count(origins, up, precision="exact"),
        "all_fast": lambda: scene.intersect_all(origins, up, precision="fast"),
        "all_exact": lambda: scene.intersect_all(origins, up, precision="exact"),
        "contains": lambda: scene.contains(origins, method="winding"),
        "transmit": lambda: scene.transmittance(origins, up),
    }
    print(f"{dev.info.name}, {n:,} rays")
    for name in sys.argv[3:]:
        sent = [0.0]

        def fire() -> None:
            time.sleep(1.0)
            sent[0] = time.monotonic()
            os.kill(os.getpid(), signal.SIGINT)

        began = time.monotonic()
        thread = threading.Thread(target=fire)
        thread.start()
        try:
            queries[name]()
            thread.join()
            print(f"| {name} | finished in {time.monotonic() - began:.2f} s (before the signal) |", flush=True)
        except KeyboardInterrupt:
            print(f"| {name} | KeyboardInterrupt {time.monotonic() - sent[0]:.2f} s after SIGINT |", flush=True)
            thread.join()


if __name__ == "__main__":
    main()
