"""``sandbox sweep``: runs levels under many perturbations and measures how often they pass.

Layout of ``--out DIR``::

    DIR/summary.md, summary.csv          one line per level: runs, pass rate, 95 % interval
    DIR/<level>/runs.csv                 one row per run, appended as runs finish
    DIR/<level>/report.json              pass rate, endings, failures and worst margin per criterion
    DIR/<level>/axes.png                 pass rate over each axis
    DIR/<level>/time_vs_margin.png       frame time against the worst criterion margin
    DIR/<level>/runs/<run>/              the run's own outputs: spec.json, summary.json,
                                         metrics.jsonl, state.npz, log.txt (frames with --frames-every)

Running the same command again runs only the runs without a row (and, with
``--retry-errors``, those that did not complete).
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import signal
import sys
import threading
import time
from collections.abc import Callable

from sandbox.sweep import backends, plan, report, table
from sandbox.sweep.execute import RunSpec, criterion_names, make_row

DEFAULT_TIMEOUT = 3600.0
"""Seconds a run may take before it is killed and recorded as ``timeout``."""


@dataclasses.dataclass
class SweepOptions:
    """How to run a sweep (see ``sandbox sweep --help``)."""

    out: pathlib.Path
    workers: int = 0  # 0: the machine's cores
    backend: str = "local"
    address: str | None = None
    shared: bool = False
    timeout: float | None = DEFAULT_TIMEOUT
    frames: int | None = None
    frames_every: int = 0
    threads: int = 0  # CPU threads per run; 0: one (loops in the launching thread, sandbox.runtime)
    retry_errors: bool = False
    progress: bool = True
    plots: bool = True


def cores() -> int:
    """CPU cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


@dataclasses.dataclass
class _Level:
    runs: list[plan.Run]
    header: list[str]
    criteria: list[str]
    folder: pathlib.Path


def prepare(levels: list[str | pathlib.Path], variants_of: Callable[[dict], list[tuple[str, plan.Variant]]],
            out: pathlib.Path, *, sweep_base: pathlib.Path | None = None, source: str = "<sweep>",
            frames: int | None = None) -> list[_Level]:
    """Every run of every level, resolved and checked; nothing runs if anything is wrong.

    Raises:
        SweepError: listing every problem of every level.
    """
    from sandbox.levels import load_level
    from sandbox.levels.issues import LevelIssue

    prepared: list[_Level] = []
    problems = []
    names: dict[str, str] = {}
    for path in levels:
        path = pathlib.Path(path)
        if not path.is_file():
            problems.append(LevelIssue(str(path), 0, 0, "", "level file not found"))
            continue
        try:
            level = load_level(path)
            data = plan.yamlio.parse(path.read_text(encoding="utf-8")).data
            runs = plan.resolve(path, variants_of(data), sweep_base=sweep_base, source=source, frames=frames)
        except plan.SweepError as exc:
            problems += exc.issues
            continue
        except ValueError as exc:  # LevelError: the level itself is invalid
            problems += getattr(exc, "errors", [LevelIssue(str(path), 0, 0, "", str(exc))])
            continue
        if level.name in names:
            problems.append(LevelIssue(str(path), 0, 0, "name", f"level name {level.name!r} is also the name of "
                                                                f"{names[level.name]}: one folder per level name"))
            continue
        names[level.name] = str(path)
        crit = criterion_names(level.success)
        columns = [table.criterion_column(n, c) for n, c in zip(crit, level.success)]
        axes: list[str] = []
        for r in runs:
            axes += [k for k in r.variant if k not in axes]
        prepared.append(_Level(runs, table.columns(axes, columns), columns, out / level.name))
    if problems:
        raise plan.SweepError(problems)
    return prepared


def run_sweep(levels: list[str | pathlib.Path], variants_of: Callable[[dict], list[tuple[str, plan.Variant]]],
              opts: SweepOptions, *, sweep_base: pathlib.Path | None = None, source: str = "<sweep>") -> int:
    """Run every variant of every level that has no row yet; write the tables and reports.

    Returns:
        0 when every run has a row, 130 when interrupted (the rows written
        stay; running the same sweep again goes on from there).

    Raises:
        SweepError: the sweep or a level is invalid (nothing has run).
        ValueError: ``out`` holds tables of another sweep.
    """
    out = pathlib.Path(opts.out).resolve()  # tasks on other nodes (--shared) get the full path
    prepared = prepare(levels, variants_of, out, sweep_base=sweep_base, source=source, frames=opts.frames)
    env = {k: os.environ[k] for k in ("SANDBOX_LIMITS", "SANDBOX_MESH_DIRS") if os.environ.get(k)}
    workers = opts.workers or cores()
    threads = opts.threads or 1
    tables = {}
    jobs = []
    skipped = 0
    try:
        for lv in prepared:
            tables[lv.folder.name] = t = table.Table(lv.folder / table.FILE, lv.header)
            _, rows = table.read(t.path)
            done = {str(r["run"]) for r in rows
                    if r["status"] != "interrupted" and not (opts.retry_errors and r["status"] != "completed")}
            for run in lv.runs:
                if run.id in done:
                    skipped += 1
                    continue
                run_env = dict(env)
                if run.mesh_dirs:
                    run_env["SANDBOX_MESH_DIRS"] = os.pathsep.join([*filter(None, [env.get("SANDBOX_MESH_DIRS")]),
                                                                    *run.mesh_dirs])
                spec = RunSpec(run.id, run.level, run.overrides, run.compile, threads, opts.frames,
                               opts.frames_every, opts.timeout, run_env)
                jobs.append(((lv, run), spec, lv.folder / "runs" / run.id))
        jobs = interleave(jobs)
        print(f"sweep: {len(jobs)} runs to go ({skipped} already done) over {len(prepared)} level(s), "
              f"{workers} worker(s), {threads} thread(s) per run, backend {opts.backend} -> {out}", file=sys.stderr)
        code = _drive(jobs, tables, workers, opts)
    finally:
        for t in tables.values():
            t.close()
    if any(report.level_folders(out)):
        for rep in report.write_reports(out, plots=opts.plots):
            rate = "-" if rep["pass_rate"] is None else f"{100 * rep['pass_rate']:.0f} %"
            lo, hi = rep["interval95"]
            print(f"{rep['level']}: {rep['passed']}/{rep['runs']} passed ({rate}, 95 % {100 * lo:.0f}-{100 * hi:.0f} %)"
                  + (f"; fails most: {rep['most_failed']} ({rep['most_failed_count']})" if rep["most_failed"] else ""))
        print(f"tables, reports and plots in {out}", file=sys.stderr)
    return code


def interleave(jobs: list) -> list:
    """Jobs in the order they run: each level's in a fixed shuffled order, the levels taking turns.

    A sweep stopped early (or still going) then holds about as many runs of
    every level, each a random draw from that level's set: its partial pass
    rates are unbiased, where the written order would cover the first
    placements of the first level only. The shuffle is seeded by the run
    ids, so the same sweep always runs in the same order.
    """
    import random

    by_level: dict[str, list] = {}
    for job in jobs:
        by_level.setdefault(job[0][0].folder.name, []).append(job)
    queues = []
    for name, items in by_level.items():
        items = sorted(items, key=lambda j: j[0][1].id)
        random.Random(name).shuffle(items)
        queues.append(items)
    out = []
    while any(queues):
        for q in queues:
            if q:
                out.append(q.pop(0))
    return out


def _drive(jobs, tables, workers: int, opts: SweepOptions) -> int:
    if not jobs:
        return 0
    bar = None
    if opts.progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), desc="sweep", unit="run", disable=None)
    passed = failed = 0
    old_term = None
    if threading.current_thread() is threading.main_thread():
        def on_term(signum, frame):
            raise KeyboardInterrupt

        old_term = signal.signal(signal.SIGTERM, on_term)
    if opts.backend == "ray":
        results = backends.run_ray(jobs, workers, address=opts.address, shared=opts.shared)
    else:
        results = backends.run_local(jobs, workers)
    t0 = time.perf_counter()
    try:
        for (lv, run), result, files in results:
            folder = lv.folder / "runs" / run.id
            if files is not None:
                _write_files(folder, files)
            row = make_row(run, result, lv.criteria, backend=opts.backend)
            tables[lv.folder.name].append(row)
            if row["success"]:
                passed += 1
            else:
                failed += 1
            if bar is not None:
                bar.set_postfix_str(f"passed {passed}, failed {failed}")
                bar.update(1)
        return 0
    except KeyboardInterrupt:
        print(f"\nsweep interrupted after {time.perf_counter() - t0:.0f} s: {passed + failed} rows written; "
              "run the same command again to go on", file=sys.stderr)
        return 130
    finally:
        results.close()
        if bar is not None:
            bar.close()
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)


def _write_files(folder: pathlib.Path, files: dict[str, bytes]) -> None:
    import shutil

    if folder.exists():
        shutil.rmtree(folder)
    for rel, data in files.items():
        path = folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
