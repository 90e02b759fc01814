"""Overlay runs frame by frame from their metrics.jsonl: largest strain, substeps and largest speed.

Usage: python tools/plot_frames.py RUN_A RUN_B ... [--labels a b ...] [--body NAME] [--out frames.png]
RUN is a `sandbox run` output folder. The strain is the largest of the
named body (default: of every rope and cloth) in each frame, on a log scale;
the substeps are what each frame took (they adapt to the motion).
"""

import argparse
import json
import pathlib


def frame_series(run: pathlib.Path, body: str | None = None) -> dict[str, list[float]]:
    """Per-frame ``frame``, ``strain`` (the body's, or the largest of all), ``substeps`` (None where the
    metrics do not record them) and ``speed``."""
    rows = [json.loads(line) for line in (pathlib.Path(run) / "metrics.jsonl").read_text().splitlines() if line]
    if not rows:
        raise ValueError(f"{run}: metrics.jsonl has no frames")
    if body is not None and body not in rows[0]["strain"]:
        raise ValueError(f"{run}: no body {body!r}; bodies: {', '.join(rows[0]['strain']) or '(none)'}")
    return {
        "frame": [r["frame"] for r in rows],
        "strain": [r["strain"][body] if body else max(r["strain"].values(), default=0.0) for r in rows],
        "substeps": [r.get("substeps") for r in rows],  # None in runs from before adaptive substeps
        "speed": [r["max_speed"] for r in rows],
    }


def plot_frames(runs: list[pathlib.Path], labels: list[str], out: pathlib.Path, body: str | None = None) -> None:
    """Write the overlay of ``runs`` (output folders) to ``out`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if len(labels) != len(runs):
        raise ValueError(f"{len(runs)} runs but {len(labels)} labels: give one label per run")
    fig, ax = plt.subplots(1, 3, figsize=(15, 3.8))
    for k, (run, label) in enumerate(zip(runs, labels)):
        s = frame_series(run, body)
        color = f"C{k % 10}"
        ax[0].semilogy(s["frame"], [max(100.0 * v, 1e-4) for v in s["strain"]], color=color, label=label)
        if None not in s["substeps"]:
            ax[1].step(s["frame"], s["substeps"], where="post", color=color, label=label)
        ax[2].plot(s["frame"], s["speed"], color=color, label=label)
    for a, title in zip(ax, (f"largest stretch (%){' of ' + body if body else ''}", "substeps", "largest speed (m/s)")):
        a.set_title(title)
        a.set_xlabel("frame")
        a.grid(True, alpha=0.3)
    ax[0].legend()
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("runs", nargs="+", type=pathlib.Path)
    p.add_argument("--labels", nargs="+")
    p.add_argument("--body", default=None)
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("frames.png"))
    a = p.parse_args()
    plot_frames(a.runs, a.labels or [r.name for r in a.runs], a.out, a.body)
    print(a.out)


if __name__ == "__main__":
    main()
