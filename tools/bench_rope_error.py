"""Benchmark: run time against error for the rope solvers on the winding level.

A state in the middle of ``rope_wind`` (C half wound around T, one particle
driven) is taken once; from it, each solver configuration advances the same
``--frames`` frames with the driven target fixed and the FSM off:

- XPBD (the engine's path) over a sweep of substeps x iterations;
- the paper's projection (Eq. 6-8, SciPy sparse solve) with 1-3 Gauss-Newton
  iterations per projection.

Error of a run: (a) the largest rod strain |l - r| / r or capsule overlap /
radius seen after any of its frames (constraint violation), (b) the largest
particle distance after the last frame to a tightly converged reference
(XPBD, 200 substeps x 8 iterations). Time: median ms per frame, JIT warm-up
excluded. Writes a JSON table and a log-log PNG (time on x, error on y).

Usage: python tools/bench_rope_error.py [--frames 3] [--start 50] [--out runs/bench_rope_error]
"""

import argparse
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

LEVEL = pathlib.Path(__file__).resolve().parents[1] / "levels" / "rope_wind.yaml"
XPBD_SWEEP = [(s, i) for s in (5, 10, 20, 40) for i in (1, 2, 4)]
PROJECTION_SWEEP = [(s, g) for s in (5, 20) for g in (1, 2, 3)]
REFERENCE = (200, 8)


def start_state(frames: int):
    """(x, v, control snapshot) after ``frames`` frames of the level as shipped."""
    from sandbox.api import Sandbox

    sb = Sandbox.from_level(LEVEL)
    for _ in range(frames):
        sb.step()
    w = sb.world
    return w.state.save(), w.control.snapshot(), w.fsm.state


def violation(world) -> tuple[float, float]:
    """(largest rod strain, largest capsule overlap over the smaller radius) now.

    Each solver is held to its own Eq. 2: XPBD to the rest lengths of the
    built rope (a rod across a polyline corner is a little shorter), the
    projection to the rope's nominal rod length r.
    """
    x = world.positions().astype(np.float64)
    x0 = world.data.x0.astype(np.float64)
    worst = 0.0
    for r in world.ropes.values():
        seg = np.linalg.norm(np.diff(x[r.start:r.end], axis=0), axis=1)
        if world.reference is not None:
            rest = np.full_like(seg, r.rod_length)
        else:
            rest = np.linalg.norm(np.diff(x0[r.start:r.end], axis=0), axis=1)
        worst = max(worst, float(np.abs(seg / rest - 1.0).max()))
    gap = world.solver.ropecol.measure()
    rmin = min(r.radius for r in world.ropes.values())
    return worst, float(max(0.0, -gap.min())) / rmin


def advance(start, frames: int, substeps: int, iterations: int, solver: str = "xpbd") -> dict:
    """Advance ``frames`` frames from ``start`` with one solver configuration."""
    from sandbox.api import Sandbox

    sb = Sandbox.from_level(LEVEL, overrides={"sim.substeps": substeps, "sim.iterations": iterations,
                                              "sim.solver": solver})
    w = sb.world
    w.fsm = None  # the driven target stays where the start state had it
    (snap, ctl, _) = start

    def reset():
        w.state.restore(snap)
        w.control.restore(ctl)

    reset()
    w.step_physics()  # JIT warm-up
    reset()
    ms, strain, overlap = [], 0.0, 0.0
    for _ in range(frames):
        t0 = time.perf_counter()
        w.step_physics()
        ms.append(1e3 * (time.perf_counter() - t0))
        s, o = violation(w)
        strain, overlap = max(strain, s), max(overlap, o)
    return {"solver": solver, "substeps": substeps, "iterations": iterations,
            "frame_ms_p50": float(np.median(ms)), "violation": max(strain, overlap), "strain": strain,
            "overlap_ratio": overlap, "x": w.positions().astype(np.float64)}


def main() -> None:
    from sandbox import runtime
    from sandbox.bench import calibrate, machine

    p = argparse.ArgumentParser()
    p.add_argument("--frames", type=int, default=3,
                   help="frames measured (C's free tail swings chaotically: keep the horizon short)")
    p.add_argument("--start", type=int, default=50, help="frames of the level before the measured ones")
    p.add_argument("--arch", default="cpu")
    p.add_argument("--out", default="runs/bench_rope_error")
    p.add_argument("--plot-only", action="store_true", help="redraw the PNG from the JSON in --out")
    a = p.parse_args()
    if a.plot_only:
        out = pathlib.Path(a.out)
        plot(json.loads((out / "bench_rope_error.json").read_text())["runs"], out / "bench_rope_error.png")
        return
    runtime.init(a.arch)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    calib = calibrate()
    start = start_state(a.start)
    ref = advance(start, a.frames, *REFERENCE)
    rows = []
    for solver, sweep in (("xpbd", XPBD_SWEEP), ("projection", PROJECTION_SWEEP)):
        for s, i in sweep:
            r = advance(start, a.frames, s, i, solver)
            r["distance_to_reference"] = float(np.linalg.norm(r.pop("x") - ref["x"], axis=1).max())
            rows.append(r)
            print(f"{solver:10s} substeps {s:3d} it {i}: {r['frame_ms_p50']:8.2f} ms/frame, "
                  f"violation {r['violation']:.2e} (strain {r['strain']:.1e}, overlap/r {r['overlap_ratio']:.1e}), distance {r['distance_to_reference']:.2e} m", flush=True)
    ref.pop("x")
    result = {"machine": machine(), "calibration_ms": calib, "level": LEVEL.name, "start_state": start[2],
              "frames": a.frames, "reference": ref, "runs": rows}
    (out / "bench_rope_error.json").write_text(json.dumps(result, indent=2))
    plot(rows, out / "bench_rope_error.png")
    print(f"calibration {calib:.1f} ms/frame; {result['machine']}; wrote {out}")


def plot(rows: list[dict], path: pathlib.Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label in ((axes[0], "violation", "max violation: strain or overlap / r"),
                           (axes[1], "distance_to_reference", "distance to converged reference (m)")):
        for solver, marker in (("xpbd", "o"), ("projection", "s")):
            pts = [r for r in rows if r["solver"] == solver]
            ax.scatter([r["frame_ms_p50"] for r in pts], [max(r[key], 1e-9) for r in pts], marker=marker,
                       label=solver if solver == "xpbd" else "projection (Eq. 6-8)")
            for r in pts:
                ax.annotate(f"{r['substeps']}x{r['iterations']}", (r["frame_ms_p50"], max(r[key], 1e-9)),
                            fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.axvline(16.0, color="grey", ls=":", lw=1)
        ax.text(16.0, 0.02, " paper, Eq. 6: 16 ms", fontsize=7, color="grey", transform=ax.get_xaxis_transform())
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("ms per frame (median)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("rope_wind, 3 frames from mid-winding: substeps x iterations (projection: x Gauss-Newton)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
