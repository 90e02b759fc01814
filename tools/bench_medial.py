"""Benchmark: one medial-sheet pass (sandbox/collision/medial.py) on a 163 x 163 cloth, lines 1 and 3,
and one count of cloth through cloth (sandbox/collision/interpenetration.py).

    python tools/bench_medial.py [--n 163] [--repeats 20] [--arch cpu]

Times one pass (hash of the segments, then every free particle checked and
moved where it crossed) on three states of the cloth: flat at rest (nothing to
move), folded in waves and squeezed to 30 % of its width, and squeezed to 5 %
(the two lines' cloth pressed together, most particles within reach of both
lines). Also the paper's rule by brute force in NumPy on the same state, the
count of structural edges through the cloth's own triangles on each state, and
the calibration workload, all in one process. Median of ``--repeats`` after
warm-up, ``ti.sync()`` before every stop.
"""

import argparse
import pathlib
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from sandbox import runtime  # noqa: E402
from sandbox.bench import calibrate, machine  # noqa: E402

LEVEL = """
version: 1
name: medial_bench
scene:
  gravity: [0, 0, 0]
  cloths:
    - {{name: c, resolution: [{n}, {n}], size: [1.6, 1.6], center: [0, 0.5, 0], self_collision: false,
        medial_sheet: [1, 3]}}
fsm:
  - {{run: Wait}}
success:
  - {{metric: fsm_state, equals: success}}
"""


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--n", type=int, default=163)
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--arch", default="cpu")
    a = p.parse_args()
    runtime.init(a.arch)
    import taichi as ti

    from sandbox.api import Sandbox
    from sandbox.collision.medial_np import pass_brute

    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "medial_bench.yaml"
        path.write_text(LEVEL.format(n=a.n))
        w = Sandbox.from_level(path).world
    from sandbox.collision.interpenetration import ClothCrossings

    ms = w.solver.medial[0]
    crossings = ClothCrossings(w.state, w.cloths["c"])
    x0 = w.data.x0
    calib = calibrate()
    print(f"{a.n} x {a.n} cloth, {ms.n_free} free particles, {ms.n_seg} segments; reach {ms.reach * 1e3:.1f} mm, "
          f"step {ms.step * 1e3:.2f} mm; calibration {calib:.1f} ms; {machine()['processor']}")
    w_np = np.full(len(x0), 1.0, np.float32)
    for label, squeeze in (("flat", None), ("folded, 30 % wide", 0.3), ("folded, 5 % wide", 0.05)):
        x = x0.copy()
        if squeeze is not None:
            x[:, 1] += 0.02 * np.sin(40.0 * x[:, 0])
            x[:, 0] *= squeeze
        x = x.astype(np.float32)
        times = []
        for k in range(a.repeats + 2):
            w.state.x.from_numpy(x)
            w.solver.w.from_numpy(w_np)
            ti.sync()
            t0 = time.perf_counter()
            moved = ms.run_pass()
            ti.sync()
            if k >= 2:
                times.append(1e3 * (time.perf_counter() - t0))
        w.state.x.from_numpy(x)
        crossings.count()
        t_cross = []
        for _ in range(5):
            t0 = time.perf_counter()
            n_cross = crossings.count()
            t_cross.append(1e3 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        _, wrong = pass_brute(x.astype(np.float64), ms.free_np, ms.own_np, *ms.seg_np, ms.step, ms.reach)
        t_np = 1e3 * (time.perf_counter() - t0)
        print(f"{label:20s} pass {np.median(times):6.2f} ms (x{np.median(times) / calib:.2f} calibration), "
              f"moved {moved} (NumPy brute force: {int(wrong.sum())} in {t_np:.0f} ms); "
              f"cloth through cloth {np.median(t_cross):.1f} ms ({n_cross} edges)")


if __name__ == "__main__":
    main()
