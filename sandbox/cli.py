"""Command line: ``sandbox run|play|check|bench|sweep``."""

from __future__ import annotations

import argparse
import pathlib
import re
import sys

ARCHES = ("auto", "cpu", "cuda", "vulkan", "metal")
TIERS = ("accurate", "interactive")


class UsageError(Exception):
    """A user's mistake on the command line: one line on stderr, exit 2."""


def _overrides(items: list[str]) -> dict:
    from sandbox.levels import parse_overrides

    try:
        return parse_overrides(items)
    except ValueError as exc:
        raise UsageError(f"--set: {exc}") from None


def _limits(a: argparse.Namespace) -> None:
    """``--limit`` and ``--allow-dir`` into the environment, where level checks (and runs started from here) read them."""
    import os

    from sandbox.levels.limits import Limits, allow

    if getattr(a, "limit", None):
        try:
            Limits.parse(",".join(a.limit), Limits.from_env())
        except ValueError as exc:
            raise UsageError(f"--limit: {exc}") from None
        os.environ["SANDBOX_LIMITS"] = ",".join([os.environ.get("SANDBOX_LIMITS", ""), *a.limit]).strip(",")
    for d in getattr(a, "allow_dir", None) or []:
        if not pathlib.Path(d).is_dir():
            raise UsageError(f"--allow-dir {d}: not a folder")
        allow("SANDBOX_MESH_DIRS", str(pathlib.Path(d).resolve()))


def _whole(lo: int, hi: int):
    """An argparse type: a whole number in [lo, hi], else a usage error that says what is allowed."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{text!r} is not allowed; allowed: a whole number from {lo} to {hi}")
        return value

    return parse


def _names(text: str) -> list[str]:
    """Comma-separated names, a comma inside brackets kept (cloth lines such as ``F.[3,4]..center``)."""
    return [n.strip() for n in re.split(r",(?![^\[]*\])", text) if n.strip()]


def cmd_run(a: argparse.Namespace) -> int:
    from sandbox.runner import RunOptions, run_level

    if a.out is not None and not a.out.strip():
        raise UsageError("--out is empty; give a folder (default runs/<level>)")
    follow = _names(a.follow) if a.follow is not None else None
    if follow is not None and not follow:
        raise UsageError("--follow names no rope; give ROPE[,ROPE...] (ropes, R[i0:i1] or cloth lines)")
    out = pathlib.Path(a.out or pathlib.Path("runs") / pathlib.Path(a.level).stem)
    overrides = _overrides(a.set or [])
    if a.tier:
        overrides["sim.tier"] = a.tier
    _limits(a)
    opts = RunOptions(
        out=out, frames=a.frames, arch=a.arch, ply=a.ply, frames_every=a.frames_every or 0, video=a.video,
        gif=a.gif, width=a.width, height=a.height, progress=not a.quiet, overrides=overrides,
        follow=follow or None,
        follow_distance=a.follow_distance, overwrite=a.overwrite,
    )
    code, summary = run_level(a.level, opts)
    if summary.get("status") == "invalid":
        print(summary["errors"], file=sys.stderr)
        return code
    fm = summary.get("frame_ms", {})
    print(f"{summary.get('level')}: {summary['status']}, {summary.get('frames_run', 0)} frames, "
          f"frame p50 {fm.get('p50') or 0:.1f} ms p95 {fm.get('p95') or 0:.1f} ms -> {out}")
    for c in summary.get("criteria", []):
        mark = "ok  " if c["ok"] else "FAIL"
        bounds = " ".join(f"{k} {c[k]}" for k in ("min", "max", "equals") if c[k] is not None)
        print(f"  {mark} {c['metric']}{'(' + str(c['of']) + ')' if c['of'] else ''} = {c['value']}  ({bounds})")
    if summary.get("message"):
        print(summary["message"], file=sys.stderr)
    print("success" if summary.get("success") else "FAILED")
    return code


def cmd_play(a: argparse.Namespace) -> int:
    try:
        from sandbox.viewer.play import main as play
    except ImportError as exc:
        print(f"sandbox play is unavailable ({exc}); use: sandbox run {a.level} --frames-every 5 --video")
        return 2
    return play(a.level, arch=a.arch, tier=a.tier)


def cmd_check(a: argparse.Namespace) -> int:
    from sandbox.levels import LevelError, dump_level, load_level

    import sandbox.maneuvers  # noqa: F401

    _limits(a)
    code = 0
    for path in a.levels:
        try:
            level = load_level(path)
            print(f"{path}: ok ({level.name})")
            if a.dump:
                print(dump_level(level))
        except (LevelError, FileNotFoundError) as exc:
            print(exc, file=sys.stderr)
            code = 2
        except RecursionError:
            print(f"{path}:1:1: <root>: the level is nested too deeply", file=sys.stderr)
            code = 2
    return code


def cmd_bench(a: argparse.Namespace) -> int:
    from sandbox.bench import main as bench

    return bench(a)


def cmd_sweep(a: argparse.Namespace) -> int:
    from sandbox.sweep import SweepError, SweepOptions, load_sweep, run_sweep, write_reports
    from sandbox.sweep import plan

    if a.report:
        if a.levels or a.standard or a.grid:
            print("sandbox sweep --report DIR takes no levels, --standard or --grid", file=sys.stderr)
            return 2
        try:
            reports = write_reports(pathlib.Path(a.report), plots=not a.no_plots)
        except FileNotFoundError as exc:
            print(exc, file=sys.stderr)
            return 2
        for rep in reports:
            print(f"{rep['level']}: {rep['passed']}/{rep['runs']} passed")
        print((pathlib.Path(a.report) / "summary.md").read_text())
        return 0
    problem = None
    if not a.levels:
        problem = "give one or more level files (or --report DIR)"
    elif bool(a.standard) == bool(a.grid):
        problem = "give exactly one of --standard and --grid FILE"
    elif a.standard and (a.samples is not None or a.seed is not None):
        problem = "--samples and --seed draw from the axes of --grid FILE, not from --standard"
    elif a.seed is not None and a.samples is None:
        problem = "--seed goes with --samples N"
    elif a.samples is not None and a.samples < 1:
        problem = f"--samples must be >= 1, got {a.samples}"
    elif a.workers is not None and a.workers < 1:
        problem = f"--workers must be >= 1, got {a.workers}"
    elif a.timeout is not None and not a.timeout > 0:
        problem = f"--timeout must be > 0 s, got {a.timeout}"
    elif a.shared and a.backend != "ray":
        problem = "--shared is for --backend ray (tasks write their outputs into --out on a shared file system)"
    elif a.address and a.backend != "ray":
        problem = "--address is for --backend ray"
    if problem:
        print(f"sandbox sweep: {problem}", file=sys.stderr)
        return 2
    _limits(a)
    try:
        if a.standard:
            variants_of, base, source = plan.standard_variants, None, "--standard"
        else:
            axes = load_sweep(a.grid)
            base, source = pathlib.Path(a.grid).parent, a.grid
            if a.samples is not None:
                drawn = plan.sample_variants(axes, a.samples, a.seed or 0)
                points = [v for k, v in enumerate(drawn) if v not in drawn[:k]]  # a point drawn twice runs once
                if len(points) < len(drawn):
                    print(f"sweep: {len(drawn) - len(points)} of {len(drawn)} points drawn twice run once",
                          file=sys.stderr)
            else:
                points = plan.grid_variants(axes)
            variants_of = lambda data: [("", v) for v in points]  # noqa: E731
        opts = SweepOptions(out=pathlib.Path(a.out), workers=a.workers or 0, backend=a.backend, address=a.address,
                            shared=a.shared, timeout=a.timeout, frames=a.frames, frames_every=a.frames_every or 0,
                            threads=a.threads or 0, retry_errors=a.retry_errors, progress=not a.quiet,
                            plots=not a.no_plots)
        return run_sweep(a.levels, variants_of, opts, sweep_base=base, source=source)
    except SweepError as exc:
        print(exc, file=sys.stderr)
        return 2
    except (ValueError, ImportError) as exc:
        print(f"sandbox sweep: {exc}", file=sys.stderr)
        return 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sandbox", description="Geodesic Control sandbox for ropes and cloth")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="show the Python traceback of an internal error")
    limits = argparse.ArgumentParser(add_help=False)
    limits.add_argument("--limit", action="append", metavar="KEY=N",
                        help="raise a resource limit: particles (1e6), steps (frames x substeps, 1e8), memory_gb (8)")
    limits.add_argument("--allow-dir", action="append", metavar="DIR",
                        help="also read mesh files from DIR (by default only from the level's folder and below)")
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run a level headless and write its outputs", parents=[common, limits])
    r.add_argument("level")
    r.add_argument("--out", help="output folder (default runs/<level>)")
    r.add_argument("--frames", type=_whole(1, 1_000_000), help="frames to run (default: the level's sim.frames)")
    r.add_argument("--arch", choices=ARCHES, help="Taichi backend (default: the level's sim.arch)")
    r.add_argument("--ply", action="store_true", help="also write final meshes to out/meshes/*.ply")
    r.add_argument("--frames-every", type=_whole(0, 1_000_000), metavar="K",
                   help="write out/frames/NNNNN.png every K frames (0: none)")
    r.add_argument("--video", action="store_true", help="write out/anim.mp4")
    r.add_argument("--gif", action="store_true", help="write out/anim.gif")
    r.add_argument("--width", type=_whole(16, 8192), default=640, help="pixels of a rendered frame")
    r.add_argument("--height", type=_whole(16, 8192), default=480, help="pixels of a rendered frame")
    r.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a level value, e.g. sim.substeps=20")
    r.add_argument("--tier", choices=TIERS, help="frame time against accuracy (default: the level's sim.tier, "
                                                 "else accurate); as --set sim.tier=...")
    r.add_argument("--follow", metavar="ROPE[,ROPE...]",
                   help="rendered frames follow the knot of these ropes or cloth lines (F.line1, F.P..Q; "
                        "close-up; over the level's camera)")
    r.add_argument("--follow-distance", type=float, metavar="M",
                   help="m from the followed knot to the camera (default: the level camera's distance, or 0.4)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--overwrite", action="store_true", help="replace the outputs of an earlier run in --out")
    r.set_defaults(fn=cmd_run)
    pl = sub.add_parser("play", help="open an interactive window (needs a display and Vulkan)", parents=[common])
    pl.add_argument("level")
    pl.add_argument("--arch", choices=ARCHES, default="auto")
    pl.add_argument("--tier", choices=TIERS,
                    help="frame time against accuracy (default: the level's sim.tier, else interactive)")
    pl.set_defaults(fn=cmd_play)
    c = sub.add_parser("check", help="validate level files", parents=[common, limits])
    c.add_argument("levels", nargs="+")
    c.add_argument("--dump", action="store_true", help="print the level back as YAML")
    c.set_defaults(fn=cmd_check)
    b = sub.add_parser("bench", help="time levels headless against their budgets and a baseline", parents=[common])
    b.add_argument("levels", nargs="*")
    b.add_argument("--frames", type=_whole(1, 1_000_000), default=60)
    b.add_argument("--baseline", help="JSON baseline to compare with")
    b.add_argument("--save", help="write results as a new baseline JSON")
    b.add_argument("--arch", choices=ARCHES, default="cpu")
    b.add_argument("--tier", choices=TIERS, help="run every level at this tier (default: each level's sim.tier)")
    b.set_defaults(fn=cmd_bench)
    sw = sub.add_parser("sweep", help="run levels under many perturbations and report their pass rates",
                        parents=[common, limits])
    sw.add_argument("levels", nargs="*")
    sw.add_argument("--out", default="runs/sweep", help="sweep folder (default runs/sweep); a second run of the "
                                                       "same sweep goes on where it stopped")
    sw.add_argument("--standard", action="store_true",
                    help="the shipped set: 6 placements x {as shipped, nudged 1 um, substeps +25 %%, "
                         "iterations +1}, plus object swaps for levels that wrap an object in cloth")
    sw.add_argument("--grid", metavar="FILE", help="a sweep file of axes; runs their product")
    sw.add_argument("--samples", type=int, metavar="N", help="N random points of --grid's axes instead of the product")
    sw.add_argument("--seed", type=int, metavar="S", help="seed of --samples (default 0)")
    sw.add_argument("--workers", type=int, metavar="K", help="runs at a time (default: this machine's cores)")
    sw.add_argument("--threads", type=int, metavar="T", help="CPU threads per run (default 1: docs/benchmarks.md, 'CPU threads')")
    sw.add_argument("--backend", choices=("local", "ray"), default="local")
    sw.add_argument("--address", help="Ray cluster to join (default: start a local Ray instance)")
    sw.add_argument("--shared", action="store_true", help="ray: --out is on a file system every node sees")
    sw.add_argument("--timeout", type=float, default=3600.0, metavar="S",
                    help="seconds before a run is killed and recorded as a timeout (default 3600)")
    sw.add_argument("--frames", type=_whole(1, 1_000_000), help="frames per run (default: each level's own)")
    sw.add_argument("--frames-every", type=_whole(0, 1_000_000), metavar="K",
                    help="each run writes a PNG every K frames (0: none)")
    sw.add_argument("--retry-errors", action="store_true", help="run again the runs whose row is not 'completed'")
    sw.add_argument("--report", metavar="DIR", help="only re-render the reports and plots of DIR from its tables")
    sw.add_argument("--no-plots", action="store_true", help="tables and reports without plots")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    sw.set_defaults(fn=cmd_sweep)
    return p


def main(argv: list[str] | None = None) -> int:
    """Exit codes: 0 success, 1 a criterion failed, 2 invalid input (one line on stderr), 3 the run became
    unstable or failed (an internal error: one line, the traceback with --debug), 130 interrupted."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.fn(args) or 0)
    except KeyboardInterrupt:
        return 130
    except UsageError as exc:
        print(f"sandbox {args.cmd}: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        if getattr(args, "debug", False):
            raise
        print(f"sandbox {args.cmd}: internal error: {type(exc).__name__}: {' '.join(str(exc).split())[:500]} "
              "(--debug shows the traceback)", file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())
