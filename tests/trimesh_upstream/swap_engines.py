"""Copied as conftest.py next to trimesh's ray tests by run.sh (named otherwise here, so that this
project's own pytest run does not load it). Runs trimesh's ray tests on vkray: both engines are replaced by
vkray.trimesh.RayMeshIntersector for every mesh the tests create (see run.sh)."""

import vkray.trimesh

vkray.trimesh.enable()
