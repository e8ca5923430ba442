"""Render a depth image of a mesh with vkray camera rays, and time the same rays through Embree.

    python examples/render_depth.py [MESH] [--size 512] [--out depth.png]

MESH is one of the meshes shipped with vkray (vkray.data.MESH_NAMES; default: stanford-bunny) or a
mesh file trimesh reads (OBJ, PLY, STL, ...). The picture goes to the current folder unless --out
names another path.
"""

from __future__ import annotations

import argparse
import pathlib
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402

import vkray  # noqa: E402


def read_mesh(name_or_path: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float64 (V, 3), faces int64 (F, 3)) of a shipped mesh's name or a mesh file."""
    if name_or_path in vkray.data.MESH_NAMES:
        return vkray.data.load_mesh(name_or_path)
    loaded = trimesh.load(name_or_path, process=False, force="mesh")
    return np.asarray(loaded.vertices, dtype=np.float64), np.asarray(loaded.faces, dtype=np.int64)


def camera(vertices: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """A pinhole camera 2.5 bounding radii from the mesh's centre, looking at it: (origin, dirs)."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo) / 2
    forward = np.array([0.0, -0.15, -1.0])
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    ys, xs = np.meshgrid(np.linspace(0.45, -0.45, size), np.linspace(-0.45, 0.45, size), indexing="ij")
    directions = forward + xs[..., None] * right + ys[..., None] * up
    return centre - 2.5 * radius * forward, directions


def embree_rays_per_second(vertices, faces, origin, directions) -> float:
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, vertices[faces].astype(np.float32))
    d = np.ascontiguousarray(directions.reshape(-1, 3), dtype=np.float32)
    o = np.ascontiguousarray(np.broadcast_to(origin, d.shape), dtype=np.float32)
    start = time.perf_counter()
    scene.run(o, d, output=1)
    return len(d) / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mesh", nargs="?", default="stanford-bunny", help="a shipped mesh's name or a mesh file (default: stanford-bunny)")
    parser.add_argument("--size", type=int, default=512, help="image width and height in pixels")
    parser.add_argument("--out", default="depth.png", help="where to write the PNG")
    args = parser.parse_args()

    vertices, faces = read_mesh(args.mesh)

    device = vkray.Device()
    start = time.perf_counter()
    mesh = device.mesh(vertices, faces)
    scene = device.scene(mesh)
    build_seconds = time.perf_counter() - start

    origin, directions = camera(vertices, args.size)
    scene.intersect(origin, directions[:1, :1], outputs=["t"])  # compile the query's pipeline once
    start = time.perf_counter()
    hits = scene.intersect(origin, directions)
    trace_seconds = time.perf_counter() - start
    rays = directions.shape[0] * directions.shape[1]

    depth = np.where(hits.hit, hits.t * np.linalg.norm(directions, axis=-1), np.nan)
    colours = matplotlib.colormaps["magma_r"].with_extremes(bad="white")
    plt.imsave(args.out, np.ma.masked_invalid(depth), cmap=colours, vmin=np.nanmin(depth), vmax=np.nanmax(depth))

    print(f"device      {device.name} ({device.info.device_type}, driver {device.info.driver})")
    print(f"backend     {device.backend}")
    print(f"mesh        {pathlib.Path(args.mesh).name.split('.')[0]}: {mesh.triangle_count} triangles")
    print(f"build       {build_seconds * 1e3:.1f} ms (BLAS + TLAS, upload included)")
    print(f"rays        {rays} camera rays, {int(hits.hit.sum())} hits")
    print(f"vkray       {rays / trace_seconds / 1e6:.2f} Mrays/s (numpy in, numpy out)")
    print(f"embreex     {embree_rays_per_second(vertices, faces, origin, directions) / 1e6:.2f} Mrays/s (same rays, one thread)")
    print(f"image       {args.out}")


if __name__ == "__main__":
    main()
