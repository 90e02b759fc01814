"""Exact inextensibility of chains of rods by a tridiagonal Newton step.

A chain is a sequence of particles joined by rods: a rope (paper Eq. 2), or
one row or one column of a cloth grid's structural edges. The rods of a
chain couple only neighbours, so the linearised projection
``(J W J^T) dlam = -C`` is tridiagonal and is solved exactly by the Thomas
algorithm in O(k) for a chain of k particles: the Fast Projection of
Goldenthal et al. 2007 (which the paper builds on) restricted to a chain.
Tension then crosses a whole rope or cloth row in one pass instead of one
rod per Gauss-Seidel sweep, which is what keeps hanging ropes and cloth
within a fraction of a percent of their length.

Particles that touched the ground or an object in this substep may not move
along their contact normal: their inverse mass becomes w (I - n n^T). The
chain then slides over a surface instead of being pulled through it and
pushed back out, which would otherwise lock a chain draped over a sharp edge
in a stretched state. The system stays tridiagonal and scalar. Contact is
one-sided: a particle whose chain neighbour is already off the surface
(more than 30% of a rod above it along the normal) may follow it, so a
lifted control line peels the cloth off the ground (``_peel``) instead of
meeting a rod that no motion of its free end can shorten. Only cloth chains
peel; ropes keep the two-sided restriction their knots were tuned with,
except for a rod the restriction would all but lock (``_unpin_blocked``).
A rope chain's step that would throw a particle and leave the chain further
off than it was is scaled back (``_step_scale``).

Chains are grouped so that no two chains of a group share a particle (ropes
and cloth rows in one group, cloth columns in another); the chains of a
group run in parallel, each one serially, and the groups run one after the
other.
"""

import numpy as np
import taichi as ti

from sandbox import runtime

# A stretch of chain held at both ends closer than this fraction to its full
# reach is laid straight (see ChainProjection._overreach).
SLACK = 1e-4
# A rope rod whose ends can move along it by less than this fraction of
# their free inverse mass under the contact restriction is solved with its
# particles free of their contacts (ChainProjection._unpin_blocked).
BLOCKED = 1e-3
# A chain step that moves a particle by more than this many rods and leaves
# a rod further off than before is scaled back (ChainProjection._step_scale).
THROW = 0.5
# A particle of a rope between two held particles gives way outwards to a
# contact less once the stretch through it is drawn this close to taut (its
# distances to the two holds add up to this fraction of the rods between
# them), not at all when taut (ChainProjection.taut_f).
TAUT = 0.999


def cloth_rows_and_columns(data) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Particle indices of every row and every column of the inextensible cloths."""
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    for c in data.cloths:
        if c.stretch_compliance == 0.0:
            for j in range(c.nz):
                rows.append(c.start + j * c.nx + np.arange(c.nx))
            for i in range(c.nx):
                cols.append(c.start + np.arange(c.nz) * c.nx + i)
    return rows, cols


def build_chains(data) -> list[list[np.ndarray]]:
    """Chain groups of a model: [ropes + cloth rows, cloth columns].

    Only inextensible bodies (stretch compliance 0) get chains.
    """
    rows = [np.arange(r.start, r.end) for r in data.ropes if r.stretch_compliance == 0.0 and r.end - r.start >= 2]
    cloth_rows, cols = cloth_rows_and_columns(data)
    return [g for g in (rows + cloth_rows, cols) if g]


def has_rope_chains(data) -> bool:
    """Whether a scene has an inextensible rope of at least two rods (a chain the chain step solves)."""
    return any(r.stretch_compliance == 0.0 and r.end - r.start >= 2 for r in data.ropes)


@ti.data_oriented
class ChainProjection:
    """Tridiagonal projection of every inextensible chain.

    Fields (L links in all chains, C chains):
        link_a, link_b: (L,) i32, the two particles of each rod; the links of
            a chain are consecutive and share particles (b of one is a of next).
        rest: (L,) f32, m.
        lo, hi: (C,) i32, link range of each chain.
        nrm: (L,) vec3 f32, unit rod directions at the linearisation.
        res: (L,) f32, m, -(length - rest) at the linearisation.
        cp, dp: (L,) f32, Thomas algorithm scratch.
    """

    def __init__(self, model, state, w, groups: list[list[np.ndarray]], contacts=None) -> None:
        self.model = model
        self.st = state
        self.w = w
        self.has_contacts = contacts is not None  # a ``collision.contacts.Contacts``, or None where nothing touches
        self.contact = contacts.hit if contacts is not None else None  # > 0 where the particle touched a surface
        self.normal = contacts.normal if contacts is not None else None  # the direction it was pushed
        x0 = model.data.x0
        a, b, lo, hi = [], [], [], []
        self.group_ranges = []
        self.link_ranges = []  # [first, last) link of each group (chains of a group are consecutive)
        n_links = 0
        for group in groups:
            g0 = len(lo)
            for chain in group:
                lo.append(n_links)
                a.append(chain[:-1])
                b.append(chain[1:])
                n_links += len(chain) - 1
                hi.append(n_links)
            self.group_ranges.append((g0, len(lo)))
            self.link_ranges.append((lo[g0] if len(lo) > g0 else n_links, n_links))
        a = np.concatenate(a).astype(np.int32)
        b = np.concatenate(b).astype(np.int32)
        self.n_links = n_links
        self.link_a = ti.field(ti.i32, shape=n_links)
        self.link_b = ti.field(ti.i32, shape=n_links)
        self.rest = ti.field(ti.f32, shape=n_links)
        runtime.defer(self.link_a.from_numpy, a)
        runtime.defer(self.link_b.from_numpy, b)
        runtime.defer(self.rest.from_numpy, np.linalg.norm(x0[b] - x0[a], axis=1).astype(np.float32))
        self.lo = ti.field(ti.i32, shape=len(lo))
        self.hi = ti.field(ti.i32, shape=len(hi))
        runtime.defer(self.lo.from_numpy, np.asarray(lo, np.int32))
        runtime.defer(self.hi.from_numpy, np.asarray(hi, np.int32))
        self.nrm = ti.Vector.field(3, ti.f32, shape=n_links)
        self.peeled = ti.field(ti.i32, shape=model.n) if self.has_contacts else None
        self.cloth_start = min((c.start for c in model.data.cloths), default=model.n)
        # Rope chains get the guards against near-singular steps (_unpin_blocked,
        # _step_scale); a scene without ropes compiles none of them.
        self.has_ropes = has_rope_chains(model.data)
        self.res = ti.field(ti.f32, shape=n_links)  # -(length - rest) at the linearisation
        self.cp = ti.field(ti.f32, shape=n_links)
        self.dp = ti.field(ti.f32, shape=n_links)

    @ti.func
    def _wdot(self, i, u, v):
        """u^T W_i v with W_i = w_i (I - n n^T) for a particle in contact."""
        r = self.w[i] * u.dot(v)
        if ti.static(self.has_contacts):
            if self.contact[i] > 0.0 and self.peeled[i] == 0:
                n = self.normal[i]
                r = self.w[i] * (u.dot(v) - u.dot(n) * v.dot(n))
        return r

    @ti.func
    def _wapply(self, i, u):
        """W_i u."""
        r = self.w[i] * u
        if ti.static(self.has_contacts):
            if self.contact[i] > 0.0 and self.peeled[i] == 0:
                n = self.normal[i]
                r = self.w[i] * (u - u.dot(n) * n)
        return r

    @ti.func
    def _linearise(self, l0, l1):
        """Rod directions and length residuals of links [l0, l1), all in parallel."""
        x = ti.static(self.st.x)
        for j in range(l0, l1):
            dv = x[self.link_b[j]] - x[self.link_a[j]]
            length = dv.norm()
            n = ti.math.vec3(0.0)
            if length > 1e-12:
                n = dv / length
            self.nrm[j] = n
            self.res[j] = -(length - self.rest[j])

    @ti.func
    def _overreach(self, lo, hi):
        """Lay straight the stretches between two held particles that are farther apart than their rods reach.

        Between two consecutive held particles (w = 0) a stretch of chain of
        total rest length L can only span a distance D <= L. When D > (1 -
        SLACK) L the linearised step is all but singular (the rods are all but
        collinear and their lengths along the line must add up to D): it would
        dump the excess on one rod or throw particles sideways. Such a stretch
        is laid on the straight line instead, each rod stretched by D / L, and
        its rows take no part in the step (zero residual; held particles at
        both ends decouple them from the rest of the chain). O(k) for a chain
        of k links.
        """
        x = ti.static(self.st.x)
        seg = -1  # first link after the last held particle; -1 before the first one
        reach = 0.0
        for j in range(lo, hi):
            a = self.link_a[j]
            b = self.link_b[j]
            if self.w[a] == 0.0:
                seg = j
                reach = 0.0
            reach += self.rest[j]
            if seg >= 0 and self.w[b] == 0.0:
                p = x[self.link_a[seg]]
                line = x[b] - p
                span = line.norm()
                if span > (1.0 - ti.static(SLACK)) * reach:
                    along = 0.0
                    for k in range(seg, j + 1):
                        along += self.rest[k]
                        if k < j:
                            x[self.link_b[k]] = p + (along / reach) * line
                        self.nrm[k] = line / span
                        self.res[k] = 0.0

    @ti.func
    def _chain(self, c, tol: ti.template()):
        """Solve one linearised chain: forward-eliminate, back-substitute, scatter.

        With ``tol`` > 0 the chain is linearised here (the sweep skips the
        parallel pass) and only if one of its rods is off its length by more
        than ``tol`` (relative; for cloth: stretched by more); otherwise it
        is left as it is.
        """
        lo = self.lo[c]
        hi = self.hi[c]
        active = True
        if ti.static(tol > 0.0):
            # A rope's rods count both ways; a cloth's only when stretched
            # (compressed edges are folds, and the first sweep saw to them).
            x = ti.static(self.st.x)
            cloth = self.link_a[lo] >= ti.static(self.cloth_start)
            worst = 0.0
            for j in range(lo, hi):
                off = (x[self.link_b[j]] - x[self.link_a[j]]).norm() / self.rest[j] - 1.0
                if not cloth:
                    off = ti.abs(off)
                worst = ti.max(worst, off)
            active = worst > tol
            if active:
                self._linearise(lo, hi)  # serial here: inside the loop over chains
        if active:
            self._overreach(lo, hi)
            self._solve_linear(lo, hi)

    @ti.func
    def _unpin_blocked(self, lo, hi, on: ti.template()):
        """Let a rope particle leave its contact where a rod of its chain could not change length otherwise.

        A rod from a held particle (or one that may only slide) to a particle
        whose contact normal lies all but along the rod has a pivot near
        zero: solved under the contact restriction, its residual would
        throw the particle sideways by centimetres. Such a rod's particles
        are solved free of their contact this step (the contacts pass then
        puts them back on the surface). ``on`` sets the flags, off clears
        them. Cloth chains keep their peel flags.
        """
        if ti.static(self.has_contacts and self.has_ropes):
            if self.link_a[lo] < ti.static(self.cloth_start):
                for j in range(lo, hi):
                    a = self.link_a[j]
                    b = self.link_b[j]
                    if ti.static(on):
                        n = self.nrm[j]
                        if self._wdot(a, n, n) + self._wdot(b, n, n) <= ti.static(BLOCKED) * (self.w[a] + self.w[b]):
                            self.peeled[a] = 1
                            self.peeled[b] = 1
                    else:
                        self.peeled[a] = 0
                        self.peeled[b] = 0

    @ti.func
    def _solve_linear(self, lo, hi):
        """Thomas algorithm on links [lo, hi) of one chain, then the scatter."""
        x = ti.static(self.st.x)
        self._unpin_blocked(lo, hi, True)
        for j in range(lo, hi):
            a = self.link_a[j]
            b = self.link_b[j]
            n = self.nrm[j]
            # A small relative regulariser keeps a taut chain between two pins
            # (all rods collinear: one redundant constraint) from a zero pivot.
            diag = self._wdot(a, n, n) + self._wdot(b, n, n) + 1e-6 * (self.w[a] + self.w[b])
            rhs = self.res[j]
            sub = 0.0  # A[j, j-1] = -n_{j-1}^T W_a n_j
            if j > lo:
                sub = -self._wdot(a, self.nrm[j - 1], n)
            inert = diag <= 1e-9 * (self.w[a] + self.w[b] + 1e-30)
            if inert:  # both ends immovable along the rod: the row is inert
                diag = 1.0
                rhs = 0.0
                sub = 0.0
            if j > lo:
                diag = diag - sub * self.cp[j - 1]
                rhs = rhs - sub * self.dp[j - 1]
            sup = 0.0  # A[j, j+1] = -n_j^T W_b n_{j+1}
            if j + 1 < hi and not inert:
                sup = -self._wdot(b, n, self.nrm[j + 1])
            self.cp[j] = sup / diag
            self.dp[j] = rhs / diag
        for jj in range(lo, hi):
            j = hi - 1 - (jj - lo)
            if j + 1 < hi:
                self.dp[j] = self.dp[j] - self.cp[j] * self.dp[j + 1]
        s = self._step_scale(lo, hi)
        for j in range(lo, hi):  # scatter in chain order (the order fixes the float sums)
            a = self.link_a[j]
            b = self.link_b[j]
            lam = s * self.dp[j]
            x[a] = x[a] - lam * self._wapply(a, self.nrm[j])
            x[b] = x[b] + lam * self._wapply(b, self.nrm[j])
        self._unpin_blocked(lo, hi, False)

    @ti.func
    def _step_scale(self, lo, hi) -> ti.f32:
        """1, or less for a step that would throw particles and leave the chain further off than before.

        The linearised system can be all but singular in a way no single row
        shows (a fold of rope whose particles touch a surface and may only
        slide on it): a residual of a fraction of a millimetre then comes
        back as a step of centimetres. A step that moves some particle by
        more than ``THROW`` of a rod and leaves a rod further off its rest
        length than the chain's worst rod was is halved, up to three times,
        then not taken (the Gauss-Seidel passes still see to the rods). Any
        other step is applied unchanged. O(k) per try. Rope chains only:
        cloth chains keep every step.
        """
        s = 1.0
        if ti.static(self.has_ropes):
            if self.link_a[lo] < ti.static(self.cloth_start):
                s = self._rope_step_scale(lo, hi)
        return s

    @ti.func
    def _rope_step_scale(self, lo, hi) -> ti.f32:
        x = ti.static(self.st.x)
        before = 0.0
        for j in range(lo, hi):
            before = ti.max(before, ti.abs(self.res[j]) / self.rest[j])
        s = 1.0
        done = False
        for _ in range(4):
            if not done:
                worst = 0.0
                move = 0.0
                for j in range(lo, hi):
                    a = self.link_a[j]
                    b = self.link_b[j]
                    da = -s * self.dp[j] * self._wapply(a, self.nrm[j])
                    db = s * self.dp[j] * self._wapply(b, self.nrm[j])
                    if j > lo:
                        da += s * self.dp[j - 1] * self._wapply(a, self.nrm[j - 1])
                    if j + 1 < hi:
                        db -= s * self.dp[j + 1] * self._wapply(b, self.nrm[j + 1])
                    length = (x[b] + db - x[a] - da).norm()
                    worst = ti.max(worst, ti.abs(length - self.rest[j]) / self.rest[j])
                    move = ti.max(move, ti.max(da.norm(), db.norm()) / self.rest[j])
                if worst <= before or move <= ti.static(THROW):
                    done = True
                else:
                    s *= 0.5
        if not done:
            s = 0.0
        return s

    @ti.func
    def taut_f(self, taut: ti.template(), taut_n: ti.template(), room: ti.template()):
        """Where a held stretch of rope is drawn taut: how much (``taut``), which way out (``taut_n``)
        and how far out it may still go (``room``).

        A particle k of a stretch of rope between two held particles h1, h2
        of reach L (the rods between them) can only be where |x_k - x_h1| +
        |x_k - x_h2| <= L: a spheroid with the holds as foci. On its
        boundary the stretch is straight on both sides of k, and a contact
        that pushes k out through it stretches the rods, which the chain
        step cannot undo (collinear rods held at both ends: a singular
        step, scaled back): the rope is left stretched, then snaps back.
        The rope contacts therefore take away that much of k's inverse mass
        along the boundary's outward normal n (``RopeCollision``): taut =
        (e - TAUT) / (1 - TAUT) clamped to [0, 1], e = (|x_k - x_h1| +
        |x_k - x_h2|) / L, 0 inside e <= TAUT; a taut stretch still slides
        and swings along the boundary, and the other rope gives way. A
        single contact pass can still push k from inside the spheroid out
        past it; ``room`` = (L - |x_k - x_h1| - |x_k - x_h2|) / |g| (g the
        gradient of the focal sum, |g| n = g) is how far along n that stays
        inside, to first order, and the contacts move k no further out than
        that (1e30 off held stretches). O(k) per chain.
        """
        for i in range(taut.shape[0]):
            taut[i] = 0.0
            room[i] = 1e30
        if ti.static(self.has_ropes):
            x = ti.static(self.st.x)
            g0, g1 = ti.static(self.group_ranges[0])
            for c in range(g0, g1):
                lo = self.lo[c]
                hi = self.hi[c]
                if self.link_a[lo] < ti.static(self.cloth_start):
                    seg = -1
                    reach = 0.0
                    for j in range(lo, hi):
                        a = self.link_a[j]
                        b = self.link_b[j]
                        if self.w[a] == 0.0:
                            seg = j
                            reach = 0.0
                        reach += self.rest[j]
                        if seg >= 0 and self.w[b] == 0.0 and j > seg:
                            h1 = x[self.link_a[seg]]
                            h2 = x[b]
                            for k in range(seg + 1, j + 1):
                                i = self.link_a[k]
                                d1 = x[i] - h1
                                d2 = x[i] - h2
                                l1 = d1.norm()
                                l2 = d2.norm()
                                e = (l1 + l2) / reach
                                if l1 > 1e-12 and l2 > 1e-12:
                                    n = d1 / l1 + d2 / l2
                                    ln = n.norm()
                                    if ln > 1e-6:
                                        taut_n[i] = n / ln
                                        room[i] = ti.max(reach - l1 - l2, 0.0) / ln
                                        if e > ti.static(TAUT):
                                            taut[i] = ti.min(1.0, (e - ti.static(TAUT)) / (1.0 - ti.static(TAUT)))

    @ti.func
    def _peel(self):
        """Free the contacts whose chain neighbour has left the surface (see the module docstring)."""
        x = ti.static(self.st.x)
        for i in range(self.peeled.shape[0]):
            self.peeled[i] = 0
        for j in range(self.link_a.shape[0]):
            a = self.link_a[j]
            b = self.link_b[j]
            if a >= ti.static(self.cloth_start):
                lift = 0.3 * self.rest[j]
                if self.contact[a] > 0.0 and (x[b] - x[a]).dot(self.normal[a]) > lift:
                    self.peeled[a] = 1
                if self.contact[b] > 0.0 and (x[a] - x[b]).dot(self.normal[b]) > lift:
                    self.peeled[b] = 1

    @ti.kernel
    def solve(self):
        """``solve_f`` as a kernel of its own (the solver fuses it into its substep kernel)."""
        self.solve_f()

    @ti.kernel
    def resweep(self, tol: ti.template()):
        """``resweep_f`` as a kernel of its own."""
        self.resweep_f(tol)

    @ti.func
    def solve_f(self):
        """One Newton step of every chain, group after group."""
        if ti.static(self.has_contacts and self.cloth_start < self.model.n):
            self._peel()
        self._sweep(0.0)

    @ti.func
    def resweep_f(self, tol: ti.template()):
        """Another Newton step of the chains that still have a rod off its length by more than ``tol``.

        For a second or later sweep in one iteration (after the contacts have
        moved particles again): every rod's length is checked, O(L), but only
        the chains off by more than ``tol`` are linearised and solved. The
        contact restriction is the one the first sweep found (``_peel`` is not
        repeated).
        """
        self._sweep(tol)

    @ti.func
    def _sweep(self, tol: ti.template()):
        for g in ti.static(range(len(self.group_ranges))):
            if ti.static(tol == 0.0):
                self._linearise(self.link_ranges[g][0], self.link_ranges[g][1])
            for c in range(self.group_ranges[g][0], self.group_ranges[g][1]):
                self._chain(c, tol)
