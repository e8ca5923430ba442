"""Every test runs under the Khronos validation layer where it is installed (CI requires it:
VKRAY_REQUIRE_VALIDATION=1); any message it reports raises vkray.ValidationError and fails the test.
Device-using tests run once per backend the device offers.

With VKRAY_STRICT_SKIPS=1 (scripts/test.sh sets it, so CI has it) a test that skips for want of
anything the project's own setup installs fails instead: only skips for hardware or GPU libraries
this machine lacks (CUDA, torch, cupy, a device feature or backend) stay skips. The meshes the tests
read ship with vkray (vkray.data): no test skips for want of them."""

import os
import pathlib
import sys
import warnings

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import vkray  # noqa: E402


def _validation_available() -> bool:
    try:
        vkray.Device(validation=True)
        return True
    except vkray.UnsupportedError:
        if os.environ.get("VKRAY_REQUIRE_VALIDATION") == "1":
            raise
        warnings.warn("the Khronos validation layer is not installed: tests run without it", stacklevel=2)
        return False


VALIDATION = _validation_available()
_INFO = [d for d in vkray.devices() if d.engine == "vulkan"][0]
BACKENDS = [name for name, ok in (("ray_query", _INFO.ray_query), ("pipeline", _INFO.ray_tracing_pipeline)) if ok]
# The Vulkan device's place in vkray.devices() (the CPU engine comes first where there is no GPU).
VULKAN_INDEX = _INFO.index
# The device fixture's engines: the Vulkan device's backends, then the CPU engine.
ENGINES = BACKENDS + ["cpu"]

_devices = {}


def make_device(backend: str) -> vkray.Device:
    """One device per backend for the whole session (pipelines stay compiled); "cpu": the CPU
    engine."""
    if backend not in _devices:
        if backend == "cpu":
            _devices[backend] = vkray.Device("cpu")
        else:
            _devices[backend] = vkray.Device(backend=backend, validation=VALIDATION)
    return _devices[backend]


@pytest.fixture(params=ENGINES)
def device(request) -> vkray.Device:
    return make_device(request.param)


@pytest.fixture
def any_device() -> vkray.Device:
    """For tests of host-side behaviour that does not depend on the backend."""
    return make_device(BACKENDS[0])


STRICT_SKIPS = os.environ.get("VKRAY_STRICT_SKIPS") == "1"

# What a skip may want under VKRAY_STRICT_SKIPS=1: what no setup script can give a machine. Every
# other reason (a missing package, data or tool) is the setup's to cure, and fails the test.
_HARDWARE_WORDS = ("CUDA", "GPU", "torch", "cupy", "jax", "device", "backend")


def strict_skip_failure(reason: str):
    """The failure message a skip with ``reason`` becomes under VKRAY_STRICT_SKIPS=1, or None
    where the skip stands (it wants hardware, or a GPU library, that setup does not install)."""
    if not STRICT_SKIPS or any(word in reason for word in _HARDWARE_WORDS):
        return None
    return f"skipped for want of something scripts/setup.sh installs (VKRAY_STRICT_SKIPS=1): {reason}"


def _fail_strict_skip(report) -> None:
    if report.skipped and isinstance(report.longrepr, tuple):
        message = strict_skip_failure(str(report.longrepr[2]))
        if message is not None:
            report.outcome = "failed"
            report.longrepr = message


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    report = yield
    if not hasattr(report, "wasxfail"):  # an xfail's outcome is its own verdict
        _fail_strict_skip(report)
    return report


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector):
    report = yield
    _fail_strict_skip(report)  # a whole module skipped (importorskip at its top)
    return report
