"""Plot a cloth's final stretch strain per structural edge from a run's state.npz.

Usage: python tools/plot_strain.py RUN_DIR [--cloth NAME] [--level LEVEL.yaml]
Writes RUN_DIR/strain_<cloth>.png: row strain, column strain and height maps
in grid coordinates (i right, j up), where folds and hot spots are easy to see.
"""

import argparse
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("run")
    p.add_argument("--cloth", default=None)
    p.add_argument("--level", default=None, help="the level file (default: from summary.json)")
    a = p.parse_args()
    run = pathlib.Path(a.run)
    import json

    from sandbox.levels import load_level

    summary = json.loads((run / "summary.json").read_text())
    level = load_level(a.level or summary["path"])
    spec = next(c for c in level.scene.cloths if a.cloth in (None, c.name))
    # The grid the run simulated: the level's, or the interactive tier's coarser one.
    nx, nz = summary.get("cloth_grids", {}).get(spec.name, spec.resolution)
    dx, dz = spec.size[0] / (nx - 1), spec.size[1] / (nz - 1)
    with np.load(run / "state.npz") as st:
        x = st[f"cloth_{spec.name}"].astype(np.float64).reshape(nz, nx, 3)
    rows = np.maximum(np.linalg.norm(x[:, 1:] - x[:, :-1], axis=2) / dx - 1.0, 0.0)
    cols = np.maximum(np.linalg.norm(x[1:] - x[:-1], axis=2) / dz - 1.0, 0.0)
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.6))
    for k, (img, title) in enumerate(((rows, "row stretch"), (cols, "column stretch"), (x[:, :, 1], "height (m)"))):
        im = ax[k].imshow(np.clip(img, 0, 0.05) if k < 2 else img, origin="lower")
        ax[k].set_title(title + (" (clipped at 5 %)" if k < 2 else ""))
        ax[k].set_xlabel("i")
        ax[k].set_ylabel("j")
        plt.colorbar(im, ax=ax[k])
    all_s = np.concatenate([rows.ravel(), cols.ravel()])
    fig.suptitle(f"{level.name}/{spec.name}: stretch p99 {100 * np.percentile(all_s, 99):.2f} %, "
                 f"max {100 * all_s.max():.1f} %, {int((all_s > 0.02).sum())} of {all_s.size} edges over 2 %")
    out = run / f"strain_{spec.name}.png"
    fig.savefig(out, dpi=70)
    print(out)


if __name__ == "__main__":
    main()
