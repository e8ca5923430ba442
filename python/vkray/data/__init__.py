"""Five small real meshes shipped with vkray, for its examples, notebook, benchmarks and tests.

``load_mesh(name)`` returns ``(vertices float64 (V, 3), faces int64 (F, 3))``, ready for
``Device.mesh``; ``mesh_path(name)`` is the file (an OBJ of ``v`` and triangular ``f`` lines only,
gzip-compressed: polygons were fan-triangulated and texture coordinates dropped).

========================  ========  =========  ======  ==================================================
name                      vertices  triangles  closed  origin
========================  ========  =========  ======  ==================================================
``"stanford-bunny"``      35,947    69,451     no      Stanford 3D Scanning Repository (holes at its base)
``"fandisk"``             6,475     12,946     yes     Hugues Hoppe: a CAD part with sharp creases
``"spot"``                2,930     5,856      yes     Keenan Crane, CC0 1.0
``"cow"``                 2,903     5,804      yes     Viewpoint Animation / Sun Microsystems
``"teapot"``              3,644     6,320      no      Martin Newell's Utah teapot
========================  ========  =========  ======  ==================================================

All five come from the public "common 3D test models" collection, which redistributes them for
research and testing; the Stanford bunny's terms ask that its source be credited (above). The
closed ones suit inside/outside and parity tests; fandisk's creases and the bunny's holes are hard
cases.
"""

from __future__ import annotations

import gzip
import pathlib
from typing import Tuple

import numpy as np

__all__ = ["MESH_NAMES", "load_mesh", "mesh_path"]

MESH_NAMES: Tuple[str, ...] = ("stanford-bunny", "fandisk", "spot", "cow", "teapot")

_FOLDER = pathlib.Path(__file__).resolve().parent


def mesh_path(name: str) -> pathlib.Path:
    """The gzip-compressed OBJ file of the shipped mesh ``name`` (one of ``MESH_NAMES``)."""
    if name not in MESH_NAMES:
        raise ValueError(f"no shipped mesh named {name!r}: the names are {', '.join(map(repr, MESH_NAMES))}")
    return _FOLDER / f"{name}.obj.gz"


def load_mesh(name: str) -> Tuple[np.ndarray, np.ndarray]:
    """``(vertices float64 (V, 3), faces int64 (F, 3))`` of the shipped mesh ``name``.

    Vertices are the OBJ's decimal values read as float64 (so float32 consumers round once);
    faces are 0-based."""
    with gzip.open(mesh_path(name), "rt", encoding="ascii") as f:
        lines = f.read().splitlines()
    vertex_words = [w for line in lines if line.startswith("v ") for w in line.split()[1:4]]
    # An "f" corner may read "v", "v/vt", "v//vn" or "v/vt/vn": the vertex index comes first.
    face_words = [w.split("/", 1)[0] for line in lines if line.startswith("f ") for w in line.split()[1:4]]
    vertices = np.array(vertex_words, dtype=np.float64).reshape(-1, 3)
    faces = np.array(face_words, dtype=np.int64).reshape(-1, 3) - 1
    return vertices, faces
