"""Cloth self-collision: particle spheres of the collision thickness.

Two cloth particles closer than the thickness are pushed apart along their
separation (averaged Jacobi: each particle gathers its own correction in a
fixed neighbour order, so results are bitwise repeatable). Grid neighbours
within two rows and columns of each other are excluded: the structural,
shear and skip-one bending constraints keep them apart, and a flat sheet
then has no self-contact candidates at all.

Candidates come from Verlet lists: each particle keeps the non-excluded
particles that were closer than ``thickness + skin`` when the lists were
built, sorted by index. The lists are rebuilt (spatial hash, then a 27-cell
scan) only when some particle has moved half the skin or more since then,
moves measured from their common part; until then every pair now closer
than the thickness was closer than ``thickness + skin`` at the build, so
the lists miss no contact. Which pairs touch and the order in which they
are summed do not depend on when the lists were rebuilt. A particle with
more candidates than a list holds scans the hash cells around it instead.
"""


import taichi as ti

from sandbox.collision.hashgrid import HashGrid, cell_of, hash_cell, neighbor_offset


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
        x_ref: (k,) vec3 f32, m, positions when the lists were built.
        valid: () i32, 1 while the lists are good for the current positions.
        move_lo, move_hi: () vec3 f32, m, bounding box of the moves since the build.
        rebuilds, overflows: () i32, list builds so far; particles over
            capacity at the last build.
        sx, skey, scell: (k,) positions (m), packed (cloth, j, i) keys and
            cells, copied in bucket order for the build's 27-cell scans.
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
        # Cells a little wider than the reach, so that a 27-cell scan cannot
        # miss a pair closer than the reach through rounding in cell_of.
        self.grid = HashGrid(self.count, self.reach * (1.0 + 1e-4))
        self.capacity = int(capacity)
        self.cand = ti.field(ti.i32, shape=(self.count, self.capacity))
        self.n_cand = ti.field(ti.i32, shape=self.count)
        self.x_ref = ti.Vector.field(3, ti.f32, shape=self.count)
        self.valid = ti.field(ti.i32, shape=())
        self.move_lo = ti.Vector.field(3, ti.f32, shape=())
        self.move_hi = ti.Vector.field(3, ti.f32, shape=())
        self.rebuilds = ti.field(ti.i32, shape=())
        self.overflows = ti.field(ti.i32, shape=())
        self.dx = ti.Vector.field(3, ti.f32, shape=self.count)
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
        """Copy particle data into bucket order, so the build's neighbour scans read contiguous memory."""
        for s in range(go * self.count):
            q = self.grid.entries[s]
            i = self.start + q
            self.sx[s] = self.st.x[i]
            ij = self.model.grid_ij[i]
            self.skey[s] = (self.model.cloth_id[i] << 20) | (ij[1] << 10) | ij[0]
            self.scell[s] = self.grid.item_cell[q]

    @ti.func
    def _build_lists(self, go):
        """Each particle's non-excluded partners closer than the reach, ascending (O(n k)).

        Each pair is tested once, from the particle that comes first in bucket
        order, and entered in both lists (atomic slots); sorting the lists
        afterwards makes them independent of the thread schedule.
        """
        reach_sq = self.reach * self.reach
        for k in range(go * self.count):
            self.n_cand[k] = 0
        for s in range(go * self.count):
            p = self.grid.entries[s]
            xi = self.sx[s]
            ki = self.skey[s]
            ci = self.scell[s]
            self.x_ref[p] = xi
            for o in range(27):
                c = ci + neighbor_offset(o)
                h = hash_cell(c, self.grid.mask)
                for t in range(ti.max(self.grid.start[h], s + 1), self.grid.start[h + 1]):
                    # Nested tests, the most selective first: the distance;
                    # the cell (a bucket may hold other cells); then the rest
                    # neighbours.
                    if (xi - self.sx[t]).norm_sqr() < reach_sq:
                        if (self.scell[t] == c).all():
                            kj = self.skey[t]
                            near = (ki >> 20) == (kj >> 20) \
                                and ti.abs(((ki >> 10) & 1023) - ((kj >> 10) & 1023)) <= self.ring \
                                and ti.abs((ki & 1023) - (kj & 1023)) <= self.ring
                            if not near:
                                q = self.grid.entries[t]
                                a = ti.atomic_add(self.n_cand[p], 1)
                                if a < self.capacity:
                                    self.cand[p, a] = q
                                b = ti.atomic_add(self.n_cand[q], 1)
                                if b < self.capacity:
                                    self.cand[q, b] = p
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
        """Rebuild the candidate lists if some particle moved half the skin since the last build (O(n)).

        Moves are measured from their common part: a pair's distance changes
        by at most the two particles' moves relative to any one shift, and
        the centre of the moves' bounding box leaves the least. A falling
        sheet then keeps its lists.
        """
        self.move_lo[None] = ti.math.vec3(1e30)
        self.move_hi[None] = ti.math.vec3(-1e30)
        for k in range(self.count):
            d = self.st.x[self.start + k] - self.x_ref[k]
            ti.atomic_min(self.move_lo[None], d)
            ti.atomic_max(self.move_hi[None], d)
        shift = 0.5 * (self.move_lo[None] + self.move_hi[None])
        for k in range(self.count):
            if (self.st.x[self.start + k] - self.x_ref[k] - shift).norm_sqr() >= self.moved_sq:
                self.valid[None] = 0
        go = 1 - self.valid[None]
        if go:
            self.overflows[None] = 0
        self.grid.build_if_f(self.st.x, self.start, self.count, go)
        self._gather_sorted(go)
        self._build_lists(go)
        if go:
            self.valid[None] = 1
            self.rebuilds[None] += 1

    @ti.func
    def _scan_hash(self, k, xi, wi):
        """Correction of particle k from a 27-cell scan around its cell at the last build (overflow path)."""
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
