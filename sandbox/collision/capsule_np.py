"""Capsule geometry in NumPy: segment-segment closest points and distance gradients.

Reference implementation, vectorised over N segment pairs, used by the
projection solver (paper Eq. 5) and as the brute-force oracle for the Taichi
capsule kernels. All lengths are in metres (or any consistent unit).
"""

from __future__ import annotations

import numpy as np

_EPS_LEN2 = 1e-24
"""Squared length (m^2) under which a segment counts as a point."""

_EPS_PARALLEL = 1e-12
"""Relative threshold on ``(a e - b^2) / (a e)`` (= sin^2 of the angle) for parallel segments."""


def _as_pairs(*arrays: np.ndarray) -> tuple[list[np.ndarray], bool]:
    """Broadcast inputs to (N, 3) float64; report whether they were single points."""
    arrs = [np.asarray(a, dtype=np.float64) for a in arrays]
    single = all(a.ndim == 1 for a in arrs)
    arrs = np.broadcast_arrays(*[np.atleast_2d(a) for a in arrs])
    return [np.ascontiguousarray(a) for a in arrs], single


def segment_segment_closest(p0, p1, q0, q1):
    """Closest points between segments [p0, p1] and [q0, q1].

    Ericson, Real-Time Collision Detection, §5.1.9, vectorised with clamping:
    c1 = p0 + s (p1 - p0), c2 = q0 + t (q1 - q0), s, t in [0, 1]. Zero-length
    segments degenerate to point-segment (or point-point) queries; parallel
    segments (sin^2 of the angle below 1e-12) take s = 0 and the matching t,
    which is one of the (non-unique) minimisers.

    Args:
        p0, p1: (N, 3) or (3,) end points of the first segments (m).
        q0, q1: (N, 3) or (3,) end points of the second segments (m).

    Returns:
        (s, t, c1, c2, dist): parameters (N,), closest points (N, 3) and
        distances |c1 - c2| (N,) in metres; scalars / (3,) for single inputs.
    """
    (p0, p1, q0, q1), single = _as_pairs(p0, p1, q0, q1)
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    f = np.einsum("ij,ij->i", d2, r)
    c = np.einsum("ij,ij->i", d1, r)
    b = np.einsum("ij,ij->i", d1, d2)

    p_pt = a <= _EPS_LEN2
    q_pt = e <= _EPS_LEN2
    a_safe = np.where(p_pt, 1.0, a)
    e_safe = np.where(q_pt, 1.0, e)

    denom = a * e - b * b
    parallel = denom <= _EPS_PARALLEL * a_safe * e_safe
    s_gen = np.where(parallel, 0.0, (b * f - c * e) / np.where(parallel, 1.0, denom))
    s_gen = np.clip(s_gen, 0.0, 1.0)
    t_gen = (b * s_gen + f) / e_safe
    # Re-clamp t and recompute s for the clamped t (Ericson's two branches).
    s_gen = np.where(t_gen < 0.0, np.clip(-c / a_safe, 0.0, 1.0),
                     np.where(t_gen > 1.0, np.clip((b - c) / a_safe, 0.0, 1.0), s_gen))
    t_gen = np.clip(t_gen, 0.0, 1.0)

    # Degenerate branches: first is a point, second is a point, or both.
    s = np.where(p_pt, 0.0, np.where(q_pt, np.clip(-c / a_safe, 0.0, 1.0), s_gen))
    t = np.where(p_pt, np.where(q_pt, 0.0, np.clip(f / e_safe, 0.0, 1.0)),
                 np.where(q_pt, 0.0, t_gen))

    c1 = p0 + s[:, None] * d1
    c2 = q0 + t[:, None] * d2
    dist = np.linalg.norm(c1 - c2, axis=1)
    if single:
        return s[0], t[0], c1[0], c2[0], dist[0]
    return s, t, c1, c2, dist


def point_segment_closest(x, q0, q1):
    """Closest point on segment [q0, q1] to x.

    Args:
        x, q0, q1: (N, 3) or (3,) points (m).

    Returns:
        (t, c, dist): parameter (N,) in [0, 1], closest point (N, 3), distance (N,) (m).
    """
    (x, q0, q1), single = _as_pairs(x, q0, q1)
    d = q1 - q0
    e = np.einsum("ij,ij->i", d, d)
    t = np.where(e <= _EPS_LEN2, 0.0,
                 np.einsum("ij,ij->i", x - q0, d) / np.where(e <= _EPS_LEN2, 1.0, e))
    t = np.clip(t, 0.0, 1.0)
    c = q0 + t[:, None] * d
    dist = np.linalg.norm(x - c, axis=1)
    if single:
        return t[0], c[0], dist[0]
    return t, c, dist


def contact_normals(p0, p1, q0, q1, c1, c2, dist, eps: float = 1e-12):
    """Unit normals n = dD/dc1 of the segment distance D, pointing from segment q to p.

    Where the axes touch (dist <= eps) the distance is not differentiable; the
    normal falls back to the common perpendicular d1 x d2, then to a direction
    perpendicular to d1 (parallel or point segments), then to +y, signed so
    that its first non-zero component among (y, x, z) is positive: exactly
    intersecting axes are separated with p moved up.

    Args:
        p0, p1, q0, q1: (N, 3) segment end points (m).
        c1, c2: (N, 3) closest points from :func:`segment_segment_closest` (m).
        dist: (N,) distances |c1 - c2| (m).
        eps: distance (m) under which the fallback is used.

    Returns:
        (N, 3) unit normals.
    """
    p0, p1, q0, q1, c1, c2 = (np.atleast_2d(np.asarray(a, dtype=np.float64))
                              for a in (p0, p1, q0, q1, c1, c2))
    dist = np.atleast_1d(dist)
    n = (c1 - c2) / np.maximum(dist, eps)[:, None]
    bad = dist <= eps
    if np.any(bad):
        d1 = p1[bad] - p0[bad]
        d2 = q1[bad] - q0[bad]
        fb = np.cross(d1, d2)
        ln = np.linalg.norm(fb, axis=1)
        # Parallel or degenerate: perpendicular to d1 (or +y if d1 is zero).
        weak = ln <= 1e-12 * np.maximum(
            np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1), 1e-300)
        if np.any(weak):
            base = d1[weak]
            helper = np.where(np.abs(base[:, [0]]) < 0.9 * np.linalg.norm(base, axis=1,
                                                                         keepdims=True),
                              np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
            perp = np.cross(base, helper)
            pl = np.linalg.norm(perp, axis=1)
            perp[pl <= 0.0] = (0.0, 1.0, 0.0)
            fb[weak] = perp
            ln[weak] = np.linalg.norm(perp, axis=1)
        fb /= ln[:, None]
        # Deterministic side (p above q): first non-zero of the y, x, z components positive.
        key = np.where(fb[:, 1] != 0.0, fb[:, 1], np.where(fb[:, 0] != 0.0, fb[:, 0], fb[:, 2]))
        fb[key < 0.0] *= -1.0
        n[bad] = fb
    return n


def capsule_distance_jacobian(s, t, normals):
    """Gradient of the segment distance D with respect to the four end points.

    With unique closest points c1 = (1-s) p0 + s p1, c2 = (1-t) q0 + t q1 and
    n = (c1 - c2)/|c1 - c2|, the envelope theorem gives dD/dp0 = (1-s) n,
    dD/dp1 = s n, dD/dq0 = -(1-t) n, dD/dq1 = -t n (paper Eq. 5 Jacobian).

    Args:
        s, t: (N,) closest-point parameters.
        normals: (N, 3) unit normals from :func:`contact_normals`.

    Returns:
        (N, 4, 3) gradients for (p0, p1, q0, q1) (dimensionless).
    """
    s = np.atleast_1d(s)[:, None]
    t = np.atleast_1d(t)[:, None]
    n = np.atleast_2d(normals)
    return np.stack([(1.0 - s) * n, s * n, -(1.0 - t) * n, -t * n], axis=1)
