"""Medial sheet (paper §5.2, Fig. 10): cloth gathered around control lines keeps to its own line's side.

When two corners of a cloth are knotted, the cloth gathered around each
control line is squeezed against the other's, and particle self-collision
alone lets one layer slip through the other. The paper puts a medial sheet
between the lines without building it: each free particle f (a cloth
particle on none of the lines) is associated, at rest, with the ``M = 3``
consecutive line segments nearest to it along the cloth (L_f). After the
simulation pass, a particle whose nearest segment is not in L_f (it has
crossed the medial sheet) moves by a step ``a`` towards the closest point on
L_f; those particles are held while the pass is re-run, at most 3 times.

Association at rest: the cloth is flat at rest, so "along the cloth" is the
distance in the rest configuration; exact nearest segments from a k-d tree
over the segments' midpoints, O(n log m) once. The pass: the segments'
midpoints are binned in a spatial hash whose cells are twice ``reach``
plus a segment wide, and each free particle visits the 2 x 2 x 2 cells
around it: O(n k)
for k segments near a particle, against the paper's O(n m) over every pair
(0.2 s per frame at 163 x 163). Only segments within ``reach`` count: the
sheet separates layers that are close, and a particle far from every line
is left alone.

A push is inelastic, as self-collision's: the velocity pass takes back what
it put into the particle's velocity (``settle``), so separating two layers
does not throw them apart.
"""


import numpy as np
import taichi as ti
from scipy.spatial import cKDTree

from sandbox import runtime
from sandbox.collision.contacts import push_settled_velocity
from sandbox.collision.hashgrid import HashGrid, cell_of, hash_cell
from sandbox.collision.medial_np import point_segment, window

# Segments associated with each free particle (the paper's M).
M_SEGMENTS = 3
# The step a, as a share of the cloth's spacing: the paper's 0.01 at spacing 0.2.
STEP_SHARE = 0.05
# Passes (each followed by a re-run of the simulation pass with the moved particles held).
PASSES = 3
# Default reach, in rows of the cloth: segments farther from a particle do not count.
REACH_ROWS = 3.0


def line_segments(lines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Segments of control lines (each an array of particle indices along the line).

    Returns (seg_a, seg_b, line_of, line_lo, line_hi): segment end particles
    (S,), the line of each segment (S,), and each line's segments [lo, hi).
    """
    a, b, of, lo, hi = [], [], [], [], []
    s = 0
    for k, line in enumerate(lines):
        line = np.asarray(line, np.int64)
        if len(line) < 2:
            raise ValueError(f"medial sheet: control line {k} has {len(line)} particles; a line needs at least 2")
        a.append(line[:-1])
        b.append(line[1:])
        of.append(np.full(len(line) - 1, k))
        lo.append(s)
        s += len(line) - 1
        hi.append(s)
    return (np.concatenate(a), np.concatenate(b), np.concatenate(of), np.asarray(lo, np.int64),
            np.asarray(hi, np.int64))


def associate(x0: np.ndarray, free: np.ndarray, seg_a, seg_b, line_of, line_lo, line_hi,
              m: int = M_SEGMENTS) -> np.ndarray:
    """(F, 2) [lo, hi) of each free particle's ``m`` segments, centred on its nearest at rest (first of equals).

    Exact: the nearest segment's midpoint lies within (the nearest midpoint's
    distance + the longest segment) of the particle, so every segment whose
    midpoint is that close is measured, and no other can be nearer.
    """
    pa, pb = x0[seg_a], x0[seg_b]
    mids = 0.5 * (pa + pb)
    longest = float(np.linalg.norm(pb - pa, axis=1).max())
    pts = x0[free]
    d0, _ = cKDTree(mids).query(pts)
    cands = cKDTree(mids).query_ball_point(pts, d0 + longest + 1e-9)
    out = np.empty((len(free), 2), np.int64)
    for q, cand in enumerate(cands):
        cand = np.sort(np.asarray(cand, np.int64))
        d, _ = point_segment(pts[q : q + 1], pa[cand], pb[cand])
        s = int(cand[np.argmin(d[0])])
        out[q] = window(s, line_lo[line_of[s]], line_hi[line_of[s]], m)
    return out


@ti.func
def _closest(p, a, b):
    """Closest point to p on segment [a, b], and its distance."""
    e = b - a
    t = ti.min(ti.max((p - a).dot(e) / ti.max(e.dot(e), 1e-30), 0.0), 1.0)
    q = a + t * e
    return q, (p - q).norm()


@ti.data_oriented
class MedialSheet:
    """The medial-sheet pass for the control lines of one cloth.

    Args:
        state: the State (positions ``x``, moved in place).
        w: the solver's inverse masses (n,) f32; a moved particle's is 0 until ``release``.
        x0: (n, 3) rest positions.
        cloth: the cloth's ``ClothRange``.
        lines: particle indices of each control line (at least two particles each, all of this cloth).
        reach: m, segments farther from a particle do not count (None: ``REACH_ROWS`` rows of the cloth).
        step: m, the paper's a (None: ``STEP_SHARE`` of the spacing).

    Fields (F free particles, S segments):
        free, lo, hi: (F,) i32 particle index and its own segments [lo, hi).
        seg_a, seg_b: (S,) i32 segment ends; mid: (S,) vec3 midpoints (hashed).
        keep: (F,) f32 a held particle's inverse mass; held: (F,) i32.
        push: (F,) vec3 what the passes of this substep moved it (m).
        moved: () i32 particles the last pass moved.
    """

    def __init__(self, state, w, x0: np.ndarray, cloth, lines: list[np.ndarray], reach: float | None = None,
                 step: float | None = None) -> None:
        spacing = float(min(cloth.spacing))
        for k, line in enumerate(lines):
            line = np.asarray(line)
            if line.size and (line.min() < cloth.start or line.max() >= cloth.end):
                raise ValueError(f"medial sheet: control line {k} has particles outside cloth {cloth.name!r}")
        self.st = state
        self.w = w
        self.reach = float(REACH_ROWS * spacing if reach is None else reach)
        self.step = float(STEP_SHARE * spacing if step is None else step)
        if self.reach <= 0.0 or self.step <= 0.0:
            raise ValueError(f"medial sheet: reach and step must be positive, got {self.reach} and {self.step}")
        seg_a, seg_b, line_of, line_lo, line_hi = line_segments(lines)
        on_line = np.zeros(cloth.end - cloth.start, bool)
        on_line[np.concatenate([np.asarray(x) for x in lines]) - cloth.start] = True
        free = cloth.start + np.flatnonzero(~on_line)
        own = associate(x0, free, seg_a, seg_b, line_of, line_lo, line_hi)
        self.n_free, self.n_seg = len(free), len(seg_a)
        self.free_np, self.own_np, self.seg_np = free, own, (seg_a, seg_b)
        longest = float(np.linalg.norm(x0[seg_b] - x0[seg_a], axis=1).max())
        # A segment within reach has its midpoint within reach + half a segment (rods stretch a little):
        # cells twice that wide put every such midpoint in the 2 x 2 x 2 cells around the particle.
        self.grid = HashGrid(self.n_seg, 2.0 * (self.reach + longest))
        self.free = ti.field(ti.i32, shape=self.n_free)
        self.lo = ti.field(ti.i32, shape=self.n_free)
        self.hi = ti.field(ti.i32, shape=self.n_free)
        self.seg_a = ti.field(ti.i32, shape=self.n_seg)
        self.seg_b = ti.field(ti.i32, shape=self.n_seg)
        self.mid = ti.Vector.field(3, ti.f32, shape=self.n_seg)
        self.keep = ti.field(ti.f32, shape=self.n_free)
        self.held = ti.field(ti.i32, shape=self.n_free)
        self.push = ti.Vector.field(3, ti.f32, shape=self.n_free)
        self.moved = ti.field(ti.i32, shape=())
        runtime.defer(self.free.from_numpy, free.astype(np.int32))
        runtime.defer(self.lo.from_numpy, own[:, 0].astype(np.int32))
        runtime.defer(self.hi.from_numpy, own[:, 1].astype(np.int32))
        runtime.defer(self.seg_a.from_numpy, seg_a.astype(np.int32))
        runtime.defer(self.seg_b.from_numpy, seg_b.astype(np.int32))

    @ti.func
    def _hash_f(self):
        """Bin the segments' midpoints."""
        x = ti.static(self.st.x)
        for s in range(self.n_seg):
            self.mid[s] = 0.5 * (x[self.seg_a[s]] + x[self.seg_b[s]])
        self.grid.build_f(self.mid, 0, self.n_seg)

    @ti.func
    def _check(self, q, p):
        """(wrong, target): whether p, free particle q's position, is nearer (within reach) a segment not its own
        than its own, and the closest point on its own segments."""
        x = ti.static(self.st.x)
        lo = self.lo[q]
        hi = self.hi[q]
        best = 1e30
        target = p
        for s in range(lo, hi):
            c, d = _closest(p, x[self.seg_a[s]], x[self.seg_b[s]])
            if d < best:
                best = d
                target = c
        lim = ti.min(best, ti.static(self.reach))
        wrong = 0
        c0 = cell_of(p - ti.static(0.5 * self.grid.cell), ti.static(self.grid.inv_cell))
        for o in range(8):
            cell = c0 + ti.Vector([o & 1, (o >> 1) & 1, (o >> 2) & 1])
            h = hash_cell(cell, self.grid.mask)
            for k in range(self.grid.start[h], self.grid.start[h + 1]):
                s = self.grid.entries[k]
                if wrong == 0 and (s < lo or s >= hi) and all(self.grid.item_cell[s] == cell):
                    _, d = _closest(p, x[self.seg_a[s]], x[self.seg_b[s]])
                    if d < lim:
                        wrong = 1
        return wrong, target

    @ti.func
    def pass_f(self):
        """One pass of the rule: moves and holds the particles nearer another segment than their own."""
        x = ti.static(self.st.x)
        self._hash_f()
        self.moved[None] = 0
        for q in range(self.n_free):
            i = self.free[q]
            if self.w[i] > 0.0:  # held by a hand, pinned, or already moved: not moved again
                p = x[i]
                wrong, target = self._check(q, p)
                if wrong:
                    delta = target - p
                    dist = delta.norm()
                    mv = delta
                    if dist > ti.static(self.step):
                        mv = ti.static(self.step) / dist * delta
                    x[i] = p + mv
                    self.push[q] += mv
                    self.keep[q] = self.w[i]
                    self.held[q] = 1
                    self.w[i] = 0.0
                    ti.atomic_add(self.moved[None], 1)

    @ti.func
    def release_f(self, inv_dt: ti.f32):
        """End of the substep: held particles get their mass back, and their velocity loses what the pushes gave."""
        for q in range(self.n_free):
            if self.held[q]:
                i = self.free[q]
                self.w[i] = self.keep[q]
                self.held[q] = 0
            i = self.free[q]
            self.st.v[i] = push_settled_velocity(self.st.v[i], self.push[q], inv_dt)
            self.push[q] = ti.math.vec3(0.0)

    @ti.kernel
    def run_pass(self) -> ti.i32:
        """``pass_f`` as a kernel; returns how many particles it moved."""
        self.pass_f()
        return self.moved[None]

    @ti.kernel
    def release(self, inv_dt: ti.f32):
        """``release_f`` as a kernel."""
        self.release_f(inv_dt)

    @ti.kernel
    def _count_wrong(self) -> ti.i32:
        """Free particles nearer another segment (within reach) than their own; moves nothing."""
        self._hash_f()
        n = 0
        for q in range(self.n_free):
            wrong, _ = self._check(q, self.st.x[self.free[q]])
            n += wrong
        return n

    def wrong_side(self) -> int:
        """How many free particles are on the wrong side of the medial sheet now."""
        return int(self._count_wrong())
