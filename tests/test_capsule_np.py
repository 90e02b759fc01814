"""NumPy segment-segment closest points against brute-force sampling and closed forms."""

import numpy as np
import pytest

from sandbox.collision.capsule_np import (capsule_distance_jacobian, contact_normals,
                                          point_segment_closest, segment_segment_closest)

K = 401  # samples per segment for the brute-force reference


def _brute(p0, p1, q0, q1):
    """Minimum distance over K x K samples of both segments, per pair."""
    u = np.linspace(0.0, 1.0, K)
    out = np.empty(len(p0))
    for i in range(len(p0)):
        a = p0[i] + u[:, None] * (p1[i] - p0[i])                        # (K, 3)
        b = q0[i] + u[:, None] * (q1[i] - q0[i])
        d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
        k = np.argmin(d2)                                               # exact distance below
        out[i] = np.linalg.norm(a[k // K] - b[k % K])
    return out


def _special_cases():
    """Parallel, collinear, touching, crossing, zero-length and nearly parallel pairs."""
    z = np.zeros(3)
    ex, ey, ez = np.eye(3)
    cases = [
        (z, ex, ey, ey + ex),                    # parallel, overlapping in projection
        (z, ex, ey + 2 * ex, ey + 3 * ex),       # parallel, disjoint in projection
        (z, 2 * ex, ex, 3 * ex),                 # collinear, overlapping (distance 0)
        (z, ex, 2 * ex, 3 * ex),                 # collinear, disjoint
        (z, ex, ex, ex + ey),                    # touching at an end point
        (-ex, ex, -ez + 0.3 * ey, ez + 0.3 * ey),  # crossing above
        (-ex, ex, -ez, ez),                      # crossing through (distance 0)
        (z, z, ey, ey + ex),                     # first is a point
        (ey, ey + ex, 0.5 * ex, 0.5 * ex),       # second is a point
        (z, z, ey, ey),                          # both points
        (z, ex, ey, ey + ex + 1e-9 * ez),        # nearly parallel
        (z, ex, ex + ey, ey),                    # anti-parallel
        (z, ex, 0.5 * ex + 0.2 * ey, 0.5 * ex + 0.2 * ey + ez),  # T-junction
    ]
    return [np.array(c, dtype=np.float64) for c in zip(*cases)]


def _random_cases(rng, n):
    """Random pairs, plus random parallel and degenerate ones."""
    p0, p1, q0, q1 = (rng.normal(size=(n, 3)) for _ in range(4))
    par = rng.random(n) < 0.2                      # parallel: q1 - q0 = k (p1 - p0)
    q1[par] = q0[par] + rng.normal(size=(par.sum(), 1)) * (p1 - p0)[par]
    deg = rng.random(n) < 0.1
    p1[deg] = p0[deg]
    return p0, p1, q0, q1


@pytest.mark.parametrize("kind", ["special", "random"])
def test_distance_matches_brute_force(kind):
    """Distance is never above any sampled pair and within sampling tolerance of the minimum."""
    rng = np.random.default_rng(3)
    p0, p1, q0, q1 = _special_cases() if kind == "special" else _random_cases(rng, 150)
    s, t, c1, c2, dist = segment_segment_closest(p0, p1, q0, q1)
    ref = _brute(p0, p1, q0, q1)
    h = 0.5 / (K - 1) * (np.linalg.norm(p1 - p0, axis=1) + np.linalg.norm(q1 - q0, axis=1))
    assert np.all(dist <= ref + 1e-12)
    assert np.all(dist >= ref - h - 1e-12)


def test_outputs_are_consistent():
    """c1, c2 lie on their segments at s, t in [0, 1] and dist = |c1 - c2|."""
    rng = np.random.default_rng(4)
    p0, p1, q0, q1 = _random_cases(rng, 200)
    s, t, c1, c2, dist = segment_segment_closest(p0, p1, q0, q1)
    assert np.all((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1))
    np.testing.assert_allclose(c1, p0 + s[:, None] * (p1 - p0), atol=1e-14)
    np.testing.assert_allclose(c2, q0 + t[:, None] * (q1 - q0), atol=1e-14)
    np.testing.assert_allclose(dist, np.linalg.norm(c1 - c2, axis=1), atol=0)


def test_closed_forms():
    """Crossing lines, parallel lines and collinear gaps give their exact distances."""
    ex, ey, ez = np.eye(3)
    s, t, c1, c2, d = segment_segment_closest(-ex, ex, -ez + 0.3 * ey, ez + 0.3 * ey)
    assert d == pytest.approx(0.3, abs=1e-15)
    assert s == pytest.approx(0.5) and t == pytest.approx(0.5)
    assert segment_segment_closest(0 * ex, ex, 2 * ey, 2 * ey + ex)[4] == pytest.approx(2.0)
    assert segment_segment_closest(0 * ex, ex, 3 * ex, 5 * ex)[4] == pytest.approx(2.0)
    assert segment_segment_closest(0 * ex, 0 * ex, ey, ey)[4] == pytest.approx(1.0)
    assert np.ndim(d) == 0 and np.shape(c1) == (3,)


def test_point_segment_against_sampling():
    """Point-segment distance is the sampled minimum (zero-length segments included)."""
    rng = np.random.default_rng(5)
    x, q0, q1 = (rng.normal(size=(100, 3)) for _ in range(3))
    q1[:10] = q0[:10]
    t, c, d = point_segment_closest(x, q0, q1)
    u = np.linspace(0, 1, 2001)
    pts = q0[:, None, :] + u[None, :, None] * (q1 - q0)[:, None, :]
    ref = np.linalg.norm(pts - x[:, None, :], axis=-1).min(axis=1)
    assert np.all(d <= ref + 1e-12)
    assert np.all(d >= ref - np.linalg.norm(q1 - q0, axis=1) / 4000 - 1e-12)


def test_distance_jacobian_matches_finite_differences():
    """dD/d(end points) from barycentric weights equals central differences for generic pairs."""
    rng = np.random.default_rng(6)
    p0, p1, q0, q1 = (rng.normal(size=(20, 3)) for _ in range(4))
    s, t, c1, c2, d = segment_segment_closest(p0, p1, q0, q1)
    jac = capsule_distance_jacobian(s, t, contact_normals(p0, p1, q0, q1, c1, c2, d))
    pts = np.stack([p0, p1, q0, q1], axis=1)
    h = 1e-6
    for a in range(4):
        for c in range(3):
            hi, lo = pts.copy(), pts.copy()
            hi[:, a, c] += h
            lo[:, a, c] -= h
            fd = (segment_segment_closest(*hi.transpose(1, 0, 2))[4]
                  - segment_segment_closest(*lo.transpose(1, 0, 2))[4]) / (2 * h)
            np.testing.assert_allclose(jac[:, a, c], fd, atol=1e-6)


def test_normals_fallback_when_axes_touch():
    """At zero distance the normal is unit, perpendicular to both segments and points up (+y)."""
    ex, ey, ez = np.eye(3)
    p0, p1, q0, q1 = (np.array([v]) for v in (-ex + 1e-3 * ey, ex - 1e-3 * ey, -ez, ez))
    s, t, c1, c2, d = segment_segment_closest(p0, p1, q0, q1)
    assert d[0] < 1e-12
    n = contact_normals(p0, p1, q0, q1, c1, c2, d)[0]
    assert np.linalg.norm(n) == pytest.approx(1.0)
    assert abs(n @ (p1 - p0)[0]) < 1e-12 and abs(n @ ez) < 1e-12 and n[1] > 0.9
    n_swapped = contact_normals(q0, q1, p0, p1, c2, c1, d)[0]
    assert n_swapped[1] > 0.9                                  # deterministic, not order-based
    par = contact_normals(np.zeros((1, 3)), ex[None], np.zeros((1, 3)), 2 * ex[None],
                          np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1))[0]
    assert np.linalg.norm(par) == pytest.approx(1.0) and abs(par @ ex) < 1e-12
