"""Sweeps: axes and sweep files, the standard set, placements, the table, reports, and whole sweeps."""

import json
import math
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from sandbox.model.pose import euler_matrix, keyframe_pose
from sandbox.sweep import SweepError, grid_variants, parse_sweep, sample_variants, standard_variants, wilson
from sandbox.sweep import placement, plan, report, table

ROOT = pathlib.Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "levels" / "sweep_tiny.yaml"


def _level(name: str) -> dict:
    return yaml.safe_load((ROOT / "levels" / f"{name}.yaml").read_text())


# ----------------------------------------------------------------------------- axes and sweep files


def test_grid_is_the_product_in_order():
    """A grid runs every combination of the axes' values, the first axis slowest, the same every time."""
    axes = parse_sweep("version: 1\naxes:\n  sim.substeps: [10, 20]\n  compile: [full, fast]\n"
                       "  place.scene.turn: {range: [-10, 10], steps: 3}\n")
    got = grid_variants(axes)
    assert len(got) == 12
    assert got[0] == {"sim.substeps": 10, "compile": "full", "place.scene.turn": -10.0}
    assert got[1]["place.scene.turn"] == 0.0 and got[3]["compile"] == "fast" and got[6]["sim.substeps"] == 20
    assert grid_variants(axes) == got


def test_samples_are_seeded_and_within_ranges():
    """--samples draws the same points for the same seed, other points for another, inside each range."""
    axes = parse_sweep("version: 1\naxes:\n  sim.iterations: {range: [1, 4]}\n"
                       "  place.scene.turn: {range: [-5.0, 5.0]}\n  compile: [full, fast]\n")
    a, b, c = sample_variants(axes, 40, 7), sample_variants(axes, 40, 7), sample_variants(axes, 40, 8)
    assert a == b and a != c
    assert all(isinstance(v["sim.iterations"], int) and 1 <= v["sim.iterations"] <= 4 for v in a)
    assert {v["sim.iterations"] for v in a} == {1, 2, 3, 4}
    assert all(-5.0 <= v["place.scene.turn"] <= 5.0 for v in a)
    assert {v["compile"] for v in a} == {"full", "fast"}


def test_bad_sweep_file_lists_every_problem_with_its_line():
    """Unknown keys and axes, bad values and ranges are all reported at once, each with its line."""
    text = ("version: 2\n"
            "axis: 1\n"
            "axes:\n"
            "  compile: [full, quick]\n"
            "  place.scene.shift: [[0, 0]]\n"
            "  wobble: [1]\n"
            "  sim.substeps: {range: [30, 10]}\n"
            "  swap.box: [teapot]\n"
            "  sim.iterations: [{add: x}]\n")
    with pytest.raises(SweepError) as err:
        parse_sweep(text, source="bad.yaml")
    lines = {i.line: i.message for i in err.value.issues}
    assert set(lines) == {1, 2, 4, 5, 6, 7, 8, 9}
    assert "allowed: full, fast" in lines[4]
    assert "[dx, dy, dz]" in lines[5]
    assert "unknown axis 'wobble'" in lines[6] and "place.TARGET.shift" in lines[6]
    assert "lo <= hi" in lines[7]
    assert "sphere" in lines[8]
    assert "{add: x}" in lines[9]
    assert str(err.value).startswith("bad.yaml:1:")


def test_standard_set_has_six_placements_by_four_settings_and_swaps_for_wraps():
    """--standard: 24 runs per level; a level that wraps an object in cloth adds one swap per other shape."""
    knot = standard_variants(_level("self_knot"))
    assert len(knot) == 24 and len({json.dumps(v, sort_keys=True) for _, v in knot}) == 24
    assert sum(1 for _, v in knot if v.get("place.scene.nudge") == plan.NUDGE) == 6
    assert sum(1 for _, v in knot if "place.scene.turn" in v) == 4
    wrap = standard_variants(_level("wrap_box_two"))
    swaps = [v["swap.box"] for _, v in wrap if "swap.box" in v]
    assert len(wrap) == 24 + len(swaps) and "box" not in swaps and set(swaps) == set(placement.SWAP_SHAPES) - {"box"}


def test_nudge_adds_to_the_shift_and_is_bounded():
    """place.TARGET.nudge moves the target by that much along each axis on top of its shift; a nudge of more
    than a millimetre is refused as a placement in disguise."""
    base, shifted, both = plan.resolve(ROOT / "levels" / "rope_wind.yaml", [
        ("", {}), ("", {"place.scene.shift": [0.02, 0.0, 0.0]}),
        ("", {"place.scene.shift": [0.02, 0.0, 0.0], "place.scene.nudge": 1e-6})])
    assert base.overrides == {} and set(both.overrides) == set(shifted.overrides)
    moved = [np.subtract(both.overrides[k], shifted.overrides[k]) for k in shifted.overrides]
    assert moved and all(np.allclose(d, 1e-6, rtol=0, atol=1e-12) for d in moved)
    assert parse_sweep("version: 1\naxes:\n  place.scene.nudge: {range: [-1e-6, 1e-6], steps: 3}\n")[0].grid() \
        == [-1e-6, 0.0, 1e-6]
    with pytest.raises(SweepError) as err:
        parse_sweep("version: 1\naxes:\n  place.box.nudge: [0.01]\n")
    assert "at most 0.001" in str(err.value)


def test_resolve_makes_relative_values_and_checks_each_variant():
    """Relative values are resolved against the level; a missing body or a bad value stops the sweep."""
    runs = plan.resolve(ROOT / "levels" / "drape_box.yaml",
                        [("", {"sim.substeps": {"scale": 1.25}}), ("", {"sim.iterations": {"add": 1}})])
    assert runs[0].overrides == {"sim.substeps": 13} and runs[1].overrides == {"sim.iterations": 2}
    wind = plan.resolve(ROOT / "levels" / "rope_wind.yaml", [("", {"fsm.1.with.w0": {"scale": 1.25}})])
    assert wind[0].overrides == {"fsm.1.with.w0": 1.25}  # not a whole number by the schema: kept as it comes
    again = plan.resolve(ROOT / "levels" / "rope_wind.yaml", [("", {"fsm.1.with.w0": {"scale": 1.25}})], frames=20)
    assert again[0].id != wind[0].id  # a run of other frames is another run
    with pytest.raises(SweepError) as err:
        plan.resolve(TINY, [("a", {"place.ghost.shift": [0, 0, 0]}), ("b", {"swap.cord": "sphere"}),
                            ("c", {"sim.substeps": 0})])
    text = str(err.value)
    assert "place.ghost: not a body of the level; allowed: scene, post, cord" in text
    assert "'cord' is not an object of the level; objects: post" in text
    assert "sim.substeps" in text and "[c]" in text


# ----------------------------------------------------------------------------- placements


def test_scene_shift_and_turn_move_every_body_rigidly():
    """A scene placement moves rope points, object poses and the camera by one rigid motion."""
    data = _level("rope_wind_moving")
    ov = placement.placement_overrides(data, "scene", (0.02, 0.03, -0.05), 10.0)
    q = euler_matrix([0, 10, 0])
    before = np.array(data["scene"]["ropes"][1]["points"], float)
    after = np.array(ov["scene.ropes.1.points"], float)
    d0 = np.linalg.norm(before[:, None] - before[None], axis=2)
    d1 = np.linalg.norm(after[:, None] - after[None], axis=2)
    np.testing.assert_allclose(d1, d0, atol=1e-12)
    c = placement.pivot(data, list(placement.bodies(data)))
    np.testing.assert_allclose(after, (before - c) @ q.T + c + [0.02, 0.03, -0.05], atol=1e-12)
    spin = {"time": 0.0, "position": [0, 0, 0], "rotation": [0, 360, 0]}
    assert placement._turned(spin["rotation"], 10.0) == [0.0, 370.0, 0.0]  # a spin stays a spin
    block = data["scene"]["objects"][2]
    np.testing.assert_allclose(euler_matrix(ov["scene.objects.2.rotation"]),
                               q @ euler_matrix(block.get("rotation", [0, 0, 0])), atol=1e-12)
    np.testing.assert_allclose(ov["scene.camera.look_at"],
                               q @ (np.array(data["scene"]["camera"]["look_at"]) - c) + c + [0.02, 0.03, -0.05])


def test_pinned_rope_motion_follows_a_turned_scene():
    """A pin carried by a script in a turned scene is, at every time, the turned pin of the level as shipped."""
    data = _level("rope_wind_moving")
    data["scene"]["ropes"][0]["motion"]["keyframes"][1]["rotation"] = [5.0, 20.0, -3.0]
    shift, turn = np.array([0.01, -0.02, 0.04]), 25.0
    ov = placement.placement_overrides(data, "scene", shift, turn)
    moved = json.loads(json.dumps(data))
    for k, v in ov.items():
        node, parts = moved, k.split(".")
        for p in parts[:-1]:
            node = node[int(p)] if isinstance(node, list) else node[p]
        node[parts[-1]] = v

    class Key:
        def __init__(self, d):
            self.time, self.position, self.rotation = d["time"], d["position"], d.get("rotation", [0, 0, 0])

    class Motion:
        def __init__(self, d):
            self.keyframes, self.loop = [Key(k) for k in d["keyframes"]], d.get("loop", False)

    c = placement.pivot(data, list(placement.bodies(data)))
    q = euler_matrix([0, turn, 0])
    x0 = np.array(data["scene"]["ropes"][0]["points"][0], float)
    x0m = np.array(moved["scene"]["ropes"][0]["points"][0], float)
    for t in (0.0, 0.4, 0.75, 1.1):
        p, r = keyframe_pose(Motion(data["scene"]["ropes"][0]["motion"]), t)
        pm, rm = keyframe_pose(Motion(moved["scene"]["ropes"][0]["motion"]), t)
        if t in (0.0, 0.75):  # at keyframes the pose is exact (between them Euler angles interpolate)
            np.testing.assert_allclose(rm @ x0m + pm, q @ (r @ x0 + p - c) + c + shift, atol=1e-9)


def test_cloth_yaw_turns_the_grid_about_its_centre():
    """A cloth's yaw turns its particles about the vertical through its centre; corner A turns with it."""
    from sandbox.levels import load_level_from_string
    from sandbox.model.builder import ModelBuilder

    text = (TINY.read_text().replace("  ropes:", "  cloths:\n    - {name: sheet, resolution: [5, 4], size: [0.4, 0.3], "
                                                 "center: [0.1, 0.6, -0.2], yaw: 30}\n  ropes:"))
    level = load_level_from_string(text, base_dir=TINY.parent)
    b = ModelBuilder()
    cloth = b.add_cloth(level.scene.cloths[0])
    x = np.concatenate(b._x)
    a = x[cloth.site("A") - cloth.start]
    expect = euler_matrix([0, 30, 0]) @ np.array([-0.2, 0.0, -0.15]) + [0.1, 0.6, -0.2]
    np.testing.assert_allclose(a, expect, atol=1e-12)
    np.testing.assert_allclose(x.mean(axis=0), [0.1, 0.6, -0.2], atol=1e-12)


def test_swap_keeps_the_bounding_box_volume():
    """A swapped object is scaled so that its bounds have the volume of the old object's bounds."""
    data = _level("wrap_box_two")
    for shape in ("sphere", "wine_bottle", "statue", "basket"):
        ov = placement.swap_overrides(data, "box", shape, ROOT / "levels")
        new = placement.object_extent({"shape": ov["scene.objects.0.shape"], "params": ov["scene.objects.0.params"]},
                                      ROOT / "levels")
        assert math.isclose(np.prod(new), 0.5 * 0.4 * 0.5, rel_tol=1e-6), shape


# ----------------------------------------------------------------------------- table and report


def test_wilson_interval_closed_forms():
    """Wilson's interval: k = 0 and k = n have closed-form ends; 5 of 10 is symmetric about 1/2."""
    z = report.Z95
    lo, hi = wilson(0, 10)
    assert lo == 0.0 and math.isclose(hi, z * z / (10 + z * z), rel_tol=1e-12)
    lo, hi = wilson(10, 10)
    assert hi == 1.0 and math.isclose(lo, 10 / (10 + z * z), rel_tol=1e-12)
    lo, hi = wilson(5, 10)
    assert math.isclose(lo + hi, 1.0, rel_tol=1e-12) and math.isclose(lo, 0.236593090, rel_tol=1e-6)
    assert wilson(0, 0) == (0.0, 1.0)


def test_reports_count_outcomes_of_the_level_as_it_is():
    """Rows of an older level file, interrupted runs and lost workers are set aside, not counted as failures."""
    header = table.columns([], ["x <= 1"])
    rows = [{"run": "1", "level_sha": "old", "status": "completed", "success": True},
            {"run": "2", "level_sha": "new", "status": "interrupted", "success": False},
            {"run": "3", "level_sha": "new", "status": "lost", "success": False},
            {"run": "4", "level_sha": "new", "status": "completed", "success": True, "ok:x <= 1": True},
            {"run": "5", "level_sha": "new", "status": "completed", "success": False, "ok:x <= 1": False}]
    rep = report.level_report(header, rows)
    assert rep["runs"] == 2 and rep["passed"] == 1
    assert rep["set_aside"] == {"older level": 1, "interrupted": 1, "lost": 1}
    assert rep["most_failed"] == "x <= 1" and rep["most_failed_count"] == 1


def test_margins_are_fractions_of_the_bar():
    """A criterion's margin is its distance to the bar over the bar, negative when it fails."""
    assert math.isclose(report.margin("max_strain(R) <= 0.01", 0.0075), 0.25)
    assert math.isclose(report.margin("coverage(c,b) >= 0.2", 0.1), -0.5)
    assert math.isclose(report.margin("winding_number(C,T) in [0.85, 1.15]", 1.0), 0.15 / 1.15)
    assert report.margin("knot(R) = square", "square") is None
    assert report.margin("max_strain(R) <= 0.01", None) is None


def test_table_keeps_whole_rows_and_the_latest_of_a_run(tmp_path):
    """A row cut short by a kill is skipped; appending goes on on a new line; a later row of a run wins."""
    header = table.columns(["compile"], ["x <= 1"])
    t = table.Table(tmp_path / "runs.csv", header)
    t.append({"run": "a", "status": "interrupted", "compile": "fast", "value:x <= 1": 0.5})
    t.append({"run": "b", "status": "completed", "success": True, "value:x <= 1": [1, 2]})
    t.close()
    with open(tmp_path / "runs.csv", "a") as f:
        f.write('c,lev,sha,"half a row, its quote open')
    t = table.Table(tmp_path / "runs.csv", header)
    t.append({"run": "a", "status": "completed", "success": False, "value:x <= 1": 2.0})
    t.append({"run": "1234567890e12345", "status": "error", "error": "two lines,\nand a comma"})
    t.close()
    _, rows = table.read(tmp_path / "runs.csv")
    got = {r["run"]: r for r in rows}
    assert set(got) == {"a", "b", "1234567890e12345"}  # an id that looks like a number stays text
    assert got["1234567890e12345"]["error"] == "two lines,\nand a comma"
    assert got["a"]["status"] == "completed" and got["a"]["value:x <= 1"] == 2.0
    assert got["b"]["value:x <= 1"] == [1, 2] and got["b"]["success"] is True
    with pytest.raises(ValueError, match="another sweep"):
        table.Table(tmp_path / "runs.csv", table.columns([], ["x <= 1"]))


# ----------------------------------------------------------------------------- whole sweeps


def _sweep(*args, timeout=600, **kw):
    extra = [] if "--report" in args else ["--threads", "1"]
    return subprocess.run([sys.executable, "-m", "sandbox.cli", "sweep", *map(str, args), *extra, "--quiet"],
                          cwd=ROOT, capture_output=True, text=True, timeout=timeout, **kw)


def _grid(tmp_path, text: str) -> pathlib.Path:
    path = tmp_path / "grid.yaml"
    path.write_text("version: 1\naxes:\n" + text)
    return path


def test_sweep_killed_half_way_resumes_without_repeating_or_losing_a_run(tmp_path):
    """A sweep killed (SIGKILL) after its first rows leaves them; the same command runs only the rest."""
    grid = _grid(tmp_path, "  place.scene.shift: [[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01]]\n")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "sandbox.cli", "sweep", str(TINY), "--grid", str(grid), "--out", str(out),
           "--workers", "1", "--threads", "1", "--quiet"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    csv = out / "sweep_tiny" / "runs.csv"
    deadline = time.time() + 300
    while time.time() < deadline and len(table.read(csv)[1]) < 1:
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    first = table.read(csv)[1]
    assert 1 <= len(first) < 4
    time.sleep(1.0)  # the run in flight dies with its sweep: it writes nothing more
    assert len(table.read(csv)[1]) == len(first)
    done = _sweep(TINY, "--grid", grid, "--out", out, "--workers", "1")
    assert done.returncode == 0, done.stderr
    assert f"{4 - len(first)} runs to go ({len(first)} already done)" in done.stderr
    with open(csv) as f:
        ids = [line.split(",")[0] for line in f.read().splitlines()[1:]]
    assert len(ids) == 4 == len(set(ids))
    rows = {r["run"]: r for r in table.read(csv)[1]}
    assert all(rows[r["run"]] == r for r in first)
    assert all(r["status"] == "completed" and r["success"] is True for r in rows.values())
    again = _sweep(TINY, "--grid", grid, "--out", out, "--workers", "1")
    assert "0 runs to go (4 already done)" in again.stderr


def test_failing_and_overlong_runs_leave_error_rows_and_the_sweep_completes(tmp_path):
    """A run that blows up and one past the time limit each give a row with their error; reports are written."""
    # Free of its pin and of the ground, at 1000 m/s^2 the rope passes 200 m/s in frame 12: unstable.
    grid = _grid(tmp_path, "  scene.gravity: [[0, -9.81, 0], [0, -1000, 0]]\n  scene.ground: [false]\n"
                           "  scene.ropes.0.pins: [[]]\n  sim.frames: [20]\n")
    res = _sweep(TINY, "--grid", grid, "--out", tmp_path / "a", "--workers", "2")
    assert res.returncode == 0, res.stderr
    rows = {r["scene.gravity"][1]: r for r in table.read(tmp_path / "a" / "sweep_tiny" / "runs.csv")[1]}
    assert rows[-9.81]["status"] == "completed" and rows[-9.81]["ok:min_height(cord) >= 0.3"] is False
    bad = rows[-1000]
    assert bad["status"] == "unstable" and bad["exit_code"] == 3 and "200 m/s" in bad["error"]
    assert bad["success"] is False and 5 <= bad["frames_run"] < 20
    rep = json.loads((tmp_path / "a" / "sweep_tiny" / "report.json").read_text())
    assert rep["runs"] == 2 and rep["passed"] == 0 and rep["status"] == {"completed": 1, "unstable": 1}
    assert rep["criteria"]["min_height(cord) >= 0.3"]["failed"] == 1
    for name in ("axes.png", "time_vs_margin.png"):
        assert (tmp_path / "a" / "sweep_tiny" / name).stat().st_size > 1000
    slow = _sweep(TINY, "--grid", _grid(tmp_path, "  compile: [full]\n"), "--out", tmp_path / "b", "--timeout", "0.3")
    assert slow.returncode == 0, slow.stderr
    (row,) = table.read(tmp_path / "b" / "sweep_tiny" / "runs.csv")[1]
    assert row["status"] == "timeout" and "0.3 s" in row["error"]
    assert (tmp_path / "b" / "sweep_tiny" / "runs" / row["run"] / "spec.json").exists()


def test_local_and_ray_backends_make_the_same_runs(tmp_path):
    """The same sweep on the local pool and on Ray gives the same rows and bitwise the same final states."""
    pytest.importorskip("ray")
    grid = _grid(tmp_path, "  place.scene.turn: [0, 15]\n  compile: [fast]\n")
    outs = {}
    for backend in ("local", "ray"):
        res = _sweep(TINY, "--grid", grid, "--out", tmp_path / backend, "--workers", "1", "--backend", backend)
        assert res.returncode == 0, res.stderr
        outs[backend] = {r["run"]: r for r in table.read(tmp_path / backend / "sweep_tiny" / "runs.csv")[1]}
    assert set(outs["local"]) == set(outs["ray"]) and len(outs["local"]) == 2
    for run, a in outs["local"].items():
        b = outs["ray"][run]
        timing = {"wall_s", "frame_ms_p50", "backend", "host"}
        assert {k: v for k, v in a.items() if k not in timing} == {k: v for k, v in b.items() if k not in timing}
        assert a["backend"] == "local" and b["backend"] == "ray" and a["status"] == "completed"
        sa = np.load(tmp_path / "local" / "sweep_tiny" / "runs" / run / "state.npz")
        sb = np.load(tmp_path / "ray" / "sweep_tiny" / "runs" / run / "state.npz")
        assert set(sa.files) == set(sb.files)
        for k in sa.files:
            assert np.array_equal(sa[k], sb[k]), k
    # the reports come back from the table alone
    folder = tmp_path / "ray" / "sweep_tiny"
    before = json.loads((folder / "report.json").read_text())
    for name in ("report.json", "axes.png", "time_vs_margin.png"):
        (folder / name).unlink()
    res = _sweep("--report", tmp_path / "ray")
    assert res.returncode == 0, res.stderr
    assert json.loads((folder / "report.json").read_text()) == before
    assert (folder / "axes.png").exists() and (tmp_path / "ray" / "summary.md").exists()


def test_sweep_command_line_errors(capsys):
    """Conflicting or missing options exit 2 with a message that says what to give."""
    from sandbox.cli import main

    cases = [([str(TINY)], "exactly one of --standard and --grid"),
             ([str(TINY), "--standard", "--samples", "3"], "--samples and --seed"),
             ([str(TINY), "--standard", "--shared"], "--shared is for --backend ray"),
             (["--report", "/nonexistent/dir"], "holds no sweep table")]
    for args, text in cases:
        code = main(["sweep", *args, "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and text in err, (args, err)


def test_runs_go_in_a_fixed_shuffle_with_the_levels_taking_turns():
    """Jobs interleave levels and shuffle each level's runs, the same way every time, losing none."""
    from types import SimpleNamespace

    from sandbox.sweep.driver import interleave

    jobs = [((SimpleNamespace(folder=pathlib.Path(lv)), SimpleNamespace(id=f"{lv}{k:02d}")), None, None)
            for lv, n in (("a", 10), ("b", 3)) for k in range(n)]
    order = [j[0][1].id for j in interleave(jobs)]
    scrambled = list(reversed(jobs[:10])) + list(reversed(jobs[10:]))  # the levels in the same order
    assert order == [j[0][1].id for j in interleave(scrambled)]
    assert sorted(order) == sorted(j[0][1].id for j in jobs)
    assert [o[0] for o in order[:6]] == ["a", "b"] * 3
    assert [o for o in order if o[0] == "a"] != [f"a{k:02d}" for k in range(10)]


def test_a_run_whose_process_dies_is_recorded_as_crashed(tmp_path):
    """A run's process killed from outside (as by a segfault or the OOM killer) ends 'crashed' with the signal
    and the tail of its log; nothing else is lost."""
    import threading

    from sandbox.sweep import execute

    spec = execute.RunSpec("x", str(TINY), {"sim.frames": 100000}, threads=1)
    got = {}
    t = threading.Thread(target=lambda: got.update(execute.execute(spec, tmp_path / "run")))
    t.start()
    deadline = time.time() + 120
    while time.time() < deadline and not (tmp_path / "run" / "metrics.jsonl").exists():
        time.sleep(0.1)
    with execute._LIVE_LOCK:
        (proc,) = list(execute._LIVE)
    os.kill(proc.pid, signal.SIGKILL)
    t.join(60)
    assert got["status"] == "crashed" and "signal 9" in got["error"] and got["exit_code"] == -9
    assert (tmp_path / "run" / "spec.json").exists() and (tmp_path / "run" / "log.txt").exists()


def test_a_mesh_swapped_in_from_another_folder_is_allowed_for_that_run():
    """A ``mesh:`` swap outside the level's folder checks and runs: its folder is allowed for that run only."""
    (run,) = plan.resolve(TINY, [("", {"swap.post": "mesh:levels/assets/rock.obj"})], sweep_base=ROOT)
    assert run.overrides["scene.objects.0.shape"] == "mesh"
    assert run.mesh_dirs == [str(ROOT / "levels" / "assets")]
    from sandbox.levels import check_level

    assert check_level(TINY, run.overrides).errors  # without it the file lies outside the level's folder
