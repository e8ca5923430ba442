"""Code that tests/test_safety.py runs in subprocesses (so that a deadlock, a hang or a crash fails a
test instead of stopping the suite), plus the geometry and ray helpers the tests share.

Every worker is a function called as ``python -c "import safety_workers as w; w.NAME(...)"`` with
this folder on ``sys.path``. A worker prints ``RESULT <json>`` lines (one per case) on stdout and
arms a faulthandler watchdog, so that a hang also dumps every thread's Python stack on stderr."""

from __future__ import annotations

import faulthandler
import json
import os
import resource
import signal
import subprocess
import sys
import threading
import time
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

import vkray

TESTS_DIR = os.path.dirname(os.path.abspath(__file__))

# ---------------------------------------------------------------------------------------------
# Geometry and rays (numpy only)


def icosphere(level: int = 3, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> Tuple[np.ndarray, np.ndarray]:
    """A closed unit icosphere (20 * 4**level triangles, outward winding), scaled and moved."""
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    for _ in range(level):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        mid = v[unique[:, 0]] + v[unique[:, 1]]
        m = len(v) + inverse.reshape(3, -1).T  # midpoints of edges (0,1), (1,2), (2,0) of each face
        v = np.vstack([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
                            np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)])
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    return v * radius + np.asarray(center, dtype=np.float64), f.astype(np.int32)


def soup(n: int, seed: int, size: float = 2.0) -> Tuple[np.ndarray, np.ndarray]:
    """n random, mutually intersecting triangles in a cube of side `size` around the origin."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-size / 2, size / 2, (n, 1, 3))
    v = (centres + rng.normal(scale=0.15 * size, size=(n, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * n, dtype=np.int64).reshape(n, 3)


def rays(n: int, seed: int, radius: float = 3.0, spread: float = 1.2, center=(0.0, 0.0, 0.0)):
    """n rays from a sphere of `radius` towards random points of a cube of half-side `spread`
    (most hit a unit sphere at the centre), a fifth in random directions (many miss)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    origins = radius * u / np.linalg.norm(u, axis=1, keepdims=True) + center
    directions = rng.uniform(-spread, spread, (n, 3)) + center - origins
    wild = rng.random(n) < 0.2
    directions[wild] = rng.normal(size=(int(wild.sum()), 3))
    return origins, directions


def grid_rays(n: int, z: float = -3.0, half: float = 1.2, dtype=np.float32) -> np.ndarray:
    """(n, 3) origins on the plane `z`, spread over a square of half-side `half` (cheap to make:
    no random numbers; beyond 1M rays the first million repeat), to be traced along +z towards a
    unit sphere at the origin."""
    if n > 1_000_000:
        block = grid_rays(1_000_000, z, half, dtype)
        return np.tile(block, (-(-n // len(block)), 1))[:n]
    k = np.arange(n, dtype=np.float64)
    side = max(int(np.sqrt(n)), 1)
    o = np.empty((n, 3), dtype)
    o[:, 0] = (k % side) * (2 * half / side) - half
    o[:, 1] = (k // side) * (2 * half / max(n // side, 1)) - half
    o[:, 2] = z
    return o


def emit(**result: Any) -> None:
    print("RESULT " + json.dumps(result, default=_jsonable), flush=True)


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def watchdog(seconds: float) -> None:
    """After `seconds`, print every thread's stack on stderr and exit with status 1."""
    faulthandler.dump_traceback_later(seconds, exit=True)


def device(backend: str, validation: bool) -> vkray.Device:
    """A Vulkan device with `backend`, or ("cpu") the CPU engine."""
    if backend == "cpu":
        return vkray.Device("cpu")
    return vkray.Device(backend=backend, validation=validation)


def same(a: Any, b: Any) -> bool:
    """Answers equal field by field, NaN equal to NaN, dtypes and shapes included."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    return bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))


def answer(hits: Any) -> Any:
    """A query's answer as plain arrays: `occluded`'s bool array, or `intersect`'s asked fields."""
    if isinstance(hits, np.ndarray):
        return hits
    return {k: getattr(hits, k) for k in vkray.HIT_FIELDS if getattr(hits, k) is not None}


def describe_difference(a: Any, b: Any) -> str:
    if isinstance(a, dict):
        if a.keys() != b.keys():
            return f"fields {sorted(a)} != {sorted(b)}"
        return "; ".join(f"{k}: {describe_difference(a[k], b[k])}" for k in a if not same(a[k], b[k]))
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return f"{a.dtype}{a.shape} != {b.dtype}{b.shape}"
    differ = ~((a == b) | (np.isnan(a) & np.isnan(b)) if a.dtype.kind == "f" else (a == b))
    rows = np.unique(np.nonzero(differ)[0])
    return f"{len(rows)} rows differ, first {rows[:3].tolist()}"


# ---------------------------------------------------------------------------------------------
# 1, 2: queries from many threads; refits of another scene meanwhile

SIZES = (1, 3, 17, 100, 512, 1000, 4000, 20000)
SIZE_WEIGHTS = np.array([3, 2, 2, 2, 2, 2, 1, 0.5], dtype=np.float64)
OUTPUT_SETS = (None, ("t",), ("prim_id", "uv"), vkray.HIT_FIELDS, ("normal", "position"),
               ("instance_id", "custom_index", "geometry_id", "t"))


def three_scenes(dev: vkray.Device) -> List[vkray.Scene]:
    """A sphere; a triangle soup; and instances of both (moved, custom indices, masks, mirrored)."""
    v1, f1 = icosphere(3)
    v2, f2 = soup(3000, seed=1)
    m1 = dev.mesh(v1, f1)
    m2 = dev.mesh(v2, f2, build="fast_build")
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirror[:3, 3] = [0.4, -0.3, 0.2]
    moved = np.eye(4)
    moved[:3, 3] = [0.7, 0.2, -0.4]
    moved[:3, :3] *= 0.6
    instances = [vkray.Instance(m1, moved, custom_index=3),
                 vkray.Instance(m2, np.eye(4) * [0.5, 0.5, 0.5, 1.0], custom_index=9, mask=0x0F),
                 vkray.Instance(m1, mirror, custom_index=77, mask=0xF0, flip_facing=True)]
    return [dev.scene(m1), dev.scene(m2), dev.scene(instances)]


def query_specs(count: int, seed: int, scenes: int) -> List[Dict[str, Any]]:
    rng = np.random.default_rng(seed)
    specs = []
    for k in range(count):
        kind = "occluded" if rng.random() < 0.3 else "intersect"
        spec = dict(
            scene=int(rng.integers(scenes)),
            kind=kind,
            n=int(rng.choice(SIZES, p=SIZE_WEIGHTS / SIZE_WEIGHTS.sum())),
            precision=str(rng.choice(vkray.PRECISIONS)),
            cull=None if rng.random() < 0.6 else "back",
            outputs=None if kind == "occluded" else OUTPUT_SETS[int(rng.integers(len(OUTPUT_SETS)))],
            mask=0xFF if rng.random() < 0.7 else int(rng.choice([0x0F, 0xF0, 0x01])),
            tmax=np.inf if rng.random() < 0.7 else float(rng.uniform(2.0, 4.0)),
            seed=1000 + k,
        )
        specs.append(spec)
    return specs


def run_spec(scenes: List[vkray.Scene], spec: Dict[str, Any], ray_cache: Dict[int, Any]) -> Any:
    if spec["seed"] not in ray_cache:
        ray_cache[spec["seed"]] = rays(spec["n"], spec["seed"])
    o, d = ray_cache[spec["seed"]]
    scene = scenes[spec["scene"]]
    common = dict(tmax=spec["tmax"], precision=spec["precision"], cull=spec["cull"], mask=spec["mask"])
    if spec["kind"] == "occluded":
        return scene.occluded(o, d, **common)
    return answer(scene.intersect(o, d, outputs=spec["outputs"], **common))


def hammer(threads: int, per_thread: int, work, timeout: float,
           until: Optional[threading.Event] = None) -> Dict[str, Any]:
    """Runs work(thread_index, iteration) per_thread times (or until `until` is set) in each of
    `threads` threads at once; returns the errors (first few) and whether every thread finished
    within `timeout`."""
    errors: List[str] = []
    lock = threading.Lock()
    start = threading.Barrier(threads)

    def loop(k: int) -> None:
        start.wait()
        for i in range(per_thread):
            if until is not None and until.is_set():
                return
            try:
                problem = work(k, i)
            except Exception as exc:  # noqa: BLE001 - reported to the test
                problem = f"{type(exc).__name__}: {exc}"
            if problem:
                with lock:
                    errors.append(f"thread {k} query {i}: {problem}")
                    if len(errors) > 20:
                        return

    pool = [threading.Thread(target=loop, args=(k,), daemon=True) for k in range(threads)]
    began = time.monotonic()
    for t in pool:
        t.start()
    deadline = began + timeout
    for t in pool:
        t.join(max(deadline - time.monotonic(), 0.0))
    hung = sum(t.is_alive() for t in pool)
    return dict(errors=errors[:10], error_count=len(errors), hung_threads=hung, seconds=time.monotonic() - began)


def threads_worker(backend: str, validation: bool, threads: int, per_thread: int, pool_size: int,
                   timeout: float) -> None:
    """Decided behaviour 1: mixed queries from many threads on one scene and on several scenes of
    one device, each answer identical to the same query run single-threaded beforehand."""
    dev = device(backend, validation)
    scenes = three_scenes(dev)
    cache: Dict[int, Any] = {}
    for phase, scene_ids in (("one scene", [2]), ("three scenes", [0, 1, 2])):
        watchdog(timeout + 15)  # a deadlock holding the GIL keeps join() from ever returning
        specs = [dict(s, scene=scene_ids[s["scene"] % len(scene_ids)]) for s in query_specs(pool_size, 7, 3)]
        _threads_phase(phase, scenes, specs, cache, threads, per_thread, timeout)


def _threads_phase(phase: str, scenes: List[vkray.Scene], specs: List[Dict[str, Any]], cache: Dict[int, Any],
                   threads: int, per_thread: int, timeout: float) -> None:
    began = time.monotonic()
    reference = [run_spec(scenes, s, cache) for s in specs]
    single = time.monotonic() - began
    order = [np.random.default_rng(100 + k).integers(len(specs), size=per_thread) for k in range(threads)]

    def work(k: int, i: int) -> Optional[str]:
        j = int(order[k][i])
        got = run_spec(scenes, specs[j], cache)
        if not same(got, reference[j]):
            return f"spec {specs[j]}: {describe_difference(got, reference[j])}"
        return None

    result = hammer(threads, per_thread, work, timeout)
    emit(case=phase, single_seconds=single, **result)
    if result["hung_threads"]:
        faulthandler.dump_traceback(all_threads=True)
        os._exit(3)


def two_threads_worker(backend: str, validation: bool, n: int, repeats: int, timeout: float) -> None:
    """The deadlock as reported: two threads calling Scene.intersect `repeats` times each with n
    rays on one scene."""
    watchdog(timeout + 15)
    dev = device(backend, validation)
    v, f = icosphere(4)
    scene = dev.scene(dev.mesh(v, f))
    o, d = rays(n, seed=3)
    reference = answer(scene.intersect(o, d))

    def work(k: int, i: int) -> Optional[str]:
        got = answer(scene.intersect(o, d))
        return None if same(got, reference) else describe_difference(got, reference)

    result = hammer(2, repeats, work, timeout)
    emit(case="two threads", **result)
    if result["hung_threads"]:
        faulthandler.dump_traceback(all_threads=True)
        os._exit(3)


def _instanced_updatable(dev: vkray.Device, allow_update_scene: bool = True):
    v, f = icosphere(3)
    mesh = dev.mesh(v, f, allow_update=True)
    ta = np.stack([np.eye(4), np.eye(4)])
    ta[0, :3, 3] = [-0.6, 0.0, 0.0]
    ta[1, :3, 3] = [0.9, 0.1, 0.0]
    ta[1, :3, :3] *= 0.5
    tb = ta.copy()
    tb[0, :3, :3] = [[0, -0.8, 0], [0.8, 0, 0], [0, 0, 0.8]]
    tb[1, :3, 3] = [0.2, 0.8, 0.3]
    scene = dev.scene([vkray.Instance(mesh, ta[0], custom_index=1), vkray.Instance(mesh, ta[1], custom_index=2)],
                      allow_update=allow_update_scene)
    vb = v * [1.0, 1.3, 0.7] + [0.1, 0.0, 0.05]
    return v, f, vb, mesh, scene, ta, tb


UPDATE_QUERIES = (
    dict(kind="intersect", precision="fast", outputs=vkray.HIT_FIELDS, n=3000, seed=11),
    dict(kind="intersect", precision="reference", outputs=None, n=2000, seed=12),
    dict(kind="occluded", precision="fast", n=5000, seed=13),
    dict(kind="intersect", precision="refined", outputs=("t", "prim_id", "position"), n=500, seed=14),
)


def _run_update_query(scene: vkray.Scene, q: Dict[str, Any], cache: Dict[int, Any]) -> Any:
    spec = dict(q, scene=0, cull=None, mask=0xFF, tmax=np.inf, outputs=q.get("outputs"))
    return run_spec([scene], spec, cache)


def refit_other_scene_worker(backend: str, validation: bool, queries: int, timeout: float) -> None:
    """Decided behaviour 2: queries on one scene while another scene of the device is refitted
    (Scene.update(transforms=...), Mesh.update + Scene.update) in another thread."""
    watchdog(timeout + 15)
    dev = device(backend, validation)
    scenes = three_scenes(dev)
    v, f, vb, mesh, other, ta, tb = _instanced_updatable(dev)
    cache: Dict[int, Any] = {}
    specs = query_specs(24, 5, 3)
    reference = [run_spec(scenes, s, cache) for s in specs]
    stop = threading.Event()
    updates = [0]
    update_errors: List[str] = []

    def refit() -> None:
        k = 0
        while not stop.is_set():
            try:
                other.update(transforms=tb if k % 2 == 0 else ta)
                mesh.update(vb if k % 4 < 2 else v)
                other.update()
                updates[0] += 1
            except Exception as exc:  # noqa: BLE001
                update_errors.append(f"{type(exc).__name__}: {exc}")
                if len(update_errors) > 5:
                    return
            k += 1

    def work(k: int, i: int) -> Optional[str]:
        j = i % len(specs)
        got = run_spec(scenes, specs[j], cache)
        return None if same(got, reference[j]) else f"spec {specs[j]}: {describe_difference(got, reference[j])}"

    updater = threading.Thread(target=refit, daemon=True)
    updater.start()
    result = hammer(1, queries, work, timeout)
    stop.set()
    updater.join(max(timeout - result["seconds"], 1.0))
    hung = result["hung_threads"] + updater.is_alive()
    # The refitted scene answers for its final state like a fresh build of that state.
    last = (updates[0] - 1) if updates[0] else None
    final_ok = None
    if not hung and not update_errors:
        other.update(transforms=ta)
        mesh.update(v)
        other.update()
        fresh = dev.scene([vkray.Instance(dev.mesh(v, f), t, custom_index=c) for t, c in zip(ta, (1, 2))])
        o, d = rays(4000, seed=21)
        a = other.intersect(o, d, precision="reference")
        b = fresh.intersect(o, d, precision="reference")
        final_ok = bool(np.array_equal(a.prim_id, b.prim_id) and np.array_equal(a.instance_id, b.instance_id)
                        and np.allclose(a.t[a.hit], b.t[a.hit], rtol=1e-12))
    emit(case="refit other scene", updates=updates[0], update_errors=update_errors[:5], hung=hung,
         final_ok=final_ok, last=last, **{k: v for k, v in result.items() if k != "hung_threads"})
    if hung:
        faulthandler.dump_traceback(all_threads=True)
        os._exit(3)


def update_race_worker(backend: str, validation: bool, rounds: int, timeout: float) -> None:
    """Decided behaviour 3: Scene.update and Mesh.update while queries run on the same scene. An
    update waits for the running queries, queries started meanwhile wait for it: every answer is
    the answer of one of the two states; after a Mesh.update, a query may raise ValueError naming
    update until the scene is updated; never RuntimeError, never a deadlock."""
    dev = device(backend, validation)
    v, f, vb, mesh, scene, ta, tb = _instanced_updatable(dev)
    rebuilt = dev.scene([vkray.Instance(mesh, t) for t in ta])  # built without allow_update
    cache: Dict[int, Any] = {}

    def answers(s: vkray.Scene) -> List[Any]:
        return [_run_update_query(s, q, cache) for q in UPDATE_QUERIES]

    # The two states of each phase, single-threaded. Refits are deterministic (A -> B -> A
    # answers as A did), so these are the answers the threads must see.
    for phase in ("transforms", "vertices"):
        try:
            if phase == "transforms":
                state_a = answers(scene)
                scene.update(transforms=tb)
                state_b = answers(scene)
                scene.update(transforms=ta)
                targets = [(scene, state_a, state_b)]

                def update(k: int) -> None:
                    scene.update(transforms=tb if k % 2 == 0 else ta)
            else:
                mesh.update(vb)
                scene.update()
                rebuilt.update()
                mesh_b, rebuilt_b = answers(scene), answers(rebuilt)
                mesh.update(v)
                scene.update()
                rebuilt.update()
                mesh_a, rebuilt_a = answers(scene), answers(rebuilt)
                targets = [(scene, mesh_a, mesh_b), (rebuilt, rebuilt_a, rebuilt_b)]

                def update(k: int) -> None:
                    mesh.update(vb if k % 2 == 0 else v)
                    time.sleep(0.002)  # a window where the scenes must refuse
                    scene.update()
                    rebuilt.update()
        except Exception as exc:  # noqa: BLE001 - reported to the test
            emit(case=phase, setup_error=f"{type(exc).__name__}: {exc}")
            continue
        _update_phase(phase, targets, update, rounds, cache, timeout)


def _update_phase(phase: str, targets: List[Tuple[vkray.Scene, List[Any], List[Any]]], update, rounds: int,
                  cache: Dict[int, Any], timeout: float) -> None:
    """One thread queries the target scenes while another calls update(k) `rounds` times."""
    distinct = all(not same(a[0], b[0]) for _, a, b in targets)
    stop = threading.Event()
    counts = dict(updates=0, a=0, b=0, moved=0)
    update_errors: List[str] = []

    def updater() -> None:
        for k in range(rounds):
            try:
                update(k)
                counts["updates"] += 1
            except Exception as exc:  # noqa: BLE001
                update_errors.append(f"{type(exc).__name__}: {exc}")
                if len(update_errors) > 5:
                    break
            time.sleep(0.001)
        stop.set()

    def work(k: int, i: int) -> Optional[str]:
        s, ra, rb = targets[i % len(targets)]
        j = (i // len(targets) + k) % len(UPDATE_QUERIES)
        try:
            got = _run_update_query(s, UPDATE_QUERIES[j], cache)
        except ValueError as exc:
            if phase == "vertices" and "update" in str(exc):
                counts["moved"] += 1
                time.sleep(0.001)
                return None
            raise
        if same(got, ra[j]):
            counts["a"] += 1
        elif same(got, rb[j]):
            counts["b"] += 1
        else:
            return (f"{phase}: query {UPDATE_QUERIES[j]} answered neither state: "
                    f"vs A {describe_difference(got, ra[j])}; vs B {describe_difference(got, rb[j])}")
        return None

    watchdog(timeout + 15)
    up = threading.Thread(target=updater, daemon=True)
    up.start()
    result = hammer(1, 1 << 30, work, timeout, until=stop)
    up.join(1.0)
    hung = result["hung_threads"] + up.is_alive()
    emit(case=phase, update_errors=update_errors[:5], hung=hung, distinct=distinct, **counts,
         **{k: v for k, v in result.items() if k != "hung_threads"})
    if hung:
        faulthandler.dump_traceback(all_threads=True)
        os._exit(3)


# ---------------------------------------------------------------------------------------------
# 4: fork and spawn


def _fork_case(case: str, dev: vkray.Device, scenes: List[vkray.Scene], backend: str,
               validation: bool) -> Dict[str, Any]:
    v, f = icosphere(3)
    o, d = rays(500, seed=41)
    began = time.monotonic()
    try:
        if case == "intersect":
            got = answer(scenes[0].intersect(o, d))
        elif case == "occluded_reference":
            got = scenes[0].occluded(o, d, precision="reference")
        elif case == "reference_unbuilt":
            got = answer(scenes[1].intersect(o, d, precision="reference"))
        elif case == "mesh":
            dev.mesh(v, f)
            got = None
        elif case == "new_device":
            fresh = device(backend, validation)
            got = answer(fresh.scene(fresh.mesh(v, f)).intersect(o, d))
        elif case == "new_device_reference":
            fresh = device(backend, validation)
            got = answer(fresh.scene(fresh.mesh(v, f)).intersect(o, d, precision="reference"))
        else:
            raise AssertionError(case)
        return dict(outcome="returned", seconds=time.monotonic() - began, answer=_pack(got))
    except BaseException as exc:  # noqa: BLE001 - reported to the test
        return dict(outcome="raised", type=type(exc).__name__, mro=[c.__name__ for c in type(exc).__mro__],
                    message=str(exc), seconds=time.monotonic() - began)


def _pack(value: Any) -> Any:
    if value is None:
        return None
    if isinstance(value, dict):
        return {k: _pack(x) for k, x in value.items()}
    return dict(dtype=str(value.dtype), shape=list(value.shape), data=value.tobytes().hex())


def unpack(value: Any) -> Any:
    if value is None:
        return None
    if "dtype" not in value:
        return {k: unpack(x) for k, x in value.items()}
    return np.frombuffer(bytes.fromhex(value["data"]), dtype=value["dtype"]).reshape(value["shape"])


def fork_worker(backend: str, validation: bool, groups: List[List[str]], wait: List[float]) -> None:
    """Decided behaviour 4: a process that traced forks; each case runs in its own forked child,
    the children of one group at once, each given `wait` seconds before it counts as hung.
    "exit" is a child that leaves vkray alone and ends with sys.exit (interpreter finalization)."""
    watchdog(sum(wait) + 60)
    dev = device(backend, validation)
    v, f = icosphere(3)
    scene = dev.scene(dev.mesh(v, f))
    o, d = rays(500, seed=41)
    # The parent traces every tier it will check (the CPU tier starts its thread pool) on `scene`;
    # on `unbuilt` only the fast tier (the CPU tier's structures are made at its first query).
    expected = dict(fast=answer(scene.intersect(o, d)), reference=answer(scene.intersect(o, d, precision="reference")),
                    occluded=scene.occluded(o, d, precision="reference"))
    unbuilt = dev.scene(dev.mesh(v, f))
    assert same(answer(unbuilt.intersect(o, d)), expected["fast"])
    emit(case="expected", **{k: _pack(x) for k, x in expected.items()})
    for cases, seconds in zip(groups, wait):
        children = {}
        # A child that inherits an armed faulthandler watchdog hangs in its own finalization
        # (CPython, vkray or not): disarm it across the forks.
        faulthandler.cancel_dump_traceback_later()
        for case in cases:
            r, w = os.pipe()
            pid = os.fork()
            if pid == 0:  # the child
                os.close(r)
                if case == "exit":
                    os.close(w)
                    sys.exit(0)  # runs the interpreter's finalization, and vkray's destructors
                result = _fork_case(case, dev, [scene, unbuilt], backend, validation)
                os.write(w, json.dumps(result).encode())
                os.close(w)
                os._exit(0)
            os.close(w)
            children[case] = (pid, r)
        watchdog(sum(wait) + 60)
        began = time.monotonic()
        pending = dict(children)
        status: Dict[str, Any] = {}
        while pending and time.monotonic() - began < seconds:
            for case, (pid, _) in list(pending.items()):
                done, code = os.waitpid(pid, os.WNOHANG)
                if done:
                    status[case] = dict(exit_seconds=time.monotonic() - began, exit_status=code)
                    del pending[case]
            time.sleep(0.02)
        for case, (pid, _) in pending.items():
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            status[case] = dict(hung=True, waited=seconds)
        for case, (_, r) in children.items():
            data = b""
            while True:
                chunk = os.read(r, 1 << 20)
                if not chunk:
                    break
                data += chunk
            os.close(r)
            result = json.loads(data) if data else {}
            emit(case=case, **status[case], **result)
    # The parent is unaffected by its children.
    emit(case="parent_after", ok=same(answer(scene.intersect(o, d)), expected["fast"]))


def spawn_trace(backend: str, validation: bool) -> Dict[str, Any]:
    """Runs in a `spawn` child: its own Device, the same scene and rays as the parent."""
    dev = device(backend, validation)
    v, f = icosphere(3)
    scene = dev.scene(dev.mesh(v, f))
    o, d = rays(3000, seed=42)
    return dict(pid=os.getpid(), fast=answer(scene.intersect(o, d, outputs=vkray.HIT_FIELDS)),
                reference=answer(scene.intersect(o, d, precision="reference")),
                occluded=scene.occluded(o, d))


# ---------------------------------------------------------------------------------------------
# 5, 6: Ctrl-C and the GIL


def stacked_quads(k: int, half: float = 1.5) -> Tuple[np.ndarray, np.ndarray]:
    """k squares of half-side `half` stacked along z from 0 to 1: a ray along +z from the grid
    (`grid_rays`) crosses every one."""
    z = np.repeat(np.linspace(0.0, 1.0, k), 4)
    corners = np.tile([[-half, -half], [half, -half], [half, half], [-half, half]], (k, 1))
    v = np.column_stack([corners, z])
    base = 4 * np.arange(k)[:, None]
    f = np.vstack([base + [0, 1, 2], base + [0, 2, 3]])
    return v, f


def _interrupted_query(scene, query: str, precision: str):
    """The query a child runs on its origins (traced along +z), by name."""
    up = np.float32([0, 0, 1])
    if query == "intersect":
        return lambda o: scene.intersect(o, up, precision=precision, outputs=["t"])
    if query == "count":
        return lambda o: scene.count(o, up, precision=precision)
    if query == "intersect_all":
        return lambda o: scene.intersect_all(o, up, precision=precision, max_hits=8)
    if query == "contains":
        return lambda o: scene.contains(o, precision=precision, method="winding")
    if query == "distance":
        return lambda o: scene.distance(o, precision=precision)
    raise ValueError(query)


def interrupt_child(backend: str, validation: bool, precision: str, seconds: float, max_rays: int,
                    query: str = "intersect") -> None:
    """Starts a query sized to take about `seconds`, prints READY; the parent sends SIGINT. Prints
    INTERRUPTED <s> (KeyboardInterrupt) or FINISHED <s>, then AGAIN <ok> after tracing again.
    `query` "intersect" traces 1000 overlapping triangles; "count" and "intersect_all" 200
    stacked squares (200 hits a ray, the case that kept Ctrl-C waiting for a whole chunk);
    "contains" (by winding number) and "distance" take the origins as points among them."""
    signal.signal(signal.SIGINT, signal.default_int_handler)  # even if the parent ignores SIGINT
    watchdog(seconds * 3 + 60)
    dev = device(backend, validation)
    # 1000 overlapping triangles: 1-2.5M rays/s in the fast tier on lavapipe (2 cores), so the
    # query needs ~15-35M rays.
    v, f = soup(1000, seed=3) if query == "intersect" else stacked_quads(200)
    scene = dev.scene(dev.mesh(v, f))
    o_small, d_small = rays(2000, seed=51)
    expected = answer(scene.intersect(o_small, d_small, precision=precision))
    run = _interrupted_query(scene, query, precision)
    # Points among the squares (rays start below them).
    z = 0.5013 if query in ("contains", "distance") else -3.0
    # Calibrate: rays per second of this query on this machine, now, warm (a first run builds
    # pipelines and staging: timed alone it made an H200's rate look slower than it is, so that a
    # query sized from it ended before the interrupt).
    probe = grid_rays(200_000, z)
    run(probe)
    began = time.monotonic()
    run(probe)
    rate = len(probe) / (time.monotonic() - began)
    n = int(min(max(rate * seconds, 1_000_000), max_rays))
    origins = grid_rays(n, z)
    print(f"READY {n} {rate:.0f}", flush=True)
    began = time.monotonic()
    try:
        run(origins)
        print(f"FINISHED {time.monotonic() - began:.3f}", flush=True)
    except KeyboardInterrupt:
        print(f"INTERRUPTED {time.monotonic() - began:.3f}", flush=True)
    del origins
    ok = same(answer(scene.intersect(o_small, d_small, precision=precision)), expected)
    ok = ok and same(answer(scene.intersect(o_small, d_small, precision="fast")),
                     answer(scene.intersect(o_small, d_small)))
    print(f"AGAIN {ok}", flush=True)


def _count_while(busy, window: float = 0.0, gap: float = 0.02):
    """Counts in a loop until busy() is False (or for `window` seconds); returns (iterations per
    second, the longest pause between two blocks of 1000 iterations, the fraction of the time
    spent in pauses longer than `gap` seconds)."""
    count = 0
    began = last = time.perf_counter()
    longest = paused = 0.0
    while busy() if window == 0.0 else last - began < window:
        for _ in range(1000):
            count += 1
        now = time.perf_counter()
        longest = max(longest, now - last)
        if now - last > gap:
            paused += now - last
        last = now
    return count / (last - began), longest, paused / (last - began)


def _gil_scene(backend: str, validation: bool, n: int):
    dev = device(backend, validation)
    v, f = icosphere(4)
    scene = dev.scene(dev.mesh(v, f))
    origins = grid_rays(n)
    direction = np.float32([0, 0, 1])
    scene.intersect(origins[:1000], direction, outputs=vkray.HIT_FIELDS)  # pipelines compiled
    return dev, scene, origins, direction


def gil_sibling(backend: str, validation: bool, n: int) -> None:
    """The same query in a process of its own: prints GO, runs it, exits."""
    _, scene, origins, direction = _gil_scene(backend, validation, n)
    print("GO", flush=True)
    scene.intersect(origins, direction, outputs=vkray.HIT_FIELDS)


def gil_worker(backend: str, validation: bool, n: int, timeout: float) -> None:
    """Decided behaviour 6: while a long fast-tier query (every output: packing, trace, copying
    hits out) runs in one thread, a Python thread counting in a loop keeps counting. Measures its
    rate alone, while the query runs in another thread of this process, and while the same query
    runs in another process (no GIL shared: the best this machine's cores allow)."""
    watchdog(timeout)
    dev, scene, origins, direction = _gil_scene(backend, validation, n)
    idle, _, _ = _count_while(None, window=1.0)
    done = threading.Event()
    took: List[float] = []

    def query() -> None:
        began = time.perf_counter()
        scene.intersect(origins, direction, outputs=vkray.HIT_FIELDS)
        took.append(time.perf_counter() - began)
        done.set()

    worker = threading.Thread(target=query, daemon=True)
    worker.start()
    threaded, stall, paused = _count_while(lambda: not done.is_set())
    worker.join()
    profile = dev.last_trace_profile
    code = (f"import sys; sys.path.insert(0, {TESTS_DIR!r}); import safety_workers as w; "
            f"w.gil_sibling({backend!r}, {validation!r}, {n})")
    sibling = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert sibling.stdout.readline().strip() == "GO"
    apart, apart_stall, apart_paused = _count_while(lambda: sibling.poll() is None)
    idle_after, _, _ = _count_while(None, window=1.0)
    emit(idle=max(idle, idle_after), threaded=threaded, stall=stall, paused=paused, apart=apart,
         apart_stall=apart_stall, apart_paused=apart_paused,
         query_seconds=took[0], profile=profile)


# ---------------------------------------------------------------------------------------------
# 7: memory


def _vm_size() -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize")


def _max_rss() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def memory_worker(backend: str, validation: bool, skip: List[str]) -> None:
    """Decided behaviour 7, case by case under a soft RLIMIT_AS of the process's address space now
    plus some headroom (the hard limit stays, so the soft one is raised again between cases).
    Inputs are np.zeros arrays made beforehand: address space, but no memory touched."""
    watchdog(240)
    dev = device(backend, validation)
    v, f = icosphere(3)
    scene = dev.scene(dev.mesh(v, f))
    eye, up = np.array([0.0, 0.0, -3.0]), np.array([0.0, 0.0, 1.0])
    small_o, small_d = rays(1000, seed=71)
    small = dict(t=scene.intersect(small_o, small_d).t, occ=scene.occluded(small_o, small_d),
                 refined=answer(scene.intersect(small_o, small_d, precision="refined", outputs=vkray.HIT_FIELDS)))
    zeros = np.zeros(200_000_000)  # tmax = 0 for up to 200M rays: 1.6 GB of address space
    verts = np.zeros((4_000_000, 3), np.float32)
    faces = np.zeros((4_000_000, 3), np.int32)
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)

    def usable() -> bool:
        return bool(np.array_equal(scene.intersect(small_o, small_d).t, small["t"])
                    and np.array_equal(scene.occluded(small_o, small_d), small["occ"])
                    and same(answer(scene.intersect(small_o, small_d, precision="refined", outputs=vkray.HIT_FIELDS)),
                             small["refined"]))

    def run(case: str, headroom: float, call, check=None) -> None:
        if case in skip:
            return
        print(f"START {case}", flush=True)
        base = _vm_size()
        rss = _max_rss()
        resource.setrlimit(resource.RLIMIT_AS, (int(base + headroom), hard))
        began = time.monotonic()
        try:
            got = call()
            outcome = dict(outcome="returned", correct=None if check is None else bool(check(got)))
            del got
        except BaseException as exc:  # noqa: BLE001 - PanicException is a BaseException
            outcome = dict(outcome="raised", type=type(exc).__name__, message=str(exc)[:300])
        seconds = time.monotonic() - began
        grew = _max_rss() - rss
        try:
            after = usable()  # still under the limit
        except BaseException as exc:  # noqa: BLE001
            after = f"{type(exc).__name__}: {exc}"
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
        emit(case=case, headroom=headroom, seconds=seconds, rss_growth=grew, usable_after=after, **outcome)

    gb = 1e9
    # (a) 100M occlusion rays: the bool answer alone (100 MB) exceeds the headroom.
    run("occluded_100M", 0.08 * gb, lambda: scene.occluded(eye, up, tmax=zeros[:100_000_000]))
    # (a') 10M occlusion rays with headroom for the answer but maybe not for the work: MemoryError,
    # or the right answer (tmax = 0: nothing is hit); today this crashes inside the query.
    for headroom in (0.1, 0.15, 0.2, 0.3):
        run(f"occluded_10M_{headroom}", headroom * gb, lambda: scene.occluded(eye, up, tmax=zeros[:10_000_000]),
            check=lambda got: got.shape == (10_000_000,) and not got.any())
    # (b) 200M rays, every output, refined tier: about 15 GB of hits, a few GB of headroom.
    run("intersect_200M_refined", 3 * gb,
        lambda: scene.intersect(eye, up, tmax=zeros, precision="refined", outputs=vkray.HIT_FIELDS))
    # (c) a 4M-triangle mesh (a BLAS of some 400 MB on lavapipe) in 250 MB of headroom.
    if dev.is_software:
        run("mesh_4M", 0.25 * gb, lambda: dev.mesh(verts, faces))
    # A broadcast view of 2e9 triangles (24 GB were it copied), refused before any copy.
    wide = np.broadcast_to(np.array([0, 1, 2], np.int32), (2_000_000_000, 3))
    run("broadcast_faces_2e9", 3 * gb, lambda: dev.mesh(np.eye(3), wide))
    # (e) All hits beyond memory: 100 copies of the sphere in one place (each reported), 20k rays
    # through them: 4M hits, every output (about 0.4 GB), refused after the counting pass and
    # before any is stored. (Few rays with many hits each: lavapipe's counting pass is the cost.)
    copies = dev.scene([vkray.Instance(scene.instances[0].mesh)] * 100)
    through = np.column_stack([np.random.default_rng(5).uniform(-0.5, 0.5, (20_000, 2)), np.full(20_000, -3.0)])
    run("all_hits_4M", 0.25 * gb, lambda: copies.intersect_all(through, up, outputs=vkray.HIT_FIELDS))
    # (e') The same hits as the columns the GPU writes (t, prim_id), in 0.2 GB: refused as a
    # chunk's count comes, before its hits outgrow the headroom.
    run("all_hits_4M_columns", 0.2 * gb, lambda: copies.intersect_all(through, up, outputs=["t", "prim_id"]))
    print("START final", flush=True)
    emit(case="final", usable_after=usable(), mesh_after=dev.scene(dev.mesh(v, f)).intersect(small_o, small_d).t
         .tolist() == small["t"].tolist())
