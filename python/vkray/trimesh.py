"""vkray as trimesh's ray engine.

``vkray.trimesh.RayMeshIntersector(mesh)`` answers trimesh's duck-typed ray interface
(``intersects_id``, ``intersects_location``, ``intersects_first``, ``intersects_any``,
``contains_points``, ``.mesh``) on a vkray device; ``enable()`` makes every new ``trimesh.Trimesh``
use it (``disable()`` undoes it) and ``use(mesh)`` switches one mesh. trimesh's own helpers that
go through ``mesh.ray`` (``mesh.contains``, ``proximity.signed_distance``,
``proximity.longest_ray``, voxelization) then run on vkray.

Choices where trimesh's two engines differ (tests/test_trimesh.py checks each):

- Directions may have any length (trimesh normalizes them; vkray needs not, as no t is returned).
  A zero or non-finite direction hits nothing (trimesh's triangle engine), rather than raising.
- ``multiple_hits=True`` returns every crossing once, in order along each ray, at the ``"exact"``
  precision by default: a ray through a shared edge or vertex hits one of the triangles there
  (never both, never neither), distinct triangles at one point are all reported, and nothing is
  lost or repeated by re-casting from each hit (trimesh's embree engine re-casts with an offset,
  up to ``max_hits``). ``max_hits`` keeps the nearest per ray; None (the default) keeps all.
- A ray that crosses nothing but touches the mesh (down a side face's plane, through a silhouette
  edge or vertex) hits it where it touches, once per point, as trimesh's tests expect: such rays
  are asked again with closed triangles (the exact tier's contacts). A ray that crosses the
  surface somewhere reports its crossings only. Otherwise a ray in the plane of a face hits it
  nowhere (the watertight test has no area to hit); a ray starting on a surface hits it at t = 0
  or not at all (README: precision tiers).
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

from . import _api, _core
from ._api import Precision

__all__ = ["RayMeshIntersector", "default_device", "disable", "enable", "use"]

T = TypeVar("T")
IdsAndRays = Tuple[NDArray[np.int64], NDArray[np.int64]]

_lock = threading.Lock()
_device: Optional[_api.Device] = None


def default_device() -> _api.Device:
    """The device intersectors share unless given one: ``vkray.Device()``, opened once."""
    global _device
    with _lock:
        if _device is None:
            _device = _api.Device()
        return _device


class RayMeshIntersector:
    """trimesh's ray interface on vkray, for one ``trimesh.Trimesh`` (``geometry``).

    The scene is built on first use, on ``device`` (default: `default_device`), and rebuilt when
    the mesh changes (trimesh's cache tells: a mesh's hash changes with its data).
    """

    def __init__(self, geometry: Any, *, device: Optional[_api.Device] = None, precision: Precision = "exact") -> None:
        if precision not in ("fast", "refined", "exact", "reference"):
            raise ValueError(f"precision must be 'fast', 'refined', 'exact' or 'reference', got {precision!r}")
        self.mesh = geometry
        self.precision: Precision = precision
        self._device = device
        self._built: Optional[Tuple[Any, _api.Scene, bool]] = None
        # Set once the device refused the exact tier (no shaderFloat64, or a driver that does not
        # run the intersection shaders it needs): "reference" answers the same, on the CPU.
        self._exact_refused = False

    # --- the scene, rebuilt when the mesh changes ---------------------------------------------

    def _scene(self) -> Tuple[_api.Scene, bool]:
        """The mesh's scene and whether the mesh is closed, built for its current data."""
        key = self.mesh.__hash__()
        built = self._built
        if built is None or built[0] != key:
            device = self._device if self._device is not None else default_device()
            mesh = device.mesh(np.asarray(self.mesh.vertices), np.asarray(self.mesh.faces, dtype=np.int64))
            built = (key, device.scene(mesh), mesh.is_closed)
            self._built = built
        return built[1], built[2]

    def _run(self, query: Callable[[Precision], T]) -> T:
        """`query` at this intersector's precision (or "reference" where "exact" is refused)."""
        tier: Precision = "reference" if self.precision == "exact" and self._exact_refused else self.precision
        try:
            return query(tier)
        except _core.UnsupportedError:
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

    def _grazes(self) -> bool:
        """Whether rays that cross nothing are asked again for contacts (the exact tier alone)."""
        return self.precision == "exact" and not self._exact_refused

    def _first_hits(self, o: NDArray[np.float64], d: NDArray[np.float64], fields: List[str]) -> Dict[str, Any]:
        """Each ray's first crossing, or where it crosses nothing, its first contact (a graze
        along a silhouette edge or through a silhouette vertex)."""
        scene, _ = self._scene()
        first = self._run(lambda tier: scene.intersect(o, d, outputs=fields, precision=tier))
        out = {name: np.array(getattr(first, name)) for name in fields}
        missed = np.nonzero(out["prim_id"] < 0)[0]
        if len(missed) and self._grazes():
            grazes = scene._core.trace(o[missed], d[missed], 0.0, np.inf, "closest", fields, "exact", None, None, True)
            for name in fields:
                out[name][missed] = grazes[name]
        return out

    def _every_hit(
        self, o: NDArray[np.float64], d: NDArray[np.float64], fields: List[str], max_hits: Optional[int]
    ) -> Tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """Every crossing of each ray, in order along it; where a ray crosses nothing, its contacts
        (one per point: the triangles that share a grazed edge or vertex meet it there at once)."""
        scene, _ = self._scene()
        hits = self._run(lambda tier: scene.intersect_all(o, d, max_hits=max_hits, outputs=fields, precision=tier))
        tri, ray = np.asarray(hits.prim_id).astype(np.int64), np.asarray(hits.ray_index)
        loc = hits.position if hits.position is not None else np.zeros((len(tri), 3))
        missed = np.nonzero(np.asarray(hits.counts).reshape(-1) == 0)[0]
        if len(missed) == 0 or not self._grazes():
            return tri, ray, loc
        grazes = scene._core.trace_all(
            o[missed], d[missed], 0.0, np.inf, [*fields, "t"], "exact", None, None, max_hits, True
        )
        g_ray, g_t = grazes["ray_index"], grazes["t"]
        first_at_t = np.ones(len(g_ray), dtype=bool)
        first_at_t[1:] = (g_ray[1:] != g_ray[:-1]) | (g_t[1:] != g_t[:-1])
        g_loc = grazes["position"] if "position" in grazes else np.zeros((len(g_ray), 3))
        tri = np.concatenate([tri, grazes["prim_id"][first_at_t].astype(np.int64)])
        ray = np.concatenate([ray, missed[g_ray[first_at_t]]])
        loc = np.concatenate([loc, g_loc[first_at_t]])
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
        except _core.UnsupportedError:
            self._exact_refused = True
            return scene.contains(p, precision="reference", method=method)

    # --- pickling and copying, as trimesh's embree intersector ------------------------------

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_built"] = None  # device objects stay in their process
        state["_device"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    def __copy__(self) -> RayMeshIntersector:
        return RayMeshIntersector(self.mesh, device=self._device, precision=self.precision)

    def __deepcopy__(self, memo: Any) -> RayMeshIntersector:
        return self.__copy__()

    def __repr__(self) -> str:
        return f"<vkray.trimesh.RayMeshIntersector precision={self.precision!r} faces={len(self.mesh.faces)}>"


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


def enable(*, device: Optional[_api.Device] = None, precision: Precision = "exact") -> None:
    """Makes every ``trimesh.Trimesh`` created from now on use vkray for its ``.ray`` (whichever
    engine trimesh would have picked). `disable` undoes it; existing meshes keep their engine."""

    def factory(geometry: Any, *args: Any, **kwargs: Any) -> RayMeshIntersector:
        return RayMeshIntersector(geometry, device=device, precision=precision)

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


def use(mesh: Any, *, device: Optional[_api.Device] = None, precision: Precision = "exact") -> Any:
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
