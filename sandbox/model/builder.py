"""Build the static particle model of a scene from its rope and cloth specs.

All ropes and cloths share one particle array, so that one set of kernels
serves the whole scene. The builder works in NumPy; ``finalize`` uploads the
arrays into a :class:`~sandbox.model.model.Model`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sandbox.model.pose import euler_matrix

# Edge kinds (one field per edge): distance constraints of different meaning.
STRETCH, SHEAR, BEND = 0, 1, 2
CORNERS = ("A", "B", "C", "D")


@dataclass
class RopeRange:
    """Where a rope lives in the particle array."""

    name: str
    start: int
    end: int  # exclusive
    rod_length: float  # m
    radius: float  # m
    color: tuple[float, float, float]
    stretch_compliance: float = 0.0  # m/N; 0 = inextensible (paper Eq. 2)


@dataclass
class ClothRange:
    """Where a cloth lives in the particle array (grid index j * nx + i)."""

    name: str
    start: int
    nx: int
    nz: int
    spacing: tuple[float, float]  # m, along x and z
    thickness: float  # m, collision thickness
    faces: np.ndarray  # (m, 3) int32, local particle indices
    color: tuple[float, float, float]
    back_color: tuple[float, float, float]
    self_collision: bool
    stretch_compliance: float = 0.0  # m/N; 0 = rows and columns are exact chains
    medial_lines: tuple = ()  # particle indices of each line of the medial sheet (empty: none)
    level_grid: tuple[int, int] | None = None  # the level's [nx, nz] where the simulated grid is coarser

    @property
    def end(self) -> int:
        return self.start + self.nx * self.nz

    def index(self, i: int, j: int) -> int:
        """Global particle index of grid point (i, j)."""
        return self.start + j * self.nx + i

    def grid_of(self, name) -> tuple[int, int]:
        """Grid coordinates (i, j) of a cloth site: corner A-D, 'center' or [i, j]."""
        if isinstance(name, (list, tuple)):
            i, j = int(name[0]), int(name[1])
            nx, nz = self.level_grid or (self.nx, self.nz)
            if not (0 <= i < nx and 0 <= j < nz):
                raise ValueError(f"cloth {self.name!r}: grid index {[i, j]} outside [0,{nx - 1}]x[0,{nz - 1}]")
            if self.level_grid is not None:  # the level's grid point nearest on the coarser simulated grid
                i = int(np.floor(i * (self.nx - 1) / (nx - 1) + 0.5))
                j = int(np.floor(j * (self.nz - 1) / (nz - 1) + 0.5))
            return i, j
        corners = {"A": (0, 0), "B": (0, self.nz - 1), "C": (self.nx - 1, self.nz - 1), "D": (self.nx - 1, 0)}
        if name in corners:
            return corners[name]
        if name == "center":
            return self.nx // 2, self.nz // 2
        raise ValueError(f"cloth {self.name!r}: unknown site {name!r}; allowed: A, B, C, D, center or [i, j]")

    def site(self, name) -> int:
        """Global particle index of a cloth site: corner A-D, 'center' or [i, j]."""
        return self.index(*self.grid_of(name))

    def line_between(self, p, q) -> np.ndarray:
        """Global indices of the straight chain of particles from site p to site q (both included).

        One particle per step along the longer grid axis, the other rounded:
        rows, columns and diagonals are exact grid lines.
        """
        (i0, j0), (i1, j1) = self.grid_of(p), self.grid_of(q)
        steps = max(abs(i1 - i0), abs(j1 - j0))
        if steps == 0 and self.level_grid is not None and p != q:
            raise ValueError(f"cloth {self.name!r}: the line from {p!r} to {q!r} is shorter than one spacing of the "
                             f"{self.nx} x {self.nz} grid the interactive tier simulates it on; run it accurate "
                             f"(sim.tier: accurate) or draw the line between points further apart")
        if steps == 0:
            raise ValueError(f"cloth {self.name!r}: a control line needs two different points, got {p!r} twice")
        t = np.linspace(0.0, 1.0, steps + 1)
        ii = np.rint(i0 + t * (i1 - i0)).astype(int)
        jj = np.rint(j0 + t * (j1 - j0)).astype(int)
        return self.start + jj * self.nx + ii

    def control_line(self, k: int) -> np.ndarray:
        """Global indices of control line k (1-4): centre to corner A-D (SPEC §6)."""
        if k not in (1, 2, 3, 4):
            raise ValueError(f"control line {k} not allowed; allowed: 1, 2, 3, 4")
        return self.line_between("center", "ABCD"[k - 1])

    def area(self, name: str) -> np.ndarray:
        """Global indices of area a-d: the quadrant of the grid that holds corner A-D (SPEC §6).

        The quadrants share the centre row and column.
        """
        if name not in ("a", "b", "c", "d"):
            raise ValueError(f"cloth {self.name!r}: unknown area {name!r}; allowed: a, b, c, d")
        ci, cj = self.nx // 2, self.nz // 2
        ai, aj = self.grid_of(name.upper())
        ii = np.arange(min(ai, ci), max(ai, ci) + 1)
        jj = np.arange(min(aj, cj), max(aj, cj) + 1)
        return self.start + (jj[:, None] * self.nx + ii[None, :]).ravel()


@dataclass
class ModelData:
    """Static arrays of a scene, before upload (all float64/int64 NumPy)."""

    x0: np.ndarray  # (n, 3) m, rest positions
    inv_mass: np.ndarray  # (n,) 1/kg
    radius: np.ndarray  # (n,) m, collision radius
    friction: np.ndarray  # (n,)
    damping: np.ndarray  # (n,) per-second velocity damping fraction
    cloth_id: np.ndarray  # (n,) -1 for rope particles
    grid_ij: np.ndarray  # (n, 2) cloth grid coordinates (0 for ropes)
    edges: np.ndarray  # (m, 2) particle pairs, sorted by colour
    rest: np.ndarray  # (m,) m
    compliance: np.ndarray  # (m,) m/N
    kind: np.ndarray  # (m,) STRETCH | SHEAR | BEND
    group: np.ndarray  # (m,) body index (ropes first, then cloths)
    colors: list[tuple[int, int]]  # edge ranges [start, end) of each colour (solved edges only)
    segments: np.ndarray  # (s, 2) rope segments (consecutive particles)
    segment_rope: np.ndarray  # (s,) rope index of each segment
    pins: np.ndarray  # (p,) particle indices pinned at build
    ropes: list[RopeRange] = field(default_factory=list)
    cloths: list[ClothRange] = field(default_factory=list)

    @property
    def n_particles(self) -> int:
        return len(self.x0)


def coarse_grid(nx: int, nz: int, max_particles: int | None) -> tuple[int, int]:
    """The grid a cloth of ``nx`` x ``nz`` particles is simulated on with at most ``max_particles``.

    The level's own grid where it is small enough (or None); otherwise the finest grid whose
    spacing is the same multiple f of the level's along both axes, (nx - 1) / f + 1 and
    (nz - 1) / f + 1 rounded, that fits, an odd count kept odd (a middle row and column for "center"
    and the control lines): 163 x 163 becomes 69 x 69 within 5,000.
    """
    if max_particles is None or nx * nz <= max_particles:
        return nx, nz

    def count(n: int, f: float) -> int:
        c = max(2, int(round((n - 1) / f)) + 1)
        if n % 2 == 1 and c % 2 == 0 and c > 2:
            c -= 1  # an odd count keeps the middle row: "center" and the control lines stay symmetric
        return c

    f = float(np.sqrt(nx * nz / max_particles))
    while True:
        cx, cz = count(nx, f), count(nz, f)
        if cx * cz <= max_particles or (cx, cz) == (2, 2):
            return cx, cz
        f *= 1.01


def resample_polyline(points: np.ndarray, *, segments: int | None, rod_length: float | None) -> tuple[np.ndarray, float]:
    """Particles evenly spaced by arc length along a polyline.

    Returns:
        (particles (k+1, 3), rod length r). With ``rod_length`` given, the
        rope is as long as the polyline rounded to a whole number of rods.
    """
    pts = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    total = float(seg.sum())
    if total <= 0.0:
        raise ValueError("rope polyline has zero length")
    if segments is None:
        segments = max(1, int(round(total / float(rod_length))))
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, total, segments + 1)
    out = np.stack([np.interp(t, s, pts[:, k]) for k in range(3)], axis=1)
    # Polyline corners shorten chords slightly: use the actual mean chord.
    r = float(np.linalg.norm(np.diff(out, axis=0), axis=1).mean())
    return out, r


def greedy_edge_colors(edges: np.ndarray, n: int) -> np.ndarray:
    """Colour edges so that no two edges of a colour share a particle.

    Deterministic greedy colouring in edge order; a regular grid with its
    shear and bending edges needs 12 colours. O(m) with small constant.
    """
    used = [0] * n
    colors = np.empty(len(edges), dtype=np.int64)
    for k, (a, b) in enumerate(edges.tolist()):
        mask = used[a] | used[b]
        c = 0
        while mask >> c & 1:
            c += 1
        colors[k] = c
        used[a] |= 1 << c
        used[b] |= 1 << c
    return colors


class ModelBuilder:
    """Accumulates ropes and cloths into one particle model."""

    def __init__(self) -> None:
        self._x: list[np.ndarray] = []
        self._w: list[np.ndarray] = []
        self._rad: list[np.ndarray] = []
        self._fric: list[np.ndarray] = []
        self._damp: list[np.ndarray] = []
        self._cid: list[np.ndarray] = []
        self._ij: list[np.ndarray] = []
        self._edges: list[np.ndarray] = []
        self._rest: list[np.ndarray] = []
        self._comp: list[np.ndarray] = []
        self._kind: list[np.ndarray] = []
        self._solve: list[np.ndarray] = []
        self._group: list[np.ndarray] = []
        self._segments: list[np.ndarray] = []
        self._seg_rope: list[np.ndarray] = []
        self._pins: list[int] = []
        self.ropes: list[RopeRange] = []
        self.cloths: list[ClothRange] = []
        self.n = 0
        self._bodies = 0

    def _add_edges(self, e, rest, comp, kind):
        # Stretch edges of inextensible bodies are solved exactly as chains
        # (sandbox.solvers.rope_chain); they stay here for strain metrics only.
        self._solve.append(np.full(len(e), not (kind == STRETCH and comp == 0.0)))
        self._edges.append(e)
        self._rest.append(rest)
        self._comp.append(np.full(len(e), comp, dtype=np.float64))
        self._kind.append(np.full(len(e), kind, dtype=np.int64))
        self._group.append(np.full(len(e), self._bodies, dtype=np.int64))

    def add_rope(self, spec) -> RopeRange:
        """Add a rope (``RopeSpec``): rods (Eq. 2), skip-one bending (Eq. 3), capsules."""
        x, r = resample_polyline(np.asarray(spec.points, float), segments=spec.segments, rod_length=spec.rod_length)
        k = len(x)
        start = self.n
        idx = np.arange(start, start + k)
        self._x.append(x)
        self._w.append(np.full(k, k / spec.mass))
        self._rad.append(np.full(k, spec.radius))
        self._fric.append(np.full(k, spec.friction))
        self._damp.append(np.full(k, spec.damping))
        self._cid.append(np.full(k, -1))
        self._ij.append(np.zeros((k, 2), dtype=np.int64))
        rods = np.stack([idx[:-1], idx[1:]], axis=1)
        self._add_edges(rods, np.linalg.norm(x[1:] - x[:-1], axis=1), spec.stretch_compliance, STRETCH)
        if k >= 3:
            bends = np.stack([idx[:-2], idx[2:]], axis=1)
            self._add_edges(bends, np.full(k - 2, 2.0 * r), spec.bend_compliance, BEND)
        self._segments.append(rods)
        self._seg_rope.append(np.full(k - 1, len(self.ropes)))
        rope = RopeRange(spec.name, start, start + k, r, float(spec.radius), tuple(spec.color), float(spec.stretch_compliance))
        for pin in spec.pins:
            if pin == "start":
                self._pins.append(start)
            elif pin == "end":
                self._pins.append(start + k - 1)
            else:
                p = int(pin)
                if not -k <= p < k:
                    raise ValueError(f"rope {spec.name!r}: pin index {p} outside [-{k}, {k - 1}]")
                self._pins.append(start + (p % k))
        self.ropes.append(rope)
        self.n += k
        self._bodies += 1
        return rope

    def add_cloth(self, spec, max_particles: int | None = None) -> ClothRange:
        """Add a horizontal cloth grid (``ClothSpec``): structural, shear, bending edges.

        With ``max_particles``, a cloth of more particles is simulated on a coarser grid of the
        same size and proportions (``coarse_grid``); its ``[i, j]`` sites name the level's grid and
        are taken to the nearest point of the simulated one.
        """
        level_nx, level_nz = int(spec.resolution[0]), int(spec.resolution[1])
        nx, nz = coarse_grid(level_nx, level_nz, max_particles)
        w, d = float(spec.size[0]), float(spec.size[1])
        dx, dz = w / (nx - 1), d / (nz - 1)
        ii, jj = np.meshgrid(np.arange(nx), np.arange(nz))  # (nz, nx): row j, column i
        ii, jj = ii.ravel(), jj.ravel()
        c = np.asarray(spec.center, float)
        x = np.stack([c[0] - w / 2 + ii * dx, np.full(ii.shape, c[1]), c[2] - d / 2 + jj * dz], axis=1)
        if spec.yaw:  # turned about the vertical through the centre
            x = (x - c) @ euler_matrix([0.0, float(spec.yaw), 0.0]).T + c
        k = nx * nz
        start = self.n
        thickness = float(spec.thickness) if spec.thickness is not None else 1.5 * min(dx, dz)

        def gid(i, j):
            return start + j * nx + i

        self._x.append(x)
        self._w.append(np.full(k, k / spec.mass))
        self._rad.append(np.full(k, 0.5 * thickness))
        self._fric.append(np.full(k, spec.friction))
        self._damp.append(np.full(k, spec.damping))
        self._cid.append(np.full(k, len(self.cloths)))
        self._ij.append(np.stack([ii, jj], axis=1))
        I, J = np.meshgrid(np.arange(nx), np.arange(nz), indexing="ij")

        def pairs(di, dj):
            m = (I + di < nx) & (J + dj < nz) & (I + di >= 0)
            a = gid(I[m], J[m])
            b = gid(I[m] + di, J[m] + dj)
            e = np.stack([a, b], axis=1)
            return e, np.linalg.norm(x[b - start] - x[a - start], axis=1)

        for di, dj in ((1, 0), (0, 1)):
            e, rest = pairs(di, dj)
            self._add_edges(e, rest, spec.stretch_compliance, STRETCH)
        for di, dj in ((1, 1), (-1, 1)):
            e, rest = pairs(di, dj)
            self._add_edges(e, rest, spec.shear_compliance, SHEAR)
        for di, dj in ((2, 0), (0, 2)):
            e, rest = pairs(di, dj)
            self._add_edges(e, rest, spec.bend_compliance, BEND)
        a = (J[:-1, :-1] * nx + I[:-1, :-1]).ravel()
        faces = np.concatenate(
            [np.stack([a, a + nx, a + 1], axis=1), np.stack([a + 1, a + nx, a + nx + 1], axis=1)]
        ).astype(np.int32)
        cloth = ClothRange(
            spec.name, start, nx, nz, (dx, dz), thickness, faces, tuple(spec.color), tuple(spec.back_color),
            bool(spec.self_collision), float(spec.stretch_compliance),
            level_grid=None if (nx, nz) == (level_nx, level_nz) else (level_nx, level_nz),
        )
        cloth.medial_lines = tuple(cloth.control_line(ln) if isinstance(ln, int) else cloth.line_between(*ln)
                                   for ln in getattr(spec, "medial_sheet", ()))
        self._pins.extend(cloth.site(p) for p in spec.pins)
        self.cloths.append(cloth)
        self.n += k
        self._bodies += 1
        return cloth

    def finalize_data(self) -> ModelData:
        """Concatenate, colour and sort the constraints; returns NumPy data."""
        if self.n == 0:
            raise ValueError("the scene has no rope and no cloth: nothing to simulate")
        edges = np.concatenate(self._edges) if self._edges else np.zeros((0, 2), np.int64)
        rest = np.concatenate(self._rest) if self._rest else np.zeros(0)
        comp = np.concatenate(self._comp) if self._comp else np.zeros(0)
        kind = np.concatenate(self._kind) if self._kind else np.zeros(0, np.int64)
        group = np.concatenate(self._group) if self._group else np.zeros(0, np.int64)
        solve = np.concatenate(self._solve) if self._solve else np.zeros(0, bool)
        col = np.full(len(edges), -1, np.int64)
        if solve.any():
            col[solve] = greedy_edge_colors(edges[solve], self.n)
        n_colors = int(col.max()) + 1 if len(col) else 0
        col[~solve] = n_colors  # metric-only edges sort last, outside every colour
        order = np.argsort(col, kind="stable")
        ranges = []
        counts = np.bincount(col, minlength=n_colors + 1)
        s = 0
        for c in counts[:n_colors]:
            ranges.append((s, s + int(c)))
            s += int(c)
        segs = np.concatenate(self._segments) if self._segments else np.zeros((0, 2), np.int64)
        seg_rope = np.concatenate(self._seg_rope) if self._seg_rope else np.zeros(0, np.int64)
        return ModelData(
            x0=np.concatenate(self._x),
            inv_mass=np.concatenate(self._w),
            radius=np.concatenate(self._rad),
            friction=np.concatenate(self._fric),
            damping=np.concatenate(self._damp),
            cloth_id=np.concatenate(self._cid),
            grid_ij=np.concatenate(self._ij),
            edges=edges[order],
            rest=rest[order],
            compliance=comp[order],
            kind=kind[order],
            group=group[order],
            colors=ranges,
            segments=segs,
            segment_rope=seg_rope,
            pins=np.unique(np.asarray(self._pins, dtype=np.int64)),
            ropes=self.ropes,
            cloths=self.cloths,
        )
