"""Benchmark: drape_box at 163 x 163 with self-collision on and off, one chain sweep, no joint step, fixed substeps,
and at the interactive tier (69 x 69).

Prints median/p95 ms per frame (warm-up excluded), the per-pass split, the
final and run-max stretch strain, and the ratio to the calibration workload
measured in the same process. Usage: python tools/bench_drape.py [--frames N] [--arch cpu]
"""

import argparse
import json
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from sandbox import runtime  # noqa: E402
from sandbox.bench import bench_level, calibrate, machine  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--arch", default="cpu")
    p.add_argument("--out", default="runs/bench_drape.json")
    a = p.parse_args()
    runtime.init(a.arch)
    level = str(pathlib.Path(__file__).resolve().parents[1] / "levels" / "drape_box.yaml")
    calib = calibrate()
    res = {"machine": machine(), "calibration_ms": calib}
    variants = (
        ("self_collision_on", {"scene.cloths.0.self_collision": True}),
        ("self_collision_off", {"scene.cloths.0.self_collision": False}),
        # The level as it was before chain sweeps: faster, tens of percent of
        # stretch over the box's edges and vertices, jittering there.
        ("one_chain_sweep", {"scene.cloths.0.self_collision": True, "sim.chain_sweeps": 1}),
        # Without the joint row-and-column step: faster, 2-19 % of stretch left
        # at the box's four top vertices.
        ("no_joint_step", {"scene.cloths.0.self_collision": True, "sim.cloth_joint": 0}),
        # Six CG iterations per joint step instead of four: where the drape lies still, more
        # substeps end just over the settle bound and take another step.
        ("joint_six_cg", {"scene.cloths.0.self_collision": True, "sim.cloth_joint": 6}),
        # A fixed 10 substeps, as before adaptive substeps: faster on the
        # impact frames, which then stretch the cloth by about 20 %.
        ("fixed_substeps", {"scene.cloths.0.self_collision": True, "sim.max_substeps": 10}),
        # The interactive tier (sim.tier): the same cloth on 69 x 69, its substeps scaled with the spacing.
        ("interactive_tier", {"scene.cloths.0.self_collision": True, "sim.tier": "interactive"}),
    )
    for label, overrides in variants:
        # 40 frames in: the cloth has reached the box and is draping.
        r = bench_level(level, frames=a.frames, overrides=overrides)
        r["ratio_to_calibration"] = r["frame_ms_p50"] / calib
        res[label] = r
        print(f"{label}: p50 {r['frame_ms_p50']:.1f} ms, p95 {r['frame_ms_p95']:.1f} ms, "
              f"x{r['ratio_to_calibration']:.2f} calibration; final strain {r['final_strain']}, "
              f"run-wide {r['run_max_strain']}, substeps {r.get('substeps')}, "
              f"max speed {r['final_max_speed']:.2f} m/s; settle steps {r['joint_settle_steps']}; "
              f"passes {r['stage_ms']}")
    print(f"calibration {calib:.1f} ms/frame; {res['machine']}")
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
