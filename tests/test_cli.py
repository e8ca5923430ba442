"""The command line: `python -m vkray info` (text, JSON, and with no driver) and `python -m vkray bench`.

Each command runs in a subprocess, under the Khronos validation layer where the suite runs under it
(VKRAY_VALIDATION=1: any message it reports makes the command fail)."""

import json
import os
import subprocess
import sys

import numpy as np

import vkray
from conftest import BACKENDS, VALIDATION
from vkray import _cli


def run_vkray(*args: str, **env: str) -> subprocess.CompletedProcess:
    environ = dict(os.environ, **env)
    if VALIDATION:
        environ["VKRAY_VALIDATION"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "vkray", *args], capture_output=True, text=True, env=environ, timeout=120
    )


def test_info_lists_the_device_its_backends_and_limits():
    result = run_vkray("info")
    assert result.returncode == 0, result.stderr
    info = [d for d in vkray.devices() if d.engine == "vulkan"][0]
    out = result.stdout
    assert f"Device {info.index}: {info.name}" in out
    cpu = [d for d in vkray.devices() if d.engine == "cpu"][0]
    assert f"Device {cpu.index}: {cpu.name}" in out and "backends:   cpu (default)" in out
    assert f"driver:     {info.driver}" in out
    assert "backends:   " + ", ".join(b + (" (default)" if b == BACKENDS[0] else "") for b in BACKENDS) in out
    assert "max_primitive_count" in out and "vertex_formats" in out
    assert "Vulkan loader: " in out and "Vulkan loader: not found" not in out
    if VALIDATION:
        assert "Khronos validation layer: installed" in out
    assert "Traceback" not in result.stderr


def test_info_json():
    result = run_vkray("info", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    info = [d for d in vkray.devices() if d.engine == "vulkan"][0]
    [device] = [d for d in report["devices"] if d["index"] == info.index]
    [cpu] = [d for d in report["devices"] if d["engine"] == "cpu"]
    assert cpu["backends"] == ["cpu"] and cpu["precisions"] == ["fast", "refined", "exact", "reference"]
    assert cpu["limits"]["max_primitive_count"] > 0 and cpu["name"].startswith("CPU (")
    assert device["name"] == info.name and device["driver"] == info.driver
    assert device["backends"] == BACKENDS and device["default_backend"] == BACKENDS[0]
    assert "backend_errors" not in device
    assert device["shader_float64"] == info.shader_float64
    assert ("exact" in device["precisions"]) == info.shader_float64
    assert device["limits"]["max_primitive_count"] > 0
    assert report["error"] is None and report["hints"] == [] and report["loader"]
    if VALIDATION:
        assert report["validation_layer"]["available"] is True


def test_info_without_a_driver_says_what_to_install(tmp_path):
    missing = str(tmp_path / "none.json")
    result = run_vkray("info", VK_DRIVER_FILES=missing, VK_ICD_FILENAMES=missing)
    # The CPU engine needs no Vulkan: info lists it, and says what to install for a GPU.
    assert result.returncode == 0, result.stdout + result.stderr
    assert "No usable Vulkan device" in result.stdout and "The CPU engine answers every query" in result.stdout
    assert "mesa-vulkan-drivers" in result.stdout and "bookworm-backports" in result.stdout
    assert "VK_DRIVER_FILES" in result.stdout and "nvidia_icd.json" in result.stdout
    assert f"VK_DRIVER_FILES={missing} is set ({missing} does not exist)" in result.stdout
    assert "Traceback" not in result.stderr

    result = run_vkray("info", "--json", VK_DRIVER_FILES=missing, VK_ICD_FILENAMES=missing)
    assert result.returncode == 0
    report = json.loads(result.stdout)
    assert [d["engine"] for d in report["devices"]] == ["cpu"] and report["error"].startswith("NoDeviceError")
    assert any("mesa-vulkan-drivers" in hint for hint in report["hints"])


def test_install_hint_for_a_missing_loader():
    hints = _cli._hints(None, "NoDeviceError: the Vulkan loader could not be loaded (...)")
    assert hints[0].startswith("Install the Vulkan loader") and "libvulkan1" in hints[0]
    assert not any(hint.startswith("Install the Vulkan loader") for hint in _cli._hints("libvulkan.so.1", "x"))


def test_bench_prints_rates():
    result = run_vkray("bench", "--seconds", "1")
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    assert "M rays/s" in out
    tiers = ["fast", "exact"] if vkray.devices()[0].shader_float64 else ["fast"]
    try:
        import embreex  # noqa: F401
    except ImportError:
        embree = False
        assert "Embree: skipped" in out
    else:
        embree = True
        assert "Embree M rays/s" in out
    for query in ("intersect", "occluded", "count"):
        for tier in tiers:
            [row] = [line.split() for line in out.splitlines() if line.split()[:2] == [query, tier]]
            assert float(row[3]) > 0
            if embree:  # Embree's rate, and the ratio
                assert float(row[4]) > 0 and row[5].endswith("x")


def test_bench_json_without_embree():
    result = run_vkray("bench", "--seconds", "0.5", "--no-embree", "--subdivisions", "2", "--json")
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads(result.stdout)
    assert report["triangles"] == 320 and report["embree"] is None and report["embree_skipped"] == "--no-embree"
    assert {row["query"] for row in report["rows"]} == {"intersect", "occluded", "count"}
    assert all(row["vkray_mrays_per_s"] > 0 and row["ratio"] is None for row in report["rows"])


def test_bench_mesh_is_closed_and_rays_cross_it_an_even_number_of_times(device):
    vertices, faces = _cli.icosphere(3)
    assert faces.shape == (20 * 4**3, 3) and vertices.shape == (len(faces) // 2 + 2, 3)
    radii = np.linalg.norm(vertices, axis=1)
    assert radii.min() >= 0.8 - 1e-12 and radii.max() <= 1.2 + 1e-12
    mesh = device.mesh(vertices, faces)
    assert mesh.is_closed
    scene = device.scene(mesh)
    o, d = _cli._Rays()(2000)
    precision = "exact" if device.info.shader_float64 else "reference"
    counts = scene.count(o, d, precision=precision)
    assert np.all(counts % 2 == 0) and counts.mean() > 0.5
