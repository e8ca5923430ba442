"""A slice of a mesh's signed distance field: `Scene.signed_distance` on a grid of points in the
plane z = const through the middle of the bounding box, drawn with a diverging colormap (negative,
inside: blue; positive, outside: red) and the zero level set (the surface's cut) in black.

    python examples/sdf_slice.py [--mesh MESH] [--size 512] [--z Z] [--out sdf_slice.png]

MESH: a mesh shipped with vkray (vkray.data.MESH_NAMES; default: fandisk) or an OBJ file. The
picture goes to the current folder unless --out names another path (docs/sdf_slice.png is made
with `--out docs/sdf_slice.png`).

precision "exact" (the GPU, f64) where the device has shaderFloat64, else "reference" (the CPU).
The sign comes from `Scene.contains`: parity for a closed mesh, the winding number for an open one.
"""

from __future__ import annotations

import argparse
import pathlib
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import vkray  # noqa: E402


def read_mesh(name_or_path: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float64 (V, 3), faces int64 (F, 3)) of a shipped mesh's name, or of an OBJ file's
    v and f lines (polygons fanned)."""
    if name_or_path in vkray.data.MESH_NAMES:
        return vkray.data.load_mesh(name_or_path)
    path = pathlib.Path(name_or_path)
    vertices, faces = [], []
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                vertices.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                ids = [int(c.split("/")[0]) for c in line.split()[1:]]
                ids = [i - 1 if i > 0 else len(vertices) + i for i in ids]
                faces += [[ids[0], ids[k], ids[k + 1]] for k in range(1, len(ids) - 1)]
    return np.array(vertices, dtype=np.float64), np.array(faces, dtype=np.int64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mesh", default="fandisk", help="a shipped mesh's name or an OBJ file (default: fandisk)")
    parser.add_argument("--size", type=int, default=512, help="samples along the slice's longer side")
    parser.add_argument("--z", type=float, default=None, help="the slice's plane (default: the box's middle)")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("sdf_slice.png"))
    args = parser.parse_args()

    vertices, faces = read_mesh(args.mesh)
    label = pathlib.Path(args.mesh).name.split(".")[0]
    device = vkray.Device()
    mesh = device.mesh(vertices, faces)
    scene = device.scene(mesh)
    precision = "exact" if device.info.shader_float64 else "reference"

    # The bounding box grown by 10% about its centre, square samples, the longer side --size.
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * 1.1
    z = centre[2] if args.z is None else args.z
    step = 2 * half[:2].max() / (args.size - 1)
    nx, ny = (int(round(2 * h / step)) + 1 for h in half[:2])
    xs = centre[0] + (np.arange(nx) - (nx - 1) / 2) * step
    ys = centre[1] + (np.arange(ny) - (ny - 1) / 2) * step
    gx, gy = np.meshgrid(xs, ys)  # (ny, nx): rows are y
    points = np.stack([gx, gy, np.full_like(gx, z)], axis=-1)

    start = time.perf_counter()
    sdf = scene.signed_distance(points, precision=precision)
    seconds = time.perf_counter() - start
    sign = "parity" if mesh.is_closed else "winding number"
    print(
        f"{label}: {len(faces):,} triangles, closed={mesh.is_closed}; {points.shape[1]}x{points.shape[0]} "
        f"points at z={z:.4g}: {seconds:.3f} s on {device.name} ({device.backend}), precision={precision!r}, "
        f"sign by {sign}; {int((sdf < 0).sum()):,} inside"
    )

    # Each side of zero spans its own range, so the inside is as deep a blue as the outside is red.
    low, high = min(float(sdf.min()), -1e-12), max(float(sdf.max()), 1e-12)
    norm = matplotlib.colors.TwoSlopeNorm(vmin=low, vcenter=0.0, vmax=high)
    fig, ax = plt.subplots(figsize=(6.4, 5.4 * ny / nx + 0.6), dpi=100)
    extent = (xs[0] - step / 2, xs[-1] + step / 2, ys[0] - step / 2, ys[-1] + step / 2)
    image = ax.imshow(sdf, origin="lower", extent=extent, cmap="RdBu_r", norm=norm)
    spacing = (high - low) / 24  # iso-lines of equal distance on both sides
    levels = np.concatenate([-np.arange(1, -low / spacing) * spacing, np.arange(1, high / spacing) * spacing])
    ax.contour(xs, ys, sdf, levels=np.sort(levels), colors="k", linewidths=0.3, alpha=0.35)
    ax.contour(xs, ys, sdf, levels=[0.0], colors="k", linewidths=1.2)
    fig.colorbar(image, ax=ax, shrink=0.8, label="signed distance (negative inside)")
    ax.set_title(f"{label}: signed distance at z = {z:.3g} ({precision}, sign by {sign})", fontsize=10)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_aspect("equal")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, bbox_inches="tight", pad_inches=0.1)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
