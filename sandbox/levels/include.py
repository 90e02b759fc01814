"""Macro libraries: YAML files of macros that levels include.

A level (or a library) lists files under ``include:``; their paths are
relative to the including file's folder and must lie in the level's folder
(or below it), or in a folder allowed with ``--allow-dir`` /
``SANDBOX_MESH_DIRS``. A library holds ``macros:`` (as a level does), and
may have ``version: 1``, a ``description`` and its own ``include:``::

    version: 1
    description: knots tied by two hands
    macros:
      GrannyKnot: {params: [...], steps: [...]}

The included macros join the level's own as if written in it (a loaded
``Level`` holds them in ``macros``, and its ``include`` is empty); a name
defined twice is an error. Problems inside a library are reported at its
file, line and column.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Iterable
from typing import Any

import yaml

from sandbox.levels import yamlio
from sandbox.levels.diagnostics import Finding
from sandbox.levels.issues import LevelIssue, format_path, syntax_issue

MAX_FILES = 32
"""Most library files one level may pull in, its libraries' includes counted."""
LIBRARY_KEYS = ("version", "description", "include", "macros")


@dataclasses.dataclass(frozen=True)
class Library:
    """A macro library that was read.

    Attributes:
        path: its resolved path.
        source: its name in messages (the path as the including file wrote it, joined to that file's folder).
        doc: the parsed document (for positions).
    """

    path: pathlib.Path
    source: str
    doc: yamlio.Document


@dataclasses.dataclass
class Included:
    """What ``gather`` found.

    Attributes:
        origin: macro name -> the library it came from.
        libraries: every library read, in the order read.
        findings: problems at the level's own ``include`` or ``macros`` entries (level document paths).
        issues: problems inside libraries, already at their file positions.
    """

    origin: dict[str, Library] = dataclasses.field(default_factory=dict)
    libraries: list[Library] = dataclasses.field(default_factory=list)
    findings: list[Finding] = dataclasses.field(default_factory=list)
    issues: list[LevelIssue] = dataclasses.field(default_factory=list)


def gather(data: dict, base_dir: pathlib.Path, extra_dirs: Iterable[pathlib.Path] = (),
           level_path: pathlib.Path | None = None) -> Included:
    """Read the libraries ``data["include"]`` names and add their macros to ``data["macros"]`` in place.

    Args:
        data: the level's plain data.
        base_dir: the level file's folder.
        extra_dirs: further folders library files may come from.
        level_path: the level file itself, if it is one (a level that includes itself is an error).
    """
    out = Included()
    roots = [base_dir.resolve(), *[pathlib.Path(d).resolve() for d in extra_dirs]]
    own = data.get("macros")
    if "include" in data and own is None:
        data["macros"] = own = {}
    defined: dict[str, tuple] = {name: ("level", None) for name in own} if isinstance(own, dict) else {}

    def visit(entries: Any, folder: pathlib.Path, at: Library | None, stack: tuple[pathlib.Path, ...]) -> None:
        def problem(path: tuple, message: str) -> None:
            if at is None:
                out.findings.append(Finding(path, message))
            else:
                mark = at.doc.locate(path)[1]
                out.issues.append(LevelIssue(at.source, mark.line, mark.column, format_path(path), message))

        if entries is None:
            return
        if isinstance(entries, str):
            entries = [entries]
        if not isinstance(entries, list) or not all(isinstance(e, str) and e.strip() for e in entries):
            problem(("include",), "include must be a file name or a list of file names (YAML files of macros)")
            return
        for k, entry in enumerate(entries):
            where = ("include", k)
            path = (folder / entry).resolve()
            if not any(path == r or r in path.parents for r in roots):
                problem(where, f"macro library {entry!r} lies outside the level's folder ({roots[0]}); libraries "
                               "must be in it or below it, or in a folder allowed with --allow-dir DIR "
                               "(or SANDBOX_MESH_DIRS)")
                continue
            if path in stack:
                problem(where, f"macro library {entry!r} includes itself (through {' -> '.join(p.name for p in stack)})")
                continue
            if any(lib.path == path for lib in out.libraries):
                continue  # already read: its macros are in
            if len(out.libraries) >= MAX_FILES:
                problem(where, f"more than {MAX_FILES} macro libraries; allowed at most {MAX_FILES}")
                return
            from sandbox.levels.loader import read_text  # noqa: PLC0415  (the loader imports this module)

            source = str(folder / entry)
            text, trouble, line = read_text(path)
            if trouble:
                if not path.exists():
                    trouble = f"not found (looked for {path}; paths are relative to the including file's folder)"
                problem(where, f"macro library {entry!r}: {trouble}")
                continue
            try:
                doc = yamlio.parse(text)
            except yaml.MarkedYAMLError as exc:
                out.issues.append(syntax_issue(exc, source))
                continue
            lib = Library(path, source, doc)
            out.libraries.append(lib)
            read(lib, stack + (path,))

    def read(lib: Library, stack: tuple[pathlib.Path, ...]) -> None:
        def problem(path: tuple, message: str, *, key: bool = False) -> None:
            mark = lib.doc.locate(path, key=key)[1]
            out.issues.append(LevelIssue(lib.source, mark.line, mark.column, format_path(path), message))

        for path, mark, message in lib.doc.problems:
            out.issues.append(LevelIssue(lib.source, mark.line, mark.column, format_path(path), message))
        body = lib.doc.data
        if not isinstance(body, dict) or not isinstance(body.get("macros"), dict) or not body["macros"]:
            problem((), "a macro library must be a mapping with macros: {Name: {params: [...], steps: [...]}}")
            return
        for key in body:
            if key not in LIBRARY_KEYS:
                problem((key,), f"unknown key {key!r} in a macro library; allowed: {', '.join(LIBRARY_KEYS)}",
                        key=True)
        if "version" in body and body["version"] != 1:
            problem(("version",), f"version {body['version']!r} is not supported; allowed: 1")
        if not isinstance(body.get("description", ""), str):
            problem(("description",), "description must be text")
        visit(body.get("include"), lib.path.parent, lib, stack)
        for name, macro in body["macros"].items():
            first = defined.get(name)
            if first is not None:
                kind, other = first
                there = "in the level" if kind == "level" else f"in {other.source}"
                problem(("macros", name), f"macro {name!r} is defined twice: here and {there}; rename one",
                        key=True)
                continue
            defined[name] = ("library", lib)
            data["macros"][name] = macro
            out.origin[name] = lib

    if isinstance(own, dict) or own is None:
        visit(data.get("include"), base_dir, None, (level_path.resolve(),) if level_path is not None else ())
    data.pop("include", None)  # resolved: the level holds the macros themselves
    return out

