"""Deterministic spatial hash for broad-phase collision culling.

Items (particles or segment midpoints) are binned into cubic cells of size
``cell`` (m); cells are hashed into a table of ``table_size`` buckets. Build
is a counting sort: atomic counts, a blocked prefix sum, atomic placement,
then an insertion sort of each bucket by item id, so that the order in which
neighbours are visited (and hence every floating-point sum over them) is the
same on every run and on every backend. Build is O(n + table); a query
visits the 27 surrounding cells.
"""


import taichi as ti

_BLOCK = 256


@ti.func
def cell_of(p, inv_cell):
    """Integer cell coordinates of point p."""
    return ti.cast(ti.floor(p * inv_cell), ti.i32)


@ti.func
def neighbor_offset(o):
    """Offset of the o-th (0..26) cell of the 3x3x3 block around a cell."""
    return ti.Vector([o % 3 - 1, (o // 3) % 3 - 1, o // 9 - 1])


@ti.func
def hash_cell(c, mask):
    """Bucket of cell c (Teschner et al. 2003 primes)."""
    h = (c[0] * 73856093) ^ (c[1] * 19349663) ^ (c[2] * 83492791)
    return h & mask


@ti.data_oriented
class HashGrid:
    """Spatial hash over ``capacity`` items.

    Fields:
        count: (table,) i32 items per bucket during build.
        start: (table + 1,) i32 first entry of each bucket in ``entries``.
        entries: (capacity,) i32 item ids sorted by bucket, then by id.
        item_cell: (capacity,) ivec3 cell coordinates of each item.
    """

    def __init__(self, capacity: int, cell: float) -> None:
        table = 1
        while table < 2 * capacity:
            table *= 2
        self.capacity = capacity
        self.table_size = table
        self.mask = table - 1
        self.cell = float(cell)
        self.inv_cell = 1.0 / float(cell)
        self.n_blocks = (table + _BLOCK - 1) // _BLOCK
        self.count = ti.field(ti.i32, shape=table)
        self.start = ti.field(ti.i32, shape=table + 1)
        self.block_sum = ti.field(ti.i32, shape=self.n_blocks + 1)
        self.entries = ti.field(ti.i32, shape=capacity)
        self.item_bucket = ti.field(ti.i32, shape=capacity)
        self.item_cell = ti.Vector.field(3, ti.i32, shape=capacity)

    @ti.func
    def _count(self, pts: ti.template(), offset: ti.i32, n: ti.i32, inv_cell: ti.f32, go: ti.i32):
        for b in range(go * self.table_size):
            self.count[b] = 0
        for k in range(go * n):
            c = cell_of(pts[offset + k], inv_cell)
            h = hash_cell(c, self.mask)
            self.item_cell[k] = c
            self.item_bucket[k] = h
            ti.atomic_add(self.count[h], 1)

    @ti.func
    def _scan(self, go: ti.i32):
        for blk in range(go * self.n_blocks):
            acc = 0
            for k in range(_BLOCK):
                b = blk * _BLOCK + k
                if b < self.table_size:
                    self.start[b] = acc
                    acc += self.count[b]
            self.block_sum[blk] = acc
        ti.loop_config(serialize=True)
        for blk in range(go):
            acc = 0
            for k in range(self.n_blocks):
                v = self.block_sum[k]
                self.block_sum[k] = acc
                acc += v
            self.block_sum[self.n_blocks] = acc
        for b in range(go * self.table_size):
            self.start[b] += self.block_sum[b // _BLOCK]
            self.count[b] = 0
        if go:
            self.start[self.table_size] = self.block_sum[self.n_blocks]

    @ti.func
    def _place(self, n: ti.i32, go: ti.i32):
        for k in range(go * n):
            h = self.item_bucket[k]
            slot = self.start[h] + ti.atomic_add(self.count[h], 1)
            self.entries[slot] = k
        for b in range(go * self.table_size):
            lo = self.start[b]
            hi = self.start[b + 1]
            for a in range(lo + 1, hi):
                v = self.entries[a]
                m = a - 1
                while m >= lo and self.entries[m] > v:
                    self.entries[m + 1] = self.entries[m]
                    m -= 1
                self.entries[m + 1] = v

    @ti.func
    def build_f(self, pts: ti.template(), offset: ti.i32, n: ti.i32):
        """Bin items ``pts[offset : offset + n]`` (ids relative to offset); Taichi scope."""
        self.build_if_f(pts, offset, n, 1)

    @ti.func
    def build_if_f(self, pts: ti.template(), offset: ti.i32, n: ti.i32, go: ti.i32):
        """``build_f`` if ``go`` is 1, nothing if 0 (a run-time choice inside a fused kernel).

        Every loop runs over ``go`` times its range, so it stays a parallel
        top-level loop and costs one empty launch when skipped.
        """
        self._count(pts, offset, n, self.inv_cell, go)
        self._scan(go)
        self._place(n, go)

    @ti.kernel
    def build(self, pts: ti.template(), offset: ti.i32, n: ti.i32):
        """Bin items ``pts[offset : offset + n]``; ids are relative to offset."""
        self.build_f(pts, offset, n)
