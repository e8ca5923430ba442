"""Independent references for the tests: OBJ loading, Embree (embreex) and plain numpy geometry."""

from __future__ import annotations

import os
import pathlib

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

# ../shared/meshes beside the checkout; VKRAY_MESHES points elsewhere (machines without it).
MESH_DIR = pathlib.Path(
    os.environ.get("VKRAY_MESHES") or pathlib.Path(__file__).resolve().parents[2] / "shared" / "meshes"
)
MESH_NAMES = ("stanford-bunny", "fandisk", "spot", "cow", "teapot")

EMBREE_MISS_T = 1e37


def load_obj(name: str):
    """(vertices float64 (V, 3), faces int64 (F, 3)) of a v/f-only OBJ in ../shared/meshes."""
    vertices, faces = [], []
    with open(MESH_DIR / f"{name}.obj") as f:
        for line in f:
            if line.startswith("v "):
                vertices.append(line.split()[1:4])
            elif line.startswith("f "):
                faces.append([c.split("/")[0] for c in line.split()[1:4]])
    return np.array(vertices, dtype=np.float64), np.array(faces, dtype=np.int64) - 1


def embree(triangle_sets, origins, directions, tmax=None, query="INTERSECT"):
    """Embree's answer for rays against meshes given as (vertices, faces) pairs (geomID = order)."""
    scene = rtcs.EmbreeScene()
    for vertices, faces in triangle_sets:
        TriangleMesh(scene, np.ascontiguousarray(vertices[faces], dtype=np.float32))
    o = np.ascontiguousarray(origins, dtype=np.float32)
    d = np.ascontiguousarray(directions, dtype=np.float32)
    dists = None if tmax is None else np.ascontiguousarray(tmax, dtype=np.float32)
    if query == "OCCLUDED":
        return scene.run(o, d, dists=dists, query="OCCLUDED") >= 0
    return scene.run(o, d, dists=dists, output=1)


def bounds(vertices):
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2


def camera_rays(vertices, width=256, height=256, direction=(0.3, -0.4, -1.0)):
    """A pinhole camera looking at the mesh's centre from 2.5 radii away: (origin (3,), dirs (H*W, 3))."""
    centre, radius = bounds(vertices)
    forward = np.asarray(direction, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    origin = centre - 2.5 * radius * forward
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    ys, xs = np.meshgrid(np.linspace(0.5, -0.5, height), np.linspace(-0.5, 0.5, width), indexing="ij")
    dirs = forward + xs[..., None] * right + ys[..., None] * up
    return origin, dirs.reshape(-1, 3)


def random_rays(vertices, n, seed=0):
    """Rays from a sphere around the mesh towards random points of its bounding box, plus a
    quarter in uniformly random directions (many of which miss)."""
    rng = np.random.default_rng(seed)
    centre, radius = bounds(vertices)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    u = rng.normal(size=(n, 3))
    origins = centre + 2.0 * radius * u / np.linalg.norm(u, axis=1, keepdims=True)
    targets = rng.uniform(lo, hi, size=(n, 3))
    directions = targets - origins
    wild = rng.random(n) < 0.25
    directions[wild] = rng.normal(size=(int(wild.sum()), 3))
    return origins, directions


def triangle_normals(vertices, faces, prim):
    tri = vertices[faces[prim]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def barycentric_points(vertices, faces, prim, uv):
    tri = vertices[faces[prim]]
    u, v = uv[:, :1].astype(np.float64), uv[:, 1:].astype(np.float64)
    return (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]


def transform_points(matrix, points):
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def heightfield(n: int, seed: int, offset: float = 0.0):
    """A random heightfield of (n-1)^2 quads, two triangles each, translated by `offset` along
    every axis (baked into the float64 vertices): (vertices, faces, color) where `color` gives
    every triangle one of 18 classes such that triangles sharing a vertex never share a class."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64), indexing="xy")
    z = rng.uniform(0.0, 0.5, (n, n))
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3) + offset
    at = lambda i, j: j * n + i  # noqa: E731
    faces, color = [], []
    for j in range(n - 1):
        for i in range(n - 1):
            faces += [[at(i, j), at(i + 1, j), at(i + 1, j + 1)], [at(i, j), at(i + 1, j + 1), at(i, j + 1)]]
            color += [((i % 3) * 3 + j % 3) * 2, ((i % 3) * 3 + j % 3) * 2 + 1]
    return vertices, np.array(faces, dtype=np.int64), np.array(color)


def shared_targets(vertices, faces, n: int):
    """Points of a heightfield that several triangles share: interior vertices and the midpoints
    of interior edges (axis-aligned and diagonal)."""
    grid = vertices.reshape(n, n, 3)
    inner = grid[1:-1, 1:-1].reshape(-1, 3)
    right = 0.5 * (grid[1:-1, 1:-2] + grid[1:-1, 2:-1])
    up = 0.5 * (grid[1:-2, 1:-1] + grid[2:-1, 1:-1])
    diagonal = 0.5 * (grid[1:-2, 1:-2] + grid[2:-1, 2:-1])
    return np.concatenate([inner, right.reshape(-1, 3), up.reshape(-1, 3), diagonal.reshape(-1, 3)])


def rays_through(targets, seed: int, distance: float = 5.0):
    """Rays from above (random tilts up to 45 degrees) that pass through `targets` at t = 1."""
    rng = np.random.default_rng(seed)
    tilt = rng.uniform(-1.0, 1.0, (len(targets), 2))
    away = np.column_stack([tilt, np.ones(len(targets))])
    away *= distance / np.linalg.norm(away, axis=1, keepdims=True)
    origins = targets + away
    return origins, targets - origins
