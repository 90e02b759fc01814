"""Overlay the holds that tools/hold_rest.py recorded: energy and largest speed against time held.

Usage: python tools/plot_holds.py A/hold.json B/hold.json ... [--labels a b ...] [--out holds.png]
Each curve starts at its own FSM end (time 0 = the first held frame), so
runs whose FSMs ended at different frames line up.
"""

import argparse
import json
import pathlib


def plot_holds(paths: list[pathlib.Path], labels: list[str], out: pathlib.Path) -> None:
    """Write the overlay of the holds in ``paths`` (hold.json files) to ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if len(labels) != len(paths):
        raise ValueError(f"{len(paths)} hold files but {len(labels)} labels: give one label per file")
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    title = []
    for path, label in zip(paths, labels):
        report = json.loads(pathlib.Path(path).read_text())
        rows = report["frames"]
        t0 = rows[0]["time"]
        t = [r["time"] - t0 for r in rows]
        ax[0].semilogy(t, [max(r["energy"], 1e-12) for r in rows], label=label)
        ax[1].plot(t, [r["max_speed"] for r in rows], label=label)
        title.append(pathlib.Path(report["level"]).stem)
    ax[0].set_xlabel("time held (s)")
    ax[0].set_ylabel("kinetic energy (J)")
    ax[1].set_xlabel("time held (s)")
    ax[1].set_ylabel("largest particle speed (m/s)")
    for a in ax:
        a.legend()
    fig.suptitle(", ".join(sorted(set(title))) + ": held by its ends after the FSM")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=70)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("holds", nargs="+", type=pathlib.Path, help="hold.json files from tools/hold_rest.py")
    p.add_argument("--labels", nargs="+", default=None, help="one per file (default: the folder names)")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("holds.png"))
    a = p.parse_args()
    plot_holds(a.holds, a.labels or [h.parent.name for h in a.holds], a.out)
    print(a.out)


if __name__ == "__main__":
    main()
