"""Cloth through cloth: structural edges of a cloth that pass through one of its own triangles.

A legal cloth state has no edge of the sheet piercing a triangle of the same
sheet (other than the triangles it shares a particle with); a layer pushed
through another leaves a ring of such edges around the hole. The count needs
no history (which side a layer was on before), so it can be taken of any
single frame: it is the ``cloth_interpenetration`` metric.

``crossings_brute`` is the NumPy reference, O(E T). ``ClothCrossings`` bins
the triangles' centroids in a spatial hash with cells 2 rows wide, and
each edge tests the triangles of the 27 cells around its midpoint: an edge
can only pierce a triangle whose centroid is within half an edge plus a
triangle's reach of its midpoint. O(E k) for k triangles near an edge.
"""

import numpy as np
import taichi as ti

from sandbox import runtime
from sandbox.collision.hashgrid import HashGrid, cell_of, hash_cell, neighbor_offset


def structural_edges(nx: int, nz: int) -> np.ndarray:
    """(E, 2) local particle indices of a cloth grid's rows' and columns' edges."""
    idx = np.arange(nx * nz).reshape(nz, nx)
    rows = np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], axis=1)
    cols = np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], axis=1)
    return np.concatenate([rows, cols]).astype(np.int64)


def crossings_brute(x: np.ndarray, edges: np.ndarray, faces: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """(E,) bool: edge [a, b] passes through a triangle it shares no particle with (Moller-Trumbore, float64)."""
    x = np.asarray(x, np.float64)
    p0, p1 = x[edges[:, 0]][:, None], x[edges[:, 1]][:, None]
    v0, v1, v2 = (x[faces[:, k]][None] for k in range(3))
    d = p1 - p0
    e1, e2 = v1 - v0, v2 - v0
    h = np.cross(d, e2)
    det = (e1 * h).sum(-1)
    ok = np.abs(det) > eps
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p0 - v0
    u = inv * (s * h).sum(-1)
    q = np.cross(s, e1)
    v = inv * (d * q).sum(-1)
    t = inv * (e2 * q).sum(-1)
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)
    shared = (edges[:, None, :, None] == faces[None, :, None, :]).any(axis=(2, 3))
    return (hit & ~shared).any(axis=1)


@ti.func
def _pierces(p0, p1, v0, v1, v2) -> ti.i32:
    """Whether segment [p0, p1] passes through triangle (v0, v1, v2) (Moller-Trumbore)."""
    d = p1 - p0
    e1 = v1 - v0
    e2 = v2 - v0
    h = d.cross(e2)
    det = e1.dot(h)
    hit = 0
    if ti.abs(det) > 1e-12:
        inv = 1.0 / det
        s = p0 - v0
        u = inv * s.dot(h)
        q = s.cross(e1)
        v = inv * d.dot(q)
        t = inv * e2.dot(q)
        if u >= 0.0 and v >= 0.0 and u + v <= 1.0 and t >= 0.0 and t <= 1.0:
            hit = 1
    return hit


@ti.data_oriented
class ClothCrossings:
    """Counts a cloth's structural edges that pass through its own triangles.

    Args:
        state: the State (positions ``x``).
        cloth: the cloth's ``ClothRange``.

    Fields (E edges, T triangles):
        edge: (E,) ivec2 global particle indices; face: (T,) ivec3 global.
        cen: (T,) vec3 triangle centroids (hashed).
        crossing: (E,) i32 1 where the edge pierces a triangle, from the last count.
    """

    def __init__(self, state, cloth) -> None:
        self.st = state
        edges = structural_edges(cloth.nx, cloth.nz) + cloth.start
        faces = np.asarray(cloth.faces, np.int64) + cloth.start
        self.n_edges, self.n_faces = len(edges), len(faces)
        spacing = float(max(cloth.spacing))
        # An edge pierces a triangle only if its midpoint is within half an edge plus the triangle's
        # farthest vertex from its centroid (sqrt(5)/3 of a leg) of the centroid: 1.25 rows at rest, 1.66
        # with rods stretched by a third. Cells of 2 rows keep every such pair within the 27 around the midpoint.
        self.grid = HashGrid(self.n_faces, 2.0 * spacing)
        self.near2 = (1.7 * spacing) ** 2  # m^2: farther centroids cannot be pierced (the same bound)
        self.edge = ti.Vector.field(2, ti.i32, shape=self.n_edges)
        self.face = ti.Vector.field(3, ti.i32, shape=self.n_faces)
        self.cen = ti.Vector.field(3, ti.f32, shape=self.n_faces)
        self.crossing = ti.field(ti.i32, shape=self.n_edges)
        self.total = ti.field(ti.i32, shape=())
        runtime.defer(self.edge.from_numpy, edges.astype(np.int32))
        runtime.defer(self.face.from_numpy, faces.astype(np.int32))

    @ti.kernel
    def _count(self) -> ti.i32:
        x = ti.static(self.st.x)
        for f in range(self.n_faces):
            v = self.face[f]
            self.cen[f] = (x[v[0]] + x[v[1]] + x[v[2]]) / 3.0
        self.grid.build_f(self.cen, 0, self.n_faces)
        self.total[None] = 0
        for e in range(self.n_edges):
            a = self.edge[e][0]
            b = self.edge[e][1]
            p0 = x[a]
            p1 = x[b]
            mid = 0.5 * (p0 + p1)
            c0 = cell_of(mid, ti.static(self.grid.inv_cell))
            hit = 0
            for o in range(27):
                cell = c0 + neighbor_offset(o)
                h = hash_cell(cell, self.grid.mask)
                for k in range(self.grid.start[h], self.grid.start[h + 1]):
                    f = self.grid.entries[k]
                    v = self.face[f]
                    if hit == 0 and (self.cen[f] - mid).norm_sqr() < ti.static(self.near2) \
                            and all(self.grid.item_cell[f] == cell) and v[0] != a and v[1] != a \
                            and v[2] != a and v[0] != b and v[1] != b and v[2] != b:
                        hit = _pierces(p0, p1, x[v[0]], x[v[1]], x[v[2]])
            self.crossing[e] = hit
            self.total[None] += hit
        return self.total[None]

    def count(self) -> int:
        """How many structural edges pass through a triangle of the same cloth now."""
        return int(self._count())
