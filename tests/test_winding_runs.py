"""Rope levels run headless, ropes that move, and the Winding's options (tail, exit, pinch, clearance)."""

import pathlib

import numpy as np
import pytest

from sandbox.geometry.tube import sample_targets
from sandbox.levels import LevelError, load_level_from_string

import sandbox.maneuvers  # noqa: F401
from tests.levelkit import run_shipped as _run, world_from_text as _world

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_rope_wind_reaches_its_criteria_headless():
    s = _run("rope_wind.yaml")
    assert s["success"] and s["exit_code"] == 0, s["criteria"]


def _tied(level: str, knot: str) -> dict:
    """Run a shipped knot level headless; it passes, ties ``knot``; its criteria's values by metric."""
    s = _run(level)
    assert s["success"] and s["exit_code"] == 0, s["criteria"]
    value = {c["metric"]: c["value"] for c in s["criteria"]}
    assert value["knot"] == knot
    return value


def test_self_knot_ties_a_trefoil_headless():
    value = _tied("self_knot.yaml", "trefoil_left")
    # A tight trefoil in a 12 mm rope is more than a rope diameter across and holds more than
    # 0.1 m of rope (its ideal closed ropelength is 16.4 diameters, 0.2 m): the metrics measure it.
    assert 0.012 < value["knot_size"] <= 0.05 and 0.1 < value["knot_length"] <= 0.3, value


@pytest.mark.slow
def test_granny_knot_ties_a_granny_on_the_box_headless():
    """Two ropes tied by two half knots of the same sense read `granny_left` (a square would read
    `square`), one tight knot on the box top within every criterion (about 80 s on 2 cores)."""
    value = _tied("granny_knot.yaml", "granny_left")
    # Two half knots in a 12 mm rope, drawn together: more than one trefoil's worth of rope, one knot.
    assert 0.2 < value["knot_length"] <= 0.5 and 0.02 < value["knot_size"] <= 0.05, value


@pytest.mark.slow
def test_square_knot_ties_a_square_on_the_box_headless():
    """The granny's recipe with its second half mirrored (Crossing sign -1, Winding handedness +1) reads
    `square`, not a granny: one tight knot on the box top within every criterion."""
    value = _tied("square_knot.yaml", "square")
    assert 0.2 < value["knot_length"] <= 0.5 and 0.02 < value["knot_size"] <= 0.05, value


@pytest.mark.slow
@pytest.mark.parametrize(("contacts", "hold", "prestabilize", "inelastic"), [
    pytest.param("average", "fixed", False, False, marks=pytest.mark.xfail(
        strict=True, reason="known defect: averaged rope contacts let a held knot gain energy (docs/benchmarks.md, 'Held knots')")),
    pytest.param("balanced", "fixed", False, False, marks=pytest.mark.xfail(
        strict=True, reason="known defect: the tight trefoil held by fixed ends jitters past 5 m/s with balanced "
                            "contacts too (6.5 m/s, 0.025 -> 0.032 J); the level keeps pulling (docs/benchmarks.md, 'Tight knots')")),
    pytest.param("balanced", "fixed", True, False, marks=pytest.mark.xfail(
        strict=True, reason="with step 0 (sim.prestabilize) the held trefoil settles but not within the bar: "
                            "11 m/s in the first second of the hold, 5.1 m/s in the second, then at most 3.5 m/s; "
                            "0.027 J in the last second against 0.013 J in seconds 2-3 (docs/benchmarks.md, 'Held knots')")),
    # inelastic rope contacts: the fixed-end hold at most 0.27 m/s, 2.4e-4 J in the first second, 3.7e-5 J in the last
    ("balanced", "fixed", True, True),
    ("balanced", "pull", True, False),  # as shipped: the hands keep pulling once the knot is tight
])
def test_a_tied_knot_held_by_its_ends_comes_to_rest(contacts, hold, prestabilize, inelastic):
    """After the FSM the rope's kinetic energy may not grow (tools/hold_rest.py), with its ends held
    fixed (nothing drives the rope) or still pulled by the hands."""
    from sandbox.world import World

    text = (ROOT / "levels" / "self_knot.yaml").read_text()
    assert "hold: pull" in text
    level = load_level_from_string(text.replace("hold: pull", f"hold: {hold}"),
                                   overrides={"sim.rope_contacts": contacts, "sim.prestabilize": prestabilize,
                                              "sim.rope_inelastic": inelastic})
    w = World(level, base_dir=ROOT / "levels")
    w.attach_fsm()
    while not w.fsm.finished:
        w.step()
    assert w.fsm.succeeded
    inv = w.model.inv_mass.to_numpy().astype(np.float64)
    mass = np.where(inv > 0, 1.0 / np.maximum(inv, 1e-12), 0.0)
    energy, speed = [], []
    for _ in range(10 * w.fps):
        w.step()
        v = np.linalg.norm(w.velocities().astype(np.float64), axis=1)
        energy.append(0.5 * float((mass * v**2).sum()))
        speed.append(float(v.max()))
    # Seconds 2-3 once the pull's swing has died down, against the last second.
    settled, last = np.mean(energy[w.fps: 3 * w.fps]), np.mean(energy[-w.fps:])
    assert last <= 3.0 * settled and max(speed[w.fps:]) < 5.0, (settled, last, max(speed[w.fps:]))


@pytest.mark.slow
@pytest.mark.parametrize("level", ["rope_wind_2.yaml", "rope_wind_3.yaml"])
def test_more_turns_reach_their_criteria_headless(level):
    s = _run(level)
    assert s["success"], s["criteria"]


MOVING = """
version: 1
name: moving_pins
scene:
  ropes:
    - name: T
      points: [[-0.3, 0.5, 0], [0.3, 0.5, 0]]
      rod_length: 0.02
      radius: 0.01
      pins: [start, end]
      motion:
        keyframes:
          - {time: 0.0, position: [0, 0, 0]}
          - {time: 1.0, position: [0, 0.1, 0.2], rotation: [0, 90, 0]}
fsm:
  - {run: Wait, with: {seconds: 2}}
"""


def test_rope_pins_follow_their_motion():
    """Pins are carried by the keyframed pose: halfway at t = 0.5 s, at the last pose after t = 1 s."""
    from sandbox.model.pose import euler_matrix

    w = _world(MOVING)
    x0 = w.rope_positions("T")[[0, -1]].astype(float)
    for _ in range(30):
        w.step()
    half = x0 @ euler_matrix([0, 45, 0]).T + [0, 0.05, 0.1]
    np.testing.assert_allclose(w.rope_positions("T")[[0, -1]], half, atol=1e-5)
    for _ in range(40):
        w.step()
    end = x0 @ euler_matrix([0, 90, 0]).T + [0, 0.1, 0.2]
    np.testing.assert_allclose(w.rope_positions("T")[[0, -1]], end, atol=1e-5)


def test_rope_motion_needs_pins():
    with pytest.raises(LevelError, match="give 'pins'"):
        load_level_from_string(MOVING.replace("      pins: [start, end]\n", ""), base_dir=ROOT / "levels")


def test_an_attached_particle_keeps_its_place_on_a_moving_rope():
    """World.attach: the held particle keeps its offset in the frame of the nearest rod of T."""
    text = MOVING.replace("""    - name: T""", """    - name: C
      points: [[0.0, 0.52, 0], [0.0, 0.9, 0]]
      rod_length: 0.02
      radius: 0.005
      pins: [start]
    - name: T""")
    w = _world(text)
    c0 = w.site_particles("C", "start")[0]
    w.attach(c0, "T")
    a = w.attachments[0]
    for _ in range(60):
        xr = w.rope_positions("T").astype(float)  # targets follow T as it was when the frame began
        w.step()
    # T was carried and turned by 90 degrees: in the frame of the rod the offset is unchanged.
    e1 = xr[a["rod"] + 1] - xr[a["rod"]]
    e1 /= np.linalg.norm(e1)
    frame = np.stack([e1, a["e2"], np.cross(e1, a["e2"])])
    np.testing.assert_allclose(frame @ (w.positions()[c0] - xr[a["rod"]]), a["local"], atol=1e-4)
    assert abs(e1[2]) > 0.99  # the rod really turned from x to z
    w.control.release([c0])
    w.step()
    assert not w.attachments  # a released particle is no longer attached


@pytest.mark.slow
def test_rope_wind_moving_reaches_its_criteria_headless():
    s = _run("rope_wind_moving.yaml")
    assert s["success"] and s["exit_code"] == 0, s["criteria"]


def _wind_with_tail(carry: float):
    text = (ROOT / "levels" / "rope_wind.yaml").read_text()
    text = text.replace("handedness: 1}, timeout: 150}", f"handedness: 1, carry_tail: {carry}}}, timeout: 150}}")
    w = _world(text)
    tip = w._rope("C").end - 1
    held = []
    while w.fsm.state != "2:Wait" and not w.fsm.finished:
        w.step()
        if w.fsm.state == "1:Winding":
            held.append(bool(w.control.is_driven([tip])[0]))
    return w, tip, held


def test_winding_carries_the_tail_along_the_geodesic_tangent():
    """With carry_tail the hand keeps C's tip and ends holding it out along G's last tangent."""
    w, tip, held = _wind_with_tail(0.5)
    assert w.fsm.state == "2:Wait", w.fsm.events
    assert held and all(held)
    x = w.positions().astype(np.float64)
    c = w._rope("C")
    last = max(int(i) for i in w.windings[("C", "T")]["particles"])
    left = (tip - last) * c.rod_length
    out = x[tip] - x[last]
    # Held out by half the tail's length (within the rate limit's lag and the last target's tolerance).
    assert np.linalg.norm(out) == pytest.approx(0.5 * left, rel=0.25)
    # The carried tail does not change the winding: still one turn.
    from sandbox.io.criteria import _winding_number
    assert _winding_number(w, ["C", "T"]) == pytest.approx(1.0, abs=0.15)


def test_winding_without_carry_lets_the_tail_go():
    _, _, held = _wind_with_tail(0.0)
    assert held and not any(held[1:])


def _wind(extra: str, until_k: int | None = None):
    """rope_wind with extra Winding parameters, run until the winding is done (or has laid ``until_k`` particles)."""
    text = (ROOT / "levels" / "rope_wind.yaml").read_text()
    text = text.replace("handedness: 1}, timeout: 150}", f"handedness: 1, {extra}}}, timeout: 300}}")
    w = _world(text)
    m, i0_held_midway = None, None
    while w.fsm.state != "2:Wait" and not w.fsm.finished:
        w.step()
        if w.fsm.state == "1:Winding":
            m = w.fsm._maneuver
            if m.k == 2:
                i0_held_midway = bool(w.control.is_driven([m._particle(0)])[0])
            if until_k is not None and m.k >= until_k:
                return w, m, i0_held_midway
    assert w.fsm.state == "2:Wait", w.fsm.events
    return w, m, i0_held_midway


# The plain exit in the slow run only: the square one takes the same path and also projects the tangent.
@pytest.mark.parametrize("square", [pytest.param(False, marks=pytest.mark.slow), True])
def test_winding_exit_lays_the_tail_straight_out_of_the_turns(square):
    """``exit`` drives C's particles after the turns onto a line from G's end along its last tangent."""
    w, m, i0_held_midway = _wind("exit: 0.06" + (", exit_square: true" if square else ""))
    assert i0_held_midway is False  # without pinch the crossing particle is let go once the next is laid
    x = w.positions().astype(np.float64)
    turns = m.n_turns
    assert m.n == turns + 6  # 0.06 m at C's 0.01 m rods
    g = sample_targets(m.geodesic, m.c.rod_length)
    t = g[-1] - g[-2]
    if square:
        t = t - (t @ m.geodesic.x_hat) * m.geodesic.x_hat
        assert abs(float(t @ m.geodesic.x_hat)) < 1e-9
    t /= np.linalg.norm(t)
    line = g[-1] + np.outer(np.arange(1, 7) * m.c.rod_length, t)
    np.testing.assert_allclose(m.targets[turns:], line, atol=1e-9)
    exit_particles = [m._particle(k) for k in range(turns - 1, m.n)]
    # The last one is held at the line's end (the others are let go as the next one is laid).
    np.testing.assert_allclose(x[exit_particles[-1]], line[-1], atol=0.25 * m.c.rod_length)
    assert w.control.is_driven([exit_particles[-1]])[0] and not w.control.is_driven(exit_particles[1:-1]).any()
    # The knot's record (Tightening pulls away from its centre) is the turns alone.
    rec = w.windings[("C", "T")]["particles"]
    assert rec.max() == m._particle(turns - 1) and rec.min() == m._particle(0)


@pytest.mark.slow  # the default run checks the pinch in test_knot_reach and its absence in the exit test
def test_winding_pinch_holds_the_crossing_until_the_end():
    _, m, held_midway = _wind("pinch: true")
    assert held_midway
    w = m.world
    assert w.control.is_driven([m._particle(0), m._particle(m.n - 1)]).all()
    _, m2, held2 = _wind("pinch: false", until_k=3)  # let go as soon as the next particle is laid
    assert not held2 and not m2.world.control.is_driven([m2._particle(0)])[0]


SHIFTS = [(0, 0, 0), (0, 0.01, 0), (0, -0.02, 0), (0, 0.3, 0), (0.05, 0, 0), (0, 0, 0.3)]


@pytest.mark.slow
def test_self_knot_ties_a_trefoil_wherever_the_rope_hangs():
    """The knot's identity does not hinge on the exact placement alone (measured as shipped, balanced
    rope contacts and step 0: 5 of 6, each within every criterion; without step 0 4 of 6; with averaged
    contacts 3 of 6, 5 of 6 before the chain step's guards, 1 of 6 with the tail let go)."""
    import sys
    sys.path.insert(0, str(ROOT / "tools"))
    from sweep_level import shifted_ropes

    tied = 0
    for shift in SHIFTS:
        s = _run("self_knot.yaml", shifted_ropes(ROOT / "levels" / "self_knot.yaml", shift))
        tied += next(c["value"] for c in s["criteria"] if c["metric"] == "knot") == "trefoil_left"
    assert tied >= 3, tied


@pytest.mark.parametrize("clearance", [pytest.param(0.1, marks=pytest.mark.slow), 0.3])
def test_winding_clearance_sets_the_tube_its_targets_lie_on(clearance):
    """The targets lie on the bounding tube R = (1 + clearance)(r_C + r_T) around T's axis (straight here)."""
    text = (ROOT / "levels" / "rope_wind.yaml").read_text()
    text = text.replace("handedness: 1}, timeout: 150}", f"handedness: 1, clearance: {clearance}}}, timeout: 150}}")
    w = _world(text)
    while w.fsm.state != "1:Winding":
        w.step()
    m = w.fsm._maneuver
    assert m.R == pytest.approx((1 + clearance) * (0.005 + 0.01))
    g = m.targets[: m.n_turns]
    np.testing.assert_allclose(np.hypot(g[:, 1] - 0.5, g[:, 2]), m.R, rtol=1e-2)  # T sags by under 0.1 mm


# Rigid shifts of the whole scene, 0.2 mm to 2 mm (docs/benchmarks.md, "How robust the winding levels are").
SMALL_SHIFTS = [(0.0002, 0, 0), (0, 0.0002, 0), (0, 0, 0.0002), (0.001, 0, 0), (0, 0.001, 0), (0, 0, -0.001),
                (0.002, 0, 0), (0, 0, 0.002)]


@pytest.mark.slow
@pytest.mark.parametrize(("level", "least"), [("rope_wind.yaml", 8), ("rope_wind_moving.yaml", 6)])
def test_winding_levels_pass_when_the_scene_is_shifted_slightly(level, least):
    """A winding level passes wherever its scene sits to a millimetre or two, not only where it is
    placed. Measured: rope_wind 8 of 8; rope_wind_moving 6 of 8 (its wraps whip at 0.2 mm in depth,
    and 1 mm sideways ends at strain 1.06 %: averaged rope contacts, a known defect)."""
    import sys
    sys.path.insert(0, str(ROOT / "tools"))
    from sweep_level import shifted_scene

    passed = [_run(level, shifted_scene(ROOT / "levels" / level, shift))["success"] for shift in SMALL_SHIFTS]
    assert sum(passed) >= least, passed
