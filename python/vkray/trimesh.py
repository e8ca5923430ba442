"""vkray as trimesh's ray engine.

``vkray.trimesh.RayMeshIntersector(mesh)`` answers trimesh's duck-typed ray interface
(``intersects_id``, ``intersects_location``, ``intersects_first``, ``intersects_any``,
``contains_points``, ``.mesh``) on a vkray device; ``enable()`` makes every new ``trimesh.Trimesh``
use it (``disable()`` undoes it) and ``use(mesh)`` switches one mesh. trimesh's own helpers that
go through ``mesh.ray`` (``mesh.contains``, ``proximity.signed_distance``,
``proximity.longest_ray``, voxelization) then run on vkray.

Choices where trimesh's two engines differ (tests/test_trimesh.py checks each):

- Directions may have any length (trimesh normalizes them; vkray needs not, as no t is returned).
  A zero or non-finite direction, or a non-finite (NaN, inf) origin, hits nothing (as in trimesh's
  triangle engine), rather than raising.
- ``multiple_hits=True`` returns every crossing once, in order along each ray, at the ``"exact"``
  precision by default: a ray through a shared edge or vertex hits one of the triangles there
  (never both, never neither), distinct triangles at one point are all reported, and nothing is
  lost or repeated by re-casting from each hit (trimesh's embree engine re-casts with an offset,
  up to ``max_hits``). ``max_hits`` keeps the nearest per ray; None (the default) keeps all.
- A ray that crosses nothing but touches the mesh (down a side face's plane, through a silhouette
  edge or vertex) hits it where it touches, once per point, as trimesh's triangle engine answers and
  trimesh's tests expect, in every precision: such rays are asked again against the triangles grown
  by ``GRAZE_TOLERANCE`` times the mesh's size (``mesh.scale``) across every edge, so that a ray
  aimed at a vertex or an edge touches it although the float32 geometry on the device rounds it
  away. A ray that passes that close without touching counts as touching. A ray that crosses the
  surface somewhere reports its crossings only; a ray starting on a surface hits it at t = 0 or not
  at all (README: precision tiers).
- ``contains_points``: the parity of one ray's crossings on closed meshes (``Mesh.is_closed``),
  exact; the generalized winding number (>= 1/2) on meshes with holes, which trimesh's ray
  parity cannot answer reliably. Points on the surface are inside.

The precision: ``"exact"`` by default (on the GPU; docs/benchmarks.md measures it at 0.6–1.0× the
fast tier's speed for all hits on an H100), or any of vkray's tiers; a device that cannot answer
``"exact"`` (no shaderFloat64) falls back to ``"reference"`` (the same answers, on the CPU).
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Dict, List, Optional, Tuple, TypeVar, Union

import numpy as np
import trimesh as _trimesh
from numpy.typing import NDArray

from . import PRECISIONS, Device, Precision, Scene, UnsupportedError
from . import default_device as vkray_default_device

__all__ = ["GRAZE_TOLERANCE", "RayMeshIntersector", "default_device", "disable", "enable", "use"]

#: How close, as a fraction of the mesh's size (its bounding box's diagonal), a ray that crosses
#: nothing must pass to an edge or vertex to touch it: far above the float32 rounding of vertices
#: on the device (6e-8 of the size), far below any feature a mesh means to have.
GRAZE_TOLERANCE = 1e-6

T = TypeVar("T")
IdsAndRays = Tuple[NDArray[np.int64], NDArray[np.int64]]

#: The device these share unless given one: `vkray.default_device` (opened once a process).
default_device = vkray_default_device

_lock = threading.Lock()  # enable() and disable()


class RayMeshIntersector:
    """trimesh's ray interface on vkray, for one ``trimesh.Trimesh`` (``geometry``).

    The scene is built on first use, on ``device`` (default: `default_device`), and rebuilt when
    the mesh changes (trimesh's cache tells: a mesh's hash changes with its data).
    """

    def __init__(
        self,
        geometry: Any,
        scale_to_box: bool = True,
        *,
        device: Optional[Device] = None,
        precision: Precision = "exact",
    ) -> None:
        """``geometry``: the ``trimesh.Trimesh``. ``scale_to_box``: trimesh's embree engine scales
        meshes to a unit box for float32's sake; vkray re-centres every scene in float64 before
        anything becomes float32, so it needs no scaling and answers the same either way (the
        argument is kept so that code written for trimesh's engines runs unchanged).
        ``device``: where to trace (default: `default_device`). ``precision``: vkray's tier."""
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(map(repr, PRECISIONS))}, got {precision!r}")
        self.mesh = geometry
        self.precision: Precision = precision
        self._scale_to_box = bool(scale_to_box)
        self._device = device
        self._built: Optional[Tuple[Any, Scene, bool]] = None
        self._grown: Optional[Tuple[Any, Scene, float]] = None
        # Set once the device refused the exact tier (no shaderFloat64, or a driver that does not
        # run the intersection shaders it needs): "reference" answers the same, on the CPU.
        self._exact_refused = False

    # --- the scene, rebuilt when the mesh changes ---------------------------------------------

    def _device_or_default(self) -> Device:
        return self._device if self._device is not None else default_device()

    def _scene(self) -> Tuple[Scene, bool]:
        """The mesh's scene and whether the mesh is closed, built for its current data."""
        key = self.mesh.__hash__()
        built = self._built
        if built is None or built[0] != key:
            device = self._device_or_default()
            mesh = device.mesh(np.asarray(self.mesh.vertices), np.asarray(self.mesh.faces, dtype=np.int64))
            built = (key, device.scene(mesh), mesh.is_closed)
            self._built = built
        return built[1], built[2]

    def _grown_scene(self) -> Tuple[Scene, float]:
        """The scene of the mesh's triangles grown across every edge by the graze tolerance (each
        on its own, scaled about its incentre), and that tolerance; built on first need."""
        key = self.mesh.__hash__()
        grown = self._grown
        if grown is None or grown[0] != key:
            vertices = np.asarray(self.mesh.vertices, dtype=np.float64)
            tolerance = GRAZE_TOLERANCE * float(np.linalg.norm(np.ptp(vertices, axis=0))) if len(vertices) else 0.0
            corners = _grown_triangles(vertices[np.asarray(self.mesh.faces, dtype=np.int64)], tolerance)
            device = self._device_or_default()
            mesh = device.mesh(corners.reshape(-1, 3), np.arange(len(corners) * 3).reshape(-1, 3))
            grown = (key, device.scene(mesh), tolerance)
            self._grown = grown
        return grown[1], grown[2]

    def _run(self, query: Callable[[Precision], T]) -> T:
        """`query` at this intersector's precision (or "reference" where "exact" is refused)."""
        tier: Precision = "reference" if self.precision == "exact" and self._exact_refused else self.precision
        try:
            return query(tier)
        except UnsupportedError:
            if tier != "exact":
                raise
            self._exact_refused = True
            return query("reference")

    # --- trimesh's interface ------------------------------------------------------------------

    def intersects_id(
        self,
        ray_origins: Any,
        ray_directions: Any,
        multiple_hits: bool = True,
        max_hits: Optional[int] = None,
        return_locations: bool = False,
    ) -> Union[IdsAndRays, Tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]]:
        """The triangles the rays hit: ``(index_tri, index_ray)`` (int64), and the hit points
        ``locations`` ((m, 3) float64) when ``return_locations``. Every hit of each ray in order
        along it (``multiple_hits``; the nearest ``max_hits``), or the first."""
        rays = _Rays(ray_origins, ray_directions)
        fields = ["prim_id", "position"] if return_locations else ["prim_id"]
        loc: Any = np.zeros((0, 3))
        if len(rays) == 0:
            tri, ray = np.zeros(0, np.int64), np.zeros(0, np.int64)
        elif multiple_hits:
            tri, ray, loc = self._every_hit(rays.origins, rays.directions, fields, max_hits)
            ray = rays.index(ray)
        else:
            first = self._first_hits(rays.origins, rays.directions, fields)
            hit = first["prim_id"] >= 0
            tri, ray = first["prim_id"][hit].astype(np.int64), rays.index(np.nonzero(hit)[0])
            loc = first["position"][hit] if return_locations else loc
        if return_locations:
            return tri, ray, np.asarray(loc, dtype=np.float64).reshape(-1, 3)
        return tri, ray

    def _first_hits(self, o: NDArray[np.float64], d: NDArray[np.float64], fields: List[str]) -> Dict[str, Any]:
        """Each ray's first crossing, or where it crosses nothing, its first touch (a graze along a
        side face or a silhouette edge, through a silhouette vertex: `_grown_scene`)."""
        scene, _ = self._scene()
        first = self._run(lambda tier: scene.intersect(o, d, outputs=fields, precision=tier))
        out = {name: np.array(getattr(first, name)) for name in fields}
        missed = np.nonzero(out["prim_id"] < 0)[0]
        if len(missed):
            grown, _ = self._grown_scene()
            om, dm = o[missed], d[missed]
            touches = self._run(lambda tier: grown.intersect(om, dm, outputs=fields, precision=tier))
            for name in fields:
                out[name][missed] = getattr(touches, name)
        return out

    def _every_hit(
        self, o: NDArray[np.float64], d: NDArray[np.float64], fields: List[str], max_hits: Optional[int]
    ) -> Tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """Every crossing of each ray, in order along it; where a ray crosses nothing, its touches
        (one per point: the triangles that share a grazed edge or vertex meet it there at once)."""
        scene, _ = self._scene()
        hits = self._run(lambda tier: scene.intersect_all(o, d, max_hits=max_hits, outputs=fields, precision=tier))
        tri, ray = np.asarray(hits.prim_id).astype(np.int64), np.asarray(hits.ray_index)
        loc = hits.position if hits.position is not None else np.zeros((len(tri), 3))
        missed = np.nonzero(np.asarray(hits.counts).reshape(-1) == 0)[0]
        if len(missed) == 0:
            return tri, ray, loc
        grown, tolerance = self._grown_scene()
        om, dm = o[missed], d[missed]
        touches = self._run(
            lambda tier: grown.intersect_all(om, dm, max_hits=max_hits, outputs=[*fields, "t"], precision=tier)
        )
        g_ray, g_t = np.asarray(touches.ray_index), np.asarray(touches.t, dtype=np.float64)
        # Touches of one point (the grown triangles around a grazed vertex or edge overlap there)
        # lie within a few tolerances of each other along the ray: the first of them stands for all.
        step = np.abs(np.diff(g_t)) * np.linalg.norm(dm[g_ray[1:]], axis=1) if len(g_ray) > 1 else np.zeros(0)
        first_at_point = np.ones(len(g_ray), dtype=bool)
        first_at_point[1:] = (g_ray[1:] != g_ray[:-1]) | (step > 4 * tolerance)
        g_loc = touches.position if touches.position is not None else np.zeros((len(g_ray), 3))
        tri = np.concatenate([tri, np.asarray(touches.prim_id)[first_at_point].astype(np.int64)])
        ray = np.concatenate([ray, missed[g_ray[first_at_point]]])
        loc = np.concatenate([loc, np.asarray(g_loc)[first_at_point]])
        order = np.argsort(ray, kind="stable")
        return tri[order], ray[order], loc[order]

    def intersects_location(
        self, ray_origins: Any, ray_directions: Any, multiple_hits: bool = True
    ) -> Tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
        """``(locations, index_ray, index_tri)``: where the rays hit, as `intersects_id` finds."""
        tri, ray, loc = self.intersects_id(ray_origins, ray_directions, multiple_hits, None, True)  # type: ignore[misc]
        return loc, ray, tri

    def intersects_first(self, ray_origins: Any, ray_directions: Any) -> NDArray[np.int64]:
        """The first triangle each ray hits (int64), -1 where it hits none."""
        rays = _Rays(ray_origins, ray_directions)
        if len(rays) == 0:
            return np.full(rays.count, -1, dtype=np.int64)
        first: NDArray[np.int64] = self._first_hits(rays.origins, rays.directions, ["prim_id"])["prim_id"].astype(
            np.int64
        )
        if rays.live is None:
            return first
        out = np.full(rays.count, -1, dtype=np.int64)
        out[rays.live] = first
        return out

    def intersects_any(self, ray_origins: Any, ray_directions: Any) -> NDArray[np.bool_]:
        """Whether each ray hits the mesh."""
        return self.intersects_first(ray_origins, ray_directions) >= 0

    def contains_points(self, points: Any) -> NDArray[np.bool_]:
        """Whether each point lies inside the mesh (on its surface: inside). Closed meshes: the
        parity of one ray's crossings, exact; others: the generalized winding number."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(p) == 0:
            return np.zeros(0, dtype=bool)
        scene, closed = self._scene()
        method = "parity" if closed else "winding"
        # The f32 tiers cannot decide parity (contains refuses them): exact or reference.
        exact_or_reference: Precision = "reference" if self.precision == "reference" else "exact"
        try:
            if exact_or_reference == "exact" and self._exact_refused:
                exact_or_reference = "reference"
            return scene.contains(p, precision=exact_or_reference, method=method)
        except UnsupportedError:
            self._exact_refused = True
            return scene.contains(p, precision="reference", method=method)

    # --- pickling and copying, as trimesh's embree intersector ------------------------------

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_built"] = state["_grown"] = None  # device objects stay in their process
        state["_device"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    def __copy__(self) -> RayMeshIntersector:
        return RayMeshIntersector(self.mesh, self._scale_to_box, device=self._device, precision=self.precision)

    def __deepcopy__(self, memo: Any) -> RayMeshIntersector:
        return self.__copy__()

    def __repr__(self) -> str:
        return f"<vkray.trimesh.RayMeshIntersector precision={self.precision!r} faces={len(self.mesh.faces)}>"


def _grown_triangles(corners: NDArray[np.float64], tolerance: float) -> NDArray[np.float64]:
    """Triangles ((F, 3, 3) corners) each scaled about its incentre so that every edge moves out by
    `tolerance` (the inradius r becomes r + tolerance); triangles narrower than the tolerance (and
    degenerate ones) stay as they are, as their neighbours' growth covers them."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    sides = np.stack([np.linalg.norm(b - c, axis=1), np.linalg.norm(c - a, axis=1), np.linalg.norm(a - b, axis=1)], 1)
    perimeter = sides.sum(axis=1)
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)  # twice the area
    with np.errstate(divide="ignore", invalid="ignore"):
        incentre = np.einsum("fk,fkj->fj", sides, corners) / perimeter[:, None]
        inradius = area2 / perimeter
        scale = np.where(inradius > tolerance, (inradius + tolerance) / inradius, 1.0)
    moved = incentre[:, None, :] + scale[:, None, None] * (corners - incentre[:, None, :])
    return np.ascontiguousarray(np.where((scale > 1.0)[:, None, None], moved, corners))


class _Rays:
    """Rays as trimesh takes them: (n, 3) origins and directions of one shape. vkray takes
    directions of any length (no t is returned here), so they are not normalized; rays that can
    hit nothing (a zero or non-finite direction, a non-finite origin) are left out: `live` holds
    the others' indices, or is None when every ray is live (no copies then)."""

    def __init__(self, origins: Any, directions: Any) -> None:
        o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        if o.shape != d.shape:
            raise ValueError(f"ray origins {o.shape} and directions {d.shape} differ")
        self.count = len(o)
        ok = np.isfinite(d).all(axis=1) & (np.abs(d).max(axis=1, initial=0.0) > 0) & np.isfinite(o).all(axis=1)
        self.live: Optional[NDArray[np.int64]] = None if ok.all() else np.nonzero(ok)[0]
        self.origins, self.directions = (o, d) if self.live is None else (o[self.live], d[self.live])

    def __len__(self) -> int:
        return len(self.origins)

    def index(self, rays: NDArray[Any]) -> NDArray[np.int64]:
        """The caller's indices of rays given by their position among the live ones."""
        rays = np.asarray(rays, dtype=np.int64)
        return rays if self.live is None else self.live[rays]


# --- switching trimesh's engine ----------------------------------------------------------------

_originals: dict[str, Any] = {}


def enable(*, device: Optional[Device] = None, precision: Precision = "exact") -> None:
    """Makes every ``trimesh.Trimesh`` created from now on use vkray for its ``.ray`` (whichever
    engine trimesh would have picked). `disable` undoes it; existing meshes keep their engine."""

    def factory(geometry: Any, scale_to_box: bool = True, **kwargs: Any) -> RayMeshIntersector:
        return RayMeshIntersector(geometry, scale_to_box, device=device, precision=precision)

    with _lock:
        for name, module in _engine_modules().items():
            _originals.setdefault(name, module.RayMeshIntersector)
            module.RayMeshIntersector = factory


def disable() -> None:
    """Gives trimesh back its own engines for meshes created from now on."""
    with _lock:
        for name, module in _engine_modules().items():
            if name in _originals:
                module.RayMeshIntersector = _originals.pop(name)


def use(mesh: Any, *, device: Optional[Device] = None, precision: Precision = "exact") -> Any:
    """Switches one ``trimesh.Trimesh`` to vkray (``mesh.ray``); returns the mesh."""
    mesh.ray = RayMeshIntersector(mesh, device=device, precision=precision)
    return mesh


def _engine_modules() -> dict[str, Any]:
    """trimesh's ray engines that ``Trimesh.__init__`` may instantiate."""
    from trimesh import ray

    modules: dict[str, Any] = {"ray_triangle": ray.ray_triangle}
    if getattr(ray, "has_embree", False):
        modules["ray_pyembree"] = ray.ray_pyembree
    return modules


del _trimesh  # imported above only to fail early, with a clear ImportError, without trimesh
