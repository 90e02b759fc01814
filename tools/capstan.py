"""Benchmark: rope friction against the capstan equation, on a rope and on a solid.

A rope A hangs over a rope B held at both ends (half a turn, pi, around
it), without gravity; with ``--over sphere`` it hangs over a fixed sphere
instead (half a turn over its top; the contact's friction is the mean of
the two bodies', both mu). Hands pull A's two ends down with F1 and F2 = r F1,
each against a drag b. By the capstan equation a rope of friction mu holds
while r < exp(mu pi); beyond that it slides, and at the steady speed v
the tensions at the contact, T2 = F2 - b v and T1 = F1 + b v, stand in the
ratio exp(mu pi):

    v = (F2 - exp(mu pi) F1) / (b (1 + exp(mu pi)))    (0 while r < exp(mu pi))

Each case runs from rest and reports A's mean sliding speed from
``SETTLE`` on, until ``--seconds`` or until A has slid ``REACH``, whichever
comes first, next to that closed form. Knots hold by this friction
(a square knot drawn tight holds by the capstan of its turns), so a rope
that slides where it should hold ties knots that come undone.

Usage: python tools/capstan.py [--seconds 4] [--mu 0 0.25 0.5 1] [--over rope|sphere] [--arch cpu]
Prints one Markdown table (docs/benchmarks.md, "Rope friction" and "On a solid").
"""

import argparse
import math
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RADIUS = 0.006  # m, both ropes (the knot levels' ropes)
F1 = 0.2  # N, the lighter pull
DRAG = 0.5  # N s/m, each hand
HANG = 0.5  # m: A's ends hang this far below B
REACH = 0.25  # m: the heavier end comes at most this far down (A still hangs on both sides)
SETTLE = 0.5  # s: the pulls are taken up (A's mass over the drags: 0.03 s)
SPHERE = 0.04  # m, radius of the sphere of ``--over sphere``


def level_text(mu: float, radius: float = RADIUS, over: str = "rope") -> str:
    """The scene: B along z at y = 0.5 held at both ends, or a sphere centred there (a sphere's position is its
    lowest point); A in the x-y plane, half a turn over it, ends HANG down."""
    if over not in ("rope", "sphere"):
        raise ValueError(f"over must be 'rope' or 'sphere', got {over!r}")
    r = 2.0 * radius if over == "rope" else SPHERE + radius  # A's centre line around B's, or the sphere's centre
    arc = [(-r * math.cos(t), 0.5 + r * math.sin(t)) for t in np.linspace(0.0, math.pi, 9)]
    pts = [(-r, 0.5 - HANG)] + arc + [(r, 0.5 - HANG)]
    points = ", ".join(f"[{x:.6f}, {y:.6f}, 0.0]" for x, y in pts)
    if over == "sphere":
        below = f"""  objects:
    - {{name: ball, shape: sphere, params: {{radius: {SPHERE}}}, position: [0, {0.5 - SPHERE}, 0], friction: {mu}}}
  ropes:
"""
    else:
        below = f"""  ropes:
    - {{name: B, points: [[0, 0.5, -0.15], [0, 0.5, 0.15]], rod_length: 0.01, radius: {radius}, mass: 0.03,
       pins: [start, end], friction: {mu}}}
"""
    return f"""
version: 1
name: capstan
scene:
  gravity: [0, 0, 0]
  ground: false
{below}    - {{name: A, points: [{points}], rod_length: 0.01, radius: {radius}, mass: 0.03, friction: {mu}}}
sim: {{tier: interactive, fps: 60, substeps: 20, iterations: 4, frames: 10}}
fsm:
  - {{run: Wait, with: {{ticks: 1000000}}}}
"""


def closed_form(mu: float, ratio: float) -> float:
    """Steady sliding speed (m/s) of A towards the heavier pull: 0 while it holds."""
    e = math.exp(mu * math.pi)
    return max(0.0, (ratio * F1 - e * F1) / (DRAG * (1.0 + e)))


def slide_speed(mu: float, ratio: float, seconds: float, arch: str, over: str = "rope") -> float:
    """A's mean speed towards the heavier pull (m/s) from ``SETTLE`` until ``seconds`` have passed or the heavier
    end has come ``REACH`` down (A still hangs over B, or the sphere, on both sides)."""
    from sandbox.api import Sandbox
    from sandbox.levels.loader import load_level_from_string

    sb = Sandbox(load_level_from_string(level_text(mu, over=over), base_dir=ROOT), arch=arch)
    first = len(sb.rope_positions("B")) if over == "rope" else 0
    last = first + len(sb.rope_positions("A")) - 1
    sb.world.control.pull([first, last], [[0.0, -F1, 0.0], [0.0, -ratio * F1, 0.0]], DRAG)
    fps = sb.world.fps
    y0 = float(sb.rope_positions("A")[-1, 1])
    ys = [y0]
    while len(ys) <= int(round(seconds * fps)) and y0 - ys[-1] < REACH:
        sb.step()
        ys.append(float(sb.rope_positions("A")[-1, 1]))
    end = len(ys) - 1
    start = int(round(SETTLE * fps))
    if start >= end:  # it came REACH down before SETTLE: as fast as that
        start = 0
    return (ys[start] - ys[end]) * fps / (end - start)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--mu", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0])
    ap.add_argument("--over", choices=("rope", "sphere"), default="rope")
    ap.add_argument("--arch", default="cpu")
    args = ap.parse_args(argv)
    print("| mu | F2 / F1 | exp(mu pi) | holds by the closed form | sliding speed, closed form (m/s) "
          "| measured (m/s) |")
    print("|---|---|---|---|---|---|")
    for mu in args.mu:
        e = math.exp(mu * math.pi)
        for ratio in sorted({round(r, 2) for r in (1.5, 0.7 * e, 1.5 * e) if r > 1.0}):
            v = slide_speed(mu, ratio, args.seconds, args.arch, args.over)
            want = closed_form(mu, ratio)
            print(f"| {mu:g} | {ratio:.2f} | {e:.2f} | {'yes' if want == 0 else 'no'} | {want:.3f} | {v:.3f} |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
