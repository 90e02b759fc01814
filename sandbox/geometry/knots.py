"""Knot identification of ropes: close far away, project, simplify, compute invariants.

An open rope has no knot type until its ends are joined; ``close_rope`` joins
them far away: each end is extended outward to a large sphere around the rope
and the two exit points are joined along a great circle of that sphere. The
closed curve is simplified in 3-D (a vertex is dropped when the triangle it
spans with its neighbours is pierced by no other segment, an isotopy),
projected on a generic plane (seeded random direction, retried while the
projection is degenerate), turned into a signed Gauss code, reduced by
Reidemeister I and II moves, and its invariants computed
(``sandbox.geometry.knot_invariants``).

Chirality convention: ``trefoil_right`` is the right-handed trefoil, the one
whose standard diagram has three positive crossings; its signature is -2 and
its Jones polynomial t + t^3 - t^4. ``granny_right`` is the sum of two right
trefoils (signature -4); ``square`` is a right plus a left trefoil
(signature 0). The Alexander polynomial and the determinant do not see
chirality; the signature and the Jones polynomial do.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sandbox.geometry import knot_invariants as inv
from sandbox.geometry.knot_diagram import best_diagram, reduce_polygon
from sandbox.geometry.winding import gauss_linking

__all__ = [
    "KNOTS",
    "KnotInfo",
    "close_rope",
    "identify_closed",
    "identify_knot",
    "identify_two_ropes",
    "knot_centre",
    "linking_number",
    "touch_extent",
    "touch_length",
    "touch_points",
]

CLOSURE_MODES = ("blend", "tangent", "radial")
"""How an end leaves the rope: along its end direction, radially from the rope's
centroid, or along their normalised sum (the default, which also works when an
end points back into the rope)."""

JOIN_MODES = ("standing", "free")


def _jmul(
    p: tuple[tuple[int, int], ...], q: tuple[tuple[int, int], ...]
) -> tuple[tuple[int, int], ...]:
    """Product of two Jones polynomials (that of a connected sum)."""
    out: dict[int, int] = {}
    for a, x in p:
        for b, y in q:
            out[a + b] = out.get(a + b, 0) + x * y
    return tuple(sorted((k, v) for k, v in out.items() if v))


def _jmirror(p: tuple[tuple[int, int], ...]) -> tuple[tuple[int, int], ...]:
    """Jones polynomial of the mirror image: t -> 1/t."""
    return tuple(sorted((-k, v) for k, v in p))


_TR = ((1, 1), (3, 1), (4, -1))  # right-handed trefoil: t + t^3 - t^4
_TL = _jmirror(_TR)
_GRANNY = (1, -2, 3, -2, 1)
_CR = ((2, 1), (4, 1), (5, -1), (6, 1), (7, -1))  # right-handed cinquefoil T(2,5): t^2 + t^4 - t^5 + t^6 - t^7

KNOTS: dict[str, tuple[tuple[int, ...], int, tuple[tuple[int, int], ...]]] = {
    "unknot": ((1,), 0, ((0, 1),)),
    "trefoil_right": ((1, -1, 1), -2, _TR),
    "trefoil_left": ((1, -1, 1), 2, _TL),
    "figure_eight": ((-1, 3, -1), 0, ((-2, 1), (-1, -1), (0, 1), (1, -1), (2, 1))),
    "granny_right": (_GRANNY, -4, _jmul(_TR, _TR)),
    "granny_left": (_GRANNY, 4, _jmul(_TL, _TL)),
    "square": (_GRANNY, 0, _jmul(_TR, _TL)),
    # five half twists in one run: what two half knots of the same sense become when the
    # second is drawn into the first with no crossing between them
    "cinquefoil_right": ((1, -1, 1, -1, 1), -4, _CR),
    "cinquefoil_left": ((1, -1, 1, -1, 1), 4, _jmirror(_CR)),
}
"""Known knots: name -> (Alexander polynomial, signature, Jones polynomial)."""


@dataclass(frozen=True)
class KnotInfo:
    """What was identified, with the invariants that decided it.

    Attributes:
        name: one of ``KNOTS`` or ``"unknown"``.
        alexander: Alexander polynomial, lowest power first, Delta(1) = 1.
        determinant: |Delta(-1)|.
        signature: knot signature (right-handed trefoil: -2).
        crossings: crossings of the simplified diagram (an upper bound on the
            crossing number).
        jones: Jones polynomial ``((power, coefficient), ...)``, or None when
            the diagram was too large to contract.
        writhe: sum of crossing signs of the simplified diagram.
        gauss_code: the simplified diagram, passages ``(crossing, over)``.
        signs: crossing signs of the simplified diagram.
    """

    name: str
    alexander: tuple[int, ...]
    determinant: int
    signature: int
    crossings: int
    jones: tuple[tuple[int, int], ...] | None = None
    writhe: int = 0
    gauss_code: tuple[tuple[int, bool], ...] = field(default=(), repr=False, compare=False)
    signs: dict[int, int] = field(default_factory=dict, repr=False, compare=False)

    @property
    def chirality(self) -> str:
        """``"right"``, ``"left"`` or ``"achiral"`` (signature, else Jones polynomial)."""
        if self.signature:
            return "right" if self.signature < 0 else "left"
        if self.jones is not None and self.jones != _jmirror(self.jones):
            return "right" if sum(k * v for k, v in self.jones) > 0 else "left"
        return "achiral"


# -- closing far away -----------------------------------------------------------------------


def _end_direction(p: np.ndarray, end: int, window: int) -> np.ndarray:
    """Unit direction leaving the rope at its first (end=0) or last (end=-1) point."""
    k = min(window, len(p) - 1)
    d = p[0] - p[k] if end == 0 else p[-1] - p[-1 - k]
    n = np.linalg.norm(d)
    return d / n if n > 0 else d


def _exit_point(
    start: np.ndarray, direction: np.ndarray, centre: np.ndarray, radius: float
) -> np.ndarray:
    """Where the ray from ``start`` along unit ``direction`` leaves the sphere (centre, radius)."""
    o = start - centre
    b = float(o @ direction)
    c = float(o @ o) - radius * radius
    s = -b + np.sqrt(max(b * b - c, 0.0))
    return start + s * direction


def _great_arc(p: np.ndarray, q: np.ndarray, centre: np.ndarray, n: int) -> np.ndarray:
    """``n`` interior points of a great-circle arc from p to q on a sphere about ``centre``."""
    a, b = p - centre, q - centre
    r = 0.5 * (np.linalg.norm(a) + np.linalg.norm(b))
    ua, ub = a / np.linalg.norm(a), b / np.linalg.norm(b)
    if ua @ ub < -0.999:  # Nearly antipodal: go through a fixed perpendicular direction.
        perp = np.cross(ua, [0.0, 0.0, 1.0] if abs(ua[2]) < 0.9 else [1.0, 0.0, 0.0])
        perp /= np.linalg.norm(perp)
        half = (n + 1) // 2
        return np.vstack(
            [
                _great_arc(p, centre + r * perp, centre, half - 1),
                [centre + r * perp],
                _great_arc(centre + r * perp, q, centre, n - half),
            ]
        )
    ang = np.arccos(np.clip(ua @ ub, -1.0, 1.0))
    t = np.linspace(0.0, 1.0, n + 2)[1:-1]
    if ang < 1e-12:
        return np.empty((0, 3))
    w1 = np.sin((1.0 - t) * ang) / np.sin(ang)
    w2 = np.sin(t * ang) / np.sin(ang)
    return centre + r * (w1[:, None] * ua + w2[:, None] * ub)


def _leave_direction(
    p: np.ndarray, end: int, centre: np.ndarray, mode: str, window: int
) -> np.ndarray:
    """Unit direction in which an end is extended to the closing sphere."""
    tangent = _end_direction(p, end, window)
    radial = p[end] - centre
    nr = np.linalg.norm(radial)
    radial = radial / nr if nr > 0 else tangent
    if mode == "tangent":
        d = tangent
    elif mode == "radial":
        d = radial
    else:
        d = tangent + radial
        if np.linalg.norm(d) < 1e-6:
            d = radial
    n = np.linalg.norm(d)
    if n == 0.0:
        raise ValueError("rope end has no direction (repeated points)")
    return d / n


def _check_rope(points: np.ndarray, name: str = "points") -> np.ndarray:
    """``points`` as an ``(n >= 2, 3)`` float array, or a ValueError naming the argument."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise ValueError(f"{name} must be an (n >= 2, 3) array, got shape {p.shape}")
    return p


def close_rope(
    points: np.ndarray,
    *,
    mode: str = "blend",
    radius_factor: float = 5.0,
    arc_points: int = 16,
    end_window: int = 2,
) -> np.ndarray:
    """Close an open rope far away (the returned polyline closes back to its first point).

    Args:
        points: ``(n, 3)`` rope particles, m.
        mode: one of ``CLOSURE_MODES``.
        radius_factor: closing-sphere radius over the rope's radius about its centroid.
        arc_points: points on the closing great-circle arc.
        end_window: particles over which each end direction is measured.

    Returns:
        ``(n + arc_points + 2, 3)`` closed polyline: the rope, the last end's exit
        point, the arc, the first end's exit point.
    """
    if mode not in CLOSURE_MODES:
        raise ValueError(f"mode must be one of {CLOSURE_MODES}, got {mode!r}")
    p = _check_rope(points)
    centre = p.mean(axis=0)
    radius = radius_factor * max(float(np.linalg.norm(p - centre, axis=1).max()), 1e-9)
    e_last = _exit_point(p[-1], _leave_direction(p, -1, centre, mode, end_window), centre, radius)
    e_first = _exit_point(p[0], _leave_direction(p, 0, centre, mode, end_window), centre, radius)
    return np.vstack([p, [e_last], _great_arc(e_last, e_first, centre, arc_points), [e_first]])


# -- identification ---------------------------------------------------------------------------


def _name(alex: tuple[int, ...], sig: int, jones: tuple[tuple[int, int], ...] | None) -> str:
    """The known knot with these invariants (Jones ignored when not computed), or "unknown"."""
    for name, (a, s, j) in KNOTS.items():
        if a == alex and s == sig and (jones is None or jones == j):
            return name
    return "unknown"


def identify_closed(curve: np.ndarray, *, seed: int = 0, projections: int = 3) -> KnotInfo:
    """Identify the knot of a closed polygon (last point joins the first).

    Args:
        curve: ``(n, 3)`` closed polygon.
        seed: seed of the random projection directions.
        projections: generic projections tried; the one with fewest crossings
            after Reidemeister I/II simplification is used.
    """
    p = _check_rope(curve, "curve")
    keep = np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1) > 1e-12 * float(np.ptp(p))
    closed = reduce_polygon(p[keep] if keep.sum() >= 3 else p)
    code, signs = best_diagram(closed, seed=seed, projections=projections)
    alex = inv.alexander_polynomial(code, signs)
    sig = inv.signature(code, signs)
    jones = inv.jones_polynomial(code, signs)
    return KnotInfo(
        name=_name(alex, sig, jones),
        alexander=alex,
        determinant=inv.determinant(alex),
        signature=sig,
        crossings=len(code) // 2,
        jones=jones,
        writhe=int(sum(signs.values())),
        gauss_code=tuple(code),
        signs=dict(signs),
    )


def identify_knot(
    points: np.ndarray,
    *,
    closed: bool = False,
    mode: str = "blend",
    radius_factor: float = 5.0,
    seed: int = 0,
    projections: int = 3,
) -> KnotInfo:
    """Identify the knot tied in an open rope (closed far away first, see ``close_rope``).

    Args:
        points: ``(n, 3)`` rope particles, m.
        closed: treat ``points`` as an already closed polygon.
        mode, radius_factor: closure options (``close_rope``).
        seed, projections: projection options (``identify_closed``).
    """
    p = _check_rope(points)
    curve = p if closed else close_rope(p, mode=mode, radius_factor=radius_factor)
    return identify_closed(curve, seed=seed, projections=projections)


def _segment_distances(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """Distance of each point of ``p`` to the segment s0-s1."""
    d = s1 - s0
    t = np.clip((p - s0) @ d / max(float(d @ d), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (s0 + t[:, None] * d), axis=1)


def _clear_between(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the straight segment between a[0] and b[0] keeps clear of both ropes.

    Clear: every particle farther than the gap g = |a[0] - b[0]| along its
    rope from its joined end stays more than g / 2 from the segment. Then
    nothing passes between the two ends, and joining them straight is what
    a cloth or an object holding them side by side does. Extending them
    outward instead would cross each other when they point at each other.
    """
    gap = float(np.linalg.norm(b[0] - a[0]))
    if gap == 0.0:
        return True
    for p in (a, b):
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        far = p[arc > gap]
        if len(far) and _segment_distances(far, a[0], b[0]).min() <= 0.5 * gap:
            return False
    return True


def _joined_curve(
    a: np.ndarray, b: np.ndarray, join: str, mode: str, radius_factor: float
) -> np.ndarray:
    """One closed curve: a's and b's joined ends joined straight if clear (``_clear_between``), else
    meeting on one sphere; the other ends meet on a larger one."""
    if join not in JOIN_MODES:
        raise ValueError(f"join must be one of {JOIN_MODES}, got {join!r}")
    if mode not in CLOSURE_MODES:
        raise ValueError(f"mode must be one of {CLOSURE_MODES}, got {mode!r}")
    if join == "free":
        a, b = a[::-1], b[::-1]
    both = np.vstack([a, b])
    centre = both.mean(axis=0)
    r1 = radius_factor * max(float(np.linalg.norm(both - centre, axis=1).max()), 1e-9)
    r2 = 1.5 * r1

    def leave(p: np.ndarray, end: int, radius: float) -> np.ndarray:
        d = _leave_direction(p, end, centre, mode, 2)
        return _exit_point(p[end], d, centre, radius)

    fa, fb = leave(a, -1, r2), leave(b, -1, r2)
    if _clear_between(a, b):
        # The joined ends side by side with nothing in between: joined
        # straight, as the cloth or object that holds them joins them.
        return np.vstack([a[::-1], b, [fb], _great_arc(fb, fa, centre, 16), [fa]])
    ja, jb = leave(a, 0, r1), leave(b, 0, r1)
    # a backwards from its free end to its joined end, across to b, b forwards, back to a.
    return np.vstack(
        [
            a[::-1],
            [ja],
            _great_arc(ja, jb, centre, 16),
            [jb],
            b,
            [fb],
            _great_arc(fb, fa, centre, 16),
            [fa],
        ]
    )


def identify_two_ropes(
    a: np.ndarray,
    b: np.ndarray,
    *,
    join: str = "standing",
    mode: str = "blend",
    radius_factor: float = 5.0,
    seed: int = 0,
    projections: int = 3,
) -> KnotInfo:
    """Identify the knot that ties two ropes together (e.g. a furoshiki's corners).

    The ropes' ``join`` ends (``"standing"``: the first particles, as the cloth
    or object joins them; ``"free"``: the last ones) are joined by a straight
    segment when they sit side by side with nothing passing between them, and
    otherwise extended outward and connected far away; the other two ends are
    closed on a larger sphere, so that the two far paths cannot meet. Closed
    this way, a square (reef) knot tied between two ropes is the sum of
    opposite trefoils and reads ``square``; a granny reads ``granny_left`` or
    ``granny_right``.

    Args:
        a, b: ``(n, 3)`` and ``(m, 3)`` rope particles, m.
        join: which ends are joined, one of ``JOIN_MODES``.
        mode, radius_factor: closure options (``close_rope``).
        seed, projections: projection options (``identify_closed``).
    """
    curve = _joined_curve(_check_rope(a, "a"), _check_rope(b, "b"), join, mode, radius_factor)
    return identify_closed(curve, seed=seed, projections=projections)


def linking_number(
    a: np.ndarray,
    b: np.ndarray,
    *,
    closed: bool = False,
    mode: str = "blend",
    radius_factor: float = 5.0,
) -> int:
    """Linking number of two ropes, each closed far away (or already closed).

    Rope ``a`` closes on a sphere of ``radius_factor`` times the pair's radius,
    ``b`` on one 1.5 times larger, so that the closing arcs stay apart. The
    Gauss integral of the two closed curves is rounded to the nearest integer.

    Args:
        a, b: ``(n, 3)`` and ``(m, 3)`` points, m.
        closed: treat both as closed polygons.
        mode, radius_factor: closure options (``close_rope``).

    Returns:
        The linking number (positive for a positive clasp).
    """
    pa, pb = _check_rope(a, "a"), _check_rope(b, "b")
    if not closed:
        both = np.vstack([pa, pb])
        centre = both.mean(axis=0)
        rad = max(float(np.linalg.norm(both - centre, axis=1).max()), 1e-9)

        def close(p: np.ndarray, radius: float) -> np.ndarray:
            e_last = _exit_point(p[-1], _leave_direction(p, -1, centre, mode, 2), centre, radius)
            e_first = _exit_point(p[0], _leave_direction(p, 0, centre, mode, 2), centre, radius)
            return np.vstack([p, [e_last], _great_arc(e_last, e_first, centre, 16), [e_first]])

        pa = close(pa, radius_factor * rad)
        pb = close(pb, 1.5 * radius_factor * rad)
    return int(np.rint(gauss_linking(pa, pb)))


def touch_points(
    a: np.ndarray,
    b: np.ndarray | None = None,
    *,
    radius: float,
    gap: float = 0.5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where two ropes (or two parts of one rope) touch.

    Two capsules touch when their axes are closer than ``(2 + gap) * radius``.
    With ``b`` the touches are between rope ``a`` and rope ``b``; without it,
    between parts of ``a`` more than a half turn around a rope (pi times its
    diameter of arclength) apart, so that a bent rope does not touch itself
    at every bend. O(n m) segment pairs (NumPy).

    Args:
        a, b: ``(n, 3)`` and ``(m, 3)`` points (m).
        radius: rope radius (m).
        gap: clearance (fraction of the radius) that still counts as touching.

    Returns:
        ``(points, i, j)``: the midpoints of the closest points of each
        touching pair ``(k, 3)``, and the pair's segment indices in ``a`` and
        in ``b`` (or in ``a`` again).
    """
    from sandbox.collision.capsule_np import segment_segment_closest

    pa = _check_rope(a, "a")
    pb = pa if b is None else _check_rope(b, "b")
    i, j = np.meshgrid(np.arange(len(pa) - 1), np.arange(len(pb) - 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    if b is None:
        seg = np.linalg.norm(np.diff(pa, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        keep = (j > i) & (s[j] - s[i + 1] > np.pi * 2.0 * radius)
        i, j = i[keep], j[keep]
    if len(i) == 0:
        return np.zeros((0, 3)), i, j
    _, _, c1, c2, dist = segment_segment_closest(pa[i], pa[i + 1], pb[j], pb[j + 1])
    hit = dist < (2.0 + gap) * radius
    return 0.5 * (c1[hit] + c2[hit]), i[hit], j[hit]


def touch_extent(
    a: np.ndarray,
    b: np.ndarray | None = None,
    *,
    radius: float,
    gap: float = 0.5,
) -> float:
    """Size of a knot: the largest distance between two places where its ropes touch (``touch_points``).

    A tight knot is a few diameters across; two half knots tied apart, or
    two ropes lying side by side, measure the whole stretch where they
    touch.

    Returns:
        The extent in metres (0 where nothing touches, or only at one place).
    """
    p, _, _ = touch_points(a, b, radius=radius, gap=gap)
    if len(p) < 2:
        return 0.0
    if len(p) > 64:
        # The farthest pair lies on the convex hull: O(k log k) instead of k^2 distances
        # ("QJ" jiggles a flat or collinear set so that it has a hull).
        from scipy.spatial import ConvexHull

        p = p[ConvexHull(p, qhull_options="QJ").vertices]
    return float(np.max(np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)))


def touch_length(
    a: np.ndarray,
    b: np.ndarray | None = None,
    *,
    radius: float,
    gap: float = 0.5,
) -> float:
    """Rope in a knot: along each rope, the length from its first to its last touching segment (``touch_points``).

    Summed over the two ropes (with ``b``) or taken once (one rope). A tight
    overhand knot in a 12 mm rope holds about 20 cm of it; a loose one, or
    one whose loop was never pulled through, holds the whole loop.

    Returns:
        The length in metres (0 where nothing touches).
    """
    pa = _check_rope(a, "a")
    pb = pa if b is None else _check_rope(b, "b")
    _, i, j = touch_points(pa, b, radius=radius, gap=gap)
    if len(i) == 0:
        return 0.0

    def span(p: np.ndarray, segs: np.ndarray) -> float:
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        return float(seg[segs.min(): segs.max() + 1].sum())

    if b is None:
        return span(pa, np.concatenate([i, j]))
    return span(pa, i) + span(pb, j)


def knot_centre(ropes: list[np.ndarray], *, radius: float, gap: float = 0.5) -> np.ndarray | None:
    """Where a knot is: the median of the places its ropes touch (``touch_points``).

    Two or more ropes: touches between every pair; one rope: touches of
    parts of it more than half a turn apart. The median, not the mean, so
    that a tail brushing the rope far from the knot does not move it.

    Returns:
        ``(3,)`` point in m, or None where nothing touches.
    """
    pts = [_check_rope(p, f"ropes[{k}]") for k, p in enumerate(ropes)]
    if len(pts) == 1:
        found = [touch_points(pts[0], radius=radius, gap=gap)[0]]
    else:
        found = [touch_points(pts[i], pts[j], radius=radius, gap=gap)[0]
                 for i in range(len(pts)) for j in range(i + 1, len(pts))]
    hits = np.vstack(found)
    return np.median(hits, axis=0) if len(hits) else None
