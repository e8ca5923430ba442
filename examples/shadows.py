"""Shadows: primary rays, then secondary rays that leave the surfaces they hit.

    python examples/shadows.py [--size 512] [--out shadows.png]

The Stanford bunny stands on a ground plane among a few procedural spheres, one scene of two
triangle meshes and a sphere set. Camera rays find the visible points; shadow rays go from each
point towards a light, starting from `vkray.offset_origins` so that no shadow ray hits the
surface it leaves (no "shadow acne", on the axis-aligned plane included); `Scene.occluded` stops
each at its first hit. The image is Lambert shading times visibility.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import vkray  # noqa: E402
from vkray.data import load_mesh  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--out", default="shadows.png")
    args = parser.parse_args()

    device = vkray.Device()
    v, f = load_mesh("stanford-bunny")
    low, high = v.min(axis=0), v.max(axis=0)
    size = np.linalg.norm(high - low)
    ground = np.array([[-1, low[1], -1], [1, low[1], -1], [1, low[1], 1], [-1, low[1], 1]], float) * [size, 1, size]
    ground[:, [0, 2]] += (low + high)[[0, 2]] / 2
    rng = np.random.default_rng(1)
    centers = np.column_stack(
        [rng.uniform(low[0] - 0.3 * size, high[0] + 0.3 * size, 6), np.full(6, low[1] + 0.04 * size),
         rng.uniform(low[2], high[2] + 0.4 * size, 6)]
    )
    scene = device.scene([device.mesh(v, f), device.mesh(ground, [[0, 2, 1], [0, 3, 2]]),
                          device.spheres(centers, 0.04 * size)])

    # A camera in front of the bunny, slightly above.
    n = args.size
    eye = (low + high) / 2 + np.array([0.2, 0.35, 1.3]) * size
    target = (low + high) / 2
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0, 1, 0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    s = np.linspace(-0.45, 0.45, n)
    directions = forward + s[None, :, None] * right + -s[:, None, None] * up
    hits = scene.intersect(eye, directions, outputs=["t", "prim_id", "normal", "position"])

    light = target + np.array([-0.8, 1.5, 0.9]) * size
    to_light = light - hits.position[hits.hit]
    normals = hits.normal[hits.hit]
    # Face the normal towards the camera: the bunny's back faces count as its front here.
    normals = np.where(np.sum(normals * directions[hits.hit], axis=1, keepdims=True) > 0, -normals, normals)
    origins = vkray.offset_origins(hits.position[hits.hit], normals, to_light)
    shadowed = scene.occluded(origins, to_light, tmax=1.0)
    lambert = np.clip(np.sum(normals * to_light, axis=1) / np.linalg.norm(to_light, axis=1), 0, 1)

    image = np.full(hits.shape, 0.08)
    image[hits.hit] = 0.15 + 0.85 * lambert * ~shadowed
    plt.imsave(args.out, image, cmap="gray", vmin=0, vmax=1)
    print(f"{hits.hit.sum():,} visible points, {shadowed.mean():.1%} in shadow -> {args.out}")


if __name__ == "__main__":
    main()
