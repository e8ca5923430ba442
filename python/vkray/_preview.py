"""`vkray.preview`: a shaded picture of a scene, to look at it (a camera that frames the scene,
Lambert light, shadow rays from `offset_origins`)."""

from __future__ import annotations

from typing import Any, Tuple

import numpy as np

from . import _arrays
from ._pictures import BACKGROUND, Picture, corners, scene_balls
from ._queries import SceneLike
from ._secondary import offset_origins


def _unit(v: np.ndarray) -> np.ndarray:
    norm = float(np.linalg.norm(v))
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"a direction of zero or non-finite length: {v}")
    return np.asarray(v / norm, dtype=np.float64)


def _basis(forward: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(right, up) unit vectors of a camera looking along ``forward``, +y up (+z facing down)."""
    hint = np.array([0.0, 1.0, 0.0]) if abs(forward[1]) < 0.99 else np.array([0.0, 0.0, -1.0])
    right = _unit(np.cross(forward, hint))
    return right, np.cross(right, forward)


def _point(name: str, value: Any) -> np.ndarray:
    p = _arrays.real_coordinates(name, value).astype(np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"{name} must be 3 finite coordinates, got {value!r}")
    return p


# Instance tints where a scene has several instances (one colour for a scene of one).
_TINTS = np.array(
    [(0.90, 0.86, 0.80), (0.62, 0.78, 0.95), (0.95, 0.70, 0.60), (0.70, 0.90, 0.66), (0.88, 0.74, 0.95)],
    dtype=np.float64,
)


def preview(scene: SceneLike, *, width: int = 512, height: int = 512, eye: Any = None, target: Any = None) -> Picture:
    """A shaded picture of a scene, to look at it: a `Picture` (``np.asarray(picture)`` is uint8
    ``(height, width, 3)`` RGB; notebooks display it as a PNG).

    A pinhole camera at ``eye`` looks at ``target``; by default the target is the centre of the
    box around the scene's visible instances (mask != 0) in world space, and the eye is in front of
    it (+z, with +y up), a little to the right and above, just far enough for the scene to fill the
    picture (its vertices and spheres, or for very large scenes its meshes' boxes, seen in a field
    of view of 2 atan(0.4), about 44 degrees, across the shorter side). Given an ``eye``, the field of
    view is the narrowest that holds the scene (at most 120 degrees). Surfaces are
    Lambert-shaded from a directional light above left, shadows found with `Scene.occluded` from
    `offset_origins`, plus some light from the eye; instances get a tint each when there are
    several. Misses get a dark grey background. Deterministic: the same scene and arguments give
    the same pixels. Traces ``width * height`` primary rays and up to as many shadow rays, in the
    ``"fast"`` tier.
    """
    w = _arrays.integer("width", width, 1, 1 << 14)
    h = _arrays.integer("height", height, 1, 1 << 14)
    centres, radii = scene_balls(scene)
    if len(centres) == 0:
        centres, radii = corners(np.full(3, -1.0), np.full(3, 1.0)), np.zeros(8)
    low, high = (centres - radii[:, None]).min(axis=0), (centres + radii[:, None]).max(axis=0)
    size = max(float(np.linalg.norm(high - low)), 1e-12 * max(1.0, float(np.abs(low).max()), float(np.abs(high).max())))
    look_at = (low + high) / 2 if target is None else _point("target", target)
    short = min(w, h)
    aspect = np.array([w / short, h / short])  # the half-widths of the view, in its shorter side's
    margin = 1.05
    if eye is None:
        # In front (+z), a little to the right and above (+y up), the scene filling the view (the
        # shorter side's half-angle atan(0.4)): each ball within the view's four bounding planes,
        # |x| + r sqrt(1 + t^2) <= t z (t: the tangent of the half-angle on x's side).
        tan_short = 0.4
        forward = _unit(-np.array([0.35, 0.3, 1.0]))
        right, up = _basis(forward)
        rel = centres - look_at
        t = tan_short * aspect / margin
        across = np.abs(np.stack([rel @ right, rel @ up], axis=-1)) + radii[:, None] * np.sqrt(1 + t * t)
        distance = max(float(np.max((across / t).max(axis=1) - rel @ forward)), 1e-3 * size)
        camera = look_at - distance * forward
    else:
        camera = _point("eye", eye)
        if np.array_equal(camera, look_at):
            raise ValueError(f"eye and target are the same point, {camera.tolist()}: the camera looks nowhere")
        forward = _unit(look_at - camera)
        right, up = _basis(forward)
        rel = centres - camera
        z = rel @ forward
        # The half-angle each ball needs on each axis: its centre's angle plus its own.
        sideways = np.abs(np.stack([rel @ right, rel @ up], axis=-1))
        reach = np.hypot(sideways, z[:, None])
        with np.errstate(divide="ignore", invalid="ignore"):
            own = np.arcsin(np.clip(np.where(reach > 0, radii[:, None] / reach, 1.0), 0.0, 1.0))
        angle = np.arctan2(sideways, z[:, None]) + own
        widest = np.pi / 3
        need = float(np.max(np.tan(np.minimum(angle, widest)) / aspect)) * margin
        tan_short = min(max(need, 1e-6), float(np.tan(widest)))

    xs = ((np.arange(w) + 0.5) * 2 / w - 1) * tan_short * aspect[0]
    ys = (1 - (np.arange(h) + 0.5) * 2 / h) * tan_short * aspect[1]
    directions = forward + xs[None, :, None] * right + ys[:, None, None] * up
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    hits = scene.intersect(camera, directions, outputs=("t", "prim_id", "instance_id", "normal", "position"))
    assert hits.normal is not None and hits.position is not None and hits.instance_id is not None

    hit = hits.hit
    d = directions[hit]
    n = np.asarray(hits.normal[hit], dtype=np.float64)
    n = np.where((np.sum(n * d, axis=1) > 0)[:, None], -n, n)  # facing the camera
    light = _unit(-0.55 * right + 0.85 * up - 0.45 * forward)  # towards a light above left, behind the eye
    lambert = np.clip(n @ light, 0.0, 1.0)
    lit = lambert > 0
    visible = np.zeros(len(n), bool)
    if lit.any():
        origins = offset_origins(np.asarray(hits.position)[hit][lit], n[lit], light)
        visible[lit] = ~scene.occluded(origins, light)
    facing = np.abs(np.sum(n * d, axis=1))
    shade = 0.10 + 0.22 * facing + 0.68 * lambert * visible
    tints = _TINTS[np.asarray(hits.instance_id)[hit] % len(_TINTS)] if len(scene.instances) > 1 else _TINTS[:1]
    image = np.empty((h, w, 3), np.uint8)
    image[...] = np.array(BACKGROUND, np.uint8)
    image[hit] = np.rint(np.clip(tints * shade[:, None], 0.0, 1.0) * 255.0).astype(np.uint8)
    return Picture(image)
