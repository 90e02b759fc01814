"""Crossing, and the strand geometry that knots share (paper §4, §4.1).

A knot is crossings and windings repeated (paper Fig. 3): ``Crossing`` lifts
two strands and brings them across each other at a point X above the middle
of their constrained bottom points; ``Winding`` (``winding.py``) winds one
around the other from X; ``Tightening`` (``tightening.py``) pulls the ends
apart until the knot is tight. Strands are ropes, runs of one rope
(``R[i0:i1]``) or lines of a cloth (``F.line1``; ``sandbox.model.strands``),
so the same steps tie a self-knot (one rope crossed with itself) and knots
between two ropes or two control lines.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

import numpy as np
import pydantic

from sandbox.maneuvers.base import Maneuver, Params, Status, register
from sandbox.maneuvers.basic import Target, TargetLike, resolve_target
from sandbox.model.strands import Strand, material_distance, parse_cloth_line, parse_strand

Site = Union[str, int]
Vec3 = tuple[float, float, float]
_UP = np.array([0.0, 1.0, 0.0])
CROSS_SETTLE_FRAMES = 20
"""Frames a Crossing waits, its tips arrived, for the strands to settle before it moves the tips again."""
X_REACH = 0.8
"""Most of its reach a strand spends from its bottom to the crossing X: the rest carries it on beyond X."""
MAX_REPLANS = 4
"""Times a Crossing whose strands pass too far apart moves its tips again, toward closing that miss."""
TAUT_STRAIN = 0.02
"""Rod strain of a strand at which the hand on its tip stops advancing: the reach a Crossing plans with is a
straight line from each hold, and a strand that leaves an object under it (a cloth strip from under the box
set on it) goes round the object's edge, with less reach than that."""


def _unit(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-9 else fallback


def _flat(v: np.ndarray) -> np.ndarray:
    """``v`` with its vertical component removed."""
    return np.array([v[0], 0.0, v[2]])


def _other_end(site: Site) -> Site:
    return {"end": "start", "start": "end", -1: 0, 0: -1}.get(site, "start")


def crossing_targets(base_c, base_t, len_c, len_t, *, height, sign, gap, slack=0.9, elevation=45.0, across=None):
    """Where the tips go so that strands C and T cross at X (paper §4.1, Fig. 4).

    X sits above the midpoint of the two bottom points at ``height``, or
    nearer the bottoms where a strand's rope could not reach it: no further
    from either bottom than ``X_REACH`` of its reach (``slack`` of the rope
    between bottom and tip; a short tail left by a first half knot crosses
    lower). In the
    frame x (horizontal, from C's bottom towards T's), y (up), z = x cross y,
    C passes X at +z * sign * gap / 2 and T at -z * sign * gap / 2; beyond X
    each strand rises at ``elevation`` degrees towards the other's side, so
    that their projections on the x-y plane cross at X. The tips are placed
    so that the straight distance from bottom to tip is ``slack`` of the rope
    between them.

    Args:
        base_c, base_t: ``(3,)`` bottom points of C and T, m.
        len_c, len_t: rope length from each bottom point to its tip, m.
        height: X above the bottoms' midpoint, m.
        sign: +1 (C in front, on +z) or -1.
        gap: separation of the strands at X, m.
        slack: bottom-to-tip distance over the strand length.
        elevation: angle of the strands above the horizontal beyond X, degrees.
        across: ``(3,)`` horizontal direction of x, used instead of the bottoms'
            when they nearly coincide (two strands that leave one knot).

    Returns:
        ``(X, tip_c, tip_t, xhat, zhat)``, each ``(3,)``.
    """
    base_c, base_t = np.asarray(base_c, float), np.asarray(base_t, float)
    d = base_t - base_c if across is None else np.asarray(across, float).copy()
    d[1] = 0.0
    xhat = _unit(d, np.array([1.0, 0.0, 0.0]))
    zhat = np.cross(xhat, _UP)
    x = 0.5 * (base_c + base_t) + height * _UP
    for _ in range(16):  # alternate projections onto the two balls of reach (the nearest point of the second
        x = _within(_within(x, base_c, X_REACH * slack * len_c), base_t, X_REACH * slack * len_t)  # where apart)
    el = np.radians(elevation)
    out = []
    for base, length, side, s in ((base_c, len_c, 1.0, sign), (base_t, len_t, -1.0, -sign)):
        through = x + s * 0.5 * gap * zhat
        rise = side * np.cos(el) * xhat + np.sin(el) * _UP
        reach = max(slack * length - float(np.linalg.norm(through - base)), 0.1 * length)
        out.append(through + reach * rise)
    return x, out[0], out[1], xhat, zhat


def closest_approach(xc: np.ndarray, xt: np.ndarray, apart: np.ndarray | None = None):
    """Where two strands pass closest: ``(distance, index on C, index on T)``.

    ``apart``: ``(len(xc), len(xt))`` bool, the pairs that may count (None: all);
    pairs of one rope or cloth that are the same bend are left out by it.
    """
    d = np.linalg.norm(xc[:, None, :] - xt[None, :, :], axis=2)
    if apart is not None:
        d = np.where(apart, d, np.inf)
    i, j = np.unravel_index(int(np.argmin(d)), d.shape)
    return float(d[i, j]), int(i), int(j)


def _same_bend(c: Strand, t: Strand) -> float:
    """Particles of one rope (or cloth) closer than this in the material are the same bend, not a crossing, m.

    Half a turn of the strands' bounding tube (radius 1.1 (r_C + r_T)) plus two rods.
    """
    rod = min(c.rod_length, t.rod_length)
    return (np.pi * 1.1 * (c.radius + t.radius) / rod + 2) * rod


def _apart(c: Strand, t: Strand, gc: np.ndarray, gt: np.ndarray) -> np.ndarray | None:
    """Pairs of particles ``gc`` of ``c`` and ``gt`` of ``t`` that are not the same bend (None: all are)."""
    m = material_distance(c, t, gc, gt)
    return None if m is None else m > _same_bend(c, t)


def strand_approach(x: np.ndarray, c: Strand, t: Strand):
    """``closest_approach`` of strands ``c`` and ``t`` in positions ``x``.

    Two strands of one rope (or two lines of one cloth, which meet at its
    centre) skip pairs within half a turn of their bounding tube (radius
    1.1 (r_C + r_T)) of each other in the material.
    """
    return closest_approach(x[c.idx], x[t.idx], _apart(c, t, c.idx, t.idx))


def knot_exit(x: np.ndarray, strand, others, toward: int, radii=None) -> int | None:
    """Global index of the particle of ``strand`` nearest particle ``toward`` that touches ``others``.

    Touching is being within 1.5 (r + r_other) of one of their particles
    (strands of the same rope skip the particle's own neighbourhood). This is
    where the strand leaves a knot on its way to ``toward`` (its tip); None
    when it touches none of them. ``radii``: r of ``strand`` and of each of
    ``others`` (default: their own radii; a cloth line's is its bundle's).
    """
    r = [s.radius for s in (strand, *others)] if radii is None else list(radii)
    xs = x[strand.idx]
    near = np.zeros(len(xs), bool)
    for o, r_o in zip(others, r[1:]):
        d = np.linalg.norm(xs[:, None, :] - x[o.idx][None, :, :], axis=2)
        apart = _apart(strand, o, strand.idx, o.idx)
        if apart is not None:
            d = np.where(apart, d, np.inf)
        near |= (d <= 1.5 * (r[0] + r_o)).any(axis=1)
    touching = np.flatnonzero(near)
    if not len(touching):
        return None
    return int(strand.idx[int(touching[np.argmin(np.abs(touching - strand.local(toward)))])])


def _between(strand: Strand, base: np.ndarray, tip: np.ndarray) -> Strand:
    """The part of ``strand`` from its bottom particles to its tip's, both included."""
    at = strand.along(np.concatenate([np.atleast_1d(base), np.atleast_1d(tip)]))
    return strand.part(int(at.min()), int(at.max()))


def _off_bottom(part: Strand, base: np.ndarray, other: Strand) -> Strand:
    """``part`` (from its bottom ``base`` to its tip) less the particles within the same bend of its bottom.

    Two strands whose bottoms touch (two cloth corners stood up side by side
    on an object, two ropes leaving one knot) pass closest there; the
    crossing is above, between the bottoms and the tips. At least two
    particles are kept, at the tip's end.
    """
    k = int(np.ceil(_same_bend(part, other) / max(part.rod_length, 1e-12)))
    lo = int(part.along(part.idx[0]))
    hi = lo + len(part) - 1
    b = float(np.mean(part.along(np.atleast_1d(base))))
    if abs(b - lo) <= abs(b - hi):
        return part.part(min(lo + k, hi - 1), hi)
    return part.part(lo, max(hi - k, lo + 1))


def _within(point: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """``point`` pulled back onto the ball around ``centre`` (a tip cannot go past its rope's reach)."""
    v = point - centre
    n = float(np.linalg.norm(v))
    return point if n <= radius else centre + v * (radius / n)


def rope_holds(world, strand: Strand, exclude) -> list[tuple[int, np.ndarray]]:
    """Particles of the whole line under ``strand`` (its rope, or its cloth line) held by a hand now, but not in
    ``exclude``: (position along the line, command)."""
    idx = strand.line
    held = idx[world.control.is_driven(idx) & ~np.isin(idx, np.asarray(list(exclude), dtype=np.int64))]
    return [(int(strand.along(h)), world.control.target([h])[0].astype(np.float64)) for h in held]


def within_holds(point: np.ndarray, particle: float, holds, rod_length: float, slack: float, now: np.ndarray):
    """``point`` pulled back to where particle ``particle`` (a mean position along its line, at ``now``) can go with
    its rope's holds kept (``rope_holds``).

    A rope particle k rods from a held particle can be at most ``slack`` k
    rod lengths from it, or as far as it is now where that is more (a rope
    hanging near taut is not pulled in): the point is projected onto the
    intersection of those balls (alternating projections; the balls meet
    wherever the holds themselves are within the rope's reach of each
    other). Returns (point, the held particle that limited it most, or None
    when it was within every reach already).
    """
    balls = [(h, c, max(slack * rod_length * abs(particle - h), float(np.linalg.norm(now - c)))) for h, c in holds]
    worst, limit = 0.0, None
    for h, c, r in balls:
        over = float(np.linalg.norm(point - c)) - r
        if over > worst:
            worst, limit = over, h
    if limit is None:
        return point, None
    q = point
    for _ in range(16):
        for _, c, r in balls:
            q = _within(q, c, r)
    return q, limit


def check_two_strands(params):
    """A Crossing or Winding takes two different strands: a strand crossed with or wound around itself is not
    a knot."""
    def parsed(name: str):
        try:
            line = parse_cloth_line(name)
            return ("line", *map(repr, line)) if line is not None else ("rope", *parse_strand(name))
        except ValueError:
            return name  # reported where the strand is checked

    if parsed(params.active) == parsed(params.target):
        raise ValueError(f"active and target are the same strand {params.active!r}: name two (two ropes, two "
                         "runs of one rope R[i0:i1] for a knot in one rope, or two cloth lines such as "
                         "F.line1 and F.line3)")
    return params


class CrossingParams(Params):
    active: str  # strand C: a rope, a run R[i0:i1] of one, or a cloth line F.line1-F.line4 / F.P..Q
    target: str  # strand T (as active)
    active_tip: Site = "end"  # C's particle that is moved (held by the hand)
    target_tip: Site | None = "end"  # T's particle that is moved; None keeps T where it is
    # C's constrained bottom point (default: the end opposite its tip);
    # "contact": where the strand's rope leaves a knot tied before on its way
    # to the tip (e.g. the first half of a granny knot); a place (a point, or
    # an object's site with an offset): the strand's particle nearest it
    # (e.g. where a cloth's control line passes the top of the object it wraps).
    active_base: Site | Literal["contact"] | TargetLike | None = None
    target_base: Site | Literal["contact"] | TargetLike | None = None  # T's constrained bottom point (as ``active_base``)
    # m along each strand from its "contact" (or place) bottom towards its tip
    # where a hand pinches it (held through the crossing): the bottoms of a
    # second half knot then sit apart, on either side of the first, as the
    # strands leave it; two cloth corners stood up side by side are pinched
    # above where they leave the object.
    contact_offset: Annotated[float, pydantic.Field(ge=0)] = 0.0
    # m: the hands then carry the two pinched bottoms apart, this far, level
    # with the knot and on either side of it, before the tips cross: the
    # second half knot starts from the same U as the first, with the knot
    # tied before at its bottom instead of the object (and two strands that
    # leave one point of an object start from a U).
    contact_spread: Annotated[float, pydantic.Field(gt=0)] | None = None
    height: Annotated[float, pydantic.Field(gt=0)] = 0.15  # m, X above the bottoms
    sign: Literal[1, -1] = 1  # +1: C passes in front of T (on +z)
    gap: Annotated[float, pydantic.Field(ge=0)] | None = None  # m; default 1.5 (r_C + r_T)
    slack: Annotated[float, pydantic.Field(gt=0, le=1)] = 0.9  # most bottom-to-tip distance, over the rope between them
    lift: Annotated[float, pydantic.Field(ge=0)] = 0.05  # m, tips rise first by this much
    speed: Annotated[float, pydantic.Field(gt=0)] = 0.5  # m/s of the tips
    tolerance: Annotated[float, pydantic.Field(gt=0)] = 0.005  # m

    _two_strands = pydantic.model_validator(mode="after")(check_two_strands)

    @pydantic.model_validator(mode="after")
    def _offset_needs_contact(self):
        pinchable = [b == "contact" or isinstance(b, Target) for b in (self.active_base, self.target_base)]
        if self.contact_offset > 0 and not any(pinchable):
            raise ValueError("contact_offset moves a 'contact' or place bottom: set active_base or target_base "
                             "to 'contact' or to a place, or leave contact_offset at 0")
        if self.contact_spread is not None and not (all(pinchable) and self.contact_offset > 0):
            raise ValueError("contact_spread carries two pinched bottoms apart: set active_base and "
                             "target_base to 'contact' or to places, and contact_offset > 0, or leave "
                             "contact_spread out")
        if self.contact_spread is not None and self.contact_spread > 2.0 * self.contact_offset:
            raise ValueError(f"contact_spread {self.contact_spread} is more than the rope between the two "
                             f"pinches allows (2 x contact_offset = {2.0 * self.contact_offset:g})")
        return self


@register
class Crossing(Maneuver):
    """Bring strands ``active`` (C) and ``target`` (T) across each other at X (paper §4.1).

    The tips rise by ``lift``, move sideways to their own side of the
    crossing plane (C to +z sign gap, T to -z sign gap) and then to their
    targets (``crossing_targets``), so that they never meet on the way; no
    waypoint is further from a bottom point than ``slack`` of the rope between
    them, nor from a particle of their rope that another hand holds (a
    ``Winding``'s last wound particle, an ``Anchoring``). Done when the tips
    are there and the strands pass within ``gap`` + radii of each other; the
    tips stay held. Where they pass closest is recorded as the crossing for
    a following ``Winding``.

    The strands sag and bend on their way, so tips that arrive where they
    were planned may leave the strands passing further apart than that
    (above or beside each other). The hands then close the miss: once the
    strands have settled (``CROSS_SETTLE_FRAMES``), each moving tip goes on
    so that its strand passes where the crossing was planned (``_close_miss``):
    by its strand's error there over how far out along the strand that point
    lies (a tip moves a point halfway down its strand by half as much),
    within the same reach as its waypoints. At most ``MAX_REPLANS`` times;
    the Crossing fails only when the strands still miss 4 s after the last
    move.
    """

    name = "Crossing"
    Params = CrossingParams

    def start(self) -> None:
        p, w = self.params, self.world
        self.c = w.strand(p.active)
        self.t = w.strand(p.target)
        x = w.positions().astype(np.float64)
        tip_t_site = p.target_tip if p.target_tip is not None else "end"
        tip_c_idx = w.site_particles(p.active, p.active_tip)
        tip_t_idx = w.site_particles(p.target, tip_t_site)
        self.contacts = []  # where each "contact" bottom leaves the knot (or each place bottom is), when pinched
        base_c = self._base(x, self.c, self.t, p.active, p.active_base, p.active_tip, tip_c_idx)
        base_t = self._base(x, self.t, self.c, p.target, p.target_base, tip_t_site, tip_t_idx)
        self.moves = []  # (particle indices, current command, waypoints)
        self.limits = []  # (body, moved particle, held particle that limited it)
        self.c_part, self.t_part = self.c, self.t
        self.c_cross, self.t_cross = self.c, self.t
        if base_c is None or base_t is None:
            return  # ``update`` reports the failure with the message
        gap = p.gap if p.gap is not None else 1.5 * (self.c.radius + self.t.radius)
        self.gap = gap
        # The strands cross between their bottoms and their tips: ends held
        # side by side below the bottoms (two ropes a cloth joins) are not it.
        self.c_part = _between(self.c, base_c, tip_c_idx)
        self.t_part = _between(self.t, base_t, tip_t_idx)
        self.c_cross = _off_bottom(self.c_part, base_c, self.t)
        self.t_cross = _off_bottom(self.t_part, base_t, self.c)
        # A bottom given as a place is a hand pinching the strand where it
        # passes there and taking it from there to the tip: what an earlier
        # maneuver held in between (a cloth corner a Wrapping stood up) is let
        # go. (A bottom named as a site is held by another hand; what is held
        # between it and the tip stays held.)
        for part, base, tip, site in ((self.c_part, base_c, tip_c_idx, p.active_base),
                                      (self.t_part, base_t, tip_t_idx, p.target_base)):
            if isinstance(site, Target):
                inner = part.idx[~np.isin(part.idx, np.concatenate([np.atleast_1d(base), np.atleast_1d(tip)]))]
                w.control.release(inner[w.control.is_driven(inner)])
                w.control.drive(base, x[base])
        # Rope length between each bottom and its tip (not the whole strand).
        len_c = self.c.rod_length * abs(float(self.c.along(tip_c_idx).mean() - self.c.along(base_c).mean()))
        len_t = self.t.rod_length * abs(float(self.t.along(tip_t_idx).mean() - self.t.along(base_t).mean()))
        bc, bt = x[base_c].mean(axis=0), x[base_t].mean(axis=0)
        spread = []  # (pinched bottom, from, to) carried apart by the hands
        if p.contact_spread is not None:
            bc, bt = self._spread(x, (base_c, base_t), (tip_c_idx, tip_t_idx))
            spread = [(base_c, x[base_c].mean(axis=0), bc), (base_t, x[base_t].mean(axis=0), bt)]
        across = None
        if np.linalg.norm(_flat(bt - bc)) < 4.0 * (self.c.radius + self.t.radius):
            # Both strands leave one knot: C's tip goes over to T's tip's side.
            across = _flat(x[tip_t_idx].mean(axis=0) - x[tip_c_idx].mean(axis=0))
        self.x, tip_c, tip_t, self.xhat, self.zhat = crossing_targets(
            bc, bt, len_c, len_t, height=p.height, sign=p.sign, gap=gap, slack=p.slack,
            across=across)
        plans = [(p.active, p.active_tip, tip_c, p.sign)]
        if p.target_tip is not None:
            plans.append((p.target, p.target_tip, tip_t, -p.sign))
        bases = (bc, bt)
        reach = (p.slack * len_c, p.slack * len_t)
        self.bases, self.reach, self.n_tips = bases, reach, len(plans)
        self.replans, self.waited = 0, 0
        self.taut = [0, 0]  # times each tip's hand stopped short, its strand drawn taut
        self.misses: list[float] = []  # how far apart the strands passed each time the tips were moved again (m)
        for k, (body, site, goal, s) in enumerate(plans):
            idx = w.site_particles(body, site)
            pos = x[idx].mean(axis=0)
            side = s * (0.5 * gap + 2.0 * max(self.c.radius, self.t.radius)) * self.zhat
            up = pos + p.lift * _UP
            up_side = up - float((up - self.x) @ self.zhat) * self.zhat + side  # into its own z plane
            ways = [up, up_side, goal + (side - s * 0.5 * gap * self.zhat), goal]
            # No waypoint further from the bottom than the rope allows.
            ways = [_within(q, bases[k], max(reach[k], float(np.linalg.norm(pos - bases[k])))) for q in ways]
            self.moves.append((idx, pos, ways))
            w.control.drive(idx, np.repeat(pos[None], len(idx), axis=0))
        for idx, pos, goal in spread:
            self.moves.append((idx, pos, [goal]))
        self._keep_holds()
        # A waypoint inside an object (a pinched bottom carried apart across
        # the box it lies beside) is never reached: the hand keeps its
        # particle a radius clear of every surface on the way (``update``)
        # and would push it back out at every frame. Each waypoint is taken
        # out to that clearance first.
        self._clear_waypoints(range(len(self.moves)))
        if spread:
            # A bottom carried apart ends where its last waypoint now is (taken clear of solids, kept within
            # reach of other holds), which may be a centimetre or more from where its tip's waypoints were
            # planned around: a tail drawn taut from its pinched bottom snaps the fold beside the pinch into the
            # other rope (0.3 radius of overlap, 25 % strain in one frame). The tips' waypoints are kept within
            # reach of that end.
            for k in range(len(plans)):
                idx, pos, ways = self.moves[k]
                end = self.moves[len(plans) + k][2][-1]
                self.moves[k] = (idx, pos, [_within(q, end, max(reach[k], float(np.linalg.norm(pos - end))))
                                            for q in ways])
        self.total = sum(float(np.linalg.norm(np.diff(np.vstack([m[1], *m[2]]), axis=0), axis=1).sum())
                         for m in self.moves) or 1.0
        self.travelled = 0.0
        self.trails = [[] for _ in self.moves]  # where each hand was at the start of each frame it went on
        w.record.crossings[(p.active, p.target)] = self.x.copy()

    def _clear_waypoints(self, moves) -> None:
        """Take the waypoints of ``moves`` (indices into ``self.moves``) out to their particles' radius clear of
        every object and above the ground, where the hand keeps them on its way (``update``)."""
        for k in moves:
            idx, pos, ways = self.moves[k]
            clearance = float(self.world.model.data.radius[np.atleast_1d(idx)].max())
            self.moves[k] = (idx, pos, list(self.world.clear_of_solids(np.array(ways), clearance)))

    def _keep_holds(self) -> None:
        """Pull every waypoint back within its rope's reach from the particles other hands hold.

        A hold left by an earlier maneuver (a ``Winding``'s last wound
        particle, an ``Anchoring`` hand) stays where it is while the tips and
        pinched bottoms move; a waypoint past the rope between them would
        stretch that rope by the difference. The waypoints are pulled back
        (``within_holds``, with the crossing's ``slack``); the held particles
        that limited them are named if the crossing then fails.
        """
        moving = {int(i) for idx, _, _ in self.moves for i in np.atleast_1d(idx)}
        for k, (idx, pos, ways) in enumerate(self.moves):
            idx = np.atleast_1d(idx)
            rope = self.c if self.c.has(int(idx[0])) else self.t
            holds = rope_holds(self.world, rope, moving)
            if not holds:
                continue
            body = rope.name if rope.cloth else rope.body  # holds are named by position along it, as sites are
            at = float(rope.along(idx).mean())
            out = []
            for q in ways:
                q, h = within_holds(q, at, holds, rope.rod_length, self.params.slack, pos)
                if h is not None:
                    self.limits.append((body, int(round(at)), h))
                out.append(q)
            self.moves[k] = (idx, pos, out)

    def _spread(self, x: np.ndarray, bases, tips) -> tuple[np.ndarray, np.ndarray]:
        """Where the hands carry the two pinched bottoms: ``contact_spread`` apart about the knot.

        Level with the knot (the midpoint of the two contacts), each on its
        own tip's side (along the line from C's tip to T's), raised so that the rope
        from its contact (``contact_offset`` long) sags a little but never
        has to stretch; a bottom is brought closer to the knot where its
        tip, lifted, would be out of the reach of the rope between them.
        """
        p = self.params
        centre = 0.5 * (self.contacts[0] + self.contacts[1])
        tip_c, tip_t = (x[t].mean(axis=0) for t in tips)
        axis = _unit(_flat(tip_t - tip_c), _unit(_flat(self.contacts[1] - self.contacts[0]), np.array([1.0, 0.0, 0.0])))
        half = 0.5 * p.contact_spread
        reach = 0.95 * p.contact_offset
        rise = 0.5 * float(np.sqrt(max(reach * reach - half * half, 0.0)))
        out = []
        for side, contact, base, tip, st in ((-1.0, self.contacts[0], bases[0], tips[0], self.c),
                                             (1.0, self.contacts[1], bases[1], tips[1], self.t)):
            goal = centre + side * half * axis + rise * _UP
            lifted = x[tip].mean(axis=0) + p.lift * _UP
            tip_reach = p.slack * st.rod_length * abs(float(st.along(tip).mean() - st.along(base).mean()))
            for _ in range(8):  # alternate projections onto the two balls
                goal = _within(_within(goal, lifted, tip_reach), contact, reach)
            # Where the two balls do not meet (the rope is near taut), go only
            # as far towards the goal as keeps the bottom within both reaches
            # (its place now is, being on the rope).
            now = x[base].mean(axis=0)
            r_c = max(reach, float(np.linalg.norm(now - contact)))
            r_t = max(tip_reach, float(np.linalg.norm(now - lifted)))
            if np.linalg.norm(goal - contact) <= r_c and np.linalg.norm(goal - lifted) <= r_t:
                out.append(goal)
                continue
            lo, hi = 0.0, 1.0
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                q = now + mid * (goal - now)
                ok = np.linalg.norm(q - contact) <= r_c and np.linalg.norm(q - lifted) <= r_t
                lo, hi = (mid, hi) if ok else (lo, mid)
            out.append(now + lo * (goal - now))
        return out[0], out[1]

    def _base(self, x, strand, other, body, site, tip_site, tip_idx) -> np.ndarray | None:
        """Global indices of a strand's bottom point: a site, its far end, the particle nearest a place, or
        ``"contact"``; from a place or a contact, with ``contact_offset``, the particle that far towards the
        tip, pinched (``_pinch``).

        ``"contact"`` is where the strand's rope leaves the knot on its way to
        the tip (``knot_exit`` over the whole ropes): the top of a knot tied
        before.
        """
        if site is None:
            return self.world.site_particles(body, _other_end(tip_site))
        if site != "contact" and not isinstance(site, Target):
            return self.world.site_particles(body, site)
        if isinstance(site, Target):
            where = resolve_target(self.world, site)
            k = int(strand.idx[np.argmin(np.linalg.norm(x[strand.idx] - where, axis=1))])
            if self.params.contact_offset <= 0:
                return np.array([k])
            self.contacts.append(x[k].copy())
            return self._pinch(x, strand.whole(), k, tip_idx)
        # The knot may have slid past the strands' split while it was
        # tightened (an overhand creeps along its rope): look along the whole
        # rope, at every part of the ropes it could touch.
        whole, other_whole = strand.whole(), other.whole()
        same = len(whole.line) == len(other_whole.line) and np.array_equal(whole.line, other_whole.line)
        parts = [whole] if same else [whole, other_whole]
        tip = int(whole.at_along(int(whole.along(tip_idx).mean())))
        k = knot_exit(x, whole, parts, tip, [self._bundle(x, st, other_whole if st is whole else whole)
                                             for st in (whole, *parts)])
        if k is None:
            self.message = f"strand {body!r} does not touch {other.name!r}: no contact to cross above"
            return None
        self.contacts.append(x[k].copy())
        if self.params.contact_offset > 0:
            return self._pinch(x, whole, k, tip)
        return np.array([k])

    def _bundle(self, x: np.ndarray, strand: Strand, other: Strand) -> float:
        """Radius of ``strand`` where it passes closest to ``other``: a rope's own; for a cloth line, the cloth
        gathered around it (``gathered_radius``) over one turn of the two strands' tube."""
        if not strand.cloth:
            return strand.radius
        from sandbox.model.strands import gathered_radius

        _, i, _ = strand_approach(x, strand, other)
        w = self.world
        return gathered_radius(x, strand, w.cloth(strand.body), w.data.x0, x[strand.idx[i]],
                               2.0 * _same_bend(strand, other))

    def _pinch(self, x, whole, k: int, tip) -> np.ndarray:
        """The particle ``contact_offset`` along ``whole`` from ``k`` towards the tip, pinched where it is."""
        tip = int(whole.at_along(int(np.mean(whole.along(np.atleast_1d(tip))))))
        step = int(round(self.params.contact_offset / whole.rod_length))
        ak, at = whole.along(k), whole.along(tip)
        k = int(whole.at_along(int(np.clip(ak + np.sign(at - ak) * step, min(ak, at), max(ak, at)))))
        self.world.control.drive([k], x[k][None, :])
        return np.array([k])

    def update(self) -> Status:
        p, w = self.params, self.world
        self.ticks += 1
        if not self.moves:
            return Status.FAILED
        arrived = True
        x = w.positions().astype(np.float64)
        for k, (idx, pos, ways) in enumerate(self.moves):
            step = p.speed / w.fps
            trail = self.trails[k]
            if k < self.n_tips and float((self.c if k == 0 else self.t).strain(x).max()) > TAUT_STRAIN:
                # Its strand is drawn taut (round something its planned reach does not see): the hand goes back
                # a frame along its way and stops there, as far as the strand reaches; whether the strands cross
                # from there is checked as for a hand that arrived.
                step = 0.0
                self.taut[k] += 1
                if trail:
                    back = trail.pop()
                    self.travelled -= float(np.linalg.norm(pos - back))
                    pos = back
                self.travelled += sum(float(np.linalg.norm(b - a)) for a, b in zip([pos, *ways[:-1]], ways))
                ways = []
            else:
                trail.append(pos)
            while step > 0 and ways:
                d = ways[0] - pos
                dist = float(np.linalg.norm(d))
                if dist <= step:
                    pos = ways.pop(0)
                    step -= dist
                    self.travelled += dist
                else:
                    pos = pos + d * (step / dist)
                    self.travelled += step
                    step = 0.0
            # The hand goes round the objects (and stays above the ground), not
            # through them: it keeps its particles a radius clear.
            pos = w.clear_of_solids(pos, float(w.model.data.radius[np.atleast_1d(idx)].max()))[0]
            self.moves[k] = (idx, pos, ways)
            w.control.drive(idx, np.repeat(pos[None], len(idx), axis=0))
            arrived &= not ways
        self.progress = min(1.0, self.travelled / self.total)
        late = self.ticks > 4 * w.fps + (self.total / p.speed + self.replans * CROSS_SETTLE_FRAMES / w.fps) * w.fps
        if not arrived:
            if late:  # a hand held back on its way (by a surface it keeps clear of) for 4 s past its plan
                stuck = [(i, pos, ways[0]) for i, pos, ways in self.moves if ways]
                self.message = "a hand did not reach its waypoint: " + "; ".join(
                    f"particle {int(np.atleast_1d(i)[0])} at {np.round(pos, 3).tolist()}, "
                    f"{float(np.linalg.norm(q - pos)):.3f} m short of {np.round(q, 3).tolist()}" for i, pos, q in stuck)
                return Status.FAILED
            return Status.RUNNING
        tips_ok = all(np.linalg.norm(x[idx].mean(axis=0) - pos) <= p.tolerance for idx, pos, _ in self.moves)
        near, at_c, at_t = self.approach(x)
        if tips_ok and near <= self.gap + (self.c.radius + self.t.radius):
            # The strands cross where they pass closest (gravity lets them sag
            # below the planned X): that is where the winding starts.
            w.record.crossings[(p.active, p.target)] = 0.5 * (at_c + at_t)
            self.progress = 1.0
            if self.replans:
                self.note = f"the tips were moved again {self.replans} times to close misses of {self.misses} m"
            if any(self.taut):
                self.note = (self.note + "; " if self.note else "") + (
                    f"a hand stopped short {sum(self.taut)} times, its strand drawn taut")
            return Status.DONE
        if tips_ok and self.replans < MAX_REPLANS:
            self.waited += 1
            if self.waited >= CROSS_SETTLE_FRAMES:
                self.waited = 0
                self.misses.append(round(near, 4))
                self.replans = self.replans + 1 if self._close_miss(x) else MAX_REPLANS
                return Status.RUNNING
        if late:
            self.message = (f"the strands pass {near:.3f} m apart after the tips arrived "
                            f"(a crossing needs at most {self.gap + self.c.radius + self.t.radius:.3f} m; "
                            f"the tips were moved again {self.replans} times to close it)")
            if any(self.taut):
                self.message += (f"; a hand stopped short {sum(self.taut)} times, its strand drawn taut "
                                 f"(a rod stretched past {TAUT_STRAIN:.0%})")
            held = sorted(set(self.limits))
            if held:
                self.message += "; held back by " + ", ".join(
                    f"{body}'s particle {h} (held, {abs(m - h)} rods from the moved particle {m})" for body, m, h in held)
            return Status.FAILED
        return Status.RUNNING

    def _close_miss(self, x: np.ndarray) -> bool:
        """Send the tips on so that each strand passes where the crossing was planned: C at X + ``sign`` d
        ``zhat``, T at X - ``sign`` d ``zhat`` (both tips moving; d is half of r_C + r_T + gap / 2), or C at
        that distance in front of where T passes nearest X (T's tip held). Each tip goes on by its strand's
        error there over how far out along the strand that point lies (a point halfway down moves half as much
        as the tip), within the reach its waypoints had. False where no tip can move a millimetre."""
        apart = self.c.radius + self.t.radius + 0.5 * self.gap
        front = self.params.sign * self.zhat
        parts = (self.c_cross, self.t_cross)
        if self.n_tips == 2:
            aims = [self.x + 0.5 * apart * front, self.x - 0.5 * apart * front]
        else:
            xt = x[self.t_cross.idx]
            aims = [xt[int(np.argmin(np.linalg.norm(xt - self.x, axis=1)))] + apart * front]
        for k in range(self.n_tips):
            idx, pos, _ = self.moves[k]
            pts = x[parts[k].idx]
            at = pts[int(np.argmin(np.linalg.norm(pts - aims[k], axis=1)))]
            base = self.bases[k]
            lever = float(np.clip(np.linalg.norm(at - base) / max(float(np.linalg.norm(pos - base)), 1e-9), 0.3, 1.0))
            goal = _within(pos + (aims[k] - at) / lever, base, max(self.reach[k], float(np.linalg.norm(pos - base))))
            self.moves[k] = (idx, pos, [goal])
        self._keep_holds()
        self._clear_waypoints(range(self.n_tips))
        moved = 0.0
        for k in range(self.n_tips):
            idx, pos, ways = self.moves[k]
            step = float(np.linalg.norm(ways[0] - pos))
            self.moves[k] = (idx, pos, ways if step > 1e-4 else [])
            moved += step
        self.total += moved
        return moved > 1e-3

    def approach(self, x: np.ndarray):
        """Closest approach of C and T now: ``(distance, point on C, point on T)``."""
        d, i, j = strand_approach(x, self.c_cross, self.t_cross)
        return d, x[self.c_cross.idx[i]], x[self.t_cross.idx[j]]

    def metrics(self) -> dict[str, float]:
        return {"miss": self.approach(self.world.positions().astype(np.float64))[0]}
