"""Strands: a whole rope or a run of its particles, named in levels as ``R`` or ``R[i0:i1]``.

A self-knot winds one part of a rope around another part of the same rope
(paper Fig. 3, top), so maneuvers and criteria that take ropes also take
strands: ``R[40:]`` is rope R from particle 40 to its end, ``R[:-30]`` all
but its last 30 particles (Python slice rules, step 1, end exclusive).
"""

from __future__ import annotations

import dataclasses
import re

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


def base_name(ref: str) -> str:
    """The rope a strand belongs to: ``"R[3:9]"`` -> ``"R"`` (a plain name is returned as is)."""
    return ref.split("[", 1)[0].strip()


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
