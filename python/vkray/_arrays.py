"""Turns what numpy users pass into the C-contiguous arrays of accepted dtypes the core reads.

Types and shapes are judged here (TypeError / ValueError naming the argument); values (finite
coordinates, index ranges, ray intervals) are judged by the core, which names the first bad row.
"""

from __future__ import annotations

from typing import Tuple

import numpy as np

_FLOATS = (np.float32, np.float64)
_INDEX_DTYPES = (np.int32, np.int64, np.uint32, np.uint16)


def _asarray(name: str, value: object) -> np.ndarray:
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged lists and the like
        raise TypeError(f"{name} must be array-like: {exc}") from None


def real_coordinates(name: str, value: object) -> np.ndarray:
    """float32 and float64 pass as they are; other real numbers become float64."""
    array = _asarray(name, value)
    if array.dtype.type in _FLOATS:
        return array
    if array.dtype.kind in "iuf":
        return array.astype(np.float64)
    raise TypeError(f"{name} must hold real numbers (float32 or float64), got dtype {array.dtype}")


def points(name: str, value: object) -> np.ndarray:
    """An (N, 3) C-contiguous float32/float64 array."""
    array = real_coordinates(name, value)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {array.shape}")
    return np.ascontiguousarray(array)


def faces(value: object) -> np.ndarray:
    """An (F, 3) C-contiguous index array; int32/int64/uint32/uint16 pass without widening."""
    array = _asarray("faces", value)
    if array.dtype.kind not in "iu":
        raise TypeError(f"faces must hold integers (int32, int64, uint32 or uint16), got dtype {array.dtype}")
    if array.dtype.type not in _INDEX_DTYPES:
        if array.dtype == np.uint64 and array.size and array.max() > np.iinfo(np.int64).max:
            bad = int(np.argmax(array.max(axis=-1) > np.iinfo(np.int64).max)) if array.ndim == 2 else 0
            raise ValueError(f"faces row {bad} holds an index too large for any vertex")
        array = array.astype(np.int64 if array.dtype.itemsize >= 4 else np.int32)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {array.shape}")
    return np.ascontiguousarray(array)


def transform(value: object) -> np.ndarray:
    """A 3×4 or 4×4 float64 matrix (row-major, acting on column vectors: ``M @ [x, y, z, 1]``)."""
    array = real_coordinates("transform", value)
    if array.shape not in ((3, 4), (4, 4)):
        raise ValueError(f"transform must have shape (3, 4) or (4, 4), got {array.shape}")
    return np.ascontiguousarray(array, dtype=np.float64)


def rays(
    origins: object, directions: object, tmin: object, tmax: object
) -> Tuple[Tuple[int, ...], np.ndarray, np.ndarray, object, object]:
    """Broadcasts origins and directions (``... + (3,)``) and tmin/tmax (scalars or arrays) to one
    batch shape ``S``, as numpy would; returns ``S``, flat (N, 3) arrays and float-or-(N,) bounds.
    A single origin or direction shared by every ray stays one (1, 3) row: the core reads it for
    each ray, so a camera's eye is never copied N times."""
    o = real_coordinates("origins", origins)
    d = real_coordinates("directions", directions)
    for name, array in (("origins", o), ("directions", d)):
        if array.ndim == 0 or array.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (..., 3), got {array.shape}")
    lo = real_coordinates("tmin", tmin)
    hi = real_coordinates("tmax", tmax)
    try:
        shape = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], lo.shape, hi.shape)
    except ValueError:
        raise ValueError(
            f"origins {o.shape}, directions {d.shape}, tmin {lo.shape} and tmax {hi.shape} "
            "do not broadcast to one batch of rays"
        ) from None
    n = int(np.prod(shape, dtype=np.int64))

    def flat(array: np.ndarray) -> np.ndarray:
        if n > 0 and array.size == 3:
            return np.ascontiguousarray(array.reshape(1, 3))
        return np.ascontiguousarray(np.broadcast_to(array, shape + (3,)).reshape(n, 3))

    o, d = flat(o), flat(d)
    bounds = [
        float(b) if b.ndim == 0 else np.ascontiguousarray(np.broadcast_to(b, shape).reshape(n), dtype=np.float64)
        for b in (lo, hi)
    ]
    return shape, o, d, bounds[0], bounds[1]


def masks(value: object, shape: Tuple[int, ...]) -> object:
    """An 8-bit ray mask as an int, or uint8 (N,) for per-ray masks broadcast to ``shape``."""
    array = np.asarray(value)
    if array.dtype.kind not in "iu":
        raise TypeError(f"mask must hold integers, got dtype {array.dtype}")
    if array.size and (array.min() < 0 or array.max() > 0xFF):
        raise ValueError("mask values must be in [0, 255] (8 bits)")
    if array.ndim == 0:
        return int(array)
    try:
        array = np.broadcast_to(array, shape)
    except ValueError:
        raise ValueError(f"mask of shape {array.shape} does not broadcast to the rays' shape {shape}") from None
    return np.ascontiguousarray(array.reshape(-1), dtype=np.uint8)
