"""Tightening: pull a knot's ends apart until it is tight (paper §4, step 4; Table 3).

The hands either move the ends along set paths until a rod stretches or two
capsules press past a bound, or pull them with a force and a drag (a hand's
give) until they stop gaining rope. A second hand may push the knot's last
wound part toward a place while they pull (the paper's "towards": the
object's centre, or the half knot tied before).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
import pydantic

from sandbox.maneuvers.base import Maneuver, Params, Status, register
from sandbox.maneuvers.basic import TargetLike, follow_target
from sandbox.maneuvers.knotting import _UP, Site, Vec3, _unit
from sandbox.model.model import GRIP_GIVE
from sandbox.model.strands import base_name


SETTLE_FRAMES = 15
"""Frames every pulled end must stay below ``settle_speed`` for a forced pull to be tight."""
MAX_OVERLAP = 0.05
"""Capsule overlap, over the radius, that makes a moved pull tight."""
BACKOFF = 0.01
"""m each end of a moved pull gives back once the knot is tight."""

class Pull(Params):
    """One end pulled by Tightening: a site of a rope, a strand or a cloth line, and where it goes."""

    body: str  # a rope, a run R[i0:i1] of one, or a cloth line (F.line1, F.P..Q)
    site: Site = "end"
    direction: Vec3 | Literal["away"] = "away"  # "away": from the knot's centre
    toward: TargetLike | None = None  # pull toward this place instead (overrides ``direction``): a point, or an object's site with an offset
    # With the Tightening's ``force`` (force mode) only:
    force: Annotated[float, pydantic.Field(gt=0)] | None = None  # N on this end instead of the Tightening's
    # m: this end is pulled at most this far from where it started, then held
    # there (a cloth drawn taut over an object gives no more than its slack).
    distance: Annotated[float, pydantic.Field(gt=0)] | None = None


class Kept(Params):
    """Sites that a Tightening keeps holding (standing ends or tails held by a hand, an object or the cloth)."""

    body: str
    sites: Annotated[list[Site], pydantic.Field(min_length=1)]


class Push(Params):
    """A hand that pushes the knot's last wound part toward a place while the ends are pulled
    (paper Table 3: a Tightening goes "towards" the object's centre, or towards the half knot
    tied before, so that the second half knot closes onto the first)."""

    toward: Literal["knot"] | TargetLike  # a place (a point, or an object's site with an offset), or "knot": where the last Tightening of these strands left their knot
    force: Annotated[float, pydantic.Field(gt=0)]  # N, spread over the wound particles
    speed: Annotated[float, pydantic.Field(gt=0)] = 0.1  # m/s the wound part moves at most under it


class TighteningParams(Params):
    pulls: Annotated[list[Pull], pydantic.Field(min_length=1)]  # the ends pulled: {body, site, direction or toward, force, distance}
    push: Push | None = None  # a hand that pushes the last wound part: {toward (a point or knot), force, speed}
    keep: list[Kept] = []  # held sites that are not let go when the pull starts (standing ends an object holds, tails a hand holds)
    knot: list[str] = []  # strands whose wound part is the knot (default: the pulled bodies)
    speed: Annotated[float, pydantic.Field(gt=0)] = 0.1  # m/s of each pulled end
    # N: pull each end with this force instead of moving it; ``speed`` is then
    # its top speed (drag force / speed). The knot settles where the tensions
    # balance, and is tight when the ends stop.
    force: Annotated[float, pydantic.Field(gt=0)] | None = None
    settle_speed: Annotated[float, pydantic.Field(gt=0)] = 0.02  # m/s below which a pulled end has stopped
    # With ``force``: also tight once the farthest any end has been pulled has
    # not grown by ``stall`` m for ``stall_frames`` frames (a tight knot that
    # jitters never has every end still, but it no longer gives rope).
    stall: Annotated[float, pydantic.Field(gt=0)] = 0.002
    stall_frames: Annotated[int, pydantic.Field(ge=1)] = 45  # frames without growth that make a forced pull tight (see ``stall``)
    distance: Annotated[float, pydantic.Field(gt=0)] = 0.3  # m, most an end is pulled
    max_strain: Annotated[float, pydantic.Field(gt=0)] = 0.003  # rod strain that means "tight"

    @pydantic.model_validator(mode="after")
    def _pull_needs_force(self):
        if self.force is None:
            bad = [k for k, q in enumerate(self.pulls) if q.force is not None or q.distance is not None]
            if bad:
                raise ValueError(f"pulls {bad} set their own force or distance, which only a Tightening by "
                                 "force has: set the Tightening's force (N), or leave them out")
        return self


@register
class Tightening(Maneuver):
    """Pull ends apart until the knot is tight (paper §4, step 4).

    Every other held particle of the knot's ropes is let go first (the last
    wound particle a Winding keeps, hands that held the bottoms), except the
    sites in ``keep`` (standing ends that an object or the cloth holds). Each pulled
    site then moves along its direction at ``speed``. The knot is tight
    when pulling more would stretch a rod by more than ``max_strain`` or press
    two rope capsules into each other by more than a twentieth of a
    radius (``MAX_OVERLAP``): collisions stay hard, so the ends give back
    ``BACKOFF`` and are held there. Done when tight or after ``distance``.

    With ``force`` the hands pull instead of moving: each end stays dynamic
    and feels ``force`` newtons along its direction and a drag that keeps it
    below ``speed`` (a hand's give), so the knot slides to
    where the tensions balance (a knot between two held standing parts is
    drawn to the middle rather than to the hand that stops last). It is tight
    when every end has moved slower than ``settle_speed`` for
    ``SETTLE_FRAMES`` frames, or when the farthest pull has not grown by
    ``stall`` for ``stall_frames`` frames (the force, not ``max_strain`` or
    the overlap, bounds how hard the rope is pulled); the ends are then
    held where they are by hands that keep pulling as hard as they pulled
    but move no further (``Control.grip``): a knot drawn tighter than that
    slips through them instead of snapping through itself against hands
    that cannot give.
    A pull may set its own ``force``, and its own ``distance``: that end is
    held once it is that far from where it started (a standing part that a
    cloth draws taut gives its slack, and no more), while the others pull on;
    it stays held there firmly.
    """

    name = "Tightening"
    Params = TighteningParams

    def start(self) -> None:
        p, w = self.params, self.world
        x = w.positions().astype(np.float64)
        names = p.knot or [q.body for q in p.pulls]
        self.strands = [w.strand(n) for n in dict.fromkeys(names)]
        self.centre = self._knot_centre(x)
        # Every other held particle of the knot's ropes is let go, but for ``keep``.
        pulled = np.concatenate([w.site_particles(q.body, q.site) for q in p.pulls]
                                + [w.site_particles(k.body, s) for k in p.keep for s in k.sites])
        for st in self.strands:
            idx = st.line  # the whole rope, or the cloth line
            held = idx[w.control.is_driven(idx) & ~np.isin(idx, pulled)]
            if len(held):
                w.control.release(held)
        self.ends = []
        # Where each pull and the push aim (places beside an object follow it).
        self.aims = [follow_target(w, q.toward) if q.toward is not None else None for q in p.pulls]
        self.push_aim = follow_target(w, p.push.toward) if p.push is not None and p.push.toward != "knot" else None
        for q, aim in zip(p.pulls, self.aims):
            idx = w.site_particles(q.body, q.site)
            pos = x[idx].mean(axis=0)
            if aim is not None:
                d = _unit(aim() - pos, _UP)
            elif q.direction == "away":
                d = _unit(pos - self.centre, _UP)
            else:
                d = _unit(np.asarray(q.direction, float), _UP)
            self.ends.append((idx, pos, d))
            if p.force is None:
                w.control.drive(idx, np.repeat(pos[None], len(idx), axis=0))
            else:
                self._pull(idx, d, q.force)
        self.capped: set[int] = set()  # pulls held at their own ``distance`` (force mode)
        self.pushed = self._start_push(x)
        self.pulled = 0.0
        self.tight = False
        self.finished = False  # set when the Tightening is done (tight or pulled its whole distance)
        self.still = 0  # frames in a row that every pulled end has been still (force mode)
        self.best = 0.0  # farthest pulled so far, and frames since it last grew by ``stall`` (force mode)
        self.stalled = 0
        self.last_pos = [pos for _, pos, _ in self.ends]

    def _records(self) -> list[dict]:
        """Winding records (oldest first) that wound or were wound by one of the knot's ropes."""
        names = {base_name(s.name) for s in self.strands}
        rec = self.world.record.windings
        return [v for (c, t), v in rec.items()
                if (base_name(c) in names or base_name(t) in names) and len(np.atleast_1d(v.particles))]

    def _start_push(self, x: np.ndarray) -> np.ndarray:
        """The wound particles the ``push`` hand pushes (none without ``push``)."""
        p = self.params
        if p.push is None:
            return np.zeros(0, np.int64)
        rec = self._records()
        names = [s.name for s in self.strands]
        if not rec:
            self.message = f"push needs a winding of the knot's strands {names} before this Tightening; found none"
            return np.zeros(0, np.int64)
        if p.push.toward == "knot":
            self.knot_place = self.world.record.knots.get(self._knot_key())
            if self.knot_place is None:
                tied = sorted(self.world.record.knots) or "none"
                self.message = (f"push toward 'knot' needs a knot of {names} tightened before this Tightening "
                                f"(knots tightened so far: {tied})")
                return np.zeros(0, np.int64)
        ends = np.concatenate([idx for idx, _, _ in self.ends])
        idx = np.atleast_1d(rec[-1].particles).astype(np.int64)
        idx = idx[~np.isin(idx, ends)]
        self._push_toward(x, idx)
        return idx

    def _push_goal(self, x: np.ndarray) -> np.ndarray:
        """Where the push goes: its place, or the place where the knot tied before was left (a place, not the
        particles wound then: a tightened knot draws rope through itself, and those particles with it)."""
        return self.knot_place if self.params.push.toward == "knot" else self.push_aim()

    def _knot_key(self) -> tuple[str, ...]:
        """The knot's key in ``ManeuverRecord.knots``: its ropes (runs of one rope are that rope) and cloth lines,
        sorted, so that a Tightening naming ``R[:70]`` and one naming ``R`` mean the same knot."""
        return tuple(sorted({s.name if s.cloth else s.body for s in self.strands}))

    def _record_knot(self, x: np.ndarray) -> None:
        """Record where this Tightening leaves the knot (``ManeuverRecord.knots``); where its strands touch nowhere,
        no place is left under its key (an older one would send a later push to a knot that is not there).
        A rope is measured whole (two runs of it would touch at their join), two lines of one cloth as one curve
        through its centre (``joined_at_centre``)."""
        from sandbox.geometry.knots import knot_centre
        from sandbox.model.strands import joined_at_centre

        ropes = {s.body: s for s in self.strands if not s.cloth}
        lines = [s for s in self.strands if s.cloth]
        names = list(ropes) + [s.name for s in lines]
        curves = joined_at_centre(names, [x[s.line] for s in ropes.values()] + [x[s.idx] for s in lines])
        centre = knot_centre(curves, radius=max(s.radius for s in self.strands))
        if centre is None:
            self.world.record.knots.pop(self._knot_key(), None)
        else:
            self.world.record.knots[self._knot_key()] = centre

    def _push_toward(self, x: np.ndarray, idx: np.ndarray) -> None:
        """Push particles ``idx`` with ``push.force`` in all toward the push's goal."""
        push = self.params.push
        if not len(idx):
            return
        self._hand(idx, _unit(self._push_goal(x) - x[idx].mean(axis=0), -_UP), push.force, push.speed)

    def _update_push(self, x: np.ndarray) -> None:
        """Push on toward the goal, re-aimed every frame, until the Tightening ends: a finger on the knot while
        the ends are drawn. A hand that let go once the part stopped closing left the knot to the pulls, which
        dragged it along: on square_knot's box top, 4 to 8 cm in 8 of 24 standard-sweep runs."""
        self._push_toward(x, self.pushed)

    def _knot_centre(self, x: np.ndarray) -> np.ndarray:
        rec = self.world.record.windings
        parts = [x[v.particles] for v in rec.values() if len(np.atleast_1d(v.particles))]
        if parts:
            return np.vstack(parts).mean(axis=0)
        return np.vstack([x[s.idx] for s in self.strands]).mean(axis=0)

    def _tension(self, x: np.ndarray) -> tuple[float, float]:
        """Largest rod strain and capsule overlap / radius of the knot's ropes now."""
        strain = 0.0
        for s in self.strands:
            strain = max(strain, float(np.abs(s.strain(x)).max()))
        overlap = 0.0
        rc = self.world.solver.ropecol
        if rc is not None:
            gap = rc.measure()
            seg_rope = self.world.data.segment_rope
            names = [r.name for r in self.world.data.ropes]
            for s in self.strands:
                if s.cloth:  # cloth layers are kept apart by the cloth's self-collision, not capsules
                    continue
                g = gap[seg_rope == names.index(s.body)]
                if len(g):
                    overlap = max(overlap, float(-g.min()) / s.radius)
        return strain, overlap

    def _hold_ends(self, x: np.ndarray) -> None:
        """Hold every pulled end where it is now (force mode: ``_grip``)."""
        for k, (idx, _, _) in enumerate(self.ends):
            if k not in self.capped:
                self._grip(k, idx, x)

    def _grip(self, k: int, idx: np.ndarray, x: np.ndarray) -> None:
        """Pull ``k``'s hand holds its particles ``idx`` where they are (``Control.grip``): it goes on pulling
        with that pull's force but moves no further than ``GRIP_GIVE`` on, and lets the rope draw it back
        only where the knot pulls harder than that."""
        p, w = self.params, self.world
        force = p.pulls[k].force if p.pulls[k].force is not None else p.force
        place = x[idx] + GRIP_GIVE * self._heading(k, x[idx].mean(axis=0))
        w.control.grip(idx, place, force / len(idx), force / p.speed / len(idx))

    def _heading(self, k: int, at: np.ndarray) -> np.ndarray:
        """Unit direction of pull ``k`` from ``at``: towards its place (a ``toward`` pull turns with the end),
        else the direction it started with."""
        return _unit(self.aims[k]() - at, _UP) if self.aims[k] is not None else self.ends[k][2]

    def _pull(self, idx: np.ndarray, d: np.ndarray, force: float | None = None) -> None:
        """Pull particles ``idx`` along unit ``d`` with ``force`` N in all (default: the Tightening's),
        at most at ``speed``."""
        self._hand(idx, d, force if force is not None else self.params.force, self.params.speed)

    def _hand(self, idx: np.ndarray, d: np.ndarray, force: float, speed: float) -> None:
        """A hand on particles ``idx``: ``force`` N in all along unit ``d``, and a drag that keeps them below ``speed`` m/s."""
        self.world.control.pull(idx, np.repeat((force / len(idx)) * d[None], len(idx), axis=0),
                                force / speed / len(idx))

    def _update_pulling(self, x: np.ndarray) -> Status:
        """Force mode: watch the ends until they stop, then hold them."""
        p, w = self.params, self.world
        now = [x[idx].mean(axis=0) for idx, _, _ in self.ends]
        speed = max(float(np.linalg.norm(a - b)) * w.fps for a, b in zip(now, self.last_pos))
        self.last_pos = now
        self.pulled = max(float(np.linalg.norm(a - pos)) for a, (_, pos, _) in zip(now, self.ends))
        for k, (q, a, (idx, pos, _)) in enumerate(zip(p.pulls, now, self.ends)):
            if k in self.capped:
                continue
            if q.distance is not None and float(np.linalg.norm(a - pos)) >= q.distance:
                w.control.drive(idx, x[idx])  # as far as this end gives (its slack): held there from now on
                self.capped.add(k)
            elif q.toward is not None:  # the pull turns to keep pointing at its point
                self._pull(idx, self._heading(k, a), q.force)
        self.still = self.still + 1 if speed < p.settle_speed else 0
        if self.pulled > self.best + p.stall:
            self.best, self.stalled = self.pulled, 0
        else:
            self.stalled += 1
        self.progress = min(self.pulled / p.distance, 1.0)
        # The force bounds the tension: the knot is as tight as this pull makes it once the ends stop.
        tight = self.still >= SETTLE_FRAMES or self.stalled >= p.stall_frames
        if tight or self.pulled >= p.distance:
            self._hold_ends(x)
            self.tight = tight
            self.progress = 1.0
            self.finished = True
            return Status.DONE
        return Status.RUNNING

    def update(self) -> Status:
        p, w = self.params, self.world
        self.ticks += 1
        if self.message:
            return Status.FAILED
        x = w.positions().astype(np.float64)
        if len(self.pushed):
            self._update_push(x)
        strain, overlap = self._tension(x)
        self.last = (strain, overlap)
        if p.force is not None:
            return self._update_pulling(x)
        step = p.speed / w.fps
        if strain > p.max_strain or overlap > MAX_OVERLAP:
            # Tight: give back ``BACKOFF`` and hold the ends there, so that a
            # taut rope does not keep grinding its contacts.
            back = min(step + BACKOFF, self.pulled)
            self.ends = [(idx, pos - back * d, d) for idx, pos, d in self.ends]
            for idx, pos, _ in self.ends:
                w.control.drive(idx, np.repeat(pos[None], len(idx), axis=0))
            self.tight = True
            self.progress = 1.0
            self.finished = True
            return Status.DONE
        if self.pulled >= p.distance:
            self.progress = 1.0
            self.finished = True
            return Status.DONE
        step = min(step, p.distance - self.pulled)
        self.pulled += step
        self.ends = [(idx, pos + step * d, d) for idx, pos, d in self.ends]
        for idx, pos, _ in self.ends:
            w.control.drive(idx, np.repeat(pos[None], len(idx), axis=0))
        self.progress = self.pulled / p.distance
        return Status.RUNNING

    def stop(self) -> None:
        """The pushing hand lets go once the knot is tight (the pulled ends stay held); where a Tightening that
        finished (tight, or pulled its whole ``distance``) left the knot is recorded."""
        pushed = getattr(self, "pushed", np.zeros(0, np.int64))
        if len(pushed):
            self.world.control.release(pushed)
        if getattr(self, "finished", False):  # a Tightening that failed or timed out left no knot to push onto
            self._record_knot(self.world.positions().astype(np.float64))

    def metrics(self) -> dict[str, float]:
        s, o = getattr(self, "last", (0.0, 0.0))
        return {"pulled": self.pulled, "strain": s, "overlap": o, "tight": float(self.tight)}
