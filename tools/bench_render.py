"""Time the software renderer on a 163 x 163 cloth draped over a box.

Usage:
    python tools/bench_render.py [--frames 40] [--width 640 --height 480] [--arch cpu]
        [--no-shadows] [--shadow-size S] [--png out.png] [--profile]

Prints the median and p95 frame time in ms (JIT warm-up excluded; a sync
ends every timed frame) with the process CPU time per frame (all threads; on a
busy machine it tells the work apart from the waiting) and, with ``--profile``, the per-stage medians, first
with one camera for the whole run (as in a recording: the sky and ground are
then shaded once) and then with a camera that moves every frame.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def draped_cloth(n: int = 163, size: float = 2.0, box: float = 0.5, height: float = 0.6, phase: float = 0.0):
    """A synthetic n x n cloth (SPEC grid convention) hanging over a box top.

    Returns verts (n*n, 3) float32 and faces (2*(n-1)^2, 3) int32.
    """
    s = np.linspace(-0.5 * size, 0.5 * size, n)
    x, z = np.meshgrid(s, s)  # row j (z), column i (x): index j * n + i
    ax, az = np.abs(x), np.abs(z)
    out = np.maximum(np.maximum(ax, az) - box, 0.0)  # distance beyond the box top
    ang = np.arctan2(z, x)
    flare = 1.0 + 0.12 * out
    scale = np.where(out > 0, (box + out * 0.25 * flare) / np.maximum(np.maximum(ax, az), 1e-9), 1.0)
    fold = 0.05 * out * np.sin(14.0 * ang + phase)
    px = x * scale + fold * np.cos(ang)
    pz = z * scale + fold * np.sin(ang)
    py = height + 0.012 - 0.95 * out + 0.02 * np.cos(6.0 * ang + phase) * out
    py = np.maximum(py, 0.01)
    verts = np.stack([px, py, pz], axis=-1).reshape(-1, 3).astype(np.float32)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1))
    a = (j * n + i).ravel()
    b, c, d = a + n, a + n + 1, a + 1
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return verts, faces


def box_mesh(half: float = 0.5, height: float = 0.6):
    """A closed box resting on y = 0 (verts float32, outward faces int32)."""
    import trimesh

    m = trimesh.creation.box(extents=(2 * half, height, 2 * half))
    return (m.vertices + [0.0, 0.5 * height, 0.0]).astype(np.float32), m.faces.astype(np.int32)


def bench_scene(phase: float = 0.0):
    """The benchmark scene: draped cloth over a box on the ground."""
    from shaders import MeshItem, RenderScene, crease_split

    cv, cf = draped_cloth(phase=phase)
    bv, bf = box_mesh()
    src, bf2 = crease_split(bv, bf)
    return RenderScene(
        ground_cell=0.2,
        items=[
            MeshItem(bv[src], bf2, color=(0.62, 0.45, 0.30)),
            MeshItem(cv, cf, color=(0.80, 0.18, 0.20), back_color=(0.95, 0.80, 0.45), two_sided=True),
        ],
        ground_height=0.0,
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; returns 0."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--arch", default="cpu")
    ap.add_argument("--no-shadows", action="store_true")
    ap.add_argument("--shadow-size", type=int, help="shadow-map texels per side (default: the renderer's)")
    ap.add_argument("--png", type=pathlib.Path)
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args(argv)

    from sandbox import runtime

    backend = runtime.init(args.arch)
    from shaders import Renderer, auto_camera

    extra = {"shadow_size": args.shadow_size} if args.shadow_size else {}
    renderer = Renderer(args.width, args.height, shadows=not args.no_shadows, **extra)
    scenes = [bench_scene(phase=0.1 * k) for k in range(4)]  # moving cloth: fresh data per frame
    tris = sum(len(it.faces) for it in scenes[0].items)
    print(f"backend={backend} image={args.width}x{args.height} triangles={tris} shadows={not args.no_shadows}")
    # as in a recording: one camera for the run; then a camera that moves every frame
    aspect = args.width / args.height
    fixed = auto_camera(scenes[0], aspect)
    orbit = [auto_camera(scenes[0], aspect, direction=(np.sin(a), 0.6, np.cos(a))) for a in np.linspace(0.3, 1.2, 7)]
    for label, cams in (("static camera", [fixed]), ("moving camera", orbit)):
        for k in range(args.warmup):
            renderer.render(scenes[k % len(scenes)], cams[k % len(cams)])
        runtime.sync()
        times, cpu, stages = [], [], []
        for k in range(args.frames):
            t0, c0 = time.perf_counter(), time.process_time()
            img = renderer.render(scenes[k % len(scenes)], cams[k % len(cams)], profile=args.profile)
            runtime.sync()
            times.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
            stages.append(dict(renderer.stage_ms))
        ms = np.asarray(times)
        print(
            f"{label}: render_ms median={np.median(ms):.2f} p95={np.percentile(ms, 95):.2f} "
            f"min={ms.min():.2f} n={len(ms)}; cpu_ms median={np.median(cpu):.2f}"
        )
        if args.profile:
            print("  " + "  ".join(f"{name} {np.median([s[name] for s in stages]):.2f}" for name in stages[0]))
        if label == "static camera" and args.png:
            import imageio.v3 as iio

            iio.imwrite(args.png, img)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
