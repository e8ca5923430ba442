"""Origins for secondary rays (shadow, bounce) that cannot re-hit the surface they leave."""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from . import _arrays
from ._options import Precision, check_precision

# Wächter and Binder, "A Fast and Robust Method for Avoiding Self-Intersection" (Ray Tracing
# Gems, ch. 6), for float32; for float64 the same rule, its absolute step scaled by the 2^29
# finer ulp. Offsets grow with |p| (in ulps) so that they dominate the rounding error of a point
# interpolated from its triangle at any distance from the origin; near zero, where ulps vanish,
# a fixed step takes over.
_RULES = {
    np.dtype(np.float32): (np.int32, 256.0, 1.0 / 32.0, 2.0**-16),
    np.dtype(np.float64): (np.int64, 256.0, 1.0 / 32.0, 2.0**-45),
}
# Tiers whose traversal (which decides what a ray hits) runs in float32.
_F32_TRAVERSAL = ("fast", "refined")


def _offset(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """The rule of ``p``'s dtype (float32 or float64) applied to points ``p`` along ``n``."""
    int_type, int_scale, origin, float_scale = _RULES[p.dtype]
    steps = (int_scale * n).astype(int_type)
    as_int = np.ascontiguousarray(p).view(int_type)
    moved = (as_int + np.where(p < 0, -steps, steps)).view(p.dtype)
    return np.where(np.abs(p) < origin, p + (float_scale * n).astype(p.dtype), moved)


def _vectors(name: str, value: Any) -> np.ndarray:
    if value is None:
        raise TypeError(f"{name} must be an array of shape (..., 3), got None")
    array = _arrays.real_coordinates(name, value)
    if array.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3), got {array.shape}")
    return array


def offset_origins(
    points: Any, normals: Any, directions: Optional[Any] = None, *, precision: Precision = "fast"
) -> np.ndarray:
    """Moves surface points off their surface along the geometric normal, so that rays starting
    there do not hit the triangle they start on (robust offset of Wächter and Binder).

    points: ``(..., 3)`` hit points, float32 or float64 (other real dtypes become float64), e.g.
    ``Hits.position`` (whose error is relative to the triangle's coordinates, which this offset is
    designed for; ``o + t * d`` is not accurate enough far from the ray origin).
    normals: ``(..., 3)`` unit geometric normals, e.g. ``Hits.normal``.
    directions: where the new rays go. Given, each point moves to the side of its surface that
    its ray leaves towards (a shadow ray towards a light, a reflected or refracted ray); omitted,
    along the normal as given. Points, normals and directions broadcast together.
    precision: the tier the new rays will be traced in (as `Scene.intersect` takes it). What a
    ray hits is decided in float32 in ``"fast"`` and ``"refined"`` (the default ``"fast"``), so
    there the float32 rule applies, to the float32-rounded point, even to float64 points: the
    result is that float32 point, returned as float64 (an offset of about 256 float32 ulps of the
    coordinates, some 0.25 units at 1e4). In ``"exact"`` and ``"reference"`` float64 points get the
    float64 rule (an offset 2^29 times finer) and float32 points the float32 rule.

    Returns origins of the points' dtype, of the broadcast shape; trace from them with
    ``tmin=0``. Points or normals that are NaN (misses) give NaN origins. The step is a few hundred
    ulps of the point's coordinates, so with float32 points, or in the float32 tiers, it is large
    in absolute terms far from the origin (about 2 units at 1e5): there, trace secondary rays in
    an f64 tier from float64 positions, offset with that tier's ``precision``.
    """
    check_precision(precision)
    p = _vectors("points", points)
    n = _vectors("normals", normals).astype(np.float64)
    d = None if directions is None else _vectors("directions", directions).astype(np.float64)
    shapes = [p.shape, n.shape] + ([] if d is None else [d.shape])
    try:
        shape = np.broadcast_shapes(*shapes)
    except ValueError:
        names = "points, normals and directions" if d is not None else "points and normals"
        raise ValueError(f"{names} of shapes {', '.join(map(str, shapes))} do not broadcast together") from None
    if d is not None:
        n = np.where((np.sum(n * d, axis=-1) < 0)[..., None], -n, n)
    p = np.broadcast_to(p, shape)
    n = np.broadcast_to(n, shape)
    with np.errstate(invalid="ignore"):  # NaN rows (misses) are set to NaN below
        if precision in _F32_TRAVERSAL and p.dtype == np.float64:
            # Far enough for float32 traversal: the float32 rule's own point, exactly as float64.
            moved = _offset(p.astype(np.float32), n).astype(np.float64)
        else:
            moved = _offset(p, n)
    valid = np.isfinite(p).all(axis=-1) & np.isfinite(n).all(axis=-1)
    return np.where(valid[..., None], moved, np.nan).astype(p.dtype, copy=False)
