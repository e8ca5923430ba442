"""Copied as conftest.py next to Open3D's ray-casting tests by run.sh (named otherwise here, so
that this project's own pytest run does not load it): every ``o3d.t.geometry.RaycastingScene``
the tests make is vkray's (vkray.open3d.enable()), unless VKRAY_OPEN3D_SWAP=0 (Open3D's own
class, to see the tests pass there first)."""

import os

import vkray.open3d

if os.environ.get("VKRAY_OPEN3D_SWAP", "1") != "0":
    vkray.open3d.enable()


def pytest_report_header(config):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene
    return f"open3d {o3d.__version__}; RaycastingScene is {scene.__module__}.{scene.__qualname__}"
