"""Run a level headless over a grid of solver settings and placements and tabulate its criteria.

A level that passes only at the settings it ships with, or only where its
bodies happen to be placed, is fragile: this shows how each success
criterion depends on substeps x iterations and on a shift of the scene.
By default only the ropes move (for scenes whose maneuvers are relative to
the ropes and that have nothing else they touch, such as self_knot); with
``--rigid`` the objects, the cloths' centres and the camera move with them,
and so do the FSM's absolute points named by ``--shift-args`` (the
arguments of its top-level states, e.g. the knot levels' ``C_TOWARD``).

Usage: python tools/sweep_level.py LEVEL.yaml [--substeps 15 20 25] [--iterations 3 4 5]
                                   [--shift 0,0,0 0,0.01,0 ...] [--rigid] [--shift-args NAME ...]
                                   [--set KEY=VALUE ...]
                                   [--out runs/sweep_<level>]
Writes sweep.json (one row per setting and shift: exit code, each
criterion's value and whether it held, frame time p50) and prints a table.
"""

import argparse
import json
import pathlib
import sys

import yaml

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))


def _moved(p, shift) -> list[float]:
    return [float(a) + float(b) for a, b in zip(p, shift)]


def shifted_ropes(level: pathlib.Path, shift) -> dict:
    """Overrides that move every rope's points by ``shift`` (m)."""
    data = yaml.safe_load(level.read_text())
    out = {}
    for k, rope in enumerate(data.get("scene", {}).get("ropes", [])):
        out[f"scene.ropes.{k}.points"] = [_moved(p, shift) for p in rope["points"]]
    return out


def shifted_scene(level: pathlib.Path, shift, fsm_points=()) -> dict:
    """Overrides that move the whole scene by ``shift`` (m): ropes, objects, cloths, camera, FSM points.

    ``fsm_points`` names the arguments (``with`` keys) of the FSM's top-level
    states that are absolute points; each one found is moved as well. A
    moving object's keyframe positions move with it.

    Raises:
        ValueError: for a name in ``fsm_points`` that no top-level state has,
            or a rope whose pins' motion turns about the world origin (no
            shift of its keyframes follows the scene).
    """
    data = yaml.safe_load(level.read_text())
    scene = data.get("scene", {})
    out = shifted_ropes(level, shift)
    for rope in scene.get("ropes", []):
        frames = (rope.get("motion") or {}).get("keyframes", [])
        if any(any(float(a) != 0.0 for a in f.get("rotation", [0, 0, 0])) for f in frames):
            raise ValueError(f"rope {rope.get('name')!r}: its motion turns about the world origin, "
                             "so a shifted scene cannot follow it; shift without --rigid")
    for k, obj in enumerate(scene.get("objects", [])):
        out[f"scene.objects.{k}.position"] = _moved(obj.get("position", [0, 0, 0]), shift)
        for j, f in enumerate((obj.get("motion") or {}).get("keyframes", [])):
            out[f"scene.objects.{k}.motion.keyframes.{j}.position"] = _moved(f["position"], shift)
    for k, cloth in enumerate(scene.get("cloths", [])):
        out[f"scene.cloths.{k}.center"] = _moved(cloth.get("center", [0, 0, 0]), shift)
    for key in ("position", "look_at"):
        if key in scene.get("camera", {}):
            out[f"scene.camera.{key}"] = _moved(scene["camera"][key], shift)
    fsm = data.get("fsm", [])
    states = [st for st in (fsm if isinstance(fsm, list) else []) if isinstance(st, dict)]
    for name in fsm_points:
        found = [k for k, st in enumerate(fsm) if st in states and name in st.get("with", {})] \
            if isinstance(fsm, list) else []
        if not found:
            have = sorted({key for st in states for key in st.get("with", {})})
            raise ValueError(f"--shift-args {name!r}: no top-level FSM state has that argument "
                             f"(they have: {', '.join(have) or 'none'})")
        for k in found:
            out[f"fsm.{k}.with.{name}"] = _moved(fsm[k]["with"][name], shift)
    return out


def main() -> None:
    from sandbox import runtime
    from sandbox.levels import parse_overrides
    from sandbox.runner import RunOptions, run_level

    p = argparse.ArgumentParser()
    p.add_argument("level")
    p.add_argument("--substeps", type=int, nargs="+", default=[15, 20, 25])
    p.add_argument("--iterations", type=int, nargs="+", default=[3, 4, 5])
    p.add_argument("--shift", nargs="+", default=["0,0,0"], help="rope (or, with --rigid, scene) shifts x,y,z in m")
    p.add_argument("--rigid", action="store_true", help="shift objects, cloths, camera and --shift-args too")
    p.add_argument("--shift-args", nargs="*", default=[], metavar="NAME",
                   help="with --rigid: FSM state arguments that are absolute points")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra level overrides")
    p.add_argument("--arch", default="cpu")
    p.add_argument("--out", default=None)
    a = p.parse_args()
    runtime.init(a.arch)
    level = pathlib.Path(a.level)
    out = pathlib.Path(a.out or f"runs/sweep_{level.stem}")
    out.mkdir(parents=True, exist_ok=True)
    extra = parse_overrides(a.set)
    rows = []
    for shift_text in a.shift:
        shift = [float(v) for v in shift_text.split(",")]
        for s in a.substeps:
            for i in a.iterations:
                run_dir = out / f"s{s}_i{i}_{shift_text.replace(',', '_')}"
                overrides = {"sim.substeps": s, "sim.iterations": i, **extra,
                             **(shifted_scene(level, shift, a.shift_args) if a.rigid else shifted_ropes(level, shift))}
                code, _ = run_level(level, RunOptions(out=run_dir, progress=False, overrides=overrides))
                summary = json.loads((run_dir / "summary.json").read_text())
                row = {"substeps": s, "iterations": i, "shift": shift, "exit_code": code,
                       "frame_ms_p50": summary.get("frame_ms", {}).get("p50"),
                       "criteria": {_label(c): {"value": c["value"], "ok": c["ok"]}
                                    for c in summary.get("criteria", [])}}
                rows.append(row)
                cells = "  ".join(f"{m}={'ok' if c['ok'] else 'FAIL'}({_fmt(c['value'])})"
                                  for m, c in row["criteria"].items())
                print(f"{s:3d} x {i} shift {shift_text}: exit {code}  {cells}", flush=True)
    passed = sum(r["exit_code"] == 0 for r in rows)
    (out / "sweep.json").write_text(json.dumps({"level": str(level), "overrides": a.set, "rows": rows}, indent=2))
    print(f"{passed} of {len(rows)} runs pass; wrote {out / 'sweep.json'}")


def _label(criterion: dict) -> str:
    """``metric`` or ``metric[of]``: a level may check one metric on several bodies."""
    of = criterion.get("of")
    if of is None:
        return criterion["metric"]
    return f"{criterion['metric']}[{of if isinstance(of, str) else ','.join(of)}]"


def _fmt(v) -> str:
    return f"{v:.3g}" if isinstance(v, float) else str(v)


if __name__ == "__main__":
    main()
