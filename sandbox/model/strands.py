"""Strands: a rope, a run of its particles, or a line of a cloth's particles.

A self-knot winds one part of a rope around another part of the same rope
(paper Fig. 3, top), and a furoshiki knots two control lines of one cloth
(paper §5.2), so maneuvers and criteria that take ropes also take strands:

- ``R``: rope R; ``R[40:]`` is rope R from particle 40 to its end, ``R[:-30]``
  all but its last 30 particles (Python slice rules, step 1, end exclusive);
- ``F.line1`` ... ``F.line4``: control line 1-4 of cloth F, from its centre
  to corner A-D (SPEC §6);
- ``F.P..Q``: the straight line of cloth F's particles from point P to point
  Q, each a corner ``A``-``D``, ``center`` or a grid point ``[i, j]``
  (e.g. ``F.[3,4]..center``).

A ``Strand`` is the one shape maneuvers see: its particles in order, the
whole line it is part of (positions along that line are the distances in
rods that reach rules use), its rest spacing and radius. Only its particles
are driven; the rest of a cloth is passive.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

_STRAND = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_\-]*)\s*(?:\[\s*(-?\d*)\s*:\s*(-?\d*)\s*\])?\s*$")


def parse_strand(ref: str) -> tuple[str, int | None, int | None]:
    """Split ``"R[i0:i1]"`` into ``("R", i0, i1)`` (None where a bound is left out).

    Raises:
        ValueError: if ``ref`` is not a name, optionally followed by ``[i0:i1]``.
    """
    m = _STRAND.match(ref) if isinstance(ref, str) else None
    if m is None:
        raise ValueError(f"bad strand {ref!r}: expected a rope name, optionally with a particle range "
                         "such as 'R[10:40]', 'R[40:]' or 'R[:-5]'")
    name, lo, hi = m.groups()
    return name, (int(lo) if lo else None), (int(hi) if hi else None)


_CLOTH_LINE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_\-]*)\s*\.\s*(.*?)\s*$")
_POINT = re.compile(r"^(A|B|C|D|center|\[\s*-?\d+\s*,\s*-?\d+\s*\])$")
_CORNER_OF_LINE = {f"line{k}": "ABCD"[k - 1] for k in (1, 2, 3, 4)}


def _point(text: str):
    text = text.strip()
    if not _POINT.match(text):
        raise ValueError(f"bad cloth point {text!r}: expected a corner A-D, 'center' or a grid point '[i, j]'")
    if text.startswith("["):
        return [int(v) for v in text[1:-1].split(",")]
    return text


def parse_cloth_line(ref: str):
    """Split ``"F.line2"`` into ``("F", "center", "B")`` and ``"F.P..Q"`` into ``("F", P, Q)``; None for a rope strand.

    Raises:
        ValueError: a ``F.`` form whose line is neither ``line1``-``line4`` nor ``P..Q``.
    """
    m = _CLOTH_LINE.match(ref) if isinstance(ref, str) and "." in ref else None
    if m is None:
        return None
    cloth, line = m.groups()
    if line in _CORNER_OF_LINE:
        return cloth, "center", _CORNER_OF_LINE[line]
    if ".." in line:
        p, q = line.split("..", 1)
        return cloth, _point(p), _point(q)
    raise ValueError(f"bad cloth line {ref!r}: expected '{cloth}.line1' ... '{cloth}.line4' (a control line) or "
                     f"'{cloth}.P..Q' with P, Q a corner A-D, 'center' or '[i, j]'")


def names_strand_of(name: str, ropes, cloths) -> bool:
    """Whether ``name`` is a rope of ``ropes``, a strand ``R[i0:i1]`` of one, or a cloth line of a cloth of
    ``cloths`` (its form only: the grid points of ``F.P..Q`` are checked where the cloth's size is known)."""
    try:
        line = parse_cloth_line(name)
        return parse_strand(name)[0] in ropes if line is None else line[0] in cloths
    except ValueError:
        return False


def joined_at_centre(names: list[str], curves: list[np.ndarray]) -> list[np.ndarray]:
    """Two lines of one cloth that start at the same particle (its centre) as one curve through it.

    Where they meet is their join, not a knot: measured as one curve, the
    touches skip parts of it less than half a turn apart. Other names (ropes,
    lines of two cloths, one name) are returned as they are.
    """
    if len(names) != 2:
        return curves
    lines = [parse_cloth_line(n) for n in names]
    if None in lines or lines[0][0] != lines[1][0] or not np.array_equal(curves[0][0], curves[1][0]):
        return curves
    return [np.vstack([curves[0][::-1], curves[1][1:]])]


def base_name(ref: str) -> str:
    """The rope or cloth a strand belongs to: ``"R[3:9]"`` -> ``"R"``, ``"F.line1"`` -> ``"F"``."""
    return re.split(r"[\[.]", ref, maxsplit=1)[0].strip()


@dataclasses.dataclass(frozen=True, eq=False)
class Strand:
    """Particles that a maneuver treats as one strand, in order along it.

    Attributes:
        name: as the level names it (``R``, ``R[3:9]``, ``F.line1``).
        body: the rope or cloth it belongs to.
        idx: ``(k,)`` global particle indices, in order.
        line: ``(m,)`` global indices of the whole line it is part of (the
            whole rope, or the cloth line itself), in order; ``idx`` is a
            contiguous run of it.
        rest: ``(m - 1,)`` rest distances between consecutive particles of ``line``, m.
        radius: m; for a cloth line, half the cloth's thickness (one layer;
            ``gathered_radius`` measures the cloth bundled around it).
        cloth: True for a line of a cloth.
        rest_pos: ``(m, 3)`` rest positions of ``line``'s particles, m.
    """

    name: str
    body: str
    idx: np.ndarray
    line: np.ndarray
    rest: np.ndarray
    radius: float
    cloth: bool = False
    rest_pos: np.ndarray | None = None

    def __post_init__(self) -> None:
        pos = {int(g): i for i, g in enumerate(self.line)}
        object.__setattr__(self, "_pos", pos)
        object.__setattr__(self, "_first", pos[int(self.idx[0])])
        # A rope's line is a run of consecutive indices: positions are differences, no lookups.
        run = len(self.line) < 2 or bool(np.all(np.diff(self.line) == 1))
        object.__setattr__(self, "_base", int(self.line[0]) if run else None)

    def __len__(self) -> int:
        return len(self.idx)

    @property
    def rod_length(self) -> float:
        """Mean rest distance between consecutive particles, m."""
        return float(self.rest.mean()) if len(self.rest) else 0.0

    def along(self, g):
        """Position (in particles) of global index/indices ``g`` along the whole line."""
        if self._base is not None:
            if np.ndim(g) == 0:
                return int(g) - self._base
            return np.asarray(g, dtype=np.int64) - self._base
        if np.ndim(g) == 0:
            return self._pos[int(g)]
        return np.array([self._pos[int(v)] for v in np.ravel(g)], dtype=np.int64).reshape(np.shape(g))

    def local(self, g):
        """Position of global index/indices ``g`` within ``idx``."""
        return self.along(g) - self._first

    def has(self, g: int) -> bool:
        """Whether global particle ``g`` is one of this strand's."""
        i = self._pos.get(int(g))
        return i is not None and 0 <= i - self._first < len(self.idx)

    def at_along(self, i) -> np.ndarray:
        """Global index of the whole line's particle(s) at position(s) ``i``."""
        return self.line[np.asarray(i, dtype=np.int64)]

    def part(self, lo: int, hi: int) -> "Strand":
        """The strand's particles at whole-line positions [lo, hi] (clipped to it)."""
        a = max(int(lo), self._first)
        b = min(int(hi), self._first + len(self.idx) - 1)
        return dataclasses.replace(self, idx=self.line[a:b + 1])

    def whole(self) -> "Strand":
        """The whole line (rope) this strand is part of."""
        return dataclasses.replace(self, name=self.body if not self.cloth else self.name, idx=self.line)

    def rest_of(self, g) -> np.ndarray:
        """Rest positions of global particle(s) ``g`` of the whole line, m."""
        return self.rest_pos[self.along(g)]

    def strain(self, x: np.ndarray) -> np.ndarray:
        """Relative stretch of each gap between consecutive particles of ``idx`` at positions ``x`` (all particles)."""
        seg = np.linalg.norm(np.diff(x[self.idx], axis=0), axis=1)
        return seg / self.rest[self._first:self._first + len(self.idx) - 1] - 1.0


def rope_strand(rope, whole) -> Strand:
    """The ``Strand`` of a ``RopeRange`` ``rope`` that is part of rope ``whole`` (itself, or the rope it is a run of)."""
    line = np.arange(whole.start, whole.end)
    rest = np.full(len(line) - 1, whole.rod_length)
    along = np.concatenate([[0.0], np.cumsum(rest)])
    return Strand(name=rope.name, body=whole.name, idx=np.arange(rope.start, rope.end), line=line,
                  rest=rest, radius=rope.radius, rest_pos=np.stack([along, 0 * along, 0 * along], axis=1))


def cloth_strand(name: str, cloth, x0: np.ndarray) -> Strand:
    """The ``Strand`` that cloth line ``name`` (``F.line1``, ``F.P..Q``) names on ``ClothRange`` ``cloth``.

    ``x0``: rest positions of all particles (the line's rest spacing).
    """
    _, p, q = parse_cloth_line(name)
    line = cloth.line_between(p, q)
    rest = np.linalg.norm(np.diff(x0[line], axis=0), axis=1)
    return Strand(name=name, body=cloth.name, idx=line, line=line, rest=rest, radius=0.5 * cloth.thickness,
                  cloth=True, rest_pos=x0[line].astype(np.float64))


def material_distance(a: Strand, b: Strand, ga: np.ndarray, gb: np.ndarray) -> np.ndarray | None:
    """Distance in the material (m) between particles ``ga`` of strand ``a`` and ``gb`` of ``b``, ``(len(ga), len(gb))``.

    Along the rope for two strands of one rope; at rest, across the cloth,
    for two lines of one cloth (which meet at its centre). None for
    different bodies: nothing joins them.
    """
    if a.body != b.body:
        return None
    pa, pb = a.rest_of(ga), b.rest_of(gb)
    if not a.cloth:  # a rope's rest positions are laid out along x: the distance along the rope
        return np.abs(pa[:, None, 0] - pb[None, :, 0])
    return np.linalg.norm(pa[:, None, :] - pb[None, :, :], axis=2)


def gathered_radius(x: np.ndarray, strand: Strand, cloth, x0: np.ndarray, around: np.ndarray, length: float) -> float:
    """Radius of the cloth gathered around cloth line ``strand`` over ``length`` m of it about point ``around``.

    The cloth belonging to the line is the cloth's particles nearer to it
    than to the other control lines at rest (for a control line: its
    quadrant's half on its side; for a ``P..Q`` line: the particles within a
    quarter of the line's rest length of it); of those whose nearest point
    on the line lies within ``length`` / 2 of ``around`` (along the line),
    both now and at rest (cloth beside this part of the line in space but
    far from it in the material is not gathered here), the radius is the
    90th percentile of their distances to the line,
    plus half the thickness: the bounding tube of the bundle (paper §5.2).
    A flat, ungathered cloth gives the size of its flap; a tight roll, the roll's.
    O(n_cloth x k_line).
    """
    from sandbox.geometry.mesh_geodesic import polyline_distance

    gi = np.arange(cloth.start, cloth.end)
    rest_d, rest_s = polyline_distance(x0[gi], x0[strand.line], with_arc=True)
    others = [cloth.control_line(k) for k in (1, 2, 3, 4)]
    is_control = any(len(o) == len(strand.line) and np.array_equal(o, strand.line) for o in others)
    if is_control:
        other_d = np.min([polyline_distance(x0[gi], x0[o]) for o in others
                          if not (len(o) == len(strand.line) and np.array_equal(o, strand.line))], axis=0)
        mine = rest_d <= other_d + 1e-9
    else:
        mine = rest_d <= 0.25 * float(strand.rest.sum())
    pts = x[gi[mine]].astype(np.float64)
    line = x[strand.line].astype(np.float64)
    d, s = polyline_distance(pts, line, with_arc=True)
    s0 = polyline_distance(np.asarray(around, float), line, with_arc=True)[1][0]
    # Near ``around`` now and in the material: cloth of the line's other
    # parts that lies beside this one (a flap of the same line folded back
    # over the object) is not gathered here.
    s_rest = rest_s[mine]
    rest_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(x0[strand.line], axis=0), axis=1))])
    k0 = int(np.argmin(np.linalg.norm(line - np.asarray(around, float), axis=1)))
    near = (np.abs(s - s0) <= 0.5 * length) & (np.abs(s_rest - rest_arc[k0]) <= 0.5 * length)
    if not near.any():
        return strand.radius
    return float(np.percentile(d[near], 90.0)) + strand.radius


def strand_range(rope, ref: str):
    """The part of ``rope`` (a ``RopeRange``) that ``ref`` names, as a ``RopeRange`` named ``ref``.

    Raises:
        ValueError: if the range is empty or has fewer than two particles.
    """
    _, lo, hi = parse_strand(ref)
    k = rope.end - rope.start
    a, b, _ = slice(lo, hi).indices(k)
    if b - a < 2:
        raise ValueError(f"strand {ref!r} has {max(b - a, 0)} particles; rope {rope.name!r} has {k} "
                         "(a strand needs at least 2)")
    return dataclasses.replace(rope, name=ref, start=rope.start + a, end=rope.start + b)


def rope_site_span(name: str, k: int, site) -> tuple[int, int]:
    """The particles ``[lo, hi)`` that a site of a rope or strand of ``k`` particles names: ``start``, ``end``,
    ``all``, an index (negative counts from the end) or ``[i0, i1]`` (end exclusive).

    Raises:
        ValueError: an index or range outside the rope, naming what is allowed.
    """
    if site == "start":
        return 0, 1
    if site == "end":
        return k - 1, k
    if site == "all":
        return 0, k
    if isinstance(site, (list, tuple)) and len(site) == 2:
        lo, hi = (int(s) % (k + 1) if int(s) < 0 else int(s) for s in site)
        if not 0 <= lo < hi <= k:
            raise ValueError(f"rope {name!r}: range {list(site)} not inside [0, {k}]")
        return lo, hi
    i = int(site)
    if not -k <= i < k:
        raise ValueError(f"rope {name!r}: index {i} outside [-{k}, {k - 1}]")
    return i % k, i % k + 1
