"""The option types of vkray's calls and their values, the names of the fields its queries
return, and the one place each option's value is checked (the core checks again and names the
choices where a value reaches it unchecked)."""

from __future__ import annotations

import json
from typing import Iterable, Literal, Optional, Tuple, Union, cast, get_args

# The option strings, as types. Spelled as unions of one-value Literals, which type checkers read
# as Literal["a", "b"]: that is also a typing.Union at run time, as `python -m mypy.stubtest vkray`
# wants a union alias to be.
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


def choices(option: object) -> Tuple[str, ...]:
    """The strings of one of the option types above."""
    return tuple(value for arg in get_args(option) for value in get_args(arg) if isinstance(value, str))


#: Every hit field a query can return.
HIT_FIELDS: Tuple[str, ...] = ("t", "prim_id", "instance_id", "custom_index", "uv", "normal", "geometry_id", "position")
#: Fields `Scene.intersect` returns unless asked otherwise.
DEFAULT_FIELDS: Tuple[str, ...] = ("t", "prim_id", "instance_id", "custom_index", "uv", "normal")
#: Precision tiers, from the fastest to the CPU oracle (see `Scene.intersect` and docs/accuracy.md).
PRECISIONS = cast("Tuple[Precision, ...]", choices(Precision))
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
#: How `Scene.contains` and `Scene.signed_distance` decide inside: crossings' parity, winding number.
SIGN_METHODS: Tuple[str, ...] = ("parity", "winding")


def check_precision(precision: object) -> Precision:
    """``precision`` if it names a tier, else TypeError or ValueError naming the tiers."""
    if not isinstance(precision, str):
        raise TypeError(f"precision must be a string, one of {', '.join(map(repr, PRECISIONS))}, got {precision!r}")
    if precision not in PRECISIONS:
        named = ", ".join(repr(p) for p in PRECISIONS[:-1]) + f" or {PRECISIONS[-1]!r}"
        raise ValueError(f"precision must be {named}, got {json.dumps(precision)}")
    return precision


def check_method(method: object) -> str:
    """``method`` if it is ``"parity"`` or ``"winding"``, else ValueError."""
    if method not in SIGN_METHODS:
        raise ValueError(f"method must be 'parity' or 'winding', got {method!r}")
    return method


def check_outputs(outputs: Optional[Iterable[str]]) -> Tuple[str, ...]:
    """The hit fields a ray query computes: ``outputs`` once each (``DEFAULT_FIELDS`` for None),
    with ``prim_id`` added where neither it nor ``t`` is asked (`Hits.hit` needs one of them)."""
    fields = _fields(outputs, HIT_FIELDS, DEFAULT_FIELDS, "hit field")
    return fields if "t" in fields or "prim_id" in fields else fields + ("prim_id",)


def check_closest_outputs(outputs: Optional[Iterable[str]]) -> Tuple[str, ...]:
    """The fields a closest-point query computes: ``outputs`` once each, ``"distance"`` always
    among them (``DEFAULT_CLOSEST_FIELDS`` for None)."""
    fields = _fields(outputs, CLOSEST_FIELDS, DEFAULT_CLOSEST_FIELDS, "field")
    return fields if "distance" in fields else fields + ("distance",)


def _fields(
    outputs: Optional[Iterable[str]], known: Tuple[str, ...], default: Tuple[str, ...], what: str
) -> Tuple[str, ...]:
    """The names ``outputs`` gives (one name, or an iterable read once), each once, in order: all
    of them in ``known`` (names of a ``what``), at least one; ``default`` for None."""
    if outputs is None:
        return default
    try:
        names = (outputs,) if isinstance(outputs, str) else tuple(outputs)
    except TypeError:
        raise TypeError(f"outputs must be {what} names, got {outputs!r}") from None
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ValueError(f"unknown {what}s {unknown}; choose from {known}")
    if not names:
        raise ValueError(f"outputs must name at least one {what}")
    return tuple(dict.fromkeys(names))
