"""Origins for secondary rays (shadow, bounce) that cannot re-hit the surface they leave."""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

# Wächter and Binder, "A Fast and Robust Method for Avoiding Self-Intersection" (Ray Tracing
# Gems, ch. 6), for float32; for float64 the same rule, its absolute step scaled by the 2^29
# finer ulp. Offsets grow with |p| (in ulps) so that they dominate the rounding error of a point
# interpolated from its triangle at any distance from the origin; near zero, where ulps vanish,
# a fixed step takes over.
_RULES = {
    np.dtype(np.float32): (np.int32, 256.0, 1.0 / 32.0, 2.0**-16),
    np.dtype(np.float64): (np.int64, 256.0, 1.0 / 32.0, 2.0**-45),
}


def offset_origins(points: Any, normals: Any, directions: Optional[Any] = None) -> np.ndarray:
    """Moves surface points off their surface along the geometric normal, so that rays starting
    there do not hit the triangle they start on (robust offset of Wächter and Binder).

    points: ``(..., 3)`` hit points, float32 or float64, e.g. ``Hits.position`` (whose error is
    relative to the triangle's coordinates, which this offset is designed for; ``o + t * d`` is
    not accurate enough far from the ray origin).
    normals: ``(..., 3)`` unit geometric normals, e.g. ``Hits.normal``.
    directions: where the new rays go. Given, each point moves to the side of its surface that
    its ray leaves towards (a shadow ray towards a light, a reflected or refracted ray); omitted,
    along the normal as given.

    Returns origins of the points' dtype; trace from them with ``tmin=0``. The step is a few
    hundred ulps of the point's coordinates, so with float32 points far from the origin it is
    large in absolute terms (about 2 units at 1e5): use an f64 tier's float64 positions there.
    """
    p = np.asarray(points)
    if p.dtype not in _RULES:
        p = p.astype(np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"points must have shape (..., 3), got {p.shape}")
    int_type, int_scale, origin, float_scale = _RULES[p.dtype]
    n = np.asarray(normals, dtype=np.float64)
    if directions is not None:
        d = np.asarray(directions, dtype=np.float64)
        n = np.where((np.sum(n * d, axis=-1) < 0)[..., None], -n, n)
    n = np.broadcast_to(n, p.shape)
    steps = (int_scale * n).astype(int_type)
    as_int = np.ascontiguousarray(p).view(int_type)
    moved = (as_int + np.where(p < 0, -steps, steps)).view(p.dtype)
    return np.where(np.abs(p) < origin, p + (float_scale * n).astype(p.dtype), moved)
