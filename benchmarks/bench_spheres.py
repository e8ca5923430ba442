"""Every query on a scene of 1000 spheres (radii 0.2-1 in a cube of side 20): 1M random rays,
200k random points, M per second, best of three after one warm-up call, on each device given
(``cpu`` or an index of `vkray.devices()`; default: every device). Spheres' f64 tiers, counts, all
hits, contains and distances run on the host on either engine (docs/benchmarks.md, issue 32).

    python benchmarks/bench_spheres.py cpu 1
"""

import sys
import time

import numpy as np

import vkray


def best(call, repeat: int = 3) -> float:
    call()
    times = []
    for _ in range(repeat):
        began = time.perf_counter()
        call()
        times.append(time.perf_counter() - began)
    return min(times)


def main() -> None:
    rng = np.random.default_rng(5)
    centers, radii = rng.uniform(-10, 10, (1000, 3)), rng.uniform(0.2, 1.0, 1000)
    n, m = 1_000_000, 200_000
    origins, directions = rng.uniform(-12, 12, (n, 3)), rng.normal(size=(n, 3))
    points = rng.uniform(-11, 11, (m, 3))
    which = sys.argv[1:] or ["cpu"] + [str(d.index) for d in vkray.devices() if d.engine == "vulkan"]
    print("| device | query | M/s |\n|---|---|---|")
    for name in which:
        dev = vkray.Device(name if name == "cpu" else int(name))
        scene = dev.scene(dev.spheres(centers, radii))
        rows = [
            ("intersect, fast", n, lambda: scene.intersect(origins, directions)),
            ("intersect, exact", n, lambda: scene.intersect(origins, directions, precision="exact")),
            ("count, fast", n, lambda: scene.count(origins, directions)),
            ("intersect_all, fast", n, lambda: scene.intersect_all(origins, directions)),
            ("contains", m, lambda: scene.contains(points)),
            ("distance", m, lambda: scene.distance(points)),
            ("signed_distance", m, lambda: scene.signed_distance(points)),
        ]
        for label, count, call in rows:
            print(f"| {dev.info.name} | {label} | {count / best(call) / 1e6:.2f} |", flush=True)


if __name__ == "__main__":
    main()
