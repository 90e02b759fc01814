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

from sandbox.io.outputs import (
    SUMMARY_RESERVE,
    MetricsLog,
    write_json_atomic,
    write_json_in_place,
    write_meshes,
    write_state,
)

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
    overwrite: bool = False  # replace the outputs of an earlier run in ``out`` (else such a folder is refused)


OUTPUTS = ("summary.json", "metrics.jsonl", "state.npz", "frames", "meshes", "anim.mp4", "anim.gif", "sheet.png")
"""What a run writes into its folder: a folder holding any of them holds another run's outputs."""
RUN_MARKERS = ("summary.json", "metrics.jsonl", "state.npz")
"""Files that only a run writes: ``frames/`` and ``meshes/`` count as a run's outputs only beside one of them."""


def _prepare_out(out: pathlib.Path, overwrite: bool) -> str | None:
    """Make ``out`` ready for a run; what is wrong with it (None if nothing).

    A folder that holds another run's outputs is refused unless ``overwrite``,
    which removes those outputs first (other files stay).
    """
    import shutil

    if out.exists() and not out.is_dir():
        return f"--out {out}: exists and is not a folder"
    marked = any((out / name).is_file() for name in RUN_MARKERS)  # a run's folder: its frames/, meshes/ too
    old = [name for name in OUTPUTS if (out / name).exists() and (marked or name not in ("frames", "meshes"))]
    if old and not overwrite:
        return (f"--out {out}: holds the outputs of another run ({', '.join(old)}); give --overwrite to replace "
                "them, or another folder")
    try:
        for name in old:
            path = out / name
            shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        return f"--out {out}: cannot write there ({exc.strerror or exc})"
    return None


def _stats(ms: list[float]) -> dict:
    if not ms:
        return {"p50": None, "p95": None, "max": None, "n": 0}
    a = np.asarray(ms)
    return {"p50": float(np.median(a)), "p95": float(np.percentile(a, 95)), "max": float(a.max()), "n": len(a)}


STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))


@contextlib.contextmanager
def _deferred_sigint():
    """Ctrl-C, SIGTERM and SIGHUP stop the run at the next frame boundary (a second one at once).

    Yields a dict whose ``"stop"`` becomes the signal's name on the first one.
    """
    flag: dict = {"stop": None}
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame):
        if flag["stop"]:
            raise KeyboardInterrupt
        flag["stop"] = signal.Signals(signum).name

    old = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}
    try:
        yield flag
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def _follow_problem(level, opts: RunOptions) -> str | None:
    """What is wrong with ``opts.follow`` for this level (None if nothing)."""
    if not opts.follow and opts.follow_distance is None:
        return None
    if not (opts.frames_every or opts.video or opts.gif):
        return "--follow sets the camera of rendered frames: add --frames-every K, --video or --gif"
    if opts.follow_distance is not None and not opts.follow_distance > 0:
        return f"--follow-distance must be > 0 m, got {opts.follow_distance}"
    from sandbox.model.strands import names_strand_of

    ropes = [r.name for r in level.scene.ropes]
    cloths = [c.name for c in level.scene.cloths]
    if not opts.follow:
        return "--follow-distance needs --follow ROPE[,ROPE...]"
    bad = [n for n in opts.follow if not names_strand_of(n, ropes, cloths)]
    if bad:
        return (f"--follow: {', '.join(map(repr, bad))} not a rope or a cloth line of {level.name}; ropes: "
                f"{', '.join(ropes) or '(none)'}; cloth lines: F.line1-F.line4 or F.P..Q of "
                f"{', '.join(cloths) or '(no cloth)'}")
    return None


def run_level(path: str | pathlib.Path, opts: RunOptions) -> tuple[int, dict]:
    """Run a level headless; returns (exit code, summary)."""
    from sandbox.levels import LevelError, load_level

    path = pathlib.Path(path)
    overrides = dict(opts.overrides or {})
    if opts.frames is not None:  # checked like the level's own count: its range and the steps limit
        overrides["sim.frames"] = int(opts.frames)
    try:
        level = load_level(path, overrides or None)
    except LevelError as exc:
        return EXIT_INVALID, {"status": "invalid", "errors": str(exc)}
    except FileNotFoundError as exc:
        return EXIT_INVALID, {"status": "invalid", "errors": str(exc)}
    problem = _follow_problem(level, opts)
    if problem:
        return EXIT_INVALID, {"status": "invalid", "errors": problem}

    out = pathlib.Path(opts.out)
    problem = _prepare_out(out, opts.overwrite)
    if problem:
        return EXIT_INVALID, {"status": "invalid", "errors": problem}
    summary: dict = {
        "level": level.name,
        "path": str(path),
        "status": "running",
        "success": False,
        "frames_planned": int(level.sim.frames),
        "frames_run": 0,
        "machine": {"python": platform.python_version(), "platform": platform.platform(),
                    "processor": platform.processor() or platform.machine()},
    }
    try:
        write_json_atomic(out / "summary.json", summary, reserve=SUMMARY_RESERVE)
        log = MetricsLog(out / "metrics.jsonl")
    except OSError as exc:
        return EXIT_INVALID, {"status": "invalid", "errors": f"--out {out}: cannot write there ({exc.strerror or exc})"}
    world = None
    recorder = None
    frame_ms: list[float] = []
    systems: dict[str, list[float]] = {}
    stages: dict[str, list[float]] = {}
    code = EXIT_ERROR
    signals = contextlib.ExitStack()  # stop signals are deferred from here to the last output written
    sigint = signals.enter_context(_deferred_sigint())
    try:
        from sandbox.api import Sandbox

        sim = Sandbox(level, base_dir=path.parent, arch=opts.arch)
        world = sim.world
        world.profile_every = opts.profile_every
        summary["arch"] = world.arch
        from sandbox import runtime  # Taichi is imported once the level and --out are known to be good

        summary["backend_reason"] = runtime.reason()  # auto: what the drivers reported (sandbox/backends.py)
        summary["fast_compile"] = runtime.fast_compile()  # frame times depend on it (docs/how-it-works.md, "Compile time")
        summary["particles"] = world.model.n
        summary["tier"] = world.tier
        coarse = {c.name: [c.nx, c.nz] for c in world.data.cloths if c.level_grid is not None}
        if coarse:
            summary["cloth_grids"] = coarse  # cloths the tier simulates on a coarser grid than the level's
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
        if sigint["stop"]:  # a stop signal while the level was being built
            raise KeyboardInterrupt
        _frames(sim, world, n, log, summary, recorder, bar, frame_ms, systems, stages, last_state, sigint)
        if bar is not None:
            bar.close()
        summary["status"] = "completed"
        code = EXIT_OK
    except KeyboardInterrupt:
        summary["status"] = "interrupted"
        how = sigint["stop"] or "SIGINT"
        summary["message"] = f"interrupted ({how}); outputs cover the frames run, state.npz the last of them"
        code = EXIT_INTERRUPTED
    except Exception as exc:  # reported in the summary, never lost
        from sandbox.world import SimulationUnstable

        summary["status"] = "unstable" if isinstance(exc, SimulationUnstable) else "error"
        if isinstance(exc, OSError) and exc.errno is not None:
            summary["message"] = f"an output could not be written: {exc.strerror} ({getattr(exc, 'filename', '')})"
        else:
            summary["message"] = f"{type(exc).__name__}: {exc}"
        if not isinstance(exc, (SimulationUnstable, OSError)):
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
    try:
        write_json_atomic(out / "summary.json", summary)
    except OSError as exc:  # a full disk: the final summary goes into the place the first one kept
        summary.pop("traceback", None)
        summary["output_error"] = f"summary.json written in place: {exc.strerror or exc}"
        try:
            write_json_in_place(out / "summary.json", summary)
        except OSError:
            pass
        if code == EXIT_OK or code == EXIT_CRITERIA:
            code = EXIT_ERROR
    signals.close()
    if world is not None:
        world.close()  # frees its field tree: a host process may run many levels
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
