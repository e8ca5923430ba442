"""A stand-in for trimesh's tests/generic.py (not in trimesh's sdist), enough for its ray tests:
`np`, `trimesh`, `log`, `time`, `random`, `data`, `get_mesh`. trimesh's model files are not in the
sdist either: the models its ray tests load are made here where a plain shape stands in for them
(a unit cube, a unit sphere), and tests that need any other model are skipped, by name."""

import logging
import time  # noqa: F401 - trimesh's tests call g.time

import numpy as np
import pytest
import trimesh

log = logging.getLogger("trimesh")
random = np.random.random


def _unit_cube(**kwargs):
    return trimesh.creation.box(extents=[1.0, 1.0, 1.0], **kwargs)


def _unit_sphere(**kwargs):
    return trimesh.creation.icosphere(subdivisions=2, **kwargs)


STAND_INS = {"unit_cube.STL": _unit_cube, "unit_sphere.STL": _unit_sphere}


def get_mesh(name, **kwargs):
    if name not in STAND_INS:
        pytest.skip(f"trimesh's model {name} is not in its sdist")
    mesh = STAND_INS[name](**kwargs)
    mesh.metadata["file_name"] = name
    return mesh


class _Data(dict):
    def __getitem__(self, key):
        pytest.skip(f"trimesh's test data {key!r} is not in its sdist")


data = _Data()
