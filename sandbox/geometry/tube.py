"""Bounding tube of a rope and geodesics on it: the winding target line (paper §4.2).

The tube B around a rope T is the canal surface

    P(s, phi) = c(s) + R (cos(phi) u(s) + sin(phi) v(s)),

where c(s) is a natural cubic spline through T's particles (chord-length
knots), resampled uniformly in arc length s (m); (u, v, t = c') is a
rotation-minimising frame (RMF, double reflection method of Wang et al. 2008)
and R = r_C + r_T + eps the tube radius (m). With an RMF the metric is
orthogonal, dl^2 = h^2 ds^2 + R^2 dphi^2 with h = 1 - R (k1 cos(phi) +
k2 sin(phi)), (k1, k2) the curvature vector of c in the frame, so a geodesic
making the angle alpha with the s-lines obeys (Liouville's formula)

    ds/dl = cos(alpha) / h,  dphi/dl = sin(alpha) / R,
    dalpha/dl = (k1 sin(phi) - k2 cos(phi)) cos(alpha) / h,

integrated here with RK4 in arc length l (m). On a straight tube h = 1 and the
geodesic is a helix at the constant angle alpha = theta to the axis, of pitch
2 pi R / tan(theta).

Handedness: +1 traces a right-handed helix (positive winding, Eq. 1), the
winding that follows a positive crossing; -1 a left-handed one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_banded

from sandbox.geometry.winding import gauss_linking, winding_integral

__all__ = ["Geodesic", "Tube", "sample_targets", "trace_geodesic", "tube_radius"]


FOLD_H = 0.2
"""Least metric factor h = 1 - R k cos(phi) of the geodesic equation (``Tube.trace``). A tube of radius R
folds onto itself on the inside of a bend of curvature k > 1 / R (a rope through a knot tied before bends
about as tight as its own radius), where h <= 0: there ds/dl = cos(alpha) / h would carry a target line
metres along the axis in one step. h is held at FOLD_H or more wherever it would fall below, on the inside
of bends with k R > 1 - FOLD_H (ds/dl and dalpha/dl both divide by it): a step then moves at most 1 / FOLD_H
times its length along the axis. This removes the jump; a line traced into such a bend may still turn back
at it or run off T without reaching its turns. Where k R < 1 - FOLD_H everywhere, nothing changes."""


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``(n, 3)`` arrays (cheaper than np.cross for small n)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


def tube_radius(r_c: float, r_t: float, clearance: float = 0.1) -> float:
    """Bounding-tube radius R = r_C + r_T + eps with eps = clearance (r_C + r_T), in m.

    Args:
        r_c: radius of the active rope C, m.
        r_t: radius of the target rope T, m.
        clearance: eps over r_C + r_T (the paper's 0.1).
    """
    if r_c < 0.0 or r_t < 0.0 or r_c + r_t <= 0.0:
        raise ValueError(f"rope radii must be >= 0 with a positive sum, got {r_c}, {r_t}")
    if clearance <= 0.0:
        raise ValueError(f"clearance must be > 0, got {clearance}")
    return (1.0 + clearance) * (r_c + r_t)


def _rmf_double_reflection(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotation-minimising normals u_i along samples x_i with unit tangents t_i.

    Each step applies the double reflection map of Wang et al. (2008), a
    rotation H_i with H_i t_i = t_{i+1} that depends on the samples only. The
    steps are composed in closed form: with any normal field U_i, the frame is
    U_i turned about t_i by the running sum of the angles from U_{i+1} to
    H_i U_i, so the whole frame is computed without a Python loop.

    Args:
        x: ``(n, 3)`` sample points, m.
        t: ``(n, 3)`` unit tangents.

    Returns:
        ``(n, 3)`` unit normals u_i (u_i . t_i = 0), u_0 chosen from U_0.
    """
    n = len(x)
    # A normal field: t crossed with the world axis least aligned with it.
    ax = np.zeros_like(t)
    ax[np.arange(n), np.argmin(np.abs(t), axis=1)] = 1.0
    big_u = _cross(t, ax)
    big_u /= np.linalg.norm(big_u, axis=1, keepdims=True)
    if n == 1:
        return big_u

    def reflect(vec: np.ndarray, nrm: np.ndarray, c: np.ndarray) -> np.ndarray:
        return vec - (2.0 / c)[:, None] * np.sum(nrm * vec, axis=1)[:, None] * nrm

    v1 = x[1:] - x[:-1]
    c1 = np.maximum(np.sum(v1 * v1, axis=1), 1e-300)
    r_l = reflect(big_u[:-1], v1, c1)
    t_l = reflect(t[:-1], v1, c1)
    v2 = t[1:] - t_l
    c2 = np.sum(v2 * v2, axis=1)
    safe = c2 > 1e-300
    r_next = np.where(safe[:, None], reflect(r_l, v2, np.where(safe, c2, 1.0)), r_l)
    # Signed angle from U_{i+1} to the transported U_i, about t_{i+1}.
    u1 = big_u[1:]
    t1 = t[1:]
    d_ang = np.arctan2(np.sum(_cross(u1, r_next) * t1, axis=1), np.sum(u1 * r_next, axis=1))
    ang = np.concatenate([[0.0], np.cumsum(d_ang)])
    w = _cross(t, big_u)
    return np.cos(ang)[:, None] * big_u + np.sin(ang)[:, None] * w


class _NaturalSpline:
    """Natural cubic spline through points ``y`` at increasing parameters ``u`` (vector-valued)."""

    def __init__(self, u: np.ndarray, y: np.ndarray):
        self.u, self.y = u, y
        n = len(u)
        h = np.diff(u)
        self.m = np.zeros_like(y)  # second derivatives, zero at both ends
        if n > 2:
            slope = np.diff(y, axis=0) / h[:, None]
            ab = np.zeros((3, n - 2))
            ab[0, 1:] = h[1:-1]
            ab[1] = 2.0 * (h[:-1] + h[1:])
            ab[2, :-1] = h[1:-1]
            self.m[1:-1] = solve_banded((1, 1), ab, 6.0 * np.diff(slope, axis=0))

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value and first and second derivatives at parameters ``x``, each ``(k, dim)``."""
        i = np.clip(np.searchsorted(self.u, x, side="right") - 1, 0, len(self.u) - 2)
        h = (self.u[i + 1] - self.u[i])[:, None]
        a = (self.u[i + 1] - x)[:, None] / h
        b = 1.0 - a
        y0, y1, m0, m1 = self.y[i], self.y[i + 1], self.m[i], self.m[i + 1]
        val = a * y0 + b * y1 + ((a**3 - a) * m0 + (b**3 - b) * m1) * h * h / 6.0
        d1 = (y1 - y0) / h - (3.0 * a * a - 1.0) * h * m0 / 6.0 + (3.0 * b * b - 1.0) * h * m1 / 6.0
        d2 = a * m0 + b * m1
        return val, d1, d2


class Tube:
    """Bounding tube around a rope polyline, sampled uniformly in arc length.

    Attributes:
        radius: tube radius R, m.
        length: arc length of the axis spline, m.
        ds: spacing of the axis samples, m.
        s: ``(k,)`` arc length of the axis samples, m.
        centre: ``(k, 3)`` axis points c(s), m.
        tangent, normal, binormal: ``(k, 3)`` the RMF (t, u, v = t x u).
        k1, k2: ``(k,)`` curvature vector of the axis in (u, v), 1/m.
    """

    def __init__(self, points: np.ndarray, radius: float, *, samples_per_segment: int = 8):
        """Fit the axis spline through ``points`` and sample its frame.

        Args:
            points: ``(n >= 2, 3)`` rope particles in order, m.
            radius: tube radius R (see ``tube_radius``), m.
            samples_per_segment: axis samples per rope segment.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
            raise ValueError(f"points must be an (n >= 2, 3) array, got shape {p.shape}")
        if radius <= 0.0:
            raise ValueError(f"radius must be positive, got {radius}")
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-12])
        p = p[keep]
        if len(p) < 2:
            raise ValueError("rope points are all coincident")
        self.radius = float(radius)
        chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        spline = _NaturalSpline(chord, p)
        # Arc length of the spline from a fine sampling, then uniform resampling in s.
        m = max(2, samples_per_segment * (len(p) - 1) + 1)
        uf = np.linspace(0.0, chord[-1], 2 * m)
        sf = np.concatenate(
            [[0.0], np.cumsum(np.linalg.norm(np.diff(spline(uf)[0], axis=0), axis=1))]
        )
        self.length = float(sf[-1])
        self.s = np.linspace(0.0, self.length, m)
        self.ds = float(self.s[1] - self.s[0])
        u = np.interp(self.s, sf, uf)
        self.centre, d1, d2 = spline(u)
        speed = np.linalg.norm(d1, axis=1)
        self.tangent = d1 / speed[:, None]
        d2_normal = d2 - np.sum(d2 * self.tangent, axis=1)[:, None] * self.tangent
        kvec = d2_normal / (speed**2)[:, None]
        self.normal = _rmf_double_reflection(self.centre, self.tangent)
        self.binormal = _cross(self.tangent, self.normal)
        self.k1 = np.sum(kvec * self.normal, axis=1)
        self.k2 = np.sum(kvec * self.binormal, axis=1)
        self._k1 = self.k1.tolist()
        self._k2 = self.k2.tolist()

    # -- frames ---------------------------------------------------------------------------

    def frame(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Axis point and RMF at arc lengths ``s`` (clamped to the tube), each ``(n, 3)``."""
        s = np.clip(np.atleast_1d(np.asarray(s, dtype=np.float64)), 0.0, self.length)
        f = s / self.ds
        i = np.minimum(f.astype(np.int64), len(self.s) - 2)
        a = (f - i)[:, None]
        # Cubic Hermite between axis samples (positions and unit tangents = d/ds).
        a2, a3 = a * a, a * a * a
        c0, c1 = self.centre[i], self.centre[i + 1]
        m0, m1 = self.ds * self.tangent[i], self.ds * self.tangent[i + 1]
        c = (
            (2 * a3 - 3 * a2 + 1) * c0
            + (a3 - 2 * a2 + a) * m0
            + (-2 * a3 + 3 * a2) * c1
            + (a3 - a2) * m1
        )
        t = (6 * a2 - 6 * a) * (c0 - c1) + (3 * a2 - 4 * a + 1) * m0 + (3 * a2 - 2 * a) * m1
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        nrm = (1.0 - a) * self.normal[i] + a * self.normal[i + 1]
        nrm -= np.sum(nrm * t, axis=1)[:, None] * t
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        return c, t, nrm, _cross(t, nrm)

    def surface(self, s: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Tube points P(s, phi), ``(n, 3)`` in m, for arc lengths s (m) and angles phi (rad)."""
        c, _, u, v = self.frame(s)
        phi = np.atleast_1d(np.asarray(phi, dtype=np.float64))[:, None]
        return c + self.radius * (np.cos(phi) * u + np.sin(phi) * v)

    def project(self, x: np.ndarray) -> tuple[float, float, np.ndarray]:
        """Project a 3-D point onto the tube.

        Args:
            x: ``(3,)`` point, m.

        Returns:
            ``(s, phi, point)``: the closest axis parameter s* (m), the angle phi
            (rad) of x about the axis there, and the tube point P(s*, phi).
        """
        x = np.asarray(x, dtype=np.float64)
        a, b = self.centre[:-1], self.centre[1:]
        ab = b - a
        w = np.clip(
            np.sum((x - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0, 1
        )
        d2 = np.sum((a + w[:, None] * ab - x) ** 2, axis=1)
        k = int(np.argmin(d2))
        s = float(self.s[k] + w[k] * self.ds)
        for _ in range(2):  # Newton on (x - c(s)) . t(s) = 0 against the smooth axis.
            c, t, u, v = self.frame(s)
            r = x - c[0]
            f = float(r @ t[0])
            k1, k2 = np.interp(s, self.s, self.k1), np.interp(s, self.s, self.k2)
            den = 1.0 - float(r @ (k1 * u[0] + k2 * v[0]))
            s = min(max(s + f / max(den, 1e-6), 0.0), self.length)
        c, t, u, v = self.frame(s)
        r = x - c[0]
        phi = math.atan2(float(r @ v[0]), float(r @ u[0]))
        point = c[0] + self.radius * (math.cos(phi) * u[0] + math.sin(phi) * v[0])
        return s, phi, point

    # -- geodesic ODE ---------------------------------------------------------------------

    def trace(
        self, s0: float, phi0: float, alpha0: float, step: float, n_steps: int
    ) -> tuple[np.ndarray, bool]:
        """Integrate a geodesic with RK4 from (s0, phi0) at angle alpha0 to the s-lines.

        Args:
            s0, phi0: start on the tube (m, rad).
            alpha0: start angle (rad) from +s towards +phi.
            step: arc-length step, m.
            n_steps: number of steps.

        Returns:
            ``((k, 3) array of (s, phi, alpha), left)``; ``left`` is True when
            the geodesic ran off an end of the tube: its last step is then cut
            (linearly) at that end.
        """
        s0, phi0, alpha0 = float(s0), float(phi0), float(alpha0)
        out = [(s0, phi0, alpha0)]
        k1s, k2s = self._k1, self._k2
        last = len(k1s) - 1
        inv_ds, rad, inv_rad = 1.0 / self.ds, self.radius, 1.0 / self.radius
        cos, sin = math.cos, math.sin
        h_min = FOLD_H

        def rhs(s: float, phi: float, alpha: float) -> tuple[float, float, float]:
            f = s * inv_ds
            if f <= 0.0:
                k1, k2 = k1s[0], k2s[0]
            elif f >= last:
                k1, k2 = k1s[last], k2s[last]
            else:
                i = int(f)
                a = f - i
                k1 = k1s[i] + a * (k1s[i + 1] - k1s[i])
                k2 = k2s[i] + a * (k2s[i + 1] - k2s[i])
            cp, sp = cos(phi), sin(phi)
            h = 1.0 - rad * (k1 * cp + k2 * sp)
            if h < h_min:
                h = h_min
            ca = cos(alpha) / h
            return ca, sin(alpha) * inv_rad, (k1 * sp - k2 * cp) * ca

        s, p, a = s0, phi0, alpha0
        h2, h6 = 0.5 * step, step / 6.0
        length = self.length
        for _ in range(n_steps):
            a1, b1, c1 = rhs(s, p, a)
            a2, b2, c2 = rhs(s + h2 * a1, p + h2 * b1, a + h2 * c1)
            a3, b3, c3 = rhs(s + h2 * a2, p + h2 * b2, a + h2 * c2)
            a4, b4, c4 = rhs(s + step * a3, p + step * b3, a + step * c3)
            s += h6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            p += h6 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
            a += h6 * (c1 + 2.0 * c2 + 2.0 * c3 + c4)
            if s < 0.0 or s > length:  # Cut the last step at the tube's end.
                s_end = 0.0 if s < 0.0 else length
                s_prev, p_prev, a_prev = out[-1]
                f = (s_end - s_prev) / (s - s_prev)
                out.append((s_end, p_prev + f * (p - p_prev), a_prev + f * (a - a_prev)))
                return np.asarray(out), True
            out.append((s, p, a))
        return np.asarray(out), False


@dataclass(frozen=True)
class Geodesic:
    """A geodesic G traced on a bounding tube.

    Attributes:
        points: ``(k, 3)`` polyline from X_G, m.
        s, phi: ``(k,)`` tube coordinates of the points (m, rad).
        winding: ``(k,)`` running winding number around T from X_G (Eq. 1, or
            the Gauss linking integral, see ``method``); its sign is the
            handedness.
        reached: whether |winding| reached w0 (False if G ran off an end of T).
        method: ``"winding"`` (Eq. 1) or ``"linking"`` (Gauss integral).
        x_t: X_T, the point of T's axis closest to X, m.
        x_hat: unit winding axis, T's direction at X_T (times ``along``).
    """

    points: np.ndarray
    s: np.ndarray
    phi: np.ndarray
    winding: np.ndarray
    reached: bool
    method: str
    x_t: np.ndarray
    x_hat: np.ndarray

    @property
    def length(self) -> float:
        """Arc length of the polyline, m."""
        return float(np.linalg.norm(np.diff(self.points, axis=0), axis=1).sum())


def _axis_turns_over_90(tube: Tube, s_lo: float, s_hi: float, t0: np.ndarray) -> bool:
    """Whether T's tangent turns more than 90 degrees from t0 within [s_lo, s_hi]."""
    i0 = max(0, int(math.floor(min(s_lo, s_hi) / tube.ds)))
    i1 = min(len(tube.s) - 1, int(math.ceil(max(s_lo, s_hi) / tube.ds)))
    return bool(np.any(tube.tangent[i0 : i1 + 1] @ t0 <= 0.0))


def _running_winding(
    tube: Tube, pts: np.ndarray, x_t: np.ndarray, x_hat: np.ndarray, along: int, method: str
) -> np.ndarray:
    """Running winding of ``pts`` around the tube axis, signed by handedness."""
    if method == "winding":
        return winding_integral(pts, tube.centre, x_hat, x_t, cumulative=True)
    # Gauss integral with T extended far along its end tangents (an infinite-wire limit).
    far = 1e3 * max(tube.radius, tube.length)
    axis = np.vstack(
        [
            tube.centre[0] - far * tube.tangent[0],
            tube.centre,
            tube.centre[-1] + far * tube.tangent[-1],
        ]
    )
    lk = gauss_linking(pts, axis, closed_a=False, closed_b=False, cumulative=True)
    return along * lk


def smooth_axis(points: np.ndarray, scale: float, max_shift: float | None = None) -> np.ndarray:
    """Low-pass a rope polyline before a tube is built on it.

    A loaded rope has kinks of a rod's length where other ropes press on it;
    a straightest path is sensitive to them (the traced length of a 3-turn
    target line varied by 13 % between consecutive frames of a winding), while
    the tube only has to follow the rope on the scale of its radius. Repeated
    [1/4, 1/2, 1/4] passes approximate a Gaussian of standard deviation
    ``scale``; the end points stay put. With ``max_shift`` no point moves
    further than that from where it was: a tube of radius r_C + r_T + eps on
    an axis shifted by at most eps never cuts into the rope it bounds.

    Args:
        points: ``(n, 3)`` polyline, m, about evenly spaced.
        scale: smoothing length, m (0 returns a copy).
        max_shift: largest displacement of a point, m (None: unlimited).

    Returns:
        ``(n, 3)`` smoothed polyline.
    """
    y = np.asarray(points, dtype=np.float64).copy()
    if len(y) < 3 or scale <= 0.0:
        return y
    spacing = float(np.linalg.norm(np.diff(y, axis=0), axis=1).mean())
    passes = min(64, int(math.ceil(2.0 * (scale / max(spacing, 1e-12)) ** 2)))
    for _ in range(passes):
        y[1:-1] = 0.25 * y[:-2] + 0.5 * y[1:-1] + 0.25 * y[2:]
    if max_shift is not None:
        x = np.asarray(points, dtype=np.float64)
        d = y - x
        n = np.linalg.norm(d, axis=1, keepdims=True)
        y = x + d * np.minimum(1.0, max_shift / np.maximum(n, 1e-300))
    return y


def trace_geodesic(
    tube: Tube,
    x: np.ndarray,
    *,
    theta: float,
    w0: float,
    handedness: int = 1,
    along: int = 1,
    step: float | None = None,
    method: str = "auto",
    max_length: float | None = None,
) -> Geodesic:
    """Trace the winding target line G on the tube from the crossing point X (paper §4.2).

    G starts at X_G, the projection of X onto the tube, heading along T's
    direction x_hat at X_T rotated about the normal X_T->X_G by theta (larger
    theta winds tighter): by -theta (right-hand rule) for handedness +1, which
    makes G a right-handed helix, by +theta for -1. G is extended until its
    winding around T reaches w0; the RK4 steps are then cut where it equals w0.

    Args:
        tube: the bounding tube B of T.
        x: ``(3,)`` crossing point X, m.
        theta: angle between G and T's direction, 0 < theta < pi/2 (rad).
        w0: target number of turns, > 0.
        handedness: +1 for a right-handed (positive) winding, -1 for left.
        along: +1 to advance along T's particle order, -1 against it.
        step: RK4 arc-length step, m (default R / 4).
        method: ``"auto"`` (Eq. 1 unless T's axis turns more than 90 degrees
            over G's extent, then the Gauss linking integral), ``"winding"``
            or ``"linking"``.
        max_length: stop tracing after this length of G, m (default: the
            length of 4 w0 turns of the straight-tube helix plus T's length).

    Returns:
        The traced ``Geodesic``, cut where |winding| = w0 (linear in between).
    """
    if not 0.0 < theta < 0.5 * math.pi:
        raise ValueError(f"theta must lie in (0, pi/2), got {theta}")
    if w0 <= 0.0:
        raise ValueError(f"w0 must be positive, got {w0}")
    if handedness not in (1, -1) or along not in (1, -1):
        raise ValueError(f"handedness and along must be +1 or -1, got {handedness}, {along}")
    if method not in ("auto", "winding", "linking"):
        raise ValueError(f"method must be one of 'auto', 'winding', 'linking', got {method!r}")
    r = tube.radius
    step = 0.25 * r if step is None else float(step)
    if max_length is None:
        max_length = 4.0 * w0 * 2.0 * math.pi * r / math.sin(theta) + tube.length
    s0, phi0, _ = tube.project(x)
    c, t, _, _ = tube.frame(s0)
    x_t, x_hat = c[0], along * t[0]
    # alpha is measured from +s towards +phi; +phi turns right-handedly about +s.
    alpha0 = (0.0 if along > 0 else math.pi) + handedness * theta
    per_turn = 2.0 * math.pi * r / math.sin(theta)
    chunk = max(8, int(math.ceil(1.1 * w0 * per_turn / step)))

    states = np.array([[s0, phi0, alpha0]])
    left = False
    pts = tube.surface(states[:, 0], states[:, 1])
    use = method
    while True:
        if not left and (len(states) - 1) * step < max_length:
            n = min(chunk, int(math.ceil((max_length - (len(states) - 1) * step) / step)))
            new, left = tube.trace(*states[-1], step, max(n, 1))
            states = np.vstack([states, new[1:]])
            pts = tube.surface(states[:, 0], states[:, 1])
        if method == "auto":
            # Eq. 1 holds while T's axis turns less than 90 degrees over G's
            # extent up to where G reaches w0 (what lies beyond the cut does
            # not matter); otherwise fall back to the Gauss linking integral.
            wind = _running_winding(tube, pts, x_t, x_hat, along, "winding")
            hit = np.nonzero(handedness * wind >= w0)[0]
            upto = int(hit[0]) + 1 if len(hit) else len(states)
            turns = _axis_turns_over_90(tube, states[:upto, 0].min(), states[:upto, 0].max(), t[0])
            use = "linking" if turns else "winding"
            if use == "winding":
                if len(hit) or left or (len(states) - 1) * step >= max_length:
                    break
                continue
        wind = _running_winding(tube, pts, x_t, x_hat, along, use)
        hit = np.nonzero(handedness * wind >= w0)[0]
        if len(hit) or left or (len(states) - 1) * step >= max_length:
            break
    if len(hit):
        k = int(hit[0])
        w_a, w_b = handedness * wind[k - 1], handedness * wind[k]
        f = (w0 - w_a) / (w_b - w_a) if w_b != w_a else 1.0
        st = states[k - 1] + f * (states[k] - states[k - 1])
        states = np.vstack([states[:k], st])
        wind = np.concatenate([wind[:k], [handedness * w0]])
        pts = np.vstack([pts[:k], tube.surface(st[:1], st[1:2])])
        reached = True
    else:
        reached = False
    return Geodesic(
        points=pts,
        s=states[:, 0].copy(),
        phi=states[:, 1].copy(),
        winding=wind,
        reached=reached,
        method=use,
        x_t=x_t,
        x_hat=x_hat,
    )


def sample_targets(g: Geodesic | np.ndarray, spacing: float) -> np.ndarray:
    """Targets t_i every ``spacing`` (the rod length r, m) along G from its start.

    Args:
        g: a ``Geodesic`` or an ``(k, 3)`` polyline, m.
        spacing: arc-length spacing, m.

    Returns:
        ``(m, 3)`` points; the first is G's start, the last lies within
        ``spacing`` of G's end.
    """
    if spacing <= 0.0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    p = np.asarray(g.points if isinstance(g, Geodesic) else g, dtype=np.float64)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    at = np.arange(0.0, cum[-1] + 1e-12 * max(cum[-1], 1.0), spacing)
    return np.stack([np.interp(at, cum, p[:, k]) for k in range(3)], axis=1)
