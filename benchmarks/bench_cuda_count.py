"""Counts of 1M and 8M random rays on the bunny: numpy in and out against torch CUDA in and
vkray.CudaArray out (fast tier), best of five after a warm-up second; and whether the two agree.
Issue 33's first figure (docs/benchmarks.md); needs torch with a CUDA GPU that is the vkray
device.

    python benchmarks/bench_cuda_count.py
"""
import sys
import time

import numpy as np
import torch

sys.path.insert(0, "tests")  # the oracle's rays
import oracle  # noqa: E402
import vkray  # noqa: E402

dev = vkray.Device()
v, f = oracle.load_mesh("stanford-bunny")
scene = dev.scene([dev.mesh(v, f)])
print("| rays | numpy in and out (M rays/s) | torch CUDA in, CudaArray out | equal |\n|---|---|---|---|")
for n in (1_000_000, 8_000_000):
    o, d = oracle.random_rays(v, n, seed=5)
    o, d = o.astype(np.float32), d.astype(np.float32)
    ot, dt = torch.from_numpy(o).cuda(), torch.from_numpy(d).cuda()
    began = time.perf_counter()
    while time.perf_counter() - began < 1.0:
        scene.count(o, d)

    def best(call):
        times = []
        for _ in range(5):
            torch.cuda.synchronize()
            t = time.perf_counter()
            call()
            torch.cuda.synchronize()
            times.append(time.perf_counter() - t)
        return min(times)

    numpy_s = best(lambda: scene.count(o, d))
    cuda_s = best(lambda: torch.from_dlpack(scene.count(ot, dt)))
    same = np.array_equal(torch.from_dlpack(scene.count(ot, dt)).cpu().numpy(), scene.count(o, d))
    print(f"| {n:,} | {n / numpy_s / 1e6:.0f} | {n / cuda_s / 1e6:.0f} | {same} |", flush=True)
