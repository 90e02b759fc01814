"""Joint inextensibility of a cloth's rows and columns: one Newton step solved by preconditioned CG.

The chain step (``rope_chain.py``) solves each row and each column of a
cloth exactly, but one after the other: rows, then columns, then the rows
again. Where the two disagree (cloth crossing a box's top vertex, where the
net of rows and columns must shear hardest) that alternation is block
Gauss-Seidel on a strongly coupled system and stalls: in ``drape_box`` 26
edges stay 2-19 % stretched at the vertices, however many sweeps. Solved
together (every structural edge of the cloth in one linearised system
``(J W J^T) dlam = -C``, contact particles restricted to their tangent
plane as in the chain step, unless they have since moved off it by more
than ``LIFT`` of their radius) the same state converges: taken from the end
of a ``drape_box`` run, three such Newton steps bring every edge within
0.8 % and six within 0.1 %, moving no particle by more than 2.3 mm.

The system is solved by conjugate gradients preconditioned by the chain
step itself: the tridiagonal blocks of the rows and of the columns
(block Jacobi: each edge belongs to exactly one chain, so the blocks are
disjoint and all chains are solved at once). One CG iteration is one
product with ``J W J^T`` (matrix-free: a gather per particle over its at
most four edges, then one pass over the edges) and one Thomas solve per
chain: O(L) for L edges. ``iterations`` CG iterations make one Newton
step, warm-started from the last step's multipliers: a cloth's tension
changes little from one substep to the next, and in ``drape_box`` three
warm iterations hold every edge within 1.5 % once it has landed, where
eight cold ones leave 5 %. The step moves no particle by more than
``THROW`` of a rod (the whole step is scaled back). Sums (CG's inner products) run in fixed
blocks, then over the blocks in order, so results do not depend on the
thread schedule.
"""

import numpy as np
import taichi as ti

from sandbox import runtime
from sandbox.solvers.rope_chain import ChainProjection, cloth_rows_and_columns

# Links per block of an inner product's fixed-order sum.
_BLOCK = 64
# A joint step moves no particle by more than this many rods.
THROW = 0.5
# The share of the last step's multipliers a step starts from. The whole of
# them over-corrects where the shear pass pushes a particle off a box vertex
# every substep (a two-substep cycle at 0.5-0.75 m/s there); 0.8 damps it
# (drape_box: every criterion at 4 of 5 placements instead of 2; measured at
# a shear compliance of 1e-6, before shear became soft).
WARM_START = 0.8
# After a substep's steps, more steps (from zero multipliers, at most SETTLE_STEPS) while an edge is
# stretched by more than SETTLE_STRETCH: a step that leaves more than that met a change within the
# substep (drape_box as it lies still: 24 of about 1,900 substeps, at 4 CG iterations).
SETTLE_STRETCH = 0.01
SETTLE_STEPS = 3
# A particle that touched a surface in this substep but has since moved off it by more than this share
# of its radius (along the contact normal, from where the last push left it) is free in the step, not
# held to the surface's tangent plane (``_free_lifted``).
LIFT = 0.1
# Chains whose preconditioner solves one loop iteration steps side by side (``_precondition``).
LANES = 4


def cloth_chain_groups(data) -> list[list[np.ndarray]]:
    """Rows and columns of every inextensible cloth: [rows, columns] (empty without such a cloth)."""
    return [g for g in cloth_rows_and_columns(data) if g]


@ti.data_oriented
class JointClothProjection(ChainProjection):
    """One joint Newton step on every row and column of the inextensible cloths.

    Args:
        model, state, w, contacts: as for ``ChainProjection``.
        groups: ``cloth_chain_groups(model.data)``.
        peeled: the chain step's peel flags (n,) i32, read, so that a
            particle the chain step lets leave its surface is free here too
            (the step adds its own, ``_free_lifted``).
        iterations: CG iterations per Newton step.
        slots: how many times a substep runs the step (the solver's iterations).

    Fields (L links, P particles of the model):
        lam, rr, z, p, ap: (L,) f32, CG's multipliers (m), residual,
            preconditioned residual, direction and A times direction.
        keep: (slots, L) f32, each call's multipliers, the same call's warm
            start one substep later; call: () i32, the next call of the substep.
        cold: () i32, 1 while ``settle`` runs a step; stretch: () f32, the
            largest stretch the last step left.
        dinv, inert: (L,) f32 / i32, the preconditioner's Thomas factors
            (inverse pivots; ``cp`` holds the super-diagonal ratios) and rows whose
            both ends cannot move along the rod (left out).
        adj, sgn: (P, 4) i32 / f32, each particle's links (-1: none) and the
            sign of its gradient (+1 at b, -1 at a).
        g: (P,) vec3 f32, m, W J^T v per particle.
        peeled: (P,) i32, 1 where a particle that touched a surface is free in
            this step (peeled by the chain step, or lifted off its surface).
        blk, chain_sum, dots: (L / 64,) and (chains,) f32 partial sums of
            inner products; (4,) f32 finished ones.
    """

    def __init__(self, model, state, w, groups, contacts=None, peeled=None, iterations: int = 8,
                 slots: int = 1) -> None:
        super().__init__(model, state, w, groups, contacts)
        # The chain step's peel flags, read; the step's own flags (``self.peeled``, the parent's field) add
        # the particles that have left their surface since it pushed them.
        self.chain_peeled = peeled
        self.has_chain_peeled = peeled is not None
        self.plane = contacts.plane if contacts is not None else None
        self.iterations = int(iterations)
        L = self.n_links
        self.lam = ti.field(ti.f32, shape=L)
        # A substep that runs the step more than once (one per solver iteration) warm-starts each
        # call from the same call of the last substep: the first call of a substep meets the
        # whole of a substep's stretch, a later one only what the passes between left.
        self.slots = max(1, int(slots))
        self.extra_steps = 0  # settle's steps so far (a count for benchmarks)
        self.keep = ti.field(ti.f32, shape=(self.slots, L))
        self.call = ti.field(ti.i32, shape=())
        self.slot = ti.field(ti.i32, shape=())
        self.cold = ti.field(ti.i32, shape=())
        self.stretch = ti.field(ti.f32, shape=())
        self.rr = ti.field(ti.f32, shape=L)
        self.z = ti.field(ti.f32, shape=L)
        self.p = ti.field(ti.f32, shape=L)
        self.ap = ti.field(ti.f32, shape=L)
        self.dinv = ti.field(ti.f32, shape=L)
        self.inert = ti.field(ti.i32, shape=L)
        # Particle -> links: a particle is `a` of at most one link and `b` of
        # at most one link in each group.
        a_np = np.concatenate([np.asarray(c[:-1]) for g in groups for c in g]).astype(np.int64)
        b_np = np.concatenate([np.asarray(c[1:]) for g in groups for c in g]).astype(np.int64)
        adj = np.full((model.n, 4), -1, np.int32)
        sgn = np.zeros((model.n, 4), np.float32)
        fill = np.zeros(model.n, np.int64)
        for ends, s in ((a_np, -1.0), (b_np, 1.0)):
            for j, i in enumerate(ends):
                adj[i, fill[i]] = j
                sgn[i, fill[i]] = s
                fill[i] += 1
        assert fill.max() <= 4, "a particle in more than two links of a group"
        self.movers = np.unique(np.concatenate([a_np, b_np])).astype(np.int32)
        self.n_movers = len(self.movers)
        self.mover = ti.field(ti.i32, shape=self.n_movers)
        self.adj = ti.Vector.field(4, ti.i32, shape=model.n)
        self.sgn = ti.Vector.field(4, ti.f32, shape=model.n)
        self.g = ti.Vector.field(3, ti.f32, shape=model.n)
        runtime.defer(self.mover.from_numpy, self.movers)
        runtime.defer(self.adj.from_numpy, adj)
        runtime.defer(self.sgn.from_numpy, sgn)
        self.n_blocks = (L + _BLOCK - 1) // _BLOCK
        self.blk = ti.field(ti.f32, shape=self.n_blocks)
        self.chain_sum = ti.field(ti.f32, shape=sum(len(g) for g in groups))
        self.n_lanes = (sum(len(g) for g in groups) + LANES - 1) // LANES
        self.dots = ti.field(ti.f32, shape=4)
        self.move = ti.field(ti.f32, shape=())
        self.rod = float(np.min(np.linalg.norm(model.data.x0[b_np] - model.data.x0[a_np], axis=1)))

    # ------------------------------------------------------------ pieces
    @ti.func
    def _sum_blocks(self, slot: ti.template()):
        """dots[slot] = the sum of the block sums, in order."""
        ti.loop_config(serialize=True)
        for _ in range(1):
            acc = 0.0
            for b in range(self.n_blocks):
                acc += self.blk[b]
            self.dots[slot] = acc

    @ti.func
    def _sum_chains(self, slot: ti.template()):
        """dots[slot] = the sum of the per-chain sums, in order."""
        ti.loop_config(serialize=True)
        for _ in range(1):
            acc = 0.0
            for c in range(self.lo.shape[0]):
                acc += self.chain_sum[c]
            self.dots[slot] = acc

    @ti.func
    def _gather(self, v: ti.template()):
        """g_i = W_i J_i^T v: particle i's move for multipliers v (the sum over its at most four links)."""
        for q in range(self.n_movers):
            i = self.mover[q]
            acc = ti.math.vec3(0.0)
            for s in ti.static(range(4)):
                j = self.adj[i][s]
                if j >= 0:
                    acc += self.sgn[i][s] * v[j] * self.nrm[j]
            self.g[i] = self._wapply(i, acc)

    @ti.func
    def _reg(self, j):
        """The chain step's regulariser on link j's diagonal."""
        return 1e-6 * (self.w[self.link_a[j]] + self.w[self.link_b[j]])

    @ti.func
    def _apply_a(self, v: ti.template(), out: ti.template(), slot: ti.template()):
        """out = (J W J^T + reg) v (inert rows give 0), and dots[slot] = v . out."""
        self._gather(v)
        for b in range(self.n_blocks):
            acc = 0.0
            for j in range(b * _BLOCK, ti.min((b + 1) * _BLOCK, self.n_links)):
                r = 0.0
                if self.inert[j] == 0:
                    r = self.nrm[j].dot(self.g[self.link_b[j]] - self.g[self.link_a[j]]) + self._reg(j) * v[j]
                out[j] = r
                acc += v[j] * r
            self.blk[b] = acc
        self._sum_blocks(slot)

    @ti.func
    def _factor_link(self, j, lo, hi):
        """Thomas factors of link j of the chain [lo, hi) (from those of link j - 1)."""
        a = self.link_a[j]
        b = self.link_b[j]
        n = self.nrm[j]
        diag = self._wdot(a, n, n) + self._wdot(b, n, n) + self._reg(j)
        sub = 0.0
        if j > lo:
            sub = -self._wdot(a, self.nrm[j - 1], n)
        inert = diag <= 1e-9 * (self.w[a] + self.w[b] + 1e-30)
        self.inert[j] = ti.cast(inert, ti.i32)
        if inert:
            diag = 1.0
            sub = 0.0
        if j > lo:
            diag = diag - sub * self.cp[j - 1]
        sup = 0.0
        if j + 1 < hi and not inert:
            sup = -self._wdot(b, n, self.nrm[j + 1])
        self.dinv[j] = 1.0 / diag  # a multiply in each solve, off its serial chain of divisions
        self.cp[j] = sup / diag
        # The sub-diagonal entry, for the solves: A[j, j-1].
        self.res[j] = sub if j > lo else 0.0

    @ti.func
    def _lanes(self, k):
        """Link ranges [lo, hi) of chains k * LANES .. k * LANES + LANES - 1 (empty past the last chain), the
        longest, and whether all are that long."""
        lo = ti.Vector([0] * LANES)
        hi = ti.Vector([0] * LANES)
        n = 0
        for s in ti.static(range(LANES)):
            c = k * LANES + s
            if c < self.lo.shape[0]:
                lo[s] = self.lo[c]
                hi[s] = self.hi[c]
                n = ti.max(n, hi[s] - lo[s])
        uniform = True
        for s in ti.static(range(LANES)):
            uniform = uniform and hi[s] - lo[s] == n
        return lo, hi, n, uniform

    @ti.func
    def _factor(self):
        """Thomas factors of every chain's tridiagonal block (all chains in parallel)."""
        for c in range(self.lo.shape[0]):
            for j in range(self.lo[c], self.hi[c]):
                self._factor_link(j, self.lo[c], self.hi[c])

    @ti.func
    def _forward(self, rhs: ti.template(), out: ti.template(), j, lo):
        r = rhs[j]
        if self.inert[j]:
            r = 0.0
        if j > lo:
            r = r - self.res[j] * out[j - 1]
        out[j] = r * self.dinv[j]

    @ti.func
    def _backward(self, rhs: ti.template(), out: ti.template(), j, hi):
        if j + 1 < hi:
            out[j] = out[j] - self.cp[j] * out[j + 1]
        return rhs[j] * out[j]

    @ti.func
    def _precondition(self, rhs: ti.template(), out: ti.template(), slot: ti.template()):
        """out = M^-1 rhs, M the chains' tridiagonal blocks (factored by ``_factor``); dots[slot] = rhs . out.

        A chain's solve is a serial run of dependent multiply-adds, which keeps
        a core waiting on their latency: LANES chains of one length are
        stepped side by side in one loop iteration (at 163 x 163, 0.43 -> 0.22
        ms a solve; bitwise the same, each chain's operations in the same
        order). Only here: unrolled LANES times in the chain step as well, the
        substep compiled for seconds longer than the 0.45 ms it saved.
        """
        for k in range(self.n_lanes):
            lo, hi, n, uniform = self._lanes(k)
            if uniform:  # the usual case: LANES rows (or columns) of one cloth, as long, side by side
                acc = ti.Vector([0.0] * LANES)
                for t in range(n):
                    for s in ti.static(range(LANES)):
                        self._forward(rhs, out, lo[s] + t, lo[s])
                for t in range(n):
                    for s in ti.static(range(LANES)):
                        acc[s] += self._backward(rhs, out, hi[s] - 1 - t, hi[s])
                for s in ti.static(range(LANES)):
                    self.chain_sum[k * LANES + s] = acc[s]
            else:  # chains of different lengths, or past the last: one after the other (one copy of the code)
                for s in range(LANES):
                    c = k * LANES + s
                    if c < self.lo.shape[0]:
                        lo_c = self.lo[c]
                        hi_c = self.hi[c]
                        for j in range(lo_c, hi_c):
                            self._forward(rhs, out, j, lo_c)
                        acc_c = 0.0
                        for t in range(hi_c - lo_c):
                            acc_c += self._backward(rhs, out, hi_c - 1 - t, hi_c)
                        self.chain_sum[c] = acc_c
        self._sum_chains(slot)

    # ------------------------------------------------------------ the step
    # A Newton step is three passes: ``begin_f`` (linearise, factor, the warm start's residual), one
    # ``cg_f`` per CG iteration, ``end_f`` (move the particles). The solver launches ``cg_f`` as a
    # kernel of its own, ``iterations`` times: unrolled into one kernel, drape_box's four iterations
    # compiled in 2.5 s on this machine, one compiles in a quarter of that, for three launches more.
    @ti.func
    def begin_f(self):
        """Start a Newton step: linearise, factor, and the warm start's preconditioned residual.

        Warm-started, unless ``cold`` is set (``settle``): then from zero multipliers, and kept out of
        the next substep's warm start.
        """
        cold = self.cold[None]
        self._free_lifted()
        self._linearise(0, self.n_links)
        for j in range(self.n_links):
            # Right-hand side -C, kept in rr while res holds the factors.
            self.rr[j] = self.res[j]
        self._factor()
        slot = ti.min(self.call[None], self.slots - 1)
        self.slot[None] = slot
        if cold == 0:
            self.call[None] = slot + 1
        for j in range(self.n_links):
            # Warm start: WARM_START of the same call's multipliers one substep earlier (a cloth's
            # tension changes little from one substep to the next; zero at the start).
            lam0 = 0.0
            if cold == 0:
                lam0 = self.keep[slot, j] * ti.static(WARM_START)
            self.lam[j] = lam0
            if self.inert[j]:
                self.rr[j] = 0.0
                self.lam[j] = 0.0
        self._apply_a(self.lam, self.ap, 1)
        for j in range(self.n_links):
            self.rr[j] -= self.ap[j]
        self._precondition(self.rr, self.z, 0)
        for j in range(self.n_links):
            self.p[j] = self.z[j]

    @ti.func
    def _free_lifted(self):
        """Set the step's free flags (``peeled``): the chain step's, and every particle that touched a
        surface in this substep but has since moved off it by more than ``LIFT`` of its radius. Held to
        the plane, such a particle could move only along it, and over a box's vertex the step lifted it
        1.6 mm every other substep (drape_box: 1.3 m/s at the end, its position still)."""
        if ti.static(self.has_contacts):
            x = ti.static(self.st.x)
            for q in range(self.n_movers):
                i = self.mover[q]
                free = 0
                if ti.static(self.has_chain_peeled):
                    free = self.chain_peeled[i]
                off = x[i].dot(self.normal[i]) - self.plane[i]
                if self.contact[i] > 0.0 and off > ti.static(LIFT) * self.model.radius[i]:
                    free = 1
                self.peeled[i] = free

    @ti.func
    def cg_f(self):
        """One preconditioned CG iteration of the step ``begin_f`` started."""
        self._apply_a(self.p, self.ap, 1)
        alpha = 0.0
        if self.dots[1] > 1e-30:
            alpha = self.dots[0] / self.dots[1]
        for j in range(self.n_links):
            self.lam[j] += alpha * self.p[j]
            self.rr[j] -= alpha * self.ap[j]
        self._precondition(self.rr, self.z, 2)
        beta = 0.0
        if self.dots[0] > 1e-30:
            beta = self.dots[2] / self.dots[0]
        self.dots[0] = self.dots[2]
        for j in range(self.n_links):
            self.p[j] = self.z[j] + beta * self.p[j]

    @ti.func
    def end_f(self):
        """Finish the step: keep its multipliers for the next substep's warm start, move the particles
        by ``W J^T lam`` (scaled back as a whole if it would throw one), and leave the largest stretch it
        left in ``stretch``."""
        cold = self.cold[None]
        slot = self.slot[None]
        if cold == 0:
            for j in range(self.n_links):
                self.keep[slot, j] = self.lam[j]
        self._gather(self.lam)
        self.move[None] = 0.0
        for q in range(self.n_movers):
            i = self.mover[q]
            ti.atomic_max(self.move[None], self.g[i].norm())
        s = 1.0
        limit = ti.static(THROW * self.rod)
        if self.move[None] > limit:
            s = limit / self.move[None]
        for q in range(self.n_movers):
            i = self.mover[q]
            self.st.x[i] = self.st.x[i] + s * self.g[i]
        # stretch: only what a substep's last call (or a settle step) leaves is read, so earlier calls
        # skip the pass (the condition sits inside the loop, which stays a parallel one).
        measure = cold == 1 or slot == self.slots - 1
        if measure:
            self.stretch[None] = 0.0
        for j in range(self.n_links):
            if measure and self.inert[j] == 0:
                x = ti.static(self.st.x)
                e = (x[self.link_b[j]] - x[self.link_a[j]]).norm() / self.rest[j] - 1.0
                ti.atomic_max(self.stretch[None], e)

    @ti.kernel
    def _begin_k(self):
        self.begin_f()

    @ti.kernel
    def _cg_k(self):
        self.cg_f()

    @ti.kernel
    def _end_k(self):
        self.end_f()

    def joint(self) -> None:
        """One Newton step (``iterations`` CG iterations), each part a kernel of its own."""
        self._begin_k()
        for _ in range(self.iterations):
            self._cg_k()
        self._end_k()

    def settle(self, step) -> int:
        """Newton steps after a substep's last one, while an edge is stretched by more than SETTLE_STRETCH.

        A substep's one step (a few warm-started CG iterations) holds the cloth where it lies
        still, but not where something changed within the substep: a particle at a box's vertex
        whose contact passes from one face to another leaves its edges stretched by 5-20 %, and
        one step takes that to 6 %. Up to SETTLE_STEPS more steps, each from zero multipliers,
        take it under 1 %. ``step()`` launches one step (the solver's own launch of the joint pass:
        no kernel of its own to compile). Returns how many ran: none in a substep where nothing
        changed, which pays a pass over the links inside the step and one read-back.
        """
        for n in range(SETTLE_STEPS):
            if self.stretch[None] <= SETTLE_STRETCH:
                self.extra_steps += n
                return n
            self.cold[None] = 1
            step()
            self.cold[None] = 0
        self.extra_steps += SETTLE_STEPS
        return SETTLE_STEPS

    def forget(self) -> None:
        """Start the next step cold (multipliers zero), as after a reset of the scene."""
        self.lam.fill(0.0)
        self.keep.fill(0.0)

    @ti.func
    def begin_substep_f(self):
        """The next call is a substep's first (its multipliers from the last substep's first call)."""
        self.call[None] = 0

    @ti.kernel
    def begin_substep(self):
        """``begin_substep_f`` as a kernel of its own."""
        self.begin_substep_f()
