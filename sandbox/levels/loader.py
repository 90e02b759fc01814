"""Load, validate and dump level files.

Validation is strict and complete: the schema (types, ranges, unknown keys),
the cross-references (names, shape parameters, mesh files, criteria) and the
FSM (maneuvers and macros, their parameters after substitution, transitions)
are all checked, and every problem is reported at once with its file, line
and column. Nothing runs on an invalid level.
"""

from __future__ import annotations

import dataclasses
import pathlib
import warnings
from collections.abc import Iterable, Mapping
from typing import Any

import pydantic
import yaml

from sandbox.levels import checks, include, yamlio
from sandbox.levels.diagnostics import Finding, convert
from sandbox.levels.expand import expand
from sandbox.levels.issues import LevelError, LevelIssue, LevelWarning, Severity, format_path, syntax_issue
from sandbox.levels.schema import FSM, Level, Macro
from sandbox.maneuvers.base import REGISTRY, Maneuver

_FSM = pydantic.TypeAdapter(FSM)
_MACRO = pydantic.TypeAdapter(Macro)


@dataclasses.dataclass
class LevelCheck:
    """The outcome of checking a level.

    Attributes:
        level: the level, or None when there are errors.
        errors: problems that stop it from loading.
        warnings: problems that do not.
        libraries: the macro library files it includes (resolved paths), in the order read.
    """

    level: Level | None
    errors: list[LevelIssue]
    warnings: list[LevelIssue]
    libraries: list[pathlib.Path] = dataclasses.field(default_factory=list)


def load_level(
    path: str | pathlib.Path,
    overrides: Mapping[str, Any] | None = None,
    *,
    registry: Mapping[str, type[Maneuver]] | None = None,
) -> Level:
    """Load and validate a level file.

    Args:
        path: the YAML file; relative paths inside it (meshes) are relative
            to its folder.
        overrides: dotted keys and values set before validation, e.g.
            ``{"sim.frames": 10, "scene.ropes.0.radius": 0.01}``.
        registry: maneuver name -> class (default: the global registry).

    Raises:
        LevelError: listing every problem, one per line.
    """
    return _raise_or_return(check_level(path, overrides, registry=registry))


def load_level_from_string(
    text: str,
    *,
    source: str = "<string>",
    base_dir: str | pathlib.Path | None = None,
    overrides: Mapping[str, Any] | None = None,
    registry: Mapping[str, type[Maneuver]] | None = None,
) -> Level:
    """Load and validate a level from YAML text.

    Args:
        text: the YAML.
        source: the name used in messages.
        base_dir: folder that relative file paths start from (default: cwd).
        overrides: as for ``load_level``.
        registry: as for ``load_level``.

    Raises:
        LevelError: listing every problem, one per line.
    """
    return _raise_or_return(
        check_level_text(text, source=source, base_dir=base_dir, overrides=overrides,
                         registry=registry)
    )


def _raise_or_return(result: LevelCheck) -> Level:
    if result.errors:
        raise LevelError(result.errors, result.warnings)
    for issue in result.warnings:
        warnings.warn(str(issue), LevelWarning, stacklevel=3)
    assert result.level is not None
    return result.level


def check_level(
    path: str | pathlib.Path,
    overrides: Mapping[str, Any] | None = None,
    *,
    registry: Mapping[str, type[Maneuver]] | None = None,
    mesh_dirs: Iterable[str | pathlib.Path] = (),
) -> LevelCheck:
    """Check a level file without raising; see ``load_level``.

    ``mesh_dirs`` are folders mesh files may come from besides the level's own and those of
    ``SANDBOX_MESH_DIRS``."""
    path = pathlib.Path(path)
    text, problem, line = read_text(path)
    if problem:
        return LevelCheck(None, [LevelIssue(str(path), line, 1 if line else 0, "", problem)], [])
    return check_level_text(
        text, source=str(path), base_dir=path.parent, overrides=overrides, registry=registry,
        mesh_dirs=mesh_dirs,
    )


def read_text(path: pathlib.Path) -> tuple[str, str | None, int]:
    """A level or sweep file's text, or what is wrong with it (not a file, too big, not UTF-8) and on which line."""
    try:
        size = path.stat().st_size
        if not path.is_file():
            return "", "not a file", 0
        if size > yamlio.MAX_BYTES:
            return "", f"the file is {size} bytes; allowed at most {yamlio.MAX_BYTES}", 1
        raw = path.read_bytes()
    except OSError as exc:
        return "", f"cannot read it: {exc.strerror or exc}", 0
    try:
        return raw.decode("utf-8"), None, 0
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        return "", f"not UTF-8 text: byte 0x{raw[exc.start]:02x} cannot be read; save the file as UTF-8", line


def check_level_text(
    text: str,
    *,
    source: str = "<string>",
    base_dir: str | pathlib.Path | None = None,
    overrides: Mapping[str, Any] | None = None,
    registry: Mapping[str, type[Maneuver]] | None = None,
    mesh_dirs: Iterable[str | pathlib.Path] = (),
) -> LevelCheck:
    """Check YAML text without raising; see ``load_level_from_string`` (``mesh_dirs``: see ``check_level``)."""
    registry = REGISTRY if registry is None else registry
    base = pathlib.Path.cwd() if base_dir is None else pathlib.Path(base_dir)
    try:
        doc = yamlio.parse(text)
    except yaml.MarkedYAMLError as exc:
        return LevelCheck(None, [syntax_issue(exc, source)], [])
    if doc.data is None:
        doc.data = {}
    findings = [Finding(path, msg) for path, _, msg in doc.problems]
    if not isinstance(doc.data, dict):
        findings.append(Finding((), "a level must be a mapping (version, name, scene, fsm, ...)"))
        return _result(None, findings, doc, source, set())
    from sandbox.levels.limits import mesh_dirs as allowed_dirs  # noqa: PLC0415

    extra = [*allowed_dirs(), *[pathlib.Path(d) for d in mesh_dirs]]
    level_file = pathlib.Path(source)
    libs = include.gather(doc.data, base, extra, level_file if level_file.is_file() else None)
    findings += libs.findings
    overrides = dict(overrides or {})
    for key in [k for k in overrides if k.split(".")[0] == "include"]:
        del overrides[key]
        findings.append(Finding((), f"override {key!r}: 'include' cannot be overridden (libraries are read "
                                    "before overrides apply); set the macros themselves, e.g. macros.NAME.steps.0..."))
    overridden, problems = apply_overrides(doc.data, overrides)
    findings += problems
    level, found = _validate(doc.data, base, registry, extra)
    findings += found
    return _result(level, findings, doc, source, overridden, libs)


def _validate(
    data: dict, base_dir: pathlib.Path, registry: Mapping[str, type[Maneuver]],
    extra_dirs: list[pathlib.Path] = (),
) -> tuple[Level | None, list[Finding]]:
    findings: list[Finding] = []
    level = None
    try:
        level = Level.model_validate(data)
    except pydantic.ValidationError as exc:
        findings += convert(exc, Level, data)
    findings += checks.check_names(data)
    findings += checks.check_camera(data)
    findings += checks.check_sim(data)
    from sandbox.levels.limits import Limits  # noqa: PLC0415

    findings += checks.check_objects(data, base_dir, extra_dirs)
    try:
        findings += checks.check_resources(data, Limits.from_env())
    except ValueError as exc:
        findings.append(Finding((), f"SANDBOX_LIMITS: {exc}"))

    macros: dict[str, Macro] = {}
    unchecked: set[str] = set()
    raw_macros = data.get("macros")
    if isinstance(raw_macros, dict):
        for name, raw in raw_macros.items():
            try:
                macros[name] = _MACRO.validate_python(raw)
            except pydantic.ValidationError:
                unchecked.add(name)  # reported by the schema
    try:
        fsm = _FSM.validate_python(data.get("fsm"))
    except pydantic.ValidationError:
        fsm = None  # reported by the schema; the macros are still checked
    flat, found = expand(fsm, macros, registry, unchecked=unchecked)
    findings += found
    if fsm is not None:  # without states, a criterion's targets cannot be told apart
        findings += checks.check_criteria(data, flat.names(), checks.used_maneuvers(flat.states))
        findings += checks.check_references(data, flat.states)
    if any(f.severity is Severity.ERROR for f in findings):
        level = None
    return level, findings


def issues_from_findings(
    findings: Iterable[Finding],
    source: str,
    doc: yamlio.Document | None = None,
    overridden: set[yamlio.Path] | None = None,
    origin: Mapping[str, include.Library] | None = None,
) -> list[LevelIssue]:
    """Give findings their file positions, sorted by file and position.

    Args:
        findings: the problems.
        source: the file name written in each issue.
        doc: the parsed document (without it, lines and columns are 0).
        overridden: document paths set by overrides (their problems say so).
        origin: macro name -> the library it was included from: a problem
            under ``macros.NAME`` is placed in that library's file.
    """
    origin = origin or {}

    def where(path: yamlio.Path) -> tuple[str, yamlio.Document | None]:
        if len(path) >= 2 and path[0] == "macros" and path[1] in origin:
            return origin[path[1]].source, origin[path[1]].doc
        return source, doc

    out = []
    for f in findings:
        line = col = 0
        file, fdoc = where(f.path)
        if fdoc is not None:
            _, mark = fdoc.locate(f.path, key=f.key)
            line, col = mark.line, mark.column
        message = f.message
        for opath in overridden or ():
            if f.path[: len(opath)] == opath:
                message += f" (value set by override {'.'.join(map(str, opath))!r})"
                break
        if f.trace:
            steps = []
            for label, tpath in f.trace:
                tfile, tdoc = where(tpath)
                if tdoc is not None:
                    label += f" at {tfile + ' ' if tfile != file else ''}line {tdoc.locate(tpath, key=True)[1].line}"
                steps.append(label)
            message += f" ({'; '.join(steps)})"
        out.append(LevelIssue(file, line, col, format_path(f.path), message, f.severity))
    out.sort(key=lambda i: (i.file != source, i.file, i.line, i.column))
    return out


def _result(
    level: Level | None,
    findings: list[Finding],
    doc: yamlio.Document,
    source: str,
    overridden: set[yamlio.Path],
    libs: include.Included | None = None,
) -> LevelCheck:
    libs = libs or include.Included()
    issues = issues_from_findings(findings, source, doc, overridden, libs.origin) + libs.issues
    errors = [i for i in issues if i.severity is Severity.ERROR]
    warns = [i for i in issues if i.severity is Severity.WARNING]
    return LevelCheck(None if errors else level, errors, warns, [lib.path for lib in libs.libraries])


def apply_overrides(
    data: dict, overrides: Mapping[str, Any]
) -> tuple[set[yamlio.Path], list[Finding]]:
    """Set dotted keys in ``data`` in place (missing mappings are created).

    A numeric part indexes a list (``scene.ropes.0.radius``).

    Returns:
        The document paths set, and problems with keys that cannot be set.
    """
    done: set[yamlio.Path] = set()
    problems = []
    for dotted, value in overrides.items():
        parts: list[Any] = dotted.split(".")
        node: Any = data
        path: list[Any] = []
        for k, part in enumerate(parts):
            last = k == len(parts) - 1
            if isinstance(node, list):
                if not part.lstrip("-").isdigit() or not -len(node) <= int(part) < len(node):
                    problems.append(Finding(
                        tuple(path), f"override {dotted!r}: {part!r} is not an index of this "
                        f"list of {len(node)}",
                    ))
                    break
                part = int(part) % len(node)
            elif not isinstance(node, dict):
                problems.append(Finding(
                    tuple(path), f"override {dotted!r}: {format_path(tuple(path))} is not a mapping"
                ))
                break
            path.append(part)
            if last:
                node[part] = value
                done.add(tuple(path))
            else:
                if isinstance(node, dict) and node.get(part) is None:
                    node[part] = {}
                node = node[part]
    return done, problems


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """``["sim.frames=10", "sim.arch=cpu"]`` -> ``{"sim.frames": 10, "sim.arch": "cpu"}``.

    Values are read as YAML scalars or flow collections (``[0, 1, 0]``).

    Raises:
        ValueError: for an item without ``=`` or with a value that is not YAML.
    """
    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"override {item!r} is not of the form key=value")
        try:
            out[key.strip()] = yamlio.parse(text).data
        except yaml.YAMLError as exc:
            what = " ".join(p for p in (getattr(exc, "context", None), getattr(exc, "problem", None)) if p)
            raise ValueError(f"override {item!r}: the value is not valid YAML ({what or exc})") from exc
    return out


def dump_level(level: Level, *, defaults: bool = False) -> str:
    """The level as YAML that loads back to an equal level.

    Args:
        level: the level.
        defaults: also write the values left at their defaults.
    """
    data = level.model_dump(mode="python", by_alias=True, exclude_defaults=not defaults)
    return yamlio.dump(data)
