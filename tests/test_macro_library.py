"""Macro libraries: ``include:`` files of macros, checked with file:line like levels."""

import pathlib

import pytest

import sandbox.maneuvers  # noqa: F401  (registers the maneuvers)
from sandbox.levels import LevelError, check_level, dump_level, expand, load_level, load_level_from_string
from sandbox.maneuvers.base import REGISTRY

ROOT = pathlib.Path(__file__).resolve().parents[1]

LEVEL = """version: 1
name: lib_user
scene:
  ropes:
    - {name: R, points: [[0, 0.5, 0], [0.3, 0.5, 0]], segments: 10, radius: 0.01, pins: [start]}
include: [lib/moves.yaml]
fsm:
  - {run: Rest, with: {S: 0.25}}
"""

LIBRARY = """version: 1
description: a test library
macros:
  Rest:
    params: [S]
    steps:
      - {run: Wait, with: {seconds: $S}}
      - {run: Twice, with: {S: $S}}
  Twice:
    params: [S]
    steps:
      - {run: Wait, with: {seconds: $S}}
      - {run: Wait, with: {seconds: $S}}
"""


def _write(tmp_path, level=LEVEL, library=LIBRARY, name="level.yaml"):
    (tmp_path / "lib").mkdir(exist_ok=True)
    (tmp_path / "lib" / "moves.yaml").write_text(library)
    path = tmp_path / name
    path.write_text(level)
    return path


def _errors(path, **kw):
    result = check_level(path, **kw)
    assert result.level is None
    return [str(e) for e in result.errors]


def test_included_macros_run_as_if_written_in_the_level(tmp_path):
    level = load_level(_write(tmp_path))
    assert set(level.macros) == {"Rest", "Twice"} and level.include == []
    flat, findings = expand(level.fsm, level.macros, REGISTRY)
    assert not findings
    assert [s.params["seconds"] for s in flat.states.values()] == [0.25] * 3
    assert list(flat.states)[-1] == "0:Rest/1:Twice/1:Wait"
    # A dump holds the macros themselves and loads back equal, with no file beside it.
    again = load_level_from_string(dump_level(level), base_dir=tmp_path / "elsewhere")
    assert again == level


def test_an_error_in_a_library_is_reported_at_its_file_and_line_with_the_call(tmp_path):
    path = _write(tmp_path, library=LIBRARY.replace("{seconds: $S}}\n      - {run: Twice",
                                                    "{seconds: $S, minutes: 1}}\n      - {run: Twice"))
    errors = _errors(path)
    assert len(errors) == 1, errors
    lib = str(tmp_path / "lib" / "moves.yaml")
    assert errors[0].startswith(f"{lib}:7:"), errors
    assert "minutes" in errors[0] and f"called from fsm[0] at {path} line 8" in errors[0], errors


def test_a_library_schema_error_points_into_the_library(tmp_path):
    errors = _errors(_write(tmp_path, library=LIBRARY.replace("params: [S]\n    steps:\n      - {run: Wait, with: {seconds: $S}}\n      - {run: Wait",
                                                              "params: [S, S]\n    steps:\n      - {run: Wait, with: {seconds: $S}}\n      - {run: Wait")))
    assert any(e.startswith(str(tmp_path / "lib" / "moves.yaml") + ":10:") and "declared twice" in e for e in errors), errors


@pytest.mark.parametrize(("level", "library", "where", "says"), [
    (LEVEL.replace("lib/moves.yaml", "lib/none.yaml"), LIBRARY, "level.yaml:6:", "not found"),
    (LEVEL.replace("lib/moves.yaml", "../outside.yaml"), LIBRARY, "level.yaml:6:", "outside the level's folder"),
    (LEVEL.replace("include: [lib/moves.yaml]", "include: 3"), LIBRARY, "level.yaml:6:", "a file name or a list"),
    (LEVEL, LIBRARY.replace("version: 1\n", "version: 1\ninclude: [moves.yaml]\n"), "moves.yaml:2:", "includes itself"),
    (LEVEL.replace("lib/moves.yaml", "level.yaml"), LIBRARY, "level.yaml:6:", "includes itself"),
    (LEVEL, "- just a list\n", "moves.yaml:1:", "must be a mapping with macros"),
    (LEVEL, LIBRARY.replace("description:", "scene: {}\ndescription:"), "moves.yaml:2:", "unknown key 'scene'"),
    (LEVEL, LIBRARY.replace("version: 1", "version: 2"), "moves.yaml:1:", "version 2 is not supported"),
    (LEVEL, LIBRARY + "  : [\n", "moves.yaml:", "expected"),
    (LEVEL + "macros:\n  Rest: {steps: [{run: Wait, with: {seconds: 1}}]}\n", LIBRARY, "moves.yaml:4:",
     "macro 'Rest' is defined twice: here and in the level"),
])
def test_a_bad_include_is_refused_with_its_place(tmp_path, level, library, where, says):
    (tmp_path / "outside.yaml").write_text(LIBRARY)
    errors = _errors(_write(tmp_path, level, library))
    assert any(where in e and says in e for e in errors), errors


def test_a_library_outside_the_folder_loads_when_its_folder_is_allowed(tmp_path):
    other = tmp_path / "shared"
    other.mkdir()
    (other / "moves.yaml").write_text(LIBRARY)
    (tmp_path / "game").mkdir()
    path = _write(tmp_path / "game", LEVEL.replace("lib/moves.yaml", "../shared/moves.yaml"))
    assert _errors(path)
    result = check_level(path, mesh_dirs=[other])
    assert not result.errors and result.libraries == [(other / "moves.yaml").resolve()]


def test_an_override_reaches_into_an_included_macro(tmp_path):
    level = load_level(_write(tmp_path), {"macros.Twice.steps.1.with.seconds": 2.0})
    assert level.macros["Twice"].steps[1].with_["seconds"] == 2.0
    with pytest.raises(LevelError, match="moves.yaml:13:"):
        load_level(_write(tmp_path), {"macros.Twice.steps.1.with.seconds": -1.0})


def test_the_granny_and_the_square_share_one_definition():
    """Both levels include the knot library; their maneuvers differ only in the second half's crossing
    sign and winding hand (the square is the granny mirrored), and neither level writes a step of its own."""
    def flat(name):
        level = load_level(ROOT / "levels" / f"{name}.yaml")
        assert level.macros["GrannyKnot"] == load_level(ROOT / "levels" / "self_knot.yaml").macros["GrannyKnot"]
        states, _ = expand(level.fsm, level.macros, REGISTRY)
        return [(s.maneuver, s.params) for s in states.states.values()]

    granny, square = flat("granny_knot"), flat("square_knot")
    differ = [(g[0], {k: (v, s[1][k]) for k, v in g[1].items() if s[1].get(k) != v})
              for g, s in zip(granny, square) if g != s]
    assert len(granny) == len(square) == 14
    assert differ == [("Crossing", {"sign": (1, -1)}), ("Winding", {"handedness": (-1, 1)})]
    for name in ("granny_knot", "square_knot", "self_knot"):
        text = (ROOT / "levels" / f"{name}.yaml").read_text()
        assert "macros/knots.yaml" in text and "\nmacros:" not in text


def test_include_cannot_be_overridden(tmp_path):
    with pytest.raises(LevelError, match="'include' cannot be overridden"):
        load_level(_write(tmp_path), {"include": ["lib/other.yaml"]})
