"""Every test runs under the Khronos validation layer where it is installed (CI requires it:
VKRAY_REQUIRE_VALIDATION=1); any message it reports raises vkray.ValidationError and fails the test.
Device-using tests run once per backend the device offers."""

import os
import sys
import pathlib
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
        warnings.warn("the Khronos validation layer is not installed: tests run without it")
        return False


VALIDATION = _validation_available()
_INFO = vkray.devices()[0]
BACKENDS = [name for name, ok in (("ray_query", _INFO.ray_query), ("pipeline", _INFO.ray_tracing_pipeline)) if ok]

_devices = {}


def make_device(backend: str) -> vkray.Device:
    """One device per backend for the whole session (pipelines stay compiled)."""
    if backend not in _devices:
        _devices[backend] = vkray.Device(backend=backend, validation=VALIDATION)
    return _devices[backend]


@pytest.fixture(params=BACKENDS)
def device(request) -> vkray.Device:
    return make_device(request.param)


@pytest.fixture
def any_device() -> vkray.Device:
    """For tests of host-side behaviour that does not depend on the backend."""
    return make_device(BACKENDS[0])
