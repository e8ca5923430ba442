"""Several devices as one: `DeviceGroup` builds every mesh and scene on each of its devices and
splits each query's rays (or points) over them, in proportion to each device's measured speed.

The pieces are contiguous runs of the caller's rays, traced at once by one thread per device (every
core call releases the GIL) and put back together in the caller's order, so a `GroupScene` answers
exactly what a `Scene` on any one of the devices answers: both are `SceneLike`, whose query methods
hand this module's `GroupScene.answer` the same records they hand `Scene.answer`.
"""

from __future__ import annotations

import collections.abc
import contextlib
import dataclasses
import inspect
import math
import os
import re
import threading
import time
from concurrent.futures import FIRST_EXCEPTION, Future, ThreadPoolExecutor, wait
from typing import (
    TYPE_CHECKING,
    Any,
    Callable,
    Dict,
    Generic,
    Iterable,
    Iterator,
    List,
    Optional,
    Sequence,
    Tuple,
    TypeVar,
    Union,
    cast,
    overload,
)

import numpy as np

from . import _arrays, _progress
from ._core import ForkedDeviceError, VkrayError
from ._device import Device, Instance, Mesh, Scene, devices
from ._options import CLOSEST_FIELDS, HIT_FIELDS, Backend, Build, Cull, Precision, VertexFormat
from ._queries import PointQuery, Query, RayQuery, SceneLike
from ._results import AllHits, Closest, Hits, new_hit_arrays, out_arrays
from .sensors import Sensor

T = TypeVar("T")
if TYPE_CHECKING:
    from typing_extensions import Concatenate, ParamSpec

    _P = ParamSpec("_P")


# A device's speed is measured on pieces of at least this many rays: smaller ones take about the
# same time whatever their size (a submission, a wait), which says nothing about the device.
_MIN_TIMED_RAYS = 1 << 14
# The weight of the newest measurement in a device's moving average of rays per second.
_SPEED_SMOOTHING = 0.5


class _Speeds:
    """Rays per second of each device, per query kind: exponential moving averages of the pieces'
    measured speeds. Unmeasured devices count as the mean of the measured ones (all equal at first)."""

    def __init__(self, device_count: int) -> None:
        self._device_count = device_count
        self._lock = threading.Lock()
        self._by_kind: Dict[str, List[Optional[float]]] = {}

    def record(self, kind: str, device: int, rays: int, seconds: float) -> None:
        """Folds one piece's time into the device's average (pieces too small to tell are ignored)."""
        if rays < _MIN_TIMED_RAYS or seconds <= 0:
            return
        measured = rays / seconds
        with self._lock:
            speeds = self._by_kind.setdefault(kind, [None] * self._device_count)
            old = speeds[device]
            speeds[device] = measured if old is None else (1 - _SPEED_SMOOTHING) * old + _SPEED_SMOOTHING * measured

    def weights(self, kind: str) -> List[float]:
        """Each device's share of the next query of this kind (proportional to its speed)."""
        with self._lock:
            speeds = list(self._by_kind.get(kind, [None] * self._device_count))
        known = [s for s in speeds if s is not None]
        fill = sum(known) / len(known) if known else 1.0
        return [fill if s is None else s for s in speeds]

    def snapshot(self) -> Dict[str, List[Optional[float]]]:
        """A copy of every kind's speeds (None where unmeasured)."""
        with self._lock:
            return {kind: list(speeds) for kind, speeds in self._by_kind.items()}


def split(count: int, weights: Sequence[float]) -> List[Tuple[int, int]]:
    """``[start, stop)`` of each device's contiguous piece of ``count`` items, sized in proportion
    to ``weights`` (rounded so that the pieces cover the items exactly once; some may be empty)."""
    total = float(sum(weights))
    cumulative = np.cumsum([0.0] + [float(w) for w in weights]) / total
    bounds = np.rint(cumulative * count).astype(np.int64)
    bounds[-1] = count
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


class _Cancelled(Exception):
    """Raised from a piece's progress reporter to stop it: an earlier piece failed, or the caller
    was interrupted."""


class _Run:
    """One query's pieces in flight: their progress added up into one bar (when asked for), and
    which of them are to stop at their next chunk.

    When piece p fails, the pieces after it stop: whatever they would raise, p's error comes first
    in the caller's rays. The pieces before it run on, since one of them may hold an earlier bad
    row, and the group raises the earliest error, as one device would."""

    def __init__(self, sizes: Sequence[int], bar: Optional[_progress.Progress]) -> None:
        self._sizes = sizes
        self._done = [0.0] * len(sizes)
        self._bar = bar
        self._lock = threading.Lock()
        self._stop_after = len(sizes)  # pieces after this one stop

    def fail(self, piece: int) -> None:
        """Piece ``piece`` failed: stop the pieces after it."""
        with self._lock:
            self._stop_after = min(self._stop_after, piece)

    def stop_all(self) -> None:
        """The caller was interrupted: stop every piece."""
        with self._lock:
            self._stop_after = -1

    def check(self, piece: int) -> None:
        """Raises `_Cancelled` where piece ``piece`` is to stop."""
        if piece > self._stop_after:
            raise _Cancelled()

    def reporter(self, piece: int) -> _progress.Reporter:
        """The callable that piece ``piece``'s core call reports (done, total) to."""

        def report(done: int, total: int) -> None:
            self.check(piece)
            if self._bar is not None:
                with self._lock:
                    self._done[piece] = self._sizes[piece] * done / max(total, 1)
                    self._bar(int(sum(self._done)), int(sum(self._sizes)))

        return report


# The row or ray a core error names ("origins row 7 ...", "ray 6 has tmax ..."), counted from the
# start of the piece it came from.
_ROW_IN_ERROR = re.compile(r"\b(row|ray) (\d+)")


def in_callers_rows(error: BaseException, start: int) -> BaseException:
    """The ValueError/TypeError of a piece that starts at row ``start`` of the caller's batch,
    naming its row as the caller counts it, so that a group of devices (or vkray.dask's chunks)
    raise what one device raises for the whole batch; other errors as they are."""
    if start == 0 or type(error) not in (ValueError, TypeError):
        return error
    message = _ROW_IN_ERROR.sub(lambda m: f"{m[1]} {int(m[2]) + start}", str(error), count=1)
    return type(error)(message).with_traceback(error.__traceback__)


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the platform tells it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


_SELF = inspect.Parameter("self", inspect.Parameter.POSITIONAL_ONLY)


def _on_every_device(method: Callable[Concatenate[Device, _P], Mesh]) -> Callable[
    Concatenate[DeviceGroup, _P], GroupMesh
]:
    """``Device.<method>`` as a `DeviceGroup` method: the same arguments, run on every device at
    once (an iterator among them read once, into a list, for all), its meshes one `GroupMesh`."""

    def on_every_device(group: DeviceGroup, /, *args: _P.args, **kwargs: _P.kwargs) -> GroupMesh:
        listed = [list(a) if isinstance(a, collections.abc.Iterator) else a for a in args]
        named = {k: list(v) if isinstance(v, collections.abc.Iterator) else v for k, v in kwargs.items()}
        build: Callable[..., Mesh] = method
        return GroupMesh(group, group.on_each(lambda d: build(d, *listed, **named)))

    signature = inspect.signature(method)
    on_every_device.__signature__ = signature.replace(  # type: ignore[attr-defined]
        parameters=[_SELF, *list(signature.parameters.values())[1:]],
        return_annotation="GroupMesh",
    )
    on_every_device.__name__ = on_every_device.__qualname__ = method.__name__
    on_every_device.__doc__ = f"`Device.{method.__name__}` on every device (at once): a `GroupMesh`."
    return on_every_device


class DeviceGroup:
    """Several devices used as one: meshes and scenes are built on each, and each query's rays are
    split over them in proportion to their speed, traced at once and merged in the caller's order.

    The API is `Device`'s: `mesh`, `spheres`, `mesh_from_parts`, `meshes` and `scene` take the same
    arguments and return `GroupMesh` and `GroupScene`, whose queries take and return what `Mesh`
    and `Scene`'s do (`SceneLike`). Answers are those of one device, ray for ray.

    Parameters
    ----------
    devices:
        ``None`` (default): every usable device of `vkray.devices()`, but only the hardware ones
        where any exists (a software device such as lavapipe is many times slower, and takes the
        CPU cores that feed the GPUs). Or a list whose items are device indices or names (as
        `Device` takes them) or already opened `Device` objects. A device may appear more than
        once: ``DeviceGroup([0, 0])`` opens device 0 twice, as two independent `Device`s.
    backend, validation:
        As `Device` takes them, for the devices this group opens itself.
    weights:
        Fixed shares of each query's rays, one per device (for devices of known relative speed,
        or to choose the split). ``None`` (default) measures them: the first query of a kind is
        split equally; each piece's rays per second then update an exponential moving average per
        device and query kind (`speeds`), which sizes the next query's pieces.
    host_threads:
        Threads of its own for each device this group opens (`Device.host_threads`), for its
        pieces' host passes (packing rays, copying hits out). ``None`` (default): the cores this
        process may run on, shared out equally, when the group has more than one device, so that
        the devices' passes run side by side instead of queuing in one pool (docs/benchmarks.md,
        issue 15). Devices given already opened keep theirs.
    """

    def __init__(
        self,
        devices: Optional[Sequence[Union[int, str, Device]]] = None,
        *,
        backend: Optional[Backend] = None,
        validation: bool = False,
        weights: Optional[Sequence[float]] = None,
        host_threads: Optional[int] = None,
    ) -> None:
        if devices is not None and (isinstance(devices, (str, bytes, int, Device)) or not hasattr(devices, "__iter__")):
            raise TypeError(
                f"devices must be a list of device indices, names or Devices (or None for every GPU), got "
                f"{type(devices).__name__} {devices!r}: e.g. DeviceGroup([{devices!r}])"
            )
        chosen = default_devices() if devices is None else list(devices)
        if not chosen:
            raise ValueError("a DeviceGroup needs at least one device")
        if host_threads is not None:
            host_threads = _arrays.integer("host_threads", host_threads, 1, 4096)
        elif len(chosen) > 1:
            host_threads = max(1, usable_cores() // len(chosen))
        opened = [
            d if isinstance(d, Device) else Device(d, backend, validation=validation, host_threads=host_threads)
            for d in chosen
        ]
        self.devices: Tuple[Device, ...] = tuple(opened)
        if weights is not None:
            if isinstance(weights, (str, bytes)) or not hasattr(weights, "__iter__"):
                raise TypeError(f"weights must be a list of numbers, one per device, got {weights!r}")
            weights = [float(w) for w in weights]
            finite = all(math.isfinite(w) and w >= 0 for w in weights)
            if len(weights) != len(self.devices) or not finite or not sum(weights) > 0:
                raise ValueError(
                    f"weights must be {len(self.devices)} finite numbers >= 0 (one per device), not all 0, "
                    f"got {weights}"
                )
        self._weights = weights
        self._speeds = _Speeds(len(self.devices))
        # One thread per device: its pieces of every query, in the order they were asked for.
        self._threads = [ThreadPoolExecutor(1, thread_name_prefix=f"vkray-device-{k}") for k in range(len(opened))]
        self._busy = [0] * len(self.devices)
        self._busy_lock = threading.Lock()
        # The threads above exist in this process only: a forked child is refused (as a Device is)
        # instead of waiting forever for them.
        self._pid = os.getpid()

    def _check_process(self) -> None:
        """Raises ForkedDeviceError in a forked child of the process that opened the group."""
        if os.getpid() != self._pid:
            raise ForkedDeviceError(
                f"this DeviceGroup was opened in process {self._pid}, and process {os.getpid()} is a forked child of "
                f"it: its devices and threads stay in the parent; open a new DeviceGroup in the child (or start it "
                f"with multiprocessing's 'spawn' or 'forkserver')"
            )

    def __len__(self) -> int:
        return len(self.devices)

    @property
    def speeds(self) -> Dict[str, List[Optional[float]]]:
        """Measured rays (or points) per second of each device, by query kind (``"intersect/fast"``,
        ``"count/exact"``, ``"intersect/cuda"`` for CUDA rays, ...); ``None`` where a device has not
        been measured yet."""
        return self._speeds.snapshot()

    @property
    def chunk_rays(self) -> List[int]:
        """Each device's `Device.chunk_rays`."""
        return [d.chunk_rays for d in self.devices]

    @chunk_rays.setter
    def chunk_rays(self, rays: int) -> None:
        for d in self.devices:
            d.chunk_rays = rays

    @property
    def idle_memory(self) -> List[Dict[str, int]]:
        """Each device's `Device.idle_memory`: the staging it keeps between queries."""
        return [d.idle_memory for d in self.devices]

    def release_idle_memory(self) -> None:
        """Frees the staging every device keeps between queries (`Device.release_idle_memory`)."""
        for d in self.devices:
            d.release_idle_memory()

    def weights(self, kind: str) -> List[float]:
        """Each device's share of the next query of ``kind`` (see `speeds`), or the fixed weights."""
        return list(self._weights) if self._weights is not None else self._speeds.weights(kind)

    mesh = _on_every_device(Device.mesh)
    spheres = _on_every_device(Device.spheres)
    mesh_from_parts = _on_every_device(Device.mesh_from_parts)

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
    ) -> List[GroupMesh]:
        """`Device.meshes` on every device (at once); ``progress=True`` shows the first device's bar."""
        items = list(items)

        def build_on(k: int, d: Device) -> List[Mesh]:
            return d.meshes(
                items,
                build=build,
                allow_update=allow_update,
                compact=compact,
                budget_bytes=budget_bytes,
                vertex_format=vertex_format,
                progress=progress and k == 0,
            )

        per_device = self.on_each(build_on, with_index=True)
        return [GroupMesh(self, meshes) for meshes in zip(*per_device)]

    def scene(
        self,
        items: Union[GroupMesh, GroupInstance, Iterable[Union[GroupMesh, GroupInstance]]],
        *,
        build: Build = "fast_build",
        allow_update: bool = False,
        compact: bool = False,
    ) -> GroupScene:
        """`Device.scene` on every device (at once), over `GroupMesh`es and `GroupInstance`s."""
        if isinstance(items, (GroupMesh, GroupInstance, Mesh, Instance)):  # one item (a device's: refused below)
            items = [items]
        instances: List[GroupInstance] = []
        for i, item in enumerate(items):
            if isinstance(item, GroupMesh):
                item = GroupInstance(item)
            if not isinstance(item, GroupInstance):
                raise TypeError(
                    f"scene item {i} must be a GroupMesh or a GroupInstance (of this DeviceGroup), "
                    f"got {type(item).__name__}"
                )
            if item.mesh.group is not self:
                raise ValueError(f"scene item {i} uses a mesh built on another DeviceGroup")
            instances.append(item)

        def build_on(k: int, d: Device) -> Scene:
            return d.scene(
                [x.per_device[k] for x in instances], build=build, allow_update=allow_update, compact=compact
            )

        return GroupScene(self, self.on_each(build_on, with_index=True), instances)

    def on_each(self, work: Callable[..., T], *, with_index: bool = False) -> List[T]:
        """``work(device)`` (or ``work(index, device)``) on every device at once, each in its
        device's thread; the results in device order. When any raises, all are waited for and the
        first device's error (in device order) is raised."""
        self._check_process()
        futures = [
            thread.submit(work, *((k, d) if with_index else (d,)))
            for k, (thread, d) in enumerate(zip(self._threads, self.devices))
        ]
        wait(futures)
        for future in futures:
            error = future.exception()
            if error is not None:
                raise error
        return [future.result() for future in futures]

    def _least_busy(self, kind: str, among: Optional[Sequence[int]] = None) -> int:
        """The device with the fewest pieces in flight, the fastest for ``kind`` among those (of
        ``among``, where given)."""
        weights = self.weights(kind)
        members = range(len(self.devices)) if among is None else among
        with self._busy_lock:
            return min(members, key=lambda k: (self._busy[k], -weights[k]))

    def _run_piece(self, device: int, run: _Run, piece: int, rays: int, work: Callable[[], T], kind: str) -> T:
        """One piece in its device's thread: reports to its query's run, and times the device."""
        try:
            run.check(piece)  # an earlier piece may have failed while this one waited its turn
            with _progress.reporting(run.reporter(piece)):
                start = time.perf_counter()
                result = work()
                self._speeds.record(kind, device, rays, time.perf_counter() - start)
                return result
        finally:
            with self._busy_lock:
                self._busy[device] -= 1

    def _run_pieces(
        self, kind: str, pieces: Sequence[Tuple[int, int, int]], work: Callable[[int, int, int], T], progress: bool
    ) -> List[T]:
        """``work(device, start, stop)`` for each piece ``(device, start, stop)`` of a query of
        ``kind``, in that device's thread, all at once; the results in the pieces' order.

        A failing piece stops the pieces after it (at their next chunk), and Ctrl-C in the calling
        thread stops them all; every piece is waited for, then the earliest piece's error is
        raised, naming rows as the caller counts them (see `_Run`)."""
        self._check_process()
        bar = _progress.Progress(kind.split("/")[0]) if progress else None
        run = _Run([stop - start for _, start, stop in pieces], bar)
        futures: List[Future[T]] = []
        try:
            for p, (device, start, stop) in enumerate(pieces):
                with self._busy_lock:
                    self._busy[device] += 1

                def piece(device: int = device, start: int = start, stop: int = stop) -> T:
                    return work(device, start, stop)

                futures.append(self._threads[device].submit(self._run_piece, device, run, p, stop - start, piece, kind))
            _wait_stopping_after_failures(futures, run)
        except BaseException:
            run.stop_all()
            wait(futures)
            raise
        finally:
            if bar is not None:
                bar.close()
        for future, (_, start, _) in zip(futures, pieces):
            error = future.exception()
            if error is not None and not isinstance(error, _Cancelled):
                raise in_callers_rows(error, start)
        return [future.result() for future in futures]

    def __repr__(self) -> str:
        names = ", ".join(repr(d.name) for d in self.devices)
        return f"<vkray.DeviceGroup of {len(self.devices)} devices: {names}>"


def _wait_stopping_after_failures(futures: Sequence[Future[Any]], run: _Run) -> None:
    """Waits for every piece, telling the run of each failure as it happens."""
    index = {future: p for p, future in enumerate(futures)}
    pending = set(futures)
    while pending:
        done, pending = wait(pending, return_when=FIRST_EXCEPTION)
        for future in done:
            if future.exception() is not None:
                run.fail(index[future])


def default_devices() -> List[Union[int, str, Device]]:
    """The devices a group takes by default: every ray-tracing GPU, else the CPU engine (which
    uses every core itself), else every software device."""
    found = devices()
    gpus = [d.index for d in found if d.engine == "vulkan" and not d.is_software]
    cpu = [d.index for d in found if d.engine == "cpu"]
    return list(gpus or cpu or [d.index for d in found])


class _OfFirstDevice(Generic[T]):
    """A read-only attribute of a group's object that is its first device's object's attribute of
    the same name (the same on every device): `GroupMesh.vertices` is ``per_device[0].vertices``."""

    def __init__(self, doc: str) -> None:
        self.__doc__ = doc
        self._name = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self._name = name

    @overload
    def __get__(self, group_object: None, owner: type) -> _OfFirstDevice[T]: ...

    @overload
    def __get__(self, group_object: object, owner: type) -> T: ...

    def __get__(self, group_object: Optional[object], owner: type) -> Union[T, _OfFirstDevice[T]]:
        if group_object is None:
            return self
        return cast(T, getattr(cast(Any, group_object).per_device[0], self._name))


class GroupMesh:
    """One mesh on every device of a `DeviceGroup` (`per_device[k]` is device k's `Mesh`)."""

    def __init__(self, group: DeviceGroup, per_device: Sequence[Mesh]) -> None:
        self.group = group
        self.per_device: Tuple[Mesh, ...] = tuple(per_device)

    vertices: _OfFirstDevice[np.ndarray] = _OfFirstDevice("As `Mesh.vertices` (the same on every device).")
    faces: _OfFirstDevice[Optional[np.ndarray]] = _OfFirstDevice("The triangles' corner indices; ``None`` for spheres.")
    vertex_count: _OfFirstDevice[int] = _OfFirstDevice("Vertices (spheres) per device.")
    triangle_count: _OfFirstDevice[int] = _OfFirstDevice("Triangles per device.")
    kind: _OfFirstDevice[str] = _OfFirstDevice('``"triangles"``, or ``"spheres"``.')
    is_closed: _OfFirstDevice[bool] = _OfFirstDevice("`Mesh.is_closed`.")

    def update(self, vertices: Any) -> None:
        """`Mesh.update` on every device, one after another (the first device's error, if any,
        leaves every device's mesh as it was)."""
        for mesh in self.per_device:
            mesh.update(vertices)

    def __repr__(self) -> str:
        return f"<vkray.GroupMesh {self.per_device[0]!r} on {len(self.per_device)} devices>"


class GroupInstance:
    """A `GroupMesh` placed in a group's scene: `Instance`'s arguments, one `Instance` per device
    (`per_device`); invalid arguments raise as `Instance` raises them."""

    def __init__(
        self,
        mesh: GroupMesh,
        transform: Any = None,
        *,
        custom_index: int = 0,
        mask: int = 0xFF,
        cull_disable: bool = False,
        flip_facing: bool = False,
        opaque: Optional[bool] = None,
    ) -> None:
        if not isinstance(mesh, GroupMesh):
            raise TypeError(f"mesh must be a vkray.GroupMesh, got {type(mesh).__name__}")
        self.mesh = mesh
        self.per_device: Tuple[Instance, ...] = tuple(
            Instance(
                m,
                transform,
                custom_index=custom_index,
                mask=mask,
                cull_disable=cull_disable,
                flip_facing=flip_facing,
                opaque=opaque,
            )
            for m in mesh.per_device
        )

    transform: _OfFirstDevice[Optional[np.ndarray]] = _OfFirstDevice(
        "As `Instance.transform` (`GroupScene.update` changes it)."
    )
    custom_index: _OfFirstDevice[int] = _OfFirstDevice("As `Instance.custom_index`.")
    mask: _OfFirstDevice[int] = _OfFirstDevice("As `Instance.mask` (`GroupScene.update` changes it).")

    def __repr__(self) -> str:
        return f"<vkray.GroupInstance of {self.mesh!r} custom_index={self.custom_index} mask={self.mask:#04x}>"


class _RaysToSplit:
    """A query's rays as `Scene` would read them (broadcast, flattened), cut into contiguous pieces
    that each device's `Scene` reads back as exactly those rays."""

    def __init__(self, q: RayQuery) -> None:
        self.shape, self.origins, self.directions, self.tmin, self.tmax = _arrays.rays(
            q.origins, q.directions, q.tmin, q.tmax
        )
        self.mask = _arrays.masks(q.mask, self.shape)
        self.count = int(np.prod(self.shape, dtype=np.int64))

    def piece(self, start: int, stop: int) -> Dict[str, Any]:
        """The arguments of rays ``start:stop``: arrays of one row per ray are cut, one row shared
        by every ray (an eye) and scalars stay as they are."""

        def cut(value: Any) -> Any:
            return value[start:stop] if isinstance(value, np.ndarray) and len(value) == self.count else value

        return {
            "origins": cut(self.origins),
            "directions": cut(self.directions),
            "tmin": cut(self.tmin),
            "tmax": cut(self.tmax),
            "mask": cut(self.mask),
        }


def _cuda_rows(*arrays: Any) -> int:
    """Rays in a batch of CUDA arrays of shape S + (3,) (one of them may be a single row), for
    the progress bar and the devices' speeds: 0 where their shapes do not say."""
    rows = [int(np.prod(tuple(a.shape)[:-1], dtype=np.int64)) for a in arrays if hasattr(a, "shape")]
    return max(rows, default=0)


def _join(parts: Sequence[Optional[np.ndarray]]) -> Optional[np.ndarray]:
    """The pieces' arrays of one field end to end (None where the field was not asked)."""
    if parts[0] is None:
        return None
    return np.concatenate([p for p in parts if p is not None])


def _join_all_hits(shape: Tuple[int, ...], parts: Sequence[AllHits], starts: Sequence[int]) -> AllHits:
    """The pieces' `AllHits` as one: each piece's hits follow the previous pieces', so its offsets
    shift by the hits before it (the ray indices, made from the offsets, follow)."""
    hits_before = np.cumsum([0] + [int(p.offsets[-1]) for p in parts])
    offsets = [parts[0].offsets[:1]] + [p.offsets[1:] + h for p, h in zip(parts, hits_before)]
    arrays: Dict[str, np.ndarray] = {"offsets": np.concatenate(offsets)}
    for name in HIT_FIELDS:
        joined = _join([getattr(p, name) for p in parts])
        if joined is not None:
            arrays[name] = joined
    return AllHits(shape, arrays, parts[0].precision)


class _UpdateLock:
    """Queries share it, `GroupScene.update` takes it alone, so that all the pieces of a query see
    the scene as it was before an update, or all as it is after (on one device, `Scene.update`
    waits for the queries running on the scene, and queries started meanwhile wait for it).

    Fair both ways: queries asked during an update wait for it, and go before the next update."""

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._running = 0  # queries
        self._waiting = 0  # queries held by an update
        self._updating = False

    @contextlib.contextmanager
    def query(self) -> Iterator[None]:
        """Held by a query for as long as its pieces run."""
        with self._condition:
            self._waiting += 1
            try:
                self._condition.wait_for(lambda: not self._updating)
            finally:
                self._waiting -= 1
                self._condition.notify_all()
            self._running += 1
        try:
            yield
        finally:
            with self._condition:
                self._running -= 1
                self._condition.notify_all()

    @contextlib.contextmanager
    def update(self) -> Iterator[None]:
        """Held by an update alone, once the queries before it are done."""
        with self._condition:
            self._condition.wait_for(lambda: not self._updating and self._waiting == 0)
            self._updating = True  # queries asked from now on wait
            try:
                self._condition.wait_for(lambda: self._running == 0)
            except BaseException:  # Ctrl-C while waiting: no update, and no query left waiting
                self._updating = False
                self._condition.notify_all()
                raise
        try:
            yield
        finally:
            with self._condition:
                self._updating = False
                self._condition.notify_all()


class GroupScene(SceneLike):
    """A scene built on every device of a `DeviceGroup` (`per_device[k]` is device k's `Scene`).

    Its queries are `Scene`'s, with the same arguments and results (`SceneLike`): the rays (or
    points) of each query record (`answer`) are split into contiguous pieces, one per device,
    sized by `DeviceGroup.weights`,
    traced at once and merged in the caller's order. A sensor (`vkray.PinholeCamera`, ...) is not
    split, since its rays are generated on the device: each sensor query runs whole on the least
    busy device, so that sensor queries from several threads spread over the devices. Batches of
    at most one ray, and 0 rays, run on one device too. CUDA rays of `intersect` and `occluded`
    are split from the GPU that holds them, and their hits come back there (`_trace_cuda`).
    `progress=True` shows one bar for all pieces; a piece's error stops the others and is raised
    as one device would raise it."""

    def __init__(self, group: DeviceGroup, per_device: Sequence[Scene], instances: Sequence[GroupInstance]) -> None:
        self.group = group
        self.per_device: Tuple[Scene, ...] = tuple(per_device)
        self.instances: Tuple[GroupInstance, ...] = tuple(instances)
        self._updates = _UpdateLock()

    def update(self, transforms: Any = None, masks: Any = None) -> None:
        """`Scene.update` on every device, one after another (bad arguments raise on the first
        device, before any scene changes). It waits for the queries running on this scene, and
        queries asked meanwhile wait for it: no query mixes pieces from before and after."""
        with self._updates.update():
            for scene in self.per_device:
                scene.update(transforms, masks)

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
        """`Scene.explain` of the first device's scene (devices of one kind run the same variant)."""
        return self.per_device[0].explain(
            kind, outputs, precision, cull, opacity_threshold=opacity_threshold, sensor=sensor
        )

    def answer(self, query: Query) -> Any:
        """The answer to a `RayQuery` or `PointQuery`, split over the devices (`SceneLike.answer`)."""
        if isinstance(query, RayQuery):
            return self._trace(query, _assembly(query))
        return self._points(query, _assembly(query))

    def _run(
        self, kind: str, pieces: Sequence[Tuple[int, int, int]], work: Callable[[int, int, int], T], progress: bool
    ) -> List[T]:
        """`DeviceGroup._run_pieces`, never during an `update`."""
        with self._updates.query():
            return self.group._run_pieces(kind, pieces, work, progress)

    def _whole(
        self, kind: str, count: int, call: Callable[[Scene], T], progress: bool, on_cuda: bool = False
    ) -> T:
        """A query of ``count`` rays run unsplit on the least busy device (of those that are CUDA
        GPUs, ``on_cuda``: a ``cuda=True`` answer lands on the GPU that traced it), in its thread,
        stoppable as pieces are."""
        among = None
        if on_cuda:
            among = [k for k, d in enumerate(self.group.devices) if d.cuda_device is not None]
            if not among:
                raise TypeError("cuda=True: none of this group's devices shares memory with CUDA")
        device = self.group._least_busy(kind, among)
        return self._run(kind, [(device, 0, count)], lambda k, _start, _stop: call(self.per_device[k]), progress)[0]

    def _cuda_member(self, *arrays: Any) -> int:
        """The index of the group's device whose GPU holds these CUDA arrays."""
        places = [_arrays.dlpack_device(a) for a in arrays]
        ordinal = next(p[1] for p in places if p is not None and p[0] == _arrays.DLPACK_CUDA)
        for k, device in enumerate(self.group.devices):
            if device.cuda_device == ordinal:
                return k
        members = ", ".join(f"{d.name} (cuda:{d.cuda_device})" for d in self.group.devices)
        raise ValueError(
            f"the arrays live on cuda:{ordinal}, which is none of this group's devices ({members}): pass them on one "
            f"of those GPUs, or as numpy arrays to be split over all of them"
        )

    def _pieces(self, kind: str, count: int) -> List[Tuple[int, int, int]]:
        """(device, start, stop) of each non-empty piece of ``count`` rays."""
        spans = split(count, self.group.weights(kind))
        return [(k, start, stop) for k, (start, stop) in enumerate(spans) if stop > start]

    def _trace(self, q: RayQuery, assembly: _Assembly[T]) -> T:
        """The answer to ``q``: whole where its rays cannot be split (or where one device takes
        them all), else in pieces put together by ``assembly``; into ``q.out``'s arrays where
        given (`Scene.intersect`'s ``out=``)."""
        kind = f"{q.kind}/{q.precision}"

        def unsplit(scene: Scene) -> T:
            return cast(T, scene.answer(dataclasses.replace(q, progress=False)))

        if isinstance(q.origins, Sensor):
            return self._whole(kind, len(q.origins), unsplit, q.progress, on_cuda=q.cuda)
        if _arrays.on_cuda(q.origins, q.directions):
            return self._trace_cuda(q, unsplit)
        if q.cuda:
            raise TypeError(
                "cuda=True in a DeviceGroup is for sensors (their answer lands on the GPU that traced them): pass "
                "CUDA rays to keep the answer on their GPU"
            )
        if q.directions is None:  # the device raises what it raises
            return self._whole(kind, 0, unsplit, q.progress)
        batch = _RaysToSplit(q)
        if batch.count <= 1 or len(self.per_device) == 1:
            return self._whole(kind, batch.count, unsplit, q.progress)

        inputs = (batch.origins, batch.directions, batch.tmin, batch.tmax, batch.mask)
        into = None if q.out is None else out_arrays(q.out, batch.shape, q.outputs, q.precision, inputs)
        pieces = self._pieces(kind, batch.count)
        if q.kind == "intersect" and len(pieces) > 1:
            # Each piece's hits written by its device straight into the batch's rows (Scene's
            # out=): no arrays of the piece's own to fault in and copy over (docs/benchmarks.md).
            into = into if into is not None else new_hit_arrays(batch.count, q.outputs, q.precision)

        def piece(device: int, start: int, stop: int) -> T:
            rows = None if into is None else _piece_hits(into, start, stop, q.precision)
            part = q.with_rays(**batch.piece(start, stop), progress=False, out=rows)
            return cast(T, self.per_device[device].answer(part))

        return self._assemble(kind, pieces, piece, unsplit, assembly, batch.shape, q.progress, into)

    def _trace_cuda(self, q: RayQuery, unsplit: Callable[[Scene], T]) -> T:
        """``q`` of CUDA rays, whose hits come back on the GPU that holds them. `intersect` and
        `occluded` (the fast tier, every device a CUDA GPU) are split: each device copies its rows
        from that GPU, traces them, and copies its hits into the batch's arrays there, all in
        CUDA's stream order (over NVLink or PCIe, never through the host). Other queries run whole
        on the device that is that GPU, which answers them as `Scene` does."""
        home = self._cuda_member(q.origins, q.directions)
        kind = f"{q.kind}/cuda"
        count = _cuda_rows(q.origins, q.directions)

        def whole() -> T:
            run = self._run(kind, [(home, 0, count)], lambda k, _start, _stop: unsplit(self.per_device[k]), q.progress)
            return run[0]

        splittable = (
            q.kind in ("intersect", "occluded")
            and q.precision == "fast"  # the pieces trace in the fast tier (`trace_cuda_piece`)
            and q.stays_on_gpu
            and len(self.per_device) > 1
            and all(d.cuda_device is not None for d in self.group.devices)
        )
        pieces = self._pieces(kind, count) if splittable and count > 1 else []
        if len(pieces) <= 1:
            return whole()
        batch = self.per_device[home].split_cuda_rays(q)
        if len(batch) != count:  # shapes the arrays' own do not say (the core checked them)
            pieces = self._pieces(kind, len(batch))

        def piece(device: int, start: int, stop: int) -> None:
            self.per_device[device].trace_cuda_rows(batch, start, stop, q)

        self._run(kind, pieces, piece, q.progress)
        arrays: Dict[str, Any] = batch.finish()
        if q.kind == "occluded":
            return cast(T, arrays["prim_id"])
        return cast(T, Hits(tuple(batch.shape), arrays, "fast"))

    def _points(self, q: PointQuery, assembly: _Assembly[T]) -> T:
        """The answer to ``q``, its points of shape ``S + (3,)`` split as `_trace` splits rays."""
        kind = f"{q.kind}/{q.precision}"

        def query(scene: Scene, p: Any) -> T:
            return cast(T, scene.answer(q.with_points(p, progress=False)))

        def unsplit(scene: Scene) -> T:
            return query(scene, q.points)

        if _arrays.on_cuda(q.points, names=("points",)):
            # Answered on their GPU's device, through the host (`Scene._through_host`).
            home = self._cuda_member(q.points)
            rows = _cuda_rows(q.points)
            whole = self._run(kind, [(home, 0, rows)], lambda k, _a, _b: unsplit(self.per_device[k]), q.progress)
            return whole[0]
        p = _arrays.real_coordinates("points", q.points)
        if len(self.per_device) == 1 or p.ndim == 0 or p.shape[-1] != 3 or p.size <= 3:
            return self._whole(kind, p.size // 3, unsplit, q.progress)
        flat = p.reshape(-1, 3)

        def piece(device: int, start: int, stop: int) -> T:
            return query(self.per_device[device], flat[start:stop])

        pieces = self._pieces(kind, len(flat))
        try:
            return self._assemble(kind, pieces, piece, unsplit, assembly, p.shape[:-1], q.progress)
        except (ValueError, TypeError, VkrayError) as error:
            raise self._point_error(error, flat, query) from None

    def _point_error(self, error: BaseException, flat: np.ndarray, query: Callable[[Scene, Any], Any]) -> BaseException:
        """What one device raises for the whole batch of points, where the pieces raised ``error``.

        One device checks every point before some of a query's options (a tier it does not
        answer, spheres): a piece without bad points raises the option's error, where one device
        would name the first non-finite point. Its error is then the one-point query's at that
        point, its row counted in the caller's points (found only on this failing path)."""
        bad = ~np.isfinite(flat).all(axis=1)
        if not bad.any():
            return error
        row = int(np.argmax(bad))
        try:
            query(self.per_device[0], flat[row : row + 1])
        except (ValueError, TypeError, VkrayError) as alone:
            return in_callers_rows(alone, row)
        return error

    def _assemble(
        self,
        kind: str,
        pieces: List[Tuple[int, int, int]],
        piece: Callable[[int, int, int], T],
        unsplit: Callable[[Scene], T],
        assembly: _Assembly[T],
        shape: Tuple[int, ...],
        progress: bool,
        into: Optional[Dict[str, np.ndarray]] = None,
    ) -> T:
        """The batch's answer from ``piece(device, start, stop)`` of each of ``pieces`` (per-ray
        answers written into ``into``'s arrays, one row per ray, where given).

        One piece (one device takes every ray): that device's answer to the whole batch
        (``unsplit``), nothing to copy. Per-ray answers: each piece writes its rows into the
        batch's arrays from its own thread as it finishes (`_Rows`), at once with the other
        pieces' work. Others (`AllHits`): the pieces' answers joined once all are done."""
        if len(pieces) == 1:
            return self._run(kind, pieces, lambda device, _start, _stop: unsplit(self.per_device[device]), progress)[0]
        if not assembly.in_place:
            parts = self._run(kind, pieces, piece, progress)
            return assembly.join(shape, parts, [start for _, start, _ in pieces])
        rows = _Rows(int(np.prod(shape, dtype=np.int64)), into)

        def write(device: int, start: int, stop: int) -> None:
            rows.put(start, stop, assembly.arrays(piece(device, start, stop)))

        self._run(kind, pieces, write, progress)
        return assembly.whole(shape, rows.arrays())

    def __repr__(self) -> str:
        return f"<vkray.GroupScene {len(self.instances)} instances on {len(self.per_device)} devices>"


def _assembly(q: Query) -> _Assembly[Any]:
    """How the answers to ``q``'s pieces make its answer."""
    if q.kind == "intersect":
        return _Fields(HIT_FIELDS, lambda shape, arrays: Hits(shape, arrays, q.precision))
    if q.kind == "intersect_all":
        return _Joined(_join_all_hits)
    if q.kind == "closest_points":
        return _Fields(CLOSEST_FIELDS, lambda shape, arrays: Closest(shape, arrays, q.precision))
    return _Array()  # occluded, transmittance, count, distance, signed_distance, contains


class _Assembly(Generic[T]):
    """How a split query's answer is put together from its pieces' answers: per-ray (or per-point)
    arrays written in place (`in_place`: `arrays` of each piece into the batch's, then `whole`),
    or the pieces' answers joined once all are done (`join`)."""

    in_place = True

    def arrays(self, part: T) -> Dict[str, np.ndarray]:
        """A piece's per-ray arrays, by name."""
        raise NotImplementedError

    def whole(self, shape: Tuple[int, ...], arrays: Dict[str, np.ndarray]) -> T:
        """The batch's answer, of shape ``shape``, from its (flat) per-ray arrays."""
        raise NotImplementedError

    def join(self, shape: Tuple[int, ...], parts: List[T], starts: List[int]) -> T:
        """The batch's answer from its pieces' answers (``starts``: each piece's first ray)."""
        raise NotImplementedError


class _Array(_Assembly[np.ndarray]):
    """One array, one row per ray or point (occluded, count, transmittance, distance, contains)."""

    def arrays(self, part: np.ndarray) -> Dict[str, np.ndarray]:
        return {"": part}

    def whole(self, shape: Tuple[int, ...], arrays: Dict[str, np.ndarray]) -> np.ndarray:
        return arrays[""].reshape(shape)


class _Fields(_Assembly[T]):
    """`Hits` or `Closest`: the fields the query computed (the same in every piece)."""

    def __init__(self, names: Sequence[str], make: Callable[[Tuple[int, ...], Dict[str, np.ndarray]], T]) -> None:
        self._names = names
        self._make = make

    def arrays(self, part: T) -> Dict[str, np.ndarray]:
        found = {name: getattr(part, name) for name in self._names}
        return {name: array for name, array in found.items() if array is not None}

    def whole(self, shape: Tuple[int, ...], arrays: Dict[str, np.ndarray]) -> T:
        return self._make(shape, arrays)


class _Joined(_Assembly[T]):
    """Answers joined once every piece is done (`AllHits`: each ray's number of hits varies)."""

    in_place = False

    def __init__(self, join: Callable[[Tuple[int, ...], List[T], List[int]], T]) -> None:
        self._join = join

    def join(self, shape: Tuple[int, ...], parts: List[T], starts: List[int]) -> T:
        return self._join(shape, parts, starts)


# Rows copied by one thread at a time: big copies are cut into blocks of about this many bytes,
# copied by several threads at once (numpy copies without holding the GIL).
_COPY_BLOCK_BYTES = 1 << 22
_copiers: Optional[ThreadPoolExecutor] = None
_copiers_lock = threading.Lock()


def _piece_hits(whole: Dict[str, np.ndarray], start: int, stop: int, precision: Precision) -> Hits:
    """`Hits` of rays ``start:stop`` whose arrays are those rows of the batch's (views), for a
    piece's `Scene.intersect` to write into (``out=``)."""
    return Hits((stop - start,), {name: array[start:stop] for name, array in whole.items()}, precision)


def _same_view(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two arrays are the same memory seen the same way (nothing to copy)."""
    return (
        a.shape == b.shape
        and a.dtype == b.dtype
        and a.strides == b.strides
        and a.__array_interface__["data"][0] == b.__array_interface__["data"][0]
    )


def _copy_rows(dst: np.ndarray, src: np.ndarray) -> None:
    """``dst[...] = src`` (arrays of equal shape, rows along the first axis); big arrays by blocks
    of rows on up to 16 threads, as the core's own host passes use every core: one thread alone
    reads and writes memory several times slower than the machine can."""
    global _copiers
    rows = max(1, _COPY_BLOCK_BYTES // max(1, src[:1].nbytes))
    if len(src) <= 2 * rows:
        dst[...] = src
        return
    with _copiers_lock:
        if _copiers is None:
            _copiers = ThreadPoolExecutor(min(16, os.cpu_count() or 1), thread_name_prefix="vkray-copy")
        copiers = _copiers

    def block(start: int) -> None:
        dst[start : start + rows] = src[start : start + rows]

    for _ in copiers.map(block, range(0, len(src), rows)):
        pass


class _Rows:
    """A split query's per-ray arrays for the whole batch, written piece by piece: each piece
    copies its rows in from its device's thread as it finishes (numpy copies without holding the
    GIL), at once with the other pieces' work, rather than one thread concatenating every piece's
    arrays after the last one. The first piece to finish makes them, of its arrays' dtypes, unless
    the caller's are given (``out=``)."""

    def __init__(self, count: int, into: Optional[Dict[str, np.ndarray]] = None) -> None:
        self._count = count
        self._arrays: Optional[Dict[str, np.ndarray]] = into
        self._lock = threading.Lock()

    def put(self, start: int, stop: int, arrays: Dict[str, np.ndarray]) -> None:
        """Writes a piece's arrays (its rays ``start:stop``) into the batch's; those that are
        already the batch's rows (the piece wrote them there itself) stay as they are. A piece
        that answered another number of rays is refused: its rows would leave others unwritten."""
        short = [name for name, array in arrays.items() if len(array) != stop - start]
        if short:
            raise VkrayError(f"a piece of rays {start}:{stop} answered {len(arrays[short[0]])} rows of {short[0]}")
        with self._lock:
            if self._arrays is None:
                self._arrays = {
                    name: np.empty((self._count,) + array.shape[1:], array.dtype) for name, array in arrays.items()
                }
            whole = self._arrays
        for name, array in arrays.items():
            rows = whole[name][start : start + len(array)]
            if not _same_view(rows, array):
                _copy_rows(rows, array)

    def arrays(self) -> Dict[str, np.ndarray]:
        """The batch's arrays, once every piece has put its own."""
        if self._arrays is None:
            raise VkrayError("a split query finished without any piece's answer")
        return self._arrays
