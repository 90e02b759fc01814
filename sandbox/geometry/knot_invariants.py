"""Knot diagrams and their invariants: Reidemeister simplification, Alexander
polynomial, determinant, signature and Jones polynomial.

A diagram of a knot is held as a *signed Gauss code*: the crossings met in
order along the knot, each as ``(crossing id, over)``, plus the sign of every
crossing. Conventions:

- A crossing is positive (right-handed) when, with both strands pointing up,
  the over strand runs from lower left to upper right. The right-handed
  trefoil has three positive crossings.
- PD code (Knot Atlas style): ``X[a, b, c, d]`` lists the four edges at a
  crossing counter-clockwise, starting with the incoming under edge ``a``; on
  a positive crossing the over strand runs from ``d`` to ``b``, on a negative
  one from ``b`` to ``d``. Edge ``k`` runs from Gauss passage ``k`` to ``k+1``.
- Alexander polynomial: coefficients from the lowest power, normalised so
  that Delta(1) = +1 (Delta is symmetric, so chirality does not show).
- Signature: the right-handed trefoil has signature -2 (positive knots have
  negative signature), computed from the Goeritz matrix with the
  Gordon-Litherland correction.
- Jones polynomial: V(right-handed trefoil) = t + t^3 - t^4, from the Kauffman
  bracket (A-smoothing of ``X[a, b, c, d]`` joins a-b and c-d) with
  V(t) = (-A^3)^(-writhe) <D> at A = t^(-1/4); returned as
  ``((power, coefficient), ...)``.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

__all__ = [
    "GaussCode",
    "alexander_polynomial",
    "determinant",
    "faces",
    "gauss_to_pd",
    "jones_polynomial",
    "signature",
    "simplify",
]

GaussCode = tuple[list[tuple[int, bool]], dict[int, int]]
"""``(passages, signs)``: passages ``(crossing id, over)`` in order, and crossing signs (+-1)."""


# -- PD code and faces ------------------------------------------------------------------------


def gauss_to_pd(code: list[tuple[int, bool]], signs: dict[int, int]) -> dict[int, tuple[int, ...]]:
    """PD code ``{crossing id: (a, b, c, d)}`` of a signed Gauss code (edge k: passage k -> k+1)."""
    m = len(code)
    under: dict[int, int] = {}
    over: dict[int, int] = {}
    for k, (cid, is_over) in enumerate(code):
        (over if is_over else under)[cid] = k
    pd = {}
    for cid, p in under.items():
        q = over[cid]
        a, c = (p - 1) % m, p
        if signs[cid] > 0:
            pd[cid] = (a, q, c, (q - 1) % m)
        else:
            pd[cid] = (a, (q - 1) % m, c, q)
    return pd


def _slots(pd: dict[int, tuple[int, ...]]) -> dict[int, list[tuple[int, int]]]:
    """For each edge, the two (crossing, position) slots where it ends."""
    ends: dict[int, list[tuple[int, int]]] = defaultdict(list)
    for cid, x in pd.items():
        for pos, e in enumerate(x):
            ends[e].append((cid, pos))
    return ends


def faces(pd: dict[int, tuple[int, ...]]) -> list[list[tuple[int, int]]]:
    """Faces of the diagram on the sphere, each a list of corners ``(crossing, k)``.

    Corner k of a crossing lies between positions k and k+1 (counter-clockwise).
    From corner (X, k) the face follows the edge at position k+1 to its other end
    (Y, m) and continues with corner (Y, m).
    """
    ends = _slots(pd)
    nxt = {}
    for cid, x in pd.items():
        for k in range(4):
            slot = (cid, (k + 1) % 4)
            a, b = ends[x[(k + 1) % 4]]
            nxt[(cid, k)] = b if a == slot else a
    seen: set[tuple[int, int]] = set()
    out = []
    for start in nxt:
        if start in seen:
            continue
        face, c = [], start
        while c not in seen:
            seen.add(c)
            face.append(c)
            c = nxt[c]
        out.append(face)
    return out


def _colour(pd: dict[int, tuple[int, ...]], fcs: list[list[tuple[int, int]]]) -> list[int]:
    """Checkerboard colours (0/1) of the faces: faces across an edge differ."""
    face_of = {corner: i for i, f in enumerate(fcs) for corner in f}
    adj: dict[int, set[int]] = defaultdict(set)
    for cid in pd:
        for k in range(4):
            i, j = face_of[(cid, k)], face_of[(cid, (k + 1) % 4)]
            adj[i].add(j)
            adj[j].add(i)
    colour = [-1] * len(fcs)
    colour[0] = 0
    stack = [0]
    while stack:
        i = stack.pop()
        for j in adj[i]:
            if colour[j] < 0:
                colour[j] = 1 - colour[i]
                stack.append(j)
            elif colour[j] == colour[i]:
                raise ValueError("diagram is not checkerboard-colourable (invalid Gauss code)")
    return colour


# -- Reidemeister I / II ----------------------------------------------------------------------


def _drop(code: list[tuple[int, bool]], ids: set[int]) -> list[tuple[int, bool]]:
    return [p for p in code if p[0] not in ids]


def _r1(code: list[tuple[int, bool]]) -> set[int] | None:
    """A kink: a crossing whose two passages are adjacent along the knot."""
    m = len(code)
    for k in range(m):
        if code[k][0] == code[(k + 1) % m][0]:
            return {code[k][0]}
    return None


def _r2(code: list[tuple[int, bool]], signs: dict[int, int]) -> set[int] | None:
    """A bigon face whose one edge passes over both of its crossings."""
    pd = gauss_to_pd(code, signs)
    m = len(code)
    for f in faces(pd):
        if len(f) != 2 or f[0][0] == f[1][0]:
            continue
        # Edges of the bigon, found as passage indices: edge k joins passages k, k+1.
        (x, kx), (y, ky) = f
        e1 = pd[x][(kx + 1) % 4]
        e2 = pd[y][(ky + 1) % 4]
        if code[e1][1] == code[(e1 + 1) % m][1] and code[e2][1] == code[(e2 + 1) % m][1]:
            if code[e1][1] != code[e2][1]:
                return {x, y}
    return None


def simplify(code: list[tuple[int, bool]], signs: dict[int, int]) -> GaussCode:
    """Remove crossings by Reidemeister I and II moves until none applies.

    Args:
        code: passages ``(crossing id, over)`` in order along the knot.
        signs: crossing id -> +1 / -1.

    Returns:
        The simplified ``(code, signs)``; the knot type is unchanged.
    """
    code = list(code)
    while code:
        ids = _r1(code)
        if ids is None:
            ids = _r2(code, signs)
        if ids is None:
            break
        code = _drop(code, ids)
    signs = {c: signs[c] for c, _ in code}
    return code, signs


# -- Alexander polynomial ---------------------------------------------------------------------

_EXACT_MAX = 60
"""Largest diagram (crossings) for the exact-arithmetic Alexander fallback."""


def _poly_from_values(vals: np.ndarray) -> np.ndarray | None:
    """Integer coefficients of a polynomial from its values at the N-th roots of unity."""
    coef = np.fft.fft(vals) / len(vals)  # vals[k] = P(w^k), w = exp(2 pi i / N)
    rounded = np.rint(coef.real)
    if np.max(np.abs(coef - rounded)) > 1e-6:
        return None
    return rounded.astype(np.int64)


def _alexander_exact(mat_rows: list[dict[int, tuple[int, int]]], n: int) -> list[int]:
    """Exact determinant of the reduced Alexander matrix (fraction-free, Python ints).

    Entries are polynomials c0 + c1 t stored as (c0, c1); the determinant is
    found exactly at the integers t = 2..n+2 (Bareiss elimination) and interpolated.
    """
    from fractions import Fraction

    pts = list(range(2, n + 3))
    vals = []
    for t in pts:
        a = [[0] * (n - 1) for _ in range(n - 1)]
        for i in range(n - 1):
            for j, (c0, c1) in mat_rows[i].items():
                if j < n - 1:
                    a[i][j] = c0 + c1 * t
        vals.append(_bareiss(a))
    # Newton interpolation with exact fractions.
    coef = [Fraction(v) for v in vals]
    m = len(pts)
    for j in range(1, m):
        for i in range(m - 1, j - 1, -1):
            coef[i] = (coef[i] - coef[i - 1]) / (pts[i] - pts[i - j])
    poly = [Fraction(0)] * m
    for i in range(m - 1, -1, -1):
        # poly = poly * (t - pts[i]) + coef[i]
        new = [Fraction(0)] * m
        for k in range(m - 1):
            new[k + 1] += poly[k]
            new[k] -= pts[i] * poly[k]
        new[0] += coef[i]
        poly = new
    return [int(c) for c in poly]


def _bareiss(a: list[list[int]]) -> int:
    """Determinant of an integer matrix by fraction-free Gaussian elimination."""
    n = len(a)
    if n == 0:
        return 1
    a = [row[:] for row in a]
    sign, prev = 1, 1
    for k in range(n - 1):
        if a[k][k] == 0:
            for i in range(k + 1, n):
                if a[i][k] != 0:
                    a[k], a[i] = a[i], a[k]
                    sign = -sign
                    break
            else:
                return 0
        for i in range(k + 1, n):
            for j in range(k + 1, n):
                a[i][j] = (a[i][j] * a[k][k] - a[i][k] * a[k][j]) // prev
        prev = a[k][k]
    return sign * a[n - 1][n - 1]


def alexander_polynomial(code: list[tuple[int, bool]], signs: dict[int, int]) -> tuple[int, ...]:
    """Alexander polynomial of a diagram, normalised (lowest power first, Delta(1) = 1).

    Rows are the Fox derivatives of the Wirtinger relations, one per crossing:
    over arc k, incoming under arc i, outgoing under arc j give (1 - t) at k,
    t at i and -1 at j (positive crossing) or -1 at i and t at j (negative).
    The determinant of the matrix without its last row and column is Delta up
    to +-t^m; it is evaluated at roots of unity and recovered by an FFT. If
    the result is not integral to 1e-6, it is recomputed exactly (up to
    ``_EXACT_MAX`` crossings; beyond, the rounded values are kept).
    """
    n = len(code) // 2
    if n <= 1:
        return (1,)
    under = [k for k, (_, o) in enumerate(code) if not o]
    is_under = np.zeros(len(code), dtype=bool)
    is_under[under] = True
    arc = (np.cumsum(is_under) % n).tolist()  # arc of edge k (passage k -> k+1)
    m = len(code)
    ids = sorted(signs)
    row_of = {c: r for r, c in enumerate(ids)}
    rows: list[dict[int, tuple[int, int]]] = [defaultdict(lambda: (0, 0)) for _ in ids]

    def add(r: int, j: int, c0: int, c1: int) -> None:
        a0, a1 = rows[r][j]
        rows[r][j] = (a0 + c0, a1 + c1)

    over_arc = {c: arc[k] for k, (c, o) in enumerate(code) if o}
    for k, (c, o) in enumerate(code):
        if o:
            continue
        r = row_of[c]
        i, j = arc[(k - 1) % m], arc[k]
        add(r, over_arc[c], 1, -1)
        if signs[c] > 0:
            add(r, i, 0, 1)
            add(r, j, -1, 0)
        else:
            add(r, i, -1, 0)
            add(r, j, 0, 1)
    # Degree <= n - 1: n values at the n-th roots of unity determine it; the
    # coefficients are real, so the upper half of the values are conjugates.
    size = n
    half = size // 2 + 1
    w = np.exp(2j * np.pi * np.arange(half) / size)
    mats = np.zeros((half, n - 1, n - 1), dtype=complex)
    for r in range(n - 1):
        for j, (c0, c1) in rows[r].items():
            if j < n - 1:
                mats[:, r, j] = c0 + c1 * w
    low = np.linalg.det(mats)
    vals = np.concatenate([low, np.conj(low[1 : size - half + 1][::-1])])
    coef = _poly_from_values(vals)
    if coef is not None:
        poly = coef.tolist()
    elif n <= _EXACT_MAX:
        poly = _alexander_exact(rows, n)
    else:  # Too large for exact arithmetic here: keep the rounded values.
        poly = np.rint((np.fft.fft(vals) / size).real).astype(np.int64).tolist()
    return _normalise_alexander(poly)


def _normalise_alexander(poly: list[int]) -> tuple[int, ...]:
    """Strip zero ends and fix the sign so that Delta(1) = +1."""
    nz = [i for i, c in enumerate(poly) if c != 0]
    if not nz:
        return (0,)
    p = poly[nz[0] : nz[-1] + 1]
    if sum(p) < 0:
        p = [-c for c in p]
    return tuple(int(c) for c in p)


def determinant(alexander: tuple[int, ...]) -> int:
    """Knot determinant |Delta(-1)|."""
    return abs(sum(c * (-1) ** i for i, c in enumerate(alexander)))


# -- signature ---------------------------------------------------------------------------------


def signature(code: list[tuple[int, bool]], signs: dict[int, int], *, colour: int = 0) -> int:
    """Knot signature from the Goeritz matrix and the Gordon-Litherland correction.

    With the faces checkerboard-coloured, the surface F spanned by the faces of
    the other colour has Goeritz form G over the faces of colour ``colour``:
    G_ij = -sum eta(c) over crossings where faces i != j meet, G_ii = -sum_j G_ij,
    one face dropped. Then sigma = sign(G) - mu, mu = sum of eta(c) over the
    crossings of type II (where the colour-``colour`` corners sit between an
    incoming and an outgoing strand). eta(c) = -1 when turning the over strand
    counter-clockwise sweeps the colour-``colour`` corners, else +1 (this sets
    the sign convention: sigma(right-handed trefoil) = -2). Both colours give
    the same value (a check used by the tests).

    Args:
        code, signs: the signed Gauss code.
        colour: which checkerboard colour spans the Goeritz form (0 or 1).
    """
    if not code:
        return 0
    pd = gauss_to_pd(code, signs)
    fcs = faces(pd)
    col = _colour(pd, fcs)
    face_of = {corner: i for i, f in enumerate(fcs) for corner in f}
    white = [i for i, c in enumerate(col) if c == colour]
    index = {f: k for k, f in enumerate(white)}
    g = np.zeros((len(white), len(white)))
    mu = 0
    for cid in pd:
        # Turning the over strand (positions 1, 3) counter-clockwise sweeps corners 1 and 3.
        f1, f3 = face_of[(cid, 1)], face_of[(cid, 3)]
        if col[f1] == colour:
            eta, wa, wb, white_pair = -1, f1, f3, {1, 3}
        else:
            eta, wa, wb, white_pair = 1, face_of[(cid, 0)], face_of[(cid, 2)], {0, 2}
        # Corners between the two incoming (or two outgoing) strands:
        # 3 and 1 on a positive crossing, 0 and 2 on a negative one.
        through_pair = {1, 3} if signs[cid] > 0 else {0, 2}
        if white_pair != through_pair:
            mu += eta
        if wa != wb:
            i, j = index[wa], index[wb]
            g[i, j] -= eta
            g[j, i] -= eta
    np.fill_diagonal(g, 0.0)
    np.fill_diagonal(g, -g.sum(axis=1))
    g = g[1:, 1:]
    if g.size == 0:
        sig = 0
    else:
        ev = np.linalg.eigvalsh(g)
        tol = 1e-9 * max(1.0, float(np.abs(ev).max()))
        sig = int(np.sum(ev > tol) - np.sum(ev < -tol))
    return sig - mu


# -- Jones polynomial (Kauffman bracket) ---------------------------------------------------------


def _poly_mul(p: dict[int, int], q: dict[int, int]) -> dict[int, int]:
    """Product of two Laurent polynomials ``{power: coefficient}``."""
    out: dict[int, int] = defaultdict(int)
    for a, x in p.items():
        for b, y in q.items():
            out[a + b] += x * y
    return {k: v for k, v in out.items() if v}


def _crossing_order(pd: dict[int, tuple[int, ...]]) -> list[int]:
    """Crossings ordered so that each shares as many edges as possible with those before."""
    ends = _slots(pd)
    order: list[int] = []
    done: set[int] = set()
    frontier: dict[int, int] = defaultdict(int)
    remaining = set(pd)
    while remaining:
        c = max(remaining, key=lambda x: (frontier[x], -x)) if order else min(remaining)
        order.append(c)
        done.add(c)
        remaining.discard(c)
        for e in pd[c]:
            for other, _ in ends[e]:
                if other not in done:
                    frontier[other] += 1
    return order


def jones_polynomial(
    code: list[tuple[int, bool]], signs: dict[int, int], *, max_states: int = 4000
) -> tuple[tuple[int, int], ...] | None:
    """Jones polynomial V(t) as ``((power, coefficient), ...)``, or None if too large.

    The Kauffman bracket is contracted crossing by crossing: each partial state
    is the pairing of the open edges (as a planar tangle) with a Laurent
    polynomial in A, so the cost grows with the width of the diagram rather
    than 2^n. ``max_states`` bounds the number of live partial states.
    """
    if not code:
        return ((0, 1),)
    pd = gauss_to_pd(code, signs)
    d_loop = {2: -1, -2: -1}  # d = -A^2 - A^-2
    states: dict[tuple[tuple[int, int], ...], dict[int, int]] = {(): {0: 1}}
    for cid in _crossing_order(pd):
        a, b, c, d = pd[cid]
        new: dict[tuple[tuple[int, int], ...], dict[int, int]] = defaultdict(dict)
        for key, poly in states.items():
            match = dict(key)
            match.update((v, u) for u, v in key)
            for power, pairs in ((1, ((a, b), (c, d))), (-1, ((a, d), (b, c)))):
                mm = dict(match)
                loops = 0
                for u, v in pairs:
                    loops += _join(mm, u, v)
                p = {k + power: x for k, x in poly.items()}
                for _ in range(loops):
                    p = _poly_mul(p, d_loop)
                k2 = tuple(sorted((u, v) for u, v in mm.items() if u < v))
                acc = new[k2]
                for e, x in p.items():
                    acc[e] = acc.get(e, 0) + x
        states = {k: {e: x for e, x in v.items() if x} for k, v in new.items()}
        if len(states) > max_states:
            return None
    bracket = states.get((), {})
    # All loops were closed; divide by d once (the unknot has bracket 1).
    bracket = _poly_div_d(bracket)
    w = sum(signs.values())
    # (-A^3)^(-w)
    factor = {-3 * w: (-1) ** (w % 2)}
    v_a = _poly_mul(bracket, factor)
    out = []
    for e, x in sorted(v_a.items()):
        if e % 4:
            raise ValueError("Jones polynomial of a knot must have integer powers of t")
        out.append((-e // 4, x))
    return tuple(sorted(out))


def _join(match: dict[int, int], u: int, v: int) -> int:
    """Join open edge ends u and v in a pairing; return 1 if a loop closed, else 0."""
    if u == v:  # An edge whose two ends meet at the same smoothing closes on itself.
        if u in match:
            raise ValueError("edge seen three times")
        return 1
    mu, mv = u in match, v in match
    if not mu and not mv:
        match[u], match[v] = v, u
        return 0
    if mu and not mv:
        w = match.pop(u)
        match[w], match[v] = v, w
        return 0
    if mv and not mu:
        w = match.pop(v)
        match[w], match[u] = u, w
        return 0
    if match[u] == v:
        del match[u], match[v]
        return 1
    w, z = match.pop(u), match.pop(v)
    match[w], match[z] = z, w
    return 0


def _poly_div_d(p: dict[int, int]) -> dict[int, int]:
    """Exact division of a Laurent polynomial in A by d = -A^2 - A^-2."""
    p = dict(p)
    out: dict[int, int] = {}
    while p:
        top = max(p)
        q = -p[top]  # leading term of d is -A^2
        out[top - 2] = q
        for e, x in ((top, q), (top - 4, q)):
            p[e] = p.get(e, 0) + x
            if p[e] == 0:
                del p[e]
        if p and max(p) > top:
            raise ValueError("bracket not divisible by d")
        if len(out) > 10_000:
            raise ValueError("bracket not divisible by d")
    return out
