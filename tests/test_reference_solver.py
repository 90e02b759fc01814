"""The paper's projection solver as a level solver, and XPBD checked against it."""

import numpy as np
import pytest

from sandbox.api import Sandbox
from sandbox.levels import load_level_from_string

SCENE = """
version: 1
name: two_ropes
scene:
  ground: null
  ropes:
    - {name: swing, points: [[-0.3, 0.5, 0.0], [0.3, 0.5, 0.0]], segments: 15, radius: 0.01, pins: [start]}
    - {name: drop, points: [[0.1, 0.56, -0.2], [0.1, 0.56, 0.2]], segments: 10, radius: 0.01}
sim: {fps: 60, substeps: SUB, iterations: IT, solver: SOLVER, frames: 30}
fsm: [{run: Wait, with: {ticks: 1000}}]
"""


def _run(solver: str, substeps: int, iterations: int, frames: int = 20):
    text = SCENE.replace("SUB", str(substeps)).replace("IT", str(iterations)).replace("SOLVER", solver)
    sim = Sandbox(load_level_from_string(text), arch="cpu")
    rows = [sim.step() for _ in range(frames)]
    return sim, rows


@pytest.fixture(scope="module")
def reference():
    return _run("projection", 4, 2)


@pytest.fixture(scope="module")
def fast():
    return _run("xpbd", 20, 3)


def test_projection_solver_keeps_rods_and_contacts(reference):
    """With sim.solver = projection, rods stay within 1 % and capsules do not pass through each other."""
    sim, rows = reference
    for r in rows:
        assert max(r["strain"].values()) < 0.01
    gap = sim.world.solver.ropecol.measure()
    assert gap.min() > -0.1 * 0.01
    assert sim.world.reference.report.max_penetration < 1e-3


def test_pinned_end_stays_put_under_projection(reference):
    """The pinned start of the swinging rope does not move under the projection solver."""
    sim, _ = reference
    assert np.allclose(sim.rope_positions("swing")[0], [-0.3, 0.5, 0.0], atol=1e-6)


def test_xpbd_agrees_with_projection(reference, fast):
    """XPBD and the reference projection give the same motion: free ends within 10 % of the rope length after 1/3 s."""
    ref, _ = reference
    xp, _ = fast
    for name, length in (("swing", 0.6), ("drop", 0.4)):
        a, b = ref.rope_positions(name), xp.rope_positions(name)
        assert np.abs(a - b).max() < 0.1 * length, name
        # and both really moved (the comparison is not between two resting ropes)
        assert np.abs(a[-1] - xp.world.data.x0[xp.body_range(name)[1] - 1]).max() > 0.05


def test_projection_rejects_cloth():
    """A level with cloth and solver projection fails to build with a message naming the allowed solver."""
    text = SCENE.replace("SUB", "2").replace("IT", "1").replace("SOLVER", "projection").replace(
        "  ropes:", "  cloths:\n    - {name: c, resolution: [3, 3], size: [0.1, 0.1], center: [0, 1, 0]}\n  ropes:")
    with pytest.raises(ValueError, match="ropes only.*xpbd"):
        Sandbox(load_level_from_string(text), arch="cpu")
