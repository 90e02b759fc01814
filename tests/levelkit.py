"""Helpers shared by the maneuver tests: a World from level text, a shipped level run headless."""

import json
import pathlib
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]


def world_from_text(text: str):
    """A World (with its FSM) built from level YAML text; mesh paths resolve against ``levels/``."""
    from sandbox.levels import load_level_from_string
    from sandbox.world import World

    level = load_level_from_string(text, base_dir=ROOT / "levels")
    w = World(level, base_dir=ROOT / "levels")
    w.attach_fsm()
    return w


def run_shipped(level: str, overrides: dict | None = None) -> dict:
    """Run ``levels/<level>`` headless into a fresh folder; its summary plus ``exit_code``."""
    from sandbox.runner import RunOptions, run_level

    out = pathlib.Path(tempfile.mkdtemp())
    code, _ = run_level(ROOT / "levels" / level, RunOptions(out=out, progress=False, overrides=overrides))
    summary = json.loads((out / "summary.json").read_text())
    summary["exit_code"] = code
    return summary
