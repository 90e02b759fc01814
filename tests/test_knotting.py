"""Crossing, Tightening (with its push), strands and the knot criterion."""

import pathlib

import numpy as np
import pytest

from sandbox.geometry.knots import identify_knot, touch_extent, touch_length
from sandbox.geometry.tube import smooth_axis
from sandbox.levels import LevelError, load_level_from_string
from sandbox.maneuvers.knotting import closest_approach, crossing_targets, knot_exit
from sandbox.model.strands import parse_strand
from sandbox.maneuvers.tightening import SETTLE_FRAMES
from sandbox.model.model import GRIP_GIVE
from sandbox.record import WindingRecord

import sandbox.maneuvers  # noqa: F401
from tests.levelkit import world_from_text as _world, step_until_finished

ROOT = pathlib.Path(__file__).resolve().parents[1]


# -- strands -----------------------------------------------------------------------------------


@pytest.mark.parametrize("ref, parsed", [
    ("R", ("R", None, None)), ("R[10:40]", ("R", 10, 40)), ("R[40:]", ("R", 40, None)),
    ("R[:-5]", ("R", None, -5)), (" rope_2 [ 3 : 7 ] ", ("rope_2", 3, 7)),
])
def test_parse_strand(ref, parsed):
    assert parse_strand(ref) == parsed


@pytest.mark.parametrize("ref", ["R[1:2:3]", "R[a:b]", "[1:2]", "R[1]", ""])
def test_parse_strand_rejects_bad_refs(ref):
    with pytest.raises(ValueError, match="bad strand"):
        parse_strand(ref)


ONE_ROPE = """
version: 1
name: strands
scene:
  ropes:
    - {name: R, points: [[0, 1, 0], [1, 1, 0]], rod_length: 0.1, radius: 0.01}
fsm:
  - {run: Wait}
success:
  - {metric: max_strain, of: "R[2:5]", max: 0.01}
"""


def test_strands_index_into_their_rope():
    w = _world(ONE_ROPE)
    assert len(w.rope_positions("R")) == 11
    part = w.rope("R[2:5]")
    assert (part.start, part.end, part.name) == (2, 5, "R[2:5]")
    np.testing.assert_array_equal(w.rope_positions("R[-3:]"), w.rope_positions("R")[-3:])
    np.testing.assert_array_equal(w.site_particles("R[4:]", "start"), [4])
    with pytest.raises(ValueError, match="at least 2"):
        w.rope("R[5:6]")
    with pytest.raises(KeyError, match="no rope named 'Q'"):
        w.rope("Q[1:3]")


def test_criterion_on_unknown_strand_rope_is_a_level_error():
    with pytest.raises(LevelError, match="strand 'Q\\[2:5\\]': unknown rope 'Q'"):
        load_level_from_string(ONE_ROPE.replace('of: "R[2:5]"', 'of: "Q[2:5]"'))


# -- geometry ----------------------------------------------------------------------------------


@pytest.mark.parametrize("sign", [1, -1])
def test_crossing_targets_cross_at_x(sign):
    """Bottom -> X -> tip is one rising path per strand; in the x-y plane they cross at X."""
    bc, bt = np.array([0.2, 0.1, 0.3]), np.array([-0.2, 0.1, 0.3])
    gap = 0.02
    x, tc, tt, xh, zh = crossing_targets(bc, bt, 0.6, 0.6, height=0.15, sign=sign, gap=gap, slack=0.9)
    np.testing.assert_allclose(x, [0.0, 0.25, 0.3])
    np.testing.assert_allclose(xh, [-1, 0, 0], atol=1e-12)
    # Each tip is slack * length from its bottom, beyond X on the other side.
    for b, tip in ((bc, tc), (bt, tt)):
        through = x + (np.sign((tip - x) @ zh) or 1) * 0.5 * gap * zh
        assert np.linalg.norm(through - b) + np.linalg.norm(tip - through) == pytest.approx(0.54)
    assert (tc - x) @ xh > 0 and (tt - x) @ xh < 0  # C ends on T's side and vice versa
    assert np.sign((tc - x) @ zh) == sign and np.sign((tt - x) @ zh) == -sign


def test_crossing_targets_across_sets_x_when_the_bottoms_coincide():
    """Two strands leaving one knot: x runs along ``across``, not between the (equal) bottoms."""
    b = np.array([0.0, 0.4, 0.0])
    x, tc, tt, xh, _ = crossing_targets(b, b + 1e-4, 0.5, 0.5, height=0.1, sign=1, gap=0.02,
                                        across=[0.0, 0.3, -2.0])
    np.testing.assert_allclose(xh, [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(x, b + 0.5e-4 + [0, 0.1, 0], atol=1e-12)
    assert (tc - x) @ xh > 0 and (tt - x) @ xh < 0


def test_crossing_targets_bring_x_within_a_short_strands_reach():
    """X rises ``height`` above the bottoms' midpoint only as far as both strands reach: a strand with a short
    tail has X brought within ``X_REACH`` of its reach, and the tips still lie beyond X on the other side."""
    from sandbox.maneuvers.knotting import X_REACH

    bc, bt = np.array([0.2, 0.1, 0.3]), np.array([-0.2, 0.1, 0.3])
    x, tc, tt, xh, _ = crossing_targets(bc, bt, 0.6, 0.15, height=0.15, sign=1, gap=0.02, slack=0.9)
    assert np.linalg.norm(x - bt) == pytest.approx(X_REACH * 0.9 * 0.15, rel=1e-6)  # on the short strand's ball
    assert np.linalg.norm(x - bc) <= X_REACH * 0.9 * 0.6
    assert x[1] < 0.25  # lower than the 0.15 m asked
    assert (tc - x) @ xh > 0 and (tt - x) @ xh < 0


def _Strand(name, start, end, radius=0.005, rod_length=0.01, whole=None):
    """A rope strand over particles [start, end) of a rope spanning ``whole`` (default: the strand itself)."""
    from sandbox.model.builder import RopeRange
    from sandbox.model.strands import rope_strand

    lo, hi = whole or (start, end)
    rope = RopeRange(name.split("[")[0], lo, hi, rod_length, radius, (0, 0, 0))
    return rope_strand(RopeRange(name, start, end, rod_length, radius, (0, 0, 0)), rope)


def test_knot_exit_is_the_touching_particle_nearest_the_tip():
    """Rope A runs along x and touches B (a vertical rope at x = 0.2) only at A's particle 20."""
    t = np.arange(41) * 0.01
    a = np.stack([t, 0 * t, 0 * t], 1)
    b = np.stack([0.2 + 0 * t[:21], t[:21] - 0.1, 0.012 + 0 * t[:21]], 1)  # 12 mm apart, < 1.5 (r + r)
    x = np.vstack([a, b])
    A, B = _Strand("A", 0, 41), _Strand("B", 41, 62)
    assert knot_exit(x, A, [B], toward=40) == 20
    assert knot_exit(x, B, [A], toward=61) == 41 + 10  # B's particle at y = 0
    far = x.copy()
    far[41:, 2] = 0.05
    assert knot_exit(far, A, [B], toward=40) is None
    # One rope folded on itself: particles within its own bend do not count as touching.
    assert knot_exit(a, _Strand("R[:20]", 0, 20, whole=(0, 41)), [_Strand("R[20:]", 20, 41, whole=(0, 41))],
                     toward=0) is None


def test_closest_approach_skips_the_same_bend():
    t = np.linspace(0, 1, 11)
    a = np.stack([t, 0 * t, 0 * t], 1)
    b = np.stack([0.5 + 0 * t, t - 0.5, 0.05 + 0 * t], 1)
    d, i, j = closest_approach(a, b)
    assert d == pytest.approx(0.05) and a[i, 0] == pytest.approx(0.5) and b[j, 1] == pytest.approx(0.0)
    # Every pair the same bend: nothing is left but inf.
    d, _, _ = closest_approach(a, b, np.zeros((11, 11), bool))
    assert d == np.inf
    # A rope folded back on itself 5 cm apart: as two ropes every facing pair is 5 cm apart, the pair at
    # the fold included; as two strands of one rope the fold's pairs (within half a turn of the tube
    # along the rope: 2.35 rods here) are the same bend and skipped.
    from sandbox.maneuvers.knotting import strand_approach

    back = np.stack([1.0 - t, 0.05 + 0 * t, 0 * t], 1)
    x = np.vstack([a, back])
    one = (_Strand("R[:11]", 0, 11, rod_length=0.1, whole=(0, 22)), _Strand("R[11:]", 11, 22, rod_length=0.1, whole=(0, 22)))
    two = (_Strand("P", 0, 11, rod_length=0.1), _Strand("Q", 11, 22, rod_length=0.1))
    assert closest_approach(a, back)[0] == pytest.approx(0.05)
    assert strand_approach(x, *two)[0] == pytest.approx(0.05)
    d, i, j = strand_approach(x, *one)
    assert d == pytest.approx(0.05) and (11 + j) - i > 2.35


def test_smooth_axis_removes_kinks_and_respects_max_shift():
    s = np.linspace(0, 1, 51)
    x = np.stack([s, 0.002 * (-1.0) ** np.arange(51), 0 * s], 1)  # a 2 mm zigzag
    y = smooth_axis(x, 0.05)
    assert np.abs(y[5:-5, 1]).max() < 1e-4
    np.testing.assert_array_equal(y[[0, -1]], x[[0, -1]])
    bent = np.stack([s, np.where(s < 0.5, 0.0, s - 0.5), 0 * s], 1)  # a corner
    y = smooth_axis(bent, 0.1, max_shift=0.001)
    assert np.linalg.norm(y - bent, axis=1).max() <= 0.001 + 1e-12
    assert np.linalg.norm(smooth_axis(bent, 0.1) - bent, axis=1).max() > 0.005


# -- maneuvers in a scene ------------------------------------------------------------------------

TWO_ROPES = """
version: 1
name: cross_two
scene:
  gravity: [0, -9.81, 0]
  ropes:
    - {name: A, points: [[-0.15, 0.3, 0], [-0.15, 0.8, 0]], rod_length: 0.02, radius: 0.008}
    - {name: B, points: [[0.15, 0.3, 0], [0.15, 0.8, 0]], rod_length: 0.02, radius: 0.008}
sim: {fps: 60, substeps: 10, iterations: 2}
fsm:
  - {run: Anchoring, with: {body: A, sites: [start, end]}}
  - {run: Anchoring, with: {body: B, sites: [start, end]}}
  - {run: Crossing, with: {active: A, target: B, height: 0.15, sign: SIGN, slack: 0.95}, timeout: 300}
"""


@pytest.mark.parametrize("sign", [1, -1])
def test_crossing_two_ropes_makes_a_crossing_of_the_asked_sign(sign):
    w = _world(TWO_ROPES.replace("SIGN", str(sign)))
    step_until_finished(w, 300)
    assert w.fsm.succeeded, w.fsm.events
    a, b = w.rope_positions("A"), w.rope_positions("B")
    x = w.record.crossings[("A", "B")]
    assert 0.3 < x[1] < 0.6  # above the held bottoms
    # Tips have swapped sides along x, and where they pass A is on the asked z side of B.
    assert a[-1, 0] > 0.0 > b[-1, 0]
    ia = np.argmin(np.abs(a[:, 0] - x[0]))
    ib = np.argmin(np.abs(b[:, 0] - x[0]))
    zhat = np.cross([1.0, 0, 0], [0, 1.0, 0])  # x runs from A's bottom to B's
    assert np.sign((a[ia] - b[ib]) @ zhat) == sign
    gap = w.solver.ropecol.measure()
    assert gap.min() > -0.1 * 0.008


def test_crossing_moves_the_tip_again_when_the_strands_miss():
    """A target that does not move (``target_tip: null``) leans back from its bottom, out of the crossing's
    plane: C's tip, arrived where it was planned, passes T about 10 cm in front of it. The hand then moves the
    tip again so that C passes just in front of T where T passes nearest X, and the Crossing succeeds with the
    asked sign (it used to fail after 4 s)."""
    text = TWO_ROPES.replace("SIGN", "1").replace("slack: 0.95}", "slack: 0.95, target_tip: null}")
    w = _world(text.replace("[[0.15, 0.3, 0], [0.15, 0.8, 0]]", "[[0.15, 0.3, 0], [0.15, 0.8, -0.3]]"))
    step_until_finished(w, 300)
    assert w.fsm.succeeded, w.fsm.events
    done = [e for e in w.fsm.events if e["type"] == "done" and "Crossing" in e["state"]]
    assert "moved again" in done[0]["message"], done
    a, b = w.rope_positions("A"), w.rope_positions("B")
    assert np.abs(b[:, 0] - 0.15).max() < 0.01 and b[-1, 2] < -0.29  # T stayed where it was held
    d = np.linalg.norm(a[:, None] - b[None], axis=2)
    i, j = np.unravel_index(np.argmin(d), d.shape)
    assert d[i, j] <= 1.5 * 0.016 + 0.016  # within the crossing's gap + radii
    assert a[i, 2] > b[j, 2]  # C in front of T (sign +1: on +z)


def _with_box(text: str, centre, size: float) -> str:
    box = (f"  ground: {{height: 0.0}}\n  objects:\n    - {{name: box, shape: box, params: {{size: [{size}, {size}, {size}]}}, "
           f"position: [{centre[0]:.6f}, {centre[1]:.6f}, {centre[2]:.6f}]}}\n  ropes:")
    return text.replace("  ropes:", box, 1)


def test_clear_of_solids_moves_points_a_clearance_out_of_objects_and_above_the_ground():
    """Closed forms on a 0.2 m box standing at (0, 0.5, 0), its top at 0.7: out through the nearest
    face, round an edge, above the ground; points already clear stay where they are."""
    w = _world(_with_box(TWO_ROPES.replace("SIGN", "1"), (0.0, 0.5, 0.0), 0.2))
    c = 0.01
    pts = np.array([[0.0, 0.69, 0.0],       # inside, 1 cm under the top face
                    [0.105, 0.705, 0.0],    # outside, 7 mm from the top edge at (0.1, 0.7)
                    [0.0, 0.75, 0.0],       # clear
                    [0.5, 0.004, 0.0]])     # 4 mm above the ground
    out = w.clear_of_solids(pts, c)
    np.testing.assert_allclose(out[0], [0.0, 0.71, 0.0], atol=1e-5)
    edge = np.array([0.1, 0.7, 0.0])
    np.testing.assert_allclose(np.linalg.norm(out[1] - edge), c, atol=1e-5)
    np.testing.assert_allclose((out[1] - edge) / c, (pts[1] - edge) / np.linalg.norm(pts[1] - edge), atol=1e-4)
    np.testing.assert_array_equal(out[2], pts[2])
    np.testing.assert_allclose(out[3], [0.5, c, 0.0], atol=1e-7)


def test_crossing_hands_go_round_an_object_in_their_way():
    """A box right across a tip's straight way: the hand carries the tip round it, a radius clear.
    (A driven particle takes no contacts: a hand through the box would drag the rope through it.)"""
    plain = _world(TWO_ROPES.replace("SIGN", "1"))
    while not hasattr(plain.fsm._maneuver, "moves"):
        plain.step()
    idx, _, ways = plain.fsm._maneuver.moves[0]
    centre = 0.5 * (ways[1] + ways[2])  # the middle of its way across
    w = _world(_with_box(TWO_ROPES.replace("SIGN", "1"), centre - [0.0, 0.02, 0.0], 0.04))  # a box stands on its base
    r = 0.008
    nearest = np.inf
    for _ in range(300):
        w.step()
        d, _, _ = w.objects.query_numpy(w.positions()[idx])
        nearest = min(nearest, float(d.min()))
        if w.fsm.finished:
            break
    assert w.fsm.finished
    assert nearest >= r - 1e-4, nearest


JOINED = """
version: 1
name: cross_joined
scene:
  gravity: [0, -9.81, 0]
  ropes:
    - {name: A, points: [[-0.01, 0.3, 0], [-0.15, 0.3, 0], [-0.15, 0.8, 0]], rod_length: 0.01, radius: 0.006}
    - {name: B, points: [[0.01, 0.3, 0], [0.15, 0.3, 0], [0.15, 0.8, 0]], rod_length: 0.01, radius: 0.006}
sim: {fps: 60, substeps: 10, iterations: 2}
fsm:
  - {run: Anchoring, with: {body: A, sites: [start, 14, end]}}
  - {run: Anchoring, with: {body: B, sites: [start, 14, end]}}
  - {run: Crossing, with: {active: B, target: A, active_base: 14, target_base: 14, height: 0.12, slack: 0.97},
     timeout: 300}
"""


def test_crossing_is_found_between_the_bottoms_and_the_tips():
    """Standing ends held side by side below the bottoms (two corners a cloth joins) are not the crossing."""
    w = _world(JOINED)
    step_until_finished(w, 300)
    assert w.fsm.succeeded, w.fsm.events
    x = w.record.crossings[("B", "A")]
    assert x[1] > 0.3 + 0.06, x  # up where the strands cross, not at the held ends (0.02 m apart)
    assert abs(x[0]) < 0.05


SIDE_BY_SIDE = """
version: 1
name: side_by_side
scene:
  gravity: [0, -9.81, 0]
  ropes:
    - {name: A, points: [[-0.008, 0.3, 0], [-0.008, 0.8, 0]], rod_length: 0.01, radius: 0.006}
    - {name: B, points: [[0.008, 0.3, 0], [0.008, 0.8, 0]], rod_length: 0.01, radius: 0.006}
sim: {fps: 60, substeps: 10, iterations: 2}
fsm:
  - {run: Anchoring, with: {body: A, sites: [start, 9, 25, end]}}
  - {run: Anchoring, with: {body: B, sites: [start, 9, 25, end]}}
  - {run: Crossing, with: {active: B, target: A, active_base: [0.008, 0.4, 0], target_base: [-0.008, 0.4, 0],
                           height: 0.12, slack: 0.97OFFSET}, timeout: 300}
"""


def test_strands_cross_above_place_bottoms_and_the_hands_take_them_from_there():
    """Two strands standing up from a U (two cloth corners stood up on an object's top, apart), their
    bottoms given as places 0.1 m up (particle 10, not held before): each bottom is pinched where it
    is, what earlier hands held between it and the tip (particle 25) is let go, holds below the bottoms
    (particle 9) stay, and the strands cross above the bottoms, beyond the same bend."""
    text = (SIDE_BY_SIDE.replace("OFFSET", "").replace("-0.008", "-0.1").replace("0.008", "0.1"))
    w = _world(text)
    started = False
    for _ in range(300):
        w.step()
        m = w.fsm._maneuver
        if m is not None and m.name == "Crossing" and not started:
            started = True
            assert w.control.is_driven([10, w.rope("B").start + 10]).all()  # the bottoms: pinched
            assert not w.control.is_driven([25, w.rope("B").start + 25]).any()  # between: let go
        if w.fsm.finished:
            break
    assert started and w.fsm.succeeded, w.fsm.events
    x = w.record.crossings[("B", "A")]
    assert x[1] > 0.4 + 0.03, x  # above the bottoms (0.4 m)
    assert w.control.is_driven([9, w.rope("B").start + 9]).all()  # below the bottoms the holds stay


def test_the_crossing_is_sought_beyond_the_same_bend_from_each_bottom():
    """Strands whose bottoms touch pass closest there: the part searched for the crossing leaves out the
    particles within the same bend (half a tube turn plus two rods) of the bottom, at whichever end of
    the part the bottom is, and keeps at least two at the tip's end."""
    from sandbox.maneuvers.knotting import _off_bottom, _same_bend

    w = _world(SIDE_BY_SIDE.replace("OFFSET", ""))
    a, b = w.strand("A"), w.strand("B")
    k = int(np.ceil(_same_bend(a, b) / a.rod_length))
    assert k == 7  # pi 1.1 (0.006 + 0.006) / 0.01 + 2 = 6.15 rods, rounded up
    up = a.part(10, 50)
    np.testing.assert_array_equal(_off_bottom(up, np.array([10]), b).idx, a.idx[10 + k:51])
    np.testing.assert_array_equal(_off_bottom(up, np.array([50]), b).idx, a.idx[10:51 - k])
    short = a.part(10, 13)
    np.testing.assert_array_equal(_off_bottom(short, np.array([10]), b).idx, a.idx[12:14])


def test_contact_offset_from_a_place_bottom_pinches_the_strand_above_it():
    """``contact_offset`` from a bottom given as a place: the pinch is that far towards the tip."""
    w = _world(SIDE_BY_SIDE.replace("OFFSET", ", contact_offset: 0.05"))
    while w.fsm._maneuver is None or w.fsm._maneuver.name != "Crossing":
        w.step()
    w.step()
    assert w.control.is_driven([15, w.rope("B").start + 15]).all()  # 5 rods of 0.01 m above particle 10
    spread = ", contact_offset: 0.05, contact_spread: 0.05"
    load_level_from_string(SIDE_BY_SIDE.replace("OFFSET", spread))  # from two places: accepted
    with pytest.raises(LevelError, match="contact_spread carries two pinched bottoms apart"):
        load_level_from_string(SIDE_BY_SIDE.replace("OFFSET", spread).replace(
            "active_base: [0.008, 0.4, 0]", "active_base: 10"))


PULL = """
version: 1
name: pull
scene:
  ropes:
    - {name: R, points: [[-0.3, 0.5, 0], [0.3, 0.5, 0]], rod_length: 0.02, radius: 0.005}
sim: {fps: 60, substeps: 10, iterations: 2}
fsm:
  - {run: Tightening, with: {pulls: [{body: R, site: start, direction: [-1, 0, 0]},
                                     {body: R, site: end, direction: [1, 0, 0]}],
                             speed: 0.2, distance: 0.2, max_strain: 0.003}}
"""


def test_tightening_stops_when_the_rope_is_taut():
    """A straight rope pulled at both ends is taut at once: the ends give back and hold."""
    w = _world(PULL)
    x0 = w.rope_positions("R").copy()
    step_until_finished(w, 120)
    assert w.fsm.succeeded
    for _ in range(30):  # the ends stay held where the maneuver left them
        w.step()
    x = w.rope_positions("R")
    assert w.control.is_driven([0, len(x) - 1]).all()
    seg = np.linalg.norm(np.diff(x, axis=0), axis=1)
    assert np.abs(seg / 0.02 - 1).max() < 0.01
    # Held back inside the rope's reach, not pulled the full 0.2 m.
    assert np.linalg.norm(x[-1] - x[0]) <= np.linalg.norm(x0[-1] - x0[0]) + 1e-3


SLACK_PULL = """
version: 1
name: slack_pull
scene:
  ropes:
    - {name: R, points: [[-0.2, 0.5, 0], [0, 0.36733, 0], [0.2, 0.5, 0]], rod_length: 0.02,
       radius: 0.005, mass: 0.05}
sim: {fps: 60, substeps: 10, iterations: 2}
fsm:
  - {run: Anchoring, with: {body: R, sites: [start, end]}}
  - {run: Wait, with: {seconds: 0.5}}
  - {run: Tightening, with: {pulls: [{body: R, site: end, direction: [1, 0, 0]}],
                             keep: [{body: R, sites: [start]}], force: 1.0, speed: 0.2, settle_speed: 0.002,
                             distance: 0.5}}
"""


def test_tightening_by_force_pulls_until_the_rope_stops_then_holds():
    """An end pulled by a force (no set path) straightens a slack rope, stops and is held where it stopped.

    The other end is kept. At rest the horizontal pull F balances the rope's
    weight W about the kept end: the (nearly straight) rope hangs
    tan(phi) = W / (2F) below the horizontal, 13.8 degrees here.
    """
    w = _world(SLACK_PULL)
    x0 = w.rope_positions("R").copy()
    length = 0.02 * (len(x0) - 1)
    n = len(x0)
    for _ in range(60):
        w.step()
        if "Tightening" in w.fsm.state:
            break
    assert w.control.is_pulled([n - 1]).all() and w.control.is_driven([0]).all()
    kept = w.rope_positions("R")[0].copy()
    prev = w.rope_positions("R")[-1].copy()
    top = 0.0
    for _ in range(700):
        w.step()
        now = w.rope_positions("R")[-1]
        top = max(top, float(np.linalg.norm(now - prev)) * 60)
        prev = now.copy()
        if w.fsm.finished:
            break
    assert w.fsm.succeeded, w.fsm.events
    assert top <= 0.2 * 1.05  # never faster than force / drag
    x = w.rope_positions("R")
    assert w.control.is_driven([0, n - 1]).all()  # held where it stopped
    np.testing.assert_allclose(x[0], kept, atol=1e-6)  # the kept end did not move
    span = x[-1] - x[0]
    assert 0.97 * length < float(np.linalg.norm(span)) <= 1.005 * length  # pulled straight, not stretched
    phi = np.degrees(np.arctan2(-span[1], span[0]))
    # Stopped means the end moves slower than settle_speed: what is left of the
    # pull's imbalance is at most drag * settle_speed = 0.01 N of F = 1 N.
    assert phi == pytest.approx(np.degrees(np.arctan(0.05 * 9.81 / 2.0)), abs=1.5)
    seg = np.linalg.norm(np.diff(x, axis=0), axis=1)
    assert np.abs(seg / 0.02 - 1).max() < 0.01
    assert w.control.is_gripped([n - 1]).all()  # the pulling hand grips it: it gives, the kept hand does not
    for _ in range(30):
        w.step()
    x1 = w.rope_positions("R")
    np.testing.assert_allclose(x1[0], x[0], atol=1e-6)
    assert np.linalg.norm(x1[-1] - x[-1]) < GRIP_GIVE  # pulled on as hard as before, it stays within the grip's give


def _heads_toward(w, goal: np.ndarray) -> np.ndarray:
    """Step until the Tightening starts; over the next 10 frames R's pulled end heads for ``goal``.
    Returns where the end was when the Tightening started."""
    for _ in range(60):
        w.step()
        if "Tightening" in w.fsm.state:
            break
    start = w.rope_positions("R")[-1].copy()
    for _ in range(10):
        w.step()
    moved = w.rope_positions("R")[-1] - start
    assert moved @ (goal - start) / (np.linalg.norm(moved) * np.linalg.norm(goal - start)) > 0.9
    return start


def test_tightening_by_force_toward_a_point_keeps_aiming_at_it():
    """A pull ``toward`` a point turns with the end: the end heads for the point and stops short of it."""
    goal = np.array([0.5, 0.9, 0.0])
    w = _world(SLACK_PULL.replace("direction: [1, 0, 0]", "toward: [0.5, 0.9, 0]"))
    start = _heads_toward(w, goal)
    step_until_finished(w, 700)
    assert w.fsm.succeeded, w.fsm.events
    x = w.rope_positions("R")
    length = 0.02 * (len(x) - 1)
    # The rope's reach stops it; the pull (1 N) outweighs the rope (0.49 N), so it ends above the kept end.
    assert float(np.linalg.norm(x[-1] - x[0])) == pytest.approx(length, rel=0.03)
    assert x[-1, 1] > x[0, 1]
    assert np.linalg.norm(x[-1] - goal) < np.linalg.norm(start - goal)


def test_tightening_by_force_ends_once_the_pull_stalls():
    """An end that never comes to rest (here: a settle speed no end reaches) is tight once it stops gaining rope."""
    w = _world(SLACK_PULL.replace("settle_speed: 0.002", "settle_speed: 1.0e-9, stall: 0.002, stall_frames: 30"))
    man = None
    for _ in range(900):
        w.step()
        if getattr(w.fsm.maneuver, "name", None) == "Tightening":
            man = w.fsm.maneuver
        if w.fsm.finished:
            break
    assert w.fsm.succeeded, w.fsm.events
    assert man.tight and man.still < SETTLE_FRAMES  # tight by the stall, not by coming to rest
    assert man.pulled < 0.5  # and not stopped by the distance
    x = w.rope_positions("R")
    length = 0.02 * (len(x) - 1)
    assert float(np.linalg.norm(x[-1] - x[0])) == pytest.approx(length, rel=0.03)  # as straight as the pull makes it


def test_tightening_pull_with_its_own_force_hangs_at_that_force():
    """A pull's own ``force`` replaces the Tightening's: the rope hangs at tan(phi) = W / (2F) for that F.

    0.5 N here: 26.1 degrees, against 13.8 at the Tightening's 1 N (the
    tolerance as in the 1 N test: the end is held once it moves slower than
    ``settle_speed``, which leaves part of a swing).
    """
    w = _world(SLACK_PULL.replace("direction: [1, 0, 0]", "direction: [1, 0, 0], force: 0.5"))
    step_until_finished(w, 900)
    assert w.fsm.succeeded, w.fsm.events
    span = w.rope_positions("R")[-1] - w.rope_positions("R")[0]
    phi = np.degrees(np.arctan2(-span[1], span[0]))
    assert phi == pytest.approx(np.degrees(np.arctan(0.05 * 9.81 / 1.0)), abs=2.5)


def test_tightening_pull_with_its_own_distance_is_held_there_while_the_others_pull_on():
    """Both ends pulled apart: the start gives at most its own ``distance`` (3 cm) and is then held,
    while the end pulls on until the rope is straight."""
    w = _world(SLACK_PULL.replace(
        "keep: [{body: R, sites: [start]}]",
        "keep: []").replace(
        "pulls: [{body: R, site: end, direction: [1, 0, 0]}]",
        "pulls: [{body: R, site: end, direction: [1, 0, 0]},\n"
        "        {body: R, site: start, direction: [-1, 0, 0], distance: 0.03}]"))
    for _ in range(60):
        w.step()
        if "Tightening" in w.fsm.state:
            break
    start = w.rope_positions("R")[0].copy()
    n = len(w.rope_positions("R"))
    held_at = None
    for _ in range(900):
        w.step()
        if held_at is None and w.control.is_driven([0]).all():
            held_at = w.rope_positions("R")[0].copy()
        if w.fsm.finished:
            break
    assert w.fsm.succeeded, w.fsm.events
    assert held_at is not None  # the start stopped giving before the rope was straight
    moved = float(np.linalg.norm(held_at - start))
    assert 0.03 <= moved < 0.03 + 1.05 * 0.2 / 60  # held within one frame's travel past its distance
    x = w.rope_positions("R")
    np.testing.assert_allclose(x[0], held_at, atol=1e-6)  # and stayed there: its slack is used up
    length = 0.02 * (n - 1)
    assert 0.97 * length < float(np.linalg.norm(x[-1] - x[0])) <= 1.005 * length  # the end pulled on until straight


def test_tightening_pull_force_or_distance_needs_a_tightening_by_force():
    with pytest.raises(LevelError, match=r"pulls \[0\] set their own force or distance"):
        load_level_from_string(SLACK_PULL.replace("force: 1.0, ", "").replace(
            "direction: [1, 0, 0]", "direction: [1, 0, 0], distance: 0.1"))


TOUCHING = """
version: 1
name: touching
scene:
  ropes:
    - {name: A, points: [[-0.3, 0.5, 0], [0.3, 0.5, 0]], rod_length: 0.01, radius: 0.006, pins: [start, end]}
    - {name: B, points: [[0, 0.512, -0.3], [0, 0.512, 0.3]], rod_length: 0.01, radius: 0.006, pins: [start, end]}
sim: {fps: 60, substeps: 10, iterations: 2}
fsm:
  - {run: Crossing, with: {active: B, target: A, active_base: contact, target_base: contact,
                           contact_offset: OFFSET}, timeout: 300}
"""


def test_crossing_contact_offset_pinches_each_strand_out_of_the_contact():
    """With contact_offset the bottoms are that far from the contact towards each tip, and held there."""
    from sandbox.maneuvers.knotting import knot_exit

    w = _world(TOUCHING.replace("OFFSET", "0.05"))
    x = w.positions().astype(np.float64)
    a, b = w.strand("A"), w.strand("B")
    exits = [knot_exit(x, r, [a, b], int(r.idx[-1])) for r in (a, b)]
    assert all(e is not None for e in exits)
    w.step()
    for e, r in zip(exits, (a, b)):
        assert w.control.is_driven([e + 5])[0]  # 5 rods of 0.01 m towards the tip, the rope's last particle
        assert not w.control.is_driven([e])[0]
    w0 = _world(TOUCHING.replace("OFFSET", "0"))
    w0.step()
    assert not w0.control.is_driven([e + 5 for e in exits]).any()  # without an offset nothing is pinched


def test_contact_offset_without_a_contact_bottom_is_a_level_error():
    with pytest.raises(LevelError) as err:
        load_level_from_string(TWO_ROPES.replace("sign: SIGN,", "sign: 1, contact_offset: 0.05,"))
    assert "contact_offset moves a 'contact' or place bottom" in str(err.value)


def test_crossing_above_a_contact_fails_when_the_strands_do_not_touch():
    w = _world(TWO_ROPES.replace("sign: SIGN,", "sign: 1, active_base: contact, target_base: contact,"))
    for _ in range(5):
        w.step()
    assert w.fsm.finished and not w.fsm.succeeded
    assert any("does not touch" in e["message"] for e in w.fsm.events)


def test_tightening_keeps_the_sites_it_is_told_to_keep():
    w = _world(PULL.replace("fsm:\n", "fsm:\n  - {run: Anchoring, with: {body: R, sites: [10, 20]}}\n")
               .replace("max_strain: 0.003}", "max_strain: 0.003, keep: [{body: R, sites: [10]}]}"))
    step_until_finished(w, 120)
    assert w.fsm.succeeded, w.fsm.events
    held = w.control.is_driven([10, 20])
    assert held[0] and not held[1]


# -- headless levels -------------------------------------------------------------------------------


def test_knot_criterion_reads_the_final_rope():
    """The knot metric closes the rope far away: the same as identify_knot on its particles."""
    from sandbox.io.criteria import METRICS

    w = _world(ONE_ROPE)
    assert METRICS["knot"][1](w, "R") == identify_knot(w.rope_positions("R").astype(float)).name == "unknot"
    with pytest.raises(ValueError, match="knot needs"):
        METRICS["knot"][1](w, ["R", "R", "R"])
    x = w.rope_positions("R").astype(float)
    assert METRICS["knot_size"][1](w, "R") == touch_extent(x, radius=w.body_scale("R"))
    with pytest.raises(ValueError, match="knot_size needs"):
        METRICS["knot_size"][1](w, ["R", "R", "R"])
    assert METRICS["knot_length"][1](w, "R") == touch_length(x, radius=w.body_scale("R"))
    with pytest.raises(ValueError, match="knot_length needs"):
        METRICS["knot_length"][1](w, ["R", "R", "R"])


CROSSED_ON_BOX = """
version: 1
name: crossed
scene:
  objects:
    - {name: box, shape: box, params: {size: [0.2, 0.1, 0.2]}, position: [POS]}
  ropes:
    - {name: A, points: [[-0.2, 0.116, 0.05], [0.4, 0.116, 0.05]], rod_length: 0.01, radius: 0.005}
    - {name: B, points: [[0.1, 0.105, -0.3], [0.1, 0.105, 0.3]], rod_length: 0.01, radius: 0.005}
fsm:
  - {run: Wait}
success:
  - {metric: knot_from_top, of: [A, B, box], max: 0.05}
"""


def test_knot_from_top_measures_from_the_objects_top_site_to_where_the_strands_touch():
    """Two ropes crossed at (0.1, 0.11, 0.05), one on the other, over a box whose top site is at (0, 0.1, 0):
    the closed form is |(0.1, 0.05)| (the knot's height does not count); the box moved under the crossing
    reads 0."""
    from sandbox.io.criteria import METRICS

    fn = METRICS["knot_from_top"][1]
    w = _world(CROSSED_ON_BOX.replace("POS", "0, 0, 0"))
    assert fn(w, ["A", "B", "box"]) == pytest.approx(float(np.hypot(0.1, 0.05)), abs=1e-3)
    moved = _world(CROSSED_ON_BOX.replace("POS", "0.1, 0, 0.05"))
    assert fn(moved, ["A", "B", "box"]) == pytest.approx(0.0, abs=1e-3)
    with pytest.raises(ValueError, match="knot_from_top needs"):
        fn(w, ["A", "B"])
    with pytest.raises(LevelError) as err:  # caught when the level loads, not after the run
        load_level_from_string(CROSSED_ON_BOX.replace("POS", "0, 0, 0").replace("of: [A, B, box]", "of: [A, B]"))
    assert "knot_from_top needs one object and the knot's one or two strands" in str(err.value)
    assert "objects: box" in str(err.value)
    apart = _world(CROSSED_ON_BOX.replace("POS", "0, 0, 0").replace("0.116, 0.05]", "0.3, 0.05]"))
    with pytest.raises(ValueError, match="touch nowhere"):
        fn(apart, ["A", "B", "box"])


def test_knot_centre_is_the_middle_of_where_the_strands_touch():
    """Two ropes crossed one on the other at (0.1, 0.05) in plan, their axes at heights 0.116 and 0.105: they
    touch at the middle of the two axes' closest points, (0.1, 0.1105, 0.05); ropes apart touch nowhere."""
    from sandbox.io.criteria import knot_centre

    w = _world(CROSSED_ON_BOX.replace("POS", "0, 0, 0"))
    np.testing.assert_allclose(knot_centre(w, ["A", "B"]), [0.1, 0.1105, 0.05], atol=1e-3)
    apart = _world(CROSSED_ON_BOX.replace("POS", "0, 0, 0").replace("0.116, 0.05]", "0.3, 0.05]"))
    assert knot_centre(apart, ["A", "B"]) is None


BAD_REFS = """
version: 1
name: bad_refs
scene:
  ropes:
    - {name: R, points: [[0, 1, 0], [1, 1, 0]], rod_length: 0.1, radius: 0.01}
macros:
  Wind:
    params: [C]
    steps: [{run: Winding, with: {active: $C, target: "R[:4]"}}]
fsm:
  - {run: Anchoring, with: {body: Z, sites: [start]}}
  - {run: Wind, with: {C: "Q[5:]"}}
  - {run: MoveTo, with: {body: "R[2:3:4]", sites: [start], to: {object: box}}}
  - {run: Tightening, with: {pulls: [{body: R}], knot: [S]}}
"""


def test_unknown_bodies_strands_and_objects_in_maneuvers_are_level_errors():
    """Names in maneuver parameters are checked at load, also through macros: nothing half-runs."""
    with pytest.raises(LevelError) as err:
        load_level_from_string(BAD_REFS)
    text = str(err.value)
    assert "state '0:Anchoring': unknown rope or cloth 'Z'; ropes: R" in text
    assert "state '1:Wind/0:Winding': unknown rope 'Q[5:]'" in text
    assert "bad strand 'R[2:3:4]'" in text
    assert "unknown object 'box'; objects: (none)" in text
    assert "unknown rope 'S'" in text


# -- moving targets ------------------------------------------------------------------------------

def test_tightening_push_moves_the_wound_part_toward_its_point_and_lets_go():
    """``push``: while the end is pulled, a hand pushes the last wound part toward a point (paper Table 3,
    a Tightening "towards" a place) no faster than its speed, every frame until the Tightening ends (not only
    while it closes on the point), and then lets go.

    The rope hangs in the plane z = 0 and is pulled along x: nothing but the push moves it along z.
    """
    w = _world(SLACK_PULL.replace("distance: 0.5", "distance: 0.5,\n push: {toward: [0.0, 0.4, 0.3], force: 0.2, speed: 0.05}"))
    while w.fsm.state != "1:Wait":
        w.step()
    n = len(w.rope_positions("R"))
    wound = np.arange(n // 2 - 2, n // 2 + 3)
    w.record.windings[("R", "R")] = WindingRecord(wound, np.array([1.0, 0.0, 0.0]))
    while w.fsm.state != "2:Tightening":
        w.step()
    z0 = w.positions()[wound, 2].mean()
    pushed, top, far = [], 0.0, 0.0
    while w.fsm.state == "2:Tightening":
        w.step()
        pushed.append(bool(w.control.is_pulled(wound).all()))
        z = w.positions()[wound, 2].mean()
        if pushed[-1]:
            top, far = max(top, (z - z0) * 60), max(far, z)
        z0 = z
    assert w.fsm.succeeded, w.fsm.events
    assert len(pushed) > 30 and all(pushed[:-1])  # pushed every frame the Tightening ran, however little it closed
    assert not pushed[-1]  # the frame it ended in, the hand let go
    while not w.fsm.finished:
        w.step()
    assert not w.control.is_pulled(wound).any() and not w.control.is_driven(wound).any()
    x = w.rope_positions("R")
    assert far > 0.02  # pushed out of the rope's plane, toward z = 0.3
    assert 0.0 < top <= 0.05 * 1.05  # never pushed faster than force / drag
    seg = np.linalg.norm(np.diff(x, axis=0), axis=1)
    assert np.abs(seg / 0.02 - 1).max() < 0.01


def test_tightening_push_needs_windings_to_push():
    """A push with no wound part of the knot's strands fails at once and says why."""
    w = _world(SLACK_PULL.replace("distance: 0.5", "distance: 0.5, push: {toward: knot, force: 0.1}"))
    while not w.fsm.finished:
        w.step()
    assert not w.fsm.succeeded
    assert any("push needs a winding" in str(e) for e in w.fsm.events), w.fsm.events


CROSSED_PULL = """
version: 1
name: crossed_pull
scene:
  ropes:
    - {name: R, points: [[-0.2, 0.5, 0], [0.2, 0.5, 0]], rod_length: 0.02, radius: 0.005, mass: 0.05}
    - {name: S, points: [[0.03, 0.511, -0.2], [0.03, 0.511, 0.2]], rod_length: 0.02, radius: 0.005, mass: 0.05}
sim: {fps: 60, substeps: 10, iterations: 2}
fsm:
  - {run: Anchoring, with: {body: R, sites: [start, end]}}
  - {run: Anchoring, with: {body: S, sites: [start, end]}}
  - {run: Tightening, with: {pulls: [{body: R, site: end, direction: [1, 0, 0]}], keep: [{body: R, sites: [start]}],
                             knot: [S, R], force: 0.5, speed: 0.1, distance: 0.01}}
"""


def test_tightening_records_where_it_leaves_the_knot():
    """When a Tightening ends, the place where its strands touch (the median of their touches) is recorded under
    the strands' sorted names: here S lies across R at x = 0.03, one diameter above it."""
    w = _world(CROSSED_PULL)
    while not w.fsm.finished:
        w.step()
    assert w.fsm.succeeded, w.fsm.events
    place = w.record.knots[("R", "S")]
    r, s = w.rope_positions("R"), w.rope_positions("S")
    assert abs(place[0] - 0.03) < 0.01 and abs(place[2]) < 0.01
    assert r[:, 1].min() - 0.001 < place[1] < s[:, 1].max() + 0.001  # between the two ropes' heights


def test_tightening_push_toward_knot_needs_a_knot_tightened_before():
    """A push toward "knot" with no knot of these strands tightened before fails at once, and names the knots
    there are."""
    w = _world(SLACK_PULL.replace("distance: 0.5", "distance: 0.5, push: {toward: knot, force: 0.1}"))
    while w.fsm.state != "1:Wait":
        w.step()
    n = len(w.rope_positions("R"))
    w.record.windings[("R", "R")] = WindingRecord(np.arange(n // 2 - 2, n // 2 + 3), np.array([1.0, 0.0, 0.0]))
    while not w.fsm.finished:
        w.step()
    assert not w.fsm.succeeded
    assert any("needs a knot of ['R'] tightened before" in str(e) and "so far: none" in str(e)
               for e in w.fsm.events), w.fsm.events


def test_tightening_push_toward_knot_goes_to_the_recorded_place_not_the_particles_wound_before():
    """A push toward "knot" goes to where the last Tightening left the knot: here a place 0.3 m along +z, while
    the particles wound before (which a tightened knot may have drawn out of itself) lie at the rope's start, in
    its plane z = 0: pushed toward them, the wound part would not move along z."""
    w = _world(SLACK_PULL.replace("distance: 0.5", "distance: 0.5,\n push: {toward: knot, force: 0.2, speed: 0.05}"))
    while w.fsm.state != "1:Wait":
        w.step()
    n = len(w.rope_positions("R"))
    first, wound = np.arange(0, 4), np.arange(n // 2 - 2, n // 2 + 3)
    w.record.windings[("R", "T")] = WindingRecord(first, np.array([1.0, 0.0, 0.0]))
    w.record.windings[("R", "R")] = WindingRecord(wound, np.array([1.0, 0.0, 0.0]))
    w.record.knots[("R",)] = np.array([0.0, 0.4, 0.3])
    while w.fsm.state != "2:Tightening":
        w.step()
    z0, far = w.positions()[wound, 2].mean(), -1.0
    while not w.fsm.finished:
        w.step()
        far = max(far, w.positions()[wound, 2].mean() - z0)
    assert w.fsm.succeeded, w.fsm.events
    assert far > 0.02  # pushed toward the recorded place, z = 0.3


def test_a_place_next_to_an_object_moves_and_turns_with_it():
    """``{object, site, offset}``: the offset is in the object's own axes, so a pull ``toward`` a place
    written beside a box goes where the box goes, turned with it (a shifted or turned placement of the
    level moves its knot's pulls along)."""
    from sandbox.maneuvers.basic import Target, resolve_target

    box = "  objects:\n    - {name: box, shape: box, params: {size: [0.2, 0.1, 0.2]}, position: POS, rotation: ROT}\n  ropes:"
    toward = "toward: {object: box, site: top, offset: [0.3, 0.1, 0]}"
    places = {}
    for pos, rot in (([0, 0, 0], [0, 0, 0]), ([0.1, 0.05, -0.2], [0, 90, 0])):
        text = (SLACK_PULL.replace("  ropes:", box.replace("POS", str(pos)).replace("ROT", str(rot)))
                .replace("direction: [1, 0, 0]", toward))
        w = _world(text)
        goal = places[tuple(rot)] = resolve_target(w, Target(object="box", site="top", offset=[0.3, 0.1, 0.0]))
        _heads_toward(w, goal)
    np.testing.assert_allclose(places[(0, 0, 0)], [0.3, 0.2, 0.0], atol=1e-6)
    # Turned 90 degrees about y, the box's x axis is the world's -z.
    np.testing.assert_allclose(places[(0, 90, 0)], [0.1, 0.25, -0.2 - 0.3], atol=1e-6)
    # A pull aims every frame at a place that follows the box's pose (found once, carried along).
    from sandbox.maneuvers.basic import follow_target
    from scipy.spatial.transform import Rotation

    target = Target(object="box", site="top", offset=[0.3, 0.1, 0.0])
    aim = follow_target(w, target)
    np.testing.assert_allclose(aim(), places[(0, 90, 0)], atol=1e-6)
    k = w.object_index("box")
    w.objects.place(k, [0.4, 0.1, 0.3], Rotation.from_euler("y", 180, degrees=True).as_matrix())
    np.testing.assert_allclose(aim(), resolve_target(w, target), atol=1e-6)
    np.testing.assert_allclose(aim(), [0.4 - 0.3, 0.1 + 0.1 + 0.1, 0.3], atol=1e-6)  # top 0.1 above its position

