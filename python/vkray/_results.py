"""What queries return: `Hits` (the closest hit of each ray), `AllHits` (every hit, in CSR form)
and `Closest` (the nearest surface point of each point), and the arrays they hold: each field's
dtype and width in each tier, fresh arrays to fill and a caller's ``out=`` arrays checked."""

from __future__ import annotations

from typing import Any, Callable, Dict, Iterable, Optional, Sequence, Tuple, cast

import numpy as np

from . import _core, _pictures
from ._options import CLOSEST_FIELDS, HIT_FIELDS, Precision

#: Values a ray of each hit field has, beyond one (`Hits`' arrays are (n,) or (n, width)).
HIT_WIDTHS = {"uv": 2, "normal": 3, "position": 3}


def hit_dtype(name: str, precision: Precision) -> np.dtype[Any]:
    """The dtype of a hit field's array in ``precision``'s hits."""
    floats = np.float32 if precision == "fast" else np.float64
    return np.dtype(np.float32 if name == "normal" else (floats if name in ("t", "uv", "position") else np.int32))


def field_type(name: str, precision: Precision) -> Tuple[np.dtype[Any], Tuple[int, ...]]:
    """The dtype and trailing shape of a hit or closest-point field in ``precision``'s answers
    (``distance`` is a closest point's ``t``)."""
    tail = (HIT_WIDTHS[name],) if name in HIT_WIDTHS else ()
    return hit_dtype("t" if name == "distance" else name, precision), tail


def new_hit_arrays(count: int, fields: Iterable[str], precision: Precision) -> Dict[str, np.ndarray]:
    """Empty arrays for ``count`` rays' hits of ``fields`` (as the core makes them), to be filled."""
    return {
        name: np.empty((count, HIT_WIDTHS[name]) if name in HIT_WIDTHS else (count,), hit_dtype(name, precision))
        for name in fields
    }


def out_arrays(
    out: Hits, shape: Tuple[int, ...], fields: Iterable[str], precision: Precision, inputs: Sequence[Any] = ()
) -> Dict[str, np.ndarray]:
    """The arrays of ``out`` a query writes, flattened to one row per ray (views: each is checked
    C-contiguous first), checked against the query's dtypes and for memory shared with each other
    or with the query's ``inputs`` (the core checks again where it writes them itself; a
    `DeviceGroup` copies its pieces' rows into them)."""
    if tuple(out.shape) != tuple(shape):
        raise ValueError(f"out has shape {tuple(out.shape)}, the rays {tuple(shape)}")
    if (out.precision == "fast") != (precision == "fast"):
        raise ValueError(f"out holds {out.precision!r} hits; precision={precision!r} writes other widths")
    n = int(np.prod(shape, dtype=np.int64))
    arrays: Dict[str, np.ndarray] = {}
    for name in fields:
        array = getattr(out, name)
        if not isinstance(array, np.ndarray):
            raise ValueError(f"out has no {name} array (its call did not ask for it)")
        if not array.flags.c_contiguous or not array.flags.writeable:
            raise ValueError(f"out's {name} must be a writeable, C-contiguous array")
        want = tuple(shape) + ((HIT_WIDTHS[name],) if name in HIT_WIDTHS else ())
        if array.shape != want:
            raise ValueError(f"out's {name} has shape {list(array.shape)}, the query writes {list(want)}")
        dtype = hit_dtype(name, precision)
        if array.dtype != dtype:
            raise ValueError(f"out's {name} must be {np.dtype(dtype).name}, got {array.dtype}")
        others = [a for a in inputs if isinstance(a, np.ndarray)] + list(arrays.values())
        if any(np.may_share_memory(array, other) for other in others):
            raise ValueError(f"out's {name} shares memory with the rays or another output")
        arrays[name] = array.reshape((n,) + array.shape[len(shape) :])
    return arrays


class _SurfaceFields:
    """What a query says of a point on the surface: its triangle (``prim_id``, ``instance_id``,
    ``custom_index``, ``geometry_id``), ``uv``, ``normal`` and ``position``; None where the query
    did not ask for them."""

    prim_id: Optional[np.ndarray]
    instance_id: Optional[np.ndarray]
    custom_index: Optional[np.ndarray]
    uv: Optional[np.ndarray]
    normal: Optional[np.ndarray]
    geometry_id: Optional[np.ndarray]
    position: Optional[np.ndarray]


class _HitFields(_SurfaceFields):
    """The hit fields `Hits` (one entry a ray) and `AllHits` (one entry a hit) hold: the surface's,
    and ``t``."""

    t: Optional[np.ndarray]


class Hits(_HitFields):
    """Per-ray results of `Scene.intersect`, shaped like the rays (``S``).

    t: ``S``, distance in units of the direction's length; ``inf`` on a miss.
    prim_id, instance_id, custom_index, geometry_id: int32 ``S``; -1 on a miss.
    uv: ``S + (2,)``, barycentric weights of the triangle's vertices 1 and 2 (Vulkan's and
    Embree's convention; vertex 0 weighs ``1 - u - v``); NaN on a miss.
    normal: float32 ``S + (3,)``, unit geometric normal in world space, right-handed in the
    triangle's winding (``cross(v1 - v0, v2 - v0)``, transformed); NaN on a miss.
    position: ``S + (3,)``, the world-space hit point, interpolated from the hit triangle's
    vertices in f64 (so it lies on the triangle to the precision of its own coordinates, however
    long the ray); NaN on a miss. Asked for with ``outputs=[..., "position"]``.
    t, uv and position are float32 in the ``"fast"`` tier and float64 in the others.
    precision: the tier that produced these hits. Fields not asked for are ``None``.
    """

    def __init__(self, shape: Tuple[int, ...], fields: Dict[str, np.ndarray], precision: Precision = "fast") -> None:
        self.shape = shape
        self.precision: Precision = precision
        for name in HIT_FIELDS:
            array = fields.get(name)
            if isinstance(array, np.ndarray):
                array = array.reshape(shape + array.shape[1:])
            setattr(self, name, array)

    @property
    def hit(self) -> np.ndarray:
        """bool ``S``: whether each ray hit anything (numpy; for hits on the GPU, compare
        ``prim_id >= 0`` in your array library)."""
        if self._on_cuda():
            raise TypeError("these hits are on the GPU: use e.g. torch.from_dlpack(hits.prim_id) >= 0")
        if self.prim_id is not None:
            hit: np.ndarray = self.prim_id >= 0
        elif self.t is not None:
            hit = np.isfinite(self.t)
        else:  # a query always returns prim_id or t
            raise AttributeError("these hits hold neither prim_id nor t")
        return hit

    def _on_cuda(self) -> bool:
        """Whether these hits are `vkray.CudaArray`s (rays from CUDA arrays)."""
        return any(isinstance(cast(Any, getattr(self, name)), _core.CudaArray) for name in ("prim_id", "t"))

    def __len__(self) -> int:
        if not self.shape:
            raise TypeError("len() of hits of a single ray (0-d)")
        return self.shape[0]

    def __repr__(self) -> str:
        fields = [name for name in HIT_FIELDS if getattr(self, name) is not None]
        if self._on_cuda():
            return f"<vkray.Hits shape={self.shape} on cuda precision={self.precision!r} fields={fields}>"
        hits = int(self.hit.sum())
        return f"<vkray.Hits shape={self.shape} hits={hits} precision={self.precision!r} fields={fields}>"

    def image(self, field: str = "t", *, background: Any = None) -> np.ndarray:
        """uint8 ``(H, W, 3)``: hits of a 2-D batch shape ``(H, W)`` as an RGB image, row 0 on top.

        field: ``"t"`` (default: depth through a viridis-like colormap, the nearest hit yellow,
        the farthest dark purple, scaled to this image's range of t), ``"normal"`` (``n / 2 + 0.5``
        as RGB), ``"uv"`` (the three barycentric weights as RGB), or an id field: ``"prim_id"``,
        ``"instance_id"``, ``"custom_index"``, ``"geometry_id"`` (a colour for each id).
        Misses get ``background`` (RGB, 0-255; default dark grey, (38, 38, 46)).
        ValueError for other batch shapes, and for a field these hits do not hold.
        """
        return _pictures.hits_image(self, field, background)

    def show(self, field: str = "t") -> None:
        """Displays `image` (``field``) in a notebook; RuntimeError where IPython is missing."""
        _pictures.show(self.image(field))

    def _repr_png_(self) -> Optional[bytes]:
        """Notebooks show 2-D hits as their depth image (`image`); None for other shapes."""
        return _pictures.hits_png(self)


class AllHits(_HitFields):
    """Every hit of every ray, from `Scene.intersect_all`, in CSR form.

    offsets: int64 ``(N + 1,)``: ray i's hits are entries ``offsets[i]:offsets[i + 1]`` (rays in
    the flattened order of the batch shape ``S``).
    counts: int64 ``S``: hits per ray. ray_index: int64 ``(H,)``: the ray of each hit. (numpy
    answers make both from the offsets at first use: a caller who reads neither does not pay.)
    t, prim_id, instance_id, custom_index, geometry_id, uv, normal, position: one entry per hit,
    as `Hits` has them per ray (float64 t, uv and position), for the fields asked; else None.
    Rays in CUDA memory give every array (counts too) as a `vkray.CudaArray` on their GPU.
    Each ray's hits are in increasing t; hits at the same t in increasing (instance_id,
    geometry_id, prim_id). ``hits[i]`` is ray i's hits as `Hits` of shape ``(count,)``.
    """

    def __init__(
        self,
        shape: Tuple[int, ...],
        arrays: Dict[str, np.ndarray],
        precision: Precision,
        counts: Optional[Callable[[], Any]] = None,
    ) -> None:
        """``counts``: makes the counts where ``arrays`` has none, at first use (CUDA answers:
        the host's counts copied to the GPU, 8 MB for a million rays, 0.66 ms over an H200's bus,
        which a caller who reads only the offsets or the hits does not pay for); without either,
        the offsets' differences, at first use (numpy answers: 8 MB a million rays too)."""
        self.shape = shape
        self.precision: Precision = precision
        self.offsets: np.ndarray = arrays["offsets"]
        self._ray_index: Optional[np.ndarray] = arrays.get("ray_index")  # CUDA answers' (on the GPU)
        counts_given = arrays.get("counts")  # CUDA answers' (on the GPU)
        if isinstance(counts_given, np.ndarray):
            counts_given = counts_given.reshape(shape)
        self._counts: Optional[np.ndarray] = counts_given
        self._make_counts = counts
        for name in HIT_FIELDS:
            setattr(self, name, arrays.get(name))

    @property
    def counts(self) -> np.ndarray:
        """int64 ``S``: hits per ray (where the answer came without them, made at first use)."""
        counts = self._counts
        if counts is None:
            # Made in a local and then kept: threads that read it at once each make the same.
            made = self._make_counts() if self._make_counts is not None else counts_of(self.offsets)
            counts = made.reshape(self.shape) if isinstance(made, np.ndarray) else made
            self._counts = counts
        return counts

    @property
    def ray_index(self) -> np.ndarray:
        """int64 ``(H,)``: the ray (flat index) of each hit (where the answer came without them,
        made from the offsets at first use)."""
        rays = self._ray_index
        if rays is None:
            rays = ray_index_of(self.offsets)
            self._ray_index = rays
        return rays

    def __getstate__(self) -> Dict[str, Any]:
        # The counts made now: the maker (a closure over the device) does not pickle. The ray
        # indices are not pickled where the offsets make them.
        state = dict(self.__dict__)
        state["_counts"], state["_make_counts"] = self.counts, None
        if isinstance(self.offsets, np.ndarray):
            state["_ray_index"] = None
        return state

    def __setstate__(self, state: Dict[str, Any]) -> None:
        if "counts" in state:  # pickled when counts was a plain attribute
            state["_counts"] = state.pop("counts")
        if "ray_index" in state:  # pickled when ray_index was a plain attribute
            state["_ray_index"] = state.pop("ray_index")
        state.setdefault("_make_counts", None)
        state.setdefault("_ray_index", None)
        self.__dict__.update(state)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, ray: int) -> Hits:
        if not isinstance(ray, (int, np.integer)) or isinstance(ray, bool):
            raise TypeError(f"AllHits is indexed by a ray's flat index, got {ray!r}")
        if isinstance(cast(Any, self.offsets), _core.CudaArray):
            raise TypeError("these hits are on the GPU: index their arrays in your array library (offsets, t, ...)")
        n = len(self)
        if not -n <= int(ray) < n:
            raise IndexError(f"ray {ray} of {n}")
        lo, hi = self.offsets[int(ray) % n], self.offsets[int(ray) % n + 1]
        fields = {name: getattr(self, name)[lo:hi] for name in HIT_FIELDS if getattr(self, name) is not None}
        return Hits((int(hi - lo),), fields, self.precision)

    def __repr__(self) -> str:
        hits = len(self._ray_index) if self._ray_index is not None else int(self.offsets[-1])
        return f"<vkray.AllHits rays={len(self)} hits={hits} precision={self.precision!r}>"


class Closest(_SurfaceFields):
    """The surface point nearest to each query point, from `Scene.closest_points`.

    Each field has the points' batch shape ``S`` (plus a last axis for position, uv and normal):
    ``distance`` (float64, inf where nothing lies within max_distance), ``position`` (float64, the
    nearest surface point, NaN on a miss), ``prim_id``, ``instance_id``, ``custom_index``,
    ``geometry_id`` (int32, -1 on a miss), ``uv`` (float64 barycentrics of vertices 1 and 2),
    ``normal`` (float32, the triangle's unit normal in the world). Fields not asked are None.
    Points in CUDA memory give each field as a `vkray.CudaArray` on their GPU.
    """

    distance: Optional[np.ndarray]

    def __init__(self, shape: Tuple[int, ...], arrays: Dict[str, np.ndarray], precision: Precision) -> None:
        self.shape = shape
        self.precision: Precision = precision
        for name in CLOSEST_FIELDS:
            array = arrays.get(name)
            if isinstance(array, np.ndarray):
                array = array.reshape(shape + array.shape[1:])
            setattr(self, name, array)

    @property
    def hit(self) -> np.ndarray:
        """bool ``S``: whether a surface lies within max_distance of the point (numpy; for points
        on the GPU, compare ``prim_id >= 0`` in your array library)."""
        assert self.distance is not None
        if isinstance(cast(Any, self.distance), _core.CudaArray):
            raise TypeError("these answers are on the GPU: use e.g. torch.from_dlpack(closest.prim_id) >= 0")
        found: np.ndarray = np.isfinite(self.distance)
        return found

    def __repr__(self) -> str:
        asked = [name for name in CLOSEST_FIELDS if getattr(self, name) is not None]
        if isinstance(cast(Any, self.distance), _core.CudaArray):
            return f"<vkray.Closest shape={self.shape} on cuda precision={self.precision!r} fields={asked}>"
        found = int(self.hit.sum())
        return f"<vkray.Closest shape={self.shape} found={found} precision={self.precision!r} fields={asked}>"


def ray_index_of(offsets: np.ndarray) -> np.ndarray:
    """int64: each hit's ray, from CSR ``offsets`` (the core's on all cores where they are int64
    as it makes them, else numpy's)."""
    if isinstance(offsets, np.ndarray) and offsets.dtype == np.int64 and offsets.ndim == 1 and len(offsets) > 0:
        return _core.ray_index_of_offsets(np.ascontiguousarray(offsets))
    offsets = np.asarray(offsets)
    return np.repeat(np.arange(len(offsets) - 1, dtype=np.int64), np.diff(offsets))


def counts_of(offsets: np.ndarray) -> np.ndarray:
    """int64: each ray's hits, the differences of CSR ``offsets`` (the core's on all cores where
    they are int64 as it makes them, else numpy's)."""
    if isinstance(offsets, np.ndarray) and offsets.dtype == np.int64 and offsets.ndim == 1 and len(offsets) > 0:
        return _core.counts_of_offsets(np.ascontiguousarray(offsets))
    return np.diff(offsets)
