"""Basic maneuvers: Anchoring, MoveTo, Release, Wait.

Sites are named per body (see ``World.site_particles``): rope ``start``,
``end``, an index or an index range ``[i0, i1]``; cloth corners ``A``-``D``,
``center``, ``[i, j]`` or a control line ``line1``-``line4``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Union

import numpy as np
import pydantic

from sandbox.maneuvers.base import Maneuver, Params, Status, register
from sandbox.model.sites import MAX_COORD
from sandbox.objects.sites import SITE_NAMES

Coord = Annotated[float, pydantic.Field(ge=-MAX_COORD, le=MAX_COORD, allow_inf_nan=False)]
Vec3 = tuple[Coord, Coord, Coord]
"""A point or offset (m), within the coordinates a level may give."""
Site = Union[str, int, tuple[int, int]]


class Target(Params):
    """A point given directly or relative to an object's named site.

    Either ``point`` (m) or ``object`` (+ ``site``: top, bottom, front, back,
    left, right, center); ``offset`` (m) is added in both cases: to a point
    in world axes, to an object's site in the object's own axes (it turns
    with the object), so a place written next to an object moves and turns
    with it wherever the object is placed.
    """

    point: Vec3 | None = None
    object: str | None = None
    site: Literal[SITE_NAMES] = "top"
    offset: Vec3 = (0.0, 0.0, 0.0)

    @pydantic.model_validator(mode="after")
    def _one_of(self):
        if (self.point is None) == (self.object is None):
            raise ValueError("give exactly one of 'point' or 'object'")
        return self


def resolve_target(world, target: Target) -> np.ndarray:
    """World-space position (m) of a Target, at the object's pose now."""
    if target.point is not None:
        base = np.asarray(target.point, float)
    else:
        k = world.object_index(target.object)
        sites = world.object_sites(target.object)
        if target.site not in sites:
            raise ValueError(f"object {target.object!r} has no site {target.site!r}; allowed: {', '.join(sites)}")
        base = np.asarray(sites[target.site], float)
        _, rot = world.objects.pose(k)
        return base + rot @ np.asarray(target.offset, float)
    return base + np.asarray(target.offset, float)



def follow_target(world, target: Target):
    """A Target as a function of no arguments giving its world position now (m), for a maneuver that aims
    at it every frame: the site is found once (``resolve_target``, a ray cast into the object) and then
    carried with the object's pose, so each call costs a pose read, not a search of the mesh."""
    where = resolve_target(world, target)
    if target.point is not None:
        return lambda: where
    k = world.object_index(target.object)
    pos0, rot0 = world.objects.pose(k)
    local = rot0.T @ (where - pos0)

    def now() -> np.ndarray:
        pos, rot = world.objects.pose(k)
        return pos + rot @ local

    return now

def _as_target(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return {"point": value}
    return value


TargetLike = Annotated[Target, pydantic.BeforeValidator(_as_target)]


class WaitParams(Params):
    ticks: Annotated[int, pydantic.Field(ge=0, le=10**9)] = 0  # frames to wait
    seconds: Annotated[float, pydantic.Field(ge=0, le=1e6)] = 0.0  # simulated time to wait, added to ``ticks``


@register
class Wait(Maneuver):
    """Do nothing for ``ticks`` frames plus ``seconds`` of simulated time."""

    name = "Wait"
    Params = WaitParams

    def start(self) -> None:
        self.total = self.params.ticks + int(round(self.params.seconds * self.world.fps))

    def update(self) -> Status:
        self.ticks += 1
        self.progress = 1.0 if self.total == 0 else min(1.0, self.ticks / self.total)
        return Status.DONE if self.ticks >= self.total else Status.RUNNING


class AnchorParams(Params):
    body: str  # the rope or cloth
    sites: list[Site]  # its particles held: rope start/end/index, cloth corner/center/[i, j], or "all"
    at: TargetLike | None = None  # where to hold them (a point or an object's site); default: where they are
    # an object put on the cloth with the sites under the centre of its base
    # (paper Table 2); every particle it presses is held as well
    object: str | None = None


@register
class Anchoring(Maneuver):
    """Hold named sites of a rope or cloth where they are (or at ``at``).

    With ``object`` (paper Table 2, "position of cloth and object"): the
    object is placed on the body with the sites' centroid under the centre
    of its base, resting on the body's upper side; the sites and every
    particle of the body that the object then presses (within one collision
    radius of its surface and inside its shadow: what its weight pins) are
    held.
    """

    name = "Anchoring"
    Params = AnchorParams

    def start(self) -> None:
        w = self.world
        p = self.params
        idx = np.concatenate([w.site_particles(p.body, s) for s in p.sites])
        x_all = w.positions()
        x = x_all[idx]
        if p.at is not None:
            x = x - x.mean(axis=0) + resolve_target(w, p.at)
        if p.object is not None:
            idx, x = self._place(idx, x, x_all)
        w.control.drive(idx, x)

    def _place(self, idx, x, x_all):
        w = self.world
        p = self.params
        k = w.object_index(p.object)
        if w.object_specs[p.object].motion is not None:
            raise ValueError(f"Anchoring: object {p.object!r} follows scripted motion and cannot be placed")
        verts, _ = w.objects.world_mesh(k)
        lo, hi = verts.min(axis=0), verts.max(axis=0)
        body = w.site_particles(p.body, "all")
        r = float(w.model.data.radius[body].max())
        base = np.array([0.5 * (lo[0] + hi[0]), lo[1], 0.5 * (lo[2] + hi[2])])
        site = x.mean(axis=0)
        pos, rot = w.objects.pose(k)
        w.objects.place(k, pos + np.array([site[0], site[1] + r + 1e-4, site[2]]) - base, rot)
        d, _, kk = w.objects.query_numpy(x_all[body])
        # What the object presses: touching it and inside its shadow (not the
        # ring of cloth around its base, which is free to be lifted).
        under = body[(kk == k) & (d <= 2.0 * r) & (w.shadow_distance(p.object, x_all[body]) <= 0.0)]
        keep = np.setdiff1d(under, idx)
        return np.concatenate([idx, keep]), np.concatenate([x, x_all[keep]])

    def update(self) -> Status:
        self.progress = 1.0
        return Status.DONE


class MoveParams(Params):
    body: str  # the rope or cloth
    sites: list[Site]  # the particles moved, together (their offsets from their centre are kept)
    to: TargetLike  # where their centre goes: a point or an object's site
    via: list[TargetLike] = []  # points passed through on the way, in order
    speed: Annotated[float, pydantic.Field(gt=0)] = 0.5  # m/s of the centre
    tolerance: Annotated[float, pydantic.Field(gt=0)] = 1e-3  # m from the target that counts as arrived
    hold: bool = True  # keep holding the sites there once arrived (else let go)


@register
class MoveTo(Maneuver):
    """Drive sites through intermediate targets to a target (paper Eq. 4).

    The sites move as a rigid group: each frame their centroid advances at most
    ``speed * dt`` towards the current waypoint; done when the last waypoint is
    reached within ``tolerance``. With ``hold`` the sites stay driven after.
    """

    name = "MoveTo"
    Params = MoveParams

    def start(self) -> None:
        p = self.params
        self.idx = np.concatenate([self.world.site_particles(p.body, s) for s in p.sites])
        x = self.world.positions()[self.idx].astype(np.float64)
        self.offsets = x - x.mean(axis=0)
        self.pos = x.mean(axis=0)
        self.waypoints = [resolve_target(self.world, t) for t in [*p.via, p.to]]
        self.leg = 0
        self.total = sum(
            np.linalg.norm(b - a) for a, b in zip([self.pos, *self.waypoints[:-1]], self.waypoints)
        ) or 1.0
        self.travelled = 0.0
        self.world.control.drive(self.idx, self.pos + self.offsets)

    def update(self) -> Status:
        step = self.params.speed / self.world.fps
        while step > 0 and self.leg < len(self.waypoints):
            d = self.waypoints[self.leg] - self.pos
            dist = float(np.linalg.norm(d))
            if dist <= step:
                self.pos = self.waypoints[self.leg].copy()
                self.travelled += dist
                step -= dist
                self.leg += 1
            else:
                self.pos = self.pos + d * (step / dist)
                self.travelled += step
                step = 0.0
        self.world.control.drive(self.idx, self.pos + self.offsets)
        self.progress = min(1.0, self.travelled / self.total)
        if self.leg >= len(self.waypoints):
            # Positions are those after the last physics step: done once the
            # sites themselves (not just their command) are at the target.
            x = self.world.positions()[self.idx].mean(axis=0)
            if np.linalg.norm(x - self.waypoints[-1]) <= self.params.tolerance:
                self.progress = 1.0
                return Status.DONE
        return Status.RUNNING

    def stop(self) -> None:
        if not self.params.hold:
            self.world.control.release(self.idx)

    def metrics(self) -> dict[str, float]:
        return {"leg": self.leg, "distance_left": float(np.linalg.norm(self.waypoints[-1] - self.pos))}


class ReleaseParams(Params):
    body: str  # the rope or cloth
    sites: list[Site] = ["all"]  # the particles let go ("all": every held particle of the body)


@register
class Release(Maneuver):
    """Let sites of a rope or cloth move freely again."""

    name = "Release"
    Params = ReleaseParams

    def start(self) -> None:
        idx = np.concatenate([self.world.site_particles(self.params.body, s) for s in self.params.sites])
        self.world.control.release(idx)

    def update(self) -> Status:
        self.progress = 1.0
        return Status.DONE
