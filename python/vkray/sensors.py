"""Sensors whose rays a shader generates: pinhole and orthographic cameras, and spinning lidars.

A sensor describes its rays by a handful of float32 parameters (`Sensor._generator`) from which a
shader computes every ray itself, so no ray array need cross to the device. `Sensor.rays` computes
the same rays on the CPU with the same float32 operations in the same order (numpy's float32
elementwise operations are correctly rounded and never fused), so the two agree bit for bit.

>>> from vkray.sensors import PinholeCamera, OrthographicCamera, Lidar
>>> camera = PinholeCamera(640, 480, fov_deg=60, eye=[0, 0, 0], target=[1, 0, 0], up=[0, 0, -1])
>>> origins, directions = camera.rays()          # (480, 640, 3) float32 each
>>> lidar = Lidar.preset("VLP-16")               # 16 channels x 1800 azimuth steps
>>> lidar.shape
(16, 1800)

Every derived parameter is computed in float64 and rounded once to float32; the formulas are given
in each class's documentation.

This module needs numpy only (not vkray's compiled core).
"""

from __future__ import annotations

import abc
import math
import numbers
from typing import Any, ClassVar, Dict, List, Optional, Tuple

import numpy as np
import numpy.typing as npt

__all__ = ["Sensor", "PinholeCamera", "OrthographicCamera", "Lidar"]

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: The most rays one sensor may have: ray indices are 32-bit on the device.
MAX_RAYS = 2**32 - 1
#: The most pixels along one side of a camera: below 2**24 every pixel coordinate x + 0.5 rounds to
#: float32 the same way whether computed in float64 or as float32(x) + 0.5f on the device.
MAX_PIXELS = 2**24
# A rigid transform's rotation part R must satisfy max |R R^T - I| <= this.
_ORTHONORMAL_TOLERANCE = 1e-6
# `up` must make at least this sine with the view direction.
_PARALLEL_TOLERANCE = 1e-6
# Rays whose components could exceed this overflow float32 somewhere in the image.
_FLOAT32_LIMIT = float(np.finfo(np.float32).max) / 4

_KIND_PINHOLE = 1
_KIND_ORTHOGRAPHIC = 2
_KIND_LIDAR = 3


# --------------------------------------------------------------------------------------------------
# Validation helpers: each raises ValueError naming the parameter.


def _positive_int(name: str, value: object, maximum: Optional[int] = None) -> int:
    """`value` as a positive int (Python or numpy integer, not bool) no greater than `maximum`."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    number = int(value)
    if number <= 0:
        raise ValueError(f"{name} must be a positive integer, got {number}")
    if maximum is not None and number > maximum:
        raise ValueError(f"{name} must be at most {maximum}, got {number}")
    return number


def _real(name: str, value: object) -> float:
    """`value` as a float (Python or numpy real, not bool; NaN and infinities pass)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    return float(value)


def _finite_real(name: str, value: object) -> float:
    number = _real(name, value)
    if not math.isfinite(number):
        raise ValueError(f"{name} must be finite, got {number}")
    return number


def _array(name: str, value: object, shape: Tuple[int, ...]) -> F64:
    """`value` as a finite float64 array (a copy) of the given shape."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be an array of real numbers with shape {shape}: {error}") from None
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold real numbers, got dtype {array.dtype}")
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {array.shape}")
    result = array.astype(np.float64)
    if not np.all(np.isfinite(result)):
        raise ValueError(f"{name} must be finite (it holds NaN or infinity)")
    return result


def _rigid(name: str, value: object) -> F64:
    """A 4x4 rigid transform: finite, last row [0, 0, 0, 1], rotation part orthonormal with det > 0."""
    matrix = _array(name, value, (4, 4))
    if not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name} must have last row [0, 0, 0, 1], got {matrix[3].tolist()}")
    rotation = matrix[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):
        error = float(np.max(np.abs(rotation @ rotation.T - np.eye(3))))
    if not error <= _ORTHONORMAL_TOLERANCE:
        raise ValueError(
            f"{name}[:3, :3] is not a rotation: it is not orthonormal "
            f"(max |R R^T - I| = {error:.3g} > {_ORTHONORMAL_TOLERANCE:g})"
        )
    if np.linalg.det(rotation) < 0:
        raise ValueError(f"{name}[:3, :3] is not a rotation: its determinant is negative (a reflection)")
    return matrix


def _interval(low_name: str, low: object, high_name: str, high: object) -> Tuple[float, float]:
    """A ray interval [low, high]: 0 <= low < high, neither NaN (high may be infinite)."""
    low_value = _real(low_name, low)
    high_value = _real(high_name, high)
    if math.isnan(low_value):
        raise ValueError(f"{low_name} must not be NaN")
    if math.isnan(high_value):
        raise ValueError(f"{high_name} must not be NaN")
    if low_value < 0:
        raise ValueError(f"{low_name} must be >= 0, got {low_value}")
    if not high_value > low_value:
        raise ValueError(f"{high_name} must be greater than {low_name}, got {high_name}={high_value} <= {low_value}")
    return low_value, high_value


def _ray_count(what: str, rows: int, columns: int) -> None:
    count = rows * columns
    if count > MAX_RAYS:
        raise ValueError(f"{what} make {rows} x {columns} = {count} rays, more than 2**32 - 1 = {MAX_RAYS}")


def _unit(name: str, vector: F64) -> F64:
    """`vector` / |vector|, as Eigen's normalized() computes it where that is finite."""
    length = float(np.linalg.norm(vector))
    if length == 0:
        raise ValueError(f"{name} must be a nonzero vector")
    if not math.isfinite(length) or length < 1e-150:
        # |v|^2 overflowed or underflowed: scale first.
        scaled = vector / np.max(np.abs(vector))
        return np.asarray(scaled / np.linalg.norm(scaled), np.float64)
    return np.asarray(vector / length, np.float64)


def _look_at(eye: F64, target: F64, up: F64) -> F64:
    """World-to-camera rotation (rows: camera x, y, z in world coordinates), as Open3D builds it.

    Open3D's RaycastingScene::CreateRaysPinhole(fov_deg, center, eye, up, ...): row 1 = up/|up|,
    row 2 = (center - eye)/|center - eye|, row 0 = normalize(row 1 x row 2), then row 1 = row 2 x
    row 0. Camera y is therefore `up` made orthogonal to the view direction and camera x is up x
    forward: with a world "up" for `up` this is a 180-degree roll of the usual x-right, y-down
    camera, and images come out upside down (pass `up` = world down for upright images).
    """
    with np.errstate(over="ignore"):
        view = target - eye
    if not np.all(np.isfinite(view)):
        raise ValueError("target - eye overflows float64")
    if not np.any(view):
        raise ValueError("eye and target must differ (eye == target leaves the view direction undefined)")
    forward = _unit("target - eye", view)
    up_unit = _unit("up", up)
    right = np.cross(up_unit, forward)
    sine = float(np.linalg.norm(right))
    if sine < _PARALLEL_TOLERANCE:
        raise ValueError(
            f"up must not be parallel to the view direction target - eye "
            f"(the sine of the angle between them is {sine:.3g} < {_PARALLEL_TOLERANCE:g})"
        )
    right = right / sine
    down = np.cross(forward, right)
    return np.asarray(np.stack([right, down, forward]), np.float64)


def _float32(name: str, values: F64) -> F32:
    """`values` rounded once to float32, refusing overflow."""
    with np.errstate(over="ignore"):
        result = values.astype(np.float32)
    if not np.all(np.isfinite(result)):
        raise ValueError(f"{name} overflows float32")
    return result


def _pixel_centres(count: int) -> F32:
    """float32(i + 0.5) for i in range(count): exact in float64, rounded once."""
    return (np.arange(count, dtype=np.float64) + 0.5).astype(np.float32)


def _vector_repr(values: F64) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


# --------------------------------------------------------------------------------------------------


class Sensor(abc.ABC):
    """A sensor: a grid of rays that a shader generates from a few float32 parameters.

    Attributes common to all sensors: `shape` (the ray grid), ``len(sensor)`` (the ray count),
    `echoes` (hits recorded per ray), `tmin` and `tmax` (the ray interval), `rays()` (the rays on
    the CPU) and `_generator()` (the parameters the shader reads).
    """

    _tmin: float
    _tmax: float

    @property
    @abc.abstractmethod
    def shape(self) -> Tuple[int, int]:
        """The ray grid: (height, width) for cameras, (channels, azimuth steps) for a lidar."""

    def __len__(self) -> int:
        """The number of rays, ``shape[0] * shape[1]``; ray i is grid cell (i // shape[1], i % shape[1])."""
        rows, columns = self.shape
        return rows * columns

    @property
    def echoes(self) -> int:
        """How many hits per ray the sensor records (1 for cameras)."""
        return 1

    @property
    def tmin(self) -> float:
        """Where along each ray the interval starts, in units of the ray direction's length."""
        return self._tmin

    @property
    def tmax(self) -> float:
        """Where along each ray the interval ends (may be infinite)."""
        return self._tmax

    @abc.abstractmethod
    def rays(self) -> Tuple[F32, F32]:
        """The rays as ``(origins, directions)``.

        Returns
        -------
        origins, directions:
            C-contiguous float32 arrays of shape ``shape + (3,)``, bitwise equal to what the shader
            generates from `_generator`.
        """

    @abc.abstractmethod
    def _generator(self) -> Dict[str, Any]:
        """The parameters from which a shader generates the rays.

        Returns
        -------
        dict
            ``kind`` (int: 1 pinhole, 2 orthographic, 3 lidar), ``origin`` (float32[3]), ``axes``
            (float32[3, 3]), ``columns`` and ``rows`` (ints: ray i is row i // columns, column
            i % columns), ``tmin`` and ``tmax`` (floats), ``table`` (float32 1-D, empty for
            cameras) and ``echoes`` (int). The arrays are copies.
        """


class _Camera(Sensor):
    """What both cameras share: an image of ``height`` rows of ``width`` pixels, ray i at row
    i // width and column i % width, and the form of their GPU record."""

    _width: int
    _height: int
    _axes: F32

    def _camera_record(self, kind: int, origin: F32) -> Dict[str, Any]:
        """`Sensor._generator` of a camera whose rays start from `origin` (see the subclasses)."""
        return {
            "kind": kind,
            "origin": origin.copy(),
            "axes": self._axes.copy(),
            "columns": self._width,
            "rows": self._height,
            "tmin": self._tmin,
            "tmax": self._tmax,
            "table": np.zeros(0, np.float32),
            "echoes": 1,
        }

    @property
    def shape(self) -> Tuple[int, int]:
        """``(height, width)``."""
        return (self._height, self._width)

    @property
    def width(self) -> int:
        """Image width in pixels."""
        return self._width

    @property
    def height(self) -> int:
        """Image height in pixels."""
        return self._height


class PinholeCamera(_Camera):
    """A pinhole camera with the conventions of Open3D's ``RaycastingScene.create_rays_pinhole``.

    Give either form 1 (``K`` and ``extrinsic``) or form 2 (``fov_deg``, ``eye``, ``target`` and
    ``up``), never a mix of the two.

    Parameters
    ----------
    width, height:
        Image size in pixels (each at most 2**24, and at most 2**32 - 1 pixels in all).
    K:
        Form 1: the 3x3 intrinsic matrix (pixel = K @ camera point, up to scale).
    extrinsic:
        Form 1: the 4x4 world-to-camera rigid transform ``[[R, t], [0, 0, 0, 1]]``.
    fov_deg:
        Form 2: the horizontal field of view in degrees, in (0, 180): the focal length is
        ``0.5 * width / tan(0.5 * radians(fov_deg))`` (square pixels), the principal point
        ``(0.5 * width, 0.5 * height)``.
    eye, target, up:
        Form 2: camera centre, the point it looks at (Open3D's ``center``), and the direction that
        becomes camera +y. Open3D's camera y points down the image, so an ``up`` of world up gives
        images upside down (rotated 180 degrees); pass world *down* for upright images.
    tmin, tmax:
        The ray interval, ``0 <= tmin < tmax`` (tmax may be infinite). The directions are not
        normalized: with K's last row [0, 0, 1] (always so in form 2) each has camera-z component
        1, so t is depth along the optical axis.

    Notes
    -----
    Open3D's conventions, read in ``cpp/open3d/t/geometry/RaycastingScene.cpp`` (isl-org/Open3D,
    both ``RaycastingScene::CreateRaysPinhole`` overloads) and checked against open3d 0.20.0:

    - Output ``(height, width, 6)``, origin then direction; row y, column x; pixel centres: the
      direction of pixel (x, y) is ``R^T K^-1 (x + 0.5, y + 0.5, 1)``, computed with
      ``RT_invK = (R^T K^-1)`` in float64 cast once to float32 and then a float32 product.
      Directions are not normalized. The origin is ``-R^T t`` (float64, cast to float32).
    - Form 2 builds ``K = [[f, 0, w/2], [0, f, h/2], [0, 0, 1]]`` with
      ``f = 0.5 * width / tan(0.5 * (pi / 180) * fov_deg)`` (horizontal field of view) and the
      look-at rotation of `_look_at` (rows x = normalize(up x forward), y = forward x x,
      z = forward), ``t = -R eye``, then calls form 1.

    The rays this class (and the shader) computes: ``M = R^T @ inv(K)`` in float64; ``a, b, c`` are
    M's columns and ``o = -R^T t``, each rounded to float32; for pixel (x, y), ``px = float32(x +
    0.5)``, ``py = float32(y + 0.5)`` and direction component j is ``a[j]*px + (b[j]*py + c[j])`` in
    float32: the order of Open3D 0.20.0's float32 product, so that the rays equal Open3D's bit for
    bit.
    """

    def __init__(
        self,
        width: int,
        height: int,
        *,
        K: Optional[npt.ArrayLike] = None,
        fov_deg: Optional[float] = None,
        eye: Optional[npt.ArrayLike] = None,
        target: Optional[npt.ArrayLike] = None,
        up: Optional[npt.ArrayLike] = None,
        extrinsic: Optional[npt.ArrayLike] = None,
        tmin: float = 0.0,
        tmax: float = math.inf,
    ) -> None:
        self._width = _positive_int("width", width, MAX_PIXELS)
        self._height = _positive_int("height", height, MAX_PIXELS)
        _ray_count("width x height", self._height, self._width)
        self._tmin, self._tmax = _interval("tmin", tmin, "tmax", tmax)

        intrinsic_form = {"K": K, "extrinsic": extrinsic}
        look_at_form = {"fov_deg": fov_deg, "eye": eye, "target": target, "up": up}
        given_intrinsic = [name for name, value in intrinsic_form.items() if value is not None]
        given_look_at = [name for name, value in look_at_form.items() if value is not None]
        if given_intrinsic and given_look_at:
            raise ValueError(
                "PinholeCamera takes either K and extrinsic, or fov_deg, eye, target and up, not a mix: "
                f"got {', '.join(given_intrinsic + given_look_at)}"
            )
        if not given_intrinsic and not given_look_at:
            raise ValueError("PinholeCamera needs either K and extrinsic, or fov_deg, eye, target and up")
        chosen = intrinsic_form if given_intrinsic else look_at_form
        missing = [name for name, value in chosen.items() if value is None]
        if missing:
            given = given_intrinsic or given_look_at
            raise ValueError(f"PinholeCamera given {', '.join(given)} is missing {', '.join(missing)}")

        self._fov_deg: Optional[float] = None
        self._eye: Optional[F64] = None
        self._target: Optional[F64] = None
        self._up: Optional[F64] = None
        if given_intrinsic:
            self._K = _array("K", K, (3, 3))
            if np.linalg.matrix_rank(self._K) < 3:
                raise ValueError("K is singular (it must be invertible)")
            self._extrinsic = _rigid("extrinsic", extrinsic)
        else:
            fov = _finite_real("fov_deg", fov_deg)
            if not 0.0 < fov < 180.0:
                raise ValueError(f"fov_deg must be in (0, 180), got {fov}")
            self._fov_deg = fov
            self._eye = _array("eye", eye, (3,))
            self._target = _array("target", target, (3,))
            self._up = _array("up", up, (3,))
            rotation = _look_at(self._eye, self._target, self._up)
            focal = 0.5 * self._width / math.tan(0.5 * (math.pi / 180) * fov)
            self._K = np.array(
                [[focal, 0.0, 0.5 * self._width], [0.0, focal, 0.5 * self._height], [0.0, 0.0, 1.0]], np.float64
            )
            self._extrinsic = np.eye(4)
            self._extrinsic[:3, :3] = rotation
            with np.errstate(over="ignore", invalid="ignore"):
                self._extrinsic[:3, 3] = -rotation @ self._eye
            if not np.all(np.isfinite(self._extrinsic)):
                raise ValueError("eye overflows float64 in the extrinsic translation")

        rotation = self._extrinsic[:3, :3]
        translation = self._extrinsic[:3, 3]
        with np.errstate(over="ignore", invalid="ignore"):
            matrix = rotation.T @ np.linalg.inv(self._K)
            # Every direction component |a*px + b*py + c| stays below this bound.
            bound = np.abs(matrix[:, 0]) * self._width + np.abs(matrix[:, 1]) * self._height + np.abs(matrix[:, 2])
        if not np.all(bound < _FLOAT32_LIMIT):
            raise ValueError("K and extrinsic give ray directions too large for float32")
        self._axes = _float32("K and extrinsic: R^T inv(K)", np.ascontiguousarray(matrix.T))
        self._origin = _float32("the camera centre -R^T t", -rotation.T @ translation)

    @property
    def K(self) -> F64:
        """The 3x3 intrinsic matrix (given, or built from fov_deg), float64."""
        return self._K.copy()

    @property
    def extrinsic(self) -> F64:
        """The 4x4 world-to-camera transform (given, or built from eye, target, up), float64."""
        return self._extrinsic.copy()

    @property
    def fov_deg(self) -> Optional[float]:
        """The horizontal field of view of form 2, else None."""
        return self._fov_deg

    @property
    def eye(self) -> Optional[F64]:
        """Form 2's eye, else None."""
        return None if self._eye is None else self._eye.copy()

    @property
    def target(self) -> Optional[F64]:
        """Form 2's target, else None."""
        return None if self._target is None else self._target.copy()

    @property
    def up(self) -> Optional[F64]:
        """Form 2's up, else None."""
        return None if self._up is None else self._up.copy()

    def rays(self) -> Tuple[F32, F32]:
        """Origins (the camera centre) and unnormalized directions, each ``(height, width, 3)`` float32."""
        px = _pixel_centres(self._width)
        py = _pixel_centres(self._height)
        a, b, c = self._axes
        directions = np.empty((self._height, self._width, 3), np.float32)
        for j in range(3):
            plane = directions[:, :, j]
            np.add((a[j] * px)[np.newaxis, :], (b[j] * py + c[j])[:, np.newaxis], out=plane)
        origins = np.empty_like(directions)
        origins[...] = self._origin
        return origins, directions

    def _generator(self) -> Dict[str, Any]:
        return self._camera_record(_KIND_PINHOLE, self._origin)

    def __repr__(self) -> str:
        if self._fov_deg is not None:
            assert self._eye is not None and self._target is not None and self._up is not None
            form = (
                f"fov_deg={self._fov_deg!r}, eye={_vector_repr(self._eye)}, "
                f"target={_vector_repr(self._target)}, up={_vector_repr(self._up)}"
            )
        else:
            form = f"K={self._K.tolist()!r}, extrinsic={self._extrinsic.tolist()!r}"
        return f"PinholeCamera({self._width}, {self._height}, {form}, tmin={self._tmin!r}, tmax={self._tmax!r})"


class OrthographicCamera(_Camera):
    """An orthographic camera: parallel rays from a rectangle of origins.

    Parameters
    ----------
    width, height:
        Image size in pixels (each at most 2**24, and at most 2**32 - 1 pixels in all).
    eye:
        The centre of the image rectangle.
    target:
        A point the camera looks towards: every ray has the unit direction of ``target - eye``.
    up:
        The direction that becomes camera +y, exactly as in `PinholeCamera`'s look-at form (Open3D's
        convention): camera x (image columns) is ``normalize(up x forward)`` and camera y (image
        rows, downwards) is ``forward x x``. Give world *down* for upright images.
    extent:
        The world width of the view; pixels are square, of side ``extent / width``, so the view's
        height is ``extent * height / width``.
    tmin, tmax:
        The ray interval, ``0 <= tmin < tmax``; directions are unit length so t is distance.

    Notes
    -----
    In float64: D = normalize(target - eye); U = x * extent / width and V = y * extent / width
    (x, y the camera axes above); D, U and V are rounded to float32 and then
    ``o0 = float32(eye - U * (width / 2) - V * (height / 2))`` is computed in float64 from those
    rounded U and V. The ray of pixel (x, y), with ``px = float32(x + 0.5)`` and ``py = float32(y +
    0.5)``, has origin component j ``(o0[j] + U[j]*px) + V[j]*py`` in float32, and direction D.
    """

    def __init__(
        self,
        width: int,
        height: int,
        *,
        eye: npt.ArrayLike,
        target: npt.ArrayLike,
        up: npt.ArrayLike,
        extent: float,
        tmin: float = 0.0,
        tmax: float = math.inf,
    ) -> None:
        self._width = _positive_int("width", width, MAX_PIXELS)
        self._height = _positive_int("height", height, MAX_PIXELS)
        _ray_count("width x height", self._height, self._width)
        self._tmin, self._tmax = _interval("tmin", tmin, "tmax", tmax)
        self._eye = _array("eye", eye, (3,))
        self._target = _array("target", target, (3,))
        self._up = _array("up", up, (3,))
        self._extent = _finite_real("extent", extent)
        if not self._extent > 0:
            raise ValueError(f"extent must be > 0, got {self._extent}")
        right, down, forward = _look_at(self._eye, self._target, self._up)
        pixel = self._extent / self._width
        direction = _float32("the view direction", forward)
        u = _float32("extent: the pixel step along x", right * pixel)
        v = _float32("extent: the pixel step along y", down * pixel)
        if not (np.any(u) and np.any(v)):
            raise ValueError(f"extent {self._extent} makes pixels too small for float32")
        u64 = u.astype(np.float64)
        v64 = v.astype(np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            corner = self._eye - u64 * (self._width / 2) - v64 * (self._height / 2)
            bound = np.abs(corner) + np.abs(u64) * self._width + np.abs(v64) * self._height
        self._corner = _float32("eye and extent: the image corner", corner)
        self._axes = np.stack([u, v, direction])
        if not np.all(bound < _FLOAT32_LIMIT):
            raise ValueError("eye and extent give ray origins too large for float32")

    @property
    def eye(self) -> F64:
        """The centre of the image rectangle."""
        return self._eye.copy()

    @property
    def target(self) -> F64:
        """The point the camera looks towards."""
        return self._target.copy()

    @property
    def up(self) -> F64:
        """The direction that becomes camera +y."""
        return self._up.copy()

    @property
    def extent(self) -> float:
        """The world width of the view."""
        return self._extent

    def rays(self) -> Tuple[F32, F32]:
        """Origins on the image rectangle and the unit view direction, each ``(height, width, 3)`` float32."""
        px = _pixel_centres(self._width)
        py = _pixel_centres(self._height)
        u, v, direction = self._axes
        origins = np.empty((self._height, self._width, 3), np.float32)
        for j in range(3):
            plane = origins[:, :, j]
            np.add((self._corner[j] + u[j] * px)[np.newaxis, :], (v[j] * py)[:, np.newaxis], out=plane)
        directions = np.empty_like(origins)
        directions[...] = direction
        return origins, directions

    def _generator(self) -> Dict[str, Any]:
        return self._camera_record(_KIND_ORTHOGRAPHIC, self._corner)

    def __repr__(self) -> str:
        return (
            f"OrthographicCamera({self._width}, {self._height}, eye={_vector_repr(self._eye)}, "
            f"target={_vector_repr(self._target)}, up={_vector_repr(self._up)}, extent={self._extent!r}, "
            f"tmin={self._tmin!r}, tmax={self._tmax!r})"
        )


# --------------------------------------------------------------------------------------------------
# Lidar presets: elevation tables in degrees, listed ascending (channel 0 = lowest beam).

# Velodyne VLP-16 (Puck): VLP-16 User Manual (63-9243 Rev E), "Laser ID vertical angles" table:
# -15 to +15 in 2-degree steps (firing order -15, 1, -13, 3, ..., -1, 15). 0.2 degrees azimuth
# resolution at 10 Hz (600 rpm) -> 1800 steps.
_VLP16 = tuple(float(e) for e in range(-15, 16, 2))

# Velodyne HDL-32E: HDL-32E User's Manual, laser vertical angle table: -30.67 to +10.67 in steps of
# 4/3 degree, as printed (two decimals); the same values as ros-drivers/velodyne params/32db.yaml
# ("standard Velodyne HDL-32E calibration"). A 46.08 us firing cycle at 10 Hz -> 2170 steps.
_HDL32E = (
    -30.67, -29.33, -28.00, -26.67, -25.33, -24.00, -22.67, -21.33,
    -20.00, -18.67, -17.33, -16.00, -14.67, -13.33, -12.00, -10.67,
    -9.33, -8.00, -6.67, -5.33, -4.00, -2.67, -1.33, 0.00,
    1.33, 2.67, 4.00, 5.33, 6.67, 8.00, 9.33, 10.67,
)  # fmt: skip

# Velodyne HDL-64E S2/S3: no single table is published (every unit ships its own db.xml
# calibration); these are the nominal design angles of the two 32-laser blocks: upper block +2 to
# -8 1/3 degrees in 1/3-degree steps, lower block -8 5/6 to -24 1/3 degrees in 1/2-degree steps
# (datasheets: vertical field of view +2 to -24.8 (S2) / -24.9 (S3) degrees, ~0.4-degree vertical
# resolution). Real units' calibrations lie within a few tenths of a degree of these. 0.1728
# degrees azimuth resolution at 10 Hz (S3 manual, angular resolution table) -> 2083 steps.
_HDL64E = tuple(sorted([2.0 - k / 3.0 for k in range(32)] + [-25.0 / 3.0 - (k + 1) / 2.0 for k in range(32)]))

# Velodyne VLS-128 (Alpha Prime): VLS-128 User Manual, laser channel vertical angle table (listed
# here in channel order 0..127, sorted at use); the same values as ros-drivers/velodyne
# params/VLS128.yaml. -25 to +15 degrees, densest (0.11 degrees) near the horizon. 0.2 degrees
# azimuth resolution at 10 Hz -> 1800 steps.
_VLS128_CHANNEL_ORDER = (
    -11.742, -1.99, 3.4, -5.29, -0.78, 4.61, -4.08, 1.31, -6.5, -1.11, 4.28, -4.41, 0.1, 6.48, -3.2, 2.19,
    -3.86, 1.53, -9.244, -1.77, 2.74, -5.95, -0.56, 4.83, -2.98, 2.41, -6.28, -0.89, 3.62, -5.07, 0.32, 7.58,
    -0.34, 5.18, -3.64, 1.75, -25.0, -2.43, 2.96, -5.73, 0.54, 9.7, -2.76, 2.63, -7.65, -1.55, 3.84, -4.85,
    3.18, -5.51, -0.12, 5.73, -4.3, 1.09, -16.042, -2.21, 4.06, -4.63, 0.76, 15.0, -3.42, 1.97, -6.85, -1.33,
    -5.62, -0.23, 5.43, -3.53, 0.98, -19.582, -2.32, 3.07, -4.74, 0.65, 11.75, -2.65, 1.86, -7.15, -1.44, 3.95,
    -2.1, 3.29, -5.4, -0.01, 4.5, -4.19, 1.2, -13.565, -1.22, 4.17, -4.52, 0.87, 6.08, -3.31, 2.08, -6.65,
    1.42, -10.346, -1.88, 3.51, -6.06, -0.67, 4.72, -3.97, 2.3, -6.39, -1.0, 4.39, -5.18, 0.21, 6.98, -3.09,
    4.98, -3.75, 1.64, -8.352, -2.54, 2.85, -5.84, -0.45, 8.43, -2.87, 2.52, -6.17, -1.66, 3.73, -4.96, 0.43,
)  # fmt: skip
_VLS128 = tuple(sorted(_VLS128_CHANNEL_ORDER))

# Ouster OS1-128: OS1 datasheet (Rev 6/7): 128 channels, uniform beam spacing over a 45-degree
# vertical field of view (+22.5 to -22.5, ~0.35 degrees apart). Each unit reports its measured
# beam_altitude_angles in its metadata. 1024 columns per frame (the 1024x10 mode).
_OS1_128 = tuple(-22.5 + 45.0 * k / 127.0 for k in range(128))

# name -> (elevations ascending, default azimuth steps)
_PRESETS: Dict[str, Tuple[Tuple[float, ...], int]] = {
    "VLP-16": (_VLP16, 1800),
    "HDL-32E": (_HDL32E, 2170),
    "HDL-64E": (_HDL64E, 2083),
    "VLS-128": (_VLS128, 1800),
    "OS1-128": (_OS1_128, 1024),
}


def _preset_key(name: str) -> str:
    return "".join(ch for ch in name.lower() if ch.isalnum())


class Lidar(Sensor):
    """A spinning lidar: channels at fixed elevations, swept through evenly spaced azimuths.

    Parameters
    ----------
    elevations_deg:
        One elevation per channel, in degrees within [-90, 90]; channel c (ray grid row c) is
        ``elevations_deg[c]``, in the order given.
    azimuth_steps:
        Positive number of azimuths per revolution: step k is at ``azimuth_start_deg + 360 * k /
        azimuth_steps`` degrees (ray grid column k).
    pose:
        4x4 sensor-to-world rigid transform; default the identity. In the sensor frame x is azimuth
        0, z is up and azimuth grows from x towards y.
    min_range, max_range:
        The measured interval, ``0 <= min_range < max_range`` (max_range may be infinite); the
        directions are unit length so t is range.
    echoes:
        How many hits (returns) per beam to record, >= 1.
    azimuth_start_deg:
        Azimuth of step 0, in degrees.

    Notes
    -----
    The local direction of beam (c, k) is ``(cos e cos a, cos e sin a, sin e)``. In float64,
    ``e_c = radians(elevations_deg[c])`` and ``a_k = radians(azimuth_start_deg + 360 * k /
    azimuth_steps)``; ``ce, se = float32(cos e_c), float32(sin e_c)`` and ``ca, sa = float32(cos
    a_k), float32(sin a_k)``. Then in float32: ``lx = ce*ca``, ``ly = ce*sa``, ``lz = se`` and,
    with ``R = float32(pose[:3, :3])``, world direction component j ``(R[j,0]*lx + R[j,1]*ly) +
    R[j,2]*lz``; every origin is ``float32(pose[:3, 3])``. Ray i is channel i // azimuth_steps,
    step i % azimuth_steps.
    """

    #: Names accepted by `Lidar.preset` (case, hyphens and underscores do not matter).
    PRESETS: ClassVar[Tuple[str, ...]] = tuple(_PRESETS)

    def __init__(
        self,
        elevations_deg: npt.ArrayLike,
        azimuth_steps: int,
        *,
        pose: Optional[npt.ArrayLike] = None,
        min_range: float = 0.0,
        max_range: float = math.inf,
        echoes: int = 1,
        azimuth_start_deg: float = 0.0,
    ) -> None:
        try:
            elevations = np.asarray(elevations_deg)
        except (TypeError, ValueError) as error:
            raise ValueError(f"elevations_deg must be a 1-D array of real numbers: {error}") from None
        if elevations.ndim != 1:
            raise ValueError(f"elevations_deg must be 1-D, got shape {elevations.shape}")
        if elevations.size == 0:
            raise ValueError("elevations_deg is empty: a lidar needs at least one channel")
        self._elevations = _array("elevations_deg", elevations, elevations.shape)
        outside = np.flatnonzero(np.abs(self._elevations) > 90.0)
        if outside.size:
            raise ValueError(
                f"elevations_deg must lie within [-90, 90]: channel {int(outside[0])} is "
                f"{float(self._elevations[outside[0]])}"
            )
        self._steps = _positive_int("azimuth_steps", azimuth_steps)
        _ray_count("elevations_deg and azimuth_steps", self._elevations.size, self._steps)
        self._pose = np.eye(4) if pose is None else _rigid("pose", pose)
        self._tmin, self._tmax = _interval("min_range", min_range, "max_range", max_range)
        self._echoes = _positive_int("echoes", echoes)
        self._start = _finite_real("azimuth_start_deg", azimuth_start_deg)
        self._rotation = _float32("pose", self._pose[:3, :3])
        self._origin = _float32("pose translation", self._pose[:3, 3])
        self._preset: Optional[str] = None

    @classmethod
    def preset(
        cls,
        name: str,
        *,
        azimuth_steps: Optional[int] = None,
        pose: Optional[npt.ArrayLike] = None,
        min_range: float = 0.0,
        max_range: float = math.inf,
        echoes: int = 1,
        azimuth_start_deg: float = 0.0,
    ) -> Lidar:
        """A lidar with a common sensor's published elevation table (channels ascending).

        Parameters
        ----------
        name:
            One of `Lidar.PRESETS`: ``"VLP-16"`` (Velodyne Puck, 16 channels), ``"HDL-32E"`` (32),
            ``"HDL-64E"`` (64, nominal S2/S3 angles), ``"VLS-128"`` (Velodyne Alpha Prime, 128) or
            ``"OS1-128"`` (Ouster, 128 uniform). Case, hyphens and underscores do not matter.
        azimuth_steps:
            Default: the sensor's azimuth resolution at 10 Hz (VLP-16 1800, HDL-32E 2170, HDL-64E
            2083, VLS-128 1800, OS1-128 1024).
        pose, min_range, max_range, echoes, azimuth_start_deg:
            As for `Lidar`.
        """
        if not isinstance(name, str):
            raise ValueError(f"preset name must be a string, one of {', '.join(cls.PRESETS)}; got {name!r}")
        matches = [preset for preset in _PRESETS if _preset_key(preset) == _preset_key(name)]
        if not matches:
            raise ValueError(f"unknown lidar preset {name!r}: the choices are {', '.join(cls.PRESETS)}")
        elevations, default_steps = _PRESETS[matches[0]]
        lidar = cls(
            elevations,
            default_steps if azimuth_steps is None else azimuth_steps,
            pose=pose,
            min_range=min_range,
            max_range=max_range,
            echoes=echoes,
            azimuth_start_deg=azimuth_start_deg,
        )
        lidar._preset = matches[0]
        return lidar

    @property
    def shape(self) -> Tuple[int, int]:
        """``(channels, azimuth_steps)``."""
        return (int(self._elevations.size), self._steps)

    @property
    def echoes(self) -> int:
        """How many hits per beam the lidar records."""
        return self._echoes

    @property
    def channels(self) -> int:
        """The number of channels (beams at distinct elevations)."""
        return int(self._elevations.size)

    @property
    def elevations_deg(self) -> F64:
        """Each channel's elevation in degrees, float64, in channel order."""
        return self._elevations.copy()

    @property
    def azimuth_steps(self) -> int:
        """Azimuths per revolution."""
        return self._steps

    @property
    def azimuth_start_deg(self) -> float:
        """Azimuth of step 0 in degrees."""
        return self._start

    @property
    def azimuths_deg(self) -> F64:
        """Each step's azimuth in degrees, ``azimuth_start_deg + 360 * k / azimuth_steps``, float64."""
        return self._start + (360.0 * np.arange(self._steps, dtype=np.float64)) / self._steps

    @property
    def pose(self) -> F64:
        """The 4x4 sensor-to-world transform, float64."""
        return self._pose.copy()

    @property
    def min_range(self) -> float:
        """The nearest range measured (== tmin)."""
        return self._tmin

    @property
    def max_range(self) -> float:
        """The farthest range measured (== tmax)."""
        return self._tmax

    def _trig(self) -> Tuple[F32, F32, F32, F32]:
        """float32 cos and sin of each channel's elevation, then of each step's azimuth."""
        elevation = np.radians(self._elevations)
        azimuth = np.radians(self.azimuths_deg)
        return (
            np.cos(elevation).astype(np.float32),
            np.sin(elevation).astype(np.float32),
            np.cos(azimuth).astype(np.float32),
            np.sin(azimuth).astype(np.float32),
        )

    def rays(self) -> Tuple[F32, F32]:
        """Origins (the pose's translation) and unit directions, each ``(channels, azimuth_steps, 3)`` float32."""
        ce, se, ca, sa = self._trig()
        lx = ce[:, np.newaxis] * ca[np.newaxis, :]
        ly = ce[:, np.newaxis] * sa[np.newaxis, :]
        r = self._rotation
        directions = np.empty((self.channels, self._steps, 3), np.float32)
        for j in range(3):
            plane = directions[:, :, j]
            np.multiply(r[j, 0], lx, out=plane)
            plane += r[j, 1] * ly
            plane += (r[j, 2] * se)[:, np.newaxis]
        origins = np.empty_like(directions)
        origins[...] = self._origin
        return origins, directions

    def _generator(self) -> Dict[str, Any]:
        ce, se, ca, sa = self._trig()
        table = np.concatenate([np.stack([ce, se], axis=1).ravel(), np.stack([ca, sa], axis=1).ravel()])
        return {
            "kind": _KIND_LIDAR,
            "origin": self._origin.copy(),
            "axes": self._rotation.copy(),
            "columns": self._steps,
            "rows": self.channels,
            "tmin": self._tmin,
            "tmax": self._tmax,
            "table": np.ascontiguousarray(table, np.float32),
            "echoes": self._echoes,
        }

    def __repr__(self) -> str:
        options: List[str] = [f"azimuth_steps={self._steps}"]
        if not np.array_equal(self._pose, np.eye(4)):
            options.append(f"pose={self._pose.tolist()!r}")
        if self._tmin != 0.0:
            options.append(f"min_range={self._tmin!r}")
        if self._tmax != math.inf:
            options.append(f"max_range={self._tmax!r}")
        if self._echoes != 1:
            options.append(f"echoes={self._echoes}")
        if self._start != 0.0:
            options.append(f"azimuth_start_deg={self._start!r}")
        if self._preset is not None:
            return f"Lidar.preset({self._preset!r}, {', '.join(options)})"
        return f"Lidar({_vector_repr(self._elevations)}, {', '.join(options)})"
