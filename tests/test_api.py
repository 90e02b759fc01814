"""The embedding API driven like a host game loop: fixed-step accumulator, read-back, FSM progress, maneuvers."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest
import taichi as ti

from sandbox.api import Sandbox
from sandbox.levels import load_level_from_string

ROOT = pathlib.Path(__file__).resolve().parents[1]
FPS = 60
DT = 1.0 / FPS

SCENE = """
version: 1
name: api_scene
scene:
  ground: {{height: -2.0, friction: 0.5}}
  objects:
    - {{name: block, shape: box, params: {{size: [0.2, 0.2, 0.2]}}, position: [2.0, -2.0, 0.0]}}
  cloths:
    - {{name: sheet, resolution: [5, 4], size: [0.4, 0.3], center: [-2.0, 1.0, 0.0], self_collision: false,
       pins: [A, D]}}
  ropes:
    - {{name: cord, points: [[0.0, 1.0, 0.0], [0.4, 1.0, 0.0]], segments: 8, radius: 0.01, pins: [start]}}
sim: {{fps: {fps}, substeps: 4, iterations: 1, frames: 100}}
fsm: {fsm}
"""

TARGET = (0.2, 0.8, 0.0)
SCENARIO = (
    "[{run: Wait, with: {ticks: 3}}, {run: Wait, with: {ticks: 2}},"
    " {run: MoveTo, with: {body: cord, sites: [end], to: [0.2, 0.8, 0.0], speed: 1.0, tolerance: 0.002}},"
    " {run: Wait, with: {ticks: 2}},"
    " {run: Release, with: {body: cord, sites: [end]}},"
    " {run: Wait, with: {ticks: 100000}}]"
)
ROD = """
version: 1
name: api_rod
scene:
  ground: false
  ropes:
    - {{name: rod, points: [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], segments: 1, radius: 0.01}}
sim: {{fps: {fps}, substeps: 2, iterations: 1, frames: 100}}
fsm: [{{run: Wait, with: {{ticks: 100000}}}}]
"""


class FakeClock:
    """A monotonic clock the test advances by hand (s)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _rod(**kwargs) -> Sandbox:
    """A one-rod scene (cheap to compile) for the accumulator tests."""
    return Sandbox(load_level_from_string(ROD.format(fps=FPS), base_dir=ROOT), arch="cpu", **kwargs)


@pytest.fixture(scope="module")
def scenario():
    """The API scene run through Wait(3), Wait(2), MoveTo, Release and Wait, recorded frame by frame.

    Building a scene compiles its kernels, so one run serves every test below.
    """
    sim = Sandbox(load_level_from_string(SCENE.format(fps=FPS, fsm=SCENARIO), base_dir=ROOT), arch="cpu")
    rec = {"sim": sim, "rope0": sim.rope_positions("cord"), "cloth0": sim.cloth_positions("sheet"),
           "states": [], "rows": [], "ends": [], "pins": [], "driven": []}
    end = sim.world.site_particles("cord", "end")
    for _ in range(80):
        row = sim.step()
        rec["rows"].append(row)
        rec["states"].append((sim.fsm_state, sim.finished))
        rope = sim.rope_positions("cord")
        rec["ends"].append(rope[-1].astype(np.float64))
        rec["pins"].append(rope[0].copy())
        rec["driven"].append(bool(sim.world.control.is_driven(end).all()))
    rec["events"] = list(sim.events)
    return rec


def _near_whole(x: float) -> bool:
    return abs(x - round(x)) < 1e-9


# ------------------------------------------------------------------ fixed-step accumulator
def test_advance_runs_every_whole_frame_of_accumulated_time():
    """With no cap, advance() has run exactly floor(accumulated wall time / dt) frames after every call, alpha in [0, 1)."""
    clock = FakeClock()
    sim = _rod(clock=clock, max_frames_per_advance=10**6)
    assert sim.advance() == 0                     # the first call only starts the clock
    rng = np.random.default_rng(1)
    total = 0.0
    for k in range(40):
        inc = 0.0 if k % 7 == 3 else float(rng.uniform(0.0, 2.5 * DT))
        clock.now += inc
        total += inc
        before = sim.frame
        n = sim.advance()
        assert n == sim.frame - before
        if not _near_whole(total / DT):
            assert sim.frame == math.floor(total / DT)
        assert 0.0 <= sim.alpha < 1.0
        assert sim.alpha * DT == pytest.approx(total - sim.frame * DT, abs=1e-9)
    assert sim.frame > 30 and sim.dropped_time == 0.0
    assert sim.time == pytest.approx(sim.frame * DT)


def test_advance_caps_frames_and_counts_dropped_time():
    """advance() runs at most max_frames_per_advance frames per call and drops whole frames of the rest, accounting for all wall time."""
    clock = FakeClock()
    cap = 3
    sim = _rod(clock=clock, max_frames_per_advance=cap)
    sim.advance()
    rng = np.random.default_rng(2)
    total = 0.0
    hitches = 0
    for k in range(30):
        inc = 10.3 * DT if k % 6 == 5 else float(rng.uniform(0.0, 1.5 * DT))
        avail = sim.alpha + inc / DT                 # frames owed before the call
        dropped_before = sim.dropped_time
        clock.now += inc
        total += inc
        n = sim.advance()
        assert n <= cap
        if not _near_whole(avail):
            assert n == min(cap, math.floor(avail))
            dropped = (sim.dropped_time - dropped_before) / DT
            assert dropped == pytest.approx(max(0, math.floor(avail) - cap), abs=1e-6)
            hitches += dropped > 0
        assert 0.0 <= sim.alpha < 1.0
        assert sim.frame * DT + sim.dropped_time + sim.alpha * DT == pytest.approx(total, abs=1e-9)
    assert hitches == 5
    with pytest.raises(ValueError):
        sim.advance(-0.01)


# ------------------------------------------------------------------ read-back
def test_readback_shapes_and_dtypes(scenario):
    """Rope, cloth and object read-back arrays have the documented shapes, dtypes and grid layout."""
    sim = scenario["sim"]
    assert sim.rope_names == ["cord"] and sim.cloth_names == ["sheet"] and sim.object_names == ["block"]
    rope = scenario["rope0"]
    assert sim.rope_positions("cord").shape == rope.shape == (9, 3) and rope.dtype == np.float32
    np.testing.assert_allclose(rope[[0, -1]], [[0.0, 1.0, 0.0], [0.4, 1.0, 0.0]], atol=1e-6)

    nx, nz = sim.cloth_shape("sheet")
    assert (nx, nz) == (5, 4)
    cloth = scenario["cloth0"]
    assert sim.cloth_positions("sheet").shape == cloth.shape == (nx * nz, 3) and cloth.dtype == np.float32
    grid = cloth.reshape(nz, nx, 3)                  # particle (i, j) at j * nx + i
    np.testing.assert_allclose(grid[0, :, 0], np.linspace(-2.2, -1.8, nx), atol=1e-6)
    np.testing.assert_allclose(grid[:, 0, 2], np.linspace(-0.15, 0.15, nz), atol=1e-6)
    faces = sim.cloth_faces("sheet")
    assert faces.shape == (2 * (nx - 1) * (nz - 1), 3) and faces.dtype == np.int32
    assert faces.min() == 0 and faces.max() == nx * nz - 1

    verts, tris = sim.object_mesh("block")
    assert verts.ndim == 2 and verts.shape[1] == 3 and verts.dtype == np.float32
    assert tris.ndim == 2 and tris.shape[1] == 3 and tris.dtype == np.int32
    np.testing.assert_allclose(verts.min(axis=0), [1.9, -2.0, -0.1], atol=1e-6)
    np.testing.assert_allclose(verts.max(axis=0), [2.1, -1.8, 0.1], atol=1e-6)
    assert sim.ground_height == -2.0 and sim.camera is None
    assert set(sim.timings()) == {"physics", "fsm", "metrics"}


# ------------------------------------------------------------------ FSM and maneuvers
def test_wait_chain_states_and_events_by_tick(scenario):
    """A Wait(3) then Wait(2) chain is in the right state after each frame and logs enter/done/exit at the right ticks."""
    assert [r["fsm_state"] for r in scenario["rows"][:6]] == [s for s, _ in scenario["states"][:6]]
    assert scenario["states"][:6] == [("0:Wait", False), ("0:Wait", False), ("1:Wait", False), ("1:Wait", False),
                                      ("2:MoveTo", False), ("2:MoveTo", False)]
    events = [(e["tick"], e["type"], e["state"]) for e in scenario["events"] if e["tick"] <= 5]
    assert events == [(1, "enter", "0:Wait"), (3, "done", "0:Wait"), (3, "exit", "0:Wait"),
                      (3, "enter", "1:Wait"), (5, "done", "1:Wait"), (5, "exit", "1:Wait"),
                      (5, "enter", "2:MoveTo")]
    assert not any(f for _, f in scenario["states"])


def test_moveto_reaches_target_then_release_lets_go(scenario):
    """MoveTo brings the rope end to its target within tolerance, reports done and holds it; after Release the end falls."""
    target = np.asarray(TARGET)
    start = scenario["ends"][4]                      # where the end was when MoveTo started (tick 5)
    ends, driven = scenario["ends"], scenario["driven"]
    done = [e for e in scenario["events"] if e["type"] == "done" and e["state"] == "2:MoveTo"]
    assert len(done) == 1, scenario["events"]
    tick = done[0]["tick"]
    # entered at tick 5; at 1 m/s it cannot arrive in fewer than distance * fps frames
    assert tick - 5 >= np.linalg.norm(target - start) * FPS
    assert np.linalg.norm(ends[tick - 2] - target) > 0.002, "not done before getting close"
    for k in (tick, tick + 1):                       # held at the target (frames tick + 1, tick + 2)
        assert np.linalg.norm(ends[k] - target) <= 0.002
    assert all(driven[4 : tick + 1]), "the end is held while it moves and after"

    released = [e for e in scenario["events"] if e["type"] == "enter" and e["state"] == "4:Release"]
    assert released and released[0]["tick"] == tick + 2
    assert not any(driven[tick + 1 :])
    heights = [e[1] for e in ends[tick + 1 : tick + 21]]
    assert heights[-1] < TARGET[1] - 0.1, "the released end falls"
    assert scenario["states"][-1] == ("5:Wait", False)
    for pin in scenario["pins"]:
        np.testing.assert_array_equal(pin, scenario["rope0"][0])


EARLY = """
version: 1
name: early
scene:
  ground: false
  ropes:
    - {{name: cord, points: [[0.0, 1.0, 0.0], [0.3, 1.0, 0.0]], segments: 4, radius: 0.01, pins: [end]}}
sim: {{fps: 60, substeps: 4, iterations: 1, frames: 100}}
fsm:
  - {{run: MoveTo, with: {{body: cord, sites: [end], to: [{x!r}, 1.0, 0.0], speed: 1.0, tolerance: 0.002}}}}
  - {{run: Wait, with: {{ticks: 100000}}}}
"""


def test_moveto_done_only_within_tolerance():
    """When MoveTo reports done, its site is within tolerance of the target."""
    d = 10.0 / 60.0 + 0.005                          # 10 whole frames at 1 m/s, then 5 mm
    sim = Sandbox(load_level_from_string(EARLY.format(x=0.3 + d), base_dir=ROOT), arch="cpu")
    target = np.array([0.3 + d, 1.0, 0.0])
    for _ in range(20):
        sim.step()
        if any(e["type"] == "done" for e in sim.events):
            break
    assert sim.fsm_state == "1:Wait"
    assert np.linalg.norm(sim.rope_positions("cord")[-1] - target) <= 0.002


HANGING = """
version: 1
name: hanging
scene:
  ground: false
  ropes:
    - {name: cord, points: [[0.0, 1.0, 0.0], [0.0, 0.6, 0.0]], segments: 8, radius: 0.01, pins: [start]}
sim: {fps: 60, substeps: 4, iterations: 1, frames: 100}
fsm:
  - {run: Wait, with: {ticks: 3}}
  - {run: Anchoring, with: {body: cord, sites: [end]}}
  - {run: Wait, with: {ticks: 100000}}
"""


def test_anchoring_the_end_of_a_hanging_rope():
    """Anchoring the lower end of a rope hanging straight down (taut, rods collinear) holds it without blowing up."""
    sim = Sandbox(load_level_from_string(HANGING, base_dir=ROOT), arch="cpu")
    for _ in range(3):
        sim.step()
    held = sim.rope_positions("cord")[-1].copy()     # Anchoring starts at tick 3, holding the end here
    for _ in range(10):
        row = sim.step()
        assert row["retries"] == 0 and row["strain"]["cord"] <= 0.01
    assert sim.fsm_state == "2:Wait"
    np.testing.assert_array_equal(sim.rope_positions("cord")[-1], held)


def test_positions_field_is_a_live_view(scenario):
    """positions_field is the simulation's own Taichi field: its body_range slices match read-back, follow steps and take writes."""
    sim = scenario["sim"]
    field = sim.positions_field
    assert isinstance(field, ti.MatrixField) and field.n == 3 and field.dtype == ti.f32
    a, b = sim.body_range("cord")
    c, d = sim.body_range("sheet")
    assert b - a == 9 and d - c == 20 and field.shape == (max(b, d),)
    for _ in range(3):
        sim.step()
        x = field.to_numpy()                         # the handle taken before stepping
        np.testing.assert_array_equal(x[a:b], sim.rope_positions("cord"))
        np.testing.assert_array_equal(x[c:d], sim.cloth_positions("sheet"))
    field[a + 4] = ti.math.vec3(5.0, 6.0, 7.0)
    np.testing.assert_array_equal(sim.rope_positions("cord")[4], [5.0, 6.0, 7.0])
    with pytest.raises(KeyError):
        sim.body_range("nothing")


# ------------------------------------------------------------------ field trees
def _trees() -> int:
    return ti.lang.impl.get_runtime().prog.get_snode_tree_size()


@pytest.mark.parametrize("level", ["rope_wind.yaml", pytest.param("wrap_bottle.yaml", marks=pytest.mark.slow)])
def test_a_world_takes_one_field_tree(level):
    """Taichi never frees a field tree and a process holds a few hundred: a World (ropes; or cloth, a mesh object and its
    distance grid) allocates all its fields into one, so a host can load levels again and again."""
    root = pathlib.Path(__file__).resolve().parents[1] / "levels"
    sim = Sandbox.from_level(root / level, arch="cpu")
    sim.step()
    before = _trees()
    sim = Sandbox.from_level(root / level, arch="cpu")
    for _ in range(2):
        sim.step()
    assert _trees() - before == 1


def test_batched_uploads_run_at_the_end_and_catch_early_reads():
    from sandbox import runtime

    with runtime.batched():
        f = ti.field(ti.f32, shape=4)
        runtime.defer(f.from_numpy, np.arange(4, dtype=np.float32))
    np.testing.assert_array_equal(f.to_numpy(), np.arange(4))
    with pytest.raises(RuntimeError, match="runtime.defer"):
        with runtime.batched():
            g = ti.field(ti.f32, shape=4)
            g.from_numpy(np.ones(4, np.float32))  # not deferred: materialises inside the block


def test_closing_a_level_frees_its_field_tree():
    """Load, run and close a level again and again: the process's count of field trees stays put."""
    # A small level: each load compiles its kernels again.
    level = ROOT / "tests" / "data" / "levels" / "engine_small.yaml"
    with Sandbox.from_level(level, arch="cpu") as sim:
        sim.step()
    before = _trees()
    # one more load (each compiles its kernels again): a leak would add a tree
    with Sandbox.from_level(level, arch="cpu") as sim:
        sim.step()
        x = sim.rope_positions("cord")
        assert np.isfinite(x).all() and x[:, 1].max() > 0.25
    assert _trees() == before
    with pytest.raises(RuntimeError, match="closed"):
        sim.step()
    with pytest.raises(RuntimeError, match="closed"):
        sim.rope_positions("cord")  # a read of freed fields would crash the process


# ------------------------------------------------------------------ runtime
def test_runtime_fast_compile_is_one_per_process_and_read_from_the_environment(monkeypatch):
    """The test processes run with SANDBOX_FAST_COMPILE=1 unless it is set otherwise (tests/conftest.py): Taichi's
    advanced optimisations are off then; a second init may not change it, and the variable takes only 0 or 1."""
    import os

    from sandbox import runtime

    on = os.environ["SANDBOX_FAST_COMPILE"] == "1"
    assert runtime.fast_compile() is on
    assert ti.lang.impl.current_cfg().advanced_optimization is not on
    assert runtime.init("cpu") == runtime.current_arch()  # the same settings: a no-op
    with pytest.raises(runtime.RuntimeConfigError, match=f"fast_compile={on}"):
        runtime.init("cpu", fast_compile=not on)
    monkeypatch.setenv("SANDBOX_FAST_COMPILE", "yes")
    with pytest.raises(ValueError, match=r"SANDBOX_FAST_COMPILE='yes' is not allowed; allowed: 1 \(on\) or 0 \(off\)"):
        runtime.init("cpu")
    monkeypatch.setenv("SANDBOX_FAST_COMPILE", "0" if on else "1")
    with pytest.raises(runtime.RuntimeConfigError):
        runtime.init("cpu")


def test_cpu_runtime_skips_the_cfg_pass_and_says_why_it_runs_there():
    """On the CPU the control-flow-graph optimisation is off (the fused substep compiles 2-3x faster at the same
    frame time; ``runtime.CPU_CFG_OPTIMIZATION``), and ``reason`` says the backend was asked for."""
    from sandbox import runtime

    assert ti.lang.impl.current_cfg().cfg_optimization is runtime.CPU_CFG_OPTIMIZATION is False
    assert runtime.reason() == "requested cpu"


ORDER_SCRIPT = """
import json, os, sys
sys.path.insert(0, os.getcwd())
from sandbox import runtime
runtime.init("cpu")
import numpy as np, taichi as ti
n = 1 << 16
order, counter = ti.field(ti.i32, shape=n), ti.field(ti.i32, shape=())
@ti.kernel
def take():
    for i in range(n):
        order[i] = ti.atomic_add(counter[None], 1)
take()
print(json.dumps({"threads": runtime.threads(), "serial": runtime.serial_loops(),
                  "in_order": bool((order.to_numpy() == np.arange(n)).all())}))
"""


def _run_threads(value: str, folder: pathlib.Path, **env):
    import os
    import subprocess
    import sys

    script = folder / "order.py"  # Taichi reads a kernel's source from its file
    script.write_text(ORDER_SCRIPT)
    env = {**os.environ, **env, "SANDBOX_THREADS": value}
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=ROOT, env=env,
                          timeout=300)


def test_one_cpu_thread_runs_each_loop_in_order_and_more_threads_share_it(tmp_path):
    """The CPU runs ``SANDBOX_THREADS`` threads, 1 unless set: then loops compile to run in the launching thread, their
    iterations in order (each takes the next count); with two, Taichi's thread pool runs them. Anything but a whole
    number of at least one is refused, saying what is allowed."""
    import json

    from sandbox import runtime

    assert runtime.threads() == 1 and runtime.serial_loops()  # this test process: the default
    one, two = (json.loads(_run_threads(v, tmp_path).stdout.strip().splitlines()[-1]) for v in ("1", "2"))
    assert one == {"threads": 1, "serial": True, "in_order": True}
    assert (two["threads"], two["serial"]) == (2, False)
    bad = _run_threads("0", tmp_path)
    assert bad.returncode != 0
    assert "SANDBOX_THREADS='0' is not allowed; allowed: a whole number of CPU threads, 1 or more" in bad.stderr


def test_kernels_loop_over_ranges_which_one_thread_runs_in_the_launching_thread():
    """Every loop in a kernel or Taichi function loops over ``range``, ``ti.ndrange`` or ``ti.static``: Taichi hands a
    loop over a field (``for i in field``) to its thread pool even when told to serialize it, a thread wake-up per
    loop (``runtime._serialize_loops_when_asked``)."""
    import ast

    found = []
    for path in sorted([*(ROOT / "sandbox").rglob("*.py"), *(ROOT / "shaders").rglob("*.py")]):
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef) or not any(
                    ast.unparse(d).split("(")[0] in ("ti.kernel", "ti.func") for d in fn.decorator_list):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.For):
                    it = node.iter
                    head = ast.unparse(it.func) if isinstance(it, ast.Call) else ""
                    if head not in ("range", "ti.ndrange", "ti.static"):
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno}: for ... in {ast.unparse(it)}")
    assert not found, "\n".join(found)


def test_a_stale_lock_in_the_kernel_cache_is_removed_and_the_cache_written_again(tmp_path, monkeypatch):
    """A process killed while it held the kernel cache's lock leaves the lock file: Taichi then neither reads nor writes
    the cache in any later process. A lock older than ``runtime.STALE_LOCK_S`` is removed at start; a fresh one (a
    process writing now) is left alone."""
    import os
    import time

    from sandbox import runtime

    cache = tmp_path / "cache"
    cache.mkdir()
    lock = cache / "ticache.lock"
    lock.touch()
    monkeypatch.setenv("TI_OFFLINE_CACHE_FILE_PATH", str(cache))
    assert runtime._clear_stale_cache_locks() == [] and lock.exists()  # fresh: someone is writing
    old = time.time() - runtime.STALE_LOCK_S - 5
    os.utime(lock, (old, old))
    run = _run_threads("1", tmp_path, TI_OFFLINE_CACHE_FILE_PATH=str(cache))
    assert run.returncode == 0, run.stderr
    assert not lock.exists()
    assert list(cache.glob("*.tic")), "the process wrote its kernels to the cache"
    assert "Lock" not in run.stderr + run.stdout


def test_one_cpu_thread_compiles_every_range_loop_serial():
    """With one thread every range loop compiles as a serial loop, not only those marked
    ``ti.loop_config(serialize=True)``: Taichi allows ``break`` in a kernel's outermost loop only then (with
    two threads, this kernel does not compile)."""
    from sandbox import runtime

    assert runtime.serial_loops()
    a, limit, found = ti.field(ti.f32, shape=8), ti.field(ti.f32, shape=()), ti.field(ti.i32, shape=())

    @ti.kernel
    def first_over():  # no annotations: this module's are strings (``from __future__ import annotations``)
        found[None] = -1
        for i in range(8):
            if a[i] > limit[None]:
                found[None] = i
                break

    a.from_numpy(np.arange(8, dtype=np.float32))
    for lim, first in ((4.5, 5), (9.0, -1)):
        limit[None] = lim
        first_over()
        assert found[None] == first
