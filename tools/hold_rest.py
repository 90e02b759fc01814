"""Stress test: hold a level's end state and watch whether it comes to rest.

Runs a level headless until its FSM ends (every maneuver's holds stay as
they are: a tightened knot stays held by its ends), then keeps stepping for
``--seconds`` more and records, every frame, the ropes' and cloths' kinetic
energy, largest and mean particle speed, largest rod or edge strain and deepest
rope capsule overlap (in radii). Nothing drives the bodies any more and
gravity does no net work on a state that hangs still, so the energy
should fall or stay level (the rope's damping is its only loss); energy
that grows is energy the solver puts in. For knot levels the knot is
identified again at the end, and every frame records where each knot lies
(``knot_centre``: the mean of the places where its strands touch): a held
knot that creeps along what it lies on has come to rest no more than one
that gains energy.

Usage: python tools/hold_rest.py LEVEL.yaml [--seconds 10] [--set KEY=VALUE ...]
                                 [--out runs/hold_<level>] [--arch cpu]
Writes hold.json (per frame: time, energy, speeds, strain, overlap) and
hold.png (energy, largest speed and each knot's drift against time) and
prints the energy over the first and the last second of the hold and how
far each knot moved from where the FSM left it.
"""

import argparse
import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def _overlap_ratio(world) -> float:
    """Deepest rope capsule overlap now, in radii of the rope (0 when nothing touches)."""
    rc = world.solver.ropecol
    if rc is None:
        return 0.0
    gap = rc.measure()
    radius = np.array([r.radius for r in world.data.ropes])[world.data.segment_rope]
    return float(max(0.0, (-gap / radius).max()))


def _sample(world, mass: np.ndarray) -> dict:
    v = world.velocities().astype(np.float64)
    speed = np.linalg.norm(v, axis=1)
    strain = world.solver.measure()["strain"]
    return {"time": world.time, "energy": float(0.5 * (mass * speed**2).sum()),
            "max_speed": float(speed.max()), "mean_speed": float(speed.mean()),
            "strain": float(strain.max()) if len(strain) else 0.0, "overlap": _overlap_ratio(world)}


def _knots(world, level) -> dict:
    from sandbox.io.criteria import METRICS

    return {str(c.of): METRICS["knot"][1](world, c.of) for c in level.success if c.metric == "knot"}


def _knot_strands(level) -> dict[str, list[str]]:
    """The strands of each knot the level's criteria identify, by the criterion's ``of``."""
    return {str(c.of): [c.of] if isinstance(c.of, str) else list(c.of) for c in level.success if c.metric == "knot"}


def _centres(world, knots: dict[str, list[str]]) -> dict[str, list[float] | None]:
    """Each knot's centre now (m), None where its strands touch nowhere."""
    from sandbox.io.criteria import knot_centre

    out = {}
    for key, strands in knots.items():
        c = knot_centre(world, strands)
        out[key] = None if c is None else [float(v) for v in c]
    return out


def _moved(c0: list[float] | None, rows: list[dict], key: str) -> list[tuple[float, float]]:
    """(time, distance in m of knot ``key``'s centre from ``c0``) over the frames where both are known."""
    return [(r["time"], float(np.linalg.norm(np.subtract(r["knot_centre"][key], c0))))
            for r in rows if c0 is not None and r["knot_centre"].get(key) is not None]


def knot_drift(start: dict, rows: list[dict]) -> dict[str, dict]:
    """How far each knot moved while held: the largest and the final distance (m) of its centre from where it
    was when the FSM ended (``start``), over the frames where both are known."""
    out = {}
    for key, c0 in start.items():
        d = [m for _, m in _moved(c0, rows, key)]
        out[key] = {"largest": max(d) if d else None, "final": d[-1] if d else None}
    return out


def main() -> None:
    from sandbox import runtime
    from sandbox.api import Sandbox
    from sandbox.levels import parse_overrides

    p = argparse.ArgumentParser()
    p.add_argument("level")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to hold the end state (s)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="level overrides")
    p.add_argument("--arch", default="cpu")
    p.add_argument("--out", default=None)
    a = p.parse_args()
    runtime.init(a.arch)
    level_path = pathlib.Path(a.level)
    out = pathlib.Path(a.out or f"runs/hold_{level_path.stem}")
    out.mkdir(parents=True, exist_ok=True)
    sim = Sandbox.from_level(level_path, arch=a.arch, overrides=parse_overrides(a.set))
    w = sim.world
    inv = w.model.inv_mass.to_numpy().astype(np.float64)
    mass = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), 0.0)
    while not w.fsm.finished and w.frame < w.level.sim.frames:
        sim.step()
    knots = _knot_strands(w.level)
    fsm_end = {"frame": w.frame, "state": w.fsm.state, "knots": _knots(w, w.level),
               "knot_centre": _centres(w, knots)}
    rows = []
    for _ in range(int(round(a.seconds * w.fps))):
        w.step()
        rows.append(_sample(w, mass))
        rows[-1]["retries"] = w.last_retries
        rows[-1]["knot_centre"] = _centres(w, knots)
    second = int(w.fps)
    first, last = rows[:second], rows[-second:]
    report = {
        "level": str(level_path), "overrides": a.set, "fsm_end": fsm_end, "seconds": a.seconds,
        "energy_first_second": float(np.mean([r["energy"] for r in first])),
        "energy_last_second": float(np.mean([r["energy"] for r in last])),
        "max_speed": max(r["max_speed"] for r in rows), "max_strain": max(r["strain"] for r in rows),
        "max_overlap": max(r["overlap"] for r in rows), "retries": sum(r["retries"] for r in rows),
        "knots_at_end": _knots(w, w.level), "knot_drift": knot_drift(fsm_end["knot_centre"], rows),
        "frames": rows,
    }
    (out / "hold.json").write_text(json.dumps(report, indent=1))
    _plot(rows, fsm_end["knot_centre"], out / "hold.png",
          f"{w.level.name}: held from frame {fsm_end['frame']} ({fsm_end['state']})")
    print(f"{w.level.name}: FSM ended at frame {fsm_end['frame']} ({fsm_end['state']}), knots {fsm_end['knots']}")
    print(f"held {a.seconds:g} s: energy {report['energy_first_second']:.3g} J (first second) -> "
          f"{report['energy_last_second']:.3g} J (last second); max speed {report['max_speed']:.2f} m/s, "
          f"max strain {100 * report['max_strain']:.2f} %, max overlap {report['max_overlap']:.3f} radius, "
          f"retries {report['retries']}, knots at the end {report['knots_at_end']}")
    for key, d in report["knot_drift"].items():
        if d["largest"] is not None:
            print(f"knot {key} moved {1e3 * d['final']:.1f} mm from where the FSM left it "
                  f"(at most {1e3 * d['largest']:.1f} mm)")
    print(out / "hold.json")


def _plot(rows: list[dict], start: dict, path: pathlib.Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["time"] for r in rows]
    fig, ax = plt.subplots(1, 3, figsize=(15, 3.8))
    ax[0].semilogy(t, [max(r["energy"], 1e-12) for r in rows])
    ax[0].set_xlabel("time (s)")
    ax[0].set_ylabel("kinetic energy (J)")
    ax[1].plot(t, [r["max_speed"] for r in rows], label="largest")
    ax[1].plot(t, [r["mean_speed"] for r in rows], label="mean")
    ax[1].set_xlabel("time (s)")
    ax[1].set_ylabel("particle speed (m/s)")
    ax[1].legend()
    for key, c0 in start.items():
        pts = _moved(c0, rows, key)
        if pts:
            ax[2].plot([t for t, _ in pts], [1e3 * m for _, m in pts], label=f"knot {key}")
    ax[2].set_xlabel("time (s)")
    ax[2].set_ylabel("knot centre moved since the FSM ended (mm)")
    if start:
        ax[2].legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=70)


if __name__ == "__main__":
    main()
