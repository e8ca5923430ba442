import pytest

import vkray
from conftest import BACKENDS, VALIDATION


def test_devices_are_listed_best_first():
    infos = vkray.devices()
    assert infos, "the suite needs at least one usable device"
    assert [i.index for i in infos] == list(range(len(infos)))
    software = [i.is_software for i in infos]
    assert software == sorted(software), "GPUs must come before software devices"
    for info in infos:
        assert info.ray_query or info.ray_tracing_pipeline


def test_device_reports_backend_and_limits(device):
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
    info = vkray.devices()[0]
    expected = "ray_query" if info.ray_query else "pipeline"
    assert vkray.Device(0).backend == expected


def test_missing_driver_is_a_clear_no_device_error(tmp_path):
    import subprocess
    import sys

    script = (
        "import vkray\ntry:\n    vkray.devices()\nexcept vkray.NoDeviceError as e:\n    print('NoDeviceError', e)\n"
    )
    env = dict(__import__("os").environ, VK_DRIVER_FILES=str(tmp_path / "none.json"))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env).stdout
    assert out.startswith("NoDeviceError") and "VK_DRIVER_FILES" in out
