"""Pictures for notebooks: hits as images, PNG encoding, HTML summaries and a shaded preview.

No dependency beyond numpy and the standard library: a small PNG encoder (zlib and struct), a
viridis-like colormap interpolated from a few control points, and IPython only where a picture
is shown (`show`).
"""

from __future__ import annotations

import html
import importlib
import struct
import zlib
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

# The objects drawn and summarized here (Device, Mesh, Scene, Hits) are read by their public
# attributes alone and typed Any: this module sits below the modules that define them, which call
# it for their pictures and notebook summaries.
Device = Any
Hits = Any
Mesh = Any
Scene = Any

#: The colour of pixels whose ray hit nothing (RGB, 0-255): dark grey.
BACKGROUND: Tuple[int, int, int] = (38, 38, 46)

#: The fields `Hits.image` draws: depth, normal and barycentrics by value, ids by a colour each.
IMAGE_FIELDS: Tuple[str, ...] = ("t", "normal", "uv", "prim_id", "instance_id", "custom_index", "geometry_id")

# matplotlib's viridis at 0, 1/8, ..., 1: dark purple to yellow, its lightness increasing throughout.
_VIRIDIS = np.array(
    [
        (68, 1, 84),
        (72, 40, 120),
        (62, 73, 137),
        (49, 104, 142),
        (38, 130, 142),
        (31, 158, 137),
        (53, 183, 121),
        (110, 206, 88),
        (253, 231, 37),
    ],
    dtype=np.float64,
)

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def colormap(values: Any) -> np.ndarray:
    """uint8 ``S + (3,)``: values in [0, 1] (clipped; NaN as 0) through the viridis-like colormap."""
    x = np.nan_to_num(np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)) * (len(_VIRIDIS) - 1)
    low = np.minimum(x.astype(np.intp), len(_VIRIDIS) - 2)
    w = (x - low)[..., None]
    rgb = np.rint(_VIRIDIS[low] * (1.0 - w) + _VIRIDIS[low + 1] * w)
    out: np.ndarray = rgb.astype(np.uint8)
    return out


def png(image: Any) -> bytes:
    """An 8-bit PNG of a ``(H, W)`` grey, ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA uint8 image.

    Each row is stored with PNG's "Up" filter (its difference from the row above), then deflated.
    """
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise TypeError(f"a PNG is made of uint8 pixels, got {a.dtype}")
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise ValueError(f"an image must have shape (H, W), (H, W, 3) or (H, W, 4), got {np.shape(image)}")
    height, width, channels = a.shape
    if height == 0 or width == 0:
        raise ValueError(f"a PNG needs at least one pixel, got shape {np.shape(image)}")
    rows = a.reshape(height, width * channels)
    up = np.diff(rows, axis=0, prepend=np.zeros((1, rows.shape[1]), np.uint8))  # wraps mod 256 in uint8
    raw = np.empty((height, 1 + rows.shape[1]), np.uint8)
    raw[:, 0] = 2  # filter type "Up"
    raw[:, 1:] = up
    colour_type = {1: 0, 3: 2, 4: 6}[channels]
    header = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return (
        _PNG_SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
        + _chunk(b"IEND", b"")
    )


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _background(value: Any) -> np.ndarray:
    if value is None:
        return np.array(BACKGROUND, np.uint8)
    b = np.asarray(value)
    if b.shape != (3,) or not np.issubdtype(b.dtype, np.number) or not ((b >= 0) & (b <= 255)).all():
        raise ValueError(f"background must be 3 values in [0, 255] (RGB), got {value!r}")
    out: np.ndarray = np.rint(b).astype(np.uint8)
    return out


def _id_colours(ids: np.ndarray) -> np.ndarray:
    """A distinct, fairly light colour for each id (a hash of it: the same id, the same colour)."""
    h = ids.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    h ^= h >> np.uint64(29)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(32)
    channels = np.stack([(h >> np.uint64(8 * k)) & np.uint64(0xFF) for k in range(3)], axis=-1)
    return (64 + channels.astype(np.uint16) * 3 // 4).astype(np.uint8)


def hits_image(hits: Hits, field: str = "t", background: Any = None) -> np.ndarray:
    """uint8 ``(H, W, 3)``: one field of 2-D hits as an RGB image (see `Hits.image`)."""
    if len(hits.shape) != 2:
        raise ValueError(
            f"an image needs hits of a 2-D batch shape (height, width), got shape {hits.shape}: "
            "trace rays of shape (H, W, 3), or reshape"
        )
    if not isinstance(field, str) or field not in IMAGE_FIELDS:
        raise ValueError(f"field must be one of {', '.join(map(repr, IMAGE_FIELDS))}, got {field!r}")
    values = getattr(hits, field)
    if values is None:
        raise ValueError(f"these hits have no {field!r}: ask for it with outputs=[..., {field!r}]")
    hit = hits.hit
    image = np.empty(hits.shape + (3,), np.uint8)
    image[...] = _background(background)
    if field == "t":
        t = np.asarray(values, dtype=np.float64)
        valid = hit & np.isfinite(t)
        if valid.any():
            low, high = float(t[valid].min()), float(t[valid].max())
            depth = (t[valid] - low) / (high - low) if high > low else np.full(int(valid.sum()), 0.5)
            image[valid] = colormap(1.0 - depth)  # near bright (yellow), far dark (purple)
    elif field == "normal":
        n = np.asarray(values, dtype=np.float64)[hit]
        image[hit] = np.rint(np.clip(np.nan_to_num(n) * 0.5 + 0.5, 0.0, 1.0) * 255.0).astype(np.uint8)
    elif field == "uv":
        uv = np.nan_to_num(np.asarray(values, dtype=np.float64)[hit])
        weights = np.stack([uv[:, 0], uv[:, 1], 1.0 - uv[:, 0] - uv[:, 1]], axis=-1)
        image[hit] = np.rint(np.clip(weights, 0.0, 1.0) * 255.0).astype(np.uint8)
    else:
        ids = np.asarray(values)
        valid = hit & (ids >= 0)
        image[valid] = _id_colours(ids[valid])
    return image


def _default_field(hits: Hits) -> Optional[str]:
    return next((name for name in ("t", "normal", "prim_id", "instance_id") if getattr(hits, name) is not None), None)


def hits_png(hits: Hits) -> Optional[bytes]:
    """PNG bytes of 2-D hits' depth (else normals, else ids); None for other shapes or no pixels."""
    field = _default_field(hits)
    if len(hits.shape) != 2 or 0 in hits.shape or field is None or not isinstance(getattr(hits, field), np.ndarray):
        return None  # hits on the GPU (vkray.CudaArray) are not pictured
    return png(hits_image(hits, field))


def show(image: np.ndarray) -> None:
    """Displays an RGB image in a notebook (IPython's display)."""
    try:
        display = importlib.import_module("IPython.display")
    except ImportError:
        raise RuntimeError(
            "showing a picture needs IPython (a Jupyter notebook or an IPython shell); without it, "
            "take the RGB array (Hits.image, np.asarray(picture)) or save a PNG (Picture.save)"
        ) from None
    display.display(display.Image(data=png(image), format="png"))


class Picture:
    """An RGB picture (uint8 ``(height, width, 3)``) that notebooks display as a PNG.

    ``np.asarray(picture)`` (or ``picture.array``) is the array; ``picture.png()`` its PNG bytes,
    ``picture.save(path)`` writes them.
    """

    def __init__(self, array: np.ndarray) -> None:
        #: uint8 ``(height, width, 3)``.
        self.array = array

    @property
    def shape(self) -> Tuple[int, ...]:
        return tuple(self.array.shape)

    def __array__(self, dtype: Any = None, copy: Optional[bool] = None) -> np.ndarray:
        if copy:
            return np.array(self.array, dtype=dtype, copy=True)
        return self.array if dtype is None else self.array.astype(dtype, copy=False)

    def png(self) -> bytes:
        return png(self.array)

    def save(self, path: Any) -> None:
        """Writes the picture to ``path`` as a PNG file."""
        with open(path, "wb") as f:
            f.write(self.png())

    def show(self) -> None:
        """Displays the picture (IPython)."""
        show(self.array)

    def _repr_png_(self) -> bytes:
        return self.png()

    def __repr__(self) -> str:
        height, width = self.array.shape[:2]
        return f"<vkray.Picture {width}x{height}>"


# Bounds and the preview.


# Up to this many vertices and spheres in all, a scene is framed by them, transformed into world
# space; beyond, by the transformed corners of its meshes' boxes.
_EXACT_POINTS = 2_000_000


def corners(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """(8, 3): the corners of a box."""
    pick = np.array([[(k >> axis) & 1 for axis in range(3)] for k in range(8)], bool)
    return np.where(pick, high, low)


def _own_balls(mesh: Mesh, exact: bool) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """Balls (centres (N, 3), radii (N,)), in the mesh's own frame, that hold it: its vertices
    (radius 0) or spheres or, not ``exact``, the corners of their box; None when empty."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if len(v) == 0:
        return None
    r = np.zeros(len(v))
    if mesh.kind == "spheres" and mesh.radii is not None:
        r = np.broadcast_to(mesh.radii.reshape(-1), (len(v),)).astype(np.float64)
    if exact:
        return v, r
    return corners((v - r[:, None]).min(axis=0), (v + r[:, None]).max(axis=0)), np.zeros(8)


def scene_balls(scene: Scene) -> Tuple[np.ndarray, np.ndarray]:
    """(centres float64 (N, 3), radii (N,)) in world space, whose balls hold the scene's visible
    instances (mask != 0): their vertices (radius 0) and spheres while there are at most
    2,000,000 in all, else the corners of their meshes' boxes."""
    visible = [x for x in scene.instances if x.mask != 0]
    exact = sum(len(x.mesh.vertices) for x in visible) <= _EXACT_POINTS
    own: Dict[int, Optional[Tuple[np.ndarray, np.ndarray]]] = {}
    centres: List[np.ndarray] = []
    radii: List[np.ndarray] = []
    for instance in visible:
        mesh = instance.mesh
        if id(mesh) not in own:
            own[id(mesh)] = _own_balls(mesh, exact)
        balls = own[id(mesh)]
        if balls is None:
            continue
        m = instance.transform
        if m is None:
            centres.append(balls[0])
            radii.append(balls[1])
        else:  # a ball becomes an ellipsoid, within the ball of its largest axis
            centres.append(balls[0] @ m[:3, :3].T + m[:3, 3])
            radii.append(balls[1] * float(np.linalg.norm(m[:3, :3], 2)))
    if not centres:
        return np.empty((0, 3)), np.empty(0)
    return np.concatenate(centres), np.concatenate(radii)


def scene_bounds(scene: Scene) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(low, high) float64 (3,): the world-space box of the scene's visible instances (mask != 0),
    exact up to 2,000,000 vertices and spheres without transforms, else a box around it (around
    each mesh's transformed box; around each transformed sphere's ball); None for a scene with
    nothing to see."""
    centres, radii = scene_balls(scene)
    if len(centres) == 0:
        return None
    return (centres - radii[:, None]).min(axis=0), (centres + radii[:, None]).max(axis=0)


# HTML summaries.


def _bytes(n: Any) -> str:
    if n is None:
        return "?"
    value = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            break
        value /= 1024
    return f"{int(n):,} B" if unit == "B" else f"{value:.1f} {unit} ({int(n):,} B)"


def _seconds(s: Any) -> str:
    return "?" if s is None else f"{float(s) * 1e3:.2f} ms"


def _vector(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _table(title: str, rows: Iterable[Tuple[str, Any]]) -> str:
    cells = "".join(
        f'<tr><th style="text-align:left">{html.escape(str(key))}</th>'
        f'<td style="text-align:left">{html.escape(str(value))}</td></tr>'
        for key, value in rows
    )
    return f'<div class="vkray"><strong>{html.escape(title)}</strong><table>{cells}</table></div>'


def _flags(stats: Dict[str, Any]) -> str:
    flags = [f"build={stats.get('build')}"]
    flags += [name for name in ("allow_update", "compacted") if stats.get(name)]
    return ", ".join(flags)


def _device_rows(device: Device) -> List[Tuple[str, Any]]:
    return [("device", device.name), ("backend", device.backend)]


def device_html(device: Device) -> str:
    info = device.info
    limits = device.limits
    features: Sequence[str] = [
        name for name in ("ray_query", "ray_tracing_pipeline", "shader_float64") if getattr(info, name)
    ]
    rows: List[Tuple[str, Any]] = [
        ("name", info.name),
        ("type", info.device_type + (" (software)" if info.is_software else "")),
        ("backend", device.backend),
        ("Vulkan", info.api_version),
        ("driver", info.driver),
        ("features", ", ".join(features)),
        ("validation", "on" if device.validation else "off"),
        ("vertex formats", ", ".join(limits.get("vertex_formats", []))),
        ("max triangles a mesh", f"{int(limits['max_primitive_count']):,}"),
        ("max instances a scene", f"{int(limits['max_instance_count']):,}"),
        ("rays a submission", f"{device.chunk_rays:,}"),
    ]
    return _table(f"vkray.Device #{info.index}", rows)


def mesh_html(mesh: Mesh) -> str:
    stats = mesh.stats
    rows: List[Tuple[str, Any]] = []
    if mesh.kind == "spheres":
        rows.append(("spheres", f"{mesh.vertex_count:,}"))
    else:
        rows += [("vertices", f"{mesh.vertex_count:,}"), ("triangles", f"{mesh.triangle_count:,}")]
        if mesh.part_count > 1:
            rows.append(("parts", f"{mesh.part_count:,}"))
        if mesh.closedness_known:  # shown once known: computing it takes a pass over the faces
            rows.append(("closed", "yes" if mesh.is_closed else "no"))
    balls = _own_balls(mesh, exact=True)
    if balls is not None:
        low, high = (balls[0] - balls[1][:, None]).min(axis=0), (balls[0] + balls[1][:, None]).max(axis=0)
        rows.append(("bounds", f"{_vector(low)} to {_vector(high)}"))
    if "vertex_format" in stats:
        rows.append(("vertex format", f"{stats['vertex_format']}, {_bytes(stats.get('vertex_bytes'))}"))
    rows.append(("BLAS", _bytes(stats.get("bytes"))))
    if stats.get("compacted"):
        rows.append(("BLAS before compaction", _bytes(stats.get("built_bytes"))))
    rows += [
        ("build scratch", _bytes(stats.get("scratch_bytes"))),
        ("build flags", _flags(stats)),
        ("build time", _seconds(stats.get("build_seconds"))),
    ]
    return _table(f"vkray.Mesh ({mesh.kind})", rows + _device_rows(mesh.device))


def scene_html(scene: Scene) -> str:
    stats = scene.stats
    meshes = {id(x.mesh): x.mesh for x in scene.instances}
    triangles = sum(x.mesh.triangle_count for x in scene.instances if x.mesh.kind == "triangles")
    spheres = sum(x.mesh.vertex_count for x in scene.instances if x.mesh.kind == "spheres")
    rows: List[Tuple[str, Any]] = [
        ("instances", f"{len(scene.instances):,}"),
        ("meshes", f"{len(meshes):,}"),
        ("triangles", f"{triangles:,}"),
    ]
    if spheres:
        rows.append(("spheres", f"{spheres:,}"))
    bounds = scene_bounds(scene)
    if bounds is not None:
        rows.append(("bounds", f"{_vector(bounds[0])} to {_vector(bounds[1])}"))
    blas = sum(int(m.stats.get("bytes") or 0) for m in meshes.values())
    rows += [
        ("TLAS", _bytes(stats.get("bytes"))),
        ("BLASes", _bytes(blas)),
        ("build flags", _flags(stats)),
        ("build time", _seconds(stats.get("build_seconds"))),
    ]
    return _table("vkray.Scene", rows + _device_rows(scene.device))
