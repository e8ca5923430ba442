import threading

import numpy as np
import pytest

import oracle
import vkray
from conftest import BACKENDS, VALIDATION
from test_precision import tiers


def test_devices_are_listed_best_first():
    infos = vkray.devices()
    assert infos, "the suite needs at least one usable device"
    assert [i.index for i in infos] == list(range(len(infos)))
    software = [i.is_software for i in infos]
    assert software == sorted(software), "GPUs must come before software devices"
    # The CPU engine is always there, after the GPUs and before software Vulkan devices.
    [cpu] = [i for i in infos if i.engine == "cpu"]
    assert cpu.device_type == "cpu" and not cpu.is_software and cpu.shader_float64
    assert all(i.device_type != "cpu" or i.engine == "cpu" or i.is_software for i in infos[: cpu.index])
    for info in infos:
        assert info.engine == "cpu" or info.ray_query or info.ray_tracing_pipeline


def test_the_default_device_is_a_gpu_else_the_cpu_engine_and_lavapipe_only_when_named():
    infos = vkray.devices()
    gpus = [i for i in infos if i.engine == "vulkan" and not i.is_software]
    expected = gpus[0] if gpus else [i for i in infos if i.engine == "cpu"][0]
    assert vkray.Device().name == expected.name
    software = [i for i in infos if i.is_software]
    if software:
        assert vkray.Device(software[0].index).info == software[0]
        assert vkray.Device("llvmpipe").is_software


def test_device_reports_backend_and_limits(device):
    if device.engine == "cpu":
        assert device.backend == "cpu" and not device.validation and device.cuda_device is None
        assert device.limits["max_primitive_count"] >= 1 << 31
        return
    assert device.backend in BACKENDS
    assert device.validation == VALIDATION
    limits = device.limits
    assert limits["min_acceleration_structure_scratch_offset_alignment"] >= 1
    assert limits["max_primitive_count"] >= 1 << 20
    assert all(c >= 1 for c in limits["max_compute_work_group_count"])
    if device.backend == "pipeline":
        assert limits["shader_group_handle_size"] >= 16
        assert limits["shader_group_base_alignment"] >= limits["shader_group_handle_alignment"]


def test_device_selection_by_index_and_name(monkeypatch):
    first = vkray.devices()[0]
    assert vkray.Device(0).name == first.name
    assert vkray.Device(first.name.split()[0].upper()).name == first.name
    monkeypatch.setenv("VKRAY_DEVICE", "0")
    assert vkray.Device().name == first.name
    with pytest.raises(vkray.NoDeviceError, match="no usable device matches"):
        vkray.Device("no such device anywhere")
    with pytest.raises(vkray.NoDeviceError):
        vkray.Device(len(vkray.devices()))


def test_backend_environment_override(monkeypatch):
    for backend in BACKENDS:
        monkeypatch.setenv("VKRAY_BACKEND", backend)
        assert vkray.Device().backend == backend
    monkeypatch.setenv("VKRAY_BACKEND", "cuda")
    with pytest.raises(ValueError, match="backend"):
        vkray.Device()


def test_bad_device_arguments():
    with pytest.raises(ValueError, match="backend"):
        vkray.Device(backend="optix")
    with pytest.raises(TypeError):
        vkray.Device(device=1.5)


def test_default_backend_follows_ray_query_feature():
    info = [d for d in vkray.devices() if d.engine == "vulkan"][0]
    expected = "ray_query" if info.ray_query else "pipeline"
    assert vkray.Device(info.index).backend == expected


def test_missing_driver_is_a_clear_no_device_error(tmp_path):
    import subprocess
    import sys

    # Without a Vulkan driver the CPU engine is the one device; asking for Vulkan says why not.
    script = (
        "import vkray\nprint([d.engine for d in vkray.devices()], vkray.Device().engine)\n"
        "try:\n    vkray.Device(backend='ray_query')\nexcept vkray.NoDeviceError as e:\n    print('NoDeviceError', e)\n"
    )
    env = dict(__import__("os").environ, VK_DRIVER_FILES=str(tmp_path / "none.json"))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env).stdout
    first, second = out.split("\n", 1)
    assert first == "['cpu'] cpu", out
    assert second.startswith("NoDeviceError") and "VK_DRIVER_FILES" in second


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_device_keeps_staging_for_as_many_queries_as_ran_at_once(backend):
    """Four threads query one device at once, five rounds: the staging the first round made is
    kept for the next rounds (a device that kept a fixed two queries' worth made more in every
    round past two threads: 7 → 45 ms a 4M-ray call on an H200). Answers equal one thread's;
    `release_idle_memory` frees what is kept, and the next query makes it again."""
    device = vkray.Device(backend=backend, validation=VALIDATION)  # counts of its own
    device.chunk_rays = 20_000
    v, f, _ = oracle.heightfield(64, seed=3)
    scene = device.scene(device.mesh(v, f))
    o, d = (a.astype(np.float32) for a in oracle.random_rays(v, 60_000, seed=4))
    want = scene.intersect(o, d, outputs=["t", "prim_id"])
    alone = device.idle_memory
    assert alone["made"] > 0 and alone["kept"] == alone["made"] and alone["bytes"] > 0

    barrier = threading.Barrier(4)

    def work(_k):
        answers = []
        for _ in range(5):
            barrier.wait()
            answers.append(scene.intersect(o, d, outputs=["t", "prim_id"]))
        return answers

    for answers in oracle.in_threads(4, work):
        for got in answers:
            np.testing.assert_array_equal(got.prim_id, want.prim_id)
            np.testing.assert_array_equal(got.t, want.t)
    after = device.idle_memory
    assert after["made"] <= 4 * alone["made"], (alone, after)
    assert after["kept"] == after["made"] and after["bytes"] >= alone["bytes"]

    device.release_idle_memory()
    assert device.idle_memory == {"bytes": 0, "kept": 0, "made": after["made"], "pinned_bytes": 0}
    scene.intersect(o, d, outputs=["t", "prim_id"])
    assert device.idle_memory == {**alone, "made": after["made"] + alone["made"]}


@pytest.mark.parametrize("backend", [*BACKENDS, "cpu"])
def test_all_hits_records_are_kept_for_the_next_query(backend):
    """The host's records of an all-hits answer are kept for the next query (their pages touched
    already) and counted in idle_memory, on both engines; four threads at once get answers equal
    to one thread's; release_idle_memory frees them."""
    if backend == "cpu":
        device = vkray.Device("cpu")
    else:
        device = vkray.Device(backend=backend, validation=VALIDATION)
    v, f = oracle.load_mesh("cow")
    scene = device.scene(device.mesh(v, f))
    o, d = oracle.random_rays(v, 20_000, seed=7)
    want = scene.intersect_all(o, d, outputs=["t", "prim_id"])
    records = 32 * len(want.t)
    before = device.idle_memory["bytes"]
    scene.intersect_all(o, d, outputs=["t", "prim_id"])
    assert device.idle_memory["bytes"] == before  # the same records, filled again

    def work(_k):
        return [scene.intersect_all(o, d, outputs=["t", "prim_id"]) for _ in range(3)]

    for answers in oracle.in_threads(4, work):
        for got in answers:
            for name in ("offsets", "t", "prim_id"):
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    device.release_idle_memory()
    assert device.idle_memory["bytes"] == 0
    scene.intersect_all(o, d, outputs=["t", "prim_id"])
    assert device.idle_memory["bytes"] >= records


@pytest.mark.parametrize("backend", BACKENDS)
def test_queries_of_two_kinds_in_turn_find_their_staging_kept(backend):
    """One thread, fast and exact queries in turn (their staging differs: f32 or f64 rays): after
    the first of each, neither allocates again, though one query at a time is the peak."""
    device = vkray.Device(backend=backend, validation=VALIDATION)
    if "exact" not in tiers(device):
        pytest.skip(f"{device.name} has no exact tier")
    v, f, _ = oracle.heightfield(16, seed=5)
    scene = device.scene(device.mesh(v, f))
    o, d = oracle.random_rays(v, 5_000, seed=6)
    made = []
    for _ in range(4):
        for precision in ("fast", "exact"):
            scene.intersect(o, d, outputs=["t"], precision=precision)
            made.append(device.idle_memory["made"])
    # The first exact query may also probe the driver (a query of its own) on a new device.
    assert made[1] > made[0] > 0
    assert made[2:] == [made[2]] * 6, made
