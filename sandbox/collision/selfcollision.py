"""Cloth self-collision: particle spheres of the collision thickness.

Two cloth particles closer than the thickness are pushed apart along their
separation (Jacobi, each particle gathers its own correction in a fixed
neighbour order, so results are bitwise repeatable). Rest neighbours (the
1-ring of the grid: structural and shear partners) are excluded; they are
held by the distance constraints.
"""


import taichi as ti

from sandbox.collision.hashgrid import HashGrid, cell_of, hash_cell, neighbor_offset


@ti.data_oriented
class ClothSelfCollision:
    """Self-collision of all cloth particles (indices ``start .. n``).

    Fields:
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
        self.dx = ti.Vector.field(3, ti.f32, shape=self.count)
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
            if ti.abs(d[0]) <= 1 and ti.abs(d[1]) <= 1:
                out = True
        return out

    @ti.func
    def solve_f(self):
        """One Jacobi pass of self-collision."""
        for k in range(self.count):
            acc = ti.math.vec3(0.0)
            cnt = 0
            wi = self.wall[self.start + k]
            if wi > 0.0:
                i = self.start + k
                xi = self.st.x[i]
                ci = cell_of(xi, self.grid.inv_cell)
                for o in range(27):
                    c = ci + neighbor_offset(o)
                    h = hash_cell(c, self.grid.mask)
                    for slot in range(self.grid.start[h], self.grid.start[h + 1]):
                        q = self.grid.entries[slot]
                        if (self.grid.item_cell[q] == c).all():
                            j = self.start + q
                            if not self._excluded(i, j):
                                d = xi - self.st.x[j]
                                dist = d.norm()
                                target = self.model.radius[i] + self.model.radius[j]
                                wsum = wi + self.wall[j]
                                if dist < target and dist > 1e-9:
                                    acc += (wi / wsum) * (target - dist) / dist * d
                                    cnt += 1
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
        """Per cloth particle: distance to the nearest non-neighbour minus thickness (m)."""
        self.grid.build(self.st.x, self.start, self.count)
        self._measure()
        return self.gap.to_numpy()
