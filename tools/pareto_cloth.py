"""Run time against error for cloth: a level over solver settings, one point per setting.

    python tools/pareto_cloth.py [LEVEL.yaml] [--frames N] [--out runs/pareto.json] [--plot docs/img/pareto_drape.png]

Each setting runs the level from its first frame for ``--frames`` frames (default:
all of the level's own), timed after three warm-up frames, and reports the median ms
per frame, the largest stretch of the cloth over the run and the deepest the cloth went
into an object or the ground over the run, with the ratio of the median to the
calibration workload timed in the same process. The plot puts ms per frame against
the stretch and against the depth, one point per setting; the front (no setting both
faster and more accurate) is joined.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from sandbox import runtime  # noqa: E402
from sandbox.bench import bench_level, calibrate, machine  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]

# (label, overrides): the level as shipped, then one change at a time along each knob that
# trades time for stretch (substeps, chain sweeps, the joint step and how often it runs).
SETTINGS = (
    ("shipped", {}),
    ("joint 3 CG", {"sim.cloth_joint": 3}),
    ("joint 12 CG", {"sim.cloth_joint": 12}),
    ("joint every 2nd substep", {"sim.cloth_joint_every": 2}),
    ("no joint", {"sim.cloth_joint": 0}),
    ("no joint, 1 sweep", {"sim.cloth_joint": 0, "sim.chain_sweeps": 1}),
    ("no joint, 5 sweeps", {"sim.cloth_joint": 0, "sim.chain_sweeps": 5}),
    ("5 substeps", {"sim.substeps": 5, "sim.max_substeps": 20}),
    ("20 substeps", {"sim.substeps": 20, "sim.max_substeps": 80}),
    ("no joint, 20 substeps", {"sim.cloth_joint": 0, "sim.substeps": 20, "sim.max_substeps": 80}),
    # The interactive tier: the same cloth on a coarser grid (69 x 69 for 163 x 163), substeps scaled with it.
    ("interactive tier", {"sim.tier": "interactive"}),
    ("interactive, no joint", {"sim.tier": "interactive", "sim.cloth_joint": 0}),
)


def front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats on both coordinates (lower is better), by the first."""
    order = sorted(range(len(points)), key=lambda i: points[i])
    out, best = [], float("inf")
    for i in order:
        if points[i][1] < best:
            out.append(i)
            best = points[i][1]
    return out


def peer_points(peers: dict, calibration_ms: float) -> list[dict]:
    """The peers' rows of ``tools/peers_cloth.py``, their ms scaled to this run's calibration workload (the two
    runs are separate processes); a peer that diverged or was stopped keeps its row (``diverged_at``,
    ``stopped``) and is not drawn."""
    scale = calibration_ms / peers["calibration_ms"]
    return [dict(r, ms=r["ms"] * scale) for r in peers["rows"]]


def plot(rows: list[dict], path: pathlib.Path, title: str, peers: list[dict] = ()) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label in ((axes[0], "stretch", "largest stretch over the run (%)"),
                           (axes[1], "depth_mm", "deepest into the box or ground over the run (mm)")):
        xs = [r["ms"] for r in rows]
        ys = [r[key] for r in rows]
        ax.scatter(xs, ys, color="tab:blue", zorder=3)
        ax.set_xlabel("median ms per frame")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3, which="both")
        if max(ys) <= 0.0:  # a log axis and labels would only pile up on zero
            ax.text(0.5, 0.7, "0 for every setting", transform=ax.transAxes, ha="center")
            continue
        span = max(xs) - min(xs) or 1.0
        placed: list[tuple[float, float]] = []
        for r, x, y in sorted(zip(rows, xs, ys), key=lambda t: t[1]):
            # A label next to one already placed (close in time and, on the log axis, in error) goes below.
            near = any(abs(x - px) < 0.08 * span and abs(np.log10(max(y, 1e-9) / max(py, 1e-9))) < 0.15
                       for px, py in placed)
            ax.annotate(r["label"], (x, y), textcoords="offset points", xytext=(4, -10 if near else 3), fontsize=7)
            placed.append((x, y))
        for r in peers:
            if r.get("diverged_at") is None and r.get("stopped") is None:
                ax.scatter([r["ms"]], [max(r[key], 1e-3)], color="tab:red", marker="s", zorder=3)
                ax.annotate(f"{r['label']} ({r['frames']} frames)", (r["ms"], max(r[key], 1e-3)),
                            textcoords="offset points", xytext=(4, -9), fontsize=7, color="tab:red")
        idx = front(list(zip(xs, ys)))
        ax.plot([xs[i] for i in idx], [ys[i] for i in idx], color="tab:orange", lw=1, zorder=2, label="front")
        if min(ys) > 0.0:
            ax.set_yscale("log")
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def _title(res: dict) -> str:
    return (f"{res['level']}: run time against error ({res['frames']} frames, calibration "
            f"{res['calibration_ms']:.1f} ms, {res['machine']['processor']})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("level", nargs="?", default=str(ROOT / "levels" / "drape_box.yaml"))
    ap.add_argument("--frames", type=int, help="frames per setting (default: the level's own)")
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--out", default="runs/pareto_cloth.json")
    ap.add_argument("--plot", help="write the plot to this PNG")
    ap.add_argument("--replot", metavar="JSON", help="only draw --plot from an earlier run's --out")
    ap.add_argument("--peers", metavar="JSON", help="also draw the peers' points from tools/peers_cloth.py's --out")
    a = ap.parse_args(argv)
    if a.replot:
        res = json.loads(pathlib.Path(a.replot).read_text())
        peers = peer_points(json.loads(pathlib.Path(a.peers).read_text()), res["calibration_ms"]) if a.peers else []
        plot(res["rows"], pathlib.Path(a.plot or "pareto.png"), _title(res), peers)
        return 0
    runtime.init(a.arch)
    from sandbox.levels import load_level

    level = load_level(pathlib.Path(a.level))
    frames = a.frames or level.sim.frames
    cloths = [c.name for c in level.scene.cloths]
    if not cloths:
        raise SystemExit(f"{a.level}: no cloth to measure")
    calib = calibrate()
    rows = []
    for label, overrides in SETTINGS:
        r = bench_level(a.level, frames=max(1, frames - 3), overrides=overrides)
        row = {"label": label, "overrides": overrides, "ms": r["frame_ms_p50"], "ms_p95": r["frame_ms_p95"],
               "ratio": r["frame_ms_p50"] / calib,
               "stretch": 100.0 * max(r["run_max_strain"][c] for c in cloths),
               "depth_mm": 1e3 * max(r["run_max_penetration"][c] for c in cloths),
               "substeps_mean": r["substeps"]["mean"]}
        rows.append(row)
        print(f"{label:>24}: {row['ms']:7.1f} ms (x{row['ratio']:.2f} calib)  stretch {row['stretch']:6.2f} %  "
              f"depth {row['depth_mm']:5.2f} mm  substeps {row['substeps_mean']:.1f}", flush=True)
    res = {"machine": machine(), "calibration_ms": calib, "level": level.name, "frames": frames, "rows": rows}
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"calibration {calib:.1f} ms/frame; {res['machine']['processor']}")
    if a.plot:
        peers = peer_points(json.loads(pathlib.Path(a.peers).read_text()), calib) if a.peers else []
        plot(rows, pathlib.Path(a.plot), _title(res), peers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
