"""Winding and linking of curves: paper Eq. 1, the Gauss linking integral, writhe.

Curves are polylines given as ``(n, 3)`` arrays of points in m. A *closed*
polyline has an implicit last segment from ``p[-1]`` back to ``p[0]``.

Sign conventions (right-handed coordinates):

- The winding integral of a right-handed helix about its axis is positive,
  whichever way the helix is traversed (Eq. 1 integrates over increasing x).
- The linking number of two closed curves is positive when their mutual
  crossings are positive (right-handed): a positive Hopf link has Lk = +1.
- Writhe is the sum of those signs for a curve with itself, averaged over
  projection directions; a right-handed (positive) trefoil has writhe > 0.

The Gauss integral uses the exact solid angle of a pair of straight segments
(Klenin & Langowski 2000, Eq. 13-15), so closed curves give integers up to
round-off, whatever their discretisation.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "gauss_linking",
    "segment_pair_solid_angles",
    "winding_about_axis",
    "winding_integral",
    "wound_turns",
    "writhe",
]

_CHUNK = 1 << 18
"""Segment pairs evaluated at once (bounds the temporary arrays to ~100 MB)."""


def _segments(points: np.ndarray, closed: bool) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points of a polyline's segments, each ``(m, 3)``."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise ValueError(f"expected an (n >= 2, 3) array of points, got shape {p.shape}")
    if closed:
        return p, np.roll(p, -1, axis=0)
    return p[:-1], p[1:]


def _unit_cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Normalised ``a x b`` row-wise; zero where the product vanishes."""
    c = np.cross(a, b)
    n = np.linalg.norm(c, axis=-1, keepdims=True)
    return np.divide(c, n, out=np.zeros_like(c), where=n > 1e-300)


def segment_pair_solid_angles(
    a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray
) -> np.ndarray:
    """Signed solid angle (sr) of segment pairs (a0->a1, b0->b1), broadcast row-wise.

    The double Gauss integral over two straight segments equals Omega / (4 pi)
    with Omega the solid angle computed here. Coplanar or touching pairs give 0.

    Args:
        a0, a1: ``(..., 3)`` start and end of the first segments, m.
        b0, b1: ``(..., 3)`` start and end of the second segments, m.

    Returns:
        ``(...)`` signed solid angles in [-2 pi, 2 pi].
    """
    r13 = b0 - a0
    r14 = b1 - a0
    r23 = b0 - a1
    r24 = b1 - a1
    n1 = _unit_cross(r13, r14)
    n2 = _unit_cross(r14, r24)
    n3 = _unit_cross(r24, r23)
    n4 = _unit_cross(r23, r13)

    def asin_dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.arcsin(np.clip(np.sum(u * v, axis=-1), -1.0, 1.0))

    omega = asin_dot(n1, n2) + asin_dot(n2, n3) + asin_dot(n3, n4) + asin_dot(n4, n1)
    sign = np.sign(np.sum(np.cross(b1 - b0, a1 - a0) * r13, axis=-1))
    return omega * sign


def _pair_sum(
    a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray, mask: np.ndarray | None = None
) -> np.ndarray:
    """Per-segment-of-a sums of solid angles against all segments of b, ``(ma,)``."""
    ma, mb = len(a0), len(b0)
    out = np.zeros(ma)
    rows = max(1, _CHUNK // max(mb, 1))
    for i in range(0, ma, rows):
        j = slice(i, min(i + rows, ma))
        om = segment_pair_solid_angles(
            a0[j, None, :], a1[j, None, :], b0[None, :, :], b1[None, :, :]
        )
        if mask is not None:
            om = np.where(mask[j], om, 0.0)
        out[j] = om.sum(axis=1)
    return out


def gauss_linking(
    a: np.ndarray,
    b: np.ndarray,
    *,
    closed_a: bool = True,
    closed_b: bool = True,
    cumulative: bool = False,
) -> float | np.ndarray:
    """Gauss linking integral of two polylines (exact per segment pair).

    Lk = 1/(4 pi) sum_ij Omega_ij. For two closed, disjoint curves this is the
    linking number (an integer up to round-off); for open curves it is the real
    number used as a winding measure where Eq. 1 does not apply (paper §4.2).

    Args:
        a, b: ``(n, 3)`` and ``(m, 3)`` points, m.
        closed_a, closed_b: whether each polyline closes back to its first point.
        cumulative: if True, return the running sum over the segments of ``a``
            (one value per point of ``a``, starting at 0) instead of the total.

    Returns:
        The linking integral (dimensionless), or its ``(n,)`` running sum.
    """
    a0, a1 = _segments(a, closed_a)
    b0, b1 = _segments(b, closed_b)
    per = _pair_sum(a0, a1, b0, b1) / (4.0 * np.pi)
    if cumulative:
        return np.concatenate([[0.0], np.cumsum(per)])
    return float(per.sum())


def writhe(curve: np.ndarray, *, closed: bool = True) -> float:
    """Writhe of one polyline: the Gauss integral of the curve with itself.

    Adjacent segments (sharing a point) contribute nothing and are skipped.

    Args:
        curve: ``(n, 3)`` points, m.
        closed: whether the polyline closes back to its first point.

    Returns:
        Writhe (dimensionless); positive for right-handed coiling.
    """
    a0, a1 = _segments(curve, closed)
    m = len(a0)
    idx = np.arange(m)
    d = np.abs(idx[:, None] - idx[None, :])
    mask = d > 1
    if closed:
        mask &= d < m - 1
    return float(_pair_sum(a0, a1, a0, a1, mask).sum() / (4.0 * np.pi))


def _x_monotone_part(axis: np.ndarray, x: np.ndarray, start: int) -> tuple[np.ndarray, np.ndarray]:
    """The run of axis points around ``start`` along which x is monotone, in increasing x."""
    n = len(axis)
    if n == 1:
        return x, axis
    sg = np.sign(np.diff(x))
    j = min(start, n - 2)
    s = sg[j] if sg[j] != 0 else 1.0
    bad = np.nonzero(sg != s)[0]
    before = bad[bad < j]
    after = bad[bad >= j]
    lo = int(before[-1]) + 1 if len(before) else 0
    hi = int(after[0]) if len(after) else n - 1
    xs, ps = x[lo : hi + 1], axis[lo : hi + 1]
    if s < 0:
        xs, ps = xs[::-1], ps[::-1]
    return xs, ps


def winding_integral(
    curve: np.ndarray,
    axis_curve: np.ndarray,
    x_hat: np.ndarray,
    origin: np.ndarray | None = None,
    *,
    cumulative: bool = False,
    signed: bool = True,
) -> float | np.ndarray:
    """Winding integral of ``curve`` (G) around ``axis_curve`` (T), paper Eq. 1.

    w = 1/(2 pi) int x_hat . (r x r') / |r|^2 dx over increasing x, with r(x) the
    vector from T to G in the plane normal to x_hat at each x. T must be
    monotone in x near ``origin`` (its axis turns less than 90 degrees there);
    beyond the ends of that monotone run T is extended along x_hat.

    Args:
        curve: ``(n, 3)`` points of G, m.
        axis_curve: ``(m, 3)`` points of T, m.
        x_hat: winding direction (normalised here), usually T's tangent at X_T.
        origin: a point on T where x = 0 (default: T's point nearest G's start).
        cumulative: if True, return the running value at each point of G.
        signed: as ``winding_about_axis``.

    Returns:
        Number of turns (dimensionless); positive for a right-handed helix.
    """
    g = np.asarray(curve, dtype=np.float64)
    t = np.asarray(axis_curve, dtype=np.float64)
    xh = np.asarray(x_hat, dtype=np.float64)
    xh = xh / np.linalg.norm(xh)
    if origin is None:
        origin = t[np.argmin(np.linalg.norm(t - g[0], axis=1))]
    origin = np.asarray(origin, dtype=np.float64)
    xt = (t - origin) @ xh
    start = int(np.argmin(np.linalg.norm(t - origin, axis=1)))
    xs, ps = _x_monotone_part(t, xt, start)
    xg = (g - origin) @ xh
    if len(xs) >= 2:
        tx = np.stack([np.interp(xg, xs, ps[:, k]) for k in range(3)], axis=1)
        # Beyond the monotone run, continue T straight along x_hat.
        tx += np.clip(xg - xs[-1], 0.0, None)[:, None] * xh
        tx += np.clip(xg - xs[0], None, 0.0)[:, None] * xh
    else:
        tx = ps[0] + (xg - xs[0])[:, None] * xh
    return winding_about_axis(g, tx, xh, cumulative=cumulative, signed=signed)


def winding_about_axis(
    curve: np.ndarray, axis_points: np.ndarray, x_hat: np.ndarray, *, cumulative: bool = False,
    signed: bool = True,
) -> float | np.ndarray:
    """Turns of ``curve`` about matched ``axis_points`` (one per curve point), about x_hat.

    The angle of r = curve - axis_points (projected normal to x_hat) is
    unwrapped along the curve; its total change over 2 pi is signed by the
    overall progress of the curve along x_hat, as Eq. 1 integrates over
    increasing x.

    Args:
        curve: ``(n, 3)`` points, m.
        axis_points: ``(n, 3)`` the matching axis points, m.
        x_hat: unit winding direction.
        cumulative: if True, return the running value at each point.
        signed: if False, the turns of r about x_hat alone, whichever way the curve progresses
            along it (for comparing parts of two curves that progress little).

    Returns:
        Number of turns (dimensionless).
    """
    xh = np.asarray(x_hat, dtype=np.float64)
    r = np.asarray(curve, dtype=np.float64) - axis_points
    e1 = np.cross(xh, [1.0, 0.0, 0.0] if abs(xh[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(xh, e1)
    ang = np.unwrap(np.arctan2(r @ e2, r @ e1))
    progress = float((curve[-1] - curve[0]) @ xh)
    sign = 1.0 if progress >= 0.0 or not signed else -1.0
    w = sign * (ang - ang[0]) / (2.0 * np.pi)
    return w if cumulative else float(w[-1])


def wound_turns(curve: np.ndarray, axis_curve: np.ndarray, x_hat: np.ndarray, touch: float) -> float:
    """Turns of the wound part of G around T: Eq. 1 over G from its first to its last point that touches T.

    A point touches T within ``touch`` of T's polyline (m; for ropes, r_C + r_T plus a contact band).
    The ends of a laid winding that a pull lifts off T (a lead-in swung round by T's motion) are
    not wound around it: counted, they add the angle of where they point, up to a fifth of a turn
    in ``rope_wind_moving``. Fewer than two touching points: 0 (nothing is wound).

    Args:
        curve: ``(n, 3)`` points of G (the laid turns), m.
        axis_curve: ``(m, 3)`` points of T, m.
        x_hat: winding direction, as ``winding_integral``.
        touch: the largest distance from T's polyline of a point that touches it, m.

    Returns:
        Number of turns, >= 0.
    """
    from sandbox.geometry.mesh_geodesic import polyline_distance

    g = np.asarray(curve, dtype=np.float64)
    on = np.flatnonzero(polyline_distance(g, axis_curve) <= touch)
    if len(on) < 2:
        return 0.0
    return abs(float(winding_integral(g[on[0]:on[-1] + 1], axis_curve, x_hat)))
