"""Step 0 of the XPBD substep, wherever ropes collide: overlap the last substep left is pushed apart
before the prediction, without turning into velocity."""

import numpy as np
import pytest

from sandbox.levels import LevelError, load_level_from_string
from tests.levelkit import world_from_text

# Two free ropes at rest, no gravity, crossing at right angles with their axes 10.8 mm apart: the
# capsules (radius 6 mm each) overlap by 1.2 mm, 0.2 radius (a knot pulled tight leaves less). They
# cross half a rod from any particle: crossing on a particle, its two rods tie as the nearest, and
# which one takes the contact turns on the last bit of rounding (the speed left after one frame then
# differed by 1.5x between two compile settings).
CROSSED = """
version: 1
name: crossed
scene:
  gravity: [0, 0, 0]
  ropes:
    - {name: A, points: [[-0.1, 0.5, 0.005], [0.1, 0.5, 0.005]], rod_length: 0.01, radius: 0.006,
       bend_compliance: 1.0e-6}
    - {name: B, points: [[0.005, 0.5108, -0.1], [0.005, 0.5108, 0.1]], rod_length: 0.01, radius: 0.006,
       bend_compliance: 1.0e-6}
sim: {fps: 60, substeps: 20, iterations: 4}
fsm:
  - {run: Wait, with: {seconds: 1.0}}
"""


def without_step_zero(w):
    """``w`` with its solver's step 0 left out (what it changes is measured against that)."""
    w.solver.stages_zero = ()
    return w


def _after_one_frame(pre: bool):
    w = world_from_text(CROSSED)
    if not pre:
        without_step_zero(w)
    x0 = w.positions().astype(np.float64)
    w.step()
    x = w.positions().astype(np.float64)
    v = w.velocities().astype(np.float64)
    gap = w.solver.ropecol.measure()
    return w, x0, x, v, gap


@pytest.fixture(scope="module")
def frames():
    return {pre: _after_one_frame(pre) for pre in (False, True)}


def test_prestabilized_overlap_is_pushed_apart_without_speed(frames):
    """One frame from a 0.2 radius overlap, with step 0 and without: the overlap is gone, no push turned into
    speed, the centre of mass stayed and no rod stretched."""
    _, _, _, v_plain, _ = frames[False]
    w, x0, x, v, gap = frames[True]
    # Nothing but the overlap acts. Pushed out of it in one substep as speed, each rope would move at
    # 0.6 mm / (1/1200 s) = 0.72 m/s. The push is taken back out of the velocity (inelastic contacts),
    # with step 0 or without; what is left is the chain step after it moving the particles next to the
    # contact along their rods (0.022-0.023 m/s either way).
    push_speed = 0.0006 * 20 * 60
    for vel in (v, v_plain):
        assert np.linalg.norm(vel, axis=1).max() < 0.05 * push_speed
    radius = 0.006
    assert gap.min() > -0.02 * radius
    # Equal and opposite (split contacts), equal masses: the centre of mass stays where it was,
    # and each rope's rods keep their length.
    np.testing.assert_allclose(x.mean(axis=0), x0.mean(axis=0), atol=1e-6)
    strain = w.solver.measure()["strain"]
    assert strain.max() < 1e-3


@pytest.mark.parametrize("key", ["prestabilize: true", "rope_contacts: split"])
def test_rope_contact_solving_is_engine_behaviour_not_an_option(key):
    with pytest.raises(LevelError, match=key.split(":")[0]):
        load_level_from_string(CROSSED.replace("iterations: 4}", f"iterations: 4, {key}}}"))


def test_step_zero_runs_wherever_ropes_collide_and_profiles_as_it_steps(frames):
    cloth_only = world_from_text("""
version: 1
name: sheet
scene:
  cloths:
    - {name: c, resolution: [5, 5], size: [0.1, 0.1], center: [0, 1, 0]}
sim: {fps: 60, substeps: 20, iterations: 4}
fsm:
  - {run: Wait}
""")
    assert cloth_only.solver.ropecol is None and cloth_only.solver.stages_zero == ()  # nothing for it to do
    w = frames[True][0]
    assert w.solver.stages_zero  # settle, hash, rope contacts, chain step
    # One launch per pass (profile_substep) runs the same passes in the same order as the fused
    # substep: from the same state, three substeps each way end in the same positions.
    dt = 1.0 / (60 * 20)
    start = w.state.save()
    ends = []
    for step in ("substep", "profile_substep"):
        w.state.restore(start)
        w.solver.begin_frame()
        for k in range(3):
            getattr(w.solver, step)(dt, (k + 1) / 20, k, 20)
        ends.append(w.positions())
    np.testing.assert_allclose(ends[0], ends[1], atol=1e-7)
    assert "settle" in w.solver.timings


def test_step_zero_alone_pushes_the_overlap_apart_and_leaves_the_velocities():
    """Step 0 on the state a substep starts from: one contact pass and one chain step, before the
    prediction. The 0.2 radius overlap shrinks (by 30 % here: the crossing lies mid-rod, where the
    neighbouring rods' capsules share the contact and split the particles' masses between them) and
    no velocity changed."""
    w = world_from_text(CROSSED)
    s = w.solver
    s.begin_frame()
    before = s.ropecol.measure().min()
    gh, gmu = s._ground()
    s._run_k(s.stages_zero, 1.0 / (w.fps * w.substeps), 1.0 / w.substeps, gh, gmu)
    after = s.ropecol.measure().min()
    assert before < -0.19 * 0.006 and after > 0.8 * before
    assert np.abs(w.velocities()).max() == 0.0
