"""Soak: each level stepped for many frames (its FSM, then the scene left to itself), memory watched.

A level must come through 10,000 frames with no NaN, no instability that a
retry did not recover, and flat memory. Prints one line per level and
writes JSON with ``--out``.

Usage: python tools/soak.py [LEVEL...] [--frames 10000] [--out soak.json]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def rss_mb() -> float:
    """Resident memory of this process (MB)."""
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    import os

    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def soak(level: str | pathlib.Path, frames: int = 10_000, *, sample_every: int = 250) -> dict:
    """Step ``level`` for ``frames`` frames; NaN count, retries, instabilities and memory over time.

    Memory growth is the slope (MB per 1000 frames) of resident memory over
    the second half of the run, after kernels and caches have settled.
    """
    from sandbox.api import Sandbox
    from sandbox.world import SimulationUnstable

    sim = Sandbox.from_level(level, arch="cpu")
    out = {"level": sim.world.level.name, "frames": 0, "nan_frames": 0, "retries": 0, "unstable": None,
           "rss_mb": [], "fsm_finished_at": None}
    t0 = time.perf_counter()
    try:
        for f in range(frames):
            try:
                row = sim.step()
            except SimulationUnstable as exc:
                out["unstable"] = f"frame {f}: {exc}"
                break
            out["frames"] = f + 1
            out["retries"] += int(row.get("retries", 0))
            if not np.isfinite(row.get("max_speed", 0.0)):
                out["nan_frames"] += 1
            if out["fsm_finished_at"] is None and sim.finished:
                out["fsm_finished_at"] = f + 1
            if f % sample_every == 0:
                out["rss_mb"].append((f, round(rss_mb(), 1)))
        x = sim.world.positions()
        out["finite_at_end"] = bool(np.isfinite(x).all())
    finally:
        sim.close()
    out["seconds"] = round(time.perf_counter() - t0, 1)
    half = [(f, m) for f, m in out["rss_mb"] if f >= frames // 2]
    out["rss_slope_mb_per_1000_frames"] = (float(np.polyfit([f for f, _ in half], [m for _, m in half], 1)[0] * 1000)
                                           if len(half) >= 3 else None)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("levels", nargs="*")
    p.add_argument("--frames", type=int, default=10_000)
    p.add_argument("--out", help="write the results as JSON")
    a = p.parse_args(argv)
    from sandbox import runtime

    runtime.init("cpu")
    root = pathlib.Path(__file__).resolve().parents[1]
    levels = a.levels or sorted(str(x) for x in (root / "levels").glob("*.yaml"))
    results, bad = [], 0
    for level in levels:
        r = soak(level, a.frames)
        results.append(r)
        ok = r["unstable"] is None and r["nan_frames"] == 0 and r["finite_at_end"]
        bad += not ok
        print(f"{r['level']:>18}: {r['frames']} frames in {r['seconds']} s, retries {r['retries']}, "
              f"NaN frames {r['nan_frames']}, memory {r['rss_mb'][-1][1] if r['rss_mb'] else '-'} MB "
              f"(slope {r['rss_slope_mb_per_1000_frames']} MB/1000 frames), {'ok' if ok else r['unstable']}")
    if a.out:
        pathlib.Path(a.out).write_text(json.dumps(results, indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
