"""Load and close a level over and over and watch resident memory: a host that reloads levels must not leak.

Usage: python tools/leak_cycles.py [LEVEL] [--cycles 200] [--warmup 20] [--steps 1] [--no-release]
Prints MB per cycle after the warm-up (the slope of resident memory) for
load-and-close cycles with that many steps each. Each cycle ends with
``sandbox.runtime.release()``, as a host that loads many levels does;
``--no-release`` leaves Taichi's kernels of every closed world in memory.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from soak import rss_mb  # noqa: E402


def cycles(level: str | pathlib.Path, n: int = 200, *, warmup: int = 20, steps: int = 1,
           release: bool = True) -> dict:
    """Resident memory after each of ``n`` load, ``steps`` frames, close (and release) cycles; the slope
    past ``warmup`` and the mean seconds per cycle."""
    import gc
    import time

    from sandbox import runtime
    from sandbox.api import Sandbox

    mem = []
    t0 = time.perf_counter()
    for _ in range(n):
        sim = Sandbox.from_level(level, arch="cpu")
        for _ in range(steps):
            sim.step()
        sim.close()
        del sim
        if release:
            runtime.release()
        gc.collect()
        mem.append(rss_mb())
    seconds = (time.perf_counter() - t0) / n
    after = np.asarray(mem[warmup:])
    slope = float(np.polyfit(np.arange(len(after)), after, 1)[0]) if len(after) >= 3 else None
    return {"level": str(level), "cycles": n, "steps": steps, "warmup": warmup, "rss_mb_first": mem[0],
            "rss_mb_last": mem[-1], "mb_per_cycle": slope, "release": release, "seconds_per_cycle": seconds}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    root = pathlib.Path(__file__).resolve().parents[1]
    p.add_argument("level", nargs="?", default=str(root / "tests" / "data" / "levels" / "engine_small.yaml"))
    p.add_argument("--cycles", type=int, default=200)
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--steps", type=int, default=1)
    p.add_argument("--no-release", action="store_true", help="keep the runtime between cycles")
    a = p.parse_args(argv)
    from sandbox import runtime

    runtime.init("cpu")
    r = cycles(a.level, a.cycles, warmup=a.warmup, steps=a.steps, release=not a.no_release)
    what = "close, release" if r["release"] else "close"
    print(f"{r['cycles']} cycles of load, {r['steps']} step(s), {what}: {r['rss_mb_first']:.0f} -> "
          f"{r['rss_mb_last']:.0f} MB; {r['mb_per_cycle']:.3f} MB per cycle after {r['warmup']}; "
          f"{r['seconds_per_cycle']:.2f} s per cycle")
    return 0


if __name__ == "__main__":
    sys.exit(main())
