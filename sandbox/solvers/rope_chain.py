"""Exact inextensibility of rope chains by a tridiagonal Newton step.

The rods of one rope (paper Eq. 2) couple only neighbours, so the linearised
projection ``(J W J^T) dlam = -C`` is tridiagonal and is solved exactly by
the Thomas algorithm in O(k) for a rope of k particles (the Fast Projection
of Goldenthal et al. 2007 that the paper builds on, restricted to a chain).
Ropes run in parallel, each one serially. One step removes the strain to
first order; repeated per solver iteration it leaves strain at round-off
level except where contacts push against it.
"""

import numpy as np
import taichi as ti


@ti.data_oriented
class RopeInextensibility:
    """Chain projection of every inextensible rope.

    Fields (R ropes, s segments):
        seg_lo, seg_hi: (R,) i32, segment range of each rope.
        seg_rest: (s,) f32, m, rod rest lengths.
        nrm: (s,) vec3 f32, unit rod directions at the linearisation.
        cp, dp: (s,) f32, Thomas algorithm scratch.
    """

    def __init__(self, model, state, w) -> None:
        d = model.data
        self.model = model
        self.st = state
        self.w = w
        lo, hi = [], []
        s = 0
        for r in d.ropes:
            k = r.end - r.start
            if r.stretch_compliance == 0.0:
                lo.append(s)
                hi.append(s + k - 1)
            s += k - 1
        self.n_ropes = len(lo)
        self.s = s
        self.seg_lo = ti.field(ti.i32, shape=self.n_ropes)
        self.seg_hi = ti.field(ti.i32, shape=self.n_ropes)
        self.seg_lo.from_numpy(np.asarray(lo, np.int32))
        self.seg_hi.from_numpy(np.asarray(hi, np.int32))
        segs = d.segments
        rest = np.linalg.norm(d.x0[segs[:, 1]] - d.x0[segs[:, 0]], axis=1)
        self.seg_rest = ti.field(ti.f32, shape=s)
        self.seg_rest.from_numpy(rest.astype(np.float32))
        self.nrm = ti.Vector.field(3, ti.f32, shape=s)
        self.cp = ti.field(ti.f32, shape=s)
        self.dp = ti.field(ti.f32, shape=s)

    @ti.func
    def solve_f(self):
        """One Newton step of all rods of all ropes (exact for the linearisation)."""
        x = ti.static(self.st.x)
        seg = ti.static(self.model.segment)
        for r in range(self.n_ropes):
            lo = self.seg_lo[r]
            hi = self.seg_hi[r]
            # Forward sweep: build rows on the fly, eliminate the sub-diagonal.
            for j in range(lo, hi):
                a = seg[j][0]
                b = seg[j][1]
                dv = x[b] - x[a]
                length = dv.norm()
                n = ti.math.vec3(0.0)
                if length > 1e-12:
                    n = dv / length
                self.nrm[j] = n
                diag = self.w[a] + self.w[b]
                rhs = -(length - self.seg_rest[j])
                sub = 0.0  # A[j, j-1] = -w_a n_{j-1} . n_j
                if j > lo:
                    sub = -self.w[a] * self.nrm[j - 1].dot(n)
                if diag <= 1e-12:  # both ends immovable: the row is inert
                    diag = 1.0
                    rhs = 0.0
                    sub = 0.0
                denom = diag
                if j > lo:
                    denom = diag - sub * self.cp[j - 1]
                    rhs = rhs - sub * self.dp[j - 1]
                sup = 0.0  # A[j, j+1] = -w_b n_j . n_{j+1}, n_{j+1} from current x
                if j + 1 < hi:
                    c = seg[j + 1][1]
                    dn = x[c] - x[b]
                    ln = dn.norm()
                    if ln > 1e-12 and self.w[a] + self.w[b] > 1e-12:
                        sup = -self.w[b] * n.dot(dn / ln)
                self.cp[j] = sup / denom
                self.dp[j] = rhs / denom
            # Back substitution: dp becomes the multipliers.
            for jj in range(lo, hi):
                j = hi - 1 - (jj - lo)
                if j + 1 < hi:
                    self.dp[j] = self.dp[j] - self.cp[j] * self.dp[j + 1]
            # Scatter: dx_a -= w_a lam n, dx_b += w_b lam n (serial within the rope).
            for j in range(lo, hi):
                a = seg[j][0]
                b = seg[j][1]
                lam = self.dp[j]
                x[a] = x[a] - self.w[a] * lam * self.nrm[j]
                x[b] = x[b] + self.w[b] * lam * self.nrm[j]
