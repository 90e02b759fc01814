"""Headless runner: a level from start to end, writing its outputs.

Exit codes: 0 success; 1 the level ran but a criterion failed; 2 invalid
level or arguments; 3 the simulation became unstable or raised; 130
interrupted (Ctrl-C). Every ending leaves a valid ``summary.json`` whose
``status`` says which.
"""

from __future__ import annotations

import contextlib
import dataclasses
import pathlib
import platform
import signal
import threading
import time
import traceback

import numpy as np

from sandbox import runtime
from sandbox.io.outputs import MetricsLog, write_json_atomic, write_meshes, write_state

WARMUP_FRAMES = 3  # JIT compilation happens in the first frames; kept out of timings
EXIT_OK, EXIT_CRITERIA, EXIT_INVALID, EXIT_ERROR, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


@dataclasses.dataclass
class RunOptions:
    """What to run and what to write."""

    out: pathlib.Path
    frames: int | None = None
    arch: str | None = None
    ply: bool = False
    frames_every: int = 0
    video: bool = False
    gif: bool = False
    width: int = 640
    height: int = 480
    progress: bool = True
    profile_every: int = 30
    overrides: dict | None = None
    follow: list[str] | None = None  # ropes whose knot the frames' camera follows (over the level's camera)
    follow_distance: float | None = None  # m from the knot to the camera


def _stats(ms: list[float]) -> dict:
    if not ms:
        return {"p50": None, "p95": None, "max": None, "n": 0}
    a = np.asarray(ms)
    return {"p50": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max()), "n": len(a)}


@contextlib.contextmanager
def _deferred_sigint():
    """Ctrl-C stops the run at the next frame boundary (a second Ctrl-C at once).

    Yields a dict whose ``"stop"`` becomes True on the first Ctrl-C.
    """
    flag = {"stop": False}
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame):
        if flag["stop"]:
            raise KeyboardInterrupt
        flag["stop"] = True

    old = signal.signal(signal.SIGINT, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, old)


def _follow_problem(level, opts: RunOptions) -> str | None:
    """What is wrong with ``opts.follow`` for this level (None if nothing)."""
    if not opts.follow and opts.follow_distance is None:
        return None
    if not (opts.frames_every or opts.video or opts.gif):
        return "--follow sets the camera of rendered frames: add --frames-every K, --video or --gif"
    if opts.follow_distance is not None and not opts.follow_distance > 0:
        return f"--follow-distance must be > 0 m, got {opts.follow_distance}"
    ropes = [r.name for r in level.scene.ropes]
    if not opts.follow:
        return "--follow-distance needs --follow ROPE[,ROPE...]"
    bad = [n for n in opts.follow if n not in ropes]
    if bad:
        return f"--follow: {', '.join(map(repr, bad))} not a rope of {level.name}; ropes: {', '.join(ropes) or '(none)'}"
    return None


def run_level(path: str | pathlib.Path, opts: RunOptions) -> tuple[int, dict]:
    """Run a level headless; returns (exit code, summary)."""
    from sandbox.levels import LevelError, load_level

    path = pathlib.Path(path)
    try:
        level = load_level(path, opts.overrides or None)
    except LevelError as exc:
        return EXIT_INVALID, {"status": "invalid", "errors": str(exc)}
    except FileNotFoundError as exc:
        return EXIT_INVALID, {"status": "invalid", "errors": str(exc)}
    problem = _follow_problem(level, opts)
    if problem:
        return EXIT_INVALID, {"status": "invalid", "errors": problem}

    out = pathlib.Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict = {
        "level": level.name,
        "path": str(path),
        "status": "running",
        "success": False,
        "frames_planned": int(opts.frames or level.sim.frames),
        "frames_run": 0,
        "machine": {"python": platform.python_version(), "platform": platform.platform(),
                    "processor": platform.processor() or platform.machine()},
    }
    write_json_atomic(out / "summary.json", summary)
    log = MetricsLog(out / "metrics.jsonl")
    world = None
    recorder = None
    frame_ms: list[float] = []
    systems: dict[str, list[float]] = {}
    stages: dict[str, list[float]] = {}
    code = EXIT_ERROR
    try:
        from sandbox.api import Sandbox

        sim = Sandbox(level, base_dir=path.parent, arch=opts.arch)
        world = sim.world
        world.profile_every = opts.profile_every
        summary["arch"] = world.arch
        summary["fast_compile"] = runtime.fast_compile()  # frame times depend on it (docs/how-it-works.md, "Compile time")
        summary["particles"] = world.model.n
        summary["constraints"] = world.model.m
        summary["stages"] = [*world.solver.stages_zero, *world.solver.stages]
        if opts.frames_every or opts.video or opts.gif:
            from sandbox.io.frames import FrameRecorder, KnotFollower

            # the level camera's follow, or --follow over it; None: the level camera or an automatic one
            follow = KnotFollower.from_camera(sim.camera, opts.follow, distance=opts.follow_distance)
            recorder = FrameRecorder(out, every=max(1, opts.frames_every or 1), video=opts.video, gif=opts.gif,
                                     width=opts.width, height=opts.height, follow=follow)
        n = summary["frames_planned"]
        bar = None
        if opts.progress:
            from tqdm import tqdm

            bar = tqdm(total=n, desc=level.name, unit="frame", leave=False, disable=None)  # None: off when stderr is not a terminal
        last_state = world.fsm.state if world.fsm else ""
        with _deferred_sigint() as sigint:
            _frames(sim, world, n, log, summary, recorder, bar, frame_ms, systems, stages, last_state, sigint)
        if bar is not None:
            bar.close()
        summary["status"] = "completed"
        code = EXIT_OK
    except KeyboardInterrupt:
        summary["status"] = "interrupted"
        summary["message"] = "interrupted by the user (Ctrl-C); outputs cover the frames run"
        code = EXIT_INTERRUPTED
    except Exception as exc:  # reported in the summary, never lost
        from sandbox.world import SimulationUnstable

        summary["status"] = "unstable" if isinstance(exc, SimulationUnstable) else "error"
        summary["message"] = f"{type(exc).__name__}: {exc}"
        if not isinstance(exc, SimulationUnstable):
            summary["traceback"] = traceback.format_exc()
        code = EXIT_ERROR
    finally:
        log.close()
    summary["frame_ms"] = _stats(frame_ms)
    summary["systems_ms"] = {k: _stats(v) for k, v in systems.items()}
    summary["stage_ms_per_frame"] = {k: float(np.median(v)) for k, v in stages.items()}
    if world is not None:
        summary["retries"] = world.retries_total
        used = world.substep_frames
        summary["substeps"] = {"fixed": world.substeps, "max": world.max_substeps,
                               "per_frame": {str(k): used[k] for k in sorted(used)},
                               "mean": world.mean_substeps}
        summary["sim_time"] = world.time
        summary["max_strain"] = world.run_max["strain"]
        summary["max_penetration"] = world.run_max["penetration"]
        if world.fsm is not None:
            summary["fsm"] = {"state": world.fsm.state, "events": world.fsm.events,
                              "durations": world.fsm.durations}
        try:
            write_state(out / "state.npz", world)
            if opts.ply:
                summary["meshes"] = write_meshes(out / "meshes", world)
        except Exception as exc:
            summary["output_error"] = f"{type(exc).__name__}: {exc}"
        if recorder is not None:
            try:
                summary["render"] = recorder.close(sim)
            except Exception as exc:
                summary["render"] = {"error": f"{type(exc).__name__}: {exc}"}
        if summary["status"] == "completed":
            from sandbox.io.criteria import evaluate

            summary["criteria"] = evaluate(level.success, world)
            summary["success"] = all(c["ok"] for c in summary["criteria"])
            code = EXIT_OK if summary["success"] else EXIT_CRITERIA
    write_json_atomic(out / "summary.json", summary)
    if world is not None:
        world.close()  # frees its field tree: a process may run many levels (tools/sweep_level.py)
    return code, summary


def _frames(sim, world, n, log, summary, recorder, bar, frame_ms, systems, stages, last_state, sigint) -> None:
    """The frame loop; a frame's physics, metrics row and picture stay together."""
    for f in range(n):
        if sigint["stop"]:
            raise KeyboardInterrupt
        t0 = time.perf_counter()
        row = sim.step()
        dt_ms = 1e3 * (time.perf_counter() - t0)
        row["frame_ms"] = round(dt_ms, 3)
        profiled = "stage_ms" in row
        if f >= WARMUP_FRAMES and not profiled:
            frame_ms.append(dt_ms)
            for k, v in row["ms"].items():
                systems.setdefault(k, []).append(v)
        if profiled and f >= WARMUP_FRAMES:
            for k, v in row["stage_ms"].items():
                stages.setdefault(k, []).append(v)
        log.write(row)
        summary["frames_run"] = f + 1
        state = world.fsm.state if world.fsm else ""
        if recorder is not None:
            recorder.on_frame(sim, f, state, state != last_state)
        last_state = state
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{state} {dt_ms:.0f} ms")
