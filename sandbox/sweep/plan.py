"""What a sweep runs: axes, the shipped ``--standard`` set, and runs resolved against a level.

An axis is one key with the values it takes:

- any key that ``sandbox run --set`` accepts (``sim.substeps``,
  ``fsm.1.with.w0``, ``scene.objects.0.friction``, ...): a list of values,
  or a range ``{range: [lo, hi], steps: n}``; a numeric value may be
  relative to the level's own, ``{add: x}`` or ``{scale: x}`` (an integer
  setting stays an integer, rounded half up);
- ``place.TARGET.shift`` (``[dx, dy, dz]`` m) and ``place.TARGET.turn``
  (degrees about the vertical), TARGET ``scene`` or a body's name: a rigid
  placement (``sandbox.sweep.placement``);
- ``place.TARGET.nudge`` (m): a further shift by this much along each axis,
  added to the target's ``shift``. A micrometre is no physical change at a
  rope's scale but changes the float rounding of every position: it
  measures how much an outcome depends on rounding alone;
- ``swap.OBJECT``: a shape name or ``mesh:PATH``, the object replaced by
  one of similar size;
- ``compile``: ``full`` or ``fast`` (Taichi's advanced optimisations on or
  off). On the CPU, with fast-math and the CFG pass off
  (``sandbox.runtime``), both compile to the same float operations and give
  the same frames; a GPU backend is not measured.

A sweep file holds the axes::

    version: 1
    description: substeps against placement   # optional
    axes:
      sim.substeps: [15, 20, {scale: 1.5}]
      place.scene.shift: [[0.02, 0, 0], [0, 0, -0.05]]
      place.scene.turn: {range: [-10, 10], steps: 3}
      compile: [full, fast]

``--grid`` runs the product of the axes; ``--samples N --seed S`` draws N
points instead, each axis independently (a list uniformly, a range
uniformly between its ends; whole numbers for a key the schema holds as an
integer, such as ``sim.substeps``). A point drawn twice runs once.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import pathlib
from typing import Any

import numpy as np
import yaml

from sandbox.levels import yamlio
from sandbox.levels.issues import LevelIssue, format_path, syntax_issue
from sandbox.sweep import placement

COMPILE_MODES = ("full", "fast")
NUDGE = 1e-6
"""The standard set's rounding perturbation (m): the scene moved 1 um along each axis. Positions are
about 0.3 m from the origin, where a float32 step is 3e-8 m, so every coordinate rounds differently."""
MAX_NUDGE = 1e-3
"""Largest ``nudge`` allowed (m): beyond a millimetre it is a placement, and ``shift`` says so."""
SET_ROOTS = ("scene", "sim", "fsm", "macros", "success", "budget")
"""First parts of the level keys an axis may set."""
TOP_KEYS = ("version", "description", "axes")


class SweepError(ValueError):
    """A sweep file or a sweep's runs are not valid; ``issues`` holds every problem found."""

    def __init__(self, issues: list[LevelIssue]):
        self.issues = list(issues)
        super().__init__(str(self))

    def __str__(self) -> str:
        return "\n".join(str(i) for i in self.issues)


def integer_key(key: str) -> bool:
    """Whether a level key holds an integer by the schema (``sim.substeps``, a rope's ``segments``, ...)."""
    from sandbox.levels.schema import Sim  # noqa: PLC0415

    parts = key.split(".")
    if parts[0] == "sim" and len(parts) == 2 and parts[1] in Sim.model_fields:
        return "int" in str(Sim.model_fields[parts[1]].annotation)
    if parts[0] == "scene" and len(parts) >= 4:
        return (parts[1], parts[3]) in (("ropes", "segments"), ("cloths", "resolution"))
    return False


@dataclasses.dataclass(frozen=True)
class Range:
    """Values between ``lo`` and ``hi``: ``steps`` of them, evenly, in a grid; uniform when sampled.

    ``integer``: whole numbers (grid values rounded half up), for a key the schema holds as an integer.
    """

    lo: float
    hi: float
    steps: int
    integer: bool = False

    def grid(self) -> list:
        vals = np.linspace(self.lo, self.hi, self.steps)
        return [int(np.floor(v + 0.5)) for v in vals] if self.integer else [float(v) for v in vals]

    def draw(self, rng: np.random.Generator):
        if self.integer:
            return int(rng.integers(math.ceil(self.lo), math.floor(self.hi) + 1))
        return float(rng.uniform(self.lo, self.hi))


@dataclasses.dataclass(frozen=True)
class Axis:
    """One swept key and its values (a list, or a ``Range``)."""

    key: str
    values: tuple | Range

    def grid(self) -> list:
        return self.values.grid() if isinstance(self.values, Range) else list(self.values)

    def draw(self, rng: np.random.Generator):
        if isinstance(self.values, Range):
            return self.values.draw(rng)
        return self.values[int(rng.integers(len(self.values)))]


Variant = dict  # axis key -> value; an absent key means as shipped


@dataclasses.dataclass
class Run:
    """One run of a sweep: a level with a variant, resolved to overrides.

    Attributes:
        id: stable key of the run (level content and variant): a re-run of the
            sweep skips ids it has a row for.
        level: absolute path of the level file.
        level_name: the level's ``name``.
        level_sha: first 12 hex digits of the SHA-1 of the level file and the macro libraries it includes.
        variant: axis key -> value as written (JSON-able).
        label: the variant in words.
        overrides: dotted level keys -> values that make the variant.
        compile: ``full`` or ``fast``.
        mesh_dirs: folders the run may read mesh files from besides the level's (swapped-in meshes).
    """

    id: str
    level: str
    level_name: str
    level_sha: str
    variant: dict
    label: str
    overrides: dict
    compile: str = "full"
    mesh_dirs: list = dataclasses.field(default_factory=list)


# ----------------------------------------------------------------------------- sweep files


def _kind(key: str) -> str | None:
    parts = key.split(".")
    if key == "compile":
        return "compile"
    if parts[0] == "place" and len(parts) == 3 and parts[2] in ("shift", "turn", "nudge") and parts[1]:
        return parts[2]
    if parts[0] == "swap" and len(parts) == 2 and parts[1]:
        return "swap"
    if parts[0] in SET_ROOTS and len(parts) >= 2 and all(parts):
        return "set"
    return None


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _value_problem(kind: str, value: Any, base: pathlib.Path) -> str | None:
    """What is wrong with one value of an axis of this kind (None if nothing)."""
    if kind == "compile" and value not in COMPILE_MODES:
        return f"{value!r} is not a compile mode; allowed: {', '.join(COMPILE_MODES)}"
    if kind == "shift" and not (isinstance(value, list) and len(value) == 3 and all(map(_is_number, value))):
        return f"{value!r} is not a shift; allowed: [dx, dy, dz] in m, finite numbers"
    if kind == "nudge" and not (_is_number(value) and abs(value) <= MAX_NUDGE):
        return f"{value!r} is not a nudge; allowed: a finite number of m, at most {MAX_NUDGE:g} in size"
    if kind == "turn" and not _is_number(value):
        return f"{value!r} is not a turn; allowed: degrees, a finite number"
    if kind == "swap":
        if not isinstance(value, str):
            return f"{value!r} is not a swap; allowed: {', '.join(placement.SWAP_SHAPES)} or mesh:PATH"
        if value.startswith("mesh:"):
            if not (base / value[5:]).is_file():
                return f"mesh file {value[5:]!r} not found (looked for {base / value[5:]})"
        elif value not in placement.SWAP_SHAPES:
            return f"{value!r} is not a shape; allowed: {', '.join(placement.SWAP_SHAPES)} or mesh:PATH"
    if kind == "set" and isinstance(value, dict):
        if set(value) not in ({"add"}, {"scale"}) or not _is_number(next(iter(value.values()))):
            return (f"{value!r} is not a relative value; allowed: {{add: x}} or {{scale: x}} with a "
                    "finite number x")
    return None


def parse_sweep(text: str, *, source: str = "<string>", base_dir: pathlib.Path | None = None) -> list[Axis]:
    """Axes of a sweep file, validated strictly.

    Args:
        text: the YAML.
        source: the name used in messages.
        base_dir: folder that ``mesh:`` paths start from (default: cwd).

    Raises:
        SweepError: listing every problem, with file, line and column, and
            what is allowed.
    """
    base = pathlib.Path.cwd() if base_dir is None else pathlib.Path(base_dir)
    try:
        doc = yamlio.parse(text)
    except yaml.MarkedYAMLError as exc:
        raise SweepError([syntax_issue(exc, source)]) from None
    found: list[tuple[tuple, str, bool]] = [(p, m, False) for p, _, m in doc.problems]
    data = doc.data
    axes: list[Axis] = []
    if not isinstance(data, dict):
        found.append(((), "a sweep file must be a mapping with 'version: 1' and 'axes'", False))
        data = {}
    for key in data:
        if key not in TOP_KEYS:
            found.append(((key,), f"unknown key {key!r}; allowed: {', '.join(TOP_KEYS)}", True))
    if data and data.get("version") != 1:
        found.append((("version",), f"version must be 1, got {data.get('version')!r}", False))
    if "description" in data and not isinstance(data["description"], str):
        found.append((("description",), "description must be a string", False))
    raw = data.get("axes")
    if data and not isinstance(raw, dict) or isinstance(raw, dict) and not raw:
        found.append((("axes",), "axes must be a non-empty mapping of key -> values", False))
        raw = {}
    for key, values in (raw or {}).items():
        path = ("axes", key)
        kind = _kind(str(key))
        if kind is None:
            found.append((path, f"unknown axis {key!r}; allowed: compile, place.TARGET.shift, "
                                f"place.TARGET.turn, place.TARGET.nudge, swap.OBJECT, or a level key starting with "
                                f"{', '.join(r + '.' for r in SET_ROOTS)}", True))
            continue
        if isinstance(values, dict) and "range" in values:
            extra = sorted(set(values) - {"range", "steps"})
            rng = values.get("range")
            steps = values.get("steps", 2)
            if extra:
                found.append((path, f"unknown key(s) {', '.join(extra)} in a range; allowed: range, steps", False))
            elif kind not in ("set", "turn", "nudge"):
                found.append((path, f"axis {key!r} takes a list of values, not a range", False))
            elif not (isinstance(rng, list) and len(rng) == 2 and all(map(_is_number, rng)) and rng[0] <= rng[1]):
                found.append((path + ("range",), f"range must be [lo, hi] with finite numbers lo <= hi, got {rng!r}",
                              False))
            elif kind == "nudge" and max(abs(rng[0]), abs(rng[1])) > MAX_NUDGE:
                found.append((path + ("range",), f"a nudge is at most {MAX_NUDGE:g} m in size, got {rng!r}", False))
            elif not (isinstance(steps, int) and not isinstance(steps, bool) and steps >= 1):
                found.append((path + ("steps",), f"steps must be an integer >= 1, got {steps!r}", False))
            else:
                whole = kind == "set" and integer_key(str(key))
                axes.append(Axis(str(key), Range(rng[0], rng[1], steps, whole)))
            continue
        if not isinstance(values, list) or not values:
            found.append((path, "an axis takes a non-empty list of values or {range: [lo, hi], steps: n}", False))
            continue
        ok = True
        for i, value in enumerate(values):
            problem = _value_problem(kind, value, base)
            if problem:
                found.append((path + (i,), problem, False))
                ok = False
        if ok:
            axes.append(Axis(str(key), tuple(values)))
    issues = []
    for path, message, key in found:
        _, mark = doc.locate(path, key=key)
        issues.append(LevelIssue(source, mark.line, mark.column, format_path(path), message))
    if issues:
        issues.sort(key=lambda i: (i.line, i.column))
        raise SweepError(issues)
    return axes


def load_sweep(path: str | pathlib.Path) -> list[Axis]:
    """Axes of a sweep file (``parse_sweep``); ``mesh:`` paths are relative to its folder."""
    from sandbox.levels.loader import read_text  # noqa: PLC0415

    path = pathlib.Path(path)
    text, problem, line = read_text(path)
    if problem:
        raise SweepError([LevelIssue(str(path), line, 1 if line else 0, "", problem)])
    return parse_sweep(text, source=str(path), base_dir=path.parent)


def grid_variants(axes: list[Axis]) -> list[Variant]:
    """The product of the axes' values, the first axis varying slowest."""
    keys = [a.key for a in axes]
    return [dict(zip(keys, combo)) for combo in itertools.product(*(a.grid() for a in axes))]


def sample_variants(axes: list[Axis], n: int, seed: int) -> list[Variant]:
    """``n`` points drawn independently per axis from a generator seeded with ``seed``."""
    rng = np.random.default_rng(seed)
    return [{a.key: a.draw(rng) for a in axes} for _ in range(n)]


# ----------------------------------------------------------------------------- the standard set

STANDARD_PLACEMENTS: tuple[tuple[str, Variant], ...] = (
    ("x +2 cm", {"place.scene.shift": [0.02, 0.0, 0.0]}),
    ("x -2 cm", {"place.scene.shift": [-0.02, 0.0, 0.0]}),
    ("z +5 cm", {"place.scene.shift": [0.0, 0.0, 0.05]}),
    ("z -5 cm", {"place.scene.shift": [0.0, 0.0, -0.05]}),
    ("up 3 cm", {"place.scene.shift": [0.0, 0.03, 0.0]}),
    ("turn 10 deg", {"place.scene.turn": 10.0}),
)
"""The six placements of ``--standard``: the whole scene moved (FSM points stay)."""

STANDARD_SETTINGS: tuple[tuple[str, Variant], ...] = (
    ("as shipped", {}),
    ("nudged 1 um", {"place.scene.nudge": NUDGE}),
    ("substeps +25 %", {"sim.substeps": {"scale": 1.25}}),
    ("iterations +1", {"sim.iterations": {"add": 1}}),
)
"""The four settings of ``--standard``, each run at every placement."""


def wrapped_objects(data: dict) -> list[str]:
    """Objects that the level wraps in cloth: the ``object`` of its ``Wrapping`` steps (macros included)."""
    found: list[str] = []

    def visit(node):
        if isinstance(node, dict):
            w = node.get("with")
            if node.get("run") == "Wrapping" and isinstance(w, dict) and isinstance(w.get("object"), str):
                if w["object"] not in found:
                    found.append(w["object"])
            for v in node.values():
                visit(v)
        elif isinstance(node, list):
            for v in node:
                visit(v)

    if (data.get("scene") or {}).get("cloths"):
        visit(data.get("fsm"))
        visit(data.get("macros"))
    return [name for name in found if placement.bodies(data).get(name, ("",))[0] == "object"]


def standard_variants(data: dict) -> list[tuple[str, Variant]]:
    """The ``--standard`` set for one level, as (label, variant) pairs.

    Six placements x four settings (24 runs); a level that wraps an object
    in cloth also runs, as shipped, with that object swapped for each other
    procedural shape of similar size (``SWAP_SHAPES``).
    """
    out = []
    for (pl, pv), (sl, sv) in itertools.product(STANDARD_PLACEMENTS, STANDARD_SETTINGS):
        out.append((f"{pl}, {sl}", {**pv, **sv}))
    for name in wrapped_objects(data):
        k = placement.bodies(data)[name][1]
        own = data["scene"]["objects"][k].get("shape")
        for shape in placement.SWAP_SHAPES:
            if shape != own:
                out.append((f"{name} -> {shape}", {f"swap.{name}": shape}))
    return out


# ----------------------------------------------------------------------------- runs of a level


def describe(variant: Variant) -> str:
    """A variant in words: ``key=value`` pairs, or ``as shipped``."""
    if not variant:
        return "as shipped"
    return ", ".join(f"{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in variant.items())


def _lookup(data: Any, dotted: str) -> Any:
    node = data
    for part in dotted.split("."):
        if isinstance(node, list) and part.lstrip("-").isdigit() and -len(node) <= int(part) < len(node):
            node = node[int(part)]
        elif isinstance(node, dict) and part in node:
            node = node[part]
        else:
            raise KeyError(dotted)
    return node


def _relative(key: str, base: Any, rel: dict) -> Any:
    (op, x), = rel.items()
    if not _is_number(base):
        raise ValueError(f"its value in the level is {base!r}, not a number")
    value = base + x if op == "add" else base * x
    if integer_key(key):
        return int(math.floor(value + 0.5))
    return float(value)


def run_id(level_sha: str, variant: Variant, frames: int | None = None) -> str:
    """Stable id of a run: 16 hex digits of the SHA-1 of the level's content hash, the variant and the frames
    to run (when not the level's own)."""
    text = json.dumps([level_sha, variant] if frames is None else [level_sha, variant, frames], sort_keys=True)
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def resolve(level: pathlib.Path, variants: list[tuple[str, Variant]], *, sweep_base: pathlib.Path | None = None,
            source: str = "<sweep>", frames: int | None = None) -> list[Run]:
    """The runs of ``variants`` on one level, each checked as the level it makes.

    Args:
        level: the level file.
        variants: (label, variant) pairs; an empty label is replaced by
            ``describe(variant)``.
        sweep_base: folder that ``mesh:`` swap paths start from.
        source: the name of the sweep in messages.
        frames: frames each run runs, when not the level's own (part of the run's id).

    Raises:
        SweepError: every variant that cannot be made or does not make a valid
            level, with what was wrong (nothing has run).
    """
    from sandbox.levels import check_level  # noqa: PLC0415
    from sandbox.levels.loader import apply_overrides, dump_level  # noqa: PLC0415

    import sandbox.maneuvers  # noqa: F401, PLC0415  (registers the maneuvers the levels name)

    level = pathlib.Path(level).resolve()
    base = pathlib.Path(sweep_base or pathlib.Path.cwd())
    raw = level.read_bytes()
    first = check_level(level)
    if first.errors:
        raise SweepError(first.errors)
    digest = hashlib.sha1(raw)
    for library in first.libraries:  # a macro library's change is the level's change
        digest.update(library.read_bytes())
    sha = digest.hexdigest()[:12]
    name = first.level.name
    data = yamlio.parse(raw.decode("utf-8")).data
    full = yaml.safe_load(dump_level(first.level, defaults=True))  # the level's values, defaults included
    runs: list[Run] = []
    problems: list[LevelIssue] = []

    def problem(label: str, message: str) -> None:
        problems.append(LevelIssue(source, 0, 0, f"{name} [{label}]", message))

    for label, variant in variants:
        label = label or describe(variant)
        overrides: dict[str, Any] = {}
        compile_mode = "full"
        mesh_dirs: list[str] = []
        ok = True
        shifts: dict[str, dict] = {}
        for key, value in variant.items():
            kind = _kind(key)
            if kind == "compile":
                compile_mode = value
            elif kind in ("shift", "turn", "nudge"):
                shifts.setdefault(key.split(".")[1], {})[kind] = value
            elif kind == "swap":
                obj = key.split(".", 1)[1]
                path = f"mesh:{(base / value[5:]).resolve()}" if value.startswith("mesh:") else value
                if value.startswith("mesh:"):
                    mesh_dirs.append(str((base / value[5:]).resolve().parent))  # the swap's file may be read
                try:
                    overrides.update(placement.swap_overrides(data, obj, path, level.parent))
                except KeyError:
                    objs = [n for n, (k, _) in placement.bodies(data).items() if k == "object"]
                    problem(label, f"{key}: {obj!r} is not an object of the level; objects: "
                                   f"{', '.join(objs) or '(none)'}")
                    ok = False
                except (ValueError, FileNotFoundError) as exc:
                    problem(label, f"{key}: {exc}")
                    ok = False
            elif kind == "set":
                if isinstance(value, dict):
                    try:
                        value = _relative(key, _lookup(full, key), value)
                    except KeyError:
                        problem(label, f"{key}: the level has no value there to be relative to")
                        ok = False
                        continue
                    except ValueError as exc:
                        problem(label, f"{key}: {exc}")
                        ok = False
                        continue
                overrides[key] = value
        placed = data
        for target, move in sorted(shifts.items(), key=lambda kv: kv[0] != placement.SCENE):  # scene first
            try:
                shift = np.add(move.get("shift", (0.0, 0.0, 0.0)), move.get("nudge", 0.0)).tolist()
                moved = placement.placement_overrides(placed, target, shift, move.get("turn", 0.0))
                overrides.update(moved)
                placed = json.loads(json.dumps(placed))  # a body placed after the scene moves from where it went
                apply_overrides(placed, moved)
            except KeyError:
                names = ", ".join(placement.bodies(data)) or "(none)"
                problem(label, f"place.{target}: not a body of the level; allowed: scene, {names}")
                ok = False
        if not ok:
            continue
        check = check_level(level, overrides, mesh_dirs=mesh_dirs)
        if check.errors:
            for e in check.errors:
                problem(label, f"{e.path}: {e.message}")
            continue
        plain = json.loads(json.dumps(variant))
        runs.append(Run(run_id(sha, plain, frames), str(level), name, sha, plain, label, overrides, compile_mode,
                        mesh_dirs))
    if problems:
        raise SweepError(problems)
    seen: dict[str, str] = {}
    for r in runs:
        if r.id in seen:
            raise SweepError([LevelIssue(source, 0, 0, name, f"variants {seen[r.id]!r} and {r.label!r} are the same run")])
        seen[r.id] = r.label
    return runs
