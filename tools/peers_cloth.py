"""The peers on drape_box's workload: NVIDIA Warp's XPBD (warp.sim) and MuJoCo's flex, same grid, same machine.

    pip install '.[peers]'            # warp-lang (with warp.sim) and mujoco: an optional extra, never a dependency
    python tools/peers_cloth.py [--frames 150] [--out runs/peers_cloth.json] [--only warp|mujoco]

The scene is drape_box's: a 163 x 163 cloth, 1.6 m square (1 cm spacing), 0.5 kg, dropped
from 0.7 m onto a 0.5 x 0.4 x 0.5 m box on the ground, 60 frames per second with 10 substeps
(Warp) or a 1/600 s step (MuJoCo), on the CPU. Each peer runs ``--frames`` frames (or
what it gets through in ``--seconds``; it stops where its positions blow up, or where one
step takes longer than that); the
median ms per frame is taken after three warm-up frames (JIT and model set-up excluded), and
the largest stretch of the cloth's structural edges over the run (|l - r| / r, stretched
edges only, as ``max_strain`` measures it here) and the deepest a particle centre went into
the box or the ground. Neither peer has self-collision on here (drape_box has it on).
``tools/pareto_cloth.py --peers runs/peers_cloth.json`` draws the points with our front.
"""

import argparse
import json
import math
import pathlib
import platform
import sys
import time

import numpy as np

N = 163
SIZE = 1.6
MASS = 0.5
HEIGHT = 0.7
BOX = (0.5, 0.4, 0.5)  # full extents, standing on the ground
FPS = 60
SUBSTEPS = 10


def grid_edges(n: int) -> np.ndarray:
    """(E, 2) structural edges of an n x n grid, particle k = j n + i."""
    idx = np.arange(n * n).reshape(n, n)
    return np.concatenate([np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
                           np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1)])


def stretch(x: np.ndarray, edges: np.ndarray, rest: float) -> float:
    """Largest relative stretch of the edges (compression counts as 0)."""
    length = np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1)
    return float(max(0.0, (length.max() - rest) / rest))


def depth(x: np.ndarray, up: int) -> float:
    """Deepest a point is inside the box or under the ground (m), for a y-up (1) or z-up (2) frame."""
    h = x[:, up]
    horiz = [a for a in range(3) if a != up]
    half = np.array([BOX[0] / 2, BOX[2] / 2])
    inside = (np.abs(x[:, horiz]) < half).all(1) & (h < BOX[1]) & (h > 0)
    d_box = np.where(inside, np.minimum((half - np.abs(x[:, horiz])).min(1), BOX[1] - h), 0.0)
    return float(max(d_box.max(initial=0.0), (-h).max(initial=0.0), 0.0))


def run_warp(frames: int, seconds: float) -> dict:
    import warp as wp
    import warp.sim

    wp.config.quiet = True
    wp.init()
    cell = SIZE / (N - 1)
    b = wp.sim.ModelBuilder()
    b.add_cloth_grid(pos=wp.vec3(-SIZE / 2, HEIGHT, -SIZE / 2), rot=wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), math.pi / 2),
                     vel=wp.vec3(0.0, 0.0, 0.0), dim_x=N - 1, dim_y=N - 1, cell_x=cell, cell_y=cell,
                     mass=MASS / (N * N), tri_ke=0.0, tri_ka=0.0, tri_kd=0.0, edge_ke=0.0, edge_kd=0.0,
                     add_springs=True, spring_ke=1.0e4, spring_kd=0.0, particle_radius=0.75 * cell)
    b.add_shape_box(body=-1, pos=wp.vec3(0.0, BOX[1] / 2, 0.0), hx=BOX[0] / 2, hy=BOX[1] / 2, hz=BOX[2] / 2, mu=0.5)
    model = b.finalize(device="cpu")
    model.ground = True
    model.soft_contact_mu = 0.5
    integrator = wp.sim.XPBDIntegrator(iterations=1)
    s0, s1 = model.state(), model.state()
    dt = 1.0 / FPS / SUBSTEPS
    x0 = s0.particle_q.numpy()
    # The grid as built: particles in rows along x; rest spacing `cell`.
    edges = grid_edges(N)
    assert abs(np.linalg.norm(x0[1] - x0[0]) - cell) < 1e-6

    def frame():
        nonlocal s0, s1
        for _ in range(SUBSTEPS):
            s0.clear_forces()
            wp.sim.collide(model, s0)
            integrator.simulate(model, s0, s1, dt)
            s0, s1 = s1, s0
        wp.synchronize()

    return _measure("Warp XPBD (warp.sim 1.7, CPU)", frame, lambda: s0.particle_q.numpy(), frames, edges, cell, 1,
                    seconds)


def run_mujoco(frames: int, seconds: float) -> dict:
    import mujoco

    cell = SIZE / (N - 1)
    xml = f"""
<mujoco>
  <option timestep="{1.0 / FPS / SUBSTEPS}" integrator="implicitfast"/>
  <worldbody>
    <geom type="plane" size="3 3 0.1"/>
    <geom type="box" size="{BOX[0] / 2} {BOX[2] / 2} {BOX[1] / 2}" pos="0 0 {BOX[1] / 2}" friction="0.5"/>
    <flexcomp name="cloth" type="grid" count="{N} {N} 1" spacing="{cell} {cell} {cell}" pos="0 0 {HEIGHT}"
              radius="{0.375 * cell}" dim="2" mass="{MASS}">
      <edge equality="true"/>
      <contact selfcollide="none" condim="3" friction="0.5"/>
    </flexcomp>
  </worldbody>
</mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    vadr = model.flex_vertadr[0]
    xv = data.flexvert_xpos[vadr : vadr + N * N]
    # flexcomp numbers a grid's vertices along its first axis fastest or slowest: find the neighbour at `cell`.
    edges = grid_edges(N)
    if abs(np.linalg.norm(xv[1] - xv[0]) - cell) > 1e-6:
        raise RuntimeError("unexpected flexcomp grid order")

    def frame():
        for _ in range(SUBSTEPS):
            t0 = time.perf_counter()
            mujoco.mj_step(model, data)
            if time.perf_counter() - t0 > seconds:
                raise TooSlow(f"one step took {time.perf_counter() - t0:.0f} s with {data.ncon} contacts")

    return _measure(f"MuJoCo flex ({mujoco.__version__}, CPU)", frame,
                    lambda: data.flexvert_xpos[vadr : vadr + N * N].copy(), frames, edges, cell, 2, seconds)


class TooSlow(Exception):
    """A peer's frame ran past ``--seconds``."""


def _measure(name: str, frame, positions, frames: int, edges, rest: float, up: int, seconds: float) -> dict:
    for _ in range(3):
        frame()
    ms, worst, deep, diverged, stopped = [], 0.0, 0.0, None, None
    start = time.perf_counter()
    for f in range(3, frames):
        if time.perf_counter() - start > seconds:
            break
        t0 = time.perf_counter()
        try:
            frame()
        except TooSlow as exc:
            stopped = f"frame {f}: {exc}"
            break
        ms.append(1e3 * (time.perf_counter() - t0))
        x = positions()
        if not np.isfinite(x).all() or np.abs(x).max() > 100.0:
            diverged = f
            break
        worst = max(worst, stretch(x, edges, rest))
        deep = max(deep, depth(x, up))
    out = {"label": name, "ms": float(np.median(ms)), "ms_p95": float(np.percentile(ms, 95)),
           "stretch": 100.0 * worst, "depth_mm": 1e3 * deep, "frames": len(ms) + 3, "diverged_at": diverged,
           "stopped": stopped}
    end = (f"diverged at frame {diverged}" if diverged else f"stopped at {stopped}" if stopped
           else f"stretch {out['stretch']:.2f} %, depth {out['depth_mm']:.2f} mm")
    print(f"{name}: {out['ms']:.1f} ms per frame over {out['frames']} frames, {end}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--out", default="runs/peers_cloth.json")
    ap.add_argument("--only", choices=["warp", "mujoco"])
    ap.add_argument("--seconds", type=float, default=600.0, help="stop a peer's timed frames after this long")
    a = ap.parse_args()
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from sandbox import runtime
    from sandbox.bench import calibrate

    runtime.init("cpu")
    calib = calibrate()
    rows = []
    for key, fn in (("warp", run_warp), ("mujoco", run_mujoco)):
        if a.only in (None, key):
            rows.append(fn(a.frames, a.seconds))
    res = {"machine": platform.processor() or platform.machine(), "calibration_ms": calib, "rows": rows}
    print(f"calibration {calib:.1f} ms")
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
