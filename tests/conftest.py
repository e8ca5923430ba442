"""Every test runs under the Khronos validation layer where it is installed (CI requires it:
VKRAY_REQUIRE_VALIDATION=1); any message it reports raises vkray.ValidationError and fails the test.
Device-using tests run once per backend the device offers.

Tests that read meshes from ../shared/meshes (or the folder VKRAY_MESHES names) are skipped, with
the reason, where that folder does not exist, and fail instead where VKRAY_REQUIRE_MESHES=1 (CI)."""

import os
import pathlib
import sys
import warnings

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import oracle  # noqa: E402
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


REQUIRE_MESHES = os.environ.get("VKRAY_REQUIRE_MESHES") == "1"


def _skip_or_fail_for_missing_meshes(exc: FileNotFoundError) -> None:
    """Skips (or, with VKRAY_REQUIRE_MESHES=1, fails) a test whose error is a mesh read from a
    meshes folder that does not exist at all; returns for any other error. A folder that exists but
    lacks a mesh is a broken checkout: that error stands."""
    if oracle.MESH_DIR.is_dir() or exc.filename is None or pathlib.Path(exc.filename).parent != oracle.MESH_DIR:
        return
    where = f"{oracle.MESH_DIR} (../shared/meshes beside the checkout, or the folder VKRAY_MESHES names)"
    if REQUIRE_MESHES:
        pytest.fail(f"VKRAY_REQUIRE_MESHES=1 but the meshes folder {where} does not exist", pytrace=False)
    pytest.skip(f"needs the meshes folder {where}, which does not exist")


# Meshes are read inside tests and fixtures (oracle.load_obj): both phases are covered.
@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item):
    try:
        return (yield)
    except FileNotFoundError as exc:
        _skip_or_fail_for_missing_meshes(exc)
        raise


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item):
    try:
        return (yield)
    except FileNotFoundError as exc:
        _skip_or_fail_for_missing_meshes(exc)
        raise
