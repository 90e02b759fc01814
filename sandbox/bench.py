"""Frame-time benchmarks: ``sandbox bench`` and ``tools/bench_*.py``.

Machines are shared and noisy, so every result is also given as a ratio to a
calibration workload timed in the same process: a bare Taichi Jacobi PBD
loop over a 163 x 163 grid (20 sweeps of its structural edges per frame, no
collisions). JIT warm-up is excluded; ``ti.sync()`` stops every timer.
"""


import json
import pathlib
import platform
import sys
import time

import numpy as np
import taichi as ti

from sandbox import runtime


@ti.data_oriented
class Calibration:
    """Bare Jacobi PBD on an n x n grid: the reference workload.

    Fields: x, x_new (n*n,) vec3 f32 positions (m).
    """

    def __init__(self, n: int = 163, sweeps: int = 20) -> None:
        self.n, self.sweeps = n, sweeps
        self.x = ti.Vector.field(3, ti.f32, shape=n * n)
        self.x_new = ti.Vector.field(3, ti.f32, shape=n * n)
        self.rest = 1.6 / (n - 1)
        self._init()

    @ti.kernel
    def _init(self):
        for k in range(self.x.shape[0]):
            self.x[k] = ti.math.vec3(k % self.n * self.rest, 1.0, k // self.n * self.rest)

    @ti.kernel
    def _sweep(self, dt: ti.f32):
        for k in range(self.x.shape[0]):
            i = k % self.n
            j = k // self.n
            p = self.x[k] + ti.math.vec3(0.0, -9.81 * dt * dt, 0.0)
            acc = ti.math.vec3(0.0)
            cnt = 0
            for d in ti.static([(1, 0), (-1, 0), (0, 1), (0, -1)]):
                ii = i + d[0]
                jj = j + d[1]
                if 0 <= ii < self.n and 0 <= jj < self.n:
                    q = self.x[jj * self.n + ii]
                    e = p - q
                    length = e.norm()
                    if length > 1e-9:
                        acc += -0.5 * (length - self.rest) * e / length
                        cnt += 1
            self.x_new[k] = p + acc / ti.max(cnt, 1)
        for k in range(self.x.shape[0]):
            self.x[k] = self.x_new[k]

    def frame(self) -> None:
        for _ in range(self.sweeps):
            self._sweep(1.0 / 60.0 / self.sweeps)


def time_calls(fn, repeats: int, warmup: int = 2) -> np.ndarray:
    """Wall times (ms) of ``repeats`` calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    ti.sync()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ti.sync()
        out.append(1e3 * (time.perf_counter() - t0))
    return np.asarray(out)


def calibrate(repeats: int = 20) -> float:
    """Median ms per frame of the calibration workload."""
    return float(np.median(time_calls(Calibration().frame, repeats)))


def bench_level(path: str, frames: int = 60, overrides: dict | None = None, profile_frames: int = 3) -> dict:
    """Frame times of a level (warm-up excluded) and a per-pass split from ``profile_frames`` (>= 1) more frames."""
    if profile_frames < 1:
        raise ValueError(f"profile_frames must be at least 1, got {profile_frames}")
    from sandbox.api import Sandbox

    sim = Sandbox.from_level(path, overrides=overrides or None)
    w = sim.world
    for _ in range(3):  # JIT warm-up
        sim.step()
    ms = time_calls(sim.step, frames, warmup=0)
    stages: dict[str, list[float]] = {}
    w.profile_every = 1
    for _ in range(profile_frames):
        row = sim.step()
        for k, v in w.stage_ms.items():
            stages.setdefault(k, []).append(v)
    w.profile_every = 0
    m = w.solver.measure()
    return {
        "level": w.level.name,
        "tier": w.tier,
        "particles": w.model.n,
        "frame_ms_p50": float(np.median(ms)),
        "frame_ms_p95": float(np.percentile(ms, 95)),
        "frame_ms_max": float(ms.max()),
        "stage_ms": {k: float(np.median(v)) for k, v in stages.items()},
        "final_strain": {n: float(s) for n, s in zip(list(w.ropes) + list(w.cloths), m["strain"])},
        "run_max_strain": dict(w.run_max["strain"]),
        "run_max_penetration": dict(w.run_max["penetration"]),  # m, deepest into the ground or an object
        "final_max_speed": float(row["max_speed"]),  # the last frame's metrics row
        "substeps": {"mean": w.mean_substeps, "most": max(w.substep_frames)},
        # Newton steps the joint cloth step added where a substep left the cloth stretched (whole run).
        "joint_settle_steps": w.solver.joint.extra_steps if getattr(w.solver, "joint", None) is not None else 0,
        "budget": w.level.budget.model_dump(),
    }


def machine() -> dict:
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "arch": runtime.current_arch(), "backend_reason": runtime.reason(), "fast_compile": runtime.fast_compile(),
            "cpu_threads": runtime.threads(), "serial_loops": runtime.serial_loops()}


def main(args) -> int:
    """``sandbox bench``: time levels, compare with budgets and a baseline."""
    base = None
    if args.baseline:
        base, problem = read_baseline(pathlib.Path(args.baseline))
        if problem:
            print(f"sandbox bench: --baseline {args.baseline}: {problem}", file=sys.stderr)
            return 2
    if args.save:
        save = pathlib.Path(args.save)
        if save.is_dir() or not save.resolve().parent.is_dir():
            print(f"sandbox bench: --save {args.save}: not a file in an existing folder", file=sys.stderr)
            return 2
    runtime.init(args.arch)
    levels = args.levels or sorted(str(p) for p in pathlib.Path("levels").glob("*.yaml"))
    calib = calibrate()
    results = {"machine": machine(), "calibration_ms": calib, "levels": {}}
    code = 0
    for path in levels:
        r = bench_level(path, frames=args.frames, overrides={"sim.tier": args.tier} if getattr(args, "tier", None) else None)
        r["ratio_to_calibration"] = r["frame_ms_p50"] / calib
        verdicts = []
        b = r["budget"]
        if b.get("frame_ms_p50") and r["frame_ms_p50"] > b["frame_ms_p50"]:
            verdicts.append(f"p50 {r['frame_ms_p50']:.1f} ms over budget {b['frame_ms_p50']} ms")
        if b.get("frame_ms_p95") and r["frame_ms_p95"] > b["frame_ms_p95"]:
            verdicts.append(f"p95 {r['frame_ms_p95']:.1f} ms over budget {b['frame_ms_p95']} ms")
        key = f"{r['level']}@{args.tier}" if getattr(args, "tier", None) else r["level"]
        if base and key in base["levels"]:
            old = base["levels"][key]["ratio_to_calibration"]
            if r["ratio_to_calibration"] > 1.25 * old:
                verdicts.append(f"ratio {r['ratio_to_calibration']:.2f} regressed from baseline {old:.2f} (>25%)")
        r["verdicts"] = verdicts
        code = code or (1 if verdicts else 0)
        results["levels"][key] = r
        print(f"{r['level']:>16} ({r['tier']}): p50 {r['frame_ms_p50']:7.1f} ms  p95 {r['frame_ms_p95']:7.1f} ms  "
              f"x{r['ratio_to_calibration']:.2f} calib  {'; '.join(verdicts) or 'ok'}")
    print(f"calibration (Jacobi PBD 163x163, 20 sweeps): {calib:.1f} ms/frame on {results['machine']['processor']}")
    if args.save:
        from sandbox.io.outputs import write_json_atomic

        write_json_atomic(pathlib.Path(args.save), results)
    return code


def read_baseline(path: pathlib.Path) -> tuple[dict | None, str | None]:
    """A baseline written by ``--save``, or what is wrong with it (checked before any timing)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        return None, f"cannot read it ({exc.strerror or exc})"
    except (ValueError, UnicodeDecodeError) as exc:
        return None, f"not JSON ({exc})"
    levels = data.get("levels") if isinstance(data, dict) else None
    if not isinstance(levels, dict):
        return None, "not a baseline: it needs a 'levels' mapping, as 'sandbox bench --save' writes"
    for name, entry in levels.items():
        ratio = entry.get("ratio_to_calibration") if isinstance(entry, dict) else None
        if isinstance(ratio, bool) or not isinstance(ratio, (int, float)) or not ratio > 0:
            return None, f"levels.{name}.ratio_to_calibration must be a positive number, got {ratio!r}"
    return data, None
