"""The query surface, defined once: every query's parameters, their defaults, checks and docs.

`SceneLike` holds the public query methods (`intersect`, `occluded`, `transmittance`,
`intersect_all`, `count`, `closest_points`, `distance`, `signed_distance`, `contains`). Each checks
what it can without the rays' device and hands one record, a `RayQuery` or a `PointQuery`, to
`SceneLike.answer`, which each kind of scene implements: `Scene` (one device) runs it, `GroupScene`
splits it over devices and hands each device's `Scene` a record of its piece, and `vkray.dask`
sends a record of each chunk to a worker's scene. A keyword added to every query is added here
(the signature and the record), and read where a scene answers it.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, Iterable, Optional, Tuple, Union, cast

import numpy as np

from . import _arrays
from ._options import (
    Cull,
    Precision,
    check_closest_outputs,
    check_method,
    check_outputs,
    check_precision,
)
from ._results import AllHits, Closest, Hits

__all__ = ["PointQuery", "RayQuery", "SceneLike"]

#: The fields of all hits the GPU writes for CUDA rays (the others are the host's).
_GPU_HIT_COLUMNS = frozenset(("t", "uv", "prim_id", "instance_id", "geometry_id"))


@dataclasses.dataclass(frozen=True)
class RayQuery:
    """One query of rays, as a scene's `SceneLike.answer` takes it: ``kind`` is the method's name
    (``"intersect"``, ``"occluded"``, ``"transmittance"``, ``"intersect_all"``, ``"count"``); the
    rays and options as that method documents them, its options checked (``outputs`` resolved to
    the fields computed). `with_rays` makes the record of a part of the rays."""

    kind: str
    origins: Any
    directions: Any
    tmin: Any = 0.0
    tmax: Any = np.inf
    mask: Any = 0xFF
    precision: Precision = "fast"
    cull: Cull = None
    progress: bool = False
    opacity_threshold: float = 0.5
    outputs: Tuple[str, ...] = ()
    max_hits: Optional[int] = None
    out: Optional[Hits] = None
    cuda: bool = False

    @property
    def stays_on_gpu(self) -> bool:
        """Whether CUDA rays of this query are traced without leaving the GPU (the GPU-resident
        path: copied device to device, packed and traced there): `intersect`, `occluded`, `count`,
        `transmittance` and `intersect_all` in the fast and exact tiers, of one mask for every
        ray, without ``position`` (computed on the host), ``out=`` or a progress bar; all hits
        only of fields the GPU writes (t, uv, prim_id, instance_id, geometry_id). Not counts,
        transmittance or all hits of a scene with spheres, nor the exact tier's all hits of
        multi-part meshes (`Scene._stays_on_gpu`). Other queries of CUDA arrays go through the
        host."""
        one_mask = np.ndim(self.mask) == 0 and _arrays.dlpack_device(self.mask, "mask") is None
        columns = self.kind != "intersect_all" or set(self.outputs) <= _GPU_HIT_COLUMNS
        return (
            self.kind in ("intersect", "occluded", "count", "transmittance", "intersect_all")
            and self.precision in ("fast", "exact")
            and "position" not in self.outputs
            and columns
            and self.out is None
            and not self.progress
            and one_mask
        )

    def with_rays(self, origins: Any, directions: Any, tmin: Any, tmax: Any, mask: Any, **changes: Any) -> RayQuery:
        """The same query of other rays (a piece of these, a chunk), with ``changes`` to its options."""
        return dataclasses.replace(
            self, origins=origins, directions=directions, tmin=tmin, tmax=tmax, mask=mask, **changes
        )


@dataclasses.dataclass(frozen=True)
class PointQuery:
    """One query of points, as `SceneLike.answer` takes it: ``kind`` is the method's name
    (``"closest_points"``, ``"distance"``, ``"signed_distance"``, ``"contains"``), its options
    checked as that method documents them (``outputs`` resolved; ``method`` None for
    `signed_distance`'s choice by closedness). `with_points` makes the record of a part of them."""

    kind: str
    points: Any
    precision: Precision = "reference"
    progress: bool = False
    max_distance: float = np.inf
    outputs: Tuple[str, ...] = ()
    method: Optional[str] = None

    def with_points(self, points: Any, **changes: Any) -> PointQuery:
        """The same query of other points (a piece of these, a chunk), with ``changes``."""
        return dataclasses.replace(self, points=points, **changes)


Query = Union[RayQuery, PointQuery]


class SceneLike(abc.ABC):
    """The queries that `Scene` (one device) and `GroupScene` (several) both answer, with the same
    arguments and the same results: code written against it runs on either. A subclass answers
    `RayQuery` and `PointQuery` records (`answer`) and refits (`update`).

    Every query takes CUDA arrays (torch, cupy, jax: DLPack on the device's GPU) for its rays or
    points, in every tier, and answers with `vkray.CudaArray`s on that GPU (in `Hits`, `AllHits`
    and `Closest` each field is one), read in the caller's stream order. `intersect`, `occluded`,
    `count`, `transmittance` and `intersect_all` (of the fields the GPU writes) in the fast and
    exact tiers, of one mask, never leave the GPU (`RayQuery.stays_on_gpu`; all hits a ray of
    which the GPU cannot settle, more than 32, go through the host); the other queries and tiers copy
    the arrays to the host and the answers back (one copy each way over the bus, 1-2 ms for 1M
    float32 rays on an H200: docs/benchmarks.md)."""

    #: The scene's instances, in the order of their ``instance_id``.
    instances: Tuple[Any, ...]

    @abc.abstractmethod
    def answer(self, query: Query) -> Any:
        """The answer to one query record: what each query method returns. The one documented
        internal entry (vkray.trimesh, vkray.dask and `GroupScene` hand records of their own)."""

    @abc.abstractmethod
    def update(self, transforms: Any = None, masks: Any = None) -> None:
        """Refits the scene's instances (`Scene.update`)."""

    def intersect(
        self,
        origins: Any,
        directions: Any = None,
        *,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        outputs: Optional[Iterable[str]] = None,
        precision: Precision = "fast",
        cull: Cull = None,
        mask: Any = 0xFF,
        progress: bool = False,
        cuda: bool = False,
        opacity_threshold: float = 0.5,
        out: Optional[Hits] = None,
    ) -> Hits:
        """The closest hit of each ray within [tmin, tmax].

        origins, directions: arrays of shape ``S + (3,)`` that broadcast together (one origin for
        many directions is fine); float32 or float64. Directions need not be unit length: ``t`` is
        measured in units of the direction's length. Or a sensor (`vkray.PinholeCamera`,
        `vkray.OrthographicCamera`, `vkray.Lidar`) alone: the GPU generates its rays (nothing is
        uploaded; ``sensor.rays()`` are the same rays as arrays), ``S`` is ``sensor.shape`` and the
        sensor's range is the interval (tmin and tmax are not given). A lidar with ``echoes=k > 1``
        gives its first k returns along each beam: fields of shape ``S + (k,)``, misses after the
        last return.
        tmin, tmax: scalars or arrays of shape ``S``; ``0 <= tmin <= tmax``. Hits exactly at the
        bounds follow Vulkan's rules (the interval is closed up to f32 rounding of traversal).
        outputs: which `Hits` fields to compute (default: all but ``geometry_id``). Unasked fields
        are never written by the GPU and come back as ``None`` (``prim_id`` is added when neither
        it nor ``t`` is asked, so that ``Hits.hit`` works).
        precision: which tier answers (docs/accuracy.md has what each costs and gains):

        - ``"fast"``: f32 hits straight from hardware traversal. Meshes and scenes are re-centred
          in f64 before anything becomes f32, so far from the origin they keep the precision of
          their own size, but a ray through a shared edge may still miss or hit twice.
        - ``"refined"``: the same traversal; each hit is then re-intersected with its triangle in
          f64 on the host, so ``t``, ``uv`` and ``position`` are float64 to ~1e-15 of the scene.
          Which triangle is hit is still f32's decision.
        - ``"exact"``: f64 watertight test (Woop et al.) on the GPU, with a tie-break rule: a ray
          through a shared edge or vertex reports exactly one triangle, at any offset. Needs the
          device's shaderFloat64.
        - ``"reference"``: the same test on the CPU (all cores), no GPU involved: the oracle the
          other tiers are measured against.

        Hits at the interval's ends: ``"fast"`` and ``"refined"`` follow Vulkan (tmin and tmax
        compared in f32 by the traversal); ``"exact"`` and ``"reference"`` accept
        ``tmin <= t <= tmax`` exactly in f64.
        cull: ``"back"`` ignores triangles whose back the ray meets, ``"front"`` those whose front
        (the side their ``normal`` points to); ``None`` (default) culls nothing. Instances made
        with ``cull_disable=True`` are never culled; ``flip_facing=True`` swaps their sides.
        mask: 8-bit ray mask, one for all rays or an integer array of shape ``S``: a ray sees an
        instance when ``instance.mask & mask != 0``.
        progress: show a progress bar as chunks finish (tqdm's when installed, else a line on
        stderr); the same on `occluded`, `intersect_all`, `count` and `contains`.
        opacity_threshold: in (0, 1]; a triangle whose opacity (`Device.mesh`) is below it lets
        rays through; 1 lets through all but fully opaque triangles. Instances made with
        ``opaque=True`` block everywhere. The same in `occluded`, `intersect_all` and `count`.
        out: the `Hits` of an earlier call of the same shape, fields and precision, whose arrays
        this call writes again instead of allocating new ones (as numpy's ``out=``): a loop over
        frames then allocates nothing (each field's array must be writeable, C-contiguous, of the
        query's dtype and shape, and share no memory with the rays; other threads must leave it
        alone during the call). Returns Hits over those arrays. numpy rays only, one hit per ray.
        A call that raises may have written some of out's rows.

        cuda: answer in CUDA memory of the device's GPU, as for CUDA rays (`vkray.CudaArray`s):
        a sensor's hits straight into torch (``torch.from_dlpack(hits.t)``). They are found as
        for host rays and copied to the GPU once. The same on `occluded` (int32 blocking
        triangles, as for CUDA rays), `transmittance`, `intersect_all` and `count`; not with
        ``out=``.

        Rays in CUDA memory (torch, cupy, jax on the device's GPU) give `vkray.CudaArray` hits
        on that GPU (README: rays that never leave the GPU; `SceneLike` says which queries copy
        through the host).
        """
        fields = check_outputs(outputs)
        if out is not None and not isinstance(out, Hits):
            raise TypeError(f"out must be the Hits of an earlier intersect, got {type(out).__name__}")
        query = RayQuery("intersect", origins, directions, tmin, tmax, mask, check_precision(precision), cull,
                         progress, opacity_threshold, fields, out=out, cuda=cuda)
        return cast(Hits, self.answer(query))

    def occluded(
        self,
        origins: Any,
        directions: Any = None,
        *,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        precision: Precision = "fast",
        cull: Cull = None,
        mask: Any = 0xFF,
        progress: bool = False,
        cuda: bool = False,
        opacity_threshold: float = 0.5,
    ) -> np.ndarray:
        """bool ``S``: whether anything lies along each ray within [tmin, tmax].

        Traversal stops at the first hit found (TerminateOnFirstHit), so this is cheaper than
        `intersect`; ``occluded(...) == intersect(...).hit`` ray for ray, in every tier
        (``"refined"`` decides hits as ``"fast"`` does). Rays or a sensor, ``cull``, ``mask`` and
        ``opacity_threshold`` as in `intersect`. CUDA rays give a `CudaArray` of int32 ``S``, the hit
        triangle (>= 0 where occluded, -1 where not), on their GPU.
        """
        query = RayQuery("occluded", origins, directions, tmin, tmax, mask, check_precision(precision), cull,
                         progress, opacity_threshold, ("prim_id",), cuda=cuda)
        return cast(np.ndarray, self.answer(query))

    def transmittance(
        self,
        origins: Any,
        directions: Any = None,
        *,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        precision: Precision = "fast",
        cull: Cull = None,
        mask: Any = 0xFF,
        progress: bool = False,
        cuda: bool = False,
    ) -> np.ndarray:
        """The light each ray keeps within [tmin, tmax]: the product of ``1 - opacity`` over every
        triangle it crosses (`Device.mesh`'s opacity; opaque triangles give 0, cut-outs 1):
        attenuation through foliage, glass or shielding. Computed during traversal without storing
        the hits (the GPU tiers stop a ray once nothing is left). In a scene without opacity (or
        whose translucent instances are forced opaque) it is 1 or 0, and `occluded` answers it.

        precision: ``"fast"`` (float32; at a shared edge a ray may cross both triangles or
        neither, as in `count`), ``"exact"`` (float64; each crossing once, by the f64 test on the
        GPU), ``"refined"`` (the fast tier's crossings re-intersected in f64) or ``"reference"``
        (the f64 test on the CPU: the oracle). Rays or a sensor, ``cull`` and ``mask`` as in
        `intersect`. Spheres are opaque; in a scene with spheres and translucent triangles every
        tier runs on the host (f64, the fast tier's answer in float32).
        """
        query = RayQuery("transmittance", origins, directions, tmin, tmax, mask, check_precision(precision), cull,
                         progress, outputs=("t",), cuda=cuda)
        return cast(np.ndarray, self.answer(query))

    def intersect_all(
        self,
        origins: Any,
        directions: Any = None,
        *,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        max_hits: Optional[int] = None,
        outputs: Optional[Iterable[str]] = None,
        precision: Precision = "fast",
        cull: Cull = None,
        mask: Any = 0xFF,
        progress: bool = False,
        cuda: bool = False,
        opacity_threshold: float = 0.5,
    ) -> AllHits:
        """Every hit of each ray within [tmin, tmax], nearest first (see `AllHits`).

        Hits at the same t come in increasing (instance_id, geometry_id, prim_id). No cap: a
        counting pass sizes each ray's list before a storing pass fills it, chunk by chunk, and a
        result that cannot fit in host memory raises MemoryError before it is stored.
        max_hits: keep only the nearest ``max_hits`` of each ray (None: all, however many).

        precision:

        - ``"exact"`` and ``"reference"``: each crossing of a surface is reported exactly once
          (the f64 watertight test and its tie-break: a ray through a shared edge or vertex hits
          one of the triangles there), while distinct triangles at the same t (coplanar copies,
          stacked layers, instances in one place) are all reported. ``"exact"`` runs on the GPU
          (needs shaderFloat64), ``"reference"`` on all CPU cores; their answers are the same.
        - ``"fast"`` (default): the GPU's f32 traversal decides, each triangle it meets reported
          once (t, uv in float32). At a shared edge or vertex it may report both triangles or
          neither (docs/benchmarks.md counts how often).
        - ``"refined"``: the fast tier's hits, each re-intersected with its triangle in f64 and
          sorted again (float64); a ray with a hit whose f64 answer leaves [tmin, tmax] is traced
          again on the CPU. Edges as in ``"fast"``.

        A sphere is hit where a ray enters it and where it leaves (once from inside, twice at one t
        by a tangent ray); spheres are opaque and not culled. Scenes with spheres answer every tier
        on the host (f64; the fast and refined tiers' values as theirs). Triangles below
        ``opacity_threshold`` are not hits. Other arguments (rays or a sensor) as in `intersect`.

        CUDA rays' hits stay on the GPU in the fast and exact tiers where ``outputs`` are among
        t, uv, prim_id, instance_id and geometry_id (the default's custom_index and normal are
        the host's): the GPU writes every array (`counts` is made at first use).
        """
        fields = check_outputs(outputs)
        limit = None if max_hits is None else _arrays.integer("max_hits", max_hits, 1, _arrays.U64_MAX)
        query = RayQuery("intersect_all", origins, directions, tmin, tmax, mask, check_precision(precision), cull,
                         progress, opacity_threshold, fields, limit, cuda=cuda)
        return cast(AllHits, self.answer(query))

    def count(
        self,
        origins: Any,
        directions: Any = None,
        *,
        tmin: Any = 0.0,
        tmax: Any = np.inf,
        precision: Precision = "fast",
        cull: Cull = None,
        mask: Any = 0xFF,
        progress: bool = False,
        cuda: bool = False,
        opacity_threshold: float = 0.5,
    ) -> np.ndarray:
        """int32 ``S``: the number of hits of each ray within [tmin, tmax], as `intersect_all`
        finds them at the same precision (``count(...) == intersect_all(...).counts``), without
        storing them (but at ``"refined"``, whose hits are re-intersected on the host).

        precision: ``"fast"`` (default: f32 traversal on the GPU, each triangle it meets counted;
        at shared edges it may count two or none), ``"exact"`` (the f64 test on the GPU through
        per-triangle boxes: every crossing counted once; needs shaderFloat64), ``"reference"``
        (the same f64 test on all CPU cores) or ``"refined"``. Rays or a sensor, and the other
        arguments, as in `intersect`. CUDA rays give a `CudaArray` of int32 ``S`` on their GPU
        (the fast tier, of one mask, counted without leaving it)."""
        query = RayQuery("count", origins, directions, tmin, tmax, mask, check_precision(precision), cull,
                         progress, opacity_threshold, cuda=cuda)
        return cast(np.ndarray, self.answer(query))

    def closest_points(
        self,
        points: Any,
        *,
        max_distance: float = np.inf,
        outputs: Optional[Iterable[str]] = None,
        precision: Precision = "reference",
        progress: bool = False,
    ) -> Closest:
        """The surface point nearest to each point, for points of shape ``S + (3,)``.

        Per point (see `Closest`): the ``distance`` to the surface, the nearest surface
        ``position``, and its triangle (``prim_id``, ``instance_id``, ``custom_index``,
        ``geometry_id``), ``uv`` (the barycentrics of the point on it) and ``normal``. Points
        farther than ``max_distance`` from every surface get a miss: distance inf, ids -1, NaN.
        Distances are the scene's (world) distances whatever an instance's transform (rotation,
        non-uniform scale, mirroring). A point equally near several triangles (an edge, a vertex)
        gets the one with the lower (instance_id, prim_id).

        precision:

        - ``"fast"``: the GPU, each candidate triangle measured in f32 in the scene's frame: the
          nearest to within f32 rounding (float32 distance, uv, position).
        - ``"exact"``: the GPU, measuring in f64 with the reference tier's operations in its
          order: its answers to f64 rounding (bit for bit on lavapipe; a GPU's f64 division and
          square root may round otherwise, and a near-tie then go to the other triangle).
        - ``"reference"`` (default): f64 best-first search over the scene's hierarchies on all CPU
          cores: the oracle.

        On the GPU one compute invocation per point searches the reference tier's own
        hierarchies (each mesh's, and the one over the instances), uploaded once per scene, best
        first: the same search as the CPU's, on the GPU's cores. Both GPU tiers need the device's
        shaderFloat64. Scenes with spheres are measured on the host in every tier (f64), their
        instances a rotation, mirror and one scale (others stretch spheres into ellipsoids:
        `UnsupportedError`); a sphere's ``uv`` is NaN.
        """
        query = PointQuery("closest_points", points, check_precision(precision), progress,
                           _max_distance(max_distance), check_closest_outputs(outputs))
        return cast(Closest, self.answer(query))

    def distance(
        self, points: Any, *, max_distance: float = np.inf, precision: Precision = "reference", progress: bool = False
    ) -> np.ndarray:
        """float64 ``S``: the distance from each point to the nearest surface (inf beyond
        ``max_distance``), as `closest_points` finds it."""
        query = PointQuery("distance", points, check_precision(precision), progress, _max_distance(max_distance),
                           ("distance",))
        return cast(np.ndarray, self.answer(query))

    def signed_distance(
        self,
        points: Any,
        *,
        max_distance: float = np.inf,
        precision: Precision = "reference",
        method: Optional[str] = None,
        progress: bool = False,
    ) -> np.ndarray:
        """float64 ``S``: `distance`, negative inside (as Open3D and Warp sign it). The sign is
        `contains`' answer, not a vote of jittered rays: ``method="parity"`` (closed meshes: the
        exact crossing count of one ray per point) or ``"winding"`` (the generalized winding
        number, for meshes with holes); ``None`` (default) takes parity where every mesh is closed
        (`Mesh.is_closed`), else the winding number. A point on the surface is at distance 0.
        With one instance, on the GPU, the distance search and the sign's rays (one exact ray
        from each point) run in one pass; the answers are those of `distance` and `contains`."""
        query = PointQuery("signed_distance", points, check_precision(precision), progress,
                           _max_distance(max_distance), method=None if method is None else check_method(method))
        return cast(np.ndarray, self.answer(query))

    def contains(
        self, points: Any, *, precision: Precision = "exact", method: str = "parity", progress: bool = False
    ) -> np.ndarray:
        """bool ``S`` for points of shape ``S + (3,)``: whether each lies inside any instance.

        method: ``"parity"`` (default) casts one ray per point and counts each instance's
        crossings, each exactly once (the exact test decides rays through edges and vertices):
        no jitter, no vote, the same answer every time. It needs closed meshes (`Mesh.is_closed`)
        and raises ValueError otherwise. ``"winding"``: the generalized winding number of each
        instance (Jacobson et al. 2013) is at least 1/2; meaningful for meshes with holes too.
        A point on a surface (within a few f64 ulps of a triangle) counts as inside, by either
        method. precision: ``"exact"`` (default: parity's crossings found on the GPU by the f64
        test; the winding numbers on the GPU, with points within the GPU's rounding of 1/2 and
        points on a surface decided by the CPU's f64 test) or ``"reference"`` (everything on the
        CPU): the same answers. The f32 tiers raise `UnsupportedError`: they may count a crossing at an edge
        twice or not at all.

        On the GPU, the winding number of a scene of one instance comes from one ray a point too:
        the mesh less the caps that close its holes (per hole, the fan from the mean of its
        corners over its boundary edges; up to 4,096 edges in all) has no boundary, so its winding
        number is the signed count of the ray's crossings with both, each exact; the caps' own
        winding numbers (sums over their few triangles) are added. A ray passes over a cap it
        cannot cross and whose winding number is bounded small, unless that bound could move the
        sum near 1/2. Scenes of several instances sum each instance's triangles over its
        hierarchy instead.
        """
        query = PointQuery("contains", points, check_precision(precision), progress, method=check_method(method))
        return cast(np.ndarray, self.answer(query))


def _max_distance(max_distance: float) -> float:
    """A point query's max_distance: >= 0, or inf."""
    limit = float(max_distance)
    if not limit >= 0:
        raise ValueError(f"max_distance must be >= 0 (or inf), got {max_distance}")
    return limit
