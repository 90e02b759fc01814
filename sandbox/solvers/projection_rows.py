"""Constraint rows of the rope projection (paper §4.3, Eq. 2-5), in NumPy.

A block of m constraint rows is stored in a compact, sparse-friendly form:
each row r touches ``k`` particles ``idx[r, :]`` with 3-vector coefficients
``coef[r, :, :]``, so that the row of the Jacobian is
``J[r] dp = sum_j coef[r, j] . dp[idx[r, j]]``. Values ``C`` are evaluated
at the linearisation point. Everything here is in the solver's scaled,
dimensionless length unit (see ``projection.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from sandbox.collision.capsule_np import (capsule_distance_jacobian, contact_normals,
                                          segment_segment_closest)

SdfFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""Signed distance: points (k, 3) -> (d (k,), unit outward normals (k, 3)), metres."""


@dataclass
class RopeSystem:
    """A set of ropes as plain arrays.

    Attributes:
        x: (n, 3) float64 particle positions of all ropes concatenated (m).
        rope_ranges: per rope, the half-open particle range (start, end).
        rest_length: (n_ropes,) rod length r per rope (m).
        radius: (n_ropes,) capsule radius per rope (m).
        pinned: (n,) bool, pinned particles never move (eliminated unknowns).
    """

    x: np.ndarray
    rope_ranges: list[tuple[int, int]]
    rest_length: np.ndarray
    radius: np.ndarray
    pinned: np.ndarray = field(default=None)

    def __post_init__(self) -> None:
        self.x = np.asarray(self.x, dtype=np.float64).reshape(-1, 3)
        self.rope_ranges = [(int(a), int(b)) for a, b in self.rope_ranges]
        self.rest_length = np.atleast_1d(np.asarray(self.rest_length, dtype=np.float64))
        self.radius = np.atleast_1d(np.asarray(self.radius, dtype=np.float64))
        n = len(self.x)
        self.pinned = (np.zeros(n, bool) if self.pinned is None
                       else np.asarray(self.pinned, dtype=bool).reshape(n))
        n_ropes = len(self.rope_ranges)
        if self.rest_length.size != n_ropes or self.radius.size != n_ropes:
            raise ValueError(f"rest_length and radius need {n_ropes} entries (one per rope)")
        prev = 0
        for a, b in self.rope_ranges:
            if a < prev or b <= a or b > n:
                raise ValueError(f"rope range ({a}, {b}) must be ordered, non-empty, "
                                 f"within [0, {n}]")
            prev = b
        if np.any(self.rest_length <= 0.0) or np.any(self.radius < 0.0):
            raise ValueError("rest_length must be > 0 and radius >= 0")

    @property
    def n_particles(self) -> int:
        """Number of particles n."""
        return len(self.x)

    def topology(self) -> "Topology":
        """Index arrays of rods, bending triples and segments (static per rope set)."""
        return Topology.build(self)


@dataclass
class Topology:
    """Static index arrays derived from a :class:`RopeSystem`.

    Attributes:
        rods: (m, 2) particle pairs (i, i+1); also the capsule segments.
        rod_rope: (m,) rope id of each rod.
        bends: (q, 3) particle triples (i-1, i, i+1).
        bend_rope: (q,) rope id of each triple.
        seg_local: (m,) index of the segment inside its rope.
        particle_rope: (n,) rope id of each particle (-1 if in no rope).
        self_gap: (n_ropes,) smallest segment index gap tested for self-collision.
    """

    rods: np.ndarray
    rod_rope: np.ndarray
    bends: np.ndarray
    bend_rope: np.ndarray
    seg_local: np.ndarray
    particle_rope: np.ndarray
    self_gap: np.ndarray

    @classmethod
    def build(cls, system: RopeSystem) -> "Topology":
        """Index arrays for all ropes; O(n)."""
        rods, rr, bends, br, loc = [], [], [], [], []
        prope = np.full(system.n_particles, -1, dtype=np.int64)
        for k, (a, b) in enumerate(system.rope_ranges):
            prope[a:b] = k
            i = np.arange(a, b - 1)
            rods.append(np.stack([i, i + 1], axis=1))
            rr.append(np.full(len(i), k))
            loc.append(np.arange(len(i)))
            j = np.arange(a + 1, b - 1)
            bends.append(np.stack([j - 1, j, j + 1], axis=1))
            br.append(np.full(len(j), k))
        cat = lambda xs, w: (np.concatenate(xs).astype(np.int64) if xs
                             else np.zeros((0,) + w, dtype=np.int64))
        # Segments i and i+g of one rope are (g-1) r apart when straight: the paper
        # skips adjacent capsules (g >= 2); thick ropes (2 r_rope > r) skip more.
        gap = np.maximum(2, np.ceil(2.0 * system.radius / system.rest_length - 1e-9) + 1)
        return cls(cat(rods, (2,)).reshape(-1, 2), cat(rr, ()), cat(bends, (3,)).reshape(-1, 3),
                   cat(br, ()), cat(loc, ()), prope, gap.astype(np.int64))


@dataclass
class Rows:
    """A block of linearised constraint rows C(p + dp) ~ C + J dp.

    Attributes:
        idx: (m, k) particle indices touched by each row.
        coef: (m, k, 3) Jacobian coefficients per touched particle.
        value: (m,) constraint values C at the linearisation point.
    """

    idx: np.ndarray
    coef: np.ndarray
    value: np.ndarray

    @classmethod
    def empty(cls, k: int = 1) -> "Rows":
        """A block with no rows."""
        return cls(np.zeros((0, k), np.int64), np.zeros((0, k, 3)), np.zeros(0))

    def __len__(self) -> int:
        return len(self.value)

    def take(self, sel) -> "Rows":
        """Sub-block of the selected rows."""
        return Rows(self.idx[sel], self.coef[sel], self.value[sel])

    def triplets(self, free_map: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """COO triplets (row, col, value) of J over free DOFs; pinned and zero entries dropped."""
        m, k = self.idx.shape
        col_p = free_map[self.idx]                       # (m, k), -1 when pinned
        keep = (col_p >= 0)[:, :, None] & (self.coef != 0.0)
        rows = np.broadcast_to(np.arange(m)[:, None, None], (m, k, 3))
        cols = 3 * col_p[:, :, None] + np.arange(3)[None, None, :]
        return rows[keep], cols[keep], self.coef[keep]

    def matrix(self, free_map: np.ndarray, n_free: int) -> sp.csr_matrix:
        """Sparse Jacobian (m, 3 n_free) over free particles; pinned entries are dropped."""
        r, c, v = self.triplets(free_map)
        return sp.csr_matrix((v, (r, c)), shape=(len(self), 3 * n_free))

    def gram_triplets(self, w: np.ndarray, free_map: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """COO triplets of J^T diag(w) J over free DOFs (duplicates to be summed), O(m k^2)."""
        col_p = free_map[self.idx]                                      # (m, k)
        blk = np.einsum("r,rac,rbd->rabcd", w, self.coef, self.coef)     # (m, k, k, 3, 3)
        dof = 3 * col_p[:, :, None] + np.arange(3)                       # (m, k, 3)
        ca = np.broadcast_to(dof[:, :, None, :, None], blk.shape)
        cb = np.broadcast_to(dof[:, None, :, None, :], blk.shape)
        if np.all(col_p >= 0):
            return ca.ravel(), cb.ravel(), blk.ravel()
        ok = ((col_p[:, :, None] >= 0) & (col_p[:, None, :] >= 0))[:, :, :, None, None]
        keep = np.broadcast_to(ok, blk.shape)
        return ca[keep], cb[keep], blk[keep]

    def rmatvec(self, y: np.ndarray, free_map: np.ndarray, n_free: int) -> np.ndarray:
        """J^T y over free DOFs, shape (3 n_free,)."""
        r, c, v = self.triplets(free_map)
        return np.bincount(c, weights=v * y[r], minlength=3 * n_free)

    def apply(self, dp: np.ndarray) -> np.ndarray:
        """J dp for a full (n, 3) displacement."""
        return np.einsum("rkc,rkc->r", self.coef, dp[self.idx])


def stretch_rows(x: np.ndarray, topo: Topology, r: np.ndarray) -> Rows:
    """Inextensibility C_e = |p_{i+1} - p_i|^2 - r^2 (Eq. 2); J = (-2 d, 2 d), d = p_{i+1} - p_i."""
    d = x[topo.rods[:, 1]] - x[topo.rods[:, 0]]
    val = np.einsum("ij,ij->i", d, d) - r[topo.rod_rope] ** 2
    return Rows(topo.rods, np.stack([-2.0 * d, 2.0 * d], axis=1), val)


def bend_rows(x: np.ndarray, topo: Topology, r: np.ndarray) -> Rows:
    """Bending C_b = |p_{i+1} - p_{i-1}| - 2 r (Eq. 3); J = (-u, 0, u), u the unit chord."""
    ends = topo.bends[:, [0, 2]]
    d = x[ends[:, 1]] - x[ends[:, 0]]
    ln = np.linalg.norm(d, axis=1)
    u = d / np.maximum(ln, 1e-300)[:, None]
    return Rows(ends, np.stack([-u, u], axis=1), ln - 2.0 * r[topo.bend_rope])


def kinematic_rows(x: np.ndarray, targets: Sequence[tuple[int, np.ndarray]],
                   pinned: np.ndarray) -> Rows:
    """Kinematic targets (Eq. 4) as the vector constraint p_c - p_k = 0: three rows per target.

    |C_k|^2 = |p_c - p_k|^2 is exactly the sum of the squares of the three rows,
    so the soft term c |C_k|^2 is unchanged while the Jacobian (identity) stays
    regular at C_k = 0 where the norm's gradient is undefined. Targets on pinned
    particles are ignored (the pin wins).
    """
    tg = [(int(i), np.asarray(p, dtype=np.float64)) for i, p in targets if not pinned[int(i)]]
    if not tg:
        return Rows.empty(1)
    idx = np.repeat(np.array([i for i, _ in tg], dtype=np.int64), 3)[:, None]
    coef = np.tile(np.eye(3), (len(tg), 1))[:, None, :]
    val = np.concatenate([x[i] - p for i, p in tg])
    return Rows(idx, coef, val)


def broad_phase_pairs(x: np.ndarray, topo: Topology, radius: np.ndarray,
                      margin: float) -> np.ndarray:
    """Candidate capsule pairs (s_i < s_j) from a cKDTree on segment midpoints.

    Two segments with midpoints m_i, m_j and half-lengths h_i, h_j are at least
    |m_i - m_j| - h_i - h_j apart, so querying with radius
    2 max(h) + max(r_i + r_j) + margin misses no pair closer than the margin.
    Same-rope pairs closer than the rope's ``self_gap`` in index are dropped.
    O(m log m) to build, O(m) pairs for a rope of bounded density.
    """
    if len(topo.rods) < 2:
        return np.zeros((0, 2), np.int64)
    a, b = x[topo.rods[:, 0]], x[topo.rods[:, 1]]
    mid = 0.5 * (a + b)
    half = 0.5 * np.linalg.norm(b - a, axis=1)
    query = 2.0 * half.max() + 2.0 * radius.max() + margin
    pairs = cKDTree(mid).query_pairs(query, output_type="ndarray").astype(np.int64)
    if len(pairs) == 0:
        return pairs.reshape(0, 2)
    ri, rj = topo.rod_rope[pairs[:, 0]], topo.rod_rope[pairs[:, 1]]
    gap = np.abs(topo.seg_local[pairs[:, 0]] - topo.seg_local[pairs[:, 1]])
    keep = (ri != rj) | (gap >= topo.self_gap[ri])
    pairs = pairs[keep]
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def capsule_rows(x: np.ndarray, topo: Topology, radius: np.ndarray,
                 pairs: np.ndarray) -> Rows:
    """Capsule collision C_c = D(capsule_i, capsule_j) - (r_i + r_j) >= 0 (Eq. 5).

    Jacobian from the closest points with barycentric weights,
    (1-s) n, s n, -(1-t) n, -t n on the four end points.
    """
    if len(pairs) == 0:
        return Rows.empty(4)
    si, sj = topo.rods[pairs[:, 0]], topo.rods[pairs[:, 1]]
    p0, p1, q0, q1 = x[si[:, 0]], x[si[:, 1]], x[sj[:, 0]], x[sj[:, 1]]
    s, t, c1, c2, dist = segment_segment_closest(p0, p1, q0, q1)
    n = contact_normals(p0, p1, q0, q1, c1, c2, dist)
    rsum = radius[topo.rod_rope[pairs[:, 0]]] + radius[topo.rod_rope[pairs[:, 1]]]
    return Rows(np.concatenate([si, sj], axis=1), capsule_distance_jacobian(s, t, n),
                dist - rsum)


def ground_rows(x: np.ndarray, particles: np.ndarray, prad: np.ndarray,
                height: float) -> Rows:
    """Ground half-space y - h - radius >= 0 per particle, J = e_y."""
    coef = np.zeros((len(particles), 1, 3))
    coef[:, 0, 1] = 1.0
    return Rows(particles[:, None], coef, x[particles, 1] - height - prad[particles])


def sdf_rows(x: np.ndarray, particles: np.ndarray, prad: np.ndarray, sdf: SdfFn,
             scale: float) -> Rows:
    """Object contact d(p) - radius >= 0 per particle, linearised with the SDF normal.

    ``sdf`` works in metres; ``scale`` (m per solver unit) converts to and from it.
    """
    d, nrm = sdf(x[particles] * scale)
    d = np.asarray(d, dtype=np.float64).reshape(-1) / scale
    nrm = np.asarray(nrm, dtype=np.float64).reshape(-1, 3)
    return Rows(particles[:, None], nrm[:, None, :], d - prad[particles])


def concat_rows(blocks: Sequence[Rows]) -> Rows:
    """Stack blocks with different ``k`` by padding (index 0, zero coefficient)."""
    blocks = [b for b in blocks if len(b)]
    if not blocks:
        return Rows.empty(1)
    k = max(b.idx.shape[1] for b in blocks)
    m = sum(len(b) for b in blocks)
    idx, coef = np.zeros((m, k), np.int64), np.zeros((m, k, 3))
    start = 0
    for b in blocks:
        kb = b.idx.shape[1]
        idx[start:start + len(b), :kb] = b.idx
        coef[start:start + len(b), :kb] = b.coef
        start += len(b)
    return Rows(idx, coef, np.concatenate([b.value for b in blocks]))
