"""Time one chain pass (every row and column of a 163 x 163 cloth, rope_chain.py) on this machine.

Usage: python tools/bench_chains.py [--level levels/wrap_bottle.yaml] [--calls 300]
Prints ms per pass (median of 5 blocks, JIT warm-up excluded) next to a
calibration workload timed in the same process (a NumPy matrix product),
so that runs on a shared machine can be compared as ratios.
"""

import argparse
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def main() -> None:
    from sandbox import runtime
    from tests.levelkit import world_from_text

    p = argparse.ArgumentParser()
    p.add_argument("--level", default="levels/wrap_bottle.yaml")
    p.add_argument("--calls", type=int, default=300)
    a = p.parse_args()
    runtime.init("cpu")
    import taichi as ti

    w = world_from_text(pathlib.Path(a.level).read_text())
    for _ in range(3):
        w.step()
    chains = w.solver.inext
    x = w.state.x.to_numpy()
    chains.solve()
    ti.sync()
    blocks = []
    for _ in range(5):
        w.state.x.from_numpy(x)
        t = time.perf_counter()
        for _ in range(a.calls // 5):
            chains.solve()
        ti.sync()
        blocks.append((time.perf_counter() - t) / (a.calls // 5) * 1e3)
    m = np.random.default_rng(0).normal(size=(300, 300))
    t = time.perf_counter()
    for _ in range(20):
        m = m @ m
        m /= np.abs(m).max()
    calib = (time.perf_counter() - t) / 20 * 1e3
    ms = float(np.median(blocks))
    print(f"chain pass {ms:.3f} ms ({chains.n_links} rods), calibration {calib:.3f} ms, ratio {ms / calib:.2f}")


if __name__ == "__main__":
    main()
