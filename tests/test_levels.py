"""Level schema v1 and the strict loader: errors with lines, macros, round trip."""

from __future__ import annotations

import pathlib
import re

import pydantic
import pytest

from sandbox.levels import (
    Level,
    LevelError,
    LevelWarning,
    check_level,
    check_level_text,
    dump_level,
    load_level,
    load_level_from_string,
    parse_overrides,
)
from sandbox.levels.schema import FSMGraph, RopeSpec
from sandbox.maneuvers.base import REGISTRY, Maneuver, Params, Status, register

DATA = pathlib.Path(__file__).parent / "data" / "levels"


def _register(cls: type[Maneuver]) -> type[Maneuver]:
    return REGISTRY[cls.name] if cls.name in REGISTRY else register(cls)


class _WaitParams(Params):
    ticks: int = pydantic.Field(1, ge=1)


class _MoveParams(Params):
    target: tuple[float, float, float]
    speed: float = pydantic.Field(1.0, gt=0)


@_register
class _Wait(Maneuver):
    name = "lv_wait"
    Params = _WaitParams

    def update(self) -> Status:
        return Status.DONE


@_register
class _Move(Maneuver):
    name = "lv_move"
    Params = _MoveParams

    def update(self) -> Status:
        return Status.DONE


BASE = """\
version: 1
name: base
scene:
  ropes:
    - name: rope
      points: [[0, 1, 0], [1, 1, 0]]
      segments: 10
      radius: 0.01
macros:
  lift:
    params: [H]
    steps:
      - run: lv_move
        with: {target: [0, $H, 0]}
      - run: lv_wait
fsm:
  initial: start
  states:
    start:
      run: lv_wait
      with: {ticks: 2}
      on: {done: up}
    up:
      run: lift
      with: {H: 0.5}
"""


def line_of(text: str, needle: str) -> int:
    """1-based number of the first line of ``text`` that contains ``needle``."""
    for n, line in enumerate(text.splitlines(), start=1):
        if needle in line:
            return n
    raise AssertionError(f"{needle!r} not in text")


def errors_of(text: str, **kw) -> list:
    """The errors found in ``text`` (which must be invalid)."""
    with pytest.raises(LevelError) as info:
        load_level_from_string(text, **kw)
    return info.value.errors


def only_error(text: str, **kw):
    """The single error found in ``text``."""
    errs = errors_of(text, **kw)
    assert len(errs) == 1, "\n".join(map(str, errs))
    return errs[0]


def test_base_level_is_valid():
    """The base text used by the error tests loads without errors."""
    level = load_level_from_string(BASE)
    assert isinstance(level.fsm, FSMGraph)
    assert level.macros["lift"].params == ["H"]


def test_unknown_key_gives_line_and_allowed_keys():
    """An unknown key is reported at its own line, with the keys allowed there."""
    text = BASE.replace("      radius: 0.01\n", "      radius: 0.01\n      colour: red\n")
    err = only_error(text)
    assert err.line == line_of(text, "colour:")
    assert err.column == 7
    assert err.path == "scene.ropes[0].colour"
    assert "unknown key 'colour'" in err.message
    assert "rod_length" in err.message and "bend_compliance" in err.message


def test_wrong_type_gives_line():
    """A string where a number is expected is an error at that value's line and column."""
    text = BASE.replace("radius: 0.01", 'radius: "0.01"')
    err = only_error(text)
    assert (err.line, err.column) == (line_of(text, "radius:"), 15)
    assert err.path == "scene.ropes[0].radius"
    assert "valid number" in err.message and "'0.01'" in err.message


def test_boolean_is_not_a_number():
    """YAML booleans are rejected for numeric fields (strict types)."""
    text = BASE.replace("segments: 10", "segments: true")
    err = only_error(text)
    assert err.line == line_of(text, "segments:") and "integer" in err.message


def test_out_of_range_states_the_range():
    """An out-of-range value says which range is allowed."""
    text = BASE.replace("segments: 10", "segments: 5000")
    err = only_error(text)
    assert err.line == line_of(text, "segments:")
    assert "5000 is out of range; allowed [1, 4096]" in err.message


def test_chain_sweeps_range_and_round_trip():
    """``sim.chain_sweeps`` takes 1..16 and ``sim.chain_tolerance`` 0..1; both survive dump and load."""
    head = BASE.replace("macros:", "sim: {chain_sweeps: 0, chain_tolerance: 2.0}\nmacros:")
    errs = errors_of(head)
    messages = " | ".join(e.message for e in errs)
    assert "0 is out of range; allowed [1, 16]" in messages
    assert "2.0 is out of range; allowed [0, 1]" in messages
    level = load_level_from_string(BASE.replace("macros:", "sim: {chain_sweeps: 3, chain_tolerance: 0.002}\nmacros:"))
    assert (level.sim.chain_sweeps, level.sim.chain_tolerance) == (3, 0.002)
    assert load_level_from_string(dump_level(level)) == level


def test_chain_sweeps_default_to_three_with_an_inextensible_cloth_and_one_for_ropes():
    """Unset, the solver takes CLOTH_CHAIN_SWEEPS where an inextensible cloth is (rows and columns re-solved over
    an object's edges), one in a scene of ropes or of stretchy cloth; a level's own count is kept."""
    from sandbox.levels.schema import CLOTH_CHAIN_SWEEPS
    from sandbox.solvers.xpbd import SolverConfig

    def sweeps(text):
        level = load_level_from_string(text)
        return SolverConfig.of_level(level.scene, level.sim).chain_sweeps

    cloth = "  cloths:\n    - {name: c, resolution: [4, 3], size: [1, 1], center: [0, 1, 0]%s}\nmacros:"
    assert CLOTH_CHAIN_SWEEPS == 3
    assert sweeps(BASE) == 1
    assert sweeps(BASE.replace("macros:", cloth % "")) == 3
    assert sweeps(BASE.replace("macros:", cloth % ", stretch_compliance: 1.0e-4")) == 1
    own = (cloth % "").replace("\nmacros:", "\nsim: {chain_sweeps: 2}\nmacros:")
    assert sweeps(BASE.replace("macros:", own)) == 2


def test_cloth_joint_range_and_round_trip():
    """``sim.cloth_joint`` takes 0..64 CG iterations and ``sim.cloth_joint_every`` 1..200; both survive dump and load."""
    errs = errors_of(BASE.replace("macros:", "sim: {cloth_joint: 65, cloth_joint_every: 0}\nmacros:"))
    messages = " | ".join(e.message for e in errs)
    assert "65 is out of range; allowed [0, 64]" in messages
    assert "0 is out of range; allowed [1, 200]" in messages
    level = load_level_from_string(BASE.replace("macros:", "sim: {cloth_joint: 3, cloth_joint_every: 2}\nmacros:"))
    assert (level.sim.cloth_joint, level.sim.cloth_joint_every) == (3, 2)
    assert load_level_from_string(dump_level(level)) == level


def test_the_documented_example_level_is_valid():
    """The level that opens docs/levels.md loads, with every sim key it lists."""
    readme = (pathlib.Path(__file__).resolve().parents[1] / "docs" / "levels.md").read_text()
    text = re.search(r"```yaml\n(version: 1\n.*?)```", readme, re.S).group(1)
    level = load_level_from_string(text, base_dir=pathlib.Path(__file__).resolve().parents[1] / "levels")
    listed = set(re.findall(r"(\w+):", text[text.index("\nsim:"):text.index("\ninclude:")])) - {"sim"}
    assert listed == set(type(level.sim).model_fields), "the example lists every sim key, and only those"


def test_the_readme_example_level_is_valid():
    """The level in brief in the README loads."""
    readme = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    text = re.search(r"```yaml\n(version: 1\n.*?)```", readme, re.S).group(1)
    assert load_level_from_string(text).name == "rope_wind"


def test_adaptive_substeps_range_and_round_trip():
    """``sim.max_substeps`` takes substeps..200 (unset: 4 x substeps); a maximum below ``substeps`` says both;
    it survives dump and load. The travel per substep is the engine's, not an option."""
    errs = errors_of(BASE.replace("macros:", "sim: {max_substeps: 201, substep_travel: 0.3}\nmacros:"))
    messages = " | ".join(e.message for e in errs)
    assert "201 is out of range; allowed [1, 200]" in messages
    assert "substep_travel" in messages
    text = BASE.replace("macros:", "sim: {substeps: 12, max_substeps: 8}\nmacros:")
    err = only_error(text)
    assert err.path == "sim.max_substeps" and err.line == line_of(text, "sim:")
    assert "max_substeps (8) is below substeps (12)" in err.message and "12 to 200" in err.message
    err = only_error(BASE.replace("macros:", "sim: {max_substeps: 8}\nmacros:"))  # against the default substeps
    assert "max_substeps (8) is below substeps (10)" in err.message
    assert load_level_from_string(BASE).sim.max_substeps is None
    level = load_level_from_string(BASE.replace("macros:", "sim: {substeps: 8, max_substeps: 8}\nmacros:"))
    assert level.sim.max_substeps == 8
    assert load_level_from_string(dump_level(level)) == level


def test_unknown_maneuver_lists_registered_ones():
    """An unknown maneuver name is reported at its `run` line with the registered names."""
    text = BASE.replace("run: lv_wait\n      with: {ticks: 2}", "run: lv_jump\n      with: {ticks: 2}")
    err = only_error(text)
    assert err.line == line_of(text, "lv_jump")
    assert err.path == "fsm.states.start.run"
    assert "lv_wait" in err.message and "lv_move" in err.message and "lift" in err.message


def test_maneuver_params_are_validated_with_line():
    """A maneuver's parameters go through its Params model; errors point at the key."""
    text = BASE.replace("with: {ticks: 2}", "with: {ticks: 2, tick: 3}")
    err = only_error(text)
    assert (err.line, err.path) == (line_of(text, "tick: 3"), "fsm.states.start.with.tick")
    assert "allowed keys: ticks" in err.message
    text = BASE.replace("with: {ticks: 2}", "with: {ticks: 0}")
    err = only_error(text)
    assert err.path == "fsm.states.start.with.ticks" and "greater than or equal to 1" in err.message


def test_missing_mesh_file(tmp_path: pathlib.Path):
    """A mesh path is resolved from the level's folder; a missing file is an error at `path`."""
    obj = "  objects:\n    - {name: statue, shape: mesh, params: {path: meshes/cupid.obj}}\n"
    text = BASE.replace("scene:\n", "scene:\n" + obj)
    level_file = tmp_path / "level.yaml"
    level_file.write_text(text)
    with pytest.raises(LevelError) as info:
        load_level(level_file)
    (err,) = info.value.errors
    assert err.file == str(level_file)
    assert err.line == line_of(text, "cupid.obj") and err.path == "scene.objects[0].params.path"
    assert "not found" in err.message
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "cupid.obj").write_text("v 0 0 0\n")
    with pytest.raises(LevelError, match="holds no triangles"):  # the file is read at load
        load_level(level_file)
    (tmp_path / "meshes" / "cupid.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    assert load_level(level_file).scene.objects[0].params == {"path": "meshes/cupid.obj"}


def test_unknown_shape_parameter_lists_allowed():
    """A shape parameter the builder does not know is an error listing the allowed names."""
    obj = "  objects:\n    - {name: b, shape: sphere, params: {radius: 0.1, size: 2}}\n"
    text = BASE.replace("scene:\n", "scene:\n" + obj)
    err = only_error(text)
    assert err.path == "scene.objects[0].params.size" and "allowed: radius" in err.message


def test_bad_transition_target():
    """A transition to a state that does not exist lists the states allowed."""
    text = BASE.replace("on: {done: up}", "on: {done: upp}")
    err = only_error(text)
    assert (err.line, err.path) == (line_of(text, "upp"), "fsm.states.start.on.done")
    assert "allowed: start, up, success, failure" in err.message


def test_bad_event_name():
    """Only done, failed and timeout may label transitions."""
    text = BASE.replace("on: {done: up}", "on: {finished: up}")
    err = only_error(text)
    assert err.line == line_of(text, "finished") and "'done', 'failed' or 'timeout'" in err.message


def test_unknown_initial_state():
    """The initial state must be one of the states."""
    text = BASE.replace("initial: start", "initial: begin")
    err = only_error(text)
    assert err.line == line_of(text, "initial:") and "allowed: start, up" in err.message


def test_macro_with_missing_arg():
    """Calling a macro without one of its declared parameters is an error at the call site."""
    text = BASE.replace("with: {H: 0.5}", "with: {}")
    err = only_error(text)
    assert err.line == line_of(text, "with: {}")
    assert "needs argument(s) H" in err.message


def test_macro_with_unknown_arg():
    """An argument the macro does not declare is reported at that argument."""
    text = BASE.replace("with: {H: 0.5}", "with: {H: 0.5, W: 1}")
    err = only_error(text)
    assert err.path == "fsm.states.up.with.W" and "declared parameters: H" in err.message


def test_macro_params_validated_after_substitution():
    """A bad argument is reported at the call site, with the macro step's line."""
    text = BASE.replace("with: {H: 0.5}", "with: {H: high}")
    err = only_error(text)
    assert (err.line, err.path) == (line_of(text, "H: high"), "fsm.states.up.with.H")
    assert "lv_move" in err.message
    assert f"in macro 'lift' step 0 at line {line_of(text, '- run: lv_move')}" in err.message


def test_macro_step_error_points_at_macro_step():
    """A bad value written in a macro step is reported there, with the call site's line."""
    text = BASE.replace("with: {target: [0, $H, 0]}", "with: {target: [0, $H, 0], speed: -1}")
    err = only_error(text)
    assert err.line == line_of(text, "speed: -1")
    assert err.path == "macros.lift.steps[0].with.speed"
    assert f"called from fsm.states.up at line {line_of(text, '    up:')}" in err.message


def test_undeclared_macro_reference():
    """A `$X` in a macro for an undeclared parameter is an error in the macro."""
    text = BASE.replace("[0, $H, 0]", "[0, $Z, 0]")
    errs = errors_of(text)
    assert any(e.path == "macros.lift.steps[0].with.target[1]" and "'$Z'" in e.message
               for e in errs)


def test_macro_recursion_is_detected():
    """Macros that call each other in a cycle are reported, not expanded forever."""
    text = BASE.replace("      - run: lv_wait\nfsm:", "      - run: again\n  again:\n"
                        "    steps:\n      - {run: lift, with: {H: 1}}\nfsm:")
    errs = errors_of(text)
    assert any("macro recursion: lift -> again -> lift" in e.message for e in errs)


def test_rope_with_both_segments_and_rod_length():
    """A rope may give segments or rod_length, not both; the error is at rod_length."""
    text = BASE.replace("segments: 10\n", "segments: 10\n      rod_length: 0.1\n")
    err = only_error(text)
    assert err.line == line_of(text, "rod_length") and "not both" in err.message


def test_rope_with_neither_segments_nor_rod_length():
    """A rope without segments and rod_length is an error at the rope."""
    text = BASE.replace("      segments: 10\n", "")
    err = only_error(text)
    assert err.line == line_of(text, "- name: rope") and "give one of" in err.message


def test_rope_segment_count_from_rod_length():
    """rod_length resolves into a whole number of rods along the polyline."""
    rope = RopeSpec(name="r", points=[(0, 0, 0), (1, 0, 0), (1, 1, 0)], rod_length=0.1,
                    radius=0.01)
    assert rope.segment_count == 20


def test_duplicate_names_across_kinds():
    """A rope and a cloth may not share a name."""
    cloth = "  cloths:\n    - {name: rope, resolution: [4, 4], size: [1, 1], center: [0, 1, 0]}\n"
    text = BASE.replace("scene:\n", "scene:\n" + cloth)
    err = only_error(text)
    assert err.path == "scene.ropes[0].name" and "already used by cloth 0" in err.message


def test_cloth_pin_outside_grid():
    """A cloth pin index beyond the resolution is an error naming the allowed range."""
    cloth = ("  cloths:\n    - {name: c, resolution: [4, 3], size: [1, 1], center: [0, 1, 0], "
             "pins: [A, [3, 3]]}\n")
    err = only_error(BASE.replace("scene:\n", "scene:\n" + cloth))
    assert "i in [0, 3], j in [0, 2]" in err.message


def test_keyframe_times_must_increase():
    """Kinematic keyframes must be in strictly increasing time order."""
    obj = ("  objects:\n    - name: b\n      shape: sphere\n      motion:\n        keyframes:\n"
           "          - {time: 1, position: [0, 0, 0]}\n          - {time: 1, position: [1, 0, 0]}\n")
    err = only_error(BASE.replace("scene:\n", "scene:\n" + obj))
    assert err.path == "scene.objects[0].motion.keyframes" and "increase strictly" in err.message


def test_bad_criterion_target_and_metric():
    """Criteria must name a known metric and existing targets."""
    text = BASE + "success:\n  - {metric: knot_typ, equals: trefoil}\n  - {metric: max_strain, of: [rope, sheet], max: 0.5}\n"
    errs = errors_of(text)
    assert [(e.path, e.line) for e in errs] == [
        ("success[0].metric", line_of(text, "knot_typ")),
        ("success[1].of[1]", line_of(text, "sheet")),
    ]
    assert "allowed:" in errs[0].message and "max_strain" in errs[0].message
    assert "ropes: rope" in errs[1].message


def test_criterion_may_name_states():
    """A criterion may apply to an FSM state, including an expanded macro state."""
    text = BASE + "success:\n  - {metric: fsm_state, of: [up, up/0:lv_move], equals: success}\n"
    assert load_level_from_string(text).success[0].targets() == ["up", "up/0:lv_move"]


def test_criterion_needs_a_bound():
    """A criterion without min, max or equals is an error."""
    err = only_error(BASE + "success:\n  - {metric: max_strain}\n")
    assert "at least one of" in err.message


def test_several_errors_reported_at_once():
    """Every problem of a file is reported together, each at its tagged line, in file order."""
    path = DATA / "many_errors.yaml"
    text = path.read_text()
    with pytest.raises(LevelError) as info:
        load_level(path)
    errs = info.value.errors
    expected = {tag: line_of(text, f"E:{tag}") for tag in re.findall(r"E:(\w+)", text)}
    assert len(expected) == 7
    assert sorted(e.line for e in errs) == sorted(expected.values())
    assert [e.line for e in errs] == sorted(e.line for e in errs)
    lines = str(info.value).splitlines()
    assert len(lines) == len(errs)
    for line, err in zip(lines, errs):
        assert line.startswith(f"{path}:{err.line}:{err.column}: {err.path}: ")


def test_yaml_syntax_error_has_a_line():
    """A YAML syntax error is reported as one issue with its position."""
    text = BASE.replace("fsm:\n", "fsm: [\n")
    err = only_error(text)
    assert err.line > 0 and "YAML syntax" in err.message


def test_duplicate_yaml_key():
    """A key written twice in a mapping is an error (YAML would keep the last silently)."""
    text = BASE.replace("      radius: 0.01\n", "      radius: 0.01\n      radius: 0.02\n")
    err = only_error(text)
    assert err.line == line_of(text, "radius: 0.02") and "duplicate key" in err.message


def test_yaml_core_scalars():
    """`on` is a string key, 1e-6 is a float and `ground: false` means no ground."""
    text = BASE.replace("scene:\n", "scene:\n  ground: false\n").replace(
        "radius: 0.01", "radius: 1e-2\n      bend_compliance: 1e-6")
    level = load_level_from_string(text)
    assert level.scene.ground is None
    assert level.scene.ropes[0].radius == 0.01 and level.scene.ropes[0].bend_compliance == 1e-6
    assert level.fsm.states["start"].on == {"done": "up"}


def test_unreachable_state_is_a_warning():
    """An unreachable state does not stop loading but is reported as a warning."""
    text = BASE + "    orphan:\n      run: lv_wait\n"
    with pytest.warns(LevelWarning, match="'orphan' cannot be reached"):
        load_level_from_string(text)
    result = check_level_text(text)
    assert result.errors == [] and result.warnings[0].line == line_of(text, "orphan:")


def test_overrides_are_applied_before_validation():
    """Dotted overrides set values before validation, and bad ones are reported."""
    level = load_level_from_string(BASE, overrides={"sim.frames": 10, "sim.arch": "cpu",
                                                    "scene.ropes.0.radius": 0.02})
    assert (level.sim.frames, level.sim.arch, level.scene.ropes[0].radius) == (10, "cpu", 0.02)
    err = only_error(BASE, overrides={"sim.fps": 0})
    assert err.path == "sim.fps" and "override 'sim.fps'" in err.message
    assert parse_overrides(["sim.frames=10", "scene.gravity=[0, 0, 0]"]) == {
        "sim.frames": 10, "scene.gravity": [0, 0, 0]}


def test_full_level_loads_and_round_trips():
    """A level using every section loads, and dump -> load gives an equal level."""
    level = load_level(DATA / "full.yaml")
    assert level.scene.cloths[0].pins == ["A", "center", (31, 0)]
    assert level.scene.objects[1].motion.loop is True
    assert level.scene.ropes[0].pins == ["start", -1]
    text = dump_level(level)
    again = load_level_from_string(text, base_dir=DATA)
    assert again == level
    assert isinstance(again.fsm, FSMGraph)
    assert load_level_from_string(dump_level(level, defaults=True)) == level


def test_chain_round_trips_as_a_chain():
    """A chain FSM is dumped back as a list, not as a graph."""
    text = BASE.replace(BASE[BASE.index("fsm:"):], "fsm:\n  - {run: lv_wait}\n  - {run: lift, with: {H: 1}}\n")
    level = load_level_from_string(text)
    assert isinstance(level.fsm, list)
    again = load_level_from_string(dump_level(level))
    assert again == level and isinstance(again.fsm, list)


def test_string_that_looks_like_a_number_round_trips():
    """Strings such as 'on', 'yes' or '1e-6' stay strings through dump and load."""
    level = Level.model_validate({
        "version": 1, "name": "1e-6", "description": "on", "scene": {},
        "fsm": [{"run": "lv_wait", "name": "yes"}],
    })
    text = dump_level(level)
    assert load_level_from_string(text) == level


def test_check_level_reports_unreadable_file(tmp_path: pathlib.Path):
    """A missing level file is one issue, not an exception."""
    result = check_level(tmp_path / "missing.yaml")
    assert result.level is None and "cannot read" in result.errors[0].message


def test_macros_are_checked_when_the_fsm_is_invalid():
    """Problems in macros are reported along with a broken FSM."""
    text = BASE.replace("      - run: lv_wait\nfsm:", "      - run: lv_nope\nfsm:").replace(
        "initial: start", "initial: [start]")
    paths = [e.path for e in errors_of(text)]
    assert paths == ["macros.lift.steps[1].run", "fsm.initial"]


def test_camera_follow_names_ropes_and_round_trips():
    """A camera may follow ropes of the scene or strands of them (and dumps back); other names are errors
    that list the ropes and the cloth lines (a cloth line of a cloth the scene lacks is one)."""
    cam = "  camera: {position: [0, 1, 1], look_at: [0, 1, 0], follow: [%s], distance: 0.3, smoothing: 0.2}\n"
    good = BASE.replace("scene:\n", "scene:\n" + cam % "rope", 1)
    level = load_level_from_string(good)
    assert level.scene.camera.follow == ["rope"] and level.scene.camera.distance == 0.3
    assert load_level_from_string(dump_level(level)) == level
    bad = BASE.replace("scene:\n", "scene:\n" + cam % "rope, cord", 1)
    err = only_error(bad)
    assert err.path == "scene.camera.follow[1]" and err.line == line_of(bad, "cord")
    assert "'cord' is neither" in err.message and "ropes: rope" in err.message
    strand = BASE.replace("scene:\n", "scene:\n" + cam % '"rope[0:10]", "rope[10:]"', 1)
    assert load_level_from_string(strand).scene.camera.follow == ["rope[0:10]", "rope[10:]"]
    line = only_error(BASE.replace("scene:\n", "scene:\n" + cam % "F.line1", 1))
    assert "'F.line1' is neither" in line.message and "of (no cloth)" in line.message
    neg = BASE.replace("scene:\n", "scene:\n" + (cam % "rope").replace("0.3", "-0.3"), 1)
    assert only_error(neg).path == "scene.camera.distance"
