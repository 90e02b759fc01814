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


def shipped_world(level: str, overrides: dict | None = None):
    """A World (with its FSM) of ``levels/<level>`` with dotted overrides (``{"fsm.1.with.pinch": True}``)."""
    from sandbox.levels import load_level
    from sandbox.world import World

    w = World(load_level(ROOT / "levels" / level, overrides), base_dir=ROOT / "levels")
    w.attach_fsm()
    return w


def run_shipped(level: str, overrides: dict | None = None) -> dict:
    """Run ``levels/<level>`` headless into a fresh folder, as shipped; its summary plus ``exit_code``.

    A process of its own with Taichi's full optimisations (``SANDBOX_FAST_COMPILE=0``), as
    ``sandbox run`` runs it: the tests' own processes skip them to compile faster, and a knot
    level's chaotic run does not come out bitwise the same without them (``self_knot`` then
    overlaps 0.111 radius in one violent frame of its `Tightening`, against 0.048 shipped).
    """
    import os
    import subprocess
    import sys

    out = pathlib.Path(tempfile.mkdtemp())
    sets = [f"--set={k}={json.dumps(v)}" for k, v in (overrides or {}).items()]
    cmd = [sys.executable, "-m", "sandbox.cli", "run", str(ROOT / "levels" / level), "--out", str(out), "--quiet",
           *sets]
    env = {**os.environ, "SANDBOX_FAST_COMPILE": "0"}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=3600)
    path = out / "summary.json"
    assert path.exists(), proc.stderr[-3000:]
    summary = json.loads(path.read_text())
    summary["exit_code"] = proc.returncode
    assert summary.get("fast_compile", False) is False  # absent where the level did not load
    return summary


def solver_masses(w):
    """Set the solver's per-substep inverse masses as a frame would (the model's, zero where driven); (n,) float64."""
    import numpy as np

    n = w.model.n
    driven = w.control.is_driven(np.arange(n)).astype(bool)
    inv_mass = np.where(driven, 0.0, w.solver.model.inv_mass.to_numpy()).astype(np.float64)
    w.solver.w.from_numpy(inv_mass.astype(np.float32))
    return inv_mass


def random_contacts(rng, n: int, share: float = 0.25):
    """``share`` of n particles touching, with random unit normals: (touching (n,) bool, normal (n, 3))."""
    import numpy as np

    touching = np.zeros(n, bool)
    touching[rng.choice(n, int(n * share), replace=False)] = True
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    return touching, normal


def step_until_finished(w, frames: int) -> None:
    """Step world ``w`` until its FSM finishes, at most ``frames`` frames."""
    for _ in range(frames):
        w.step()
        if w.fsm.finished:
            return
