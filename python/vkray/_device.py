"""One device and what lives on it: `Device` (a Vulkan device or the CPU engine: `devices()` lists them), the
`Mesh`es it builds, their `Instance`s, and the `Scene`s over them, which answer the queries of
`SceneLike` by running them on the device (or its CPU tiers)."""

from __future__ import annotations

import importlib.util
import os
import threading
from collections import abc
from dataclasses import dataclass, replace
from typing import Any, Callable, Dict, Iterable, List, Literal, Optional, Protocol, Tuple, Union, cast

import numpy as np

from . import _arrays, _core, _pictures, _progress
from ._options import HIT_FIELDS, Backend, Build, Cull, Precision, VertexFormat, check_outputs
from ._queries import PointQuery, Query, RayQuery, SceneLike
from ._results import AllHits, Closest, Hits, counts_of, out_arrays, ray_index_of


class MeshObject(Protocol):
    """Another library's triangle mesh, as `Device.mesh` and `Device.scene` take it: ``vertices``
    (V, 3) and ``faces`` (F, 3) array-likes (a `trimesh.Trimesh`)."""

    @property
    def vertices(self) -> Any: ...

    @property
    def faces(self) -> Any: ...


@dataclass(frozen=True)
class DeviceInfo:
    """A usable device, as `devices()` lists it: a Vulkan device (``engine == "vulkan"``) or the
    CPU engine (``engine == "cpu"``, ``device_type == "cpu"``). ``index`` is its place in
    `devices()`, which `Device` takes."""

    index: int
    name: str
    device_type: str
    is_software: bool
    api_version: str
    driver: str
    ray_query: bool
    ray_tracing_pipeline: bool
    shader_float64: bool
    engine: str = "vulkan"


def embree_places() -> List[str]:
    """Folders the CPU engine loads Embree from, first match wins: ``VKRAY_EMBREE_PATH``, the
    copy vkray's wheel carries, then an installed embreex's (a source checkout's tests)."""
    here = os.path.dirname(os.path.abspath(__file__))
    places = [os.environ["VKRAY_EMBREE_PATH"]] if os.environ.get("VKRAY_EMBREE_PATH") else []
    places.append(os.path.join(here, "_embree"))
    embreex = importlib.util.find_spec("embreex")  # found, not imported
    if embreex is not None and embreex.origin:
        places.append(os.path.join(os.path.dirname(os.path.dirname(embreex.origin)), "embreex.libs"))
    return places


_CPU_ENGINE_INFO: List[Optional[Dict[str, Any]]] = []


def _cpu_engine_info() -> Optional[Dict[str, Any]]:
    """The CPU engine's `devices()` entry, or None where Embree cannot be loaded (found once a
    process: two threads asking first both look, and the first answer stays)."""
    if not _CPU_ENGINE_INFO:
        try:
            info: Optional[Dict[str, Any]] = dict(_core.Device("cpu", None, False, embree_places()).info)
        except _core.NoDeviceError:
            info = None
        _CPU_ENGINE_INFO.append(info)
    return _CPU_ENGINE_INFO[0]


def _vulkan_infos() -> List[Dict[str, Any]]:
    """The Vulkan devices, as the core lists them (none where Vulkan cannot be loaded)."""
    try:
        return [dict(info) for info in _core.devices()]
    except _core.NoDeviceError:
        return []


def _listed() -> List[Tuple[DeviceInfo, str]]:
    """`devices()` with the selector the core opens each by."""
    vulkan = [(DeviceInfo(**info), str(info["index"])) for info in _vulkan_infos()]
    cpu = _cpu_engine_info()
    gpus = [entry for entry in vulkan if not entry[0].is_software]
    software = [entry for entry in vulkan if entry[0].is_software]
    ordered = gpus + ([(DeviceInfo(**cpu), "cpu")] if cpu is not None else []) + software
    return [(replace(info, index=k), selector) for k, (info, selector) in enumerate(ordered)]


def devices() -> List[DeviceInfo]:
    """The devices vkray can use, best first: ray-tracing GPUs, then the CPU engine (Embree on
    every core, carried by the wheel: always there), then software Vulkan devices (Mesa's
    lavapipe), which `Device()` takes only when named.

    A Vulkan device qualifies with Vulkan 1.2, acceleration structures, buffer device addresses,
    64-bit shader integers, and ray queries or a ray-tracing pipeline.
    """
    return [info for info, _ in _listed()]


def _selector(device: Union[int, str, None], vulkan: bool = False) -> Optional[str]:
    """The core's selector for `Device`'s ``device``: an index or name among `devices()`, or
    (None) ``VKRAY_DEVICE``, else the best device but a software one; the best Vulkan device
    where the caller asked for a Vulkan feature (`vulkan`: a backend, the validation layer)."""
    if device is None:
        device = os.environ.get("VKRAY_DEVICE") or None
    if device is None:
        listed = [entry for entry in _listed() if not vulkan or entry[0].engine == "vulkan"]
        best: List[Optional[str]] = [selector for info, selector in listed if not info.is_software]
        anything: List[Optional[str]] = [selector for _, selector in listed]
        return (best or anything or [None])[0]
    listed = _listed()
    text = str(device).strip()
    if text.lower() == "cpu":
        return "cpu"
    if text.lstrip("-").isdigit():
        k = int(text)
        if not 0 <= k < len(listed):
            raise _core.NoDeviceError(f"device index {k} is out of range: {len(listed)} devices (vkray.devices())")
        return listed[k][1]
    named = [selector for info, selector in listed if text.lower() in info.name.lower()]
    return named[0] if named else text


class Device:
    """A Vulkan device that builds acceleration structures and traces rays.

    Parameters
    ----------
    device:
        Index into `devices()` or a case-insensitive substring of the device name. ``None`` takes
        the ``VKRAY_DEVICE`` environment variable, else the best device (a GPU before lavapipe).
    backend:
        ``"ray_query"`` (compute shaders with ray queries) or ``"pipeline"`` (a ray-tracing
        pipeline). ``None`` takes ``VKRAY_BACKEND``, else ray queries where the device has them.
    validation:
        Enable the Khronos validation layer; every message it reports becomes a
        `vkray.ValidationError`. ``VKRAY_VALIDATION=1`` turns it on as well.
    host_threads:
        Threads of this device's own for its queries' host passes (see `host_threads`); ``None``
        (default): the process's shared pool, on every core.
    """

    def __init__(
        self,
        device: Union[int, str, None] = None,
        backend: Optional[Backend] = None,
        *,
        validation: bool = False,
        host_threads: Optional[int] = None,
    ) -> None:
        if (
            device is not None
            and not isinstance(device, (int, np.integer, str))
            or isinstance(device, (bool, np.bool_))
        ):
            raise TypeError(f"device must be an index, a name or None, got {device!r}")
        if host_threads is not None:  # checked before the device is opened
            host_threads = _arrays.integer("host_threads", host_threads, 1, 4096)
        asks_vulkan = backend is not None or bool(validation) or bool(os.environ.get("VKRAY_BACKEND"))
        selector = _selector(None if device is None else str(device), vulkan=asks_vulkan)
        # The core checks backend (and reads VKRAY_BACKEND and VKRAY_VALIDATION).
        self._core = _core.Device(selector, backend, bool(validation), embree_places())
        info = dict(self._core.info)
        listed = [d for d in devices() if (d.engine, d.name) == (info["engine"], info["name"])]
        self.info = DeviceInfo(**{**info, "index": listed[0].index if listed else info["index"]})
        if host_threads is not None:
            self.host_threads = host_threads

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def backend(self) -> Union[Backend, Literal["cpu"]]:
        """``"ray_query"`` or ``"pipeline"``: how this Vulkan device traces; ``"cpu"`` for the
        CPU engine."""
        return self._core.backend

    @property
    def engine(self) -> str:
        """``"vulkan"`` or ``"cpu"`` (Embree on the host's cores)."""
        return self.info.engine

    @property
    def is_software(self) -> bool:
        """True for CPU implementations such as Mesa's lavapipe."""
        return self.info.is_software

    @property
    def validation(self) -> bool:
        return self._core.validation

    @property
    def limits(self) -> Dict[str, Any]:
        """The device limits vkray queried and obeys (scratch alignment, dispatch sizes, SBT...)."""
        return dict(self._core.limits)

    @property
    def last_trace_profile(self) -> Dict[str, Optional[float]]:
        """Where this device's last trace spent its time, in seconds.

        Host clock: ``pack`` (checking rays and converting them into staging), ``submit``,
        ``wait`` (GPU time not hidden behind packing), ``unpack`` (copying hits out), ``total``.
        A chunk's hits are copied out while the next chunk's rays are packed, so ``pack`` and
        ``unpack`` (each side's own time) may add up to more than the time they took together.
        GPU timestamps, summed over chunks (``None`` where the queue has no timestamps):
        ``gpu_upload`` (staging → device copy), ``gpu_trace`` (the trace alone), ``gpu_readback``.
        ``host_f64``: the host's f64 work (refined and reference tiers). ``store``: all hits on
        the GPU, the storing pass (the host clock's phases are the counting pass's; ``gpu_*``,
        ``chunks`` and ``total`` cover both). ``order``: ``contains`` in grid order, the host's sort of
        the points and the scatter of the answers back (outside ``total``). Plus ``rays``,
        ``chunks``, ``host_threads`` (the threads its host passes ran on: `host_threads`, or the
        shared pool's) and ``ray_bytes`` (the rays the host packed for the GPU, in bytes: 32 a
        ray, 24 for float32 rays of one interval, 12 for those from one origin, each chunk of the
        leaner two with 32 more; 64 a ray in the exact tier), and ``gpu_columns`` (all hits: the
        chunks whose answer columns the GPU wrote; the host writes those of a chunk whose lists
        it must sort, and of answers asking position, normal or custom_index)."""
        return dict(self._core.last_trace_profile)

    @property
    def idle_memory(self) -> Dict[str, int]:
        """The staging memory this device keeps between queries, so that the next query need not
        allocate it (host-visible buffers for rays and hits, their device copies, packing
        scratch, CUDA leases): ``bytes`` held now, ``kept`` (how many sets of buffers), and
        ``made`` (how many its queries had to allocate so far, because none was idle);
        ``pinned_bytes``: page-locked host memory kept for CUDA arrays that queries copy through
        the host (up to 512 MiB of blocks and 64 MiB of buffers; 0 where CUDA was never used).

        A device keeps as many as its queries used at once (several threads querying it at the
        same time each hold their own), at least two queries' worth and up to eight: a query's
        staging takes two chunks (`chunk_rays`) of 76 bytes a ray, twice over on discrete GPUs
        (1.3 GB on an H200). An allocation that runs out of memory frees them all and tries
        again; `release_idle_memory` frees them at once."""
        return dict(self._core.idle_memory)

    def release_idle_memory(self) -> None:
        """Frees the staging memory kept between queries (`idle_memory`), e.g. after a burst of
        queries from many threads, and the page-locked host memory that CUDA arrays of queries
        without a GPU-resident path crossed through; later queries allocate what they need again."""
        self._core.release_idle_memory()

    @property
    def cuda_device(self) -> Optional[int]:
        """CUDA's index of this GPU (the device id of its CUDA arrays in DLPack, ``cuda:N`` in
        torch), or None where it is no CUDA device sharing memory with Vulkan: CUDA arrays of this
        index are the rays this device traces without leaving the GPU."""
        return self._core.cuda_device

    @property
    def chunk_rays(self) -> int:
        """The most rays traced per submission (staging memory holds two chunks, 72 bytes a ray
        each). Chunks are smaller where a query runs slowly: each is sized by the rate the one
        before it ran at to last a fraction of a second, so that Ctrl-C is heard within one."""
        return self._core.chunk_rays

    @chunk_rays.setter
    def chunk_rays(self, rays: int) -> None:
        self._core.chunk_rays = _arrays.integer("chunk_rays", rays, 1, _arrays.U64_MAX)

    @property
    def host_threads(self) -> Optional[int]:
        """How many threads of its own this device's queries use for their host passes (checking
        and packing rays, copying hits into the result arrays), or ``None``: the process's
        shared pool, on every core (the default).

        Devices that trace at the same time each want cores of their own: in one shared pool
        their passes queue behind each other, while each GPU's link could take its own (a
        `DeviceGroup` gives every device it opens an equal share of the cores). Setting it
        starts the threads; queries already under way finish on the threads they started with.
        """
        return self._core.host_threads

    @host_threads.setter
    def host_threads(self, threads: Optional[int]) -> None:
        checked = None if threads is None else _arrays.integer("host_threads", threads, 1, 4096)
        self._core.host_threads = checked

    def mesh(
        self,
        vertices: Any,
        faces: Any = None,
        *,
        build: Build = "fast_trace",
        allow_update: bool = False,
        compact: bool = False,
        vertex_format: VertexFormat = "float32",
        opacity: Any = None,
    ) -> Mesh:
        """Uploads a triangle mesh and builds its bottom-level acceleration structure.

        vertices: (V, 3) float32/float64 (other real dtypes become float64); any memory layout.
        Or a mesh object with ``.vertices`` and ``.faces`` (a `trimesh.Trimesh`), faces omitted.
        faces: (F, 3) int32/int64/uint32/uint16 corner indices into vertices (uint16 and uint32
        reach the device without widening).
        build: ``"fast_trace"`` (default), ``"fast_build"`` or ``"low_memory"``.
        allow_update: the mesh may be refitted later with `Mesh.update`.
        compact: compact the structure after building (smaller, built slower).
        vertex_format: ``"float32"`` (default; 12 bytes a vertex), or ``"float16"`` / ``"snorm16"``
        (8 bytes: the vertices re-centred and scaled into [-1, 1], then quantized). Every tier then
        traces the quantized surface; docs/benchmarks.md measures the memory saved and the
        accuracy lost. ``Device.limits["vertex_formats"]`` lists what the device accepts.
        opacity: ``None`` (default: opaque), one float, or one float per triangle, each in [0, 1]:
        1 blocks rays, 0 cuts the triangle out; in between, `Scene.intersect` and the other
        queries let a ray through where the opacity is below their ``opacity_threshold`` (0.5 by
        default), and `Scene.transmittance` multiplies ``1 - opacity`` over every crossing. A mesh
        whose triangles are all opaque keeps Vulkan's OPAQUE flag and never runs an any-hit stage;
        translucent meshes make their scenes run one (see `Scene.explain`).
        """
        if faces is None:
            if not (hasattr(vertices, "vertices") and hasattr(vertices, "faces")):
                raise TypeError("mesh() needs faces, or a mesh object with .vertices and .faces")
            vertices, faces = vertices.vertices, vertices.faces
        _arrays.check_mesh_size(vertices, faces, int(self._core.limits["max_primitive_count"]))
        v = _arrays.points("vertices", vertices)
        f = _arrays.faces(faces)
        alpha = opacity_per_triangle(opacity, len(f))
        core = self._core.mesh(v, f, build, bool(allow_update), bool(compact), vertex_format, alpha)
        return Mesh(self, core, v, f, alpha)

    def spheres(self, centers: Any, radii: Any, *, build: Build = "fast_trace", compact: bool = False) -> Mesh:
        """A set of spheres as one BLAS of boxes, whose spheres a shader intersects (a numerically
        careful quadratic: Haines et al., Ray Tracing Gems ch. 7), in both backends.

        centers: (N, 3) floats; radii: one positive float or N of them. The result is a `Mesh`
        (``kind == "spheres"``) that scenes take like any other, mixed with triangle meshes; hits
        give the sphere's index as ``prim_id`` and the outward unit ``normal``; ``uv`` is NaN.
        Scenes holding spheres trace at ``precision="fast"`` only (``position`` of a sphere hit is
        ``origin + t * direction`` in float64), and the queries' ``cull`` does not apply to spheres.
        """
        c = _arrays.points("centers", centers)
        r = _arrays.real_coordinates("radii", radii)
        if r.ndim != 0 and r.shape != (len(c),):
            raise ValueError(f"radii must be one value or {len(c)} values, got shape {r.shape}")
        radius = float(r) if r.ndim == 0 else np.ascontiguousarray(r, dtype=np.float64)
        core = self._core.spheres(c, radius, build, bool(compact))
        return Mesh(self, core, c, None, radii=np.asarray(radius, dtype=np.float64))

    def mesh_from_parts(
        self,
        parts: Iterable[Tuple[Any, ...]],
        *,
        build: Build = "fast_trace",
        allow_update: bool = False,
        compact: bool = False,
        vertex_format: VertexFormat = "float32",
        opacity: Optional[Iterable[Any]] = None,
    ) -> Mesh:
        """One mesh of several parts, each a geometry of one BLAS: ``parts`` are ``(vertices,
        faces)`` or ``(vertices, faces, transform)`` (a 3×4 or 4×4 affine matrix as `Instance`
        takes it, applied to that part's vertices in float64 before anything becomes float32).

        ``Hits.geometry_id`` says which part was hit and ``Hits.prim_id`` counts triangles within
        that part. The mesh's ``vertices`` and ``faces`` are all parts' (transformed) in order.
        Refitting (`Mesh.update`) is for single-part meshes. opacity: ``None`` or one entry per
        part, each as `Device.mesh` takes it (``None``, a float, or one float per triangle).
        """
        arrays = []
        for k, part in enumerate(parts):
            if not isinstance(part, (tuple, list)) or len(part) not in (2, 3):
                raise TypeError(f"part {k} must be (vertices, faces) or (vertices, faces, transform)")
            _arrays.check_mesh_size(part[0], part[1], int(self._core.limits["max_primitive_count"]))
            v = _arrays.points("vertices", part[0])
            if len(part) == 3 and part[2] is not None:
                # Rejected as `Instance` transforms are: the Python layer applies this one itself.
                m = _arrays.affine(_arrays.transform(part[2]), f"part {k}")
                v = np.ascontiguousarray(v.astype(np.float64) @ m[:3, :3].T + m[:3, 3])
            arrays.append((v, _arrays.faces(part[1])))
        if not arrays:
            raise ValueError("a mesh needs at least one part")
        alpha = None
        if opacity is not None:
            per_part = list(opacity)
            if len(per_part) != len(arrays):
                raise ValueError(f"opacity has {len(per_part)} entries for {len(arrays)} parts")
            alphas = [
                opacity_per_triangle(a, len(f), f"opacity[{k}]") for k, (a, (_, f)) in enumerate(zip(per_part, arrays))
            ]
            if any(a is not None for a in alphas):
                alpha = np.concatenate(
                    [np.ones(len(f), np.float32) if a is None else a for a, (_, f) in zip(alphas, arrays)]
                )
        core = self._core.mesh_parts(arrays, build, bool(allow_update), bool(compact), vertex_format, alpha)
        first = np.cumsum([0] + [len(v) for v, _ in arrays[:-1]])
        vertices = np.concatenate([v.astype(np.float64) for v, _ in arrays])
        faces = np.concatenate([f.astype(np.int64) + o for (_, f), o in zip(arrays, first)])
        return Mesh(self, core, vertices, faces, alpha)

    def meshes(
        self,
        items: Iterable[Tuple[Any, Any]],
        *,
        build: Build = "fast_trace",
        allow_update: bool = False,
        compact: bool = False,
        budget_bytes: Optional[int] = None,
        vertex_format: VertexFormat = "float32",
        progress: bool = False,
    ) -> List[Mesh]:
        """Builds many meshes at once: ``items`` are (vertices, faces) pairs as `mesh` takes them.

        The builds go to the device in as few submissions as ``budget_bytes`` of build scratch
        memory allow (one scratch buffer, reused by every batch at aligned offsets; unbounded by
        default: one submission). With ``compact=True`` each batch is compacted before the next is
        built, so the uncompacted structures never all exist at once. ``Mesh.stats["batch"]`` tells
        which submission built a mesh, ``build_seconds`` that batch's time. A mesh whose own build
        needs more scratch than the budget raises ValueError naming it. ``progress=True`` shows a
        bar of the meshes built, batch by batch (Ctrl-C stops between batches).
        """
        budget = None if budget_bytes is None else _arrays.integer("budget_bytes", budget_bytes, 1, _arrays.U64_MAX)
        arrays = []
        for k, item in enumerate(items):
            try:
                vertices, faces = item
            except (TypeError, ValueError):
                raise TypeError(f"meshes item {k} must be a (vertices, faces) pair") from None
            _arrays.check_mesh_size(vertices, faces, int(self._core.limits["max_primitive_count"]))
            arrays.append((_arrays.points("vertices", vertices), _arrays.faces(faces)))
        cores = _progress.call(
            progress,
            "meshes",
            lambda bar: self._core.meshes(arrays, build, bool(allow_update), bool(compact), budget, vertex_format, bar),
            unit="mesh",
        )
        return [Mesh(self, core, v, f) for core, (v, f) in zip(cores, arrays)]

    def scene(
        self,
        items: Union[Mesh, Instance, MeshObject, Iterable[Union[Mesh, Instance, MeshObject]]],
        *,
        build: Build = "fast_build",
        allow_update: bool = False,
        compact: bool = False,
    ) -> Scene:
        """Builds a top-level acceleration structure over meshes and instances.

        A bare `Mesh` is an instance with the identity transform; so is a mesh object with
        ``.vertices`` and ``.faces`` (a `trimesh.Trimesh`), which `mesh` uploads first (with its
        defaults). Instance ids (``Hits.instance_id``) follow the order of `items`.
        """
        if isinstance(items, (Mesh, Instance)) or is_mesh_object(items):
            items = [cast(Union[Mesh, Instance, MeshObject], items)]
        if not isinstance(items, abc.Iterable):
            raise TypeError(f"scene() takes a Mesh, an Instance or a list of them, got {type(items).__name__}")
        instances = []
        for i, item in enumerate(items):
            if is_mesh_object(item):
                item = self.mesh(item)
            if isinstance(item, Mesh):
                item = Instance(item)
            if not isinstance(item, Instance):
                raise TypeError(
                    f"scene item {i} must be a Mesh, an Instance or a mesh object with .vertices and .faces, "
                    f"got {type(item).__name__}"
                )
            if item.mesh.device is not self:
                raise ValueError(f"scene item {i} uses a mesh built on another Device")
            instances.append(item)
        core = self._core.scene(
            [(x.mesh._core, x.transform, x.custom_index, x.mask, x._flags()) for x in instances],
            build,
            bool(allow_update),
            bool(compact),
        )
        return Scene(self, core, instances)

    def __repr__(self) -> str:
        return f"<vkray.Device {self.name!r} backend={self.backend!r} type={self.info.device_type!r}>"

    def _repr_html_(self) -> str:
        """A table for notebooks: the device, its backend, features and limits."""
        return _pictures.device_html(self)


_default_lock = threading.Lock()
_default: Optional[Device] = None


def default_device() -> Device:
    """The process's shared device: ``vkray.Device()`` (the best device, or ``VKRAY_DEVICE``'s),
    opened on first use and kept. vkray.trimesh's intersectors and vkray.open3d's scenes use it
    unless given a device."""
    global _default
    with _default_lock:
        if _default is not None:
            return _default
    # Opened outside the lock (opening a device releases the GIL and waits on the driver): two
    # first calls at once may both open one; the first to return is kept, the other dropped.
    device = Device()
    with _default_lock:
        if _default is None:
            _default = device
        return _default


def is_mesh_object(item: Any) -> bool:
    """Whether `item` is another library's triangle mesh (``.vertices`` and ``.faces``: trimesh's
    `Trimesh`), which `Device.mesh` takes as it is."""
    return not isinstance(item, (Mesh, Instance)) and hasattr(item, "vertices") and hasattr(item, "faces")


class Mesh:
    """Triangles on a device with their bottom-level acceleration structure (BLAS).

    Made by `Device.mesh`. Keeps its device buffers alive as long as any scene uses it.
    """

    def __init__(
        self,
        device: Device,
        core: _core.Mesh,
        vertices: np.ndarray,
        faces: Optional[np.ndarray],
        opacity: Optional[np.ndarray] = None,
        radii: Optional[np.ndarray] = None,
    ) -> None:
        self.device = device
        self._core = core
        self.vertices = vertices
        #: The triangles' corner indices; ``None`` for spheres.
        self.faces = faces
        #: float32 opacity per triangle, or ``None`` where every triangle is opaque.
        self.opacity = None if opacity is None or bool((opacity >= 1).all()) else opacity
        #: Spheres (`Device.spheres`): their radii, one for all or one a sphere; ``None`` for triangles.
        self.radii = radii
        self._closed: Optional[bool] = None

    @property
    def vertex_count(self) -> int:
        return self._core.vertex_count

    @property
    def triangle_count(self) -> int:
        return self._core.triangle_count

    @property
    def kind(self) -> str:
        """``"triangles"``, or ``"spheres"`` for `Device.spheres`."""
        return self._core.kind

    @property
    def part_count(self) -> int:
        """Geometries in the BLAS: 1, or the parts of `Device.mesh_from_parts`."""
        return self._core.part_count

    @property
    def stats(self) -> Dict[str, Any]:
        """Build figures: ``bytes`` (size now), ``built_bytes`` (before compaction),
        ``scratch_bytes``, ``update_scratch_bytes``, ``build_seconds``, ``update_seconds`` (the
        last `update`), and the options built with."""
        return dict(self._core.stats)

    def update(self, vertices: Any) -> None:
        """Moves the vertices and refits the BLAS in place instead of rebuilding it (the mesh
        must be built with ``allow_update=True``). Same vertex count, same faces; a refitted
        BVH traces a little slower than a fresh one as the shape drifts from the one it was built
        for. Scenes holding the mesh must be `Scene.update`d before their next query (they raise
        until then). Not to be called while another thread queries a scene holding this mesh."""
        array = _arrays.points("vertices", vertices)
        self._core.update(array)
        self.vertices = array

    @property
    def is_closed(self) -> bool:
        """Whether the triangles close a volume consistently: every edge is shared by exactly two
        triangles that run along it in opposite directions (each directed edge ``(a, b)`` once,
        and ``(b, a)`` once). Only then does the parity of crossings say inside or outside
        (`Scene.contains`). Computed once (a mesh's topology never changes). A sphere set is
        closed."""
        if self._closed is None:
            self._closed = self.kind == "spheres" or _closed(np.asarray(self.faces))
        return self._closed

    @property
    def closedness_known(self) -> bool:
        """Whether `is_closed` has been computed (a summary shows it then, as it costs a pass over
        the faces the first time)."""
        return self._closed is not None

    def __repr__(self) -> str:
        if self.kind == "spheres":
            return f"<vkray.Mesh of {self.vertex_count} spheres>"
        return f"<vkray.Mesh {self.vertex_count} vertices, {self.triangle_count} triangles>"

    def _repr_html_(self) -> str:
        """A table for notebooks: counts, bounds, bytes, build flags and device."""
        return _pictures.mesh_html(self)


_MAX_CUSTOM_INDEX = (1 << 24) - 1


class Instance:
    """A mesh placed in a scene.

    transform: 4×4 or 3×4 affine matrix, row-major, acting on column vectors (``M @ [x, y, z, 1]``,
    the way numpy code writes it); ``None`` is the identity.
    custom_index: 24-bit value returned as ``Hits.custom_index`` for hits on this instance.
    mask: 8-bit visibility mask: a ray sees the instance when ``instance mask & ray mask != 0``
    (rays' masks default to 0xFF: an instance with mask 0 is never hit).
    cull_disable: queries' ``cull=`` does not apply to this instance.
    flip_facing: swap front and back for ``cull=``. Front is the side the hit's ``normal`` points
    to (so a mirroring transform, which flips the normal, flips facing with it).
    opaque: ``True`` forces opaque, ``False`` non-opaque (traversal then hands its triangles to the
    shader, which accepts them: vkray has no any-hit programs yet), ``None`` keeps the geometry's
    (opaque).
    """

    def __init__(
        self,
        mesh: Mesh,
        transform: Any = None,
        *,
        custom_index: int = 0,
        mask: int = 0xFF,
        cull_disable: bool = False,
        flip_facing: bool = False,
        opaque: Optional[bool] = None,
    ) -> None:
        if not isinstance(mesh, Mesh):
            raise TypeError(f"mesh must be a vkray.Mesh, got {type(mesh).__name__}")
        self.mesh = mesh
        self.transform = None if transform is None else _arrays.transform(transform)
        self.custom_index = _arrays.integer("custom_index", custom_index, 0, _MAX_CUSTOM_INDEX, " (24 bits)")
        self.mask = _arrays.integer("mask", mask, 0, 0xFF, " (8 bits)")
        if opaque is not None and not isinstance(opaque, (bool, np.bool_)):
            raise TypeError(f"opaque must be True, False or None, got {opaque!r}")
        self.cull_disable = bool(cull_disable)
        self.flip_facing = bool(flip_facing)
        #: True (forced opaque), False (forced non-opaque) or None; numpy bools become bools.
        self.opaque: Optional[bool] = None if opaque is None else bool(opaque)

    def _flags(self) -> int:
        return (
            int(self.cull_disable)
            | int(self.flip_facing) << 1
            | int(self.opaque is True) << 2
            | int(self.opaque is False) << 3
        )

    def __repr__(self) -> str:
        return f"<vkray.Instance of {self.mesh!r} custom_index={self.custom_index} mask={self.mask:#04x}>"


class Scene(SceneLike):
    """Instances of meshes under a top-level acceleration structure (TLAS), ready for queries
    (`SceneLike`: `intersect`, `occluded`, `count`, `contains`, ... run on this device).

    Made by `Device.scene`.
    """

    def __init__(self, device: Device, core: _core.Scene, instances: List[Instance]) -> None:
        self.device = device
        self._core = core
        self.instances = tuple(instances)

    @property
    def stats(self) -> Dict[str, Any]:
        """TLAS build figures, as `Mesh.stats`."""
        return dict(self._core.stats)

    def update(self, transforms: Any = None, masks: Any = None) -> None:
        """Refits the TLAS in place (the scene must be built with ``allow_update=True``).

        transforms: ``(N, 3, 4)`` or ``(N, 4, 4)``, one per instance (as `Instance` takes them);
        masks: ``(N,)`` 8-bit masks. Either may be omitted to keep the current ones. Also picks up
        the `Mesh.update`s of its meshes. The scene keeps the frame it was built in, so instances
        moved far away lose f32 precision (in the f32 tiers) until the scene is rebuilt.
        """
        n = len(self.instances)
        t = None
        if transforms is not None:
            t = _arrays.real_coordinates("transforms", transforms).astype(np.float64)
            if t.ndim != 3 or t.shape[0] != n or t.shape[1:] not in ((3, 4), (4, 4)):
                raise ValueError(f"transforms must have shape ({n}, 3, 4) or ({n}, 4, 4), got {t.shape}")
            t = np.ascontiguousarray(t)
        m = _arrays.optional_masks(masks, n)
        self._core.update(t, m)
        for k, instance in enumerate(self.instances):
            if t is not None:
                instance.transform = t[k]
            if m is not None:
                instance.mask = int(m[k])

    def answer(self, query: Query) -> Any:
        """The answer to a `RayQuery` or `PointQuery` on this device (`SceneLike.answer`)."""
        run = _ANSWERS.get(query.kind)
        if run is None:
            raise ValueError(f"no query named {query.kind!r}")
        if _cuda_query(query):
            on_gpu = self._contains_cuda(query) if isinstance(query, PointQuery) else None
            if on_gpu is not None:
                return on_gpu
            if not self._stays_on_gpu(query):
                return self._through_host(query, run)
        if isinstance(query, RayQuery) and query.cuda:
            return self._onto_gpu(query, run)
        return run(self, query)

    def _stays_on_gpu(self, query: Query) -> bool:
        """Whether CUDA rays of ``query`` are traced where they lie: `RayQuery.stays_on_gpu`, and
        a query the GPU answers for what this scene holds (not counts or transmittance of a scene
        with spheres, whose answers are the host's)."""
        return (
            isinstance(query, RayQuery)
            and query.stays_on_gpu
            and bool(self._core.stays_on_gpu(_CORE_QUERIES[query.kind], query.precision, list(query.outputs)))
        )

    def _onto_gpu(self, query: RayQuery, run: Callable[[Scene, Any], Any]) -> Any:
        """A query of host rays (arrays or a sensor) answered in CUDA memory (``cuda=True``): as
        for host rays, then each answer copied to the device's GPU."""
        if query.out is not None:
            raise TypeError("out= takes numpy hits: cuda=True answers in new arrays vkray owns")
        if self.device.cuda_device is None:
            raise TypeError(
                f"cuda=True: {self.device.name} does not share memory with CUDA (not a CUDA GPU, or its Vulkan "
                f"driver cannot share memory with CUDA)"
            )
        core = self.device._core
        on_host = replace(query, cuda=False)
        if query.kind == "occluded":
            # As for CUDA rays: the blocking triangle (-1 where none), int32.
            return _arrays.numpy_to_cuda(core, self._occluded(on_host, "prim_id"))
        return _to_cuda(core, run(self, on_host))

    def _through_host(self, query: Query, run: Callable[[Scene, Any], Any]) -> Any:
        """A query of CUDA arrays that has no GPU-resident path (the refined and reference tiers,
        all hits of fields the GPU does not write or lists it cannot settle, the point queries,
        the host-made ``position``): its CUDA arrays are
        copied to the host in stream order, it runs as for numpy, and its answer is copied to new
        `vkray.CudaArray`s on the same GPU (one copy each way over the bus: docs/benchmarks.md)."""
        if isinstance(query, RayQuery) and query.out is not None:
            raise TypeError("out= takes numpy hits: CUDA rays' hits are new arrays vkray owns")
        core = self.device._core

        def host(value: Any, name: str, kinds: str = "f") -> Any:
            """A CUDA array argument read to the host; numbers pass; host arrays are refused, as
            on the GPU-resident path (every array of a CUDA query lives on its GPU)."""
            if not _arrays.on_cuda(value, names=(name,)):
                if np.ndim(value) == 0:
                    return value
                raise TypeError(
                    f"{name} is in host memory while the query's other arrays are CUDA arrays: pass every array "
                    f"on the GPU (or every one in host memory)"
                )
            array = _arrays.cuda_to_numpy(core, value, name)
            if array.dtype.kind not in kinds or (kinds == "f" and array.dtype.itemsize < 4):
                wanted = "float32 or float64" if kinds == "f" else "integers"
                raise TypeError(f"{name} must be {wanted}, got {array.dtype}")
            return array

        if isinstance(query, RayQuery):
            if query.directions is None:
                raise TypeError("directions are needed, unless origins is a sensor (vkray.PinholeCamera ...)")
            on_host_rays = query.with_rays(
                host(query.origins, "origins"), host(query.directions, "directions"), host(query.tmin, "tmin"),
                host(query.tmax, "tmax"), host(query.mask, "mask", "iu"),
            )
            if query.kind == "occluded":
                # As the GPU-resident path answers: the blocking triangle (-1 where none), int32.
                return _arrays.numpy_to_cuda(core, self._pinned(lambda: self._occluded(on_host_rays, "prim_id")))
            return _to_cuda(core, self._pinned(lambda: run(self, on_host_rays)))
        on_host_points = query.with_points(host(query.points, "points"))
        return _to_cuda(core, self._pinned(lambda: run(self, on_host_points)))

    def _pinned(self, answer: Callable[[], Any]) -> Any:
        """``answer()`` with its arrays made in page-locked memory of the GPU (`_through_host`'s
        answers, copied to CUDA memory next: by DMA from where they were written, without a copy
        into staging: on an H200, fandisk's 1M CUDA points' closest points with every field in 15.2 ms
        instead of 17.6)."""
        core = self.device._core
        core.pinned_answers(True)
        try:
            return answer()
        finally:
            core.pinned_answers(False)

    def _intersect(self, q: RayQuery) -> Hits:
        if q.out is not None and _arrays.on_cuda(q.origins, q.directions):
            raise TypeError("out= takes numpy hits: CUDA rays' hits are new arrays vkray owns")
        if _arrays.on_cuda(q.origins, q.directions):
            cuda = self._trace_cuda(q, "closest")
            return Hits(_cuda_shape(cuda), cuda, q.precision)
        batch = _RayBatch(q)
        if batch.echoes > 1:
            if q.out is not None:
                raise ValueError("out= is for one hit per ray: a lidar's echoes come back as new arrays")
            return self._echoes(batch, q)
        given = None if q.out is None else out_arrays(q.out, batch.shape, q.outputs, q.precision,
                                                      (*batch.arrays, batch.mask))
        arrays = self._traced(q, batch, lambda bar: self._core.trace(
            *batch.arrays, "closest", list(q.outputs), q.precision, q.cull, batch.mask, progress=bar,
            opacity_threshold=q.opacity_threshold, sensor=batch.sensor, out=given))
        return Hits(batch.shape, arrays, q.precision)

    def _echoes(self, batch: _RayBatch, q: RayQuery) -> Hits:
        """The first ``batch.echoes`` hits of each ray, as Hits of shape ``S + (echoes,)``."""
        k = batch.echoes
        arrays = self._traced(q, batch, lambda bar: self._core.trace_all(
            *batch.arrays, list(q.outputs), q.precision, q.cull, batch.mask, k, progress=bar,
            opacity_threshold=q.opacity_threshold, sensor=batch.sensor))
        offsets = arrays["offsets"]
        n = len(offsets) - 1
        rays = ray_index_of(offsets)
        rank = np.arange(len(rays)) - offsets[rays]
        slot = rays * k + rank
        padded: Dict[str, np.ndarray] = {}
        for name in q.outputs:
            values = arrays[name]
            miss = np.inf if name == "t" else (np.nan if values.dtype.kind == "f" else -1)
            out = np.full((n * k,) + values.shape[1:], miss, dtype=values.dtype)
            out[slot] = values
            padded[name] = out
        return Hits(batch.shape + (k,), padded, q.precision)

    def _occluded(self, q: RayQuery, field: str = "hit") -> np.ndarray:
        if _arrays.on_cuda(q.origins, q.directions):
            # Typed as the numpy path's result: CUDA rays are the exception, and documented.
            return cast(np.ndarray, self._trace_cuda(q, "occluded")["prim_id"])
        batch = _RayBatch(q)
        # ["hit"]: bools made from the hit triangles as the core copies them out; ["prim_id"]:
        # the blocking triangles (CUDA rays' answer).
        arrays = self._traced(q, batch, lambda bar: self._core.trace(
            *batch.arrays, "occluded", [field], q.precision, q.cull, batch.mask, progress=bar,
            opacity_threshold=q.opacity_threshold, sensor=batch.sensor))
        return cast(np.ndarray, arrays[field].reshape(batch.shape))

    def _transmittance(self, q: RayQuery) -> np.ndarray:
        if _arrays.on_cuda(q.origins, q.directions):
            # Typed as the numpy path's result: CUDA rays are the exception, and documented.
            return cast(np.ndarray, self._trace_cuda(replace(q, outputs=("t",)), "transmittance")["t"])
        batch = _RayBatch(q)
        arrays = self._traced(q, batch, lambda bar: self._core.trace(
            *batch.arrays, "transmittance", ["t"], q.precision, q.cull, batch.mask, progress=bar, sensor=batch.sensor))
        return cast(np.ndarray, arrays["t"].reshape(batch.shape))

    def _intersect_all(self, q: RayQuery) -> AllHits:
        if _arrays.on_cuda(q.origins, q.directions):
            resident = self._trace_cuda_all(q)
            if resident is not None:
                return resident
            # A list the GPU cannot settle (a ray of more than 32 hits, a triangle reported
            # twice): the query again through the host.
            return cast(AllHits, self._through_host(q, _ANSWERS["intersect_all"]))
        batch = _RayBatch(q)
        arrays = self._traced(q, batch, lambda bar: self._core.trace_all(
            *batch.arrays, list(q.outputs), q.precision, q.cull, batch.mask, q.max_hits, progress=bar,
            opacity_threshold=q.opacity_threshold, sensor=batch.sensor))
        return AllHits(batch.shape, arrays, q.precision)

    def _count(self, q: RayQuery) -> np.ndarray:
        if _arrays.on_cuda(q.origins, q.directions):
            # Typed as the numpy path's result: CUDA rays are the exception, and documented.
            # The count comes back in prim_id's place (one int32 a ray).
            counted = self._trace_cuda(replace(q, outputs=("prim_id",)), "count")
            return cast(np.ndarray, counted["prim_id"])
        batch = _RayBatch(q)
        counts = self._traced(q, batch, lambda bar: self._core.count(
            *batch.arrays, q.precision, q.cull, batch.mask, progress=bar, opacity_threshold=q.opacity_threshold,
            sensor=batch.sensor))
        return cast(np.ndarray, counts.reshape(batch.shape))

    def _traced(self, q: RayQuery, batch: _RayBatch, call: Callable[[Any], Any]) -> Any:
        """``call(bar)``: a core call of ``q``'s rays under its progress bar (if asked)."""
        return _progress.call(q.progress, q.kind, call)

    def _trace_cuda(self, q: RayQuery, core_query: str) -> Dict[str, Any]:
        """The GPU-resident path: rays in CUDA memory, hits left there (see `intersect`)."""
        ray_mask = _check_cuda_query(q)
        return cast(
            Dict[str, Any],
            self._core.trace_cuda(q.origins, q.directions, q.tmin, q.tmax, core_query, list(q.outputs), q.cull,
                                  ray_mask, q.opacity_threshold, q.precision),
        )

    def _trace_cuda_all(self, q: RayQuery) -> Optional[AllHits]:
        """All hits of CUDA rays left on the GPU (the GPU-resident path), or None where a list
        needs the host. The counts are made at first use from the offsets (read to the host, 8
        MB a million rays, and the counts written back)."""
        ray_mask = _check_cuda_query(q)
        answer = self._core.trace_cuda_all(q.origins, q.directions, q.tmin, q.tmax, list(q.outputs), q.cull, ray_mask,
                                           q.opacity_threshold, q.precision, q.max_hits)
        if answer is None:
            return None
        shape, arrays = tuple(answer[0]), cast(Dict[str, Any], answer[1])
        core, offsets = self.device._core, arrays["offsets"]

        def counts() -> Any:
            host_offsets = _arrays.cuda_to_numpy(core, offsets, "offsets")
            return _arrays.numpy_to_cuda(core, counts_of(host_offsets).reshape(shape))

        return AllHits(shape, arrays, q.precision, counts=counts)

    def split_cuda_rays(self, q: RayQuery) -> Any:
        """A batch of CUDA rays on this device's GPU for several devices to trace in pieces
        (`DeviceGroup`): a `_core.CudaBatch` of ``q``'s rays, checked as a CUDA query is. An
        internal entry of `GroupScene`'s, documented here: `trace_cuda_rows` traces its pieces."""
        ray_mask = _check_cuda_query(q)
        return self._core.cuda_batch(q.origins, q.directions, q.tmin, q.tmax, list(q.outputs), ray_mask)

    def trace_cuda_rows(self, batch: Any, start: int, stop: int, q: RayQuery) -> None:
        """Rows ``start:stop`` of a `split_cuda_rays` batch traced on this device, their hits
        written into the batch (``q``: the query, for its kind, cull and threshold)."""
        core_query = "closest" if q.kind == "intersect" else "occluded"
        self._core.trace_cuda_piece(batch, start, stop, core_query, q.cull, q.opacity_threshold)

    def _closest_points(self, q: PointQuery) -> Closest:
        p = _points(q.points, q.precision)
        core_fields = ["t" if name == "distance" else name for name in q.outputs]
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        arrays = _progress.call(
            q.progress,
            "closest_points",
            lambda bar: self._core.closest_points(flat, core_fields, q.max_distance, q.precision, bar),
        )
        if "t" in arrays:
            arrays["distance"] = arrays.pop("t")
        if q.precision == "fast":
            for name in ("distance", "uv", "position"):
                if name in arrays:
                    arrays[name] = arrays[name].astype(np.float32)
        return Closest(p.shape[:-1], arrays, q.precision)

    def _distance(self, q: PointQuery) -> np.ndarray:
        found = self._closest_points(q)
        assert found.distance is not None
        return found.distance

    def _signed_distance(self, q: PointQuery) -> np.ndarray:
        p = _points(q.points, q.precision)
        method = q.method
        if method is None:
            method = "parity" if all(x.mesh.is_closed for x in self.instances) else "winding"
        if method == "parity":
            self._check_closed()
        precision = q.precision
        tier: Precision = "reference" if precision == "reference" or not self.device.info.shader_float64 else "exact"
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        signed: np.ndarray = _progress.call(
            q.progress,
            "signed_distance",
            lambda bar: self._core.signed_distance(flat, q.max_distance, precision, tier, method == "winding", bar),
        )
        signed = signed.reshape(p.shape[:-1])
        return signed.astype(np.float32) if precision == "fast" else signed

    def _contains_cuda(self, q: PointQuery) -> Any:
        """`contains` of CUDA points answered on the GPU through the scene's inside grid (a bool
        `vkray.CudaArray`), or None where that path does not answer (another query or tier, no
        grid kept yet, several instances): the query then goes through the host, which builds
        the grid as numpy points' queries do."""
        # A progress bar is the host path's (it counts the points' chunks).
        if q.kind != "contains" or q.precision != "exact" or q.progress or self.device.cuda_device is None:
            return None
        if q.method == "parity":
            self._check_closed()
        return self._core.contains_cuda(q.points, q.method == "winding")

    def _contains(self, q: PointQuery) -> np.ndarray:
        p = _points(q.points)
        if q.method == "parity":
            self._check_closed()
        inside = _progress.call(
            q.progress,
            "contains",
            lambda bar: self._core.contains(
                np.ascontiguousarray(p.reshape(-1, 3)), q.precision, q.method == "winding", bar
            ),
        )
        return cast(np.ndarray, inside.reshape(p.shape[:-1]))

    def explain(
        self,
        kind: str = "closest",
        outputs: Optional[Iterable[str]] = None,
        precision: Precision = "fast",
        cull: Cull = None,
        *,
        opacity_threshold: float = 0.5,
        sensor: bool = False,
    ) -> Dict[str, Any]:
        """The shader variant a query would run on this scene, and why (nothing is traced).

        A variant is a pure function of what the scene holds (opacity, spheres, non-opaque
        instances) and what the query asks (kind, outputs, culling, tier, rays from arrays or a
        sensor), compiled once per device and cached. kind: ``"closest"`` (`intersect`),
        ``"occluded"``, ``"all"`` (`intersect_all`'s storing pass), ``"count"``, ``"contains"``
        (with one instance) or ``"transmittance"``. outputs: `intersect`'s fields (default as
        there; other kinds write what they need).

        Returns a dict: ``stages`` (the shader stages by role: ray generation, miss, closest-hit,
        any-hit, intersection; or the ray-query backend's compute shader), ``ray_query_branches``
        (the candidate loop's branches that are compiled in), ``ray_flags`` (the static ray flags
        by name), ``pipeline_flags`` (primitives the whole pipeline skips), ``outputs`` (the hit
        fields the GPU writes), ``specialization`` (the constants' values), ``device``,
        ``backend``, ``kind`` and ``precision``. The ``"reference"`` tier runs on the host, and so
        does the CPU engine: their ``stages`` say what runs, and the CPU engine's ``filter`` what
        its fast tier's hit filter handles (``"culling"``, ``"opacity"``, ``"every hit"``; empty:
        Embree's plain traversal, no filter). ``RAY_SOURCE`` is shown for rays in the full layout (0) or a sensor's (1):
        float32 rays of one interval run the same variant reading the leaner layouts (3: origin and
        direction a ray; 4: from one origin, a direction a ray), which the rays decide.
        """
        kinds = {"closest": "closest", "occluded": "occluded", "all": "all", "count": "count"}
        kinds.update({"contains": "contains", "transmittance": "transmittance"})
        if kind not in kinds:
            raise ValueError(f"kind must be one of {tuple(kinds)}, got {kind!r}")
        if kind == "closest":
            fields: Tuple[str, ...] = check_outputs(outputs)
        else:
            if outputs is not None:
                raise ValueError(f"a {kind!r} query writes what it needs: outputs are for 'closest'")
            fields = ("t",) if kind == "transmittance" else ("prim_id",)
        if kind == "contains":
            precision = "exact" if precision == "fast" else precision
        core = self._core.explain(kind, list(fields), precision, cull, opacity_threshold, bool(sensor))
        base = {"device": self.device.name, "backend": self.device.backend, "kind": kind, "precision": precision}
        if core is None or "filter" in core:
            # The host's tiers, or the CPU engine: no shader variant; ``filter`` names what the
            # CPU engine's hit filter does (none: Embree's plain traversal).
            host: Dict[str, Any] = {"stages": ["host: f64 watertight test on all CPU cores"], "filter": []}
            host.update(ray_query_branches=[], ray_flags=[], pipeline_flags=[], outputs=list(fields))
            host["specialization"] = {}
            return {**base, **host, **(core or {})}
        return {**base, **core}

    def _check_closed(self) -> None:
        """Parity needs closed meshes: ValueError naming the instances that are not."""
        open_meshes = sorted({i for i, x in enumerate(self.instances) if not x.mesh.is_closed})
        if open_meshes:
            raise ValueError(
                f"instances {open_meshes} are not closed meshes (Mesh.is_closed), so the parity of "
                "crossings says nothing: use method='winding'"
            )

    def __repr__(self) -> str:
        return f"<vkray.Scene {len(self.instances)} instances on {self.device.name!r}>"

    def _repr_html_(self) -> str:
        """A table for notebooks: instance, mesh and triangle counts, bounds, bytes, build flags."""
        return _pictures.scene_html(self)


#: Each query's implementation in `Scene`, by the query method's name.
_ANSWERS: Dict[str, Callable[[Scene, Any], Any]] = {
    "intersect": Scene._intersect,
    "occluded": Scene._occluded,
    "transmittance": Scene._transmittance,
    "intersect_all": Scene._intersect_all,
    "count": Scene._count,
    "closest_points": Scene._closest_points,
    "distance": Scene._distance,
    "signed_distance": Scene._signed_distance,
    "contains": Scene._contains,
}


def _points(points: Any, precision: Optional[Precision] = None) -> np.ndarray:
    """A point query's points: real, of shape ``S + (3,)``. The fast tier answers distances in
    float32: a point beyond its range (whose distance float32 cannot hold) is refused there,
    naming the row, rather than answered inf and unhit."""
    p = _arrays.real_coordinates("points", points)
    if p.ndim == 0 or p.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {p.shape}")
    limit = float(np.finfo(np.float32).max)
    # Two reductions without temporaries first (a whole pass of temporaries cost the fast tier 5x
    # its time on an H200); the rows only where one is beyond (NaN and inf are the core's to refuse).
    if precision == "fast" and p.dtype == np.float64 and p.size and (p.max() > limit or p.min() < -limit):
        far = (np.isfinite(p) & (np.abs(p) > limit)).any(axis=-1).reshape(-1)
        if far.any():
            row = int(np.argmax(far))
            raise ValueError(
                f"points row {row} is beyond float32's range, in which precision='fast' answers: "
                f"{p.reshape(-1, 3)[row].tolist()}; precision='exact' or 'reference' answers in float64"
            )
    return p


class _RayBatch:
    """A query's rays as the core takes them: arrays (flattened, bounds), or a sensor's record."""

    def __init__(self, q: RayQuery) -> None:
        from .sensors import Sensor

        origins, directions, tmin, tmax = q.origins, q.directions, q.tmin, q.tmax
        self.sensor: Optional[Dict[str, Any]] = None
        self.echoes = 1
        if isinstance(origins, Sensor):
            if directions is not None:
                raise TypeError("a sensor generates its own rays: pass it alone, without directions")
            numbers = (int, float, np.integer, np.floating)
            if not (isinstance(tmin, numbers) and tmin == 0 and isinstance(tmax, numbers) and tmax == np.inf):
                raise TypeError("a sensor's range is its own (its tmin and tmax): do not pass tmin or tmax")
            self.shape: Tuple[int, ...] = tuple(origins.shape)
            self.sensor = _sensor_record(origins)
            self.echoes = int(origins.echoes)
            empty = np.empty((0, 3), np.float32)
            self.arrays: Tuple[np.ndarray, np.ndarray, Union[float, np.ndarray], Union[float, np.ndarray]] = (
                empty,
                empty,
                float(origins.tmin),
                float(origins.tmax),
            )
            self.mask = _arrays.masks(q.mask, ())
            return
        if directions is None:
            raise TypeError("directions are needed, unless origins is a sensor (vkray.PinholeCamera ...)")
        shape, o, d, lo, hi = _arrays.rays(origins, directions, tmin, tmax)
        self.shape = shape
        self.arrays = (o, d, lo, hi)
        self.mask = _arrays.masks(q.mask, shape)


#: The core's name of each ray query that may stay on the GPU (`Scene._stays_on_gpu`).
_CORE_QUERIES = {
    "intersect": "closest", "occluded": "occluded", "count": "count", "transmittance": "transmittance",
    "intersect_all": "all",
}


def _cuda_query(q: Query) -> bool:
    """Whether a query's rays or points are CUDA arrays (its answer then stays on their GPU)."""
    if isinstance(q, RayQuery):
        return _arrays.on_cuda(q.origins, q.directions)
    return _arrays.on_cuda(q.points, names=("points",))


def _to_cuda(core: Any, answer: Any) -> Any:
    """A query's numpy answer (an array, `Hits`, `AllHits` or `Closest`) with each array copied
    to the GPU of ``core`` (a `_core.Device`) as a `vkray.CudaArray`."""
    if isinstance(answer, np.ndarray):
        return _arrays.numpy_to_cuda(core, answer)
    # All hits' counts are copied at first use (the host's kept till then).
    names = ("offsets", "ray_index", "distance") + tuple(HIT_FIELDS)
    arrays = {name: getattr(answer, name, None) for name in names}
    on_gpu = {name: _arrays.numpy_to_cuda(core, a) for name, a in arrays.items() if isinstance(a, np.ndarray)}
    if isinstance(answer, AllHits):
        # The host's offsets kept (not its counts, made only if asked for).
        host_offsets, shape = answer.offsets, answer.shape
        return AllHits(shape, on_gpu, answer.precision,
                       counts=lambda: _arrays.numpy_to_cuda(core, counts_of(host_offsets).reshape(shape)))
    if isinstance(answer, Closest):
        return Closest(answer.shape, on_gpu, answer.precision)
    return Hits(answer.shape, on_gpu, answer.precision)


def _check_cuda_query(q: RayQuery) -> int:
    """The one mask of a GPU-resident query (`RayQuery.stays_on_gpu`; `Scene.answer` sends the
    others through the host)."""
    if q.directions is None:
        raise TypeError("directions are needed, unless origins is a sensor (vkray.PinholeCamera ...)")
    if not q.stays_on_gpu:
        raise _core.UnsupportedError(
            f"this {q.kind} query (precision={q.precision!r}) does not stay on the GPU: Scene.answer takes it "
            f"through the host"
        )
    return _arrays.integer("mask", q.mask, 0, 255, " (one mask for every CUDA ray)")


def _cuda_shape(arrays: Dict[str, Any]) -> Tuple[int, ...]:
    """The rays' shape S of a GPU-resident query's hits (``t`` or ``prim_id`` always has it)."""
    for name in ("t", "prim_id", "instance_id", "custom_index", "geometry_id"):
        if name in arrays:
            return tuple(arrays[name].shape)
    return (0,)


def _sensor_record(sensor: Any) -> Dict[str, Any]:
    """The core's record of a sensor (src/geometry/sensor.rs SensorRays) from its parameters."""
    g = sensor._generator()
    table = np.asarray(g["table"], dtype=np.float32)
    if g["kind"] == 3:
        # sensors.py lists channels' (cos, sin) first; the shaders read the steps' first.
        channels = 2 * int(g["rows"])
        table = np.concatenate([table[channels:], table[:channels]])
    return {
        "kind": int(g["kind"]),
        "origin": [float(x) for x in np.asarray(g["origin"], np.float32).reshape(3)],
        "axes": [float(x) for x in np.asarray(g["axes"], np.float32).reshape(9)],
        "columns": int(g["columns"]),
        "rows": int(g["rows"]),
        "pixel_offset": float(g.get("pixel_offset", 0.5)),
        "tmin": float(g["tmin"]),
        "tmax": float(g["tmax"]),
        "table": [float(x) for x in table],
    }


def opacity_per_triangle(value: Any, triangles: int, name: str = "opacity") -> Optional[np.ndarray]:
    """float32 ``(triangles,)`` opacity in [0, 1] from None, one number or one per triangle."""
    if value is None:
        return None
    a = _arrays.real_coordinates(name, value)
    if a.ndim == 0:
        a = np.full(triangles, float(a))
    if a.shape != (triangles,):
        raise ValueError(f"{name} must be one float or {triangles} (one per triangle), got shape {a.shape}")
    bad = ~((a >= 0) & (a <= 1))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{name}[{i}] must be in [0, 1] (1 blocks, 0 cuts the triangle out), got {a[i]}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _closed(faces: np.ndarray) -> bool:
    """Every directed edge once, and its reverse once."""
    f = faces.astype(np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    if np.any(directed[:, 0] == directed[:, 1]):
        return False
    key = directed[:, 0] * (int(f.max()) + 1) + directed[:, 1]
    reverse = directed[:, 1] * (int(f.max()) + 1) + directed[:, 0]
    unique = np.unique(key)
    return len(unique) == len(key) and bool(np.isin(reverse, unique, assume_unique=False).all())
