"""The command line, ``python -m vkray``.

``info``: the Vulkan loader, the usable devices (the backends each opens with, its features,
precision tiers and limits, its driver), whether the Khronos validation layer is installed, and,
where no device is found, what to install. Exits 0 when a device was found, 1 otherwise.

``bench``: a self-benchmark of about ``--seconds`` (10 by default) on a built-in mesh: rays per
second of `Scene.intersect`, `Scene.occluded` and `Scene.count` at the fast and exact tiers,
and of Embree (embreex) on the same rays where it is installed.
"""

from __future__ import annotations

import argparse
import ctypes
import dataclasses
import importlib
import json
import os
import pathlib
import platform
import sys
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
from numpy.typing import NDArray

from . import _core
from ._core import UnsupportedError, VkrayError
from ._device import Device, devices
from ._options import PRECISIONS, Backend, Precision

_BACKENDS: Tuple[Backend, ...] = ("ray_query", "pipeline")
_VALIDATION_LAYER = "VK_LAYER_KHRONOS_validation"
# Environment variables that change what the loader or vkray picks, shown when set.
_ENVIRONMENT = (
    "VK_DRIVER_FILES",
    "VK_ICD_FILENAMES",
    "VK_ADD_DRIVER_FILES",
    "VK_LAYER_PATH",
    "VK_ADD_LAYER_PATH",
    "VK_LOADER_LAYERS_ENABLE",
    "VK_INSTANCE_LAYERS",
    "VKRAY_DEVICE",
    "VKRAY_BACKEND",
    "VKRAY_VALIDATION",
)
_NVIDIA_ICD = "/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json"


def _version() -> str:
    from . import __version__

    return __version__


# ------------------------------------------------------------------------------------------------
# info


def _loader() -> Optional[str]:
    """Where the Vulkan loader lives (its path where the platform tells), or None when it cannot be
    loaded."""
    if sys.platform == "win32":
        names = ["vulkan-1.dll"]
    elif sys.platform == "darwin":
        names = ["libvulkan.1.dylib", "libvulkan.dylib", "libMoltenVK.dylib"]
    else:
        names = ["libvulkan.so.1", "libvulkan.so"]
    for name in names:
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        maps = pathlib.Path("/proc/self/maps")
        if maps.is_file():
            for line in maps.read_text(errors="replace").splitlines():
                path = line.split(maxsplit=5)[-1] if len(line.split()) >= 6 else ""
                if pathlib.Path(path).name.startswith(name.split(".")[0] + "."):
                    return path
        return name
    return None


def _layer_manifest_dirs() -> List[pathlib.Path]:
    """The folders the Vulkan loader reads explicit layer manifests from (Linux and macOS rules)."""
    if os.environ.get("VK_LAYER_PATH"):
        return [pathlib.Path(p) for p in os.environ["VK_LAYER_PATH"].split(os.pathsep) if p]
    dirs = [pathlib.Path(p) for p in os.environ.get("VK_ADD_LAYER_PATH", "").split(os.pathsep) if p]
    config = os.environ.get("XDG_CONFIG_DIRS") or "/etc/xdg"
    home = os.environ.get("XDG_DATA_HOME") or str(pathlib.Path.home() / ".local" / "share")
    data = os.environ.get("XDG_DATA_DIRS") or "/usr/local/share:/usr/share"
    bases = [*config.split(":"), "/etc", home, *data.split(":")]
    dirs += [pathlib.Path(base) / "vulkan" / "explicit_layer.d" for base in bases if base]
    return dirs


def _validation_manifest() -> Optional[str]:
    """A manifest of the Khronos validation layer the loader would find, or None."""
    for folder in _layer_manifest_dirs():
        try:
            manifests = sorted(folder.glob("*.json"))
        except OSError:
            continue
        for manifest in manifests:
            try:
                if _VALIDATION_LAYER in manifest.read_text(errors="replace"):
                    return str(manifest)
            except OSError:
                continue
    return None


def _hints(loader: Optional[str], error: Optional[str]) -> List[str]:
    """What to install (or set) when no usable device was found."""
    hints: List[str] = []
    if loader is None or (error is not None and "loader could not be loaded" in error):
        hints.append(
            "Install the Vulkan loader (libvulkan.so.1): Debian/Ubuntu `sudo apt-get install libvulkan1`, "
            "Fedora `sudo dnf install vulkan-loader`."
        )
    hints.append("Install a Vulkan driver with acceleration structures and ray queries or ray-tracing pipelines:")
    hints.append(
        "  CPU only, Mesa's lavapipe (Mesa >= 24.1): on Debian bookworm from bookworm-backports: "
        "`echo 'deb http://deb.debian.org/debian bookworm-backports main' | "
        "sudo tee /etc/apt/sources.list.d/bookworm-backports.list && sudo apt-get update && "
        "sudo apt-get install -t bookworm-backports libvulkan1 mesa-vulkan-drivers`; on Ubuntu >= 24.04 "
        "or Debian trixie: `sudo apt-get install libvulkan1 mesa-vulkan-drivers`."
    )
    hints.append(
        "  NVIDIA GPU: the NVIDIA driver, with its Vulkan ICD (nvidia_icd.json; in containers, "
        "NVIDIA_DRIVER_CAPABILITIES must include `graphics`). Where the loader finds no driver, point it "
        f"at the ICD: `export VK_DRIVER_FILES={_NVIDIA_ICD}` (or /usr/share/vulkan/icd.d/nvidia_icd.json)."
    )
    for name in ("VK_DRIVER_FILES", "VK_ICD_FILENAMES"):
        value = os.environ.get(name)
        if value:
            missing = [p for p in value.split(os.pathsep) if p and not pathlib.Path(p).exists()]
            note = f" ({', '.join(missing)} does not exist)" if missing else ""
            hints.append(f"{name}={value} is set{note}: the loader reads only the drivers it names.")
    hints.append(
        "From a source checkout, `bash scripts/setup-system.sh` installs all of this on Debian/Ubuntu; "
        "`vulkaninfo --summary` (Debian: vulkan-tools) shows what the loader sees."
    )
    return hints


def _device_report(index: int, info: Dict[str, Any]) -> Dict[str, Any]:
    """One device: its `DeviceInfo`, the backends that open, its precision tiers and limits."""
    report = dict(info)
    if info.get("engine") == "cpu":
        # The CPU engine: Embree on the host's cores, every tier; no Vulkan backend.
        report["backends"], report["default_backend"] = ["cpu"], "cpu"
        report["precisions"] = list(PRECISIONS)
        report["limits"] = Device("cpu").limits
        return report
    offered = [b for b in _BACKENDS if info["ray_query" if b == "ray_query" else "ray_tracing_pipeline"]]
    backends: List[str] = []
    errors: Dict[str, str] = {}
    limits: Dict[str, Any] = {}
    for backend in offered:
        try:
            device = Device(index, backend)
        except VkrayError as exc:
            errors[backend] = f"{type(exc).__name__}: {exc}"
            continue
        backends.append(backend)
        limits = limits or device.limits
    report["backends"] = backends
    report["default_backend"] = "ray_query" if info["ray_query"] else "pipeline"
    if errors:
        report["backend_errors"] = errors
    tiers: List[str] = [p for p in PRECISIONS if p != "exact" or info["shader_float64"]]
    report["precisions"] = tiers
    report["limits"] = limits
    return report


def _validation(found: List[Dict[str, Any]]) -> Tuple[Optional[bool], str]:
    """Whether the Khronos validation layer is present, and how that was decided. Where a device
    opens, vkray asks the loader (as the tests' conftest does); else the layer manifests are read."""
    found = [d for d in found if d.get("engine") != "cpu"]
    if found and found[0]["backends"]:
        try:
            Device(found[0]["index"], found[0]["backends"][0], validation=True)
            return True, "a device opened with it"
        except UnsupportedError as exc:
            if "validation" in str(exc):
                return False, str(exc)
        except VkrayError as exc:
            return None, f"{type(exc).__name__}: {exc}"
    manifest = _validation_manifest()
    if manifest is not None:
        return True, f"manifest {manifest}"
    return False, "no VK_LAYER_KHRONOS_validation manifest in the loader's layer folders"


def gather_info() -> Dict[str, Any]:
    """Everything `info` prints, as JSON-ready values."""
    loader = _loader()
    report: Dict[str, Any] = {
        "vkray": _version(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "loader": loader,
        "environment": {name: os.environ[name] for name in _ENVIRONMENT if name in os.environ},
        "devices": [],
        "error": None,
    }
    try:
        infos = [dataclasses.asdict(info) for info in devices()]
    except VkrayError as exc:
        report["error"] = f"{type(exc).__name__}: {exc}"
        infos = []
    report["devices"] = [_device_report(info["index"], info) for info in infos]
    if not any(info["engine"] == "vulkan" for info in infos) and report["error"] is None:
        try:
            _core.devices()
            report["error"] = (
                "NoDeviceError: the Vulkan loader found drivers, but no device with acceleration structures and "
                "ray queries or ray-tracing pipelines (lavapipe needs Mesa >= 24.1)"
            )
        except VkrayError as exc:
            report["error"] = f"{type(exc).__name__}: {exc}"
    available, how = _validation(report["devices"])
    report["validation_layer"] = {"available": available, "how": how}
    report["hints"] = _hints(loader, report["error"]) if report["error"] is not None else []
    return report


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


def _format_limit(value: Any) -> str:
    if isinstance(value, bool) or not isinstance(value, (int, float, list)):
        return str(value)
    if isinstance(value, list):
        return ", ".join(str(v) for v in value)
    return f"{value:,}" if isinstance(value, int) else f"{value:g}"


def print_info(report: Dict[str, Any]) -> None:
    print(f"vkray {report['vkray']} (Python {report['python']}, {report['platform']})")
    print(f"Vulkan loader: {report['loader'] or 'not found'}")
    for name, value in report["environment"].items():
        print(f"  {name}={value}")
    layer = report["validation_layer"]
    state = {True: "installed", False: "not installed", None: "unknown"}[layer["available"]]
    extra = (
        "" if layer["available"] else " (Debian: vulkan-validationlayers; needed for VKRAY_VALIDATION=1 and the tests)"
    )
    print(f"Khronos validation layer: {state}{extra}")
    for device in report["devices"]:
        print()
        print(f"Device {device['index']}: {device['name']}")
        kind = device["device_type"] + (", software" if device["is_software"] else "")
        print(f"  type:       {kind}")
        print(f"  driver:     {device['driver']}")
        if device.get("engine") == "cpu":
            print("  engine:     the CPU engine (Embree, SIMD chosen for this CPU, every core; no Vulkan)")
        else:
            print(f"  Vulkan:     {device['api_version']}")
        backends = [b + (" (default)" if b == device["default_backend"] else "") for b in device["backends"]]
        print(f"  backends:   {', '.join(backends) or 'none opened'}")
        for backend, message in device.get("backend_errors", {}).items():
            print(f"    {backend} failed: {message}")
        print(
            f"  features:   ray queries {_yes(device['ray_query'])}, ray-tracing pipeline "
            f"{_yes(device['ray_tracing_pipeline'])}, shaderFloat64 {_yes(device['shader_float64'])}"
        )
        print(f"  precisions: {', '.join(device['precisions'])}")
        if device["limits"]:
            print("  limits:")
            width = max(len(name) for name in device["limits"])
            for name, value in device["limits"].items():
                print(f"    {name:<{width}}  {_format_limit(value)}")
    if report["error"] is not None:
        print()
        print(f"No usable Vulkan device: {report['error']}")
        if any(device.get("engine") == "cpu" for device in report["devices"]):
            print("The CPU engine answers every query meanwhile; a Vulkan device adds the GPU's speed.")
    if report["hints"]:
        print()
        for hint in report["hints"]:
            print(hint)


def _info(args: argparse.Namespace) -> int:
    report = gather_info()
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print_info(report)
    return 0 if report["devices"] else 1


# ------------------------------------------------------------------------------------------------
# bench

_F32 = NDArray[np.float32]
_MAX_RAYS = 1 << 22


def icosphere(subdivisions: int) -> Tuple[NDArray[np.float64], NDArray[np.int32]]:
    """A closed bumpy sphere: an icosahedron subdivided `subdivisions` times (20 * 4**subdivisions
    triangles), its vertices pushed out radially by a smooth bump pattern (radius 0.8 to 1.2)."""
    p = (1.0 + 5.0**0.5) / 2.0
    v = np.array(
        [[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p],
         [0, -1, -p], [0, 1, -p], [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]],
        dtype=np.float64,
    )  # fmt: skip
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]],
        dtype=np.int64,
    )  # fmt: skip
    for _ in range(subdivisions):
        edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = (len(v) + inverse.reshape(-1, 3)).astype(np.int64)
        v = np.concatenate([v, (v[unique[:, 0]] + v[unique[:, 1]]) / 2.0])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = mid[:, 0], mid[:, 1], mid[:, 2]
        f = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    bump = np.sin(5.0 * v[:, 0]) * np.sin(5.0 * v[:, 1] + 1.0) * np.sin(5.0 * v[:, 2] + 2.0)
    return v * (1.0 + 0.2 * bump)[:, None], f.astype(np.int32)


class _Rays:
    """Rays from a sphere of radius 3 around the mesh towards random points of the box [-1.2, 1.2]^3
    (most hit), float32, generated as needed; the first n of them."""

    def __init__(self, seed: int = 7) -> None:
        self.seed = seed
        self.origins: _F32 = np.zeros((0, 3), np.float32)
        self.directions: _F32 = np.zeros((0, 3), np.float32)

    def __call__(self, n: int) -> Tuple[_F32, _F32]:
        if n > len(self.origins):
            rng = np.random.default_rng(self.seed)
            u = rng.normal(size=(n, 3))
            origins = 3.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
            targets = rng.uniform(-1.2, 1.2, size=(n, 3))
            self.origins = np.ascontiguousarray(origins, dtype=np.float32)
            self.directions = np.ascontiguousarray(targets - origins, dtype=np.float32)
        return self.origins[:n], self.directions[:n]


_Query = Callable[[_F32, _F32], object]


def _measure(query: _Query, rays: _Rays, seconds: float) -> Tuple[float, int]:
    """The best rate (rays per second) of `query` within about `seconds`, and the rays per call:
    calls grow fourfold (up to 4M rays) while a call takes less than an eighth of the time."""
    deadline = time.perf_counter() + seconds
    n, best = 4096, 0.0
    while True:
        o, d = rays(n)
        start = time.perf_counter()
        query(o, d)
        elapsed = max(time.perf_counter() - start, 1e-9)
        best = max(best, n / elapsed)
        left = deadline - time.perf_counter()
        if left <= 0 or elapsed > left:
            return best, n
        if elapsed * 8 < seconds and elapsed * 4 < left and n < _MAX_RAYS:
            n *= 4


class _Embree:
    """Embree (embreex) on one thread (its ``run`` holds the GIL), float32 rays as vkray gets them."""

    def __init__(self, vertices: NDArray[np.float64], faces: NDArray[np.int32]) -> None:
        scenes = importlib.import_module("embreex.rtcore_scene")
        construction = importlib.import_module("embreex.mesh_construction")
        self.scene: Any = scenes.EmbreeScene()
        construction.TriangleMesh(self.scene, np.ascontiguousarray(vertices[faces], dtype=np.float32))
        self.offset = 1e-6 * float(np.ptp(vertices, axis=0).max())
        # Embree commits the scene lazily: build it now, not inside the timed queries.
        self.scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))

    def intersect(self, o: _F32, d: _F32) -> object:
        return self.scene.run(o, d, output=1)

    def occluded(self, o: _F32, d: _F32) -> object:
        return self.scene.run(o, d, query="OCCLUDED")

    def count(self, o: _F32, d: _F32) -> NDArray[np.int32]:
        """Hits per ray as trimesh counts them with Embree: cast again from just past each hit."""
        unit = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
        origins = o.copy()
        counts = np.zeros(len(o), np.int32)
        active = np.arange(len(o))
        for _ in range(256):
            if not len(active):
                break
            result = self.scene.run(origins[active], unit[active], output=1)
            hit = result["primID"] >= 0
            active = active[hit]
            counts[active] += 1
            step = (result["tfar"][hit] + self.offset)[:, None]
            origins[active] += unit[active] * step.astype(np.float32)
        return counts


def _embree_version() -> str:
    try:
        from importlib import metadata

        return metadata.version("embreex")
    except Exception:
        return "?"


def run_bench(
    seconds: float,
    device: Optional[str] = None,
    backend: Optional[Backend] = None,
    subdivisions: int = 6,
    embree: bool = True,
) -> Dict[str, Any]:
    """Times the queries; returns JSON-ready results."""
    began = time.perf_counter()
    dev = Device(device, backend)  # an index as a string is an index
    vertices, faces = icosphere(subdivisions)
    start = time.perf_counter()
    scene = dev.scene(dev.mesh(vertices, faces))
    build = time.perf_counter() - start
    tiers: List[Precision] = ["fast", "exact"] if dev.info.shader_float64 else ["fast"]
    runs: List[Tuple[str, str, _Query]] = []
    for name in ("intersect", "occluded", "count"):
        for precision in tiers:
            runs.append((name, precision, _vkray_query(scene, name, precision)))
    engine: Optional[_Embree] = None
    skipped: Optional[str] = None
    if embree:
        try:
            engine = _Embree(vertices, faces)
        except ImportError:
            skipped = "embreex is not installed (pip install embreex)"
    else:
        skipped = "--no-embree"
    if engine is not None:
        runs += [("intersect", "embree", engine.intersect), ("occluded", "embree", engine.occluded)]
        runs.append(("count", "embree", engine.count))
    rays = _Rays()
    o, d = rays(1024)
    for _, _, fn in runs:  # warm-up: pipelines compile on first use
        fn(o, d)
    hit_fraction = float(scene.occluded(*rays(1 << 14)).mean())
    slot = max(seconds - (time.perf_counter() - began), 0.1 * len(runs)) / len(runs)
    rates: Dict[Tuple[str, str], Tuple[float, int]] = {}
    for name, engine_or_tier, fn in runs:
        rates[name, engine_or_tier] = _measure(fn, rays, slot)
    rows = []
    for name, engine_or_tier, _ in runs:
        if engine_or_tier == "embree":
            continue
        rate, n = rates[name, engine_or_tier]
        other = rates.get((name, "embree"))
        rows.append(
            {
                "query": name,
                "precision": engine_or_tier,
                "rays_per_call": n,
                "vkray_mrays_per_s": rate / 1e6,
                "embree_mrays_per_s": None if other is None else other[0] / 1e6,
                "embree_rays_per_call": None if other is None else other[1],
                "ratio": None if other is None else rate / other[0],
            }
        )
    return {
        "device": dev.name,
        "device_type": dev.info.device_type,
        "driver": dev.info.driver,
        "backend": dev.backend,
        "mesh": f"bumpy icosphere, {subdivisions} subdivisions",
        "triangles": int(len(faces)),
        "build_seconds": build,
        "hit_fraction": hit_fraction,
        "embree": None if engine is None else f"embreex {_embree_version()}, one thread",
        "embree_skipped": skipped,
        "rows": rows,
        "seconds": time.perf_counter() - began,
    }


def _vkray_query(scene: Any, query: str, tier: Precision) -> _Query:
    if query == "intersect":
        return lambda o, d: scene.intersect(o, d, precision=tier)
    if query == "occluded":
        return lambda o, d: scene.occluded(o, d, precision=tier)
    return lambda o, d: scene.count(o, d, precision=tier)


def print_bench(result: Dict[str, Any]) -> None:
    print(
        f"Device: {result['device']} ({result['device_type']}), backend {result['backend']}, driver {result['driver']}"
    )
    print(
        f"Mesh: {result['mesh']}, {result['triangles']:,} triangles (BLAS + TLAS built in "
        f"{result['build_seconds']:.3f} s); rays from a sphere around it, {result['hit_fraction']:.0%} hit"
    )
    if result["embree"] is not None:
        print(f"Embree: {result['embree']}; ratio = vkray / Embree on the same query", end="")
        print(" (Embree's count casts again from just past each hit)")
    else:
        print(f"Embree: skipped ({result['embree_skipped']})")
    print("Numpy in, numpy out; best call of each query; 'M rays/s' = millions of rays per second.")
    print()
    header = f"{'query':<10} {'precision':<9} {'rays/call':>10} {'vkray M rays/s':>15}"
    if result["embree"] is not None:
        header += f" {'Embree M rays/s':>16} {'ratio':>7}"
    print(header)
    print("-" * len(header))
    for row in result["rows"]:
        line = f"{row['query']:<10} {row['precision']:<9} {row['rays_per_call']:>10,} {row['vkray_mrays_per_s']:>15.3f}"
        if row["embree_mrays_per_s"] is not None:
            line += f" {row['embree_mrays_per_s']:>16.3f} {row['ratio']:>6.2f}x"
        print(line)
    print()
    print(f"Took {result['seconds']:.1f} s.")


def _bench(args: argparse.Namespace) -> int:
    if args.seconds <= 0:
        raise SystemExit("python -m vkray bench: error: --seconds must be positive")
    try:
        result = run_bench(args.seconds, args.device, args.backend, args.subdivisions, not args.no_embree)
    except VkrayError as exc:
        print(f"{type(exc).__name__}: {exc}\n(`python -m vkray info` says what is missing)", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print_bench(result)
    return 0


# ------------------------------------------------------------------------------------------------


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="python -m vkray", description="vkray: Vulkan ray casting from numpy. Check a machine, or time it."
    )
    top.add_argument("--version", action="version", version=f"vkray {_version()}")
    commands = top.add_subparsers(dest="command", required=True, metavar="{info,bench}")
    info = commands.add_parser(
        "info",
        help="the Vulkan devices, their backends, features and limits, and what to install if none is found",
        description="Lists the Vulkan devices vkray can use, with the backends each opens with, its features, "
        "precision tiers, limits and driver; says whether the Khronos validation layer is installed; and, "
        "where no device is found, what to install. Exit status 0 when a device was found, else 1.",
    )
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    info.set_defaults(run=_info)
    bench = commands.add_parser(
        "bench",
        help="a short self-benchmark: intersect, occluded and count on a built-in mesh (and Embree, if installed)",
        description="Rays per second of intersect, occluded and count at the fast and exact tiers on a built-in "
        "mesh (a bumpy icosphere), and of Embree (embreex) on the same rays where it is installed.",
    )
    bench.add_argument("--seconds", type=float, default=10.0, help="the time budget (default: 10)")
    bench.add_argument("--device", default=None, help="device index or name (default: VKRAY_DEVICE, else the best)")
    bench.add_argument(
        "--backend", choices=_BACKENDS, default=None, help="default: VKRAY_BACKEND, else ray_query where offered"
    )
    bench.add_argument(
        "--subdivisions", type=int, default=6, choices=range(0, 9), metavar="0-8",
        help="icosphere subdivisions: 20 * 4**N triangles (default: 6, 81,920 triangles)",
    )  # fmt: skip
    bench.add_argument("--no-embree", action="store_true", help="time vkray alone")
    bench.add_argument("--json", action="store_true", help="print JSON instead of text")
    bench.set_defaults(run=_bench)
    return top


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parser().parse_args(argv)
    code: int = args.run(args)
    return code
