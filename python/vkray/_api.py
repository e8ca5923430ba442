"""vkray's public classes: Device, Mesh, Instance, Scene and Hits."""

from __future__ import annotations

from collections import abc
from dataclasses import dataclass
from typing import (
    Any,
    Dict,
    Iterable,
    List,
    Literal,
    Optional,
    Protocol,
    Sequence,
    Tuple,
    Union,
    cast,
    get_args,
)

import numpy as np

from . import _arrays, _core, _pictures, _progress

# The option strings, as types (the core checks their values and names the choices when wrong).
# Spelled as unions of one-value Literals, which type checkers read as Literal["a", "b"]: that is
# also a typing.Union at run time, as `python -m mypy.stubtest vkray` wants a union alias to be.
#: A precision tier (see `Scene.intersect` and docs/accuracy.md), fastest first.
Precision = Union[Literal["fast"], Literal["refined"], Literal["exact"], Literal["reference"]]
#: Which triangles' side a query ignores; ``None`` culls nothing.
Cull = Optional[Literal["back", "front"]]
#: What an acceleration structure's build favours.
Build = Union[Literal["fast_trace"], Literal["fast_build"], Literal["low_memory"]]
#: How a device traces: compute shaders with ray queries, or a ray-tracing pipeline.
Backend = Union[Literal["ray_query"], Literal["pipeline"]]
#: How a mesh's vertices are stored on the device.
VertexFormat = Union[Literal["float32"], Literal["float16"], Literal["snorm16"]]


class MeshObject(Protocol):
    """Another library's triangle mesh, as `Device.mesh` and `Device.scene` take it: ``vertices``
    (V, 3) and ``faces`` (F, 3) array-likes (a `trimesh.Trimesh`)."""

    @property
    def vertices(self) -> Any: ...

    @property
    def faces(self) -> Any: ...


def _choices(option: object) -> Tuple[str, ...]:
    """The strings of one of the option types above."""
    return tuple(value for arg in get_args(option) for value in get_args(arg) if isinstance(value, str))


#: Every hit field a query can return.
HIT_FIELDS: Tuple[str, ...] = (
    "t",
    "prim_id",
    "instance_id",
    "custom_index",
    "uv",
    "normal",
    "geometry_id",
    "position",
)
#: Fields `Scene.intersect` returns unless asked otherwise.
DEFAULT_FIELDS: Tuple[str, ...] = ("t", "prim_id", "instance_id", "custom_index", "uv", "normal")
#: Precision tiers, from the fastest to the CPU oracle (see `Scene.intersect` and docs/accuracy.md).
PRECISIONS = cast("Tuple[Precision, ...]", _choices(Precision))


@dataclass(frozen=True)
class DeviceInfo:
    """A usable Vulkan device, as `devices()` lists it."""

    index: int
    name: str
    device_type: str
    is_software: bool
    api_version: str
    driver: str
    ray_query: bool
    ray_tracing_pipeline: bool
    shader_float64: bool


def devices() -> List[DeviceInfo]:
    """The Vulkan devices vkray can use, best first (GPUs before software rasterizers).

    A device qualifies with Vulkan 1.2, acceleration structures, buffer device addresses, 64-bit
    shader integers, and ray queries or a ray-tracing pipeline.
    """
    return [DeviceInfo(**info) for info in _core.devices()]


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
        selector = None if device is None else str(device)
        self._core = _core.Device(selector, backend, bool(validation))  # the core checks backend
        info = self._core.info
        self.info = DeviceInfo(**info)
        if host_threads is not None:
            self.host_threads = host_threads

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def backend(self) -> Backend:
        """``"ray_query"`` or ``"pipeline"``: how this device traces."""
        return self._core.backend

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
        leaner two with 32 more; 64 a ray in the exact tier)."""
        return dict(self._core.last_trace_profile)

    @property
    def idle_memory(self) -> Dict[str, int]:
        """The staging memory this device keeps between queries, so that the next query need not
        allocate it (host-visible buffers for rays and hits, their device copies, packing
        scratch, CUDA leases): ``bytes`` held now, ``kept`` (how many sets of buffers), and
        ``made`` (how many its queries had to allocate so far, because none was idle).

        A device keeps as many as its queries used at once (several threads querying it at the
        same time each hold their own), at least two queries' worth and up to eight: a query's
        staging takes two chunks (`chunk_rays`) of 76 bytes a ray, twice over on discrete GPUs
        (1.3 GB on an H200). An allocation that runs out of memory frees them all and tries
        again; `release_idle_memory` frees them at once."""
        return dict(self._core.idle_memory)

    def release_idle_memory(self) -> None:
        """Frees the staging memory kept between queries (`idle_memory`), e.g. after a burst of
        queries from many threads; later queries allocate what they need again."""
        self._core.release_idle_memory()

    @property
    def cuda_device(self) -> Optional[int]:
        """CUDA's index of this GPU (the device id of its CUDA arrays in DLPack, ``cuda:N`` in
        torch), or None where it is no CUDA device sharing memory with Vulkan: CUDA arrays of this
        index are the rays this device traces without leaving the GPU."""
        return self._core.cuda_device

    @property
    def chunk_rays(self) -> int:
        """Rays traced per submission. Staging memory holds two chunks (72 bytes a ray each)."""
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
        alpha = _opacity(opacity, len(f))
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
        mesh = Mesh(self, core, c, None)
        mesh._radii = np.asarray(radius, dtype=np.float64)  # for bounds (pictures)
        return mesh

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
            alphas = [_opacity(a, len(f), f"opacity[{k}]") for k, (a, (_, f)) in enumerate(zip(per_part, arrays))]
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
        if isinstance(items, (Mesh, Instance)) or _is_mesh_object(items):
            items = [cast(Union[Mesh, Instance, MeshObject], items)]
        if not isinstance(items, abc.Iterable):
            raise TypeError(f"scene() takes a Mesh, an Instance or a list of them, got {type(items).__name__}")
        instances = []
        for i, item in enumerate(items):
            if _is_mesh_object(item):
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


def _is_mesh_object(item: Any) -> bool:
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
    ) -> None:
        self.device = device
        self._core = core
        self.vertices = vertices
        #: The triangles' corner indices; ``None`` for spheres.
        self.faces = faces
        #: float32 opacity per triangle, or ``None`` where every triangle is opaque.
        self.opacity = None if opacity is None or bool((opacity >= 1).all()) else opacity
        self._closed: Optional[bool] = None
        self._radii: Optional[np.ndarray] = None  # spheres: one radius, or one a sphere

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
        (`Scene.contains`). Computed once (a mesh's topology never changes)."""
        if self._closed is None:
            self._closed = self.kind == "triangles" and _closed(np.asarray(self.faces))
        return self._closed

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


class Hits:
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

    t: Optional[np.ndarray]
    prim_id: Optional[np.ndarray]
    instance_id: Optional[np.ndarray]
    custom_index: Optional[np.ndarray]
    uv: Optional[np.ndarray]
    normal: Optional[np.ndarray]
    geometry_id: Optional[np.ndarray]
    position: Optional[np.ndarray]

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


class Scene:
    """Instances of meshes under a top-level acceleration structure (TLAS), ready for queries.

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
        """
        fields = DEFAULT_FIELDS if outputs is None else _check_outputs(outputs)
        if out is not None and not isinstance(out, Hits):
            raise TypeError(f"out must be the Hits of an earlier intersect, got {type(out).__name__}")
        if out is not None and _arrays.on_cuda(origins, directions):
            raise TypeError("out= takes numpy hits: CUDA rays' hits are new arrays vkray owns")
        if _arrays.on_cuda(origins, directions):
            cuda = self._trace_cuda(origins, directions, tmin, tmax, "closest", fields, precision, cull, mask, progress,
                                    opacity_threshold)
            return Hits(_cuda_shape(cuda), cuda, precision)
        batch = _RayBatch(origins, directions, tmin, tmax, mask)
        if batch.echoes > 1:
            if out is not None:
                raise ValueError("out= is for one hit per ray: a lidar's echoes come back as new arrays")
            return self._echoes(batch, fields, precision, cull, progress, opacity_threshold)
        given = None if out is None else _out_arrays(out, batch.shape, fields, precision, (*batch.arrays, batch.mask))
        arrays = _progress.call(
            progress,
            "intersect",
            lambda bar: self._core.trace(
                *batch.arrays,
                "closest",
                list(fields),
                precision,
                cull,
                batch.mask,
                progress=bar,
                opacity_threshold=opacity_threshold,
                sensor=batch.sensor,
                out=given,
            ),
        )
        return Hits(batch.shape, arrays, precision)

    def _echoes(
        self,
        batch: _RayBatch,
        fields: Tuple[str, ...],
        precision: Precision,
        cull: Cull,
        progress: bool,
        opacity_threshold: float,
    ) -> Hits:
        """The first ``batch.echoes`` hits of each ray, as Hits of shape ``S + (echoes,)``."""
        k = batch.echoes
        arrays = _progress.call(
            progress,
            "intersect",
            lambda bar: self._core.trace_all(
                *batch.arrays,
                list(fields),
                precision,
                cull,
                batch.mask,
                k,
                progress=bar,
                opacity_threshold=opacity_threshold,
                sensor=batch.sensor,
            ),
        )
        offsets = arrays["offsets"]
        n = len(offsets) - 1
        rank = np.arange(len(arrays["ray_index"])) - offsets[arrays["ray_index"]]
        slot = arrays["ray_index"] * k + rank
        padded: Dict[str, np.ndarray] = {}
        for name in fields:
            values = arrays[name]
            miss = np.inf if name == "t" else (np.nan if values.dtype.kind == "f" else -1)
            out = np.full((n * k,) + values.shape[1:], miss, dtype=values.dtype)
            out[slot] = values
            padded[name] = out
        return Hits(batch.shape + (k,), padded, precision)

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
        opacity_threshold: float = 0.5,
    ) -> np.ndarray:
        """bool ``S``: whether anything lies along each ray within [tmin, tmax].

        Traversal stops at the first hit found (TerminateOnFirstHit), so this is cheaper than
        `intersect`; ``occluded(...) == intersect(...).hit`` ray for ray, in every tier
        (``"refined"`` decides hits as ``"fast"`` does). Rays or a sensor, ``cull``, ``mask`` and
        ``opacity_threshold`` as in `intersect`. CUDA rays give a `CudaArray` of int32 ``S``, the hit
        triangle (>= 0 where occluded, -1 where not), which stays on the GPU.
        """
        if _arrays.on_cuda(origins, directions):
            cuda = self._trace_cuda(origins, directions, tmin, tmax, "occluded", ("prim_id",), precision, cull, mask,
                                    progress, opacity_threshold)
            # Typed as the numpy path's result: CUDA rays are the exception, and documented.
            return cast(np.ndarray, cuda["prim_id"])
        batch = _RayBatch(origins, directions, tmin, tmax, mask)
        arrays = _progress.call(
            progress,
            "occluded",
            lambda bar: self._core.trace(
                *batch.arrays,
                "occluded",
                ["hit"],  # bools made from the hit triangles as the core copies them out
                precision,
                cull,
                batch.mask,
                progress=bar,
                opacity_threshold=opacity_threshold,
                sensor=batch.sensor,
            ),
        )
        return arrays["hit"].reshape(batch.shape)

    def _trace_cuda(
        self,
        origins: Any,
        directions: Any,
        tmin: Any,
        tmax: Any,
        query: str,
        fields: Iterable[str],
        precision: Precision,
        cull: Cull,
        mask: Any,
        progress: bool,
        opacity_threshold: float,
    ) -> Dict[str, Any]:
        """The GPU-resident path: rays in CUDA memory, hits left there (see `intersect`)."""
        ray_mask = _check_cuda_query(fields, precision, progress, mask)
        return cast(
            Dict[str, Any],
            self._core.trace_cuda(origins, directions, tmin, tmax, query, list(fields), cull, ray_mask,
                                  opacity_threshold),
        )

    def _cuda_batch(
        self, origins: Any, directions: Any, tmin: Any, tmax: Any, fields: Iterable[str], precision: Precision,
        mask: Any, progress: bool,
    ) -> Any:
        """A batch of CUDA rays on this device's GPU for several devices to trace in pieces
        (`DeviceGroup`): `_core.CudaBatch`, checked as `_trace_cuda` checks a query."""
        ray_mask = _check_cuda_query(fields, precision, progress, mask)
        return self._core.cuda_batch(origins, directions, tmin, tmax, list(fields), ray_mask)

    def _cuda_piece(self, batch: Any, start: int, stop: int, query: str, cull: Cull, opacity_threshold: float) -> None:
        """Rows ``start:stop`` of ``batch`` traced on this device, their hits written into the batch."""
        self._core.trace_cuda_piece(batch, start, stop, query, cull, opacity_threshold)

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
        ``backend``, ``kind`` and ``precision``. The ``"reference"`` tier runs on the CPU: its
        stages are empty. ``RAY_SOURCE`` is shown for rays in the full layout (0) or a sensor's (1):
        float32 rays of one interval run the same variant reading the leaner layouts (3: origin and
        direction a ray; 4: from one origin, a direction a ray), which the rays decide.
        """
        kinds = {"closest": "closest", "occluded": "occluded", "all": "all", "count": "count"}
        kinds.update({"contains": "contains", "transmittance": "transmittance"})
        if kind not in kinds:
            raise ValueError(f"kind must be one of {tuple(kinds)}, got {kind!r}")
        if kind == "closest":
            fields: Tuple[str, ...] = DEFAULT_FIELDS if outputs is None else _check_outputs(outputs)
        else:
            if outputs is not None:
                raise ValueError(f"a {kind!r} query writes what it needs: outputs are for 'closest'")
            fields = ("t",) if kind == "transmittance" else ("prim_id",)
        if kind == "contains":
            precision = "exact" if precision == "fast" else precision
        core = self._core.explain(kind, list(fields), precision, cull, opacity_threshold, bool(sensor))
        base = {"device": self.device.name, "backend": self.device.backend, "kind": kind, "precision": precision}
        if core is None:
            empty: Dict[str, Any] = {"stages": ["host: f64 watertight test on all CPU cores"]}
            empty.update(ray_query_branches=[], ray_flags=[], pipeline_flags=[], outputs=list(fields))
            empty["specialization"] = {}
            return {**base, **empty}
        return {**base, **core}

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
        `intersect`; scenes with spheres raise `UnsupportedError`.
        """
        batch = _RayBatch(origins, directions, tmin, tmax, mask)
        arrays = _progress.call(
            progress,
            "transmittance",
            lambda bar: self._core.trace(
                *batch.arrays,
                "transmittance",
                ["t"],
                precision,
                cull,
                batch.mask,
                progress=bar,
                sensor=batch.sensor,
            ),
        )
        return arrays["t"].reshape(batch.shape)

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

        Scenes with spheres raise `UnsupportedError`. Triangles below ``opacity_threshold`` are
        not hits. Other arguments (rays or a sensor) as in `intersect`.
        """
        fields = DEFAULT_FIELDS if outputs is None else _check_outputs(outputs)
        limit = None if max_hits is None else _arrays.integer("max_hits", max_hits, 1, _arrays.U64_MAX)
        batch = _RayBatch(origins, directions, tmin, tmax, mask)
        arrays = _progress.call(
            progress,
            "intersect_all",
            lambda bar: self._core.trace_all(
                *batch.arrays,
                list(fields),
                precision,
                cull,
                batch.mask,
                limit,
                progress=bar,
                opacity_threshold=opacity_threshold,
                sensor=batch.sensor,
            ),
        )
        return AllHits(batch.shape, arrays, precision)

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
        opacity_threshold: float = 0.5,
    ) -> np.ndarray:
        """int32 ``S``: the number of hits of each ray within [tmin, tmax], as `intersect_all`
        finds them at the same precision (``count(...) == intersect_all(...).counts``), without
        storing them (but at ``"refined"``, whose hits are re-intersected on the host).

        precision: ``"fast"`` (default: f32 traversal on the GPU, each triangle it meets counted;
        at shared edges it may count two or none), ``"exact"`` (the f64 test on the GPU through
        per-triangle boxes: every crossing counted once; needs shaderFloat64), ``"reference"``
        (the same f64 test on all CPU cores) or ``"refined"``. Rays or a sensor, and the other
        arguments, as in `intersect`."""
        batch = _RayBatch(origins, directions, tmin, tmax, mask)
        counts = _progress.call(
            progress,
            "count",
            lambda bar: self._core.count(
                *batch.arrays,
                precision,
                cull,
                batch.mask,
                progress=bar,
                opacity_threshold=opacity_threshold,
                sensor=batch.sensor,
            ),
        )
        return counts.reshape(batch.shape)

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
        shaderFloat64. Scenes with spheres raise `UnsupportedError`.
        """
        fields = _closest_outputs(outputs)
        p, limit = _points_within(points, max_distance, precision)
        core_fields = ["t" if name == "distance" else name for name in fields]
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        arrays = _progress.call(
            progress,
            "closest_points",
            lambda bar: self._core.closest_points(flat, core_fields, limit, precision, bar),
        )
        if "t" in arrays:
            arrays["distance"] = arrays.pop("t")
        if precision == "fast":
            for name in ("distance", "uv", "position"):
                if name in arrays:
                    arrays[name] = arrays[name].astype(np.float32)
        return Closest(p.shape[:-1], arrays, precision)

    def distance(
        self, points: Any, *, max_distance: float = np.inf, precision: Precision = "reference", progress: bool = False
    ) -> np.ndarray:
        """float64 ``S``: the distance from each point to the nearest surface (inf beyond
        ``max_distance``), as `closest_points` finds it."""
        found = self.closest_points(
            points, max_distance=max_distance, outputs=["distance"], precision=precision, progress=progress
        )
        assert found.distance is not None
        return found.distance

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
        p, limit = _points_within(points, max_distance, precision)
        if method is None:
            method = "parity" if all(x.mesh.is_closed for x in self.instances) else "winding"
        if method not in ("parity", "winding"):
            raise ValueError(f"method must be 'parity' or 'winding', got {method!r}")
        if method == "parity":
            self._check_closed()
        tier: Precision = "reference" if precision == "reference" or not self.device.info.shader_float64 else "exact"
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        signed: np.ndarray = _progress.call(
            progress,
            "signed_distance",
            lambda bar: self._core.signed_distance(flat, limit, precision, tier, method == "winding", bar),
        )
        signed = signed.reshape(p.shape[:-1])
        return signed.astype(np.float32) if precision == "fast" else signed

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
        if method not in ("parity", "winding"):
            raise ValueError(f"method must be 'parity' or 'winding', got {method!r}")
        p = _arrays.real_coordinates("points", points)
        if p.ndim == 0 or p.shape[-1] != 3:
            raise ValueError(f"points must have shape (..., 3), got {p.shape}")
        if method == "parity":
            self._check_closed()
        inside = _progress.call(
            progress,
            "contains",
            lambda bar: self._core.contains(
                np.ascontiguousarray(p.reshape(-1, 3)), precision, method == "winding", bar
            ),
        )
        return inside.reshape(p.shape[:-1])

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


def _points_within(points: Any, max_distance: float, precision: object = None) -> Tuple[np.ndarray, float]:
    """A point query's points (real, of shape S + (3,)) and its max_distance (>= 0, or inf). The
    fast tier answers in float32: a point beyond its range (whose distance float32 cannot hold)
    is refused there, naming the row, rather than answered inf and unhit."""
    p = _arrays.real_coordinates("points", points)
    if p.ndim == 0 or p.shape[-1] != 3:
        raise ValueError(f"points must have shape (..., 3), got {p.shape}")
    if precision == "fast" and p.dtype == np.float64:
        far = (np.isfinite(p) & (np.abs(p) > np.finfo(np.float32).max)).any(axis=-1).reshape(-1)
        if far.any():
            row = int(np.argmax(far))
            raise ValueError(
                f"points row {row} is beyond float32's range, in which precision='fast' answers: "
                f"{p.reshape(-1, 3)[row].tolist()}; precision='exact' or 'reference' answers in float64"
            )
    limit = float(max_distance)
    if not limit >= 0:
        raise ValueError(f"max_distance must be >= 0 (or inf), got {max_distance}")
    return p, limit


# precision, cull, build, backend and vertex_format are checked by the core alone: its
# ValueError names the argument, the choices and the value given.


#: Values a ray of each hit field has, beyond one (`Hits`' arrays are (n,) or (n, width)).
_HIT_WIDTHS = {"uv": 2, "normal": 3, "position": 3}


def _hit_dtype(name: str, precision: Precision) -> np.dtype[Any]:
    """The dtype of a hit field's array in ``precision``'s hits."""
    floats = np.float32 if precision == "fast" else np.float64
    return np.dtype(np.float32 if name == "normal" else (floats if name in ("t", "uv", "position") else np.int32))


def _new_hit_arrays(count: int, fields: Iterable[str], precision: Precision) -> Dict[str, np.ndarray]:
    """Empty arrays for ``count`` rays' hits of ``fields`` (as the core makes them), to be filled."""
    return {
        name: np.empty((count, _HIT_WIDTHS[name]) if name in _HIT_WIDTHS else (count,), _hit_dtype(name, precision))
        for name in fields
    }


def _out_arrays(
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
        want = tuple(shape) + ((_HIT_WIDTHS[name],) if name in _HIT_WIDTHS else ())
        if array.shape != want:
            raise ValueError(f"out's {name} has shape {list(array.shape)}, the query writes {list(want)}")
        dtype = _hit_dtype(name, precision)
        if array.dtype != dtype:
            raise ValueError(f"out's {name} must be {np.dtype(dtype).name}, got {array.dtype}")
        others = [a for a in inputs if isinstance(a, np.ndarray)] + list(arrays.values())
        if any(np.may_share_memory(array, other) for other in others):
            raise ValueError(f"out's {name} shares memory with the rays or another output")
        arrays[name] = array.reshape((n,) + array.shape[len(shape) :])
    return arrays


class _RayBatch:
    """A query's rays as the core takes them: arrays (flattened, bounds), or a sensor's record."""

    def __init__(self, origins: Any, directions: Any, tmin: Any, tmax: Any, mask: Any) -> None:
        from .sensors import Sensor

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
            self.mask = _arrays.masks(mask, ())
            return
        if directions is None:
            raise TypeError("directions are needed, unless origins is a sensor (vkray.PinholeCamera ...)")
        shape, o, d, lo, hi = _arrays.rays(origins, directions, tmin, tmax)
        self.shape = shape
        self.arrays = (o, d, lo, hi)
        self.mask = _arrays.masks(mask, shape)


def _check_cuda_query(fields: Iterable[str], precision: Precision, progress: bool, mask: Any) -> int:
    """The one mask of a GPU-resident query, once its options are checked (only the fast tier and
    the fields computed on the GPU, no progress bar)."""
    if precision != "fast":
        raise _core.UnsupportedError(
            f"precision={precision!r} is not available for CUDA rays: only 'fast' stays on the GPU; pass numpy "
            f"arrays for the other tiers (e.g. tensor.cpu().numpy())"
        )
    if "position" in fields:
        raise _core.UnsupportedError("'position' is computed on the host: not available for CUDA rays")
    if progress:
        raise _core.UnsupportedError("progress is not shown for CUDA rays (one submission, nothing to report)")
    return _arrays.integer("mask", mask, 0, 255, " (one mask for every CUDA ray)")


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


#: Every field `Scene.closest_points` can return, and those it returns unless asked otherwise.
CLOSEST_FIELDS: Tuple[str, ...] = (
    "distance",
    "position",
    "prim_id",
    "instance_id",
    "custom_index",
    "geometry_id",
    "uv",
    "normal",
)
DEFAULT_CLOSEST_FIELDS: Tuple[str, ...] = ("distance", "position", "prim_id", "instance_id", "uv", "normal")


def _closest_outputs(outputs: Optional[Iterable[str]]) -> Tuple[str, ...]:
    if outputs is None:
        return DEFAULT_CLOSEST_FIELDS
    names = (outputs,) if isinstance(outputs, str) else tuple(outputs)
    unknown = [name for name in names if name not in CLOSEST_FIELDS]
    if unknown:
        raise ValueError(f"unknown fields {unknown}; choose from {CLOSEST_FIELDS}")
    fields = tuple(dict.fromkeys(names))
    if not fields:
        raise ValueError("outputs must name at least one field")
    return fields if "distance" in fields else fields + ("distance",)


class Closest:
    """The surface point nearest to each query point, from `Scene.closest_points`.

    Each field has the points' batch shape ``S`` (plus a last axis for position, uv and normal):
    ``distance`` (float64, inf where nothing lies within max_distance), ``position`` (float64, the
    nearest surface point, NaN on a miss), ``prim_id``, ``instance_id``, ``custom_index``,
    ``geometry_id`` (int32, -1 on a miss), ``uv`` (float64 barycentrics of vertices 1 and 2),
    ``normal`` (float32, the triangle's unit normal in the world). Fields not asked are None.
    """

    distance: Optional[np.ndarray]
    position: Optional[np.ndarray]
    prim_id: Optional[np.ndarray]
    instance_id: Optional[np.ndarray]
    custom_index: Optional[np.ndarray]
    geometry_id: Optional[np.ndarray]
    uv: Optional[np.ndarray]
    normal: Optional[np.ndarray]

    def __init__(self, shape: Tuple[int, ...], arrays: Dict[str, np.ndarray], precision: Precision) -> None:
        self.shape = shape
        self.precision: Precision = precision
        for name in CLOSEST_FIELDS:
            array = arrays.get(name)
            setattr(self, name, None if array is None else array.reshape(shape + array.shape[1:]))

    @property
    def hit(self) -> np.ndarray:
        """bool ``S``: whether a surface lies within max_distance of the point."""
        assert self.distance is not None
        found: np.ndarray = np.isfinite(self.distance)
        return found

    def __repr__(self) -> str:
        asked = [name for name in CLOSEST_FIELDS if getattr(self, name) is not None]
        found = int(self.hit.sum())
        return f"<vkray.Closest shape={self.shape} found={found} precision={self.precision!r} fields={asked}>"


def _opacity(value: Any, triangles: int, name: str = "opacity") -> Optional[np.ndarray]:
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


class AllHits:
    """Every hit of every ray, from `Scene.intersect_all`, in CSR form.

    offsets: int64 ``(N + 1,)``: ray i's hits are entries ``offsets[i]:offsets[i + 1]`` (rays in
    the flattened order of the batch shape ``S``).
    counts: int64 ``S``: hits per ray. ray_index: int64 ``(H,)``: the ray of each hit.
    t, prim_id, instance_id, custom_index, geometry_id, uv, normal, position: one entry per hit,
    as `Hits` has them per ray (float64 t, uv and position), for the fields asked; else None.
    Each ray's hits are in increasing t; hits at the same t in increasing (instance_id,
    geometry_id, prim_id). ``hits[i]`` is ray i's hits as `Hits` of shape ``(count,)``.
    """

    t: Optional[np.ndarray]
    prim_id: Optional[np.ndarray]
    instance_id: Optional[np.ndarray]
    custom_index: Optional[np.ndarray]
    uv: Optional[np.ndarray]
    normal: Optional[np.ndarray]
    geometry_id: Optional[np.ndarray]
    position: Optional[np.ndarray]

    def __init__(self, shape: Tuple[int, ...], arrays: Dict[str, np.ndarray], precision: Precision) -> None:
        self.shape = shape
        self.precision: Precision = precision
        self.offsets: np.ndarray = arrays["offsets"]
        self.ray_index: np.ndarray = arrays["ray_index"]
        self.counts: np.ndarray = np.diff(self.offsets).reshape(shape)
        for name in HIT_FIELDS:
            setattr(self, name, arrays.get(name))

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, ray: int) -> Hits:
        if not isinstance(ray, (int, np.integer)) or isinstance(ray, bool):
            raise TypeError(f"AllHits is indexed by a ray's flat index, got {ray!r}")
        n = len(self)
        if not -n <= int(ray) < n:
            raise IndexError(f"ray {ray} of {n}")
        lo, hi = self.offsets[int(ray) % n], self.offsets[int(ray) % n + 1]
        fields = {name: getattr(self, name)[lo:hi] for name in HIT_FIELDS if getattr(self, name) is not None}
        return Hits((int(hi - lo),), fields, self.precision)

    def __repr__(self) -> str:
        return f"<vkray.AllHits rays={len(self)} hits={len(self.ray_index)} precision={self.precision!r}>"


def _check_outputs(outputs: Iterable[str]) -> Tuple[str, ...]:
    if isinstance(outputs, str):
        outputs = (outputs,)
    try:
        outputs = tuple(outputs)  # once: a generator would be spent by the first look
    except TypeError:
        raise TypeError(f"outputs must be hit field names, got {outputs!r}") from None
    unknown = [name for name in outputs if name not in HIT_FIELDS]
    if unknown:
        raise ValueError(f"unknown hit fields {unknown}; choose from {HIT_FIELDS}")
    fields = tuple(dict.fromkeys(outputs))
    if not fields:
        raise ValueError("outputs must name at least one hit field")
    if "t" not in fields and "prim_id" not in fields:
        fields += ("prim_id",)  # Hits.hit needs one of them
    return fields
