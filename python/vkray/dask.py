"""vkray queries over Dask arrays, on as many GPUs and machines as a Dask cluster has.

Needs Dask (``pip install 'vkray[dask]'``). A cluster has one worker process per GPU, each told its
device by the ``VKRAY_DEVICE`` environment variable (an index or a name, as `vkray.Device` reads
it); `local_cluster` starts such a cluster on this machine:

>>> import dask, dask.array as da, vkray.dask
>>> from dask.distributed import Client
>>> cluster = vkray.dask.local_cluster()                  # one worker per GPU
>>> client = Client(cluster)
>>> spec = vkray.dask.SceneSpec([(vertices, faces)])      # meshes as numpy arrays
>>> origins = da.from_array(o, chunks=4_000_000)          # (N, 3) rays, any chunking along N
>>> directions = da.from_array(d, chunks=4_000_000)
>>> hits = vkray.dask.intersect(spec, origins, directions, outputs=["t", "prim_id"])
>>> (found,) = dask.compute(hits)                         # {"t": numpy array, "prim_id": ...}

`intersect`, `occluded`, `count`, `contains` and `closest_points` take rays or points as dask
arrays of shape (N, 3) (or anything `dask.array.asarray` takes), chunked in any way along N (the
second axis is made one chunk), and return dask arrays chunked as the rays are; `intersect` and
`closest_points` return a dict of them, one per field. Each chunk's answer is `vkray.Scene`'s
for those rays, so the computed arrays equal what one `Scene` answers in one process. Compute a
dict's fields together (``dask.compute(hits)``): computed one at a time, each traces anew. Errors
are one `Scene`'s, rows counted in the caller's rays; where several chunks hold bad rays, the
error names the bad row of the chunk that failed first, not always the first bad row. Chunks of
unknown size (after boolean indexing) are refused: call ``compute_chunk_sizes()`` first.

The scene travels as a `SceneSpec`: meshes and instances as numpy arrays, or a picklable callable
that builds the scene on a device. It is one key of the task graph on which every chunk's task
depends, so it is serialized once and reaches each worker once, not once per chunk; each worker
process builds it once per device and keeps it, cached by the spec's content hash (`cache_info`).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import hashlib
import importlib.util
import inspect
import logging
import math
import operator
import os
import threading
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, TypeVar, Union, cast

import numpy as np

from . import _arrays
from ._core import NoDeviceError
from ._device import Device, Instance, Scene
from ._device_group import default_devices, in_callers_rows, usable_cores
from ._queries import PointQuery, Query, RayQuery, SceneLike
from ._results import field_type

if importlib.util.find_spec("dask") is None:
    raise ImportError("vkray.dask needs Dask: pip install 'vkray[dask]'")

import dask.array as da  # noqa: E402
from dask.base import tokenize  # noqa: E402
from dask.delayed import delayed  # noqa: E402
from dask.highlevelgraph import HighLevelGraph  # noqa: E402

if TYPE_CHECKING:
    from distributed import SpecCluster
    from typing_extensions import Concatenate, ParamSpec

    _P = ParamSpec("_P")
_R = TypeVar("_R")

__all__ = [
    "SceneSpec",
    "intersect",
    "occluded",
    "count",
    "contains",
    "closest_points",
    "transmittance",
    "distance",
    "signed_distance",
    "local_cluster",
    "cache_info",
]

#: A builder: makes the scene on the worker's device.
Builder = Callable[[Device], Scene]

# What `Instance` takes besides the mesh, as a SceneSpec's instance mappings may give it.
_INSTANCE_KEYS = ("transform", "custom_index", "mask", "cull_disable", "flip_facing", "opaque")
# Scenes a worker process keeps built (the least recently used goes first): each holds GPU memory.
MAX_CACHED_SCENES = 8


class SceneSpec:
    """What a worker needs to build a scene: meshes and instances as numpy arrays, or a builder.

    meshes: ``(vertices, faces)`` pairs, as `Device.mesh` takes them.
    instances: mappings with a ``"mesh"`` (an index into meshes) and any of `Instance`'s
    arguments (``"transform"``, ``"custom_index"``, ``"mask"``, ``"cull_disable"``,
    ``"flip_facing"``, ``"opaque"``); ``None`` places each mesh once, untransformed, in order.
    `from_builder` takes a callable instead, for anything else (spheres, parts, opacity, build
    options). `key` is a hash of the content (the arrays' bytes, or the builder's pickle):
    workers keep one built scene per key and device.
    """

    def __init__(
        self, meshes: Sequence[Tuple[Any, Any]], instances: Optional[Sequence[Mapping[str, Any]]] = None
    ) -> None:
        # Copies, read-only: the key hashes the content now, and the scene must be built from
        # that content (the caller may change its arrays after).
        self._meshes: List[Tuple[np.ndarray, np.ndarray]] = [
            (_frozen(_arrays.points("vertices", v)), _frozen(_arrays.faces(f))) for v, f in meshes
        ]
        chosen = [{"mesh": k} for k in range(len(self._meshes))] if instances is None else instances
        self._instances = [_instance_arguments(k, x, len(self._meshes)) for k, x in enumerate(chosen)]
        self._builder: Optional[Builder] = None
        self.key = _content_hash(self._meshes, self._instances)

    @classmethod
    def from_builder(cls, builder: Builder) -> SceneSpec:
        """A spec whose scene ``builder(device)`` builds on each worker's device. The builder must
        pickle (Dask pickles closures and lambdas by value, with cloudpickle), and its pickle is
        its identity: the same pickle, the same cached scene."""
        if not callable(builder):
            raise TypeError(f"a builder must be callable (device -> Scene), got {type(builder).__name__}")
        spec = cls.__new__(cls)
        spec._meshes, spec._instances, spec._builder = [], [], builder
        spec.key = hashlib.sha256(_pickled(builder)).hexdigest()
        return spec

    def build(self, device: Device) -> Scene:
        """The scene, built on ``device``."""
        if self._builder is not None:
            scene = self._builder(device)
            if not isinstance(scene, Scene):
                raise TypeError(f"the scene builder must return a vkray.Scene, got {type(scene).__name__}")
            return scene
        meshes = [device.mesh(v, f) for v, f in self._meshes]
        return device.scene([Instance(meshes[x["mesh"]], **x["arguments"]) for x in self._instances])

    def __setstate__(self, state: Dict[str, Any]) -> None:
        """Unpickled (on a worker, as its task's dependency arrives): counted in `cache_info`."""
        self.__dict__.update(state)
        with _cache_lock:
            _worker_counts["specs_received"] += 1

    def __repr__(self) -> str:
        if self._builder is not None:
            what = "a builder"
        else:
            what = f"{len(self._meshes)} meshes, {len(self._instances)} instances"
        return f"<vkray.dask.SceneSpec of {what}, key {self.key[:12]}>"


def _instance_arguments(k: int, instance: Mapping[str, Any], mesh_count: int) -> Dict[str, Any]:
    """A SceneSpec's instance, checked: its mesh's index and `Instance`'s other arguments."""
    unknown = sorted(set(instance) - {"mesh", *_INSTANCE_KEYS})
    if unknown:
        raise ValueError(f"instance {k} has unknown keys {unknown}; it takes 'mesh' and {_INSTANCE_KEYS}")
    mesh = _arrays.integer(f"instance {k}'s mesh", instance.get("mesh"), 0, mesh_count - 1)
    arguments = {key: instance[key] for key in _INSTANCE_KEYS if key in instance}
    if arguments.get("transform") is not None:
        arguments["transform"] = _frozen(_arrays.transform(arguments["transform"]))
    return {"mesh": mesh, "arguments": arguments}


def _frozen(array: np.ndarray) -> np.ndarray:
    """A read-only copy of ``array``."""
    copy = np.array(array, copy=True)
    copy.flags.writeable = False
    return copy


def _content_hash(meshes: Sequence[Tuple[np.ndarray, np.ndarray]], instances: Sequence[Dict[str, Any]]) -> str:
    """sha256 of the meshes' arrays (dtype, shape and bytes) and the instances' arguments."""
    digest = hashlib.sha256()
    for array in (a for mesh in meshes for a in mesh):
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(np.ascontiguousarray(array).tobytes())
    for instance in instances:
        arguments = dict(instance["arguments"])
        transform = arguments.pop("transform", None)
        digest.update(repr((instance["mesh"], sorted(arguments.items()))).encode())
        digest.update(b"none" if transform is None else transform.tobytes())
    return digest.hexdigest()


def _pickled(builder: Builder) -> bytes:
    """The builder's pickle as Dask sends it (cloudpickle, a dependency of Dask's: closures and
    lambdas by value)."""
    import cloudpickle  # type: ignore[import-untyped]

    pickled: bytes = cloudpickle.dumps(builder)
    return pickled


# --------------------------------------------------------------------------------------------------
# The worker's side: its device and the scenes built on it, kept between tasks.

_cache_lock = threading.Lock()
# Held while a device is opened, and per scene key while that scene is built.
_device_lock = threading.Lock()
_building: Dict[Tuple[str, str], threading.Lock] = {}
_worker_scenes: collections.OrderedDict[Tuple[str, str], Scene] = collections.OrderedDict()
_worker_devices: Dict[str, Device] = {}
_worker_counts = {"builds": 0, "specs_received": 0}


def _device_selection() -> str:
    """The device this process is told to use (``VKRAY_DEVICE``, ``VKRAY_BACKEND``)."""
    return f"{os.environ.get('VKRAY_DEVICE', '')}/{os.environ.get('VKRAY_BACKEND', '')}"


def _worker_scene(spec: SceneSpec) -> Scene:
    """The spec's scene on this process's device: built on first use, then kept. A build holds
    only its own key's lock, so tasks of scenes already built (and `cache_info`, which runs on
    the worker's event loop) do not wait for it; tasks of the same scene wait, and find it."""
    selection = _device_selection()
    key = (spec.key, selection)
    with _cache_lock:
        scene = _cached(key)
        if scene is not None:
            return scene
        building = _building.setdefault(key, threading.Lock())
    with building:
        with _cache_lock:
            scene = _cached(key)
        if scene is not None:
            return scene
        scene = spec.build(_worker_device(selection))
        with _cache_lock:
            _worker_scenes[key] = scene
            _building.pop(key, None)
            _worker_counts["builds"] += 1
            while len(_worker_scenes) > MAX_CACHED_SCENES:
                _worker_scenes.popitem(last=False)
        return scene


def _cached(key: Tuple[str, str]) -> Optional[Scene]:
    """A kept scene, marked as the most recently used (under `_cache_lock`)."""
    scene = _worker_scenes.get(key)
    if scene is not None:
        _worker_scenes.move_to_end(key)
    return scene


def _worker_device(selection: str) -> Device:
    """This process's device (``VKRAY_DEVICE``, ``VKRAY_BACKEND``), opened on first use."""
    with _device_lock:
        device = _worker_devices.get(selection)
        if device is None:
            device = _worker_devices[selection] = Device()  # reads VKRAY_DEVICE and VKRAY_BACKEND
        return device


def cache_info() -> Dict[str, Any]:
    """This process's scene cache: ``device`` (its ``VKRAY_DEVICE/VKRAY_BACKEND``), ``scenes``
    (the keys of the specs whose scenes it keeps, least recently used first), ``builds`` (scenes
    built so far) and ``specs_received`` (SceneSpecs unpickled so far). On a cluster,
    ``client.run(vkray.dask.cache_info)`` asks every worker."""
    with _cache_lock:
        scenes = [spec_key for spec_key, _ in _worker_scenes]
        return {"device": _device_selection(), "scenes": scenes, **_worker_counts}


# The one field of queries that return one array (occluded, count, contains).
_ONE_ARRAY = "result"


def _query_block(
    spec: SceneSpec, query: Query, names: Tuple[str, ...], start: int, *arrays: np.ndarray
) -> Dict[str, np.ndarray]:
    """One chunk's answer on a worker: ``query`` (a record without its arrays) of the chunk's
    arrays (named ``names``, the record's fields), as a dict of arrays (one ``"result"`` for
    queries that return one array). Errors name rows as the whole batch counts them (the chunk
    starts at row ``start``)."""
    scene = _worker_scene(spec)  # its errors (a bad mesh) name the spec's rows, not the chunk's
    try:
        answer = scene.answer(_with_fields(query, dict(zip(names, arrays))))
    except (ValueError, TypeError) as error:
        raise in_callers_rows(error, start) from None
    if isinstance(answer, np.ndarray):
        return {_ONE_ARRAY: answer}
    return {name: value for name, value in vars(answer).items() if isinstance(value, np.ndarray)}


# --------------------------------------------------------------------------------------------------
# The client's side: task graphs.


def _as_scene_spec(scene: Union[SceneSpec, Builder]) -> SceneSpec:
    """A SceneSpec, or a builder wrapped in one."""
    if isinstance(scene, SceneSpec):
        return scene
    if callable(scene):
        return SceneSpec.from_builder(scene)
    raise TypeError(f"scene must be a vkray.dask.SceneSpec or a builder (device -> Scene), got {type(scene).__name__}")


def _dask_array(name: str, value: Any, convert: Callable[[str, Any], np.ndarray] = _arrays.host_array) -> da.Array:
    """``value`` as a dask array: other input read by ``convert`` (as one device reads it: ragged
    lists and arrays of objects raise its errors); chunks of unknown size refused with the remedy
    (tasks need each chunk's first row)."""
    if not isinstance(value, da.Array):
        host = convert(name, value)
        if host.dtype == object:
            raise TypeError(f"{name} must hold numbers, got an array of Python objects")
        value = da.from_array(host)
    if any(math.isnan(c) for c in value.chunks[0]):
        raise ValueError(
            f"{name} has chunks of unknown size (as after boolean indexing): call {name}.compute_chunk_sizes() "
            f"first"
        )
    return value


def _rows(name: str, value: Any) -> da.Array:
    """An (N, 3) dask array with its three columns in one chunk."""
    array = _dask_array(name, value, _arrays.real_coordinates)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {array.shape}")
    return array.rechunk({1: -1})


def _per_ray(name: str, value: Any, rays: da.Array) -> Optional[da.Array]:
    """A per-ray argument (tmin, tmax, mask) as an (N,) dask array chunked as the rays, or None
    for one value for every ray (which the tasks take as it is)."""
    if np.ndim(value) == 0:
        return None
    array = _dask_array(name, value)
    if array.shape != rays.shape[:1]:
        raise ValueError(f"{name} must be one value or one per ray, shape {rays.shape[:1]}, got {array.shape}")
    return array.rechunk((rays.chunks[0],))


def _map_chunks(
    spec: SceneSpec,
    query: Query,
    arrays: Dict[str, da.Array],
    fields: Mapping[str, Tuple[np.dtype[Any], Tuple[int, ...]]],
) -> Dict[str, da.Array]:
    """One task per chunk of the rays (or points) answers ``query`` (a record whose ``arrays``
    fields each task fills with its chunk's) on a worker; each of its ``fields`` becomes a dask
    array chunked as the rays are.

    The spec is one key of the graph (named by its content hash), on which every chunk's task
    depends: Dask sends it to a worker once, and other workers fetch it from there once."""
    spec_key = delayed(spec, name=f"vkray-scene-{spec.key}")
    names = tuple(arrays)
    # Unoptimized: optimizing each array's graph on its own fuses what the arrays share (origins
    # and directions sliced from one array of rays) into each of them, which then runs twice.
    blocks = [arrays[name].to_delayed(optimize_graph=False).ravel() for name in names]
    lengths = arrays[names[0]].chunks[0]
    query = _with_fields(query, {name: None for name in names})  # each task's are its chunk's
    token = tokenize(spec.key, query, names, *arrays.values())
    starts = np.cumsum((0,) + lengths[:-1])
    if list(fields) == [_ONE_ARRAY]:
        dtype = fields[_ONE_ARRAY][0]
        return {_ONE_ARRAY: _answer_array(spec_key, blocks, (query, names), starts, lengths, token, dtype)}
    answers = [
        delayed(_query_block, pure=True)(
            spec_key,
            query,
            names,
            int(start),
            *(b[k] for b in blocks),
            dask_key_name=f"vkray-{query.kind}-{token}-{k}",
        )
        for k, start in enumerate(starts)
    ]
    return {name: _field_array(answers, name, query.kind, token, lengths, kind) for name, kind in fields.items()}


def _answer_array(
    spec_key: Any,
    blocks: List[Any],
    call: Tuple[Query, Tuple[str, ...]],
    starts: Any,
    lengths: Tuple[int, ...],
    token: str,
    dtype: np.dtype[Any],
) -> da.Array:
    """The answers of a query that returns one array (``call``: the query's record, the names of
    the blocks' arrays), as a dask array whose chunks are the queries' tasks themselves:
    one task a chunk. What is not a key is bound in a `functools.partial`, where Dask does not
    look for keys (a literal that equals one, as a caller's key named "fast" might, would be read
    as that key)."""
    array_name = f"vkray-{call[0].kind}-{token}"

    def keys(k: int) -> List[Any]:
        return [b[k].key for b in blocks]

    layer: Dict[Any, Any] = {
        (array_name, k): (functools.partial(_one_array_block, *call, int(start)), spec_key.key, *keys(k))
        for k, start in enumerate(starts)
    }
    dependencies = [spec_key, *(block for array_blocks in blocks for block in array_blocks)]
    graph = HighLevelGraph.from_collections(array_name, layer, dependencies=dependencies)
    return da.Array(graph, array_name, chunks=(lengths,), dtype=dtype)


def _one_array_block(
    query: Query, names: Tuple[str, ...], start: int, spec: SceneSpec, *arrays: np.ndarray
) -> np.ndarray:
    """`_query_block` of a query that returns one array, that array."""
    answer: np.ndarray = _query_block(spec, query, names, start, *arrays)[_ONE_ARRAY]
    return answer


def _field_array(
    answers: List[Any],
    name: str,
    query: str,
    token: str,
    lengths: Tuple[int, ...],
    kind: Tuple[np.dtype[Any], Tuple[int, ...]],
) -> da.Array:
    """A field of the chunks' answers as a dask array: each chunk one task that takes the field
    out of its chunk's answer (with `da.from_delayed` and `da.concatenate`, each chunk was three,
    the two others aliases that workers run as tasks all the same)."""
    dtype, tail = kind
    array_name = f"vkray-{name}-of-{query}-{token}"  # not "vkray-{query}-": the answers' keys
    corner = (0,) * len(tail)
    # The field's name inside the callable: a literal in a task that equals a key of the graph
    # (a user's "t" or "result") would be read as that key.
    take = operator.itemgetter(name)
    layer: Dict[Any, Any] = {(array_name, k, *corner): (take, a.key) for k, a in enumerate(answers)}
    graph = HighLevelGraph.from_collections(array_name, layer, dependencies=answers)
    return da.Array(graph, array_name, chunks=(lengths, *((size,) for size in tail)), dtype=dtype)


class _Recorder(SceneLike):
    """A scene that answers a query with its record: `SceneLike`'s query methods run here, on the
    client, check their options as a scene does, and give the record the chunks' tasks answer."""

    instances: Tuple[Any, ...] = ()

    def answer(self, query: Query) -> Any:
        return query

    def update(self, transforms: Any = None, masks: Any = None) -> None:
        raise TypeError("a record of queries has no instances to update")


_RECORDER = _Recorder()


def _ray_graph(scene: Union[SceneSpec, Builder], query: RayQuery) -> Dict[str, da.Array]:
    """A ray query's graph: rays aligned to the origins' chunks, per-ray arguments to theirs
    (one value for every ray stays in the record)."""
    if query.progress or query.out is not None or query.cuda:
        raise TypeError("vkray.dask answers in dask arrays: progress, out= and cuda=True are not for it")
    spec = _as_scene_spec(scene)
    o = _rows("origins", query.origins)
    d = _rows("directions", query.directions)
    if d.shape != o.shape:
        raise ValueError(f"origins {o.shape} and directions {d.shape} must have the same shape (N, 3)")
    arrays = {"origins": o, "directions": d.rechunk(o.chunks)}
    for name in ("tmin", "tmax", "mask"):
        aligned = _per_ray(name, getattr(query, name), o)
        if aligned is not None:
            arrays[name] = aligned
    return _map_chunks(spec, query, arrays, _answer_fields(query))


def _point_graph(scene: Union[SceneSpec, Builder], query: PointQuery) -> Dict[str, da.Array]:
    """A point query's graph: one task per chunk of the points."""
    if query.progress:
        raise TypeError("vkray.dask answers in dask arrays: progress is not for it")
    spec = _as_scene_spec(scene)
    return _map_chunks(spec, query, {"points": _rows("points", query.points)}, _answer_fields(query))


def _answer_fields(query: Query) -> Dict[str, Tuple[np.dtype[Any], Tuple[int, ...]]]:
    """The (dtype, trailing shape) of each array of ``query``'s answer, by name (one
    ``"result"`` for queries that answer with one array)."""
    if query.kind in ("intersect", "closest_points"):
        return {name: field_type(name, query.precision) for name in query.outputs}
    one = {"occluded": np.dtype(bool), "count": np.dtype(np.int32), "contains": np.dtype(bool)}
    if query.kind in one:
        return {_ONE_ARRAY: (one[query.kind], ())}
    return {_ONE_ARRAY: field_type("t", query.precision)}  # transmittance, distances: the tier's floats


def _with_fields(query: Query, values: Dict[str, Any]) -> Query:
    """``query`` with the fields ``values`` names (its arrays: a chunk's, or None) replaced."""
    return cast(Query, dataclasses.replace(cast(Any, query), **values))


def _one_array(arrays: Dict[str, da.Array]) -> da.Array:
    """The answer of a query that answers with one array."""
    return arrays[_ONE_ARRAY]


def _fields(arrays: Dict[str, da.Array]) -> Dict[str, da.Array]:
    """The answer of a query that answers with fields: one dask array each."""
    return arrays


def _over_chunks(
    method: Callable[Concatenate[SceneLike, _P], Any],
    graph: Callable[[Any, Any], Dict[str, da.Array]],
    result: Callable[[Dict[str, da.Array]], _R],
    doc: str,
) -> Callable[Concatenate[Union[SceneSpec, Builder], _P], _R]:
    """``method`` of `SceneLike` over dask arrays: the same arguments after the scene (so defined
    once, there), checked by the method itself on the client; its record is answered chunk by
    chunk on the workers (``graph``), and ``result`` picks the answer out of the arrays."""

    def over_chunks(scene: Union[SceneSpec, Builder], /, *args: _P.args, **kwargs: _P.kwargs) -> _R:
        return result(graph(scene, method(_RECORDER, *args, **kwargs)))

    signature = inspect.signature(method)
    scene_parameter = inspect.Parameter("scene", inspect.Parameter.POSITIONAL_ONLY, annotation="SceneSpec | Builder")
    over_chunks.__signature__ = signature.replace(  # type: ignore[attr-defined]
        parameters=[scene_parameter, *list(signature.parameters.values())[1:]],
        return_annotation=inspect.signature(result).return_annotation,
    )
    over_chunks.__name__ = over_chunks.__qualname__ = method.__name__
    over_chunks.__doc__ = f"{doc}\n\nThe arguments after the scene: `Scene.{method.__name__}`'s (not progress, out=)."
    return over_chunks


intersect = _over_chunks(SceneLike.intersect, _ray_graph, _fields, """`Scene.intersect` over dask arrays of rays
(N, 3): a dict of dask arrays, one per field asked (``outputs``), chunked as ``origins``. ``tmin``,
``tmax`` and ``mask`` are one value, or one per ray (dask or numpy arrays of shape (N,)).""")
occluded = _over_chunks(SceneLike.occluded, _ray_graph, _one_array, """`Scene.occluded` over dask arrays of rays
(N, 3): a bool dask array (N,), chunked as ``origins``.""")
transmittance = _over_chunks(SceneLike.transmittance, _ray_graph, _one_array, """`Scene.transmittance` over dask
arrays of rays (N, 3): a float dask array (N,), chunked as ``origins``.""")
count = _over_chunks(SceneLike.count, _ray_graph, _one_array, """`Scene.count` over dask arrays of rays (N, 3): an
int32 dask array (N,), chunked as ``origins``.""")
contains = _over_chunks(SceneLike.contains, _point_graph, _one_array, """`Scene.contains` over a dask array of
points (N, 3): a bool dask array (N,).""")
closest_points = _over_chunks(SceneLike.closest_points, _point_graph, _fields, """`Scene.closest_points` over a
dask array of points (N, 3): a dict of dask arrays, one per field (``outputs``, ``"distance"`` always
among them).""")
distance = _over_chunks(SceneLike.distance, _point_graph, _one_array, """`Scene.distance` over a dask array of
points (N, 3): a float dask array (N,).""")
signed_distance = _over_chunks(SceneLike.signed_distance, _point_graph, _one_array, """`Scene.signed_distance` over
a dask array of points (N, 3): a float dask array (N,).""")


def local_cluster(
    devices: Optional[Sequence[Union[int, str]]] = None,
    *,
    threads_per_worker: int = 3,
    env: Optional[Mapping[str, str]] = None,
    memory_limit: Union[str, float, None] = "auto",
) -> SpecCluster:
    """A `dask.distributed` cluster on this machine with one worker process per device, each
    with ``VKRAY_DEVICE`` set to its device and ``RAYON_NUM_THREADS`` to an equal share of the
    cores for its host passes (unless this process's environment or ``env`` sets it: with every
    worker's passes on every core, they crowd each other; docs/benchmarks.md, issue 15); ``env``
    adds more variables to every worker.

    devices: indices or names as `vkray.Device` takes them; ``None``: every usable device, only
    the hardware ones where there are any (as `vkray.DeviceGroup` chooses). A device listed twice
    gets two workers. Use it as ``with local_cluster() as cluster, Client(cluster) as client:``.
    threads_per_worker: chunks each worker traces at once on its device (3 by default: while one
    chunk is on the GPU, the others' host passes and Dask's own work between tasks run; 1.5× one
    thread's rays/s on an H200 at 4M-ray chunks, docs/benchmarks.md, session 15). Each thread's
    query holds its own staging on the device, which the device keeps between queries
    (`vkray.Device.idle_memory`: 1.3 GB a query at the default 4M-ray chunks on an H200).
    memory_limit: each worker's, past which Dask spills its data to disk (60%), pauses it (80%)
    and restarts it (95%). ``"auto"`` (default): the machine's memory shared equally by the
    workers, as `distributed.LocalCluster` shares it (a `Nanny`'s own default gives a one-thread
    worker only its thread's share of the machine: 1/64 on 64 cores, where a GPU's worker holds
    far more); else what `Nanny` takes (bytes, ``"64 GiB"``, a fraction of the machine's memory,
    ``0`` or ``None`` for no limit).
    """
    from distributed import Nanny, Scheduler, SpecCluster

    threads_per_worker = _arrays.integer("threads_per_worker", threads_per_worker, 1, 1024)
    chosen = default_devices() if devices is None else list(devices)
    if not chosen:  # a cluster without workers would wait forever for one
        if devices is None:
            raise NoDeviceError("local_cluster found no usable device (vkray.devices() is empty)")
        raise ValueError("local_cluster needs at least one device")
    limit = 1 / max(len(chosen), 1) if memory_limit == "auto" else memory_limit
    shared: Dict[str, str] = {}
    if "RAYON_NUM_THREADS" not in os.environ:
        shared["RAYON_NUM_THREADS"] = str(max(1, usable_cores() // max(len(chosen), 1)))
    shared.update(env or {})
    workers = {
        f"vkray-{k}": {
            "cls": Nanny,
            "options": {
                "nthreads": threads_per_worker,
                "env": {**shared, "VKRAY_DEVICE": str(device)},
                "memory_limit": limit,
                "silence_logs": logging.WARN,
            },
        }
        for k, device in enumerate(chosen)
    }
    scheduler = {"cls": Scheduler, "options": {"host": "127.0.0.1", "dashboard_address": ":0"}}
    return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.WARN)
