"""Winding: wind rope C around rope T along a geodesic of T's bounding tube (paper §4.2).

Targets t_i are sampled every rod length along the geodesic G from the
crossing; one particle of C at a time is driven to its target through
intermediate targets (paper Eq. 4) and, once it arrives, the control moves to
the next particle. Only the current particle is constrained: collisions keep
the wound part on the tube, and the last particle stays held when the
maneuver is done. T may move: when any of its particles has moved
by more than a tenth of the tube radius since G was traced, the tube and G
are traced again (every frame) from the crossing point
carried along with T's nearest particle. Once the turns are laid, the exit
(``exit``) keeps the line it had then: it starts at the last turn's end and
runs along G's last tangent, a direction that a millimetre's change of that
end swings by tens of degrees while T moves.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
import pydantic

from sandbox.record import WindingRecord
from sandbox.maneuvers.base import Maneuver, Params, Status, register
from sandbox.maneuvers.knotting import TAUT_STRAIN, check_two_strands, rope_holds, within_holds


STUCK_FRAMES = 15
"""Frames a particle whose command is held back (by the rope's reach from the hands that hold C, or by T's tube)
may go without closing on its target before it is laid where it stopped."""
STUCK_GAIN = 0.01
"""Closing on the target by less than this fraction of a rod in a frame counts as not closing."""
TAUT_RODS = 3
"""Rods of C on either side of the driven particle watched for a stretch (``_drawn_taut``)."""
MAX_TICKS_PER_PARTICLE = 90
"""Frames a wound particle may take to reach its target before the winding fails."""
SLIP_TURNS = 0.25
"""Turns the laid particles of C may fall behind their targets on G (Eq. 1 along each) before the winding goes
back to the first particle that slipped and lays the turns again from there."""
MAX_RELAYS = 5
"""Times one winding lays its turns again; after that it goes on without looking back (the criteria judge it)."""


class WindingParams(Params):
    active: str  # strand C: a rope, a run R[i0:i1] of one, or a cloth line F.line1-F.line4 / F.P..Q
    target: str  # strand T (as active)
    start: int | Literal["nearest"] = "nearest"  # C's particle at the crossing
    direction: Literal[1, -1] = 1  # wind C's particles after (+1) or before (-1) start
    theta: Annotated[float, pydantic.Field(gt=0, lt=90)] = 45.0  # degrees
    w0: Annotated[float, pydantic.Field(gt=0, le=10)] = 1.0  # turns
    handedness: Literal[1, -1] = 1  # +1: the turns go right-handed about T (counter-clockwise seen along it)
    along: Literal[1, -1] = 1  # advance along T's particle order (+1) or against it
    speed: Annotated[float, pydantic.Field(gt=0)] = 0.3  # m/s of the driven particle
    tolerance: Annotated[float, pydantic.Field(gt=0, le=1)] = 0.25  # fraction of C's rod length
    straighten: Annotated[float, pydantic.Field(ge=0)] = 0.0  # m of T held straight around X_T (paper §4.2)
    # m of C after the turns laid one particle at a time on a straight line
    # from G's end along its last tangent (at most to C's tip): the tail is
    # threaded out of the turns the way G leaves them, rather than left to
    # dangle back through them. ``exit_square`` drops the tangent's part
    # along T, so that the line leaves T square to it (not down T into a
    # knot tied before).
    exit: Annotated[float, pydantic.Field(ge=0)] = 0.0
    exit_square: bool = False  # the exit line leaves T square to it (see ``exit``)
    # Hold C's crossing particle for the whole winding (a hand pinching the
    # crossing), so that the turns cannot slide along T while they are laid.
    pinch: bool = False
    # eps of the bounding tube over r_C + r_T (paper: 0.1). The rods between
    # two targets on G cut inside the tube by up to R - sqrt(R^2 - l^2 / 4)
    # (1 mm for 6 mm ropes and 1 cm rods): a taut turn then presses T by that much.
    clearance: Annotated[float, pydantic.Field(gt=0, le=1)] = 0.1

    _two_strands = pydantic.model_validator(mode="after")(check_two_strands)


# How far a command may take the driven particle from another hold on C: k rods
# times this. The chain step lays a rope driven past its reach on a straight
# line, every rod stretched alike, so 1.005 keeps that within 0.5 %; a taut
# rope's command a fraction of a millimetre past it is left to the chain step.
REACH_SLACK = 1.005


@register
class Winding(Maneuver):
    """Wind rope ``active`` around rope ``target`` by Geodesic Control."""

    name = "Winding"
    Params = WindingParams

    def start(self) -> None:
        from sandbox.geometry.tube import tube_radius

        p, w = self.params, self.world
        self.c = w.strand(p.active)
        self.t = w.strand(p.target)
        x = w.positions()
        xc = x[self.c.idx]
        if p.start == "nearest":
            self.i0 = self._crossing_particle(xc)
        else:
            self.i0 = int(p.start) % len(xc)
        self.cross = xc[self.i0].astype(np.float64)
        self.rc, self.rt = self.c.radius, self.t.radius
        if self.c.cloth or self.t.cloth:
            self._cloth_tube(x.astype(np.float64))
        self.R = tube_radius(self.rc, self.rt, p.clearance)
        xt = x[self.t.idx]
        # X follows T: kept as an offset from T's particle nearest to it.
        self.j0 = int(np.argmin(np.linalg.norm(xt - self.cross, axis=1)))
        self.offset = self.cross - xt[self.j0]
        xt = xt.astype(np.float64)
        self.straight = self._straighten(xt) if p.straighten > 0 else np.zeros(0, np.int64)
        self.xt_traced = xt.astype(np.float64).copy()
        self.k = 0
        self.laid_held: int | None = None  # the particle laid last frame, held until its successor is taken
        self.tick_in_particle = 0
        self.best_miss, self.stuck = np.inf, 0  # closest the current particle came to its target; frames since
        self.off_target: list[float] = []  # how far short each particle laid out of reach stayed (m)
        self.relaid = 0  # times the laid turns slipped and were laid again (``_slipped``)
        self.short = -1  # the last particle (k) laid short of a target out of reach: turns up to it are not re-laid
        # The last particle laid short because the rope from the hands that hold C could not reach further:
        # the rope is taut up to it, and the particles after it reach only from where it lies (``_keep_holds``).
        self.taut_at: int | None = None
        self.reach_held = False  # whether the holds' reach held the current command back this frame
        self.taut_frames = 0  # frames the hand waited, C drawn taut behind it
        self.targets = self._targets(xt)
        n_left = (len(xc) - 1 - self.i0) if p.direction > 0 else self.i0
        self.too_short = self.n_turns - 1 > n_left  # the turns cannot be laid: the winding fails (``update``)
        if self.too_short:
            self.message = (f"strand {p.active!r} has {n_left} particles after the crossing; "
                            f"the winding needs {self.n_turns - 1}")
        self.targets = self.targets[: n_left + 1]  # an exit runs to C's tip at most
        self.n = len(self.targets)
        self.n_max = n_left + 1  # particles available after the crossing
        self.pos = xc[self.i0].astype(np.float64)
        # Only the current particle is constrained: a hand that held C's wound
        # side (e.g. its tip during a Crossing) lets go now.
        after = np.arange(self.i0 + 1, len(xc)) if p.direction > 0 else np.arange(0, self.i0)
        held = self.c.idx[after[w.control.is_driven(self.c.idx[after]).astype(bool)]] if len(after) else after
        if len(held):
            w.control.release(held)
        self.x_hat = self.geodesic.x_hat
        w.record.windings[(p.active, p.target)] = WindingRecord(np.atleast_1d(self._particle(0)), self.x_hat)

    def _cloth_tube(self, x: np.ndarray) -> None:
        """For a cloth line, the bounding tube is that of the cloth gathered around it, and only over a short
        length about the crossing (paper §5.2).

        The length is what ``w0`` turns at ``theta`` advance along T on the
        bundles' tube, plus two tube diameters (the bundles measured once
        over the single layers' length first); T becomes its part over that
        length, and each cloth strand's radius the bundle's
        (``gathered_radius``) there.
        """
        from sandbox.geometry.tube import tube_radius
        from sandbox.model.strands import gathered_radius

        p, w = self.params, self.world

        def span(r_c: float, r_t: float) -> float:
            big = tube_radius(r_c, r_t, p.clearance)
            return 2.0 * np.pi * big * p.w0 / np.tan(np.radians(p.theta)) + 4.0 * big

        def radii(length: float) -> tuple[float, float]:
            return tuple(gathered_radius(x, st, w.cloth(st.body), w.data.x0, self.cross, length) if st.cloth
                         else st.radius for st in (self.c, self.t))

        # The bundle's radius sets the length the turns cover, which sets the bundle: once round.
        length = span(*radii(span(self.rc, self.rt)))
        if self.t.cloth:
            line = x[self.t.idx]
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
            j = int(np.argmin(np.linalg.norm(line - self.cross, axis=1)))
            keep = np.flatnonzero(np.abs(arc - arc[j]) <= 0.5 * length + self.t.rod_length)
            first = int(self.t.along(self.t.idx[keep[0]]))
            self.t = self.t.part(first, first + len(keep) - 1)
        self.rc, self.rt = radii(length)
        self.note = f"cloth tube over {length:.3f} m of {self.t.name!r}: radii {self.rc:.4f}, {self.rt:.4f} m"

    def _straighten(self, xt: np.ndarray) -> np.ndarray:
        """Hold T straight for ``straighten`` m around X_T, along T's direction there.

        The particles within half that length of X_T (by index) are driven onto
        the line through X_T along the chord of the held run, at their rest
        spacing: the winding then starts on a straight, still piece of T.
        ``xt`` is updated in place to the straightened layout (G is traced on
        it). The run is shortened on a side where its end would land out of
        the rope's reach from the nearest particle held outside it (a hand
        pinching T, T's standing end, where its hand holds it): the rods
        between them would have to stretch by more than ``REACH_SLACK``; or,
        next to a held particle, be compressed by as much. Where X_T itself is
        out of that reach (a tip still on its way to where a hand takes it),
        nothing is held straight. Returns their global indices.
        """
        w = self.world
        half = int(round(0.5 * self.params.straighten / self.t.rod_length))
        lo, hi = max(0, self.j0 - half), min(len(xt) - 1, self.j0 + half)
        if hi - lo < 2:
            return np.zeros(0, np.int64)
        xs = xt.astype(np.float64)
        d = xs[hi] - xs[lo]
        d /= max(float(np.linalg.norm(d)), 1e-12)
        rod = self.t.rod_length
        held = np.flatnonzero(w.control.is_driven(self.t.idx))

        def reachable(i: int, h: int) -> bool:
            # Where the hand holds h (it may still be on its way there). One rod
            # from it, the rod between them must keep its length both ways: it
            # cannot take up a shortfall by bending.
            gap = float(np.linalg.norm(xs[self.j0] + (i - self.j0) * rod * d - w.control.target([self.t.idx[h]])[0]))
            return gap <= REACH_SLACK * abs(i - h) * rod and (abs(i - h) > 1 or gap >= (2.0 - REACH_SLACK) * rod)

        # A held particle inside the span bounds it: the run stops one particle short of it.
        inside = held[(held >= lo) & (held <= hi) & (held != self.j0)]
        if len(inside[inside > self.j0]):
            hi = int(inside[inside > self.j0].min()) - 1
        if len(inside[inside < self.j0]):
            lo = int(inside[inside < self.j0].max()) + 1
        below, above = held[held < lo], held[held > hi]
        while lo < self.j0 and len(below) and not reachable(lo, int(below.max())):
            lo += 1
        while hi > self.j0 and len(above) and not reachable(hi, int(above.min())):
            hi -= 1
        if hi - lo < 2 or (len(below) and not reachable(lo, int(below.max()))) or (
                len(above) and not reachable(hi, int(above.min()))):
            return np.zeros(0, np.int64)  # X_T itself out of reach: holding it where it is would stretch T
        run = np.arange(lo, hi + 1)
        line = xs[self.j0] + ((run - self.j0) * rod)[:, None] * d
        idx = self.t.idx[run]
        w.control.drive(idx, line)
        xt[run] = line
        return idx

    def _crossing_particle(self, xc: np.ndarray) -> int:
        """C's particle at the crossing: nearest the X a Crossing recorded, else nearest T.

        For two strands of one rope, particles within a tube's half turn of
        each other along the rope are not a crossing (they are the same bend).
        """
        p, w = self.params, self.world
        x = w.record.crossings.get((p.active, p.target))
        if x is not None:
            return int(np.argmin(np.linalg.norm(xc - x, axis=1)))
        from sandbox.maneuvers.knotting import strand_approach

        return strand_approach(w.positions().astype(np.float64), self.c, self.t)[1]

    def _targets(self, xt: np.ndarray, keep: int | None = None) -> np.ndarray:
        """Targets every rod along G traced on T's tube (``xt``), then the exit.

        ``keep``: the number of targets on G traced before. G's samples are
        one per rod up to where it reaches w0, so as T moves their count
        flickers by one where G's length crosses a whole number of rods, and
        with it where the exit starts (a target k along it jumps by
        centimetres, and the particle driven there chases it back and
        forth). A count one off ``keep`` is brought back to it: the last
        sample dropped, or one more rod along G's last tangent.
        """
        from sandbox.geometry.tube import Tube, sample_targets, smooth_axis, trace_geodesic

        p = self.params
        # T is followed on the scale of the tube: kinks where C presses on it
        # would otherwise make G (and the number of targets) flicker. The axis
        # moves by at most eps, so that targets never lie inside T.
        eps = self.R - (self.rc + self.rt)
        tube = Tube(smooth_axis(xt, 2.0 * self.R, max_shift=eps), self.R)
        self.tube = tube
        self.geodesic = trace_geodesic(tube, self.cross, theta=np.radians(p.theta), w0=p.w0,
                                       handedness=p.handedness, along=p.along)
        pts = sample_targets(self.geodesic, self.c.rod_length)
        if keep is not None and len(pts) == keep + 1:
            pts = pts[:keep]
        elif keep is not None and len(pts) == keep - 1 and len(pts) >= 2:
            t = pts[-1] - pts[-2]
            pts = np.vstack([pts, pts[-1] + t * (self.c.rod_length / max(float(np.linalg.norm(t)), 1e-12))])
        self.n_turns = len(pts)  # targets on G itself; an exit follows
        m = int(round(p.exit / self.c.rod_length))
        if m > 0 and len(pts) >= 2:
            # The tail leaves the last turn straight on along G's last tangent
            # (with exit_square: less its part along T).
            t = pts[-1] - pts[-2]
            if p.exit_square:
                t = t - float(t @ self.geodesic.x_hat) * self.geodesic.x_hat
            t /= max(float(np.linalg.norm(t)), 1e-12)
            pts = np.vstack([pts, pts[-1] + np.outer(np.arange(1, m + 1) * self.c.rod_length, t)])
        # The hand lays each particle at least its own radius clear of every object and the ground: where T
        # lies on an object the tube runs into it, and a driven particle there drags the cloth through.
        # (Its own radius, not a cloth bundle's: the passive cloth around it finds its own way out, and a
        # wider push would space the targets off one rod, which the held previous particle forbids.)
        return self.world.clear_of_solids(pts, self.c.radius)

    def _particle(self, k: int) -> int:
        return int(self.c.idx[self.i0 + self.params.direction * k])

    def update(self) -> Status:
        p, w = self.params, self.world
        self.ticks += 1
        if self.too_short:
            return Status.FAILED
        if self.k >= self.n:
            return Status.DONE
        now = w.positions()  # one read-back for this frame: the hands move nothing until the next step
        xt = now[self.t.idx].astype(np.float64)
        moved = float(np.linalg.norm(xt - self.xt_traced, axis=1).max())
        if moved > 0.1 * self.R and self.k < self.n_turns:
            # T has moved: re-trace G on its current tube from the crossing carried along.
            self.cross = xt[self.j0] + self.offset
            self.targets = self._targets(xt, keep=self.n_turns)[: self.n_max]
            self.xt_traced = xt.copy()
            self.n = len(self.targets)  # the count follows G: it may grow or shrink by one or two
        slip = self._slipped(xt)
        if slip is not None:
            # The turns laid so far came off T (it moves under them; only the current particle is held):
            # go back to the first particle that slipped and lay the turns again from there, rather than
            # finish a winding that is not there.
            w.control.release([self._particle(self.k)])  # k >= 2 here: never the pinched crossing particle
            self._hand_over(None)
            self.k = slip
            self.relaid += 1
            self._notes()
            self.tick_in_particle = 0
            self.best_miss, self.stuck = np.inf, 0
            self._record()
            self.pos = w.positions()[self._particle(self.k)].astype(np.float64)
        idx = self._particle(self.k)
        target = self.targets[min(self.k, self.n - 1)]
        self._hand_over(idx)
        step = p.speed / w.fps
        d = target - self.pos
        dist = float(np.linalg.norm(d))
        before = self.pos
        self.pos = target.copy() if dist <= step else self.pos + d * (step / dist)
        wanted = self.pos
        # Intermediate targets stay outside the bounding tube: a driven particle
        # is kinematic, and a straight path through T would drag T along, or
        # (projected back onto the tube from near its axis) jump through it.
        s_ax = self.tube.project(self.pos)[0]
        axis = self.tube.frame(s_ax)[0][0]
        if np.linalg.norm(self.pos - axis) < self.R:
            self.pos = self._around(before, target, step)
        self.pos = self._keep_holds(idx, self.pos)
        if self._drawn_taut(idx, now):
            # The rope behind the hand is drawn taut (the laid part lags, caught on T): the hand waits where it
            # was until it gives; a particle that then stops closing on its target is laid short, as below.
            self.pos = before
            self.taut_frames += 1
        # Held back: by the hands that hold C, or by the tube (on every step that goes round T; a command
        # that the tube keeps from a target T has moved over since it was traced stops closing on it).
        held_back = float(np.linalg.norm(self.pos - wanted)) > 1e-9
        w.control.drive([idx], self.pos[None, :])
        x = now[idx]
        self.tick_in_particle += 1
        miss = float(np.linalg.norm(x - target))
        if miss < self.best_miss - STUCK_GAIN * self.c.rod_length:
            self.best_miss, self.stuck = miss, 0
        else:
            self.stuck += 1
        # Out of reach: the hands that hold C, or T's tube, keep the command
        # off the target, and the particle has stopped closing on it. The plan gives
        # way: the particle is laid where the rope lets it, and the next one
        # goes on from there, instead of waiting out the timeout.
        out_of_reach = held_back and self.stuck >= STUCK_FRAMES
        if out_of_reach:
            self.off_target.append(miss)
            self.short = self.k
            if self.reach_held:
                self.taut_at = idx
            self._notes()
        if out_of_reach or (miss <= p.tolerance * self.c.rod_length and dist <= step):
            if self.k + 1 < self.n and not (p.pinch and self.k == 0):
                # Only the current particle is held (the last one stays held): this one is let go once the
                # next is taken, in the next frame (``_hand_over``).
                self.laid_held = idx
            self.k += 1
            self.tick_in_particle = 0
            self.best_miss, self.stuck = np.inf, 0
            self._record()
            if self.k < self.n:
                nxt = self._particle(self.k)
                self.pos = w.positions()[nxt].astype(np.float64)
        elif self.tick_in_particle > MAX_TICKS_PER_PARTICLE:
            self.message = f"particle {idx} did not reach its target within {MAX_TICKS_PER_PARTICLE} frames"
            w.control.release([idx])
            return Status.FAILED
        self.progress = self.k / max(self.n, 1)
        if self.k >= self.n:
            self.progress = 1.0
            return Status.DONE
        return Status.RUNNING

    def _drawn_taut(self, idx: int, x: np.ndarray) -> bool:
        """Whether a rod of C within ``TAUT_RODS`` of the driven particle ``idx`` is stretched past ``TAUT_STRAIN``
        at positions ``x`` (all particles)."""
        at = int(np.flatnonzero(self.c.idx == idx)[0])
        strain = self.c.strain(x)
        return bool(strain[max(at - TAUT_RODS, 0):at + TAUT_RODS].max(initial=0.0) > TAUT_STRAIN)

    def _hand_over(self, taken: int | None) -> None:
        """Let go of the particle laid last frame, now that the hand takes ``taken`` (None: nothing).

        A hand takes the next particle before it lets go of the one it laid: let go in the frame it is
        laid, the turn's end would be free for a frame, with the next particle not yet driven, and the
        tail's weight would draw it into T (a spike of a tenth of a radius of overlap). Held for one
        frame only: a hold that stays while T moves on would unwind the turn.
        """
        if self.laid_held is not None and self.laid_held != taken:
            self.world.control.release([self.laid_held])
        self.laid_held = None

    def _around(self, start: np.ndarray, goal: np.ndarray, step: float) -> np.ndarray:
        """A step of at most ``step`` from ``start`` towards ``goal`` over the tube's surface, the shorter way
        round: (s, phi) of both on the tube, moved along together."""
        s0, phi0, _ = self.tube.project(start)
        s1, phi1, _ = self.tube.project(goal)
        dphi = (phi1 - phi0 + np.pi) % (2.0 * np.pi) - np.pi
        ds = s1 - s0
        arc = float(np.hypot(ds, self.R * dphi))
        f = 1.0 if arc <= step else step / arc
        return self.tube.surface(s0 + f * ds, phi0 + f * dphi)[0]

    def _notes(self) -> None:
        """``note``: the particles laid short of their targets, and the times the laid turns were laid again."""
        notes = []
        if self.off_target:
            notes.append(f"{len(self.off_target)} particle(s) laid short of a target the hand could not "
                         f"reach (at most {max(self.off_target) * 1e3:.1f} mm)")
        if self.relaid:
            notes.append(f"the laid turns slipped off {self.params.target!r} {self.relaid} time(s) "
                         f"and were laid again")
        self.note = "; ".join(notes)

    def _record(self) -> None:
        """The winding record's particles: C's laid turns (not the exit)."""
        last = self.i0 + self.params.direction * (max(min(self.k, self.n_turns), 1) - 1)
        self.world.record.windings[(self.params.active, self.params.target)].particles = self.c.idx[
            min(self.i0, last):max(self.i0, last) + 1]

    def _slipped(self, xt: np.ndarray) -> int | None:
        """The first laid particle whose turns about T (Eq. 1, from the crossing) fall more than
        ``SLIP_TURNS`` behind its target's, or None. O(k + m) for k laid particles and T's m."""
        from sandbox.geometry.winding import winding_integral

        laid = min(self.k, self.n_turns)
        if laid < 2 or self.relaid >= MAX_RELAYS:
            return None
        x = self.world.positions()[[self._particle(i) for i in range(laid)]].astype(np.float64)
        # The targets against the T they were traced on (the exit keeps them while T moves on).
        want = winding_integral(self.targets[:laid], self.xt_traced, self.x_hat, origin=x[0], cumulative=True,
                                signed=False)
        got = winding_integral(x, xt, self.x_hat, origin=x[0], cumulative=True, signed=False)
        sign = 1.0 if want[-1] >= 0.0 else -1.0
        behind = np.flatnonzero(sign * (want - got) > SLIP_TURNS)
        behind = behind[behind > self.short]  # a particle laid short of its target stays where it could go
        return max(int(behind[0]), 1) if len(behind) else None

    def _keep_holds(self, idx: int, pos: np.ndarray) -> np.ndarray:
        """``pos`` kept within C's reach of the particles other hands hold, and one rod from a held neighbour.

        A held particle k >= 2 rods along C's rope (the pinched crossing, a
        hold left by an earlier maneuver) bounds where ``idx``
        can go: at most ``REACH_SLACK`` k rods from it, or as far as it is
        now where that is more (``within_holds``); a command past that would
        stretch the rope between them by more than half the levels' 1 %
        strain bar. So does the last particle laid short because that reach
        held it back (``taut_at``), where it lies now: the rope up to it is
        taut, wound round T, and a reach measured straight from the holds
        before it passes through T (granny_knot, z -5 cm nudged: the next
        particle, carried on within that straight reach, drew the laid turn
        taut round T and stretched it 23 % in three frames). Two held
        neighbours are joined by one rod that nothing else can fix: a command
        nearer or further than its rest length (a pinched crossing particle
        held where G was traced before T moved, the next target sampled on
        the new G) would compress or stretch it, so that rule has the last
        word. Sets ``reach_held``: whether the holds' reach moved ``pos``.
        """
        w = self.world
        a = int(self.c.along(idx))
        near = [int(self.c.line[j]) for j in (a - 1, a + 1) if 0 <= j < len(self.c.line)]
        holds = rope_holds(w, self.c, {idx, *near})
        held = [h for h in near if self.c.has(h) and w.control.is_driven([h])[0]]
        taut = self.taut_at is not None and self.taut_at != idx and not w.control.is_driven([self.taut_at])[0]
        x = w.positions() if holds or held or taut else None  # one read-back of the particles, only when needed
        if taut:
            holds.append((int(self.c.along(self.taut_at)), x[self.taut_at].astype(np.float64)))
        self.reach_held = False
        if holds:
            pos, limit = within_holds(pos, float(self.c.along(idx)), holds, self.c.rod_length, REACH_SLACK,
                                      x[idx].astype(np.float64))
            self.reach_held = limit is not None
        for h in held:
            xh = x[h].astype(np.float64)
            v = pos - xh
            n = float(np.linalg.norm(v))
            if n > 1e-12:
                pos = xh + v * (self.c.rod_length / n)
        return pos

    def stop(self) -> None:
        # The last wound particle stays held (paper §4.2: constraining it keeps
        # the winding), and so does T's straightened run, so
        # that the winding keeps its shape until a Tightening or Release. On
        # a T that a scripted motion carries, the hold rides on T: held still,
        # it would unwind the turns as T moves away.
        self._hand_over(None)
        if self.k < self.n:
            self.world.control.release([self._particle(self.k)])
        elif self.t.body in self.world.carried_ropes:
            self.world.attach(self._particle(self.n - 1), self.params.target)

    def metrics(self) -> dict[str, float]:
        return {"wound": self.k, "targets": self.n}
