"""Turns what numpy users pass into the C-contiguous arrays of accepted dtypes the core reads.

Types and shapes are judged here (TypeError / ValueError naming the argument); values (finite
coordinates, index ranges, ray intervals) are judged by the core, which names the first bad row.
Every array is handed on in native byte order (the core reads native numbers only).
"""

from __future__ import annotations

from typing import Any, Optional, Tuple, Union, cast

import numpy as np

_FLOATS: Tuple[type, ...] = (np.float32, np.float64)
_INDEX_DTYPES: Tuple[type, ...] = (np.int32, np.int64, np.uint32, np.uint16)

#: The largest value of the core's 64-bit unsigned counts (byte budgets, ray counts).
U64_MAX = (1 << 64) - 1


def _bound_text(value: int) -> str:
    return "2**64 - 1" if value == U64_MAX else str(value)


def integer(name: str, value: object, low: int, high: int, note: str = "") -> int:
    """A Python int in ``[low, high]`` from an int or numpy integer (bools refused): TypeError
    for other types, ValueError naming ``name`` and the range otherwise."""
    bounds = f"[{_bound_text(low)}, {_bound_text(high)}]{note}"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer in {bounds}, got {value!r}")
    if not low <= int(value) <= high:
        raise ValueError(f"{name} must be in {bounds}, got {int(value)}")
    return int(value)


def check_mesh_size(vertices: object, faces: object, max_triangles: int) -> None:
    """Refuses a mesh the device cannot hold or the host cannot copy, from the shapes alone:
    before anything is converted or copied (a ``np.broadcast_to`` view of billions of triangles
    takes no memory until it is copied)."""
    from . import _core

    f_shape, v_shape = (getattr(x, "shape", None) or np.shape(np.asarray(x, dtype=object)) for x in (faces, vertices))
    triangles = int(f_shape[0]) if len(f_shape) == 2 else 0
    if triangles > max_triangles:
        raise ValueError(f"faces has {triangles} triangles, more than the device's maxPrimitiveCount ({max_triangles})")
    # Contiguous native copies (8 bytes a number at most), the device's copy and the host's f64
    # copy of the vertices: a bound, not an estimate.
    needed = 3 * 8 * (int(np.prod(v_shape[:-1], dtype=np.int64)) if v_shape else 0) * 3 + 3 * 8 * triangles * 2
    available = _core.host_memory_available()
    if available is not None and needed > available:
        raise MemoryError(
            f"a mesh of {triangles} triangles needs about {needed / 1e9:.1f} GB of host memory to copy and "
            f"upload, more than the {available / 1e9:.1f} GB available"
        )


def _native(array: np.ndarray) -> np.ndarray:
    """The array in native byte order (big-endian input is converted, not refused)."""
    if not array.dtype.isnative:
        return array.astype(array.dtype.newbyteorder("="))
    return array


def _big_integers(array: np.ndarray) -> bool:
    """Whether an object array holds only integers (what numpy makes of ints beyond 64 bits)."""
    return (
        array.dtype == object
        and array.size > 0
        and all(isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_)) for x in array.flat)
    )


#: DLPack's device types (dlpack.h DLDeviceType), for naming where an array lives.
_DLPACK_DEVICES = {
    1: "cpu",
    2: "cuda",
    3: "cuda_host",
    4: "opencl",
    7: "vulkan",
    8: "metal",
    9: "vpi",
    10: "rocm",
    11: "rocm_host",
    12: "ext_dev",
    13: "cuda_managed",
    14: "oneapi",
    15: "webgpu",
    16: "hexagon",
}
_DLPACK_CPU = 1


def dlpack_device(value: object, name: str = "an array argument") -> Optional[Tuple[int, int]]:
    """(device type, index) of an object that speaks DLPack (``__dlpack__`` and
    ``__dlpack_device__``: torch, cupy, jax, numpy >= 1.22), or None. A ``__dlpack_device__``
    that raises or answers no pair of ints is a TypeError naming the argument (`name`)."""
    if isinstance(value, np.ndarray) or not hasattr(value, "__dlpack__"):
        return None
    device_of = getattr(value, "__dlpack_device__", None)
    if device_of is None:
        return None
    try:
        kind, index = device_of()
        return _dlpack_number(kind), _dlpack_number(index)
    except Exception as exc:  # the caller's object: any error is its
        raise TypeError(f"{name}: its __dlpack_device__() failed: {type(exc).__name__}: {exc}") from exc


def _dlpack_number(value: Any) -> int:
    """A device type or index as ``__dlpack_device__`` gives it: an int, or an enum whose
    ``value`` is one (Open3D's DLDeviceType, which ``int()`` refuses)."""
    return int(getattr(value, "value", value))


#: DLPack's device type of CUDA memory.
DLPACK_CUDA = 2


def on_cuda(*values: object, names: Tuple[str, ...] = ("origins", "directions")) -> bool:
    """Whether any of the rays' arrays lives in CUDA memory (the GPU-resident path); `names`:
    the arguments' names, for errors."""
    for k, value in enumerate(values):
        device = dlpack_device(value, names[k] if k < len(names) else "an array argument")
        if device is not None and device[0] == DLPACK_CUDA:
            return True
    return False


def cuda_to_numpy(core_device: Any, value: object, name: str) -> np.ndarray:
    """A CUDA array on ``core_device``'s GPU (a `_core.Device`) copied into a numpy array of its
    dtype and shape, read in stream order after its producer's writes (DLPack's contract)."""
    raw, dtype, shape, strides = core_device.cuda_read(value, name)
    flat = raw.view(np.dtype(dtype))
    compact = np.empty(0, dtype).reshape(tuple(shape)) if 0 in shape else None
    if compact is not None:
        return compact
    if tuple(strides) == _compact_strides(tuple(shape), flat.itemsize):
        return cast(np.ndarray, flat[: int(np.prod(shape, dtype=np.int64))].reshape(tuple(shape)))
    return np.lib.stride_tricks.as_strided(flat, tuple(shape), tuple(strides), writeable=False).copy()


def _compact_strides(shape: Tuple[int, ...], itemsize: int) -> Tuple[int, ...]:
    """numpy's byte strides of a C-contiguous array of ``shape`` (the core reports these for the
    arrays it copies compactly)."""
    strides = []
    step = itemsize
    for n in reversed(shape):
        strides.append(step)
        step *= n
    return tuple(reversed(strides))


def numpy_to_cuda(core_device: Any, array: np.ndarray) -> Any:
    """``array`` copied to ``core_device``'s GPU as a `vkray.CudaArray` of its dtype and shape
    (0-d included: ``ascontiguousarray`` alone would make it 1-d)."""
    flat = np.ascontiguousarray(array).reshape(-1)
    return core_device.cuda_write(flat.view(np.uint8), flat.dtype.name, list(np.shape(array)))


def _from_dlpack(name: str, value: object, device: Tuple[int, int]) -> np.ndarray:
    """A DLPack array in host memory as a numpy view of the same memory (no copy); arrays
    elsewhere are refused with an error naming their device."""
    kind, index = device
    if kind == _DLPACK_CPU:
        try:
            return np.from_dlpack(cast(Any, value))
        except (TypeError, ValueError, BufferError, RuntimeError) as exc:  # e.g. a dtype numpy lacks
            raise TypeError(f"{name}: numpy cannot read this DLPack array: {exc}") from None
    where = f"{_DLPACK_DEVICES.get(kind, f'DLPack device type {kind}')}:{index}"
    raise TypeError(
        f"{name} lives on {where} (DLPack device type {kind}), which vkray cannot read here: pass host arrays "
        f"(torch: .cpu(), cupy: .get(), jax: jax.device_get), or CUDA arrays on the GPU the vkray.Device is"
    )


def host_array(name: str, value: object) -> np.ndarray:
    device = dlpack_device(value, name)
    if device is not None:
        return _native(_from_dlpack(name, value, device))
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged lists and the like
        raise TypeError(f"{name} must be array-like: {exc}") from None
    return _native(array)


def real_coordinates(name: str, value: object) -> np.ndarray:
    """float32 and float64 pass as they are; other real numbers become float64."""
    array = host_array(name, value)
    if array.dtype.type in _FLOATS:
        return array
    if array.dtype.kind in "iuf":
        return array.astype(np.float64)
    if _big_integers(array):  # integers beyond 64 bits: still real numbers
        try:
            return np.array(array.tolist(), dtype=np.float64)
        except OverflowError:
            raise ValueError(f"{name} holds an integer too large for float64") from None
    raise TypeError(f"{name} must hold real numbers (float32 or float64), got dtype {array.dtype}")


def points(name: str, value: object) -> np.ndarray:
    """An (N, 3) C-contiguous float32/float64 array."""
    array = real_coordinates(name, value)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {array.shape}")
    return np.ascontiguousarray(array)


def faces(value: object) -> np.ndarray:
    """An (F, 3) C-contiguous index array; int32/int64/uint32/uint16 pass without widening."""
    array = host_array("faces", value)
    if _big_integers(array):  # Python ints as objects (numpy's way with ints beyond 64 bits)
        rows = array.reshape(-1, array.shape[-1] if array.ndim else 1).tolist()
        bad = next((i for i, row in enumerate(rows) if any(abs(int(x)) >= 1 << 63 for x in row)), None)
        if bad is not None:
            raise ValueError(f"faces row {bad if array.ndim == 2 else 0} holds an index too large for any vertex")
        array = array.astype(np.int64)
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


def transform(value: object, name: str = "transform") -> np.ndarray:
    """A 3×4 or 4×4 float64 matrix (row-major, acting on column vectors: ``M @ [x, y, z, 1]``)."""
    array = real_coordinates(name, value)
    if array.shape not in ((3, 4), (4, 4)):
        raise ValueError(f"{name} must have shape (3, 4) or (4, 4), got {array.shape}")
    return np.ascontiguousarray(array, dtype=np.float64)


def affine(matrix: np.ndarray, name: str) -> np.ndarray:
    """A transform as `transform` returns it, checked as the core checks instances' (finite, last
    row of a 4×4 [0, 0, 0, 1]) for transforms the Python layer applies itself."""
    if not np.isfinite(matrix).all():
        row, column = np.argwhere(~np.isfinite(matrix))[0]
        raise ValueError(f"{name}: transform[{row}, {column}] is not finite: {matrix[row, column]}")
    if matrix.shape == (4, 4) and matrix[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(
            f"{name}: transform's last row must be [0, 0, 0, 1] (an affine transform), got {matrix[3].tolist()}"
        )
    return matrix


def rays(
    origins: object, directions: object, tmin: object, tmax: object
) -> Tuple[Tuple[int, ...], np.ndarray, np.ndarray, Union[float, np.ndarray], Union[float, np.ndarray]]:
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
        if n > 0 and (array.size == 3 or _one_row(array)):
            return np.ascontiguousarray(array.reshape(-1, 3)[:1])
        return np.ascontiguousarray(np.broadcast_to(array, shape + (3,)).reshape(n, 3))

    def bound(array: np.ndarray) -> Union[float, np.ndarray]:
        if array.ndim == 0:
            return float(array)
        return np.ascontiguousarray(np.broadcast_to(array, shape).reshape(n), dtype=np.float64)

    origins_flat, directions_flat, lo_flat, hi_flat = flat(o), flat(d), bound(lo), bound(hi)
    # The core counts the rays as its longest input: where every input is one row, the
    # directions are written out to the batch's n (the origin stays one, the leanest layout).
    if n > 1 and len(origins_flat) == len(directions_flat) == 1 and not isinstance(lo_flat, np.ndarray):
        if not isinstance(hi_flat, np.ndarray):
            directions_flat = np.ascontiguousarray(np.broadcast_to(directions_flat, (n, 3)))
    return shape, origins_flat, directions_flat, lo_flat, hi_flat


def _one_row(array: np.ndarray) -> bool:
    """Whether every row of ``array`` (..., 3) is its first: a view that repeats one row with
    stride 0, as ``np.broadcast_to(eye, (n, 3))`` makes. Copying it would write n rows (a million
    rays' 12 MB, page faults and all, took 5–10 ms on an H200's host) for the core to find them one."""
    leading = zip(array.strides[:-1], array.shape[:-1])
    return array.ndim >= 2 and all(stride == 0 or length == 1 for stride, length in leading)


def masks(value: object, shape: Tuple[int, ...], name: str = "mask") -> Union[int, np.ndarray]:
    """An 8-bit ray mask as an int, or uint8 (N,) for per-ray masks broadcast to ``shape``."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        if not 0 <= int(value) <= 0xFF:  # checked before numpy, which holds ints past 64 bits as objects
            raise ValueError(f"{name} values must be in [0, 255] (8 bits), got {int(value)}")
        return int(value)
    array = host_array(name, value)
    if array.dtype.kind not in "iu" and not _big_integers(array):
        raise TypeError(f"{name} must hold integers in [0, 255] (8 bits), got dtype {array.dtype}")
    if array.size and (array.min() < 0 or array.max() > 0xFF):
        bad = array.min() if array.min() < 0 else array.max()
        raise ValueError(f"{name} values must be in [0, 255] (8 bits), got {bad}")
    if array.ndim == 0:
        return int(array)
    try:
        array = np.broadcast_to(array, shape)
    except ValueError:
        raise ValueError(f"{name} of shape {array.shape} does not broadcast to the rays' shape {shape}") from None
    return np.ascontiguousarray(array.reshape(-1), dtype=np.uint8)


def optional_masks(value: object, count: int) -> Optional[np.ndarray]:
    """`Scene.update`'s masks: None, or uint8 (count,) from ``count`` integers in [0, 255]."""
    if value is None:
        return None
    array = host_array("masks", value)
    if array.dtype.kind not in "iu" and not _big_integers(array):
        raise TypeError(f"masks must hold integers in [0, 255] (8 bits), got dtype {array.dtype}")
    if array.shape != (count,):
        raise ValueError(f"masks must have shape ({count},), one per instance, got {array.shape}")
    if array.size and (array.min() < 0 or array.max() > 0xFF):
        k = int(np.argmax((array < 0) | (array > 0xFF)))
        raise ValueError(f"masks[{k}] must be in [0, 255] (8 bits), got {array[k]}")
    return np.ascontiguousarray(array, dtype=np.uint8)
