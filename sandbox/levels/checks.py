"""Checks that need the whole level: names, shape parameters, files, criteria.

They read the plain YAML data rather than validated models, so that they
still run, and report, when other parts of the level are invalid.
"""

from __future__ import annotations

import pathlib
from collections.abc import Iterable, Mapping
from typing import Any

from sandbox.levels.diagnostics import Finding

FALLBACK_SHAPES: dict[str, dict[str, Any]] = {
    "box": {"size": None},
    "sphere": {"radius": None},
    "cylinder": {"radius": None, "height": None},
    "capsule": {"radius": None, "height": None},
    "torus": {"major_radius": None, "minor_radius": None},
    "wine_bottle": {"height": None, "radius": None, "neck_radius": None},
    "basket": {
        "radius": None, "height": None, "wall": None, "handle_radius": None, "handle_height": None,
    },
    "jeep": {"length": None, "width": None, "height": None},
    "statue": {"height": None, "seed": None},
    "mesh": {"path": None, "scale": None},
}
"""Shape -> parameter names (defaults unknown) when the builders cannot be imported."""

_KINDS = (("objects", "object"), ("cloths", "cloth"), ("ropes", "rope"))


def shapes() -> dict[str, dict[str, Any]]:
    """Shape -> {parameter: default} from ``sandbox.objects.builders.SHAPES``, or the fallback."""
    try:
        from sandbox.objects.builders import SHAPES  # noqa: PLC0415
    except ImportError:
        return FALLBACK_SHAPES
    return SHAPES


def _items(data: Any, *keys: Any) -> Iterable[tuple[int, dict]]:
    node = data
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            return
        node = node[key]
    if isinstance(node, list):
        for i, item in enumerate(node):
            if isinstance(item, dict):
                yield i, item


def scene_names(data: Any) -> dict[str, list[str]]:
    """Kind ("object", "cloth", "rope") -> names given in the scene."""
    out: dict[str, list[str]] = {kind: [] for _, kind in _KINDS}
    for section, kind in _KINDS:
        for _, item in _items(data, "scene", section):
            if isinstance(item.get("name"), str):
                out[kind].append(item["name"])
    return out


def check_names(data: Any) -> list[Finding]:
    """Names must be unique across objects, cloths and ropes."""
    seen: dict[str, str] = {}
    out = []
    for section, kind in _KINDS:
        for i, item in _items(data, "scene", section):
            name = item.get("name")
            if not isinstance(name, str):
                continue
            where = f"{kind} {i}"
            if name in seen:
                out.append(Finding(
                    ("scene", section, i, "name"),
                    f"name {name!r} is already used by {seen[name]}; names must be unique "
                    "across objects, cloths and ropes",
                ))
            else:
                seen[name] = where
    return out


def check_sim(data: Any) -> list[Finding]:
    """The substep count adapts between ``substeps`` and ``max_substeps``: ``max_substeps >= substeps``."""
    sim = data.get("sim")
    if not isinstance(sim, dict):
        return []
    from sandbox.levels.schema import Sim  # noqa: PLC0415 (the schema's own default, not a copy of it)

    most, least = sim.get("max_substeps"), sim.get("substeps", Sim.model_fields["substeps"].default)
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (most, least)) or most >= least:
        return []
    return [Finding(("sim", "max_substeps"),
                    f"max_substeps ({most}) is below substeps ({least}): allowed is {least} to 200 (at least substeps; "
                    "equal to it for a fixed count), or no max_substeps for the default")]


def check_camera(data: Any) -> list[Finding]:
    """What a camera follows must be ropes, strands of them or cloth lines of the scene."""
    from sandbox.model.strands import names_strand_of

    camera = data.get("scene", {}).get("camera") if isinstance(data.get("scene"), dict) else None
    follow = camera.get("follow") if isinstance(camera, dict) else None
    if not isinstance(follow, list):
        return []
    names = scene_names(data)
    ropes, cloths = names["rope"], names["cloth"]

    return [
        Finding(("scene", "camera", "follow", k),
                f"the camera follows the knot of ropes or cloth lines: {name!r} is neither; ropes: "
                f"{', '.join(ropes) or '(none)'} (or R[i0:i1]); cloth lines: F.line1-F.line4 or F.P..Q of "
                f"{', '.join(cloths) or '(no cloth)'}")
        for k, name in enumerate(follow)
        if isinstance(name, str) and not names_strand_of(name, ropes, cloths)
    ]


def _value_error(value: Any, default: Any) -> str | None:
    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    if default is None:
        return None
    if isinstance(default, bool):
        return None if isinstance(value, bool) else f"should be a boolean, got {value!r}"
    if number(default):
        return None if number(value) else f"should be a number, got {value!r}"
    if isinstance(default, str):
        return None if isinstance(value, str) else f"should be a string, got {value!r}"
    if isinstance(default, (list, tuple)):
        ok = isinstance(value, list) and len(value) == len(default) and all(map(number, value))
        return None if ok else f"should be a list of {len(default)} numbers, got {value!r}"
    return None


MESH_FILE_BYTES = 200_000_000
"""Largest mesh file read."""


def check_objects(data: Any, base_dir: pathlib.Path, extra_dirs: Iterable[pathlib.Path] = ()) -> list[Finding]:
    """Shape parameters must be known to the shape's builder, lengths finite and at most ``MAX_COORD``;
    the object must build (mesh files are read: triangles, finite coordinates, a size bound) and a
    mesh file must lie in the level's folder or one of ``extra_dirs``."""
    from sandbox.levels.schema import MAX_COORD  # noqa: PLC0415

    table = shapes()
    try:
        from sandbox.objects.builders import LENGTH_PARAMS, build_mesh  # noqa: PLC0415
    except ImportError:
        LENGTH_PARAMS, build_mesh = {}, None
    out = []
    for i, item in _items(data, "scene", "objects"):
        shape, params = item.get("shape"), item.get("params", {})
        if shape not in table or not isinstance(params, dict):
            continue  # reported by the schema
        base = ("scene", "objects", i, "params")
        allowed = table[shape]
        bad = False
        for key, value in params.items():
            if key not in allowed:
                out.append(Finding(
                    base + (key,),
                    f"unknown parameter {key!r} for shape {shape!r}; allowed: "
                    f"{', '.join(allowed) or '(none)'}",
                    key=True,
                ))
                bad = True
                continue
            problem = _value_error(value, allowed[key])
            if problem is None and key in LENGTH_PARAMS.get(shape, ()):
                vals = value if isinstance(value, list) else [value]
                if not all(isinstance(v, (int, float)) and 0 < v <= MAX_COORD for v in vals):
                    problem = f"is out of range ({value!r}); allowed lengths in (0, {MAX_COORD:g}] m"
            if problem:
                out.append(Finding(base + (key,), f"parameter {key!r} {problem}"))
                bad = True
        if shape == "mesh":
            mesh = params.get("path")
            if mesh is None:
                out.append(Finding(base, "a 'mesh' object needs the parameter 'path'"))
                continue
            if not isinstance(mesh, str):
                out.append(Finding(base + ("path",), f"'path' should be a string, got {mesh!r}"))
                continue
            problem = _mesh_file_problem(mesh, base_dir, extra_dirs)
            if problem:
                out.append(Finding(base + ("path",), problem))
                continue
        if bad or build_mesh is None:
            continue
        try:
            built = build_mesh(shape, params, base_dir=base_dir)
        except (ValueError, FileNotFoundError) as exc:
            out.append(Finding(base, f"object {item.get('name')!r} cannot be built: {exc}"))
            continue
        import numpy as np  # noqa: PLC0415

        v = np.asarray(built.vertices)
        if len(built.faces) == 0 or not np.isfinite(v).all():
            out.append(Finding(base, f"object {item.get('name')!r}: its mesh has no triangles or non-finite "
                                     "coordinates"))
        elif np.ptp(v, axis=0).max() > 2 * MAX_COORD:
            out.append(Finding(base, f"object {item.get('name')!r} is {np.ptp(v, axis=0).max():g} m across; "
                                     f"allowed at most {2 * MAX_COORD:g} m (a mesh in mm? set params.scale)"))
    return out


def _mesh_file_problem(mesh: str, base_dir: pathlib.Path, extra_dirs: Iterable[pathlib.Path]) -> str | None:
    path = (base_dir / mesh).resolve()
    roots = [base_dir.resolve(), *[pathlib.Path(d).resolve() for d in extra_dirs]]
    if not any(path == r or r in path.parents for r in roots):
        return (f"mesh file {mesh!r} lies outside the level's folder ({base_dir.resolve()}); mesh files must "
                "be in it or below it, or in a folder allowed with --allow-dir DIR (or SANDBOX_MESH_DIRS)")
    if path.exists() and not path.is_file():
        return f"mesh file {mesh!r} is not a file ({path} is a folder or a device); allowed: a mesh file"
    if not path.is_file():
        return (f"mesh file {mesh!r} not found (looked for {path}; paths are relative to the level file's "
                "folder)")
    size = path.stat().st_size
    if size == 0:
        return f"mesh file {mesh!r} is empty"
    if size > MESH_FILE_BYTES:
        return f"mesh file {mesh!r} is {size} bytes; allowed at most {MESH_FILE_BYTES}"
    return None


def check_resources(data: Any, limits) -> list[Finding]:
    """Particles, frames x substeps and estimated memory within ``limits`` (a ``limits.Limits``)."""
    from sandbox.levels.limits import BYTES_PER_PARTICLE, particle_count  # noqa: PLC0415
    from sandbox.levels.schema import Sim, default_max_substeps  # noqa: PLC0415

    out = []
    how = "raise it with --limit {0}=N (or SANDBOX_LIMITS='{0}=N')"
    n = particle_count(data)
    if n is not None and n > limits.particles:
        out.append(Finding(("scene",), f"the level asks for {n} particles; the limit is {limits.particles}: "
                                       f"use fewer (a longer rod_length, a coarser resolution) or "
                                       + how.format("particles")))
    if n is not None and n * BYTES_PER_PARTICLE > limits.memory_gb * 2**30:
        out.append(Finding(("scene",), f"the level's fields would take about {n * BYTES_PER_PARTICLE / 2**30:.1f} "
                                       f"GiB; the limit is {limits.memory_gb:g} GiB: " + how.format("memory_gb")))
    sim = data.get("sim") if isinstance(data, dict) else None
    sim = sim if isinstance(sim, dict) else {}
    try:
        fixed = int(sim.get("substeps", Sim.model_fields["substeps"].default))
        sub = max(fixed, int(sim.get("max_substeps") or default_max_substeps(fixed)))
        steps = int(sim.get("frames", 240)) * sub
    except (TypeError, ValueError, OverflowError):  # not whole numbers, or infinite: the schema reports them
        steps = None
    if steps is not None and steps > limits.steps:
        out.append(Finding(("sim",), f"frames x substeps is {steps}; the limit is {limits.steps}: "
                                     + how.format("steps")))
    return out


CLOTH_LINE_METRICS = ("knot", "knot_size", "knot_length", "knot_from_top")
"""Metrics whose ``of`` may name cloth lines (two lines of one cloth are joined through its centre)."""


def check_criteria(
    data: Any, states: Iterable[str], maneuvers: Iterable[str]
) -> list[Finding]:
    """Every name in a criterion's ``of`` must be a body, a state or a maneuver of the level; a cloth line
    (``F.line1``, ``F.P..Q``) only where the metric reads one (``CLOTH_LINE_METRICS``)."""
    from sandbox.model.strands import parse_cloth_line

    names = scene_names(data)
    states, maneuvers = sorted(states), sorted(maneuvers)
    known = {n for group in names.values() for n in group} | set(states) | set(maneuvers)
    listing = "; ".join(
        f"{label}: {', '.join(group)}"
        for label, group in (
            ("objects", names["object"]), ("cloths", names["cloth"]),
            ("ropes", names["rope"]), ("states", states), ("maneuvers", maneuvers),
        )
        if group
    )
    out = []
    for i, item in _items(data, "success"):
        of = item.get("of")
        if item.get("metric") == "knot_from_top":
            given = [of] if isinstance(of, str) else of if isinstance(of, list) else []
            objects = [t for t in given if t in names["object"]]
            if len(objects) != 1 or len(given) - 1 not in (1, 2):
                out.append(Finding(("success", i, "of"),
                                   f"knot_from_top needs one object and the knot's one or two strands, "
                                   f"of: [R, object] or [A, B, object] (got {of!r}); objects: "
                                   f"{', '.join(names['object']) or '(none)'}"))
        targets: list[tuple[tuple[Any, ...], Any]]
        if isinstance(of, str):
            targets = [(("success", i, "of"), of)]
        elif isinstance(of, list):
            targets = [(("success", i, "of", k), t) for k, t in enumerate(of)]
        else:
            continue
        for path, target in targets:
            try:
                line = parse_cloth_line(target) if isinstance(target, str) else None
            except ValueError as exc:
                out.append(Finding(path, str(exc)))
                continue
            if line is not None:  # a cloth line F.line1 / F.P..Q: its cloth must exist
                if item.get("metric") not in CLOTH_LINE_METRICS:
                    out.append(Finding(path, f"metric {item.get('metric')!r} does not read cloth lines "
                                             f"({target!r}); those that do: {', '.join(CLOTH_LINE_METRICS)}"))
                elif line[0] not in names["cloth"]:
                    out.append(Finding(path, f"cloth line {target!r}: unknown cloth {line[0]!r}; cloths: "
                                             f"{', '.join(names['cloth']) or '(none)'}"))
                continue
            if isinstance(target, str) and "[" in target:
                from sandbox.model.strands import parse_strand

                try:
                    base = parse_strand(target)[0]
                except ValueError as exc:
                    out.append(Finding(path, str(exc)))
                    continue
                if base not in names["rope"]:
                    out.append(Finding(path, f"strand {target!r}: unknown rope {base!r}; ropes: "
                                             f"{', '.join(names['rope']) or '(none)'}"))
                continue
            if isinstance(target, str) and target not in known:
                out.append(Finding(
                    path, f"unknown target {target!r}; allowed: {listing or '(none)'}"
                ))
    return out


def used_maneuvers(flat_states: Mapping[str, Any]) -> set[str]:
    """Maneuver names run by an expanded FSM's states."""
    return {s.maneuver for s in flat_states.values()}


_ROPE_KEYS = ("active", "target")  # maneuver parameters that name a rope, a strand of one or a cloth line
_BODY_KEYS = ("body",)  # ... a rope, a strand, a cloth line or a cloth


def check_references(data: Any, states: Mapping[str, Any]) -> list[Finding]:
    """Bodies, strands and objects named in maneuver parameters must exist in the scene.

    Walks each expanded state's parameters (after macro substitution): ``active``
    and ``target`` name ropes, strands ``R[i0:i1]`` or cloth lines (``F.line1``,
    ``F.P..Q``); ``body`` any of those or a cloth; ``knot`` a list of strands;
    ``object`` (inside a target) an object.
    """
    from sandbox.levels.limits import body_sizes  # noqa: PLC0415
    from sandbox.model.strands import parse_cloth_line, parse_strand, rope_site_span

    names = scene_names(data)
    ropes, cloths, objects = set(names["rope"]), set(names["cloth"]), set(names["object"])
    rope_n, cloth_n = body_sizes(data)
    out: list[Finding] = []

    def strand_size(value: str) -> int | None:
        """Particles of a rope or strand ``R[i0:i1]`` (None if unknown)."""
        base, lo, hi = parse_strand(value)
        if base not in rope_n:
            return None
        a, b, _ = slice(lo, hi).indices(rope_n[base])
        return max(b - a, 0)

    def site(owner: Any, value: Any, path: tuple, state: str) -> None:
        """A rope or cloth site of ``owner`` (a body name) within the body's particles."""
        if not isinstance(owner, str):
            return
        try:
            k = strand_size(owner)
        except ValueError:
            return  # reported as a bad body
        if k is not None:
            rope_site = isinstance(value, int) or (isinstance(value, list) and len(value) == 2
                                                   and all(isinstance(v, int) for v in value))
            if rope_site and not isinstance(value, bool):
                try:
                    rope_site_span(owner, k, value)  # the rule the world resolves sites by
                except ValueError as exc:
                    out.append(Finding(path, f"state {state!r}: {exc}; allowed: an index in [{-k}, {k - 1}], "
                                             f"[i0, i1] with 0 <= i0 < i1 <= {k}, 'start', 'end' or 'all'"))
        elif owner in cloth_n and isinstance(value, list) and len(value) == 2 \
                and all(isinstance(v, int) for v in value):
            nx, nz = cloth_n[owner]
            if not (0 <= value[0] < nx and 0 <= value[1] < nz):
                out.append(Finding(path, f"state {state!r}: cloth {owner!r} is {nx} x {nz} particles; allowed "
                                         f"grid indices [0, {nx - 1}] x [0, {nz - 1}], got {value}"))

    def allowed(kinds: tuple[str, ...]) -> str:
        return "; ".join(f"{k}s: {', '.join(names[k]) or '(none)'}" for k in kinds)

    def cloth_line(value: str, path: tuple, state: str) -> bool:
        """A cloth line ``F.line1`` / ``F.P..Q``: its cloth must exist and its points lie on the grid (True if it
        is one, reported or not)."""
        try:
            line = parse_cloth_line(value)
        except ValueError as exc:
            out.append(Finding(path, f"state {state!r}: {exc}"))
            return True
        if line is None:
            return False
        name, a, b = line
        if name not in cloths:
            out.append(Finding(path, f"state {state!r}: cloth line {value!r}: unknown cloth {name!r}; "
                                     f"{allowed(('cloth',))}"))
            return True
        nx, nz = cloth_n[name]
        for pt in (a, b):
            if isinstance(pt, list) and not (0 <= pt[0] < nx and 0 <= pt[1] < nz):
                out.append(Finding(path, f"state {state!r}: cloth line {value!r}: cloth {name!r} is {nx} x {nz} "
                                         f"particles; allowed grid points [0, {nx - 1}] x [0, {nz - 1}], got {pt}"))
        if a == b:
            out.append(Finding(path, f"state {state!r}: cloth line {value!r} runs from a point to itself"))
        return True

    def body(value: Any, path: tuple, state: str, kinds: tuple[str, ...]) -> None:
        if not isinstance(value, str) or cloth_line(value, path, state):
            return
        try:
            base = parse_strand(value)[0]
        except ValueError as exc:
            out.append(Finding(path, f"state {state!r}: {exc}"))
            return
        ok = base in ropes or ("cloth" in kinds and base == value and base in cloths)
        if not ok:
            out.append(Finding(path, f"state {state!r}: unknown {' or '.join(kinds)} {value!r}; {allowed(kinds)}"))
        elif base != value and (strand_size(value) or 0) < 2:
            out.append(Finding(path, f"state {state!r}: strand {value!r} has {strand_size(value)} particles of "
                                     f"the rope's {rope_n.get(base)}; a strand needs at least 2"))

    def walk(value: Any, path: tuple, state: str) -> None:
        if isinstance(value, dict):
            owner = value.get("body")
            if isinstance(value.get("sites"), list):
                for i, item in enumerate(value["sites"]):
                    site(owner, item, path + ("sites", i), state)
            if "site" in value:
                site(owner, value["site"], path + ("site",), state)
            for k, v in value.items():
                p = path + (k,)
                if k in _ROPE_KEYS:
                    body(v, p, state, ("rope",))
                elif k in _BODY_KEYS:
                    body(v, p, state, ("rope", "cloth"))
                elif k == "knot" and isinstance(v, list):
                    for i, item in enumerate(v):
                        body(item, p + (i,), state, ("rope",))
                elif k == "object" and isinstance(v, str) and v not in objects:
                    out.append(Finding(p, f"state {state!r}: unknown object {v!r}; {allowed(('object',))}"))
                else:
                    walk(v, p, state)
        elif isinstance(value, list):
            for i, item in enumerate(value):
                walk(item, path + (i,), state)

    for name, st in states.items():
        walk(st.params, tuple(st.path) + ("with",), name)
    return out
