"""Turn pydantic validation errors into findings located in the YAML document.

Pydantic reports an error at a ``loc`` tuple that mixes document keys with
labels of its own (union members, ``[key]`` for a bad mapping key). Here the
labels are dropped by walking the loc along the data actually given, and
messages are completed with what was found and what is allowed.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any

import pydantic
from pydantic import BaseModel

from sandbox.levels.issues import Severity
from sandbox.levels.yamlio import Path


@dataclasses.dataclass(frozen=True)
class Finding:
    """A problem at a document path, before it is given a file position.

    Attributes:
        path: the document path.
        message: what is wrong and what is allowed.
        severity: error or warning.
        key: point at the mapping key rather than at the value.
        trace: (label, path) pairs that show how the problem was reached
            (e.g. the call site of a macro).
    """

    path: Path
    message: str
    severity: Severity = Severity.ERROR
    key: bool = False
    trace: tuple[tuple[str, Path], ...] = ()


_TYPE_ERRORS = {
    "float_type", "int_type", "bool_type", "string_type", "list_type", "tuple_type",
    "dict_type", "model_type", "model_attributes_type", "literal_error", "float_parsing",
    "int_parsing", "finite_number", "int_from_float", "none_required", "enum",
}
_MISSING = object()


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _data_path(data: Any, loc: tuple[Any, ...], missing: bool) -> tuple[Path, bool, Any]:
    """Map a pydantic loc onto the data.

    Args:
        data: the data validated.
        loc: the error's loc.
        missing: the error is a missing field, named by the last element.

    Returns:
        (path, on_key, value): the document path, whether the error concerns a
        mapping key (``[key]``), and the value found there (``_MISSING`` when
        the last element is absent, as for a missing field).
    """
    path: list[Any] = []
    node = data
    on_key = False
    for elem in loc:
        if elem == "[key]":
            on_key = True
            continue
        if isinstance(node, dict) and elem in node:
            path.append(elem)
            node = node[elem]
        elif isinstance(node, (list, tuple)) and isinstance(elem, int) and 0 <= elem < len(node):
            path.append(elem)
            node = node[elem]
        elif missing and isinstance(node, dict) and elem is loc[-1]:
            path.append(elem)
            node = _MISSING
        # anything else is a union label of pydantic's: skipped
    return tuple(path), on_key, node


def _unwrap(tp: Any) -> tuple[Any, list[Any]]:
    meta: list[Any] = []
    while typing.get_origin(tp) is typing.Annotated:
        meta.extend(tp.__metadata__)
        tp = tp.__origin__
    return tp, meta


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _step(tp: Any, elem: Any) -> Any:
    tp, _ = _unwrap(tp)
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        members = typing.get_args(tp)
        for member in members:
            _, meta = _unwrap(member)
            if any(isinstance(m, pydantic.Tag) and m.tag == elem for m in meta):
                return member
        for member in members:
            found = _step(member, elem)
            if found is not None:
                return found
        return None
    if _is_model(tp):
        for name, field in tp.model_fields.items():
            if elem in (name, field.alias):
                return field.annotation
        return None
    if origin in (list, tuple) and isinstance(elem, int):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        if origin is tuple and len(args) > 1:
            return args[elem] if elem < len(args) else None
        return args[0] if args else None
    if origin is dict:
        return typing.get_args(tp)[1]
    return None


def model_at(root: Any, path: tuple[Any, ...]) -> type[BaseModel] | None:
    """The pydantic model that validates the mapping at ``path`` under type ``root``."""
    tp = root
    for elem in path:
        nxt = _step(tp, elem)
        if nxt is None:
            continue  # a pydantic label, or a position the types do not know
        tp = nxt
    tp, _ = _unwrap(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        models = [m for m in (_unwrap(a)[0] for a in typing.get_args(tp)) if _is_model(m)]
        tp = models[0] if len(models) == 1 else None
    return tp if _is_model(tp) else None


def allowed_keys(model: type[BaseModel]) -> list[str]:
    """The YAML keys a model accepts (aliases where given)."""
    return [field.alias or name for name, field in model.model_fields.items()]


def convert(exc: pydantic.ValidationError, root: Any, data: Any) -> list[Finding]:
    """Findings for every error of ``exc``, with paths relative to ``data``.

    Args:
        exc: the error raised validating ``data`` as ``root``.
        root: the type validated (a model class or any annotation).
        data: the plain data validated.
    """
    grouped: dict[tuple[Path, bool], list[str]] = {}
    for err in exc.errors(include_url=False):
        loc = tuple(err["loc"])
        kind = err["type"]
        path, on_key, value = _data_path(data, loc, kind == "missing")
        msg = err["msg"]
        key = on_key
        if kind == "extra_forbidden":
            model = model_at(root, loc[:-1])
            allowed = ", ".join(allowed_keys(model)) if model else "?"
            msg = f"unknown key {loc[-1]!r}; allowed keys: {allowed}"
            key = True
        elif kind == "missing" and isinstance(loc[-1], int):  # a fixed-length list (a point) cut short
            msg = f"item {loc[-1]} is missing: the list is too short"
        elif kind == "missing":
            msg = f"missing required key {loc[-1]!r}"
            path = path[:-1]
        elif on_key:
            msg = f"bad key {_short(err['input'])}: {msg}"
        elif kind in _TYPE_ERRORS and value is not _MISSING:
            msg = f"{msg}, got {_short(err['input'])}"
        grouped.setdefault((path, key), [])
        if msg not in grouped[(path, key)]:
            grouped[(path, key)].append(msg)
    return [
        Finding(path=path, message=" or ".join(msgs) if len(msgs) > 1 else msgs[0], key=key)
        for (path, key), msgs in grouped.items()
    ]
