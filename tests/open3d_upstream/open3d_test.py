"""A stand-in for Open3D's python/test/open3d_test.py (beside its tests in Open3D's sources, in
no package), enough for its ray-casting tests: ``list_devices``, the Open3D devices to run a test
on. Written here, not copied: the CPU, and the CUDA devices where asked for and present."""

import open3d as o3d


def list_devices(enable_cuda=True, enable_sycl=False, also_sycl_cpu=True):
    devices = [o3d.core.Device("CPU:0")]
    if enable_cuda and o3d.core.cuda.is_available():
        devices += [o3d.core.Device(f"CUDA:{k}") for k in range(o3d.core.cuda.device_count())]
    # SYCL: Open3D's wheels on PyPI are built without it; its tests then list the CPU alone.
    return devices
