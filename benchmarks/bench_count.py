"""Counts of crossings and inside-or-outside, by the exact tier on the GPU against the reference
tier on all CPU cores, on the same rays and points (numpy in, numpy out; best of 3).

    python benchmarks/bench_count.py
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np
from _timing import best_run as best

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
import vkray  # noqa: E402
from oracle import load_mesh, random_rays  # noqa: E402


def main() -> None:
    device = vkray.Device()
    print(f"Device: {device.name} ({device.backend}); command: python benchmarks/bench_count.py\n")
    print("| mesh | query | count | exact (GPU) M/s | reference (CPU) M/s | same answers |")
    print("|---|---|---|---|---|---|")
    for name in ("stanford-bunny", "fandisk"):
        v, f = load_mesh(name)
        scene = device.scene(device.mesh(v, f))
        for n in (1_000_000, 4_000_000):
            o, d = random_rays(v, n, seed=5)
            scene.count(o[:10], d[:10], precision="exact")
            exact, counts = best(3, lambda: scene.count(o, d, precision="exact"))
            if n == 1_000_000:
                ref, want = best(3, lambda: scene.count(o, d, precision="reference"))
                cpu, same = f"{n / ref / 1e6:.2f}", str(np.array_equal(counts, want))
            else:
                cpu, same = "-", "-"
            print(f"| {name} | count | {n:,} | {n / exact / 1e6:.1f} | {cpu} | {same} |")
        if name == "fandisk":
            rng = np.random.default_rng(1)
            points = v.mean(axis=0) + rng.normal(size=(1_000_000, 3)) * np.ptp(v, axis=0).max() * 0.3
            exact, inside = best(2, lambda: scene.contains(points, precision="exact"))
            ref, want = best(2, lambda: scene.contains(points, precision="reference"))
            same = str(np.array_equal(inside, want))
            print(f"| {name} | contains | 1,000,000 | {1 / exact:.1f} | {1 / ref:.2f} | {same} |")


if __name__ == "__main__":
    main()
