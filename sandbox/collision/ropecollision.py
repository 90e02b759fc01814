"""Rope-rope collision: capsules of non-adjacent segments (paper Eq. 5).

Segments are binned by midpoint in a hash with cells of (rod length + two
radii), so every pair that can touch is in the 27 neighbouring cells. Each
segment gathers the XPBD correction of its own two end points from all its
contacts (normal push plus Coulomb friction on the contact's slip).

The pass is a Jacobi step, so a particle touched by several contacts must
not take each one's full correction. It uses mass splitting: the contacts
are counted in a first gather; each contact is then solved as if each of
its particles had only its share of its mass (inverse mass times its
count), and particles add what they gathered. Every push is equal and
opposite (momentum-conserving), a particle with one contact takes the full
projection, and a stack of contacts on one particle closes as a whole.
Dividing each particle's gathered corrections by its count instead (a plain
Jacobi average) pushes the two sides of a contact unequally where their
counts differ: the pair's centre of mass moves, a force nothing in the
scene exerts, and a tight knot held by its ends never comes to rest. Mass
splitting was chosen over that, and over scaling each contact by
min(1, 1.5 / k), by the standard sweep of every rope level
(docs/benchmarks.md, "Rope contacts").

A pass moves no particle by more than its shortest rod (``THROW``),
which only a contact next to held particles asks for.

Same-rope pairs must be at least max(2, ceil(1 + 2 radius / rod)) segments
apart: closer ones share a particle or overlap at rest (thick ropes).
"""


import numpy as np
import taichi as ti

from sandbox import runtime
from sandbox.collision.contacts import push_settled_velocity
from sandbox.collision.hashgrid import HashGrid, cell_of, hash_cell, neighbor_offset
from sandbox.constraints.capsule import segment_closest

# Most a contact pass moves a particle, in rods of its rope: a contact next
# to a held particle (both segments held at that end) is pushed out through
# a lever of (1 - u), and its linearised step grows as 1 / (1 - u) (a rod
# thrown several times its length in one pass); the next passes finish it.
THROW = 1.0



@ti.data_oriented
class RopeCollision:
    """Capsule collisions between all rope segments.

    Fields (s segments, n particles):
        mid: (s,) vec3 f32, m, segment midpoints (hash keys).
        d0, d1: (s,) vec3 f32, m, corrections gathered for each end.
        c0, c1: (s,) i32, contacts gathered for each end.
        count: (n,) f32, contacts on each particle (at least 1), this pass.
        seg_a, seg_b: (n,) i32, segment starting / ending at each particle (-1).
        gap: (s,) f32, m, min over contacts of distance minus radii (metrics).
        max_move: (n,) f32, m, most one pass moves each particle (``THROW``
            of its shortest rod; 0 off the ropes).
    """

    def __init__(self, model, state, w, contacts=None) -> None:
        self.model = model
        self.st = state
        self.w = w
        # ``contacts`` (a ``collision.contacts.Contacts``, optional): a pushed
        # particle records its push direction there for the chain solve (see
        # rope_chain); with its taut fields, how much of each particle's
        # inverse mass is taken away along a direction, and how far along it
        # a pass may move the particle (a held stretch of rope drawn taut,
        # see rope_chain.ChainProjection.taut_f).
        self.record = contacts is not None
        self.hit = contacts.hit if contacts is not None else None
        self.normal = contacts.normal if contacts is not None else None
        self.has_taut = contacts is not None and contacts.has_taut
        self.taut, self.taut_n, self.room = (contacts.taut, contacts.taut_n, contacts.room) if self.has_taut else (None,) * 3
        d = model.data
        s = len(d.segments)
        self.s = s
        rad = np.array([r.radius for r in d.ropes])
        rod = np.array([r.rod_length for r in d.ropes])
        self.cell = float(rod.max() + 2.0 * rad.max())
        self.grid = HashGrid(s, self.cell)
        # Segments i and i + k of a straight rope are (k - 1) rods apart: pairs
        # closer in index than 1 + 2 radius / rod would touch at rest.
        skip = np.maximum(2, np.ceil(1.0 + 2.0 * rad / rod - 1e-9)).astype(np.int32)
        self.skip = ti.field(ti.i32, shape=len(skip))
        runtime.defer(self.skip.from_numpy, skip)
        self.mid = ti.Vector.field(3, ti.f32, shape=s)
        self.d0 = ti.Vector.field(3, ti.f32, shape=s)
        self.d1 = ti.Vector.field(3, ti.f32, shape=s)
        self.c0 = ti.field(ti.i32, shape=s)
        self.c1 = ti.field(ti.i32, shape=s)
        self.gap = ti.field(ti.f32, shape=s)
        self.count = ti.field(ti.f32, shape=model.n)
        seg_a = -np.ones(model.n, np.int32)
        seg_b = -np.ones(model.n, np.int32)
        seg_a[d.segments[:, 0]] = np.arange(s)
        seg_b[d.segments[:, 1]] = np.arange(s)
        self.seg_a = ti.field(ti.i32, shape=model.n)
        self.seg_b = ti.field(ti.i32, shape=model.n)
        runtime.defer(self.seg_a.from_numpy, seg_a)
        runtime.defer(self.seg_b.from_numpy, seg_b)
        self.rope_particles = np.flatnonzero((seg_a >= 0) | (seg_b >= 0)).astype(np.int32)
        # Most one pass moves each particle (m): THROW of its shortest rod.
        seg_len = np.linalg.norm(d.x0[d.segments[:, 1]] - d.x0[d.segments[:, 0]], axis=1)
        cap = np.full(model.n, np.inf)
        np.minimum.at(cap, d.segments[:, 0], THROW * seg_len)
        np.minimum.at(cap, d.segments[:, 1], THROW * seg_len)
        self.max_move = ti.field(ti.f32, shape=model.n)
        runtime.defer(self.max_move.from_numpy, np.where(np.isfinite(cap), cap, 0.0).astype(np.float32))
        # Inelastic contacts: each particle's pushes summed over a substep,
        # taken back out of its velocity along their direction (``settle``).
        # Elastic, the pushes that hold a tight knot together leave speed at
        # every substep, and a held knot never comes to rest (square_knot
        # held after its FSM: sum of v^2 over the particles 134 m^2/s^2
        # against 0.14 inelastic, docs/benchmarks.md, "Held knots").
        self.push = ti.Vector.field(3, ti.f32, shape=model.n)

    @ti.func
    def _midpoints(self):
        for s in range(self.mid.shape[0]):
            self.mid[s] = 0.5 * (self.st.x[self.model.segment[s][0]] + self.st.x[self.model.segment[s][1]])

    @ti.func
    def build_f(self):
        """Bin segment midpoints (once per substep)."""
        self._midpoints()
        self.grid.build_f(self.mid, 0, self.s)

    @ti.func
    def _pair_ok(self, s, t):
        ok = s != t
        r = self.model.segment_rope[s]
        if r == self.model.segment_rope[t]:
            if ti.abs(s - t) < self.skip[r]:
                ok = False
        return ok

    @ti.func
    def _wn(self, i, n):
        """n^T W_i n, W_i = w_i (I - taut_i m m^T) with m = taut_n_i."""
        r = self.w[i]
        if ti.static(self.has_taut):
            r = self.w[i] * (1.0 - self.taut[i] * n.dot(self.taut_n[i]) ** 2)
        return r

    @ti.func
    def _wapply(self, i, v):
        """W_i v."""
        r = self.w[i] * v
        if ti.static(self.has_taut):
            r = self.w[i] * (v - self.taut[i] * v.dot(self.taut_n[i]) * self.taut_n[i])
        return r

    @ti.func
    def _gather(self, measure: ti.template(), count: ti.template()):
        """Per segment: the gap to its nearest neighbour (``measure``), or its
        contacts per end (``count``), or the scaled corrections of its ends."""
        for s in range(self.s):
            a0 = self.model.segment[s][0]
            a1 = self.model.segment[s][1]
            p0 = self.st.x[a0]
            p1 = self.st.x[a1]
            ra = self.model.radius[a0]
            acc0 = ti.math.vec3(0.0)
            acc1 = ti.math.vec3(0.0)
            n0 = 0
            n1 = 0
            best = 1e30
            cs = cell_of(self.mid[s], self.grid.inv_cell)
            for o in range(27):
                c = cs + neighbor_offset(o)
                h = hash_cell(c, self.grid.mask)
                for slot in range(self.grid.start[h], self.grid.start[h + 1]):
                    t = self.grid.entries[slot]
                    if (self.grid.item_cell[t] == c).all() and self._pair_ok(s, t):
                        b0 = self.model.segment[t][0]
                        b1 = self.model.segment[t][1]
                        q0 = self.st.x[b0]
                        q1 = self.st.x[b1]
                        u, v = segment_closest(p0, p1, q0, q1)
                        d = (p0 + u * (p1 - p0)) - (q0 + v * (q1 - q0))
                        dist = d.norm()
                        target = ra + self.model.radius[b0]
                        best = ti.min(best, dist - target)
                        if ti.static(not measure) and dist < target and dist > 1e-9:
                            nrm = d / dist
                            wa0 = self.w[a0] * (1.0 - u)
                            wa1 = self.w[a1] * u
                            ka0 = self._wn(a0, nrm) * (1.0 - u) * (1.0 - u)
                            ka1 = self._wn(a1, nrm) * u * u
                            kb0 = self._wn(b0, nrm) * (1.0 - v) ** 2
                            kb1 = self._wn(b1, nrm) * v * v
                            wsum = ka0 + ka1 + kb0 + kb1
                            if ti.static(not count):  # mass splitting: each particle's share of its mass
                                wsum = (ka0 * self.count[a0] + ka1 * self.count[a1]
                                        + kb0 * self.count[b0] + kb1 * self.count[b1])
                            if ti.static(count) and wsum > 1e-12:
                                if wa0 > 0.0:
                                    n0 += 1
                                if wa1 > 0.0:
                                    n1 += 1
                            if ti.static(not count) and wsum > 1e-12:
                                pen = target - dist
                                # Coulomb friction on positions: the relative slip of the two
                                # closest points this substep, less than mu * pen is undone.
                                slip = ((1.0 - u) * (p0 - self.st.x_prev[a0]) + u * (p1 - self.st.x_prev[a1])) \
                                    - ((1.0 - v) * (q0 - self.st.x_prev[b0]) + v * (q1 - self.st.x_prev[b1]))
                                slip_t = slip - slip.dot(nrm) * nrm
                                lt = slip_t.norm()
                                mu = 0.25 * (self.model.friction[a0] + self.model.friction[a1]
                                             + self.model.friction[b0] + self.model.friction[b1])
                                fric = ti.math.vec3(0.0)
                                if lt > 1e-12:
                                    fric = -slip_t * ti.min(1.0, mu * pen / lt)
                                corr = (pen * nrm + fric) / wsum
                                if wa0 > 0.0:
                                    acc0 += (1.0 - u) * self._wapply(a0, corr)
                                    n0 += 1
                                if wa1 > 0.0:
                                    acc1 += u * self._wapply(a1, corr)
                                    n1 += 1
            self.d0[s] = acc0
            self.d1[s] = acc1
            self.c0[s] = n0
            self.c1[s] = n1
            self.gap[s] = best

    @ti.func
    def _count(self):
        """Contacts on each particle (from the counting gather), at least 1."""
        for i in range(self.count.shape[0]):
            cnt = 0
            if self.seg_a[i] >= 0:
                cnt += self.c0[self.seg_a[i]]
            if self.seg_b[i] >= 0:
                cnt += self.c1[self.seg_b[i]]
            self.count[i] = ti.max(ti.cast(cnt, ti.f32), 1.0)

    @ti.func
    def _apply(self):
        for i in range(self.st.x.shape[0]):
            sa = self.seg_a[i]
            sb = self.seg_b[i]
            acc = ti.math.vec3(0.0)
            cnt = 0
            if sa >= 0:
                acc += self.d0[sa]
                cnt += self.c0[sa]
            if sb >= 0:
                acc += self.d1[sb]
                cnt += self.c1[sb]
            if cnt > 0:
                dx = acc
                if ti.static(self.has_taut):
                    out = dx.dot(self.taut_n[i])
                    if out > self.room[i]:  # not out past taut (rope_chain.taut_f)
                        dx -= (out - self.room[i]) * self.taut_n[i]
                move = dx.norm()
                if move > self.max_move[i]:  # a near-held lever's throw (see THROW)
                    dx *= self.max_move[i] / move
                self.st.x[i] = self.st.x[i] + dx
                self.push[i] += dx
                if ti.static(self.record):
                    la = acc.norm()
                    if la > 1e-12:
                        self.hit[i] = 1.0
                        self.normal[i] = acc / la

    @ti.func
    def forget_f(self):
        """Clear the pushes summed so far (the prediction: a substep's pushes start from zero)."""
        for i in range(self.push.shape[0]):
            self.push[i] = ti.math.vec3(0.0)

    @ti.func
    def settle(self, i, v, inv_dt: ti.f32):
        """Particle i's velocity ``v`` less what this substep's rope contact pushes put into it (rope
        contacts are inelastic: a push out of an overlap moves the particle, but it leaves no speed apart, at most
        the push over the step and never past zero along it). Called from the velocity pass."""
        return push_settled_velocity(v, self.push[i], inv_dt)

    @ti.func
    def solve_f(self):
        """One Jacobi pass of capsule collisions: count the contacts, then solve them with split masses."""
        self._gather(False, True)
        self._count()
        self._gather(False, False)
        self._apply()

    @ti.kernel
    def solve(self):
        """Bin the segments and run one contact pass, as a kernel of its own (the solver fuses it)."""
        self.build_f()
        self.solve_f()

    @ti.kernel
    def _measure(self):
        self._midpoints()
        self.grid.build_f(self.mid, 0, self.s)
        self._gather(True, False)

    def measure(self) -> np.ndarray:
        """Per segment: min capsule distance minus radii sum (m); 1e30 if alone."""
        self._measure()
        return self.gap.to_numpy()
