"""Knot identification of ropes: diagrams, invariants, closure far away, two-rope knots, linking."""

import pathlib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sandbox.geometry import knot_invariants as inv
from sandbox.geometry.knot_diagram import gauss_code, reduce_polygon
from sandbox.geometry.knots import (
    KNOTS,
    close_rope,
    identify_closed,
    identify_knot,
    identify_two_ropes,
    linking_number,
    touch_extent,
    touch_length,
    touch_points,
)
from sandbox.geometry.winding import gauss_linking

# -- analytic curves ------------------------------------------------------------------------


def trefoil(t, *, left=False):
    """(2, 3) torus knot; right-handed (positive crossings) unless ``left``."""
    p = np.stack(
        [(2 + np.cos(3 * t)) * np.cos(2 * t), (2 + np.cos(3 * t)) * np.sin(2 * t), -np.sin(3 * t)],
        axis=1,
    )
    return p * [1, 1, -1] if left else p


def open_trefoil(n=200, *, left=False):
    """A trefoil rope: the torus knot with a small piece cut at its outermost point (t = 0)."""
    return trefoil(np.linspace(0.05, 2 * np.pi - 0.05, n), left=left)


def open_figure_eight(n=200):
    """Figure-eight rope, cut at its outermost point."""
    t = np.linspace(0.05, 2 * np.pi - 0.05, n)
    return np.stack(
        [(2 + np.cos(2 * t)) * np.cos(3 * t), (2 + np.cos(2 * t)) * np.sin(3 * t), np.sin(4 * t)],
        axis=1,
    )


def trefoil_sum(*, second_left=False, first_left=False, n=120, gap=12.0, bridge=12):
    """Connected sum of two trefoils: each cut at an outer point and joined by two bridges.

    Returns the closed curve and the index ranges of the two bridges.
    """
    t = np.linspace(0.04, 2 * np.pi - 0.04, n)
    k1 = trefoil(t, left=first_left)
    k2 = trefoil(t, left=second_left) * [-1, -1, 1] + [gap, 0, 0]  # its cut faces K1's
    f = np.linspace(0, 1, bridge + 2)[1:-1, None]
    b1 = k1[-1] + f * (k2[0] - k1[-1])
    b2 = k2[-1] + f * (k1[0] - k2[-1])
    curve = np.vstack([k1, b1, k2, b2])
    return curve, (n, n + bridge), (2 * n + bridge, 2 * n + 2 * bridge)


def open_sum(**kw):
    """A rope tying two trefoils in a row: the sum cut at an outer point of the first trefoil."""
    curve, _, _ = trefoil_sum(**kw)
    i = 40  # t ~ 2 pi / 3: an outer equator point of the first trefoil
    return np.vstack([curve[i + 1 :], curve[: i - 1]])


def two_ropes(**kw):
    """Two ropes whose standing ends meet at one bridge and tails at the other."""
    curve, (b1s, b1e), (b2s, b2e) = trefoil_sum(**kw)
    m1, m2 = (b1s + b1e) // 2, (b2s + b2e) // 2
    a = np.vstack([curve[m1 - 1 :: -1], curve[:m2:-1]])  # backwards from bridge 1 through K1
    b = curve[m1 + 1 : m2]
    return a, b


def wiggly_rope(n=200):
    """An unknotted rope that wiggles in two directions."""
    t = np.linspace(0, 1, n)
    return np.stack([3 * t, 0.3 * np.sin(20 * t), 0.2 * np.cos(13 * t)], axis=1)


def coil(n=200):
    """A helical coil of three turns (unknotted once closed)."""
    t = np.linspace(0, 6 * np.pi, n)
    return np.stack([np.cos(t), np.sin(t), 0.1 * t], axis=1)


def rotations(k):
    return [Rotation.random(random_state=s).as_matrix() for s in range(k)]


def parse(code):
    """'O1 U2 ...' into passages."""
    return [(int(tok[1:]), tok[0] == "O") for tok in code.split()]


# -- invariants of hand-made diagrams -----------------------------------------------------------

TREFOIL = parse("O1 U2 O3 U1 O2 U3")
FIG8 = parse("O1 U2 O3 U4 O2 U1 O4 U3")


def test_positive_trefoil_diagram_invariants():
    """All-positive trefoil diagram: Delta = 1 - t + t^2, sigma = -2, V = t + t^3 - t^4."""
    signs = {1: 1, 2: 1, 3: 1}
    assert inv.alexander_polynomial(TREFOIL, signs) == (1, -1, 1)
    assert inv.signature(TREFOIL, signs) == -2
    assert inv.signature(TREFOIL, signs, colour=1) == -2
    assert inv.jones_polynomial(TREFOIL, signs) == ((1, 1), (3, 1), (4, -1))
    neg = {1: -1, 2: -1, 3: -1}
    assert inv.signature(TREFOIL, neg) == 2
    assert inv.jones_polynomial(TREFOIL, neg) == ((-4, -1), (-3, 1), (-1, 1))
    assert inv.determinant((1, -1, 1)) == 3


def test_figure_eight_diagram_invariants():
    """Figure-eight diagram: Delta = -1 + 3t - t^2, det 5, sigma 0, its known Jones polynomial."""
    signs = {1: -1, 2: -1, 3: 1, 4: 1}
    assert len(inv.faces(inv.gauss_to_pd(FIG8, signs))) == 4 + 2
    alex = inv.alexander_polynomial(FIG8, signs)
    assert alex == (-1, 3, -1) and inv.determinant(alex) == 5
    assert inv.signature(FIG8, signs) == 0
    assert inv.jones_polynomial(FIG8, signs) == KNOTS["figure_eight"][2]


def curl_and_finger_unknot():
    """A square loop with a curl (one R1 crossing) and a finger laid over one side (an R2 pair)."""
    return np.array(
        [
            [0, 0, 0],
            [4, 0, 0],
            [4, 2, 0],
            [2.5, 2, 1],
            [2.5, -1, 1],
            [1.5, -1, 1],
            [1.5, 2, 1],  # finger over the bottom side
            [0, 2, 0],
            [0, 1.5, 0],
            [0, 0.5, 0],
            [-0.5, 0.8, 0.3],
            [0.5, 1.0, 0.3],
            [0, 0.3, 0],  # curl over the left side
        ],
        dtype=float,
    )


def test_reidemeister_moves_remove_curls_and_fingers():
    """A curl's crossing (R1) and a finger's two crossings (R2) are all removed."""
    code, signs = gauss_code(curl_and_finger_unknot(), [0.0, 0.0, 1.0])
    assert len(signs) == 3 and sorted(signs.values()).count(1) >= 1
    assert inv.jones_polynomial(code, signs) == ((0, 1),)  # already invariant before simplifying
    assert inv.alexander_polynomial(code, signs) == (1,)
    simple, s2 = inv.simplify(code, signs)
    assert simple == [] and s2 == {}


def test_exact_alexander_matches_fft_path(monkeypatch):
    """The exact integer fallback and the FFT evaluation give the same Alexander polynomial."""
    curve, _, _ = trefoil_sum()
    info = identify_closed(curve)
    assert info.crossings >= 6
    monkeypatch.setattr(inv, "_poly_from_values", lambda vals: None)
    exact = inv.alexander_polynomial(list(info.gauss_code), info.signs)
    assert exact == info.alexander == (1, -2, 3, -2, 1)


def test_crossing_signs_average_to_the_writhe():
    """Crossing signs (right-handed +1) per projection average to the Gauss-integral writhe."""
    from sandbox.geometry.winding import writhe

    curve = trefoil(np.linspace(0, 2 * np.pi, 60, endpoint=False))
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(300, 3))
    totals = []
    for d in dirs:
        try:
            _, signs = gauss_code(curve, d)
        except ValueError:
            continue
        totals.append(sum(signs.values()))
    assert np.mean(totals) == pytest.approx(writhe(curve), abs=0.25)
    assert writhe(curve) > 3.0
    _, signs = gauss_code(curve, [0.01, 0.02, 1.0])  # seen from above: 3 positive crossings
    assert sorted(signs.values()) == [1, 1, 1]


# -- closed curves ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("p", "q", "signature", "det"),
    [(2, 5, -4, 5), (3, 4, -6, 3), (2, 7, -6, 7)],
)
def test_torus_knot_signatures(p, q, signature, det):
    """Positive torus knots T(2,5), T(3,4), T(2,7) have the known signature and determinant; T(2,5) is the
    right cinquefoil (Jones t^2 + t^4 - t^5 + t^6 - t^7) and its mirror the left one; the others are not named."""
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    curve = np.stack(
        [(2 + np.cos(q * t)) * np.cos(p * t), (2 + np.cos(q * t)) * np.sin(p * t), -np.sin(q * t)],
        axis=1,
    )
    info = identify_closed(curve)
    assert info.signature == signature and info.determinant == det
    mirror = identify_closed(curve * [1, 1, -1])
    assert mirror.signature == -signature
    if (p, q) == (2, 5):
        assert info.name == "cinquefoil_right" and mirror.name == "cinquefoil_left"
        assert info.jones == ((2, 1), (4, 1), (5, -1), (6, 1), (7, -1))
    else:
        assert info.name == mirror.name == "unknown"


def test_reduction_keeps_the_knot_and_drops_most_vertices():
    """Triangle elimination shrinks a 300-point trefoil (same knot) to a few points, a ring to 3."""
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    curve = trefoil(t)
    small = reduce_polygon(curve)
    assert len(small) < 20
    assert identify_closed(small).name == "trefoil_right"
    ring = np.stack([np.cos(t), np.sin(t), 0 * t], axis=1)
    assert len(reduce_polygon(ring)) == 3


# -- open ropes ---------------------------------------------------------------------------------

ROPES = {
    "unknot": wiggly_rope,
    "trefoil_right": open_trefoil,
    "trefoil_left": lambda: open_trefoil(left=True),
    "figure_eight": open_figure_eight,
    "granny_right": open_sum,
    "granny_left": lambda: open_sum(first_left=True, second_left=True),
    "square": lambda: open_sum(second_left=True),
}


@pytest.mark.parametrize("name", list(ROPES))
def test_open_rope_is_identified_whatever_the_pose_and_closure(name):
    """Each rope reads as its knot under rotations, closure radii and modes, and projections."""
    rope = ROPES[name]()
    expected = KNOTS[name]
    for k, rot in enumerate(rotations(2)):
        for rf, mode in ((3.0, "blend"), (20.0, "radial")):
            info = identify_knot(rope @ rot.T, radius_factor=rf, mode=mode, seed=k)
            assert info.name == name
            assert (info.alexander, info.signature, info.jones) == expected


def test_mirror_images_flip_chirality():
    """Mirroring flips right and left trefoils and grannies and leaves the square knot square."""
    pairs = {"trefoil_right": "trefoil_left", "granny_right": "granny_left", "square": "square"}
    for name, mirror in pairs.items():
        rope = ROPES[name]()
        assert identify_knot(rope * [-1, 1, 1]).name == mirror
    assert identify_knot(ROPES["trefoil_right"]()).chirality == "right"
    assert identify_knot(ROPES["square"]()).chirality == "achiral"


def test_loose_coil_is_an_unknot():
    """A coiled rope with its ends leaving along the coil axis is unknotted."""
    info = identify_knot(coil())
    assert info.name == "unknot" and info.crossings == 0 and info.alexander == (1,)


def test_closure_is_far_away_and_keeps_the_rope():
    """The closure keeps the rope and reaches the sphere of radius_factor times the rope size."""
    rope = open_trefoil()
    closed = close_rope(rope, radius_factor=10.0)
    assert np.array_equal(closed[: len(rope)], rope)
    centre = rope.mean(axis=0)
    size = np.linalg.norm(rope - centre, axis=1).max()
    far = np.linalg.norm(closed[len(rope) :] - centre, axis=1)
    assert far.max() == pytest.approx(10.0 * size, rel=1e-9)
    with pytest.raises(ValueError, match="blend"):
        close_rope(rope, mode="sideways")


# -- two ropes ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kw", "name"),
    [
        ({}, "granny_right"),
        ({"second_left": True}, "square"),
        ({"first_left": True, "second_left": True}, "granny_left"),
    ],
)
def test_two_ropes_joined_at_standing_ends(kw, name):
    """Two ropes with standing ends joined (as by the cloth) and tails closed read as their knot."""
    a, b = two_ropes(**kw)
    for k, rot in enumerate(rotations(2)):
        info = identify_two_ropes(a @ rot.T, b @ rot.T, join="standing", seed=k)
        assert info.name == name
    assert identify_two_ropes(a[::-1], b[::-1], join="free").name == name
    with pytest.raises(ValueError, match="standing"):
        identify_two_ropes(a, b, join="middle")


def test_standing_ends_side_by_side_are_joined_straight():
    """Two simulated ropes (a half knot tied against their standing ends, held 2 cm apart and
    pointing at each other): extending those ends outward crosses them and read ``unknown``;
    joined straight, as the cloth joins them, they read the half knot, from any view."""
    data = np.load(pathlib.Path(__file__).parent / "data" / "two_ropes_side_by_side.npz")
    for a, b in zip(data["a"].astype(np.float64), data["b"].astype(np.float64)):
        assert np.linalg.norm(a[0] - b[0]) < 0.025
        for k, rot in enumerate(rotations(3)):
            assert identify_two_ropes(a @ rot.T, b @ rot.T, join="standing", seed=k).name == "trefoil_left"


def test_standing_ends_with_a_rope_between_them_are_joined_far_away():
    """A straight join is used only when nothing passes between the ends: here b comes back through the gap."""
    from sandbox.geometry.knots import _clear_between

    a = np.linspace([0.0, 0.0, 0.0], [-1.0, 0.0, 0.0], 50)
    b = np.linspace([0.1, 0.0, 0.0], [1.0, 0.0, 0.0], 50)
    assert _clear_between(a, b)
    back = np.vstack([b, np.linspace([1.0, 1.0, 0.1], [0.05, 1.0, 0.1], 50), np.linspace([0.05, 0.9, 0.02], [0.05, -1.0, 0.02], 50)])
    assert not _clear_between(a, back)
    assert identify_two_ropes(a, back).name == "unknot"


def test_linking_number_of_two_open_ropes():
    """Hooked ropes (cut Hopf rings) link as their rings; reversing one flips it; apart give 0."""
    t = np.linspace(0.1, 2 * np.pi - 0.1, 80)
    a = np.stack([-np.cos(t), -np.sin(t), 0 * t], axis=1)  # cut at (-1, 0, 0), far from b
    b = np.stack([1 + np.cos(t), 0 * t, np.sin(t)], axis=1)  # cut at (2, 0, 0), far from a
    ring_lk = round(gauss_linking(a, b))
    assert ring_lk in (-1, 1)
    assert linking_number(a, b) == ring_lk
    assert linking_number(a[::-1], b) == -ring_lk
    assert linking_number(a, b + [5.0, 0, 0]) == 0


def _line(p0, p1, n):
    return np.linspace(p0, p1, n)


def test_touch_extent_of_ropes_side_by_side_is_the_stretch_they_share():
    r = 0.006
    a = _line([0.0, 0.0, 0.0], [0.3, 0.0, 0.0], 31)
    b = np.vstack([_line([0.05, 0.1, 0.0], [0.05, 2 * r, 0.0], 10), _line([0.06, 2 * r, 0.0], [0.14, 2 * r, 0.0], 9),
                   _line([0.15, 2 * r, 0.0], [0.15, 0.1, 0.0], 10)])
    # they touch from x = 0.05 to x = 0.15, and nowhere else
    assert touch_extent(a, b, radius=r) == pytest.approx(0.10, abs=1e-9)
    assert touch_extent(a, b + [0.0, 0.1, 0.0], radius=r) == 0.0


def test_touch_extent_of_a_single_crossing_is_about_a_diameter():
    r = 0.006
    a = _line([-0.2, 0.0, 0.0], [0.2, 0.0, 0.0], 41)
    b = _line([0.0, -0.2, 2 * r], [0.0, 0.2, 2 * r], 41)
    assert touch_extent(a, b, radius=r) <= 2.5 * r * 2


def test_touch_extent_of_one_rope_ignores_its_bends_and_sees_its_crossings():
    r = 0.006
    t = np.linspace(0, 1.5 * np.pi, 200)
    arc = np.c_[0.05 * np.cos(t), 0.05 * np.sin(t), 0 * t]   # bent all along, touches itself nowhere
    assert touch_extent(arc, radius=r) == 0.0
    u = np.linspace(-0.5, 0.5, 101)   # a hairpin: two legs 2r apart over 0.3 m, joined by a tight bend
    leg = np.c_[u * 0.3 + 0.15, 0 * u, 0 * u]
    bend = np.c_[0.3 + r * np.sin(np.linspace(0, np.pi, 8)), r - r * np.cos(np.linspace(0, np.pi, 8)), 0 * np.arange(8)]
    hairpin = np.vstack([leg, bend, (leg + [0, 2 * r, 0])[::-1]])
    assert touch_extent(hairpin, radius=r) == pytest.approx(0.3, abs=0.03)


def test_touch_extent_does_not_depend_on_pose():
    rng = np.random.default_rng(4)
    a, b = two_ropes()
    e = touch_extent(a, b, radius=0.4)
    assert e > 0.0
    rot = Rotation.random(random_state=rng).as_matrix()
    assert touch_extent(a @ rot.T + 1.0, b @ rot.T + 1.0, radius=0.4) == pytest.approx(e, rel=1e-9)


def test_touch_length_is_the_rope_between_the_first_and_last_touch():
    r = 0.006
    a = _line([0.0, 0.0, 0.0], [0.3, 0.0, 0.0], 31)
    leg = 0.1 - 2 * r
    b = np.vstack([_line([0.05, 0.1, 0.0], [0.05, 2 * r, 0.0], 10), _line([0.06, 2 * r, 0.0], [0.14, 2 * r, 0.0], 9),
                   _line([0.15, 2 * r, 0.0], [0.15, 0.1, 0.0], 10)])
    # on a: the 12 one-centimetre segments from x = 0.04 to 0.16 come within 2.5 r of b;
    # on b: the flat run and its two joins (0.1 m) and the lowest segment of each leg
    assert touch_length(a, b, radius=r) == pytest.approx(0.12 + 0.10 + 2 * leg / 9, abs=1e-9)
    assert touch_length(a, b + [0.0, 0.1, 0.0], radius=r) == 0.0
    u = np.linspace(-0.5, 0.5, 101)
    leg_a = np.c_[u * 0.3 + 0.15, 0 * u, 0 * u]
    bend = np.c_[0.3 + r * np.sin(np.linspace(0, np.pi, 8)), r - r * np.cos(np.linspace(0, np.pi, 8)), 0 * np.arange(8)]
    hairpin = np.vstack([leg_a, bend, (leg_a + [0, 2 * r, 0])[::-1]])   # touches itself end to end
    assert touch_length(hairpin, radius=r) == pytest.approx(np.linalg.norm(np.diff(hairpin, axis=0), axis=1).sum())


def test_touch_extent_of_many_touches_is_the_brute_force_diameter():
    """Past 64 touching pairs the diameter is taken over the hull's vertices: the same value."""
    r = 0.006
    a = _line([0.0, 0.0, 0.0], [0.5, 0.0, 0.0], 201)
    t = np.linspace(0.0, 0.5, 201)
    b = np.c_[t, 1.5 * r * np.cos(40 * t), 1.5 * r * np.sin(40 * t)]   # winds around a all along
    p, _, _ = touch_points(a, b, radius=r)
    assert len(p) > 64
    brute = np.max(np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1))
    assert touch_extent(a, b, radius=r) == pytest.approx(brute, rel=1e-12)
