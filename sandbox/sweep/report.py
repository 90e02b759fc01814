"""Reports of a sweep, from its tables alone: pass rates with Wilson intervals, failing criteria, plots.

For each level folder ``DIR/<level>/`` holding ``runs.csv``, writes
``report.json`` (pass rate, interval, how runs ended, failures and worst
margin per criterion), ``axes.png`` (pass rate over each axis) and
``time_vs_margin.png`` (frame time against the worst criterion margin); and
for the whole sweep ``DIR/summary.csv`` and ``DIR/summary.md``, one line
per level.

A criterion's margin is its distance to the bar as a fraction of the bar:
``(max - value) / |max|`` for ``<= max``, ``(value - min) / |min|`` for
``>= min``, the smaller of the two for a range, ``-|value - v| / |v|`` for
``= v`` (numbers); positive when it holds. A named value (``= square``)
has no margin, only a pass or a fail.
"""

from __future__ import annotations

import json
import math
import pathlib
import platform
import re
from collections import Counter
from typing import Any

from sandbox.sweep import table

Z95 = 1.959963984540054
"""Standard normal quantile for a two-sided 95 % interval."""

_BAR = re.compile(r"^(?P<name>.+?) (?:(?P<op><=|>=|=) (?P<v>.+)|in \[(?P<lo>[^,]+), (?P<hi>[^\]]+)\])$")


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a proportion k/n (0..1); (0, 1) when n = 0."""
    if n <= 0:
        return 0.0, 1.0
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    lo = 0.0 if k == 0 else max(0.0, centre - half)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi


def _num(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _rel(d: float, bar: float) -> float:
    return d / abs(bar) if bar != 0 else d


def margin(column: str, value: Any) -> float | None:
    """Relative margin of ``value`` to the bar written in a criterion column (None: no margin)."""
    m = _BAR.match(column)
    v = _num(value)
    if m is None or v is None:
        return None
    if m["lo"] is not None:
        lo, hi = float(m["lo"]), float(m["hi"])
        return min(_rel(v - lo, lo), _rel(hi - v, hi))
    bar = _num(m["v"])
    if bar is None:
        return None
    if m["op"] == "<=":
        return _rel(bar - v, bar)
    if m["op"] == ">=":
        return _rel(v - bar, bar)
    return -_rel(abs(v - bar), bar)


def _criteria(header: list[str]) -> list[str]:
    return [c[len("value:"):] for c in header if c.startswith("value:")]


def _axes(header: list[str]) -> list[str]:
    crit = {c for c in header if c.startswith(("value:", "ok:"))}
    fixed = {*table.FIRST, *table.OUTCOME, *table.LAST}
    return [c for c in header if c not in fixed and c not in crit]


NOT_OUTCOMES = ("interrupted", "lost")
"""Endings that say nothing of the level (the sweep stopped, a node went away): kept out of the pass rate."""


def current_rows(rows: list[dict]) -> tuple[list[dict], dict[str, int]]:
    """The rows that measure the level as it is now: of its latest content (``level_sha`` of the last row
    written) and with an outcome; and how many were set aside, by reason."""
    if not rows:
        return [], {}
    sha = rows[-1].get("level_sha")
    aside = {"older level": sum(1 for r in rows if r.get("level_sha") != sha)}
    rows = [r for r in rows if r.get("level_sha") == sha]
    for status in NOT_OUTCOMES:
        aside[status] = sum(1 for r in rows if r.get("status") == status)
    return [r for r in rows if r.get("status") not in NOT_OUTCOMES], {k: v for k, v in aside.items() if v}


def level_report(header: list[str], rows: list[dict]) -> dict[str, Any]:
    """Pass rate, interval, endings, and per criterion its failures and worst margin (of ``current_rows``)."""
    rows, aside = current_rows(rows)
    n = len(rows)
    passed = sum(1 for r in rows if r.get("success") is True)
    lo, hi = wilson(passed, n)
    crits = {}
    for c in _criteria(header):
        fails = sum(1 for r in rows if r.get(f"ok:{c}") is False)
        margins = [m for r in rows if (m := margin(c, r.get(f"value:{c}"))) is not None]
        crits[c] = {"failed": fails, "evaluated": sum(1 for r in rows if r.get(f"ok:{c}") is not None),
                    "worst_margin": min(margins) if margins else None}
    worst = max(crits.items(), key=lambda kv: kv[1]["failed"], default=None)
    frame = sorted(v for r in rows if (v := _num(r.get("frame_ms_p50"))) is not None)
    levels = sorted({str(r.get("level")) for r in rows})
    return {
        "level": levels[0] if len(levels) == 1 else ", ".join(levels),
        "runs": n, "passed": passed, "pass_rate": passed / n if n else None, "interval95": [lo, hi],
        "set_aside": aside,
        "status": dict(Counter(str(r.get("status")) for r in rows)),
        "criteria": crits,
        "most_failed": worst[0] if worst and worst[1]["failed"] else None,
        "most_failed_count": worst[1]["failed"] if worst else 0,
        "frame_ms_p50_median": frame[len(frame) // 2] if frame else None,
        "errors": [{"variant": r.get("variant"), "status": r.get("status"), "error": r.get("error")}
                   for r in rows if r.get("status") != "completed"],
    }


def _label(v: Any) -> str:
    if v is None:
        return "as shipped"
    return v if isinstance(v, str) else json.dumps(v)


def plot_level(folder: pathlib.Path, header: list[str], rows: list[dict], title: str) -> list[str]:
    """Write ``axes.png`` and ``time_vs_margin.png`` into ``folder``; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    axes = [a for a in _axes(header) if len({_label(r.get(a)) for r in rows}) > 1]
    if axes:
        fig, subs = plt.subplots(len(axes), 1, figsize=(8, 2.2 * len(axes) + 0.6), squeeze=False)
        for ax, key in zip(subs[:, 0], axes):
            groups: dict[str, list[bool]] = {}
            for r in rows:
                groups.setdefault(_label(r.get(key)), []).append(r.get("success") is True)
            names = list(groups)
            rates = [sum(g) / len(g) for g in groups.values()]
            ints = [wilson(sum(g), len(g)) for g in groups.values()]
            err = [[max(0.0, r - i[0]) for r, i in zip(rates, ints)], [max(0.0, i[1] - r) for r, i in zip(rates, ints)]]
            ax.bar(range(len(names)), rates, yerr=err, color="#4c72b0", capsize=3)
            for x, g in enumerate(groups.values()):
                ax.text(x, 0.03, f"{sum(g)}/{len(g)}", ha="center", va="bottom", fontsize=7, color="white")
            ax.set_xticks(range(len(names)), names, fontsize=7, rotation=15)
            ax.set_ylim(0, 1.05)
            ax.set_ylabel("pass rate")
            ax.set_title(key, fontsize=9)
        fig.suptitle(f"{title}: pass rate over each axis (95 % Wilson intervals)", fontsize=10)
        fig.tight_layout()
        fig.savefig(folder / "axes.png", dpi=110)
        plt.close(fig)
        written.append("axes.png")
    crits = _criteria(header)
    pts = []
    for r in rows:
        t = _num(r.get("frame_ms_p50"))
        ms = [m for c in crits if (m := margin(c, r.get(f"value:{c}"))) is not None]
        if t is None or not ms:
            continue
        named_fail = any(r.get(f"ok:{c}") is False and margin(c, r.get(f"value:{c}")) is None for c in crits)
        pts.append((t, min(ms), r.get("success") is True, named_fail))
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for ok, named, color, marker, label in ((True, False, "#2a9d4a", "o", "passed"),
                                            (False, False, "#c0392b", "o", "failed a bar"),
                                            (False, True, "#c0392b", "x", "failed a named value")):
        sel = [(t, m) for t, m, o, nf in pts if o == ok and (nf == named or ok)]
        if sel:
            ax.scatter([m for _, m in sel], [t for t, _ in sel], c=color, marker=marker, label=label, s=22)
    ax.axvline(0.0, color="0.4", lw=0.8, ls="--")
    ax.set_xlabel("worst criterion margin (fraction of its bar; < 0 fails)")
    ax.set_ylabel("frame time p50 (ms)")
    ax.set_title(f"{title}: {len(pts)} of {len(rows)} runs with a frame time and a margin", fontsize=10)
    if pts:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(folder / "time_vs_margin.png", dpi=110)
    plt.close(fig)
    written.append("time_vs_margin.png")
    return written


def plot_summary(path: pathlib.Path, reports: list[dict[str, Any]]) -> None:
    """Pass rate of every level with its 95 % interval, one bar per level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 0.38 * len(reports) + 1.2))
    ys = range(len(reports))
    rates = [r["pass_rate"] or 0.0 for r in reports]
    lo = [max(0.0, rate - r["interval95"][0]) for rate, r in zip(rates, reports)]
    hi = [max(0.0, r["interval95"][1] - rate) for rate, r in zip(rates, reports)]
    ax.barh(ys, rates, xerr=[lo, hi], color="#4c72b0", capsize=3)
    for y, r in zip(ys, reports):
        ax.text(1.02, y, f"{r['passed']}/{r['runs']}", va="center", fontsize=8)
    ax.set_yticks(list(ys), [r["level"] for r in reports], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, 1.12)
    ax.set_xlabel("pass rate (95 % Wilson interval)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def machine_name() -> str:
    """This machine in words: host, CPU model and cores."""
    model = platform.processor() or platform.machine()
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    from sandbox.sweep.driver import cores

    return f"{platform.node()} ({model}, {cores()} cores, {platform.system()})"


def level_folders(out: pathlib.Path) -> list[pathlib.Path]:
    """Folders of ``out`` that hold a level's table."""
    return sorted(p.parent for p in pathlib.Path(out).glob(f"*/{table.FILE}"))


def write_reports(out: pathlib.Path, *, plots: bool = True) -> list[dict[str, Any]]:
    """(Re)write every level's report and plots and the sweep's summary from the tables in ``out``.

    Raises:
        FileNotFoundError: ``out`` holds no table.
    """
    out = pathlib.Path(out)
    folders = level_folders(out)
    if not folders:
        raise FileNotFoundError(f"{out} holds no sweep table (no */{table.FILE}); is it a sweep's --out folder?")
    reports = []
    for folder in folders:
        header, rows = table.read(folder / table.FILE)
        rep = level_report(header, rows)
        rows = current_rows(rows)[0]
        rep["folder"] = folder.name
        rep["level"] = rep["level"] or folder.name
        if plots and rows:
            rep["plots"] = plot_level(folder, header, rows, rep["level"])
        (folder / "report.json").write_text(json.dumps(rep, indent=1))
        reports.append(rep)
    hosts = sorted({str(r.get("host")) for folder in folders for r in table.read(folder / table.FILE)[1]})
    machine = f"run on {', '.join(hosts)}; reported on {machine_name()}"
    lines = ["| level | runs | passed | pass rate | 95 % interval | fails most (runs) | did not finish |",
             "|---|---|---|---|---|---|---|"]
    csv_rows = []
    for rep in reports:
        rate = rep["pass_rate"]
        lo, hi = rep["interval95"]
        dnf = rep["runs"] - rep["status"].get("completed", 0)
        most = f"`{rep['most_failed']}` ({rep['most_failed_count']})" if rep["most_failed"] else "-"
        lines.append(f"| `{rep['level']}` | {rep['runs']} | {rep['passed']} | "
                     f"{'-' if rate is None else f'{100 * rate:.0f} %'} | {100 * lo:.0f}-{100 * hi:.0f} % | "
                     f"{most} | {dnf} |")
        csv_rows.append([rep["level"], rep["runs"], rep["passed"], rate, lo, hi, rep["most_failed"] or "",
                         rep["most_failed_count"], dnf])
    (out / "summary.md").write_text("\n".join(lines) + f"\n\nRuns {machine}.\n")
    if plots:
        plot_summary(out / "summary.png", reports)
    import csv

    with open(out / "summary.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["level", "runs", "passed", "pass_rate", "lo95", "hi95", "most_failed", "most_failed_runs",
                    "did_not_finish"])
        w.writerows(csv_rows)
    return reports
