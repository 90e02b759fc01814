"""Winding integral (paper Eq. 1), Gauss linking integral and writhe against closed forms."""

import numpy as np
import pytest

from sandbox.geometry.winding import gauss_linking, winding_integral, wound_turns, writhe


def circle(centre, e1, e2, n=64, radius=1.0):
    """Polygon of ``n`` points on a circle, traversed from e1 towards e2."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return (
        np.asarray(centre, float)
        + radius * np.cos(t)[:, None] * np.asarray(e1, float)
        + radius * np.sin(t)[:, None] * np.asarray(e2, float)
    )


def disc_intersection_number(ring_centre, ring_normal, curve):
    """Signed passes of a closed curve through a ring's unit disc (right-hand rule)."""
    c = np.asarray(ring_centre, float)
    nrm = np.asarray(ring_normal, float)
    p = curve
    q = np.roll(curve, -1, axis=0)
    hp, hq = (p - c) @ nrm, (q - c) @ nrm
    total = 0
    for a, b, ha, hb in zip(p, q, hp, hq):
        if ha * hb < 0:
            x = a + (b - a) * ha / (ha - hb)
            if np.linalg.norm(x - c) < 1.0:
                total += 1 if hb > ha else -1
    return total


X, Y, Z = np.eye(3)


def test_hopf_link_is_plus_or_minus_one_with_orientation_sign():
    """Hopf link: Lk = +-1, the signed count of b piercing a's disc; reversing one flips it."""
    a = circle([0, 0, 0], X, Y)  # normal +z by the right-hand rule
    b = circle([1, 0, 0], X, Z)
    lk = gauss_linking(a, b)
    expected = disc_intersection_number([0, 0, 0], Z, b)
    assert abs(expected) == 1
    assert lk == pytest.approx(expected, abs=1e-9)
    assert gauss_linking(b, a) == pytest.approx(lk, abs=1e-9)
    assert gauss_linking(a[::-1], b) == pytest.approx(-lk, abs=1e-9)
    b_mirror = b * [1, 1, -1]
    assert gauss_linking(a, b_mirror) == pytest.approx(-lk, abs=1e-9)


def test_linking_is_exact_on_coarse_polygons():
    """The segment-pair solid angle makes Lk an integer even for a triangle linked with a square."""
    a = circle([0, 0, 0], X, Y, n=3, radius=2.0)
    b = circle([1.0, 0.1, 0.05], X, Z, n=4, radius=1.5)
    lk = gauss_linking(a, b)
    assert abs(lk - round(lk)) < 1e-9
    assert abs(round(lk)) == 1


def test_unlinked_rings_have_zero_linking():
    """Two separated rings, and two rings stacked without threading, have Lk = 0."""
    a = circle([0, 0, 0], X, Y)
    assert gauss_linking(a, circle([3, 0, 0], X, Z)) == pytest.approx(0.0, abs=1e-3)
    assert gauss_linking(a, circle([0.2, 0, 0.5], X, Y)) == pytest.approx(0.0, abs=1e-3)


def test_whitehead_like_double_passage_cancels():
    """A ring threaded down and back up through another has Lk = 0 though the curves interlock."""
    t = np.linspace(0.0, 2.0 * np.pi, 200, endpoint=False) + 0.01
    # A long thin loop crossing the unit disc twice in opposite directions.
    b = np.stack([0.1 + 0.3 * np.cos(t), 0.2 * np.sin(2 * t), 2.0 * np.sin(t)], axis=1)
    a = circle([0, 0, 0], X, Y)
    assert disc_intersection_number([0, 0, 0], Z, b) == 0
    assert gauss_linking(a, b) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("turns", [1, 2, 3])
def test_winding_of_helix_around_straight_axis_counts_turns(turns):
    """A right-handed helix of n turns winds n times (Eq. 1), in either direction of travel."""
    u = np.linspace(0.0, 2.0 * np.pi * turns, 50 * turns + 1)
    helix = np.stack([0.05 * u, 0.3 * np.cos(u), 0.3 * np.sin(u)], axis=1)
    axis = np.stack([np.linspace(-1.0, 2.0, 7), np.zeros(7), np.zeros(7)], axis=1)
    assert winding_integral(helix, axis, X) == pytest.approx(turns, abs=1e-9)
    assert winding_integral(helix[::-1], axis, X) == pytest.approx(turns, abs=1e-9)
    left = helix * [1, 1, -1]
    assert winding_integral(left, axis, X) == pytest.approx(-turns, abs=1e-9)


def test_wound_turns_leave_out_ends_lifted_off_t():
    """One turn laid on T at radius 0.3 counts one, with a lead-in and a tail lifted off T on either side
    (each a quarter turn round, 1 m out), which Eq. 1 over the whole curve would count; a curve that
    no longer touches T is wound 0 times."""
    u = np.linspace(0.0, 2.0 * np.pi, 101)
    helix = np.stack([0.05 * u, 0.3 * np.cos(u), 0.3 * np.sin(u)], axis=1)
    lead = np.array([[-0.05, 0.0, -1.3]])  # a quarter turn before the helix starts, off T
    tail = np.array([[helix[-1, 0] + 0.05, 0.0, 1.3]])  # a quarter turn after it ends
    curve = np.vstack([lead, helix, tail])
    axis = np.stack([np.linspace(-1.0, 2.0, 7), np.zeros(7), np.zeros(7)], axis=1)
    assert winding_integral(curve, axis, X) == pytest.approx(1.5, abs=1e-9)
    assert wound_turns(curve, axis, X, touch=0.31) == pytest.approx(1.0, abs=1e-9)
    assert wound_turns(helix, axis, X, touch=0.31) == pytest.approx(1.0, abs=1e-9)
    assert wound_turns(curve + [0.0, 2.0, 0.0], axis, X, touch=0.31) == 0.0


def test_winding_follows_a_tilted_wavy_axis():
    """Eq. 1 with r normal to x at each x counts the turns of a helix about a curved axis."""
    x = np.linspace(0.0, 3.0, 600)
    centre = np.stack([x, 0.2 * np.sin(x), 0.1 * x], axis=1)
    u = 2.0 * np.pi * 3.0 * x / 3.0
    helix = centre + 0.05 * np.stack([0 * u, np.cos(u), np.sin(u)], axis=1)
    w = winding_integral(helix, centre[::10], X, cumulative=True)
    assert w[-1] == pytest.approx(3.0, abs=0.02)
    assert np.all(np.diff(w) > -1e-3)


def test_open_helix_linking_tends_to_turns_for_long_axis():
    """The Gauss integral of an open helix with a long straight axis tends to its turns."""
    u = np.linspace(0.0, 4.0 * np.pi, 400)
    helix = np.stack([0.01 * u, 0.1 * np.cos(u), 0.1 * np.sin(u)], axis=1)
    axis = np.array([[-1e4, 0, 0], [1e4, 0, 0]])
    lk = gauss_linking(helix, axis, closed_a=False, closed_b=False)
    assert lk == pytest.approx(2.0, abs=1e-3)
    run = gauss_linking(helix, axis, closed_a=False, closed_b=False, cumulative=True)
    assert run[0] == 0.0 and run[-1] == pytest.approx(lk)


def test_writhe_sign_follows_handedness():
    """A right trefoil has writhe near +3.4, its mirror the opposite, a planar ring 0."""
    t = np.linspace(0.0, 2.0 * np.pi, 300, endpoint=False)
    right = np.stack(
        [(2 + np.cos(3 * t)) * np.cos(2 * t), (2 + np.cos(3 * t)) * np.sin(2 * t), -np.sin(3 * t)],
        axis=1,
    )
    w = writhe(right)
    assert 3.0 < w < 4.0
    assert writhe(right * [1, 1, -1]) == pytest.approx(-w, abs=1e-9)
    assert writhe(circle([0, 0, 0], X, Y)) == pytest.approx(0.0, abs=1e-12)
