"""Run a level headless over a grid of solver settings and tabulate its criteria.

A level that passes only at the settings it ships with is fragile: this
shows how each success criterion depends on substeps x iterations.

Usage: python tools/sweep_level.py LEVEL.yaml [--substeps 15 20 25] [--iterations 3 4 5]
                                   [--out runs/sweep_<level>]
Writes sweep.json (one row per setting: exit code, each criterion's value
and whether it held, frame time p50) and prints a table.
"""

import argparse
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def main() -> None:
    from sandbox import runtime
    from sandbox.runner import RunOptions, run_level

    p = argparse.ArgumentParser()
    p.add_argument("level")
    p.add_argument("--substeps", type=int, nargs="+", default=[15, 20, 25])
    p.add_argument("--iterations", type=int, nargs="+", default=[3, 4, 5])
    p.add_argument("--arch", default="cpu")
    p.add_argument("--out", default=None)
    a = p.parse_args()
    runtime.init(a.arch)
    level = pathlib.Path(a.level)
    out = pathlib.Path(a.out or f"runs/sweep_{level.stem}")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for s in a.substeps:
        for i in a.iterations:
            run_dir = out / f"s{s}_i{i}"
            code, _ = run_level(level, RunOptions(out=run_dir, progress=False,
                                                        overrides={"sim.substeps": s, "sim.iterations": i}))
            summary = json.loads((run_dir / "summary.json").read_text())
            row = {"substeps": s, "iterations": i, "exit_code": code,
                   "frame_ms_p50": summary.get("frame_ms", {}).get("p50"),
                   "criteria": {c["metric"]: {"value": c["value"], "ok": c["ok"]}
                                for c in summary.get("criteria", [])}}
            rows.append(row)
            cells = "  ".join(f"{m}={'ok' if c['ok'] else 'FAIL'}({_fmt(c['value'])})"
                              for m, c in row["criteria"].items())
            print(f"{s:3d} x {i}: exit {code}  {cells}", flush=True)
    passed = sum(r["exit_code"] == 0 for r in rows)
    (out / "sweep.json").write_text(json.dumps({"level": str(level), "rows": rows}, indent=2))
    print(f"{passed} of {len(rows)} settings pass; wrote {out / 'sweep.json'}")


def _fmt(v) -> str:
    return f"{v:.3g}" if isinstance(v, float) else str(v)


if __name__ == "__main__":
    main()
