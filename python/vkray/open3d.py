"""vkray as Open3D's ray-casting scene: ``vkray.open3d.RaycastingScene``.

Code written for ``open3d.t.geometry.RaycastingScene`` switches with one import::

    from vkray.open3d import RaycastingScene      # in place of o3d.t.geometry.RaycastingScene
    scene = RaycastingScene()
    cube_id = scene.add_triangles(mesh)            # an open3d.t.geometry.TriangleMesh, or arrays
    ans = scene.cast_rays(rays)                    # {"t_hit", "geometry_ids", "primitive_ids", ...}

or, for code that cannot be edited, ``vkray.open3d.enable()`` puts the class in place of
``open3d.t.geometry.RaycastingScene`` (``disable()`` gives Open3D's back). Every method of Open3D's
class is here, with its arguments, result keys, dtypes and shapes (leading dimensions kept):
``add_triangles`` (arrays or a mesh; returns the geometry id), ``cast_rays``, ``test_occlusions``
(``tnear``, ``tfar``), ``count_intersections``, ``list_intersections``,
``compute_closest_points``, ``compute_distance``, ``compute_signed_distance`` and
``compute_occupancy`` (``nsamples``), ``create_rays_pinhole`` (both forms) and ``INVALID_ID``.
Open3D itself is optional: this module imports without it (pip install "vkray[open3d]" or
open3d for Open3D tensors and meshes).

Inputs and results. Open3D tensors (CPU or CUDA), numpy arrays, anything numpy can read, and
DLPack arrays (torch, cupy) are taken, float32 or float64. Open3D tensors in give Open3D tensors
out, on the input's device; other inputs give numpy arrays, also for CUDA arrays of other
libraries (``results="open3d"`` gives Open3D tensors for every input, as Open3D's class does:
that is what `enable` installs). The drop-in copies nothing in host memory: tensors are read and
answered through shared memory, and ids are int32 viewed as Open3D's uint32 (vkray's own call
then packs the rays, as when called directly). CUDA rays stay on the GPU in `cast_rays`,
`test_occlusions` (the fast tier) and `count_intersections` (the exact tier; their answers come
back as Open3D tensors on the same GPU); the other queries copy CUDA inputs through the host here
(`_host`): `list_intersections` asks vkray for the geometry ids (custom indices), which its
GPU-resident all hits do not write. Open3D's own class runs on the CPU only.

Precision (``precision=None``, the default): `cast_rays` and `test_occlusions` run vkray's
``"fast"`` tier (float32 hardware traversal, as Embree's float32 answers); `count_intersections`
and `list_intersections` the ``"exact"`` tier (each crossing of a surface once); closest points
and distances the ``"fast"`` tier (the nearest point to float32's rounding, as Open3D's
float32 search; ``precision="exact"`` measures in float64, then rounds to Open3D's float32);
occupancy and the signs of signed distances vkray's exact ``Scene.contains`` whatever the tier.
A device without shaderFloat64 answers the tiers that need it with ``"reference"`` (the same
answers, on the CPU). ``precision="fast"``, ``"refined"``, ``"exact"`` or ``"reference"`` makes
every query use that tier (``"refined"`` is ``"exact"`` for closest points and distances).

Where Open3D's answers and these differ (tests/test_open3d.py checks each):

- List order: `list_intersections` gives each ray's hits nearest first (hits at one t in
  (geometry id, triangle) order); Open3D lists them in Embree's traversal order.
- Shared edges and vertices: a ray through an edge or vertex crosses the surface once there, so
  `count_intersections` and `list_intersections` report one triangle. Open3D's count drops a
  repeat only when the same geometry's hits come one after the other, so a ray through the
  diagonal edges of two overlapping boxes counts 8 crossings where there are 4.
- Occupancy voting: `compute_occupancy` and the sign of `compute_signed_distance` are exact: the
  parity of one ray's crossings, each counted once (closed meshes), whatever ``nsamples`` (checked
  as Open3D checks it: odd and >= 1). Open3D votes with ``nsamples`` jittered rays, which may
  disagree with the exact answer near edges and vertices.
- Points on the surface are inside: occupancy 1, signed distance 0 (to float32's rounding in the
  default tier, never positive; exactly 0 with ``precision="exact"``). Open3D's jittered rays put
  them on either side.
- Open meshes' signs: a scene with a mesh that is not closed (``vkray.Mesh.is_closed``) decides
  inside by the generalized winding number (>= 1/2), which means something for meshes with holes;
  Open3D's parity of jittered rays gives arbitrary signs there.
- Several meshes: a point is inside when it is inside any of them; Open3D's parity counts every
  mesh's crossings together (its documentation assumes meshes that do not overlap, where the two
  agree).
- Geometry ids are 0, 1, 2, ... in the order of `add_triangles` (an empty mesh takes an id and is
  never hit), as in Open3D. Adding triangles after a query is allowed: the scene is rebuilt on the
  next query, and every geometry keeps its id.
- An empty scene: rays miss, distances are inf, closest points are NaN with ``INVALID_ID``s, and
  occupancy is 0 (Open3D returns unwritten memory for distances and closest points there).
- `test_occlusions` with ``tnear > tfar`` finds nothing; a negative ``tnear`` looks behind the
  origin, as Open3D's does.
- ``nthreads`` is accepted everywhere and ignored: the device's threads do the host's share
  (``vkray.Device(host_threads=n)``, given as ``vkray_device``).
- Bad input raises (indices out of range, non-finite vertices) where Open3D reads past its arrays.
- Misses in `cast_rays`: t inf and ids ``INVALID_ID`` as Open3D's, but uvs and normals NaN
  where Open3D writes 0: vkray's queries write NaN there, and making them 0 would cost a pass
  over the results as long as the query itself (``np.nan_to_num(ans["primitive_normals"])`` gives
  Open3D's zeros). Test for a hit with ``geometry_ids != INVALID_ID`` or a finite ``t_hit``.
"""

from __future__ import annotations

import importlib
import math
import sys
import threading
from typing import Any, Callable, Dict, List, Literal, Optional, Sequence, Tuple, TypeVar, Union

import numpy as np
from numpy.typing import NDArray

from . import Device, Instance, Mesh, Precision, Scene, UnsupportedError
from . import default_device as vkray_default_device

__all__ = ["INVALID_ID", "RaycastingScene", "default_device", "disable", "enable", "enabled"]

T = TypeVar("T")
#: What a query returns: ``"auto"`` (Open3D tensors for Open3D tensors in, numpy otherwise) or
#: ``"open3d"`` (Open3D tensors for every input, as Open3D's own class). A union of one-value
#: Literals, as vkray's option types (`python -m mypy.stubtest vkray` wants a union at run time).
Results = Union[Literal["auto"], Literal["open3d"]]

#: The id of no geometry and no triangle (a miss), as Open3D's ``RaycastingScene.INVALID_ID``.
INVALID_ID = 0xFFFFFFFF

_INSTALL = (
    'Open3D is not installed: pip install "vkray[open3d]" (or open3d, or open3d-cpu) for Open3D tensors and meshes'
)

#: The queries whose vkray call takes CUDA arrays without leaving the GPU (Scene.intersect and
#: Scene.occluded in the fast tier, Scene.count in the fast and exact tiers). The others copy
#: CUDA inputs through the host here (`_host`), as vkray's own queries would (results convert
#: from vkray's CUDA arrays for any query: `_Result`).
_CUDA_QUERIES = frozenset({"cast_rays", "test_occlusions", "count_intersections"})

_DLPACK_CUDA = 2

#: The device these share unless given one: `vkray.default_device` (opened once a process).
default_device = vkray_default_device

_lock = threading.Lock()  # enable() and disable()


def _open3d() -> Any:
    """The open3d module, imported now; ImportError saying what to install without it."""
    try:
        return importlib.import_module("open3d")
    except ImportError as exc:
        raise ImportError(_INSTALL) from exc


def _is_tensor(value: object) -> bool:
    """Whether ``value`` is an ``open3d.core.Tensor`` (never imports Open3D: without it loaded,
    nothing is one)."""
    o3d = sys.modules.get("open3d")
    core = getattr(o3d, "core", None)
    return core is not None and isinstance(value, core.Tensor)


def _dlpack_on_cuda(value: object) -> bool:
    """Whether ``value`` is a DLPack array in CUDA memory (an Open3D, torch or cupy tensor)."""
    if isinstance(value, np.ndarray) or not hasattr(value, "__dlpack__"):
        return False
    device_of = getattr(value, "__dlpack_device__", None)
    return device_of is not None and _device_type(device_of()[0]) == _DLPACK_CUDA


def _device_type(kind: Any) -> int:
    """DLPack's device type as an int (Open3D's ``__dlpack_device__`` gives an enum, no int)."""
    return int(getattr(kind, "value", kind))


class _Open3DCuda:
    """An Open3D CUDA tensor as vkray reads CUDA arrays (the same memory): Open3D names its
    DLPack device type by an enum, which vkray's reading of ``__dlpack_device__`` takes as no
    integer."""

    def __init__(self, tensor: Any) -> None:
        self.tensor = tensor
        self.shape = tuple(int(n) for n in tensor.shape)

    def __dlpack_device__(self) -> Tuple[int, int]:
        kind, index = self.tensor.__dlpack_device__()
        return _device_type(kind), int(index)

    def __dlpack__(self, *, stream: Optional[int] = None, **_: Any) -> Any:
        return self.tensor.__dlpack__(stream=stream)


def _host(name: str, value: Any) -> NDArray[Any]:
    """CUDA memory copied into host memory: for the queries whose vkray call does not take CUDA
    arrays yet (those not in `_CUDA_QUERIES`), and meshes (built from the host). The one place
    where inputs leave the GPU."""
    if _is_tensor(value):
        return np.asarray(value.cpu().numpy())
    try:
        return np.from_dlpack(value, device="cpu", copy=True)  # DLPack 1.0 (numpy >= 2.1, torch, cupy)
    except (TypeError, ValueError, BufferError, RuntimeError, AttributeError) as exc:
        raise TypeError(
            f"{name} lives in CUDA memory that could not be copied to the host here ({exc}): pass an Open3D "
            "tensor, or a host array (torch: .cpu(), cupy: .get())"
        ) from None


def _device_name(device: Any) -> str:
    """An Open3D device (``open3d.core.Device``) or its name ("CPU:0", "CUDA:1") as its name."""
    if device is None:
        return "CPU:0"
    if isinstance(device, str):
        kind, _, index = device.partition(":")
        if kind.upper() not in ("CPU", "CUDA", "SYCL") or not (index == "" or index.isdigit()):
            raise ValueError(f"device must be an Open3D device such as 'CPU:0' or 'CUDA:0', got {device!r}")
        return f"{kind.upper()}:{index or 0}"
    if type(device).__name__ == "Device" and type(device).__module__.startswith("open3d"):
        return str(device)
    raise TypeError(f"device must be an open3d.core.Device or its name ('CPU:0', 'CUDA:0'), got {device!r}")


def _threads(nthreads: object) -> None:
    """Open3D's ``nthreads``: an integer, accepted and not used (vkray's device decides)."""
    if isinstance(nthreads, (bool, np.bool_)) or not isinstance(nthreads, (int, np.integer)):
        raise TypeError(f"nthreads must be an integer, got {nthreads!r}")


def _samples(nsamples: object) -> None:
    """Open3D's ``nsamples``, checked as Open3D checks it (odd and >= 1); the answer is exact."""
    if isinstance(nsamples, (bool, np.bool_)) or not isinstance(nsamples, (int, np.integer)):
        raise TypeError(f"nsamples must be an integer, got {nsamples!r}")
    if nsamples < 1 or nsamples % 2 == 0:
        raise ValueError(f"nsamples must be odd and >= 1, got {int(nsamples)}")


def _scalar(name: str, value: object) -> float:
    """A real scalar (Open3D's tnear and tfar are floats)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {value!r}")
    number = float(value)
    if math.isnan(number):
        raise ValueError(f"{name} must be a number, got nan")
    return number


class _Input:
    """A query's array as vkray takes it, where its results go, and its leading shape.

    ``array``: a numpy array (host memory is shared with Open3D tensors and DLPack arrays, not
    copied) or, where ``cuda`` allows, the caller's CUDA array itself (Open3D tensors flattened to
    rows: they cannot be sliced with an Ellipsis). ``target``: the Open3D device the results go
    to, or None for numpy. ``shape``: the leading dimensions."""

    def __init__(self, name: str, value: Any, width: int, cuda: bool, results: Results, device: str) -> None:
        tensor = _is_tensor(value)
        self.target: Optional[str] = str(value.device) if tensor else (device if results == "open3d" else None)
        on_cuda = _dlpack_on_cuda(value)
        self.cuda = on_cuda and cuda
        if self.cuda:
            shape = tuple(int(n) for n in value.shape)
            _check_width(name, shape, width)
            self.array: Any = _Open3DCuda(value.reshape((-1, width))) if tensor else value
        else:
            if on_cuda:
                array = _host(name, value)
            elif tensor:
                array = value.numpy()  # a view of the tensor's memory
            elif hasattr(value, "__dlpack__") and not isinstance(value, np.ndarray):
                array = np.from_dlpack(value)  # host memory, shared
            else:
                try:
                    array = np.asarray(value)
                except (TypeError, ValueError) as exc:
                    raise TypeError(f"{name} must be array-like: {exc}") from None
            shape = array.shape
            _check_width(name, shape, width)
            self.array = array
        self.shape: Tuple[int, ...] = shape[:-1]

    def split(self) -> Tuple[Any, Any]:
        """Rays' origins and directions: views of the (..., 6) array, never copies."""
        if isinstance(self.array, _Open3DCuda):
            rows = self.array.tensor
            return _Open3DCuda(rows[:, :3]), _Open3DCuda(rows[:, 3:])
        if len(self.array.shape) == 2:
            return self.array[:, :3], self.array[:, 3:]
        return self.array[..., :3], self.array[..., 3:]


def _check_width(name: str, shape: Tuple[int, ...], width: int) -> None:
    if len(shape) == 0 or shape[-1] != width:
        raise ValueError(f"{name} must have shape (..., {width}), got {shape}")


class _Result:
    """Turns vkray's answers (numpy arrays, or `vkray.CudaArray`s for CUDA rays) into a query's
    results: numpy arrays, or Open3D tensors on the input's device, of Open3D's dtypes and of the
    input's leading shape."""

    def __init__(self, target: Optional[str], shape: Tuple[int, ...]) -> None:
        self.target = target
        self.shape = shape
        self.o3d: Any = _open3d() if target is not None else None

    def __call__(
        self, value: Any, dtype: str, *, width: int = 0, shape: Optional[Tuple[int, ...]] = None
    ) -> Any:
        """``value`` as ``dtype`` ("float32", "uint32" (from int32: -1 is INVALID_ID), "int32" or
        "bool"), of the leading shape and a last axis of ``width`` (0: none), or of ``shape``.
        Without copies where the dtype is already right (int32 ids are viewed as uint32)."""
        want = shape if shape is not None else self.shape + ((width,) if width else ())
        if not isinstance(value, np.ndarray) and self.target is None:
            value = np.asarray(value)  # a vkray.CudaArray asked for as numpy: copied to the host
        if isinstance(value, np.ndarray):
            array = _as_dtype(value, dtype)
            array = array.reshape(want)
            if self.target is None:
                return array
            tensor = _tensor_from_dlpack(self.o3d.core, array)
        else:
            # A vkray.CudaArray (rays from CUDA), read without a copy through DLPack.
            core = self.o3d.core
            tensor = _tensor_from_dlpack(core, value)
            if dtype == "bool":
                tensor = tensor.ge(0)  # occluded's CUDA answer is the hit triangle, -1 where none
            elif dtype == "uint32":
                tensor = tensor.to(core.uint32)  # -1 becomes INVALID_ID
            elif dtype == "float32" and tensor.dtype != core.float32:
                tensor = tensor.to(core.float32)
            tensor = tensor.reshape(list(want))
        if str(tensor.device) != self.target:
            tensor = tensor.to(self.o3d.core.Device(self.target))
        return tensor


def _as_dtype(array: NDArray[Any], dtype: str) -> NDArray[Any]:
    if dtype == "uint32" and array.dtype == np.int32:
        return array.view(np.uint32)  # -1 (a miss) is INVALID_ID, without a copy
    if array.dtype != np.dtype(dtype):
        return array.astype(dtype)
    return array


class RaycastingScene:
    """Open3D's ``open3d.t.geometry.RaycastingScene``, answered by vkray (see the module).

    nthreads: accepted and not used (Open3D's threads to build the scene).
    device: the Open3D device (``open3d.core.Device`` or its name, "CPU:0" by default) where results
    go when ``results="open3d"`` and the input is not an Open3D tensor.
    vkray_device: the vkray device that builds and traces (default: `default_device`).
    precision: None (each query's default tier, see the module) or one of vkray's tiers for all.
    results: ``"auto"`` (the class's default, `results`) or ``"open3d"``.

    One scene may be queried from several threads at once; `add_triangles` may come between
    queries (the scene is rebuilt at the next query).
    """

    #: The id of no geometry and no triangle (a miss).
    INVALID_ID: int = INVALID_ID
    #: What queries return unless the constructor says otherwise: "auto" here, "open3d" in the
    #: class `enable` installs.
    results: Results = "auto"

    def __init__(
        self,
        nthreads: int = 0,
        device: Any = None,
        *,
        vkray_device: Optional[Device] = None,
        precision: Optional[Precision] = None,
        results: Optional[Results] = None,
    ) -> None:
        _threads(nthreads)
        if precision is not None and precision not in ("fast", "refined", "exact", "reference"):
            raise ValueError(f"precision must be None, 'fast', 'refined', 'exact' or 'reference', got {precision!r}")
        if results is not None and results not in ("auto", "open3d"):
            raise ValueError(f"results must be 'auto' or 'open3d', got {results!r}")
        if vkray_device is not None and not isinstance(vkray_device, Device):
            raise TypeError(f"vkray_device must be a vkray.Device, got {type(vkray_device).__name__}")
        self.device = _device_name(device)
        self.precision = precision
        if results is not None:
            self.results = results
        self._vkray_device = vkray_device
        self._lock = threading.Lock()
        #: (geometry id, mesh) of every non-empty geometry added; ids count empty ones too.
        self._meshes: List[Tuple[int, Mesh]] = []
        self._geometries = 0
        self._built: Optional[Tuple[int, Scene, bool]] = None  # (geometries, scene, all closed)
        # Set once the device refused a tier for want of shaderFloat64: "reference" answers.
        self._f64_refused = False

    @property
    def vkray_device(self) -> Device:
        """The vkray device this scene builds and traces on."""
        return self._vkray_device if self._vkray_device is not None else default_device()

    # --- building ---------------------------------------------------------------------------

    def add_triangles(self, vertex_positions: Any, triangle_indices: Any = None) -> int:
        """Adds a triangle mesh; returns its geometry id (0, 1, 2, ... in order of adding).

        ``add_triangles(vertex_positions, triangle_indices)``: (N, 3) floats and (M, 3) integer
        indices (Open3D tensors, numpy arrays, ...), or ``add_triangles(mesh)``: an
        ``open3d.t.geometry.TriangleMesh`` or a legacy ``open3d.geometry.TriangleMesh``. The
        mesh is built on the device now; the scene over all meshes at the next query.
        """
        if triangle_indices is None:
            vertex_positions, triangle_indices = _mesh_arrays(vertex_positions)
        vertices = _host_array("vertex_positions", vertex_positions)
        faces = _host_array("triangle_indices", triangle_indices)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"vertex_positions must have shape (N, 3), got {vertices.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"triangle_indices must have shape (M, 3), got {faces.shape}")
        mesh = None
        if len(faces):
            # Open3D's uint32 indices: vkray takes them as they are.
            mesh = self.vkray_device.mesh(vertices, faces)
        with self._lock:
            geometry = self._geometries
            self._geometries += 1
            if mesh is not None:
                self._meshes.append((geometry, mesh))
        return geometry

    def _scene(self) -> Tuple[Scene, bool]:
        """The scene over every geometry added so far, and whether all its meshes are closed;
        built at the first query after an `add_triangles` (outside the lock: other threads'
        queries never wait for a build, and two first queries at once may both build)."""
        with self._lock:
            built, geometries, meshes = self._built, self._geometries, list(self._meshes)
        if built is not None and built[0] == geometries:
            return built[1], built[2]
        instances = [Instance(mesh, custom_index=geometry) for geometry, mesh in meshes]
        scene = self.vkray_device.scene(instances)
        closed = all(mesh.is_closed for _, mesh in meshes)
        with self._lock:
            if self._built is None or self._built[0] < geometries:
                self._built = (geometries, scene, closed)
        return scene, closed

    # --- tiers --------------------------------------------------------------------------------

    def _tier(self, default: Precision, points: bool = False) -> Precision:
        """The tier a query runs: this scene's, else the query's ``default``; "refined" is
        "exact" for point queries (they have no refined tier); "reference" for the tiers that
        need shaderFloat64 ("exact", and the GPU's point queries) once the device refused them."""
        tier = self.precision if self.precision is not None else default
        if points and tier == "refined":
            tier = "exact"
        if self._f64_refused and (tier == "exact" or points and tier == "fast"):
            return "reference"
        return tier

    def _run(self, default: Precision, query: Callable[[Precision], T], points: bool = False) -> T:
        """``query`` at its tier (`_tier`); where the device refuses it for want of shaderFloat64,
        "reference" (the same answers, on the CPU), from then on."""
        tier = self._tier(default, points)
        try:
            return query(tier)
        except UnsupportedError:
            if tier == "reference" or not (tier == "exact" or points):
                raise
            self._f64_refused = True
            return query("reference")

    def _contains_tier(self) -> Precision:
        """Occupancy and signs: exact always (the f32 tiers cannot decide parity)."""
        return "reference" if self.precision == "reference" or self._f64_refused else "exact"

    def _input(self, name: str, value: Any, width: int, query: str, cuda: bool = True) -> _Input:
        """``value`` as `_Input`; CUDA arrays stay on the GPU for the queries of `_CUDA_QUERIES`
        where ``cuda`` too allows (the fast tier)."""
        return _Input(name, value, width, cuda and query in _CUDA_QUERIES, self.results, self.device)

    # --- rays ---------------------------------------------------------------------------------

    def cast_rays(self, rays: Any, nthreads: int = 0) -> Dict[str, Any]:
        """The first hit of each ray: rays of shape (..., 6), ``[ox, oy, oz, dx, dy, dz]``
        (directions of any length: t is in units of it). Returns ``t_hit`` (float32, inf on a
        miss), ``geometry_ids`` and ``primitive_ids`` (uint32, `INVALID_ID` on a miss),
        ``primitive_uvs`` (float32 (..., 2): the barycentric weights of vertices 1 and 2) and
        ``primitive_normals`` (float32 (..., 3): the unit geometric normal); NaN on a miss (Open3D: 0)."""
        _threads(nthreads)
        # vkray's tiers other than "fast" read rays from the host.
        given = self._input("rays", rays, 6, "cast_rays", cuda=self._tier("fast") == "fast")
        scene, _ = self._scene()
        fields = ["t", "prim_id", "custom_index", "uv", "normal"]
        o, d = given.split()
        hits = self._run("fast", lambda tier: scene.intersect(o, d, outputs=fields, precision=tier))
        out = _Result(given.target, given.shape)
        return {
            "t_hit": out(hits.t, "float32"),
            "geometry_ids": out(hits.custom_index, "uint32"),
            "primitive_ids": out(hits.prim_id, "uint32"),
            "primitive_uvs": out(hits.uv, "float32", width=2),
            "primitive_normals": out(hits.normal, "float32", width=3),
        }

    def test_occlusions(self, rays: Any, tnear: float = 0.0, tfar: float = math.inf, nthreads: int = 0) -> Any:
        """bool (...): whether anything lies along each ray with ``tnear <= t <= tfar``."""
        _threads(nthreads)
        near, far = _scalar("tnear", tnear), _scalar("tfar", tfar)
        # A negative tnear moves the origins, on the host.
        cuda = near >= 0 and self._tier("fast") == "fast"
        given = self._input("rays", rays, 6, "test_occlusions", cuda=cuda)
        out = _Result(given.target, given.shape)
        if near > far:  # an empty interval holds nothing
            return out(np.zeros(given.shape, dtype=bool), "bool")
        o, d = given.split()
        if near < 0:
            # vkray's intervals start at 0: the origin moves back to where tnear is.
            o = np.asarray(o, dtype=np.float64) + near * np.asarray(d, dtype=np.float64)
            near, far = 0.0, far - near
        scene, _ = self._scene()
        hit = self._run("fast", lambda tier: scene.occluded(o, d, tmin=near, tmax=far, precision=tier))
        return out(hit, "bool")

    def count_intersections(self, rays: Any, nthreads: int = 0) -> Any:
        """int32 (...): how many times each ray crosses the scene's surfaces (each crossing once)."""
        _threads(nthreads)
        # vkray's tiers other than "fast" and "exact" read rays from the host.
        given = self._input("rays", rays, 6, "count_intersections", cuda=self._tier("exact") in ("fast", "exact"))
        scene, _ = self._scene()
        o, d = given.split()
        counts = self._run("exact", lambda tier: scene.count(o, d, precision=tier))
        return _Result(given.target, given.shape)(counts, "int32")

    def list_intersections(self, rays: Any, nthreads: int = 0) -> Dict[str, Any]:
        """Every hit of every ray, nearest first: ``ray_splits`` (uint32 (rays + 1,): ray i's hits
        are ``ray_splits[i]:ray_splits[i + 1]``), and per hit ``ray_ids``, ``geometry_ids``,
        ``primitive_ids`` (uint32), ``t_hit`` (float32) and ``primitive_uvs`` (float32 (hits, 2))."""
        _threads(nthreads)
        given = self._input("rays", rays, 6, "list_intersections")
        scene, _ = self._scene()
        o, d = given.split()
        fields = ["t", "prim_id", "custom_index", "uv"]
        hits = self._run("exact", lambda tier: scene.intersect_all(o, d, outputs=fields, precision=tier))
        out = _Result(given.target, given.shape)
        count = len(hits.ray_index)
        return {
            "ray_splits": out(hits.offsets, "uint32", shape=(len(hits.offsets),)),
            "ray_ids": out(hits.ray_index, "uint32", shape=(count,)),
            "geometry_ids": out(hits.custom_index, "uint32", shape=(count,)),
            "primitive_ids": out(hits.prim_id, "uint32", shape=(count,)),
            "primitive_uvs": out(hits.uv, "float32", shape=(count, 2)),
            "t_hit": out(hits.t, "float32", shape=(count,)),
        }

    # --- points -------------------------------------------------------------------------------

    def compute_closest_points(self, query_points: Any, nthreads: int = 0) -> Dict[str, Any]:
        """The nearest surface point to each point (..., 3): ``points`` (float32 (..., 3)),
        ``geometry_ids`` and ``primitive_ids`` (uint32), ``primitive_uvs`` (float32 (..., 2)) and
        ``primitive_normals`` (float32 (..., 3), the triangle's unit normal). A point equally near
        several triangles gets the one of the lowest (geometry id, triangle)."""
        _threads(nthreads)
        given = self._input("query_points", query_points, 3, "compute_closest_points")
        scene, _ = self._scene()
        fields = ["position", "prim_id", "custom_index", "uv", "normal"]
        p = given.array
        found = self._run("fast", lambda tier: scene.closest_points(p, outputs=fields, precision=tier), points=True)
        out = _Result(given.target, given.shape)
        return {
            "points": out(found.position, "float32", width=3),
            "geometry_ids": out(found.custom_index, "uint32"),
            "primitive_ids": out(found.prim_id, "uint32"),
            "primitive_uvs": out(found.uv, "float32", width=2),
            "primitive_normals": out(found.normal, "float32", width=3),
        }

    def compute_distance(self, query_points: Any, nthreads: int = 0) -> Any:
        """float32 (...): each point's distance to the nearest surface."""
        _threads(nthreads)
        return self._distances("compute_distance", query_points, signed=False)

    def compute_signed_distance(self, query_points: Any, nthreads: int = 0, nsamples: int = 1) -> Any:
        """float32 (...): `compute_distance`, negative inside (exact: see the module; ``nsamples``
        is checked and not needed)."""
        _threads(nthreads)
        _samples(nsamples)
        return self._distances("compute_signed_distance", query_points, signed=True)

    def _distances(self, method: str, query_points: Any, signed: bool) -> Any:
        """`compute_distance` or (``signed``) `compute_signed_distance` of checked arguments."""
        given = self._input("query_points", query_points, 3, method)
        scene, _ = self._scene()
        p = given.array
        query = scene.signed_distance if signed else scene.distance
        distance = self._run("fast", lambda tier: query(p, precision=tier), points=True)
        return _Result(given.target, given.shape)(distance, "float32")

    def compute_occupancy(self, query_points: Any, nthreads: int = 0, nsamples: int = 1) -> Any:
        """float32 (...): 1 where a point is inside (or on) a surface, 0 outside: exact, whatever
        ``nsamples`` (checked as Open3D checks it: odd and >= 1)."""
        _threads(nthreads)
        _samples(nsamples)
        given = self._input("query_points", query_points, 3, "compute_occupancy")
        scene, closed = self._scene()
        p = given.array
        method = "parity" if closed else "winding"
        try:
            inside = scene.contains(p, precision=self._contains_tier(), method=method)
        except UnsupportedError:
            self._f64_refused = True
            inside = scene.contains(p, precision="reference", method=method)
        return _Result(given.target, given.shape)(inside, "float32")

    # --- cameras ------------------------------------------------------------------------------

    @classmethod
    def create_rays_pinhole(cls, *args: Any, **kwargs: Any) -> Any:
        """Rays of a pinhole camera, float32 (height_px, width_px, 6), in two forms (as Open3D's):

        ``create_rays_pinhole(intrinsic_matrix, extrinsic_matrix, width_px, height_px)``: a 3×3
        intrinsic matrix and the 4×4 world-to-camera transform; or
        ``create_rays_pinhole(fov_deg, center, eye, up, width_px, height_px)``: the horizontal
        field of view in degrees, the point looked at, the camera's position and its up vector.

        Pixel (row y, column x) looks through image point (x + 0.5, y + 0.5); directions are not
        normalized (their camera-space z is 1). Open3D tensors in give an Open3D tensor on their
        device; other inputs numpy (or an Open3D tensor where the class's `results` is "open3d").
        """
        names: Tuple[str, ...] = ("intrinsic_matrix", "extrinsic_matrix", "width_px", "height_px")
        if len(args) + len(kwargs) == 6 or "fov_deg" in kwargs:
            names = ("fov_deg", "center", "eye", "up", "width_px", "height_px")
        bound = _bind("create_rays_pinhole", names, args, kwargs)
        width, height = _pixels(bound["width_px"], "width_px"), _pixels(bound["height_px"], "height_px")
        tensors = [value for value in bound.values() if _is_tensor(value)]
        target = str(tensors[0].device) if tensors else ("CPU:0" if cls.results == "open3d" else None)
        if "fov_deg" in bound:
            fov = _scalar("fov_deg", bound["fov_deg"])
            if not 0 < fov < 180:
                raise ValueError(f"fov_deg must be in (0, 180), got {fov}")
            center, eye, up = (_vector(name, bound[name]) for name in ("center", "eye", "up"))
            intrinsic, extrinsic = _look_at(fov, center, eye, up, width, height)
        else:
            intrinsic = _matrix("intrinsic_matrix", bound["intrinsic_matrix"], (3, 3))
            extrinsic = _matrix("extrinsic_matrix", bound["extrinsic_matrix"], (4, 4))
        rays = _pinhole_rays(intrinsic, extrinsic, width, height)
        return _Result(target, (height, width))(rays, "float32", shape=(height, width, 6))

    def __repr__(self) -> str:
        return f"<vkray.open3d.RaycastingScene {self._geometries} geometries on {self.vkray_device.name!r}>"


class _Open3DResults(RaycastingScene):
    """`RaycastingScene` giving Open3D tensors for every input, as Open3D's own class does: what
    `enable` puts in Open3D's place."""

    results: Results = "open3d"


_Open3DResults.__name__ = _Open3DResults.__qualname__ = "RaycastingScene"


# --- arrays ------------------------------------------------------------------------------------


def _tensor_from_dlpack(core: Any, value: Any) -> Any:
    """An Open3D tensor over ``value``'s memory (no copy): Open3D >= 0.20 takes any object that
    speaks DLPack, 0.19 only the capsule its ``__dlpack__`` gives."""
    try:
        return core.Tensor.from_dlpack(value)
    except TypeError:
        return core.Tensor.from_dlpack(value.__dlpack__())


def _host_array(name: str, value: Any) -> NDArray[Any]:
    """A mesh's array in host memory (Open3D tensors on a GPU are copied: meshes build from the
    host)."""
    if _dlpack_on_cuda(value):
        return _host(name, value)
    if _is_tensor(value):
        return np.asarray(value.numpy())
    if hasattr(value, "__dlpack__") and not isinstance(value, np.ndarray):
        return np.from_dlpack(value)
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be array-like: {exc}") from None


def _mesh_arrays(mesh: Any) -> Tuple[Any, Any]:
    """(vertex positions, triangle indices) of an Open3D mesh, tensor-based or legacy."""
    vertex, triangle = getattr(mesh, "vertex", None), getattr(mesh, "triangle", None)
    if vertex is not None and triangle is not None:  # open3d.t.geometry.TriangleMesh
        if "positions" not in vertex or "indices" not in triangle:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
        return vertex["positions"], triangle["indices"]
    if hasattr(mesh, "vertices") and hasattr(mesh, "triangles"):  # open3d.geometry.TriangleMesh
        return np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    raise TypeError(
        "add_triangles takes (vertex_positions, triangle_indices) or an Open3D TriangleMesh, got "
        f"{type(mesh).__name__}"
    )


def _bind(function: str, names: Sequence[str], args: Sequence[Any], kwargs: Dict[str, Any]) -> Dict[str, Any]:
    """Positional and keyword arguments bound to ``names`` (all required)."""
    if len(args) > len(names):
        raise TypeError(f"{function}() takes {len(names)} arguments ({', '.join(names)}), got {len(args)}")
    bound = dict(zip(names, args))
    for key, value in kwargs.items():
        if key not in names:
            raise TypeError(f"{function}() got an unexpected keyword argument {key!r} (takes {', '.join(names)})")
        if key in bound:
            raise TypeError(f"{function}() got two values for {key!r}")
        bound[key] = value
    missing = [name for name in names if name not in bound]
    if missing:
        raise TypeError(f"{function}() is missing {', '.join(missing)} (takes {', '.join(names)})")
    return bound


def _pixels(value: object, name: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {int(value)}")
    return int(value)


def _matrix(name: str, value: Any, shape: Tuple[int, int]) -> NDArray[np.float64]:
    array = np.asarray(_host_array(name, value), dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} must be finite")
    return array


def _vector(name: str, value: Any) -> NDArray[np.float64]:
    array = np.asarray(_host_array(name, value), dtype=np.float64).reshape(-1)
    if array.shape != (3,) or not np.isfinite(array).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {array.tolist()}")
    return array


def _look_at(
    fov_deg: float,
    center: NDArray[np.float64],
    eye: NDArray[np.float64],
    up: NDArray[np.float64],
    width: int,
    height: int,
) -> Tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The intrinsic and world-to-camera matrices of a camera at ``eye`` looking at ``center``:
    camera z forward, x along ``up × forward``, y along ``forward × x`` (Open3D's frame: image
    rows run along ``up``), and a
    focal length that spans ``fov_deg`` across the image's width."""
    forward = center - eye
    if not np.linalg.norm(forward) > 0:
        raise ValueError("center and eye must differ")
    forward = forward / np.linalg.norm(forward)
    right = np.cross(up, forward)
    if not np.linalg.norm(right) > 0:
        raise ValueError("up must not be parallel to the viewing direction (center - eye)")
    right = right / np.linalg.norm(right)
    rotation = np.stack([right, np.cross(forward, right), forward])  # world to camera
    extrinsic = np.eye(4)
    extrinsic[:3, :3] = rotation
    extrinsic[:3, 3] = -rotation @ eye
    focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    intrinsic = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return intrinsic, extrinsic


def _pinhole_rays(
    intrinsic: NDArray[np.float64], extrinsic: NDArray[np.float64], width: int, height: int
) -> NDArray[np.float32]:
    """(height, width, 6) float32 rays: from the camera's centre through each pixel's centre."""
    try:
        inverse = np.linalg.inv(intrinsic)
    except np.linalg.LinAlgError:
        raise ValueError("intrinsic_matrix is singular") from None
    rotation, translation = extrinsic[:3, :3], extrinsic[:3, 3]
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    pixels = np.stack([xs, ys, np.ones_like(xs)], axis=-1)
    camera = pixels @ inverse.T
    rays = np.empty((height, width, 6), dtype=np.float32)
    rays[..., 3:] = camera @ rotation  # rotation.T @ each camera direction
    rays[..., :3] = -rotation.T @ translation
    return rays


# --- putting it in Open3D's place ---------------------------------------------------------------

_originals: Dict[str, Any] = {}


def _geometry_modules(o3d: Any) -> Dict[str, Any]:
    """The modules through which code reaches Open3D's class (``open3d.t.geometry`` and the
    pybind module behind it, where they differ)."""
    modules = {"open3d.t.geometry": o3d.t.geometry}
    pybind = getattr(getattr(getattr(o3d, "pybind", None), "t", None), "geometry", None)
    if pybind is not None and pybind is not o3d.t.geometry:
        modules["open3d.pybind.t.geometry"] = pybind
    return modules


def enable() -> None:
    """Puts vkray's `RaycastingScene` in place of ``open3d.t.geometry.RaycastingScene``, for code
    that cannot be edited: scenes made from then on are vkray's, returning Open3D tensors for every
    input as Open3D's class does. `disable` gives Open3D's class back."""
    o3d = _open3d()
    with _lock:
        for name, module in _geometry_modules(o3d).items():
            _originals.setdefault(name, module.RaycastingScene)
            module.RaycastingScene = _Open3DResults


def disable() -> None:
    """Gives Open3D its own ``RaycastingScene`` back (scenes already made keep their class)."""
    o3d = sys.modules.get("open3d")
    if o3d is None:
        return
    with _lock:
        for name, module in _geometry_modules(o3d).items():
            if name in _originals:
                module.RaycastingScene = _originals.pop(name)


def enabled() -> bool:
    """Whether `enable` has put vkray's class in Open3D's place."""
    return bool(_originals)

