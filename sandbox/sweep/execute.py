"""One run of a sweep, in a process of its own, and the table row it gives.

Each run is a fresh Python process (``python -m sandbox.sweep.worker``) with
its own Taichi runtime; the kernel cache on disk is shared, so only the
first run of a level and compile mode compiles. A process per run is what
makes a sweep lose nothing: a run that crashes (even a segfault), is killed
or passes its time limit ends that process alone, and the row says how it
ended. The same function runs every run, whichever backend calls it, so
rows and states do not depend on the backend.
"""

from __future__ import annotations

import ctypes
import dataclasses
import json
import os
import pathlib
import platform
import shutil
import signal
import subprocess
import sys
import threading
import time
from typing import Any

STATUSES = ("completed", "invalid", "unstable", "error", "interrupted", "crashed", "timeout", "lost")
"""How a run ended: the runner's own statuses, and ``crashed`` (the process died without a
final summary), ``timeout`` (killed at the per-run time limit), ``lost`` (its worker or
node went away)."""

OUTPUT_FILES = ("spec.json", "summary.json", "metrics.jsonl", "state.npz", "log.txt")
"""What every run leaves in its folder (frames too, with ``frames_every``)."""


@dataclasses.dataclass
class RunSpec:
    """Everything a run needs, written to ``spec.json`` in its folder.

    Attributes:
        id: the run's id (``plan.run_id``).
        level: absolute path of the level file.
        overrides: dotted level keys -> values.
        compile: ``full`` or ``fast`` (``SANDBOX_FAST_COMPILE``).
        threads: CPU threads of the run's Taichi runtime (``SANDBOX_THREADS``).
        frames: frames to run (None: the level's own).
        frames_every: write a PNG every k frames (0: none).
        timeout: seconds before the run is killed (None: no limit).
        env: environment the run needs wherever it runs (``SANDBOX_LIMITS``, ``SANDBOX_MESH_DIRS``).
    """

    id: str
    level: str
    overrides: dict
    compile: str = "full"
    threads: int = 1
    frames: int | None = None
    frames_every: int = 0
    timeout: float | None = None
    env: dict = dataclasses.field(default_factory=dict)


def criterion_names(criteria) -> list[str]:
    """Column names of a level's success criteria: ``metric`` or ``metric(of)``, numbered if repeated."""
    names: list[str] = []
    for c in criteria:
        of = c.targets() if hasattr(c, "targets") else ([c["of"]] if isinstance(c.get("of"), str) else c.get("of") or [])
        metric = c.metric if hasattr(c, "metric") else c["metric"]
        name = f"{metric}({','.join(of)})" if of else metric
        base, k = name, 2
        while name in names:
            name, k = f"{base}#{k}", k + 1
        names.append(name)
    return names


_LIVE: set[subprocess.Popen] = set()
_LIVE_LOCK = threading.Lock()
_STOPPING = threading.Event()


def kill_all() -> None:
    """Kill the process groups of every run still going, and start no more (on Ctrl-C of the sweep)."""
    _STOPPING.set()
    with _LIVE_LOCK:
        procs = list(_LIVE)
    for p in procs:
        _kill(p)


def allow_runs() -> None:
    """Let runs start again (a new sweep in the same process)."""
    _STOPPING.clear()


def _kill(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def die_with_parent() -> None:
    """Have this process killed when the process that started it dies (Linux), so no run outlives its sweep.

    Called first thing in a run's process; ``SANDBOX_SWEEP_PARENT`` holds the
    pid that started it, for the case that it died before this call.
    """
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    parent = os.environ.get("SANDBOX_SWEEP_PARENT")
    if parent and os.getppid() != int(parent):
        os._exit(137)


def execute(spec: RunSpec, out: pathlib.Path) -> dict[str, Any]:
    """Run ``spec`` in a new process writing into ``out``; returns how it ended.

    ``out`` is emptied first, so that nothing from an earlier attempt is read
    as this run's. Returns a dict with ``status``, ``exit_code``,
    ``wall_s``, ``summary`` (the run's summary.json, or None) and ``error``
    (text, empty when the run completed).
    """
    out = pathlib.Path(out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / "spec.json").write_text(json.dumps(dataclasses.asdict(spec), indent=1))
    env = dict(os.environ)
    env["SANDBOX_FAST_COMPILE"] = "1" if spec.compile == "fast" else "0"
    env["SANDBOX_THREADS"] = str(int(spec.threads))
    env["PYTHONUNBUFFERED"] = "1"
    env["SANDBOX_SWEEP_PARENT"] = str(os.getpid())
    env.update({k: str(v) for k, v in spec.env.items()})
    t0 = time.perf_counter()
    status = None
    if _STOPPING.is_set():
        return {"status": "interrupted", "exit_code": None, "wall_s": 0.0, "summary": None,
                "error": "the sweep stopped before this run started"}
    with open(out / "log.txt", "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "sandbox.sweep.worker", str(out)], stdout=log, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, env=env, start_new_session=True,
        )
        with _LIVE_LOCK:
            _LIVE.add(proc)
            if _STOPPING.is_set():  # kill_all ran while this run was starting
                _kill(proc)
        try:
            code = proc.wait(timeout=spec.timeout)
        except subprocess.TimeoutExpired:
            _kill(proc)
            code = proc.wait()
            status = "timeout"
        finally:
            with _LIVE_LOCK:
                _LIVE.discard(proc)
    wall = time.perf_counter() - t0
    summary = None
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        pass
    if status is None:
        if summary is None or summary.get("status") == "running":
            status = "crashed"
        else:
            status = summary.get("status", "crashed")
    error = ""
    if status == "timeout":
        error = f"killed after the per-run limit of {spec.timeout:g} s"
    elif status == "crashed":
        how = f"signal {-code}" if code < 0 else f"exit code {code}"
        error = f"the run's process ended ({how}) without a final summary; log: {_tail(out / 'log.txt')}"
    elif summary is not None and status != "completed":
        error = summary.get("message") or summary.get("errors") or ""
    return {"status": status, "exit_code": code, "wall_s": wall, "summary": summary, "error": str(error)}


def _tail(path: pathlib.Path, n: int = 600) -> str:
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return "(none)"
    return " ".join(text[-n:].split()) or "(empty)"


def make_row(run, result: dict[str, Any], criteria: list[str], *, backend: str) -> dict[str, Any]:
    """The table row of a finished run.

    Args:
        run: the ``plan.Run``.
        result: what ``execute`` returned.
        criteria: the level's criterion columns, in the order of its ``success`` list.
        backend: the backend that ran it.
    """
    summary = result.get("summary") or {}
    row: dict[str, Any] = {
        "run": run.id, "level": run.level_name, "level_sha": run.level_sha, "variant": run.label,
        **{key: value for key, value in run.variant.items()},
        "status": result["status"], "exit_code": result["exit_code"],
        "success": bool(summary.get("success", False)) and result["status"] == "completed",
    }
    got = summary.get("criteria") or []
    for k, name in enumerate(criteria):
        c = got[k] if k < len(got) else None
        row[f"value:{name}"] = None if c is None else c.get("value")
        row[f"ok:{name}"] = None if c is None else bool(c.get("ok"))
    fm = summary.get("frame_ms") or {}
    row.update({
        "frame_ms_p50": fm.get("p50"), "wall_s": round(float(result["wall_s"]), 3),
        "frames_run": summary.get("frames_run"), "error": result.get("error", ""),
        "backend": backend, "host": platform.node(),
    })
    return row
