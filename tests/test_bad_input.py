"""Hostile input and faults: bad level files, bad options, a full disk, a reused --out, bad host calls."""

import errno
import json
import pathlib

import numpy as np
import pytest

from sandbox.cli import main

ROOT = pathlib.Path(__file__).resolve().parents[1]
BAD = ROOT / "tests" / "data" / "bad_levels"
TINY = ROOT / "tests" / "data" / "levels" / "sweep_tiny.yaml"
CORPUS = sorted(BAD.glob("*.yaml"))


def _lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


@pytest.mark.parametrize("path", CORPUS, ids=[p.stem for p in CORPUS])
def test_a_bad_level_gives_exit_2_with_its_file_and_line_and_writes_nothing(path, tmp_path, capsys):
    """Each file of the corpus: check and run exit 2, every line names the file and a line, no traceback,
    no output folder."""
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err and "Traceback" not in err
    for line in _lines(err):
        file, line_no = line.split(":")[:2]
        assert file == str(path) and int(line_no) >= 1, line
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--quiet"]) == 2
    assert "Traceback" not in capsys.readouterr().err
    assert not out.exists()


def test_a_short_point_names_the_list_and_the_missing_item(capsys):
    """A point of two numbers is reported at the point itself, with the item that is missing."""
    assert main(["check", str(BAD / "point_too_short.yaml")]) == 2
    assert ":4:12: scene.gravity: item 2 is missing: the list is too short" in capsys.readouterr().err


def test_the_corpus_has_one_fault_per_file(capsys):
    """Each bad level has one problem (two for a cloth too wide both ways), so its line says what the class is."""
    for path in CORPUS:
        main(["check", str(path)])
        n = len(_lines(capsys.readouterr().err))
        assert n == (2 if path.stem == "cloth_huge" else 1), (path.name, n)


def test_yaml_merge_keys_may_be_overridden():
    """A mapping's own key overrides one merged into it (``<<: *base``); a key given twice is still an error."""
    from sandbox.levels import yamlio

    doc = yamlio.parse("b: &b {x: 1, y: 2}\nc: {<<: *b, x: 5}\nd: {x: 1, x: 2}\n")
    assert doc.data["c"] == {"x": 5, "y": 2}
    assert [(p, m) for p, _, m in doc.problems] == [(("d", "x"), "duplicate key 'x'")]


def test_an_oversize_file_is_refused_unread(tmp_path, capsys):
    """A level file over the size bound is refused with its size and the bound."""
    big = tmp_path / "big.yaml"
    big.write_text("version: 1\nname: big\n" + "# padding\n" * 300_000)
    assert main(["check", str(big)]) == 2
    assert "allowed at most 2000000" in capsys.readouterr().err


def test_limits_and_mesh_folders_can_be_raised_by_the_user(capsys, monkeypatch):
    """--limit raises a resource limit and --allow-dir a mesh folder; bad values of either are exit 2."""
    monkeypatch.setenv("SANDBOX_LIMITS", "")  # both options write the environment: restored after the test
    monkeypatch.setenv("SANDBOX_MESH_DIRS", "")
    assert main(["check", str(BAD / "rod_tiny.yaml"), "--limit", "particles=5e6"]) == 0
    assert main(["check", str(BAD / "mesh_outside.yaml"), "--allow-dir", str(ROOT / "levels" / "assets")]) == 0
    capsys.readouterr()
    assert main(["check", str(TINY), "--limit", "atoms=3"]) == 2
    assert "KEY one of particles, steps, memory_gb" in capsys.readouterr().err
    assert main(["check", str(TINY), "--allow-dir", "/no/such/dir"]) == 2


def test_bad_options_are_exit_2_in_one_line(tmp_path, capsys):
    """A bad --set, an --out that is a file or cannot be made: exit 2, one line, nothing written."""
    cases = [(["--set", "sim.frames"], "--set: override 'sim.frames' is not of the form key=value"),
             (["--set", "sim.frames=[1,"], "the value is not valid YAML"),
             (["--set", "sim.frames=1e400"], "got inf (value set by override 'sim.frames')"),
             (["--out", str(TINY)], "exists and is not a folder"),
             (["--out", str(TINY / "sub")], "cannot write there"),
             (["--out", ""], "--out is empty"),
             (["--follow", ","], "--follow names no rope")]
    for extra, text in cases:
        args = ["run", str(TINY), "--quiet", *extra]
        if "--out" not in extra:
            args += ["--out", str(tmp_path / "o")]
        assert main(args) == 2, extra
        err = capsys.readouterr().err
        assert text in err and "Traceback" not in err and len(_lines(err)) == 1, err
    # A body overridden away: its own line first, then the criteria that named it.
    assert main(["run", str(TINY), "--quiet", "--out", str(tmp_path / "o"), "--set", "scene.ropes.0=null"]) == 2
    err = capsys.readouterr().err
    assert "got None (value set by override 'scene.ropes.0')" in _lines(err)[0] and "Traceback" not in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("option", "value", "allowed"), [
    ("--frames", "0", "from 1 to 1000000"), ("--frames", "-1", "from 1 to 1000000"),
    ("--frames", "100000000000", "from 1 to 1000000"), ("--frames", "abc", "from 1 to 1000000"),
    ("--frames-every", "-3", "from 0 to 1000000"), ("--width", "-5", "from 16 to 8192"),
    ("--height", "0", "from 16 to 8192"),
])
def test_numeric_options_out_of_range_are_exit_2_and_say_what_is_allowed(option, value, allowed, tmp_path, capsys):
    """A number of frames, a frame interval or a picture size out of range: exit 2 before anything runs."""
    with pytest.raises(SystemExit) as exc:
        main(["run", str(TINY), "--quiet", "--out", str(tmp_path / "o"), option, value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {option}: '{value}' is not allowed; allowed: a whole number {allowed}" in err
    assert "Traceback" not in err and not (tmp_path / "o").exists()


def test_a_reused_out_folder_is_refused_unless_overwrite(tmp_path, capsys):
    """--out holding another run's outputs is refused; --overwrite clears them (old frames too) and runs."""
    out = tmp_path / "o"
    assert main(["run", str(TINY), "--out", str(out), "--quiet", "--frames-every", "2"]) == 0
    assert len(list((out / "frames").glob("*.png"))) == 4
    (out / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(["run", str(TINY), "--out", str(out), "--quiet"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["run", str(TINY), "--out", str(out), "--quiet", "--overwrite"]) == 0
    assert not (out / "frames").exists() and (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "summary.json").read_text())["status"] == "completed"


def test_a_full_disk_ends_the_run_as_an_error_with_whole_files(tmp_path, monkeypatch):
    """A metrics write that fails half-way (ENOSPC) ends the run 'error' with a clear message; metrics.jsonl
    keeps only whole lines, and the summary, written in the place the first one kept, says so."""
    from sandbox.io import outputs
    from sandbox.runner import RunOptions, run_level

    real_init, real_replace = outputs.MetricsLog.__init__, outputs.os.replace
    calls = {"n": 0}

    class FullDisk:
        """The metrics file on a disk that fills up in the middle of the fourth line."""

        def __init__(self, f):
            self.f = f

        def write(self, data):
            calls["n"] += 1
            if calls["n"] == 4:
                self.f.write(data[: len(data) // 2])
                self.f.flush()
                raise OSError(errno.ENOSPC, "No space left on device", "metrics.jsonl")
            return self.f.write(data)

        def __getattr__(self, name):
            return getattr(self.f, name)

    def init(self, path):
        real_init(self, path)
        self.file = FullDisk(self.file)

    def replace(src, dst):
        if str(dst).endswith("summary.json") and calls["n"] >= 4:
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        real_replace(src, dst)

    monkeypatch.setattr(outputs.MetricsLog, "__init__", init)
    monkeypatch.setattr(outputs.os, "replace", replace)
    code, summary = run_level(TINY, RunOptions(out=tmp_path / "o", progress=False))
    assert code == 3 and summary["status"] == "error"
    assert "could not be written: No space left on device" in summary["message"]
    lines = (tmp_path / "o" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(x)["frame"] for x in lines] == [1, 2, 3]
    on_disk = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert on_disk["status"] == "error" and "in place" in on_disk["output_error"]
    assert not list((tmp_path / "o").glob("*.tmp"))


def test_advance_refuses_bad_wall_times_and_stays_usable():
    """advance(nan), advance(inf), advance(-1) raise and change nothing; advance(1/60) then runs a frame;
    a closed level cannot step."""
    from sandbox.api import Sandbox

    sim = Sandbox.from_level(TINY, arch="cpu")
    try:
        for bad in (float("nan"), float("inf"), -1.0, "0.1"):
            with pytest.raises(ValueError, match="finite number of seconds"):
                sim.advance(bad)
        assert sim.advance(1 / 60) == 1 and sim.frame == 1
        assert sim.advance(np.float32(1 / 60)) == 1
    finally:
        sim.close()
    with pytest.raises(RuntimeError, match="closed"):
        sim.step()


def test_a_stretch_or_sinking_blow_up_counts_as_unstable():
    """A rod five times its rest length, or a free particle deeper in an object than its radius, is a
    blow-up; a held particle may be anywhere."""
    from sandbox.api import Sandbox

    sim = Sandbox.from_level(TINY, arch="cpu")
    try:
        w = sim.world
        n = w.model.n
        calm = {"strain": np.array([0.01]), "depth": np.zeros(n)}
        assert not w._blown_up(calm)
        assert w._blown_up({"strain": np.array([4.5]), "depth": np.zeros(n)})
        deep = np.zeros(n)
        deep[5] = 0.011  # the rope's radius is 0.01
        assert w._blown_up({"strain": np.array([0.0]), "depth": deep})
        deep[5], deep[0] = 0.0, 0.5  # particle 0 is pinned
        assert not w._blown_up({"strain": np.array([0.0]), "depth": deep})
    finally:
        sim.close()


def test_bench_checks_its_baseline_before_timing(tmp_path, capsys):
    """A malformed --baseline is exit 2 with what is wrong, before anything is timed."""
    cases = [("{not json", "not JSON"), ('{"levels": []}', "needs a 'levels' mapping"),
             ('{"levels": {"a": {"ratio_to_calibration": -1}}}', "positive number")]
    for text, message in cases:
        base = tmp_path / "b.json"
        base.write_text(text)
        assert main(["bench", str(TINY), "--baseline", str(base), "--save", str(tmp_path / "s.json")]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "s.json").exists()


def test_an_internal_error_is_one_line_unless_debug(monkeypatch, capsys):
    """An unexpected exception is one line and exit 3; with --debug the traceback comes through."""
    import sandbox.cli as cli

    def broken(a):
        raise KeyError("boom")

    monkeypatch.setattr(cli, "cmd_check", broken)
    parser = cli.build_parser
    monkeypatch.setattr(cli, "build_parser", lambda: _with(parser(), broken))
    assert main(["check", str(TINY)]) == 3
    err = capsys.readouterr().err
    assert "internal error: KeyError: 'boom'" in err and len(_lines(err)) == 1
    with pytest.raises(KeyError):
        main(["check", str(TINY), "--debug"])


def _with(parser, fn):
    for action in parser._subparsers._group_actions:
        action.choices["check"].set_defaults(fn=fn)
    return parser
