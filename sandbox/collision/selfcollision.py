"""Cloth self-collision: particle spheres of the collision thickness.

Two cloth particles closer than the thickness are pushed apart along their
separation (averaged Jacobi: each particle gathers its own correction in a
fixed neighbour order, so results are bitwise repeatable). Grid neighbours
within two rows and columns of each other are excluded: the structural,
shear and skip-one bending constraints keep them apart, and a flat sheet
then has no self-contact candidates at all. Particle data are copied into
bucket order before each pass, so the 27-cell scans read contiguous memory.
"""


import taichi as ti

from sandbox.collision.hashgrid import HashGrid, cell_of, hash_cell, neighbor_offset


@ti.data_oriented
class ClothSelfCollision:
    """Self-collision of all cloth particles (indices ``start .. n``).

    Fields (k cloth particles):
        sx, sw, skey, scell: (k,) positions (m), inverse masses, packed
            (cloth, j, i) and cells, copied in bucket order each pass.
        dx: (k,) vec3 f32, m, correction accumulator.
        gap: (k,) f32, m, smallest distance minus thickness (metrics).
    """

    def __init__(self, model, state, w, start: int) -> None:
        self.model = model
        self.st = state
        self.wall = w
        self.start = start
        self.count = model.n - start
        self.thickness = model.max_thickness
        self.grid = HashGrid(self.count, self.thickness)
        self.ring = 2  # grid neighbours within this many rows/columns never collide
        self.target = float(self.thickness)  # m, contact distance between particle centres
        self.dx = ti.Vector.field(3, ti.f32, shape=self.count)
        self.sx = ti.Vector.field(3, ti.f32, shape=self.count)
        self.sw = ti.field(ti.f32, shape=self.count)
        self.skey = ti.field(ti.i32, shape=self.count)
        self.scell = ti.Vector.field(3, ti.i32, shape=self.count)
        self.gap = ti.field(ti.f32, shape=self.count)

    @ti.func
    def build_f(self):
        """Bin the cloth particles (once per substep)."""
        self.grid.build_f(self.st.x, self.start, self.count)

    @ti.func
    def _excluded(self, i, j):
        out = i == j
        if self.model.cloth_id[i] == self.model.cloth_id[j]:
            d = self.model.grid_ij[i] - self.model.grid_ij[j]
            if ti.abs(d[0]) <= self.ring and ti.abs(d[1]) <= self.ring:
                out = True
        return out

    @ti.func
    def _gather_sorted(self):
        """Copy particle data into bucket order, so neighbour scans read contiguous memory."""
        for s in range(self.count):
            q = self.grid.entries[s]
            i = self.start + q
            self.sx[s] = self.st.x[i]
            self.sw[s] = self.wall[i]
            ij = self.model.grid_ij[i]
            self.skey[s] = (self.model.cloth_id[i] << 20) | (ij[1] << 10) | ij[0]
            self.scell[s] = self.grid.item_cell[q]

    @ti.func
    def solve_f(self):
        """One averaged-Jacobi pass of self-collision, in bucket order."""
        self._gather_sorted()
        for s in range(self.count):
            acc = ti.math.vec3(0.0)
            cnt = 0
            wi = self.sw[s]
            if wi > 0.0:
                xi = self.sx[s]
                ki = self.skey[s]
                ci = self.scell[s]
                for o in range(27):
                    c = ci + neighbor_offset(o)
                    h = hash_cell(c, self.grid.mask)
                    for t in range(self.grid.start[h], self.grid.start[h + 1]):
                        kj = self.skey[t]
                        near = (ki >> 20) == (kj >> 20) and ti.abs(((ki >> 10) & 1023) - ((kj >> 10) & 1023)) <= self.ring \
                            and ti.abs((ki & 1023) - (kj & 1023)) <= self.ring
                        if not near and (self.scell[t] == c).all():
                            d = xi - self.sx[t]
                            dist = d.norm()
                            if dist < self.target and dist > 1e-9:
                                acc += (wi / (wi + self.sw[t])) * (self.target - dist) / dist * d
                                cnt += 1
            # Averaged Jacobi: a particle squeezed by many neighbours moves by
            # their mean push, not their sum (which overshoots and injects energy).
            self.dx[s] = acc / ti.max(cnt, 1)
        for s in range(self.count):
            i = self.start + self.grid.entries[s]
            self.st.x[i] = self.st.x[i] + self.dx[s]

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
        """Per cloth particle: distance to the nearest non-neighbour minus thickness (m)."""
        self.grid.build(self.st.x, self.start, self.count)
        self._measure()
        return self.gap.to_numpy()
