"""Cloth self-collision: particle spheres of the collision thickness.

Two cloth particles closer than the thickness are pushed apart along their
separation (averaged Jacobi: each particle gathers its own correction in a
fixed neighbour order, so results are bitwise repeatable). Grid neighbours
within two rows and columns of each other are excluded: the structural,
shear and skip-one bending constraints keep them apart, and a flat sheet
then has no self-contact candidates at all.

Candidates come from Verlet lists. Each particle keeps a reference
position (``x_ref``, where it was when its list was last made, less the
common move since then) and lists the non-excluded particles whose
references are closer than ``thickness + skin``, sorted by index. Once
some particle has moved half the skin or more from its reference (moves
measured from their common part, the mean move) the lists are patched:
the particles that moved ``PATCH_SHARE`` of that or more ("dirty") take
their current position less the mean move as reference and scan the 27
hash cells around it; the other lists drop their dirty partners and get
back those still within reach. Every pair not listed was then at least
``thickness + skin`` apart at its two references, and each particle has
moved less than half the skin from its own beyond the common move, so the
lists miss no contact. Where more than ``FULL_SHARE`` of the particles are
dirty (a landing sheet), or some list is over capacity, all lists are
rebuilt instead. A cloth lying on a box, whose particles at the edges creep
past half the skin a few at a time, then costs patches of those few, not
a rebuild of all (8 ms at 163 x 163 on 2 cores). Which pairs touch and the
order in which they are summed do not depend on when or how the lists
were made. A particle with more candidates than a list holds scans the
hash cells around its reference instead.

Self-contact is inelastic: the pushes a particle took in a substep are
summed (``push``), and at the end of the substep (``settle``, in the
velocity pass) its velocity along their direction loses what they put
there, up to the push over the step and never past zero. Read back as
velocity, a push would otherwise throw two layers of a fold apart, and
folds lying on the ground would jitter (drape_box: 0.3-0.5 m/s at the end
without it, 0.1-0.2 with it).
"""


import taichi as ti

from sandbox.collision.contacts import push_settled_velocity
from sandbox.collision.hashgrid import HashGrid, cell_of, hash_cell, neighbor_offset

# Above this share of dirty particles the lists are rebuilt rather than patched.
FULL_SHARE = 0.5
# A patch takes in the particles that moved this share of half the skin or more.
PATCH_SHARE = 0.5
# Particles per block of the mean move's fixed-order sum.
_BLOCK = 256


@ti.func
def sphere_push(xi, xj, wi, wj, target):
    """Share of particle i in separating two spheres to ``target`` (m) between centres.

    Returns (dx_i, touching); dx_i is zero unless the centres are closer than
    ``target`` (and not coincident, where the direction is undefined).
    """
    d = xi - xj
    dist = d.norm()
    dx = ti.math.vec3(0.0)
    hit = 0
    if dist < target and dist > 1e-9:
        dx = (wi / (wi + wj)) * (target - dist) / dist * d
        hit = 1
    return dx, hit


@ti.data_oriented
class ClothSelfCollision:
    """Self-collision of all cloth particles (indices ``start .. n``).

    Args:
        skin: m, how much farther than the thickness the lists reach; a
            particle may move half of it before the lists are rebuilt.
            None: half the thickness (in ``drape_box`` 0.3 or 1 thickness
            cost more per frame: more rebuilds, or longer lists).
        capacity: candidates one particle's list holds.

    Fields (k cloth particles):
        cand: (k, capacity) i32, candidate partners (cloth-relative ids),
            ascending; ``n_cand`` (k,) i32 their number, above ``capacity``
            for a particle that scans the hash instead.
        x_ref: (k,) vec3 f32, m, each particle's position when its list was made.
        dirty: (k,) i32, 1 for a particle that moved half the skin or more
            from ``x_ref`` (set at each check).
        valid: () i32, 1 while the lists are good for the current positions.
        block_move: (k / 256,) vec3 f32, m, sums of the moves from ``x_ref`` by blocks.
        shift: () vec3 f32, m, the mean move (the common part) at the last check.
        n_dirty: () i32, dirty particles at the last check.
        rebuilds, patches, overflows: () i32, full list builds and patches so
            far; particles over capacity after the last of either.
        sx, skey, scell: (k,) reference positions (m), packed (cloth, j, i)
            keys and cells, copied in bucket order for the 27-cell scans.
        dx: (k,) vec3 f32, m, correction accumulator.
        gap: (k,) f32, m, smallest distance minus thickness (metrics).
    """

    def __init__(self, model, state, w, start: int, *, skin: float | None = None, capacity: int = 128) -> None:
        self.model = model
        self.st = state
        self.wall = w
        self.start = start
        self.count = model.n - start
        self.thickness = model.max_thickness
        self.ring = 2  # grid neighbours within this many rows/columns never collide
        self.target = float(self.thickness)  # m, contact distance between particle centres
        self.skin = 0.5 * self.target if skin is None else float(skin)
        self.reach = self.target + self.skin  # m, candidate distance at a build
        # Half the skin, less a little for rounding: a particle that moved this
        # far (squared, m^2) triggers a rebuild.
        self.moved_sq = (0.5 * self.skin * (1.0 - 1e-4)) ** 2
        # A patch redoes every particle that moved PATCH_SHARE of that or more,
        # so that particles creeping along together trigger one patch, not one each.
        self.patch_sq = PATCH_SHARE**2 * self.moved_sq
        # Cells a little wider than the reach, so that a 27-cell scan cannot
        # miss a pair closer than the reach through rounding in cell_of.
        self.grid = HashGrid(self.count, self.reach * (1.0 + 1e-4))
        self.capacity = int(capacity)
        self.cand = ti.field(ti.i32, shape=(self.count, self.capacity))
        self.n_cand = ti.field(ti.i32, shape=self.count)
        self.x_ref = ti.Vector.field(3, ti.f32, shape=self.count)
        self.dirty = ti.field(ti.i32, shape=self.count)
        self.valid = ti.field(ti.i32, shape=())
        self.n_blocks = (self.count + _BLOCK - 1) // _BLOCK
        self.block_move = ti.Vector.field(3, ti.f32, shape=self.n_blocks)
        self.shift = ti.Vector.field(3, ti.f32, shape=())
        self.n_dirty = ti.field(ti.i32, shape=())
        self.n_far = ti.field(ti.i32, shape=())
        self.rebuilds = ti.field(ti.i32, shape=())
        self.patches = ti.field(ti.i32, shape=())
        self.overflows = ti.field(ti.i32, shape=())
        self.dx = ti.Vector.field(3, ti.f32, shape=self.count)
        self.push = ti.Vector.field(3, ti.f32, shape=self.count)  # this substep's pushes, summed
        self.sx = ti.Vector.field(3, ti.f32, shape=self.count)
        self.skey = ti.field(ti.i32, shape=self.count)
        self.scell = ti.Vector.field(3, ti.i32, shape=self.count)
        self.gap = ti.field(ti.f32, shape=self.count)

    @ti.func
    def _excluded(self, i, j):
        out = i == j
        if self.model.cloth_id[i] == self.model.cloth_id[j]:
            d = self.model.grid_ij[i] - self.model.grid_ij[j]
            if ti.abs(d[0]) <= self.ring and ti.abs(d[1]) <= self.ring:
                out = True
        return out

    @ti.func
    def _gather_sorted(self, go):
        """Copy reference positions and keys into bucket order, so the neighbour scans read contiguous memory."""
        for s in range(go * self.count):
            q = self.grid.entries[s]
            i = self.start + q
            self.sx[s] = self.x_ref[q]
            ij = self.model.grid_ij[i]
            self.skey[s] = (self.model.cloth_id[i] << 20) | (ij[1] << 10) | ij[0]
            self.scell[s] = self.grid.item_cell[q]

    @ti.func
    def _near(self, ki, kj):
        """Whether two packed (cloth, j, i) keys are rest neighbours (excluded)."""
        return (ki >> 20) == (kj >> 20) \
            and ti.abs(((ki >> 10) & 1023) - ((kj >> 10) & 1023)) <= self.ring \
            and ti.abs((ki & 1023) - (kj & 1023)) <= self.ring

    @ti.func
    def _add_pair(self, p, q):
        a = ti.atomic_add(self.n_cand[p], 1)
        if a < self.capacity:
            self.cand[p, a] = q
        b = ti.atomic_add(self.n_cand[q], 1)
        if b < self.capacity:
            self.cand[q, b] = p

    @ti.func
    def _scan_from(self, s, dirty_only: ti.template()):
        """Enter the pairs of the particle at bucket slot ``s`` closer than the reach (reference positions).

        Each pair is tested once. In a full build: from the particle that
        comes first in bucket order. In a patch (``dirty_only``): from the
        dirty particle, or from the first of two dirty ones.
        """
        reach_sq = self.reach * self.reach
        p = self.grid.entries[s]
        xi = self.sx[s]
        ki = self.skey[s]
        ci = self.scell[s]
        for o in range(27):
            c = ci + neighbor_offset(o)
            h = hash_cell(c, self.grid.mask)
            lo = self.grid.start[h]
            if ti.static(not dirty_only):
                lo = ti.max(lo, s + 1)
            for t in range(lo, self.grid.start[h + 1]):
                # Nested tests, the most selective first: the distance;
                # the cell (a bucket may hold other cells); then the rest
                # neighbours.
                if (xi - self.sx[t]).norm_sqr() < reach_sq:
                    if (self.scell[t] == c).all():
                        q = self.grid.entries[t]
                        once = True
                        if ti.static(dirty_only):
                            once = self.dirty[q] == 0 or t > s
                        if once and not self._near(ki, self.skey[t]):
                            self._add_pair(p, q)

    @ti.func
    def _build_lists(self, go):
        """Each particle's non-excluded partners closer than the reach, ascending (O(n k)).

        Each pair is tested once and entered in both lists (atomic slots);
        sorting the lists afterwards makes them independent of the thread
        schedule.
        """
        for k in range(go * self.count):
            self.n_cand[k] = 0
        for s in range(go * self.count):
            self._scan_from(s, False)

    @ti.func
    def _patch_lists(self, go):
        """Drop the dirty partners from every list, then scan around each dirty particle (O(n + d k)).

        A dirty particle's list is started afresh; a clean one keeps its
        clean partners (their reference positions have not changed) and
        gets its dirty ones from their scans.
        """
        for k in range(go * self.count):
            if self.dirty[k]:
                self.n_cand[k] = 0
            else:
                m = 0
                for a in range(self.n_cand[k]):
                    q = self.cand[k, a]
                    if self.dirty[q] == 0:
                        self.cand[k, m] = q
                        m += 1
                self.n_cand[k] = m
        for s in range(go * self.count):
            if self.dirty[self.grid.entries[s]]:
                self._scan_from(s, True)

    @ti.func
    def _sort_lists(self, go):
        """Sort every list by index (the order of the sums) and count the particles over capacity."""
        for k in range(go * self.count):
            m = self.n_cand[k]
            if m > self.capacity:
                ti.atomic_add(self.overflows[None], 1)
            else:
                for a in range(1, m):  # insertion sort: the gather order is the index order
                    v = self.cand[k, a]
                    b = a - 1
                    while b >= 0 and self.cand[k, b] > v:
                        self.cand[k, b + 1] = self.cand[k, b]
                        b -= 1
                    self.cand[k, b + 1] = v

    @ti.func
    def refresh_f(self):
        """Patch or rebuild the candidate lists if some particle moved half the skin from its reference (O(n)).

        Moves are measured from their common part: a pair's distance changes
        by at most the two particles' moves relative to any one shift. The
        shift is the mean move, which a few particles that moved far do not
        drag along (the centre of the moves' bounding box would: every other
        particle would then count as moved). A falling sheet keeps its lists.
        The mean is summed in fixed blocks, then the blocks in order, so it
        does not depend on the thread schedule.
        """
        for b in range(self.n_blocks):
            acc = ti.math.vec3(0.0)
            for k in range(b * _BLOCK, ti.min((b + 1) * _BLOCK, self.count)):
                acc += self.st.x[self.start + k] - self.x_ref[k]
            self.block_move[b] = acc
        ti.loop_config(serialize=True)
        for _ in range(1):
            acc = ti.math.vec3(0.0)
            for b in range(self.n_blocks):
                acc += self.block_move[b]
            self.shift[None] = acc / self.count
        shift = self.shift[None]
        self.n_dirty[None] = 0
        self.n_far[None] = 0
        for k in range(self.count):
            m = (self.st.x[self.start + k] - self.x_ref[k] - shift).norm_sqr()
            self.dirty[k] = ti.cast(m >= self.patch_sq, ti.i32)
            if m >= self.patch_sq:
                ti.atomic_add(self.n_dirty[None], 1)
            if m >= self.moved_sq:
                ti.atomic_add(self.n_far[None], 1)
        full = 0
        part = 0
        if self.valid[None] == 0 or (self.n_far[None] > 0 and (
                self.overflows[None] > 0 or self.n_dirty[None] > ti.static(FULL_SHARE * self.count))):
            full = 1
        elif self.n_far[None] > 0:
            part = 1
        go = full + part
        if go:
            self.overflows[None] = 0
        for k in range(go * self.count):
            if full:
                self.x_ref[k] = self.st.x[self.start + k]
            elif self.dirty[k]:
                # In the clean particles' frame: its move from x_ref is the
                # common shift, so a pair's change in distance stays bounded
                # by the two particles' moves beyond one shift.
                self.x_ref[k] = self.st.x[self.start + k] - shift
        self.grid.build_if_f(self.x_ref, 0, self.count, go)
        self._gather_sorted(go)
        self._build_lists(full)
        self._patch_lists(part)
        self._sort_lists(go)
        if full:
            self.valid[None] = 1
            self.rebuilds[None] += 1
        if part:
            self.patches[None] += 1

    @ti.func
    def _scan_hash(self, k, xi, wi):
        """Correction of particle k from a 27-cell scan around its reference's cell (overflow path)."""
        i = self.start + k
        acc = ti.math.vec3(0.0)
        cnt = 0
        ci = self.grid.item_cell[k]
        for o in range(27):
            c = ci + neighbor_offset(o)
            h = hash_cell(c, self.grid.mask)
            for t in range(self.grid.start[h], self.grid.start[h + 1]):
                q = self.grid.entries[t]
                j = self.start + q
                if (self.grid.item_cell[q] == c).all() and not self._excluded(i, j):
                    dx, hit = sphere_push(xi, self.st.x[j], wi, self.wall[j], self.target)
                    acc += dx
                    cnt += hit
        return acc, cnt

    @ti.func
    def solve_f(self):
        """One averaged-Jacobi pass of self-collision over the candidate lists (``refresh_f`` first)."""
        for k in range(self.count):
            i = self.start + k
            acc = ti.math.vec3(0.0)
            cnt = 0
            wi = self.wall[i]
            if wi > 0.0:
                xi = self.st.x[i]
                m = self.n_cand[k]
                if m <= self.capacity:
                    for a in range(m):
                        j = self.start + self.cand[k, a]
                        dx, hit = sphere_push(xi, self.st.x[j], wi, self.wall[j], self.target)
                        acc += dx
                        cnt += hit
                else:
                    acc, cnt = self._scan_hash(k, xi, wi)
            # Averaged Jacobi: a particle squeezed by many neighbours moves by
            # their mean push, not their sum (which overshoots and injects energy).
            self.dx[k] = acc / ti.max(cnt, 1)
        for k in range(self.count):
            i = self.start + k
            self.st.x[i] = self.st.x[i] + self.dx[k]
            self.push[k] += self.dx[k]

    @ti.func
    def settle(self, i, v, inv_dt: ti.f32):
        """Particle i's velocity ``v`` less what this substep's self-collision pushes put into it (inelastic
        self-contact; called from the velocity pass, which it saves a loop of its own). Clears the pushes."""
        out = v
        k = i - self.start
        if k >= 0:
            out = push_settled_velocity(v, self.push[k], inv_dt)
            self.push[k] = ti.math.vec3(0.0)
        return out

    @ti.kernel
    def _measure(self):
        for k in range(self.count):
            i = self.start + k
            xi = self.st.x[i]
            ci = cell_of(xi, self.grid.inv_cell)
            best = 1e30
            for o in range(27):
                c = ci + neighbor_offset(o)
                h = hash_cell(c, self.grid.mask)
                for slot in range(self.grid.start[h], self.grid.start[h + 1]):
                    q = self.grid.entries[slot]
                    j = self.start + q
                    if (self.grid.item_cell[q] == c).all() and not self._excluded(i, j):
                        best = ti.min(best, (xi - self.st.x[j]).norm() - self.model.radius[i] - self.model.radius[j])
            self.gap[k] = best

    def measure(self):
        """Per cloth particle: distance to the nearest non-neighbour minus thickness (m).

        Uses the hash of the lists, so these are rebuilt at the next pass.
        """
        self.grid.build(self.st.x, self.start, self.count)
        self._measure()
        self.valid[None] = 0
        return self.gap.to_numpy()
