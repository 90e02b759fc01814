"""The medial-sheet rule in NumPy (paper §5.2): reference for the Taichi pass in ``medial.py``.

Brute force over every particle and every control-line segment, O(n m): the
association at rest, and one pass of the rule. All lengths in metres.
"""

from __future__ import annotations

import numpy as np


def point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (N, S) from points p (N, 3) to segments [a, b] (S, 3), and the closest points (N, S, 3)."""
    p = np.asarray(p, np.float64)[:, None, :]
    a = np.asarray(a, np.float64)[None]
    b = np.asarray(b, np.float64)[None]
    e = b - a
    ee = np.maximum((e * e).sum(-1), 1e-30)
    t = np.clip(((p - a) * e).sum(-1) / ee, 0.0, 1.0)
    q = a + t[..., None] * e
    return np.linalg.norm(p - q, axis=-1), q


def window(seg: int, line_lo: int, line_hi: int, m: int) -> tuple[int, int]:
    """The ``m`` consecutive segments [lo, hi) of a line [line_lo, line_hi) centred on segment ``seg``."""
    k = min(m, line_hi - line_lo)
    lo = min(max(seg - (k - 1) // 2, line_lo), line_hi - k)
    return lo, lo + k


def associate_brute(x0, free, seg_a, seg_b, line_of, line_lo, line_hi, m: int = 3) -> np.ndarray:
    """(F, 2) [lo, hi) of each free particle's ``m`` segments, nearest at rest (first of equals), by brute force.

    Args:
        x0: (n, 3) rest positions (a flat cloth: distance along it is distance in space).
        free: (F,) particle indices.
        seg_a, seg_b: (S,) segment end particles.
        line_of: (S,) line of each segment; line_lo, line_hi: (lines,) its segments [lo, hi).
    """
    d, _ = point_segment(x0[free], x0[seg_a], x0[seg_b])
    near = np.argmin(d, axis=1)
    return np.array([window(s, line_lo[line_of[s]], line_hi[line_of[s]], m) for s in near], np.int64).reshape(-1, 2)


def pass_brute(x, free, own, seg_a, seg_b, step: float, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """One pass of the rule: new positions of the free particles (F, 3) and which moved (F,) bool.

    A free particle whose nearest segment within ``reach`` is not one of its own
    (``own`` (F, 2), [lo, hi)) moves by ``step`` towards the closest point on its
    own segments (onto it, if nearer than ``step``).
    """
    p = np.asarray(x, np.float64)[free]
    d, q = point_segment(p, x[seg_a], x[seg_b])
    s_idx = np.arange(len(seg_a))[None]
    mine = (s_idx >= own[:, :1]) & (s_idx < own[:, 1:])
    d_own = np.where(mine, d, np.inf)
    k_own = np.argmin(d_own, axis=1)
    best_own = d_own[np.arange(len(free)), k_own]
    best_other = np.where(mine, np.inf, d).min(axis=1)
    wrong = (best_other < best_own) & (best_other < reach)
    target = q[np.arange(len(free)), k_own]
    delta = target - p
    dist = np.linalg.norm(delta, axis=1)
    move = np.where(dist > step, step / np.maximum(dist, 1e-30), 1.0)[:, None] * delta
    return np.where(wrong[:, None], p + move, p), wrong
