"""The headless runner through its command line: outputs, exit codes, determinism, interruption, failure."""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "levels"
LEVEL = DATA / "engine_small.yaml"
INVALID = DATA / "engine_invalid.yaml"
FRAMES = 12


def _cmd(level: pathlib.Path, out: pathlib.Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "sandbox.cli", "run", str(level), "--out", str(out), "--quiet", "--arch", "cpu",
            *extra]


def _run(level: pathlib.Path, out: pathlib.Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(_cmd(level, out, *extra), cwd=ROOT, capture_output=True, text=True, timeout=300)


def _summary(out: pathlib.Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _metrics(out: pathlib.Path) -> list[dict]:
    return [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]


def _bits(a: np.ndarray) -> np.ndarray:
    a = np.atleast_1d(a)
    return a.view(np.uint8) if a.dtype.kind == "f" else a


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    """The small level run twice, in two fresh processes (the first also writes PLY meshes)."""
    base = tmp_path_factory.mktemp("runs")
    a, b = base / "a", base / "b"
    ra = _run(LEVEL, a, "--frames", str(FRAMES), "--ply")
    rb = _run(LEVEL, b, "--frames", str(FRAMES))
    return {"a": a, "b": b, "ra": ra, "rb": rb}


def test_two_processes_give_bitwise_equal_state(two_runs):
    """The same level run in two fresh processes ends in bitwise-equal state.npz arrays."""
    assert two_runs["ra"].returncode == 0, two_runs["ra"].stderr
    assert two_runs["rb"].returncode == 0, two_runs["rb"].stderr
    with np.load(two_runs["a"] / "state.npz") as sa, np.load(two_runs["b"] / "state.npz") as sb:
        assert sorted(sa.files) == sorted(sb.files)
        for key in sa.files:
            x, y = sa[key], sb[key]
            assert x.dtype == y.dtype and x.shape == y.shape, key
            np.testing.assert_array_equal(_bits(x), _bits(y), err_msg=key)
        # the bodies really moved, so equality is not that of two untouched start states
        assert sa["rope_cord"][:, 1].max() < 0.3 - 0.05


def test_plot_frames_overlays_runs_from_their_metrics(two_runs, tmp_path):
    """tools/plot_frames.py reads each run's metrics.jsonl (one point per frame) and writes one PNG;
    a body the runs lack and a label count that does not match are errors that say so."""
    sys.path.insert(0, str(ROOT / "tools"))
    import plot_frames

    s = plot_frames.frame_series(two_runs["a"], "sheet")
    assert s["frame"] == list(range(1, FRAMES + 1)) and s["substeps"] == [4] * FRAMES
    rows = _metrics(two_runs["a"])
    assert s["strain"] == [r["strain"]["sheet"] for r in rows]
    assert plot_frames.frame_series(two_runs["a"])["strain"] == [max(r["strain"].values()) for r in rows]
    out = tmp_path / "frames.png"
    plot_frames.plot_frames([two_runs["a"], two_runs["b"]], ["a", "b"], out)
    assert out.stat().st_size > 1000
    with pytest.raises(ValueError, match="no body 'rag'; bodies: cord, sheet"):
        plot_frames.frame_series(two_runs["a"], "rag")
    with pytest.raises(ValueError, match="one label per run"):
        plot_frames.plot_frames([two_runs["a"]], ["a", "b"], out)


def test_completed_run_writes_every_output(two_runs):
    """A completed run writes summary.json, one JSON line per frame, state.npz with every body, and PLY meshes."""
    out, proc = two_runs["a"], two_runs["ra"]
    assert proc.returncode == 0, proc.stderr
    assert "success" in proc.stdout

    s = _summary(out)
    assert s["status"] == "completed" and s["success"] is True
    assert s["frames_run"] == FRAMES == s["frames_planned"]
    assert [c["metric"] for c in s["criteria"]] == ["min_height", "max_speed"]
    assert all(c["ok"] for c in s["criteria"])
    fm = s["frame_ms"]
    assert fm["n"] > 0 and 0 < fm["p50"] <= fm["p95"] <= fm["max"]
    assert set(s["systems_ms"]) == {"physics", "fsm", "metrics"}
    for stats in s["systems_ms"].values():
        assert stats["n"] > 0 and 0 <= stats["p50"] <= stats["p95"] <= stats["max"]

    rows = _metrics(out)
    assert [r["frame"] for r in rows] == list(range(1, FRAMES + 1))
    for r in rows:
        assert set(r["strain"]) == {"cord", "sheet"} and r["retries"] == 0 and r["substeps"] == 4
    assert s["substeps"] == {"fixed": 4, "max": 16, "per_frame": {"4": FRAMES}, "mean": 4.0}

    with np.load(out / "state.npz") as st:
        assert {"rope_cord", "cloth_sheet", "object_block", "frame", "time"} <= set(st.files)
        assert st["rope_cord"].shape == (13, 3) and st["rope_cord"].dtype == np.float32
        assert st["cloth_sheet"].shape == (30, 3) and st["cloth_sheet"].dtype == np.float32
        assert st["object_block"].shape == (4, 4)
        assert int(st["frame"]) == FRAMES
        rope = st["rope_cord"]

    import trimesh

    assert sorted(s["meshes"]) == ["cloth_sheet.ply", "object_block.ply", "rope_cord.ply"]
    cloth = trimesh.load(out / "meshes" / "cloth_sheet.ply", process=False)
    assert len(cloth.vertices) == 30 and len(cloth.faces) == 2 * 5 * 4
    cord = trimesh.load(out / "meshes" / "rope_cord.ply", process=False)
    np.testing.assert_allclose(np.asarray(cord.vertices), rope, atol=1e-6)
    block = trimesh.load(out / "meshes" / "object_block.ply", process=False)
    assert len(block.vertices) == 8 and block.is_watertight


def test_failed_criterion_exits_1(tmp_path):
    """A run whose criterion cannot hold completes, marks that criterion failed and exits with 1."""
    out = tmp_path / "fail"
    proc = _run(LEVEL, out, "--frames", "3", "--set", "success.0.min=100.0")
    assert proc.returncode == 1, proc.stderr
    s = _summary(out)
    assert s["status"] == "completed" and s["success"] is False
    assert [c["ok"] for c in s["criteria"]] == [False, True]
    assert "FAIL" in proc.stdout


def test_invalid_level_exits_2_without_output(tmp_path):
    """An invalid level exits with 2, prints every error with file:line, and creates no output folder."""
    out = tmp_path / "never"
    proc = _run(INVALID, out)
    assert proc.returncode == 2
    assert "engine_invalid.yaml:9:" in proc.stderr and "radius" in proc.stderr
    assert "engine_invalid.yaml:10:" in proc.stderr and "colour" in proc.stderr
    assert not out.exists()


@pytest.mark.parametrize("opts, message", [
    ({"follow": ["cord"]}, "add --frames-every K, --video or --gif"),
    ({"follow": ["cord", "rope9"], "frames_every": 5}, "'rope9' not a rope or a cloth line of engine_small; ropes: cord"),
    ({"follow": ["cord"], "frames_every": 5, "follow_distance": 0.0}, "--follow-distance must be > 0"),
    ({"follow_distance": 0.3, "video": True}, "--follow-distance needs --follow"),
])
def test_bad_follow_exits_2_before_running(tmp_path, opts, message):
    """A close-up camera that cannot be made (no rendering, not a rope, bad distance) is refused before the run starts."""
    from sandbox.runner import EXIT_INVALID, RunOptions, run_level

    out = tmp_path / "never"
    code, summary = run_level(LEVEL, RunOptions(out=out, frames=2, progress=False, **opts))
    assert code == EXIT_INVALID and summary["status"] == "invalid"
    assert message in summary["errors"]
    assert not out.exists()


def test_follow_takes_a_strand_of_a_rope(tmp_path):
    """``--follow cord[0:20],cord[20:]`` (two runs of one rope, a self-knot's strands) is accepted."""
    from sandbox.levels import load_level
    from sandbox.runner import RunOptions, _follow_problem

    opts = RunOptions(out=tmp_path, follow=["cord[0:20]", "cord[20:]"], frames_every=5)
    assert _follow_problem(load_level(LEVEL), opts) is None


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM", "SIGHUP"])
def test_a_stop_signal_leaves_valid_outputs_and_exits_130(tmp_path, sig):
    """Ctrl-C, SIGTERM or SIGHUP during a run leave status 'interrupted' (naming the signal), a valid
    metrics.jsonl and state.npz, and exit with 130."""
    out = tmp_path / "int"
    proc = subprocess.Popen(_cmd(LEVEL, out, "--frames", "100000"), cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        metrics = out / "metrics.jsonl"
        while time.monotonic() < deadline and proc.poll() is None:
            if metrics.exists() and metrics.read_text().count("\n") >= 5:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()[1]
        proc.send_signal(getattr(signal, sig))
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    s = _summary(out)
    assert s["status"] == "interrupted" and sig in s["message"]
    rows = _metrics(out)
    assert len(rows) == s["frames_run"] >= 5
    assert [r["frame"] for r in rows] == list(range(1, len(rows) + 1))
    with np.load(out / "state.npz") as st:
        assert int(st["frame"]) >= s["frames_run"]
        assert np.isfinite(st["rope_cord"]).all() and np.isfinite(st["cloth_sheet"]).all()


# Ctrl-C lands wherever the interpreter happens to be; the two tests below put it at
# chosen places inside World.step so that the outcome is deterministic. They run in this
# process, on a one-rod level that compiles quickly.
ROD = """
version: 1
name: rod
scene:
  ground: {height: -10.0}
  ropes:
    - {name: rod, points: [[0.0, 1.0, 0.0], [0.1, 1.0, 0.0]], segments: 1, radius: 0.01}
sim: {fps: 60, substeps: 4, iterations: 1, frames: 6}
fsm:
  - {run: Wait, with: {ticks: 100000}}
"""


def _interrupted_run(tmp_path, monkeypatch, target: str, name: str, when) -> tuple[dict, pathlib.Path]:
    """Run the rod level in this process with KeyboardInterrupt raised by ``target.name`` when ``when()``."""
    import importlib

    from sandbox.runner import EXIT_INTERRUPTED, RunOptions, run_level

    module, cls = target.rsplit(".", 1)
    owner = getattr(importlib.import_module(module), cls)
    original = getattr(owner, name)

    def wrapped(self, *args, **kwargs):
        if when(self):
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(owner, name, wrapped)
    level = tmp_path / "rod.yaml"
    level.write_text(ROD)
    out = tmp_path / "run"
    code, summary = run_level(level, RunOptions(out=out, frames=6, arch="cpu", progress=False, profile_every=0))
    monkeypatch.setattr(owner, name, original)
    assert code == EXIT_INTERRUPTED and summary["status"] == "interrupted", summary.get("traceback")
    return summary, out


def test_interrupt_after_physics_keeps_outputs_consistent(tmp_path, monkeypatch):
    """Ctrl-C between a frame's physics and its metrics row leaves state.npz, metrics.jsonl and frames_run on the same frame."""
    summary, out = _interrupted_run(tmp_path, monkeypatch, "sandbox.world.World", "_frame_metrics",
                                    lambda world: world.frame == 3)
    with np.load(out / "state.npz") as st:
        frame = int(st["frame"])
    assert frame == summary["frames_run"] == len(_metrics(out))


def test_interrupt_between_substeps_saves_a_whole_frame(tmp_path, monkeypatch):
    """Ctrl-C between two substeps of a frame leaves in state.npz exactly the state of the last whole frame."""
    from sandbox.api import Sandbox
    from sandbox.levels import load_level_from_string

    calls = {"n": 0}

    def second_substep_of_frame_3(solver):
        calls["n"] += 1
        return calls["n"] == 2 * 4 + 2                     # 4 substeps per frame

    summary, out = _interrupted_run(tmp_path, monkeypatch, "sandbox.solvers.xpbd.XPBDSolver", "substep",
                                    second_substep_of_frame_3)
    clean = Sandbox(load_level_from_string(ROD), arch="cpu")
    for _ in range(summary["frames_run"]):
        clean.step()
    with np.load(out / "state.npz") as st:
        assert int(st["frame"]) == summary["frames_run"] == 2
        np.testing.assert_array_equal(st["rope_rod"], clean.rope_positions("rod"))


def test_unstable_run_exits_3(tmp_path):
    """A run that blows up exits with 3 and leaves status 'unstable', its message and the last good state.

    With no ground, 1000 m/s^2 and the substeps held at 4 (the adaptive count, up to 16, keeps this scene
    together), the scene blows up by frame 12; no retry can help.
    """
    out = tmp_path / "boom"
    proc = _run(LEVEL, out, "--frames", "30", "--set", "scene.gravity=[0.0, -1000.0, 0.0]", "--set",
                "scene.ground=false", "--set", "sim.max_substeps=4")
    assert proc.returncode == 3, proc.stderr
    s = _summary(out)
    assert s["status"] == "unstable" and s["success"] is False
    assert "SimulationUnstable" in s["message"] and "retries" in s["message"]
    assert "traceback" not in s and "criteria" not in s
    assert 5 <= s["frames_run"] < 30 and len(_metrics(out)) == s["frames_run"]
    assert "SimulationUnstable" in proc.stderr
    with np.load(out / "state.npz") as st:
        assert int(st["frame"]) == s["frames_run"]  # the last good frame
        assert np.isfinite(st["rope_cord"]).all() and np.isfinite(st["cloth_sheet"]).all()


def test_in_process_runs_give_back_their_field_trees(tmp_path):
    """run_level closes its world once the outputs are written: many runs in one process keep the field-tree count."""
    import taichi as ti

    from sandbox import runtime
    from sandbox.runner import RunOptions, run_level

    runtime.init("cpu")
    level = LEVEL  # small: each load compiles its kernels again
    run_level(level, RunOptions(out=tmp_path / "a", frames=3, progress=False))
    trees = ti.lang.impl.get_runtime().prog.get_snode_tree_size()
    # one more run (each compiles its kernels again): a leak would add a tree
    code, s = run_level(level, RunOptions(out=tmp_path / "b", frames=3, progress=False))
    assert s["status"] == "completed" and (tmp_path / "b" / "state.npz").exists()
    assert s["fast_compile"] is runtime.fast_compile()  # frame times depend on it
    assert s["backend_reason"] == runtime.reason() == "requested cpu"
    assert ti.lang.impl.get_runtime().prog.get_snode_tree_size() == trees


def test_bench_level_reports_times_passes_strain_and_speed():
    """``bench_level`` (behind ``sandbox bench`` and tools/) times frames after warm-up and reports the per-pass split,
    strain and the final largest speed of the state it leaves."""
    from sandbox.bench import bench_level

    r = bench_level(str(LEVEL), frames=4, profile_frames=1)
    assert r["particles"] > 0
    assert 0.0 < r["frame_ms_p50"] <= r["frame_ms_p95"] <= r["frame_ms_max"]
    assert "predict" in r["stage_ms"] and "velocities" in r["stage_ms"]
    assert all(v >= 0.0 for v in r["stage_ms"].values())
    assert set(r["final_strain"]) and all(np.isfinite(v) for v in r["final_strain"].values())
    assert 0.0 < r["final_max_speed"] < 200.0
    assert r["substeps"] == {"mean": 4.0, "most": 4}  # the level's fixed count
    assert set(r["run_max_penetration"]) == set(r["final_strain"])
    assert all(0.0 <= v < 1.0 for v in r["run_max_penetration"].values())  # m, deepest over the run


def test_pareto_front_and_plot_from_a_saved_run(tmp_path):
    """tools/pareto_cloth.py: the front keeps exactly the points nothing beats on both axes (closed form), and
    ``--replot`` draws a saved run, also one where every depth is 0."""
    sys.path.insert(0, str(ROOT / "tools"))
    import pareto_cloth

    pts = [(64.0, 57.0), (85.0, 17.0), (120.0, 18.5), (127.0, 0.96), (175.0, 1.64), (294.0, 0.28)]
    assert pareto_cloth.front(pts) == [0, 1, 3, 5]
    rows = [{"label": f"s{i}", "ms": x, "stretch": y, "depth_mm": 0.0} for i, (x, y) in enumerate(pts)]
    saved = tmp_path / "p.json"
    saved.write_text(json.dumps({"rows": rows, "level": "drape_box", "frames": 150, "calibration_ms": 11.6,
                                 "machine": {"processor": "x86_64"}}))
    out = tmp_path / "p.png"
    assert pareto_cloth.main(["--replot", str(saved), "--plot", str(out)]) == 0
    assert out.stat().st_size > 10_000
    # The peers' points: their ms scaled by the ratio of the two runs' calibrations; a diverged peer is kept.
    peers = {"calibration_ms": 5.8, "rows": [{"label": "a", "ms": 100.0, "stretch": 3.0, "depth_mm": 0.1, "frames": 40,
                                              "diverged_at": None},
                                             {"label": "b", "ms": 50.0, "stretch": 0.0, "depth_mm": 0.0, "frames": 17,
                                              "diverged_at": 17}]}
    got = pareto_cloth.peer_points(peers, 11.6)
    assert [r["ms"] for r in got] == [200.0, 100.0] and got[1]["diverged_at"] == 17
    (tmp_path / "peers.json").write_text(json.dumps(peers))
    assert pareto_cloth.main(["--replot", str(saved), "--plot", str(out), "--peers", str(tmp_path / "peers.json")]) == 0


def test_peers_cloth_measures_stretch_and_depth_in_closed_form():
    """tools/peers_cloth.py (no peer needed): a grid's structural edges, the stretch of a uniformly scaled grid,
    and how deep a point is in the box or under the ground, in y-up and z-up frames."""
    sys.path.insert(0, str(ROOT / "tools"))
    import peers_cloth as pc

    e = pc.grid_edges(4)
    assert len(e) == 2 * 4 * 3 and len({tuple(sorted(p)) for p in e}) == len(e)
    ii, jj = np.meshgrid(np.arange(4), np.arange(4))
    x = np.stack([ii.ravel() * 0.01, np.zeros(16), jj.ravel() * 0.01], 1)
    assert pc.stretch(x * 1.03, e, 0.01) == pytest.approx(0.03, rel=1e-6)
    assert pc.stretch(x * 0.9, e, 0.01) == 0.0  # compression is not stretch
    pts = np.array([[0.0, 0.35, 0.0], [1.0, -0.002, 0.0], [1.0, 0.5, 1.0]])  # 5 cm into the box's top; under
    assert pc.depth(pts, 1) == pytest.approx(0.05)
    assert pc.depth(pts[:, [0, 2, 1]], 2) == pytest.approx(0.05)
    assert pc.depth(pts[1:], 1) == pytest.approx(0.002)


CROSSED_FALLING = """
version: 1
name: crossed_falling
scene:
  ropes:
    - {name: A, points: [[-0.3, 1.011, 0.05], [0.3, 1.011, 0.05]], rod_length: 0.02, radius: 0.005, damping: 0.0}
    - {name: B, points: [[0.0, 1.0, -0.3], [0.0, 1.0, 0.3]], rod_length: 0.02, radius: 0.005, damping: 0.0}
sim: {fps: 60, substeps: 4, frames: 6}
fsm:
  - {run: Wait, with: {seconds: 0.05}}
success:
  - {metric: knot, of: [A, B], equals: unknot}
"""


def test_hold_rest_measures_how_far_a_knot_moves_while_held(tmp_path, monkeypatch):
    """Two crossed ropes fall together, one on the other, from rest: the place where they touch falls
    g (t1^2 - t0^2) / 2 between the FSM's end t0 and the hold's end t1 (closed form), straight down."""
    sys.path.insert(0, str(ROOT / "tools"))
    import hold_rest

    level = tmp_path / "crossed.yaml"
    level.write_text(CROSSED_FALLING)
    monkeypatch.setattr(sys, "argv", ["hold_rest.py", str(level), "--seconds", "0.25", "--out", str(tmp_path / "o")])
    hold_rest.main()
    r = json.loads((tmp_path / "o" / "hold.json").read_text())
    t0, t1 = r["fsm_end"]["frame"] / 60.0, r["frames"][-1]["time"]
    start, end = r["fsm_end"]["knot_centre"]["['A', 'B']"], r["frames"][-1]["knot_centre"]["['A', 'B']"]
    fall = 0.5 * 9.81 * (t1**2 - t0**2)
    np.testing.assert_allclose(np.subtract(start, end), [0.0, fall, 0.0], atol=0.05 * fall)
    drift = r["knot_drift"]["['A', 'B']"]
    assert drift["final"] == pytest.approx(fall, rel=0.05) and drift["largest"] == pytest.approx(drift["final"])


def test_hold_rest_holds_the_end_state_and_records_every_frame(tmp_path, monkeypatch):
    """tools/hold_rest.py runs a level to its FSM's end (here: its frame count) and then holds it."""
    sys.path.insert(0, str(ROOT / "tools"))
    import hold_rest

    monkeypatch.setattr(sys, "argv", ["hold_rest.py", str(LEVEL), "--seconds", "0.5", "--out", str(tmp_path)])
    hold_rest.main()
    r = json.loads((tmp_path / "hold.json").read_text())
    assert r["fsm_end"]["frame"] == 20 and len(r["frames"]) == 30
    times = [f["time"] for f in r["frames"]]
    assert np.allclose(np.diff(times), 1.0 / 60.0) and abs(times[0] - 21 / 60.0) < 1e-9
    assert all(f["energy"] >= 0.0 and f["max_speed"] >= f["mean_speed"] >= 0.0 for f in r["frames"])
    assert r["energy_last_second"] == pytest.approx(np.mean([f["energy"] for f in r["frames"]]))
    assert r["max_strain"] == max(f["strain"] for f in r["frames"]) and r["retries"] == 0
    assert (tmp_path / "hold.png").stat().st_size > 1000

    import plot_holds

    other = tmp_path / "b" / "hold.json"
    other.parent.mkdir()
    r["frames"] = r["frames"][:10]
    other.write_text(json.dumps(r))
    out = tmp_path / "holds.png"
    plot_holds.plot_holds([tmp_path / "hold.json", other], ["a", "b"], out)
    assert out.stat().st_size > 1000
    with pytest.raises(ValueError, match="one label per file"):
        plot_holds.plot_holds([other], ["a", "b"], out)


def test_follow_frames_are_framed_on_the_rope(tmp_path, monkeypatch):
    """``follow`` reaches the recorder: every rendered frame asks the follower for its camera, at the distance given."""
    from sandbox.io import frames
    from sandbox.runner import RunOptions, run_level

    seen = []
    update = frames.KnotFollower.update

    def spy(self, sim):
        cam = update(self, sim)
        seen.append((self.ropes, float(np.linalg.norm(np.subtract(cam.position, cam.look_at)))))
        return cam

    monkeypatch.setattr(frames.KnotFollower, "update", spy)
    level = tmp_path / "one_rope.yaml"  # a rope alone: few kernels to compile
    level.write_text("version: 1\nname: one_rope\nscene:\n  ropes:\n"
                     "    - {name: cord, points: [[0, 0.5, 0], [0.3, 0.5, 0]], segments: 12, radius: 0.01, pins: [start]}\n"
                     "fsm:\n  - {run: Wait, with: {seconds: 1.0}}\n")
    code, summary = run_level(level, RunOptions(out=tmp_path / "f", frames=2, frames_every=1, width=64, height=48,
                                                progress=False, follow=["cord"], follow_distance=0.2))
    assert summary["status"] == "completed", summary
    assert sorted(p.name for p in (tmp_path / "f" / "frames").glob("*.png")) == ["00000.png", "00001.png"]
    assert len(seen) >= 2 and all(r == ["cord"] and abs(d - 0.2) < 1e-9 for r, d in seen)
