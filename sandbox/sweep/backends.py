"""Who runs a sweep's runs: ``local`` (a pool of this machine's cores) or ``ray`` (a Ray cluster).

Both call ``execute.execute`` on the same ``RunSpec``s, so they make the same
runs; each yields ``(key, result, files)`` as runs finish, ``files`` being
the run's outputs (relative path -> bytes) when they were made somewhere
the driver cannot see, else None.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import pathlib
import shutil
import tempfile
from collections.abc import Iterator
from typing import Any

from sandbox.sweep.execute import RunSpec, allow_runs, execute, kill_all

BACKENDS = ("local", "ray")


def _guarded(spec: RunSpec, out: pathlib.Path) -> dict:
    """``execute``, with a failure to start or to read back the run (a full disk, say) as an error result."""
    try:
        return execute(spec, out)
    except Exception as exc:
        return {"status": "error", "exit_code": None, "wall_s": 0.0, "summary": None,
                "error": f"the run could not be started or read back: {type(exc).__name__}: {exc}"}


def run_local(jobs: list[tuple[Any, RunSpec, pathlib.Path]], workers: int) -> Iterator[tuple[Any, dict, None]]:
    """Runs ``(key, spec, out)`` jobs, ``workers`` at a time, each in a process of its own.

    Closing the generator early (Ctrl-C) kills the runs still going and
    starts no more.
    """
    allow_runs()
    pool = cf.ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="sweep")
    futures = {pool.submit(_guarded, spec, out): key for key, spec, out in jobs}
    try:
        for fut in cf.as_completed(futures):
            yield futures[fut], fut.result(), None
    finally:
        for fut in futures:
            fut.cancel()
        kill_all()
        pool.shutdown(wait=True, cancel_futures=True)


def _ray_task(spec: dict, shared_out: str | None) -> tuple[dict, dict[str, bytes] | None]:
    """A run as a Ray task: into ``shared_out`` (a path all nodes see), or a temporary folder returned whole."""
    spec_ = RunSpec(**spec)
    if shared_out is not None:
        return _guarded(spec_, pathlib.Path(shared_out)), None
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="sandbox-run-"))
    try:
        result = _guarded(spec_, tmp / "run")
        files = {str(p.relative_to(tmp / "run")): p.read_bytes()
                 for p in sorted((tmp / "run").rglob("*")) if p.is_file()}
        return result, files
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run_ray(jobs: list[tuple[Any, RunSpec, pathlib.Path]], workers: int, *, address: str | None = None,
            shared: bool = False) -> Iterator[tuple[Any, dict, dict[str, bytes] | None]]:
    """Runs the jobs as Ray tasks (one CPU each, never retried: a lost worker is a ``lost`` row).

    Args:
        jobs: ``(key, spec, out)``.
        workers: CPUs of the Ray instance started here when ``address`` is None.
        address: an existing cluster (``ray://host:10001`` or ``auto``); None
            starts a local instance.
        shared: ``out`` folders are on a file system that every node sees:
            tasks write there; otherwise each task returns its files.

    Raises:
        ImportError: Ray is not installed (``pip install -e '.[cluster]'``).
    """
    try:
        import ray
    except ImportError as exc:
        raise ImportError("the ray backend needs Ray: pip install -e '.[cluster]'") from exc
    started = not ray.is_initialized()
    if started:
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
        if address is None:
            kwargs["num_cpus"] = max(1, workers)
        ray.init(address=address, **kwargs)
    task = ray.remote(num_cpus=1, max_retries=0)(_ray_task)
    pending = {task.remote(dataclasses.asdict(spec), str(out) if shared else None): key for key, spec, out in jobs}
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            ref = done[0]
            key = pending.pop(ref)
            try:
                result, files = ray.get(ref)
            except Exception as exc:  # the worker or its node went away: one row lost, not the sweep
                result, files = {"status": "lost", "exit_code": None, "wall_s": 0.0, "summary": None,
                                 "error": f"{type(exc).__name__}: {' '.join(str(exc).split())[:600]}"}, None
            yield key, result, files
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()
