"""Knot diagrams from space curves: isotopy-preserving polygon reduction and
projection to a signed Gauss code.

A closed polygon is first reduced in 3-D: a vertex is dropped when the
triangle it spans with its neighbours is met by no other segment (straightening
it is then an isotopy). The reduced polygon is projected along a seeded random
direction (retried while the projection is degenerate: a crossing at a vertex,
overlapping strands, or strands touching); crossings are found exactly between
segments and turned into the signed Gauss code that
``sandbox.geometry.knot_invariants`` works on. Crossing signs follow the
right-hand rule: positive when, both strands pointing up, the over strand runs
from lower left to upper right.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from sandbox.geometry import knot_invariants as inv

__all__ = ["DegenerateProjection", "best_diagram", "gauss_code", "reduce_polygon"]


# -- simplification in 3-D ------------------------------------------------------------------


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (broadcasting, without np.cross overhead)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _triangle_hits(a, b, c, s0, s1, tol: float) -> np.ndarray:
    """Which segments (s0, s1) meet triangles (a, b, c), broadcast (Moller-Trumbore).

    The test is inflated by ``tol`` (relative) so that near misses count as hits;
    segments parallel to a triangle's plane count when they lie within the
    inflated distance of it and overlap its bounding box.
    """
    e1, e2 = b - a, c - a
    d = s1 - s0
    pv = _cross(d, e2)
    det = np.sum(pv * e1, axis=-1)
    nrm = _cross(e1, e2)
    area2 = np.linalg.norm(nrm, axis=-1)
    size = np.sqrt(area2)
    dl = np.linalg.norm(d, axis=-1)
    flat = np.abs(det) <= 1e-12 * area2 * dl
    inv_det = 1.0 / np.where(flat, 1.0, det)
    tv = s0 - a
    u = np.sum(tv * pv, axis=-1) * inv_det
    qv = _cross(tv, e1)
    v = np.sum(qv * d, axis=-1) * inv_det
    t = np.sum(qv * e2, axis=-1) * inv_det
    hit = ~flat & (u >= -tol) & (v >= -tol) & (u + v <= 1.0 + tol) & (t >= -tol) & (t <= 1.0 + tol)
    if np.any(flat):
        pad = (tol * size)[..., None]
        lo = np.minimum(np.minimum(a, b), c) - pad
        hi = np.maximum(np.maximum(a, b), c) + pad
        near = np.all((np.maximum(s0, s1) >= lo) & (np.minimum(s0, s1) <= hi), axis=-1)
        dist = np.abs(np.sum(tv * nrm, axis=-1)) / np.maximum(area2, 1e-300)
        hit |= flat & near & (dist <= tol * size)
    return hit


def _pairs_hitting(a, b, c, s0, s1, mask, tol: float, pad: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (triangle i, segment j) allowed by ``mask`` that meet, with a box prefilter."""
    t_lo = np.minimum(np.minimum(a, b), c) - pad
    t_hi = np.maximum(np.maximum(a, b), c) + pad
    g_lo, g_hi = np.minimum(s0, s1), np.maximum(s0, s1)
    near = mask.copy()
    for k in range(3):
        near &= g_hi[None, :, k] >= t_lo[:, None, k]
        near &= g_lo[None, :, k] <= t_hi[:, None, k]
    ti, sj = np.nonzero(near)
    hit = _triangle_hits(a[ti], b[ti], c[ti], s0[sj], s1[sj], tol)
    return ti[hit], sj[hit]


def _independent(cands: np.ndarray, n: int) -> np.ndarray:
    """A subset of sorted vertex indices no two of which are cyclically adjacent."""
    out: list[int] = []
    for i in cands.tolist():
        if out and i - out[-1] < 2:
            continue
        out.append(i)
    if len(out) > 1 and out[0] + n - out[-1] < 2:
        out.pop()
    return np.asarray(out, dtype=np.int64)


def reduce_polygon(closed: np.ndarray, *, tol: float = 1e-6, max_passes: int = 200) -> np.ndarray:
    """Drop vertices of a closed polygon while keeping its knot type.

    A vertex is removed when the triangle it spans with its two neighbours is
    met by no other segment, so straightening it is an isotopy. Each pass tests
    all vertices at once and removes a non-adjacent set of free ones whose
    triangles also miss each other's new segments (so the removals are valid
    in any order).

    Args:
        closed: ``(n, 3)`` closed polygon.
        tol: relative inflation of the triangle test (conservative).
        max_passes: bound on passes.

    Returns:
        ``(m, 3)`` closed polygon with 3 <= m <= n.
    """
    p = np.asarray(closed, dtype=np.float64)
    for _ in range(max_passes):
        n = len(p)
        if n <= 4:
            break
        idx = np.arange(n)
        a, b, c = p[idx - 1], p, p[(idx + 1) % n]
        pad = tol * float(np.ptp(p, axis=0).max())
        # Segment j touches triangle i when j is i-2, i-1, i or i+1 (mod n).
        off = (idx[None, :] - idx[:, None]) % n
        ti, sj = _pairs_hitting(
            a, b, c, p, np.roll(p, -1, axis=0), (off >= 2) & (off <= n - 3), tol, pad
        )
        blocked = np.zeros(n, dtype=bool)
        blocked[ti] = True
        free = np.nonzero(~blocked)[0]
        if len(free) == 0:
            break
        sel = _independent(free, n)
        if len(sel) > 1:
            # New segments p[i-1] -> p[i+1] must miss the other selected triangles.
            gap = np.abs(sel[:, None] - sel[None, :])
            gap = np.minimum(gap, n - gap)
            ti, sj = _pairs_hitting(
                a[sel], b[sel], c[sel], p[sel - 1], p[(sel + 1) % n], gap > 2, tol, pad
            )
            clash = np.zeros(len(sel), dtype=bool)
            clash[ti] = True
            clash[sj] = True
            sel = sel[~clash] if not clash.all() else sel[:1]
        p = np.delete(p, sel, axis=0)
    return p


# -- projection and Gauss code ----------------------------------------------------------------


class DegenerateProjection(ValueError):
    """The projection has a crossing at a vertex, overlapping or tangent strands."""


def _plane_basis(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Right-handed basis (e1, e2, v) with v the unit view direction."""
    v = np.asarray(direction, dtype=np.float64)
    v = v / np.linalg.norm(v)
    a = np.array([1.0, 0.0, 0.0]) if abs(v[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(a, v)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v, e1)
    return e1, e2, v


def gauss_code(closed: np.ndarray, direction: np.ndarray, *, tol: float = 1e-7) -> inv.GaussCode:
    """Signed Gauss code of a closed polygon seen from ``direction`` (towards the viewer).

    Args:
        closed: ``(n, 3)`` closed polygon.
        direction: view direction; points higher along it pass over.
        tol: relative tolerance for degenerate configurations.

    Returns:
        ``(passages, signs)`` (see ``knot_invariants``).

    Raises:
        DegenerateProjection: when the projection is not generic.
    """
    p = np.asarray(closed, dtype=np.float64)
    n = len(p)
    e1, e2, v = _plane_basis(direction)
    q = np.stack([p @ e1, p @ e2], axis=1)
    h = p @ v
    d = np.roll(q, -1, axis=0) - q
    scale = float(np.ptp(q, axis=0).max()) or 1.0
    # Folding back on itself at a vertex (adjacent segments overlapping).
    dn = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    dprev = np.roll(dn, 1, axis=0)
    crs = dprev[:, 0] * dn[:, 1] - dprev[:, 1] * dn[:, 0]
    if np.any((np.abs(crs) < 1e-9) & (np.sum(dprev * dn, axis=1) < 0)):
        raise DegenerateProjection("adjacent segments overlap in projection")
    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))
    i, j = i[keep], j[keep]
    den = d[i, 0] * d[j, 1] - d[i, 1] * d[j, 0]
    r = q[j] - q[i]
    safe = np.where(np.abs(den) > 0, den, 1.0)
    s = (r[:, 0] * d[j, 1] - r[:, 1] * d[j, 0]) / safe
    u = (r[:, 0] * d[i, 1] - r[:, 1] * d[i, 0]) / safe
    li = np.linalg.norm(d[i], axis=1)
    lj = np.linalg.norm(d[j], axis=1)
    par = np.abs(den) <= 1e-12 * li * lj
    if np.any(par):
        # Parallel pairs: degenerate only if collinear and overlapping.
        off = np.abs(r[par, 0] * d[i][par, 1] - r[par, 1] * d[i][par, 0]) / np.maximum(
            li[par], 1e-300
        )
        if np.any(off < tol * scale):
            a0 = np.sum(r[par] * d[i][par], axis=1) / li[par] ** 2
            a1 = np.sum((r[par] + d[j][par]) * d[i][par], axis=1) / li[par] ** 2
            lo, hi = np.minimum(a0, a1), np.maximum(a0, a1)
            if np.any((off < tol * scale) & (hi > -tol) & (lo < 1 + tol)):
                raise DegenerateProjection("collinear overlapping segments")
    ok = ~par
    ts, tu = tol * scale / np.maximum(li, 1e-300), tol * scale / np.maximum(lj, 1e-300)
    inside = ok & (s > -ts) & (s < 1 + ts) & (u > -tu) & (u < 1 + tu)
    near_end = inside & ((s < ts) | (s > 1 - ts) | (u < tu) | (u > 1 - tu))
    if np.any(near_end):
        raise DegenerateProjection("crossing at a vertex")
    cross = inside
    ci, cj, cs, cu = i[cross], j[cross], s[cross], u[cross]
    hi_ = h[ci] + cs * (h[(ci + 1) % n] - h[ci])
    hj_ = h[cj] + cu * (h[(cj + 1) % n] - h[cj])
    hscale = float(np.ptp(h)) or 1.0
    if np.any(np.abs(hi_ - hj_) < tol * hscale):
        raise DegenerateProjection("strands touch at a crossing")
    i_over = hi_ > hj_
    do = np.where(i_over[:, None], d[ci], d[cj])
    du = np.where(i_over[:, None], d[cj], d[ci])
    sg = np.sign(do[:, 0] * du[:, 1] - do[:, 1] * du[:, 0]).astype(int)
    passages = []
    for k in range(len(ci)):
        passages.append((ci[k] + cs[k], k, bool(i_over[k])))
        passages.append((cj[k] + cu[k], k, not bool(i_over[k])))
    passages.sort()
    code = [(k, o) for _, k, o in passages]
    return code, {k: int(sg[k]) for k in range(len(ci))}


def _random_directions(seed: int) -> Iterator[np.ndarray]:
    """Uniformly random unit vectors from a seeded generator."""
    rng = np.random.default_rng(seed)
    while True:
        v = rng.normal(size=3)
        yield v / np.linalg.norm(v)


def best_diagram(closed: np.ndarray, *, seed: int = 0, projections: int = 3) -> inv.GaussCode:
    """The Reidemeister-simplified diagram with fewest crossings over generic projections.

    Args:
        closed: ``(n, 3)`` closed polygon (ideally reduced first).
        seed: seed of the random projection directions.
        projections: number of generic projections compared.

    Raises:
        DegenerateProjection: when no generic projection is found.
    """
    best = None
    tried = 0
    for direction in _random_directions(seed):
        if tried >= 20 * projections:
            break
        tried += 1
        try:
            code, signs = gauss_code(closed, direction)
        except DegenerateProjection:
            continue
        code, signs = inv.simplify(code, signs)
        if best is None or len(code) < len(best[0]):
            best = (code, signs)
        projections -= 1
        if projections <= 0 or not code:
            break
    if best is None:
        raise DegenerateProjection("no generic projection found")
    return best
