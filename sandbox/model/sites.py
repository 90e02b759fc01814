"""Named particles of ropes and cloths, as levels and maneuvers write them (validated types)."""

from __future__ import annotations

from typing import Annotated, Any, Union

from pydantic import PlainValidator, WithJsonSchema
from pydantic_core import PydanticCustomError

from sandbox.model.builder import CORNERS

MAX_COORD = 1.0e3
"""Largest |coordinate| (m), length (m), |angle| (degrees) or |gravity component| (m/s^2) a level may
give: positions are float32, which keeps 0.06 mm at 1 km."""


def fail(kind: str, message: str) -> PydanticCustomError:
    """A validation error of type ``kind`` with a fully formatted message."""
    return PydanticCustomError(kind, message)


def _cloth_site(value: Any) -> str | tuple[int, int]:
    if isinstance(value, str) and (value in CORNERS or value == "center"):
        return value
    if (
        isinstance(value, (list, tuple))
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
    ):
        return (value[0], value[1])
    raise fail(
        "cloth_site",
        f"{value!r} is not a cloth site; allowed: a corner 'A', 'B', 'C', 'D', 'center' "
        "or a grid index [i, j]",
    )


def _rope_site(value: Any) -> str | int:
    if value in ("start", "end") and isinstance(value, str):
        return value
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    raise fail(
        "rope_site",
        f"{value!r} is not a rope site; allowed: 'start', 'end' or a particle index "
        "(negative counts from the end)",
    )


_INDEX2 = {"type": "array", "items": {"type": "integer"}, "minItems": 2, "maxItems": 2}
ClothSite = Annotated[
    Union[str, tuple[int, int]],
    PlainValidator(_cloth_site),
    WithJsonSchema({"anyOf": [{"enum": [*CORNERS, "center"]}, _INDEX2]}),
]
"""A cloth particle: a corner "A".."D", "center", or a grid index (i, j)."""
RopeSite = Annotated[
    Union[str, int],
    PlainValidator(_rope_site),
    WithJsonSchema({"anyOf": [{"enum": ["start", "end"]}, {"type": "integer"}]}),
]
"""A rope particle: "start", "end", or an index (negative counts from the end)."""


def _cloth_line(value: Any) -> int | tuple:
    if isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 4:
        return value
    if isinstance(value, (list, tuple)) and len(value) == 2:
        try:
            return (_cloth_site(value[0]), _cloth_site(value[1]))
        except PydanticCustomError:
            pass
    raise fail(
        "cloth_line",
        f"{value!r} is not a cloth line; allowed: a control line 1, 2, 3 or 4 (centre to corner A-D), "
        "or two cloth sites [P, Q] (a corner, 'center' or [i, j]) for the straight line between them",
    )


ClothLine = Annotated[
    Union[int, tuple[Any, Any]],
    PlainValidator(_cloth_line),
    WithJsonSchema({"anyOf": [{"enum": [1, 2, 3, 4]}, {"type": "array", "minItems": 2, "maxItems": 2}]}),
]
"""A line of cloth particles: control line 1-4 (centre to corner A-D) or [P, Q] between two cloth sites."""
