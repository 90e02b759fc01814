"""YAML reading with source positions, and YAML writing, for level files.

Levels are read with YAML 1.2 core scalars rather than PyYAML's YAML 1.1
defaults: ``on``/``off``/``yes``/``no`` stay strings (``on:`` is the FSM's
transition key), ``1e-6`` is a float, and ``010`` is not an octal number.
Every node's start position is recorded under its path in the document, so
that validation errors can point at a line and column.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Hashable
from typing import Any

import yaml

MAX_BYTES = 2_000_000
"""Largest YAML text read (a level or a sweep file is a few kB)."""
MAX_NODES = 200_000
"""Most nodes a document may expand to, aliases counted at each use (an alias bomb stops here)."""

Path = tuple[Any, ...]
"""A position in the document: mapping keys and sequence indices from the root."""

_INT = re.compile(r"^(?:[-+]?(?:0|[1-9][0-9_]*)|0x[0-9a-fA-F_]+|0o[0-7_]+)$")
_FLOAT = re.compile(
    r"^(?:[-+]?(?:\.[0-9][0-9_]*|[0-9][0-9_]*(?:\.[0-9_]*)?)(?:[eE][-+]?[0-9]+)?"
    r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
)
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
_NULL = re.compile(r"^(?:~|null|Null|NULL|)$")
_MERGE = re.compile(r"^(?:<<)$")


def _core_resolvers(cls: type) -> None:
    cls.yaml_implicit_resolvers = {}
    cls.add_implicit_resolver("tag:yaml.org,2002:bool", _BOOL, list("tTfF"))
    cls.add_implicit_resolver("tag:yaml.org,2002:int", _INT, list("-+0123456789"))
    cls.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+.0123456789"))
    cls.add_implicit_resolver("tag:yaml.org,2002:null", _NULL, ["~", "n", "N", ""])
    cls.add_implicit_resolver("tag:yaml.org,2002:merge", _MERGE, ["<"])


class _Loader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2 core scalar resolution."""

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        text = self.construct_scalar(node).replace("_", "")
        sign = -1 if text.startswith("-") else 1
        text = text.lstrip("+-")
        if text.startswith("0x"):
            return sign * int(text[2:], 16)
        if text.startswith("0o"):
            return sign * int(text[2:], 8)
        return sign * int(text)


_core_resolvers(_Loader)
_Loader.add_constructor("tag:yaml.org,2002:int", _Loader.construct_yaml_int)


class _Dumper(yaml.SafeDumper):
    """SafeDumper that quotes any string a YAML 1.1 or 1.2 reader would not read as a string."""


_Dumper.yaml_implicit_resolvers = {
    k: list(v) for k, v in yaml.SafeDumper.yaml_implicit_resolvers.items()
}
for _tag, _regex, _first in (
    ("tag:yaml.org,2002:bool", _BOOL, "tTfF"),
    ("tag:yaml.org,2002:int", _INT, "-+0123456789"),
    ("tag:yaml.org,2002:float", _FLOAT, "-+.0123456789"),
):
    for _ch in _first:
        _Dumper.yaml_implicit_resolvers.setdefault(_ch, []).append((_tag, _regex))


@dataclasses.dataclass(frozen=True)
class Mark:
    """A 1-based line and column in a source file."""

    line: int
    column: int


@dataclasses.dataclass
class Document:
    """A parsed YAML document with the positions of its nodes.

    Attributes:
        data: the plain Python value (dicts, lists, scalars).
        values: path -> position of the node's value.
        keys: path -> position of the mapping key that leads to it.
        problems: (path, mark, message) found while reading (duplicate keys,
            non-string keys).
    """

    data: Any
    values: dict[Path, Mark] = dataclasses.field(default_factory=dict)
    keys: dict[Path, Mark] = dataclasses.field(default_factory=dict)
    problems: list[tuple[Path, Mark, str]] = dataclasses.field(default_factory=list)

    def locate(self, path: Path, *, key: bool = False) -> tuple[Path, Mark]:
        """Closest recorded position for ``path`` (its longest recorded prefix).

        Args:
            path: a document path; elements absent from the document are skipped.
            key: prefer the position of the mapping key over that of the value.
        """
        for n in range(len(path), -1, -1):
            sub = tuple(path[:n])
            if key and sub in self.keys:
                return sub, self.keys[sub]
            if sub in self.values:
                return sub, self.values[sub]
        return (), Mark(1, 1)


class LimitError(yaml.MarkedYAMLError):
    """A document past ``MAX_BYTES`` or ``MAX_NODES``, or nested too deeply; says which and where."""


def _mark(node: yaml.Node) -> Mark:
    return Mark(node.start_mark.line + 1, node.start_mark.column + 1)


def parse(text: str) -> Document:
    """Parse one YAML document, recording node positions.

    Raises:
        yaml.MarkedYAMLError: on a syntax error; ``LimitError`` (one of them)
            for a text of more than ``MAX_BYTES`` characters, a document that
            expands to more than ``MAX_NODES`` nodes, or one nested too deeply.
    """
    if len(text) > MAX_BYTES:
        raise LimitError(problem=f"the text is {len(text)} characters long; allowed at most {MAX_BYTES}")
    try:
        loader = _Loader(text)  # the reader refuses characters YAML does not allow here
    except yaml.reader.ReaderError as exc:
        raise _unprintable(exc, text) from None
    try:
        node = loader.get_single_node()
        doc = Document(data=None)
        if node is not None:
            doc.data = _build(loader, node, (), doc, [0])
        return doc
    except RecursionError:
        raise LimitError(problem="the document is nested too deeply") from None
    except yaml.reader.ReaderError as exc:
        raise _unprintable(exc, text) from None
    finally:
        loader.dispose()


def _unprintable(exc: yaml.reader.ReaderError, text: str) -> yaml.MarkedYAMLError:
    """A character YAML does not allow (NUL, other control characters), as a syntax error at its place."""
    head = text[: max(exc.position, 0)]
    mark = yaml.Mark("", exc.position, head.count("\n"), len(head) - (head.rfind("\n") + 1), None, None)
    code = exc.character if isinstance(exc.character, int) else ord(exc.character)
    return yaml.MarkedYAMLError(problem=f"character #x{code:04x} is not allowed in a level file (control "
                                        "characters other than tab and newline)", problem_mark=mark)


def _build(loader: _Loader, node: yaml.Node, path: Path, doc: Document, count: list[int]) -> Any:
    count[0] += 1
    if count[0] > MAX_NODES:
        raise LimitError(problem=f"the document expands to more than {MAX_NODES} nodes (aliases are counted "
                                 "at each use); allowed at most that many", problem_mark=node.start_mark)
    doc.values[path] = _mark(node)
    if isinstance(node, yaml.SequenceNode):
        return [_build(loader, child, path + (i,), doc, count) for i, child in enumerate(node.value)]
    if isinstance(node, yaml.MappingNode):
        explicit = {id(k) for k, _ in node.value if k.tag != "tag:yaml.org,2002:merge"}
        loader.flatten_mapping(node)  # merged pairs first, then the mapping's own, which override them
        out: dict[Any, Any] = {}
        merged: set[Any] = set()
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                doc.problems.append((path, _mark(key_node), "mapping keys must be scalars"))
                continue
            key = loader.construct_object(key_node, deep=True)
            if not isinstance(key, Hashable) or isinstance(key, (list, dict)):
                doc.problems.append((path, _mark(key_node), "mapping keys must be scalars"))
                continue
            if key in out and key not in merged:
                doc.problems.append(
                    (path + (key,), _mark(key_node), f"duplicate key {key!r}")
                )
            merged.discard(key)
            if id(key_node) not in explicit:
                merged.add(key)
            doc.keys[path + (key,)] = _mark(key_node)
            out[key] = _build(loader, value_node, path + (key,), doc, count)
        return out
    return loader.construct_object(node, deep=True)


def dump(data: Any) -> str:
    """Write plain Python data (dicts, lists, tuples, scalars) as block YAML."""
    return yaml.dump(
        _plain(data), Dumper=_Dumper, sort_keys=False, default_flow_style=None, width=100
    )


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
