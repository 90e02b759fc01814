"""Wrapping a cloth around an object by Geodesic Control (paper §5.1, SPEC §6).

A corner's control line (the straight chain of particles from the cloth
centre to the corner) is laid onto a target line on the object (or on its
convex hull): a geodesic between two surface points, or one traced from the
start along a direction. The line is kept straight (strained) and its free
part is rotated about the last contact point until it meets the surface;
the contact then advances along the target line. Only the control-line
particles are driven; the rest of the cloth follows passively.

Geometry (per corner, at ``start``):

- i0, the contact particle: the last particle of the control line within
  one cloth thickness of the object (the control line must touch the
  target line at the start, paper §5.1);
- G, the target line on the surface, from the projection of particle i0
  (lifted by 1.5 thicknesses so that it lands on the object's side, not
  under it) to ``to``, or traced along ``angle``;
- O, G offset outward by the cloth's half thickness: where the particle
  centres lie when the cloth rests on the line. Offsets round convex edges
  (normals are swept across every turn of more than 10 degrees) so that the
  arc length along O, not along G, is the cloth's rest length.

Per frame (O(m) for m control-line particles): the contact arc c and the
free direction u give each particle with arc length s its target: O(s) for
s <= c, O(c) + (s - c) u beyond. u turns towards the desired direction
(the tangent of O ahead of c) about the contact at an angular speed that
moves the corner at ``speed``; the contact advances at ``speed`` only while
u is on the desired direction. With ``beyond: up`` the free part is aimed
at a point above the end of the line, so that corners end standing up there
(the start of a knot), each ``stop_short`` before the end.

Each particle's command moves towards its target at ``speed`` at most and
is kept a half thickness clear of every object and the ground
(``World.clear_of_solids``): a driven particle takes no contacts, and the
free part's straight line, or a command's way to it, can cut an object's
edge or vertex (on a box traced at 70 degrees the targets went 1.9 half
thicknesses into its top vertex, and the run went unstable).
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
import pydantic

from sandbox.model.sites import ClothSite
from sandbox.maneuvers.base import Maneuver, Params, Status, register
from sandbox.maneuvers.basic import TargetLike, resolve_target
from sandbox.record import WrapRecord

Corner = Literal["A", "B", "C", "D"]
LINE_OF_CORNER = {"A": 1, "B": 2, "C": 3, "D": 4}
_TURN = np.radians(10.0)  # widest normal turn between offset samples before an edge is rounded
UP = np.array([0.0, 1.0, 0.0])


def surface(world, name: str, hull: bool):
    """The (cached) ``SurfaceGeodesics`` of an object at its current pose, or of its convex hull."""
    from sandbox.geometry.mesh_geodesic import SurfaceGeodesics
    import trimesh

    cache = world.surfaces
    k = world.object_index(name)
    pose = world.objects.pose(k)
    key = (name, bool(hull))
    hit = cache.get(key)
    if hit is not None and all(np.array_equal(a, b) for a, b in zip(hit[0], pose)):
        return hit[1]
    verts, faces = world.objects.world_mesh(k)
    geo = SurfaceGeodesics(trimesh.Trimesh(np.asarray(verts, float), faces, process=False), hull=hull)
    cache[key] = (pose, geo)
    return geo


def _under_from(geo, G: np.ndarray) -> int | None:
    """First index of target line G, past its first tenth, on surface that faces the ground (normal more than
    30 degrees below the horizontal): under an overhang, or under the object where it rests on the cloth.
    None when G never runs there."""
    arc = _arc(G)
    far = np.flatnonzero(arc > 0.1 * arc[-1])
    if not len(far):
        return None
    _, face, _ = geo.project(G[far])
    down = np.flatnonzero(geo.face_normals[face] @ UP < -0.5)
    return int(far[down[0]]) if len(down) else None


def _runs_under(geo, G: np.ndarray) -> bool:
    """Whether target line G runs under the object (see ``_under_from``)."""
    return _under_from(geo, G) is not None


def offset_line(geo, line: np.ndarray, r: float) -> np.ndarray:
    """Offset a surface polyline outward by ``r`` (m), rounding convex edges.

    Samples every r / 2 along ``line``, offsets each along the normal of the
    face it lies on, inserts points on a circle of radius r about the edge
    wherever the normal turns more than 10 degrees between samples, then
    pushes every point to distance r from the surface (three fixed-point
    steps on the closest point).

    Returns:
        (k, 3) polyline (m).
    """
    from sandbox.geometry.mesh_geodesic import resample

    P = resample(line, 0.5 * r)
    _, face, _ = geo.project(P)
    N = geo.face_normals[face]
    pts = [P[0] + r * N[0]]
    for k in range(1, len(P)):
        cos = float(np.clip(N[k - 1] @ N[k], -1.0, 1.0))
        ang = np.arccos(cos)
        if ang > _TURN and ang < np.pi - 1e-3:
            m = int(np.ceil(ang / _TURN))
            pe = 0.5 * (P[k - 1] + P[k])
            for t in np.arange(1, m) / m:  # slerp between the two normals
                n = (np.sin((1 - t) * ang) * N[k - 1] + np.sin(t * ang) * N[k]) / np.sin(ang)
                pts.append(pe + r * n)
        pts.append(P[k] + r * N[k])
    X = np.asarray(pts)
    for _ in range(3):
        c = geo.project(X)[0]
        v = X - c
        norm = np.linalg.norm(v, axis=1, keepdims=True)
        ok = norm[:, 0] > 1e-9
        X[ok] = c[ok] + r * v[ok] / norm[ok]
    return X


def _arc(line: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])


def _at(line: np.ndarray, s_line: np.ndarray, s) -> np.ndarray:
    """Points at arc lengths ``s`` along a polyline (clamped to its ends)."""
    s = np.clip(np.asarray(s, float), 0.0, s_line[-1])
    return np.stack([np.interp(s, s_line, line[:, i]) for i in range(3)], axis=-1)


def _rotate_towards(u: np.ndarray, target: np.ndarray, max_angle: float) -> tuple[np.ndarray, float]:
    """Turn unit u towards unit target by at most ``max_angle`` (rad); returns (u, angle left)."""
    cos = float(np.clip(u @ target, -1.0, 1.0))
    ang = float(np.arccos(cos))
    if ang <= max_angle:
        return target.copy(), 0.0
    axis = np.cross(u, target)
    if np.linalg.norm(axis) < 1e-9:  # opposite: any perpendicular axis
        axis = np.cross(u, UP if abs(u[1]) < 0.9 else np.array([1.0, 0.0, 0.0]))
    axis /= np.linalg.norm(axis)
    a = max_angle
    out = u * np.cos(a) + np.cross(axis, u) * np.sin(a) + axis * (axis @ u) * (1 - np.cos(a))
    return out / np.linalg.norm(out), ang - a


class WrapParams(Params):
    """Parameters of ``Wrapping``.

    Attributes:
        body: the cloth.
        object: the object wrapped.
        corners: corners whose control lines (1-4 for A-D) are laid at once.
        lines: other control lines, each ``[from, to]`` between two cloth
            sites (a corner, ``center`` or ``[i, j]``): the straight chain of
            particles from ``from`` (the end that lies on or under the
            object) to ``to`` (the end that is laid over it); laid together
            with the corners' lines.
        to: end of the target line (a named site of an object or a point);
            with ``angle`` as well, the traced line is adjusted to end there
            keeping its route (paper §7).
        angle: start direction in degrees, about the outward normal at the
            start, from the direction straight up the object (counter-clockwise
            seen from outside); without ``to`` the line is traced this way for
            the control line's length. A user sets it to wind a corner
            around the thing wrapped rather than lay it to a place on it: a
            spiral around a bottle, where no site names where the corner ends.
        turns: expected turns about the vertical through the object (picks the
            route of a traced line that must end at ``to``).
        hull: target lines on the object's convex hull for every line, for a
            taut wrap that bridges each concavity. Without it the lines follow
            the surface, and the hull only where they must: an object of
            several separate parts (a car and its wheels), or a line that on
            the surface would run under the object (an overhang, a torus's
            inner side); the state's ``done`` event says which.
        beyond: what the part of a control line longer than its target line
            does: ``surface`` follows the surface geodesic on; ``up`` stands up
            along the surface normal at ``to`` (corners gathered for a knot).
        stop_short: with ``up``, each line ends this far before ``to`` (m);
            default: the cloth thickness when several corners go at once.
        speed: how fast the corner and the contact move (m/s).
        tolerance: done when every laid particle is within this distance of
            its target line (m); default half the cloth thickness.
        hold: once the line is laid, keep holding all of it (``line``), or
            only its last laid particle and what stands beyond it (``end``):
            a line on a geodesic stays put with only its end held (paper
            §4.2, §7), and the check then measures the passive cloth.
        settle: seconds to wait after the release of ``hold: end`` before the
            overlap is checked.
    """

    body: str
    object: str
    corners: Annotated[list[Corner], pydantic.Field(max_length=4)] = []
    lines: Annotated[list[tuple[ClothSite, ClothSite]], pydantic.Field(max_length=4)] = []
    to: TargetLike | None = None
    angle: float | None = None
    turns: float | None = None
    hull: bool = False
    beyond: Literal["surface", "up"] = "surface"
    stop_short: Annotated[float, pydantic.Field(ge=0)] | None = None
    speed: Annotated[float, pydantic.Field(gt=0)] = 0.4
    tolerance: Annotated[float, pydantic.Field(gt=0)] | None = None
    hold: Literal["line", "end"] = "line"
    settle: Annotated[float, pydantic.Field(ge=0)] = 0.5

    @pydantic.model_validator(mode="after")
    def _line_given(self):
        if self.to is None and self.angle is None:
            raise ValueError("give 'to' (an end point), 'angle' (a traced direction), or both")
        if len(set(self.corners)) != len(self.corners):
            raise ValueError(f"corners repeat: {self.corners}")
        for a, b in self.lines:
            if a == b:
                raise ValueError(f"line {[a, b]}: a control line needs two different cloth points")
        if not 1 <= len(self.corners) + len(self.lines) <= 4:
            raise ValueError(f"give 1 to 4 control lines in all ('corners' and 'lines'), "
                             f"got {len(self.corners) + len(self.lines)}")
        if self.beyond == "up" and self.to is None:
            raise ValueError("beyond: up needs 'to' (where the corners stand up)")
        return self


def _site_text(site) -> str:
    """A cloth site as it reads in a line's name: ``A``, ``center``, ``[3,40]``."""
    return f"[{site[0]},{site[1]}]" if isinstance(site, (list, tuple)) else str(site)


class _Line:
    """One control line being laid onto its target line."""

    def __init__(self, corner, idx, rest_arc, i0, G, O, N, c_end, aim, u0):
        self.corner = corner
        self.idx = idx  # (k,) global particle indices, centre -> corner
        self.i0 = i0  # contact particle (position in idx)
        self.s = rest_arc[i0:] - rest_arc[i0]  # arc of each laid/free particle from the contact
        self.G = G  # target line on the surface
        self.O = O  # target line of the particle centres
        self.N = N  # outward surface normal at each point of O
        self.sO = _arc(O)
        self.c_end = c_end
        self.aim = aim  # None, or (point above the end, outward normal there)
        self.c = 0.0
        self.u = u0

    @property
    def driven(self) -> np.ndarray:
        return self.idx[self.i0:]

    def tangent(self, c: float, step: float) -> np.ndarray:
        a, b = _at(self.O, self.sO, [c, min(c + step, self.sO[-1])])
        d = b - a
        if np.linalg.norm(d) < 1e-9:
            a, b = _at(self.O, self.sO, [max(c - step, 0.0), c])
            d = b - a
        return d / max(np.linalg.norm(d), 1e-12)

    def desired(self, c: float, step: float) -> np.ndarray:
        """Direction the free part should have with the contact at c."""
        t = self.tangent(c, step)
        if self.aim is None:
            return t
        point, normal = self.aim
        if c >= self.c_end - 1e-9:
            return normal
        d = point - _at(self.O, self.sO, c)
        d /= max(np.linalg.norm(d), 1e-12)
        # Aim above the end once that direction leaves the surface; before,
        # lie along it.
        n_here = _at(self.N, self.sO, c)
        return d if d @ t > 0 and d @ n_here >= 0 else t

    def targets(self) -> np.ndarray:
        s = self.s
        on = s <= self.c
        out = np.empty((len(s), 3))
        out[on] = _at(self.O, self.sO, s[on])
        base = _at(self.O, self.sO, self.c)
        free = s[~on] - self.c
        point = None if self.aim is None else self.aim[0]
        to_aim = None if point is None else point - base
        if point is None or to_aim @ self.u < 0.95 * np.linalg.norm(to_aim):
            out[~on] = base + free[:, None] * self.u  # not aimed (yet): straight on
        else:  # aimed above the end: up to the aim point, then along the normal there
            normal = self.aim[1]
            leg = float(to_aim @ self.u)
            first = np.minimum(free, leg)
            out[~on] = base + first[:, None] * self.u + (free - first)[:, None] * normal
        return out


@register
class Wrapping(Maneuver):
    """Lay control lines of a cloth onto target lines of an object (paper §5.1).

    Records ``world.record.wraps[(cloth, corner)]`` (target lines and particles) for
    the ``overlap_error`` and ``coverage`` criteria. Fails at the start when
    a control line does not touch the object. The lines stay held after.
    """

    name = "Wrapping"
    Params = WrapParams

    def start(self) -> None:
        p = self.params
        w = self.world
        cloth = w.cloth(p.body)
        self.cloth = cloth
        self.r = 0.5 * cloth.thickness
        self.step = 0.5 * min(cloth.spacing)
        self.tol = p.tolerance if p.tolerance is not None else 0.5 * cloth.thickness
        geo = surface(w, p.object, p.hull)
        notes = [f"object {p.object!r}: {geo.hull_reason}"] if geo.hull_reason else []
        k_obj = w.object_index(p.object)
        verts_lo = np.asarray(w.objects.world_mesh(k_obj)[0]).min(axis=0)
        x = w.positions().astype(np.float64)
        q = None
        if p.to is not None:
            q = geo.project(resolve_target(w, p.to))[0][0]
        specs = [(c, f"control line {LINE_OF_CORNER[c]} (corner {c})", cloth.control_line(LINE_OF_CORNER[c]))
                 for c in p.corners]
        for a, b in p.lines:
            label = f"{_site_text(a)}-{_site_text(b)}"
            specs.append((label, f"control line {label}", cloth.line_between(a, b)))
        stop_short = p.stop_short if p.stop_short is not None else (cloth.thickness if len(specs) > 1 else 0.0)
        self.lines: list[_Line] = []
        for corner, what, idx in specs:
            ij = np.stack([(idx - cloth.start) % cloth.nx, (idx - cloth.start) // cloth.nx], axis=1)
            rest = ij * np.asarray(cloth.spacing)
            rest_arc = _arc(rest)
            d, _, kk = w.objects.query_numpy(x[idx])
            touching = np.flatnonzero((kk == k_obj) & (d <= cloth.thickness))
            # The line leaves the object where it leaves the object's shadow:
            # rotating about a point under an overhang would sweep through it.
            # Under an object that rests on the cloth counts as touching its
            # hull (a car on its wheels).
            shadow = np.flatnonzero((w.shadow_distance(p.object, x[idx]) <= self.r)
                                    & (np.abs(verts_lo[1] - x[idx, 1]) <= cloth.thickness))
            touching = np.union1d(touching, shadow)
            if len(touching) == 0:
                self.message = (f"{what} of {p.body!r} does not "
                                f"touch {p.object!r}: place the object on the cloth first (Anchoring with object)")
                self.lines = []
                return
            i0 = int(touching.max())
            if i0 >= len(idx) - 1:
                self.message = f"the end of {what} of {p.body!r} already lies on {p.object!r}: nothing to wrap"
                self.lines = []
                return
            length = rest_arc[-1] - rest_arc[i0]
            line_geo = geo
            G = self._target_line(geo, x[idx[i0]], q, length, corner)
            if not geo.is_hull and _runs_under(geo, G):
                # Cloth cannot lie under the object: where the surface's
                # line would, the line follows the hull, which bridges the
                # underside (a torus's inner side, an arm's overhang).
                line_geo = surface(w, p.object, True)
                q_hull = None if q is None else line_geo.project(resolve_target(w, p.to))[0][0]
                G = self._target_line(line_geo, x[idx[i0]], q_hull, length, corner)
                notes.append(f"{what}: on the surface its target line ran under {p.object!r}; it follows the "
                             "convex hull")
            cut = _under_from(line_geo, G)
            if cut is not None:  # no cloth under the object: the line ends there and the rest stays free
                G = G[: max(cut, 2)]
                notes.append(f"{what}: its target line ends where it would run under {p.object!r}")
            # The line starts at the contact particle itself, so that its
            # link to the held part of the cloth keeps its length.
            O = offset_line(line_geo, G, self.r * 1.05)
            N = O - line_geo.project(O)[0]
            N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
            # The cloth comes out from under the object: the target line
            # starts where the surface stops facing the ground.
            first = int(np.argmax(N @ UP > -0.9)) if (N @ UP > -0.9).any() else 0
            O, N = self._above_ground(O[first:]), N[first:]
            # From the contact, the line goes to where a straight edge from
            # it touches O (the supporting tangent, searched over O's first
            # 30%): the free part then turns up outside the object, not into
            # a rim above the contact.
            x0 = x[idx[i0]].astype(np.float64)
            out = x[idx[-1]] - x0
            out[1] = 0.0
            out /= max(np.linalg.norm(out), 1e-12)
            chord = O - x0
            reach = np.flatnonzero(_arc(O) <= 0.3 * _arc(O)[-1])
            slope = (chord[reach] @ out) / np.maximum(np.linalg.norm(chord[reach], axis=1), 1e-12)
            k = int(reach[np.argmax(slope)])
            O = np.vstack([x0, O[k:]])
            N = np.vstack([N[k], N[k:]])
            L = float(_arc(O)[-1])
            aim = None
            if p.beyond == "up":
                c_end = max(min(L - stop_short, length), 0.0)
                keep = max(2, int(np.searchsorted(_arc(O), c_end + 1e-9)) + 1)
                O, N = O[:keep], N[:keep]
                n_end = N[-1]
                aim = (_at(O, _arc(O), c_end) + n_end * max(length - c_end, 0.0), n_end)
            else:
                c_end = min(L, length)
            u0 = x[idx[-1]] - x[idx[i0]]
            u0 /= max(np.linalg.norm(u0), 1e-12)
            self.lines.append(_Line(corner, idx, rest_arc, i0, G, O, N, c_end, aim, u0))
        self.note = "; ".join(notes)
        self.cmd = {ln.corner: x[ln.driven].copy() for ln in self.lines}
        self.released_at = None  # tick at which ``hold: end`` let the laid particles go
        self.total = sum(ln.c_end for ln in self.lines) or 1.0
        for ln in self.lines:
            w.record.wraps[(p.body, ln.corner)] = WrapRecord(p.object, ln.O, ln.G, ln.driven, ln.s, ln.c_end)
            w.control.drive(ln.driven, self.cmd[ln.corner])

    def _target_line(self, geo, x0, q, length: float, corner: str) -> np.ndarray:
        """G: from the contact's foot on the surface to ``to`` or along ``angle``."""
        p = self.params
        from sandbox.geometry.mesh_geodesic import polyline_length

        p0 = geo.project(x0)[0][0]
        if p.angle is None:
            G = geo.between(p0, q)
        else:
            # Climb onto the object's side first: the traced direction is
            # measured there, from the direction straight up.
            side = geo.project(x0 + 3.0 * self.r * UP)[0][0]
            head = geo.between(p0, side)
            _, face, _ = geo.project(side)
            n = geo.face_normals[face[0]]
            up = UP - (UP @ n) * n
            if np.linalg.norm(up) < 0.2:
                raise ValueError(f"corner {corner}: the target line starts on a face that looks "
                                 f"{'up' if n[1] > 0 else 'down'}; 'angle' needs a start on the object's side")
            up /= np.linalg.norm(up)
            a = np.radians(p.angle)
            t0 = np.cos(a) * up + np.sin(a) * np.cross(n, up)
            if q is None:
                return np.vstack([head[:-1], geo.trace(side, t0, 1.2 * length + 4 * self.r)])
            G = np.vstack([head[:-1], geo.trace_to(side, t0, q, turns_hint=p.turns)])
        excess = length - polyline_length(G)
        if p.beyond == "surface" and excess > 0:
            tail = G[-1] - G[-2]
            ext = geo.trace(G[-1], tail, excess + 4 * self.r)
            G = np.vstack([G, ext[1:]])
        return G

    def _above_ground(self, O: np.ndarray) -> np.ndarray:
        gh = self.world.ground_height
        if gh is not None:
            O = O.copy()
            O[:, 1] = np.maximum(O[:, 1], gh + self.r)
        return O

    def update(self) -> Status:
        if not self.lines:
            return Status.FAILED
        p = self.params
        self.ticks += 1
        if self.released_at is not None:
            return self._settling()
        dt = 1.0 / self.world.fps
        x = self.world.positions()
        settled = True
        done_arc = 0.0
        for ln in self.lines:
            cmd = self.cmd[ln.corner]
            goal = self._clear(ln.targets())
            lag = float(np.linalg.norm(goal - cmd, axis=1).max())
            if lag <= p.speed * dt:  # the command has caught up: move the line on
                self._advance(ln, p.speed * dt)
                goal = self._clear(ln.targets())
            delta = goal - cmd
            dist = np.linalg.norm(delta, axis=1, keepdims=True)
            cmd += delta * np.minimum(1.0, p.speed * dt / np.maximum(dist, 1e-12))
            cmd[:] = self._clear(cmd)  # its way to the goal may cut an edge too
            self.world.control.drive(ln.driven, cmd)
            finished = ln.c >= ln.c_end - 1e-9 and float(np.linalg.norm(goal - cmd, axis=1).max()) < 1e-6
            settled &= finished and self._overlap(ln, x)[1] <= self.tol
            done_arc += ln.c
        self.progress = min(1.0, done_arc / self.total)
        if not settled:
            return Status.RUNNING
        if p.hold == "line":
            return Status.DONE
        for ln in self.lines:  # keep the end (and what stands beyond it) held
            laid = ln.driven[ln.s < ln.c_end - 1e-9]
            self.world.control.release(laid[:-1] if len(laid) == len(ln.driven) else laid)
        self.released_at = self.ticks
        return Status.RUNNING

    def _clear(self, points: np.ndarray) -> np.ndarray:
        """``points`` kept a half thickness clear of every object and the ground: a driven particle takes no
        contacts, and the free part's straight line can cut an object's edge or vertex."""
        return self.world.clear_of_solids(points, self.r)

    def _settling(self) -> Status:
        if self.ticks - self.released_at < self.params.settle * self.world.fps:
            return Status.RUNNING
        x = self.world.positions()
        worst = max(self._overlap(ln, x)[1] for ln in self.lines)
        if worst <= self.tol:
            return Status.DONE
        self.message = (f"the released control line left its target line: {worst * 1e3:.1f} mm off "
                        f"(tolerance {self.tol * 1e3:.1f} mm)")
        return Status.FAILED

    def _advance(self, ln: _Line, budget: float) -> None:
        """Turn the free part, then move the contact, within one frame's budget."""
        free = max(float(ln.s[-1] - ln.c), self.step)
        rot = budget / free  # rad: the corner moves at most ``budget``
        arc = budget
        inc = 0.5 * self.step
        while True:
            want = ln.desired(ln.c, self.step)
            if ln.u @ want < 0.0:  # a wide turn goes the outside way: towards the surface normal first
                normal = _at(ln.N, ln.sO, ln.c)
                normal = normal / max(np.linalg.norm(normal), 1e-12)
                half = normal + want  # halfway from the normal to the line: never a turn back along the ground
                want = half / np.linalg.norm(half) if np.linalg.norm(half) > 0.5 else normal
            want = self._clear_of_ground(ln, want, free)
            ln.u, left = _rotate_towards(ln.u, want, rot)
            if left > 0.0:
                return
            rot = max(rot - float(np.arccos(np.clip(ln.u @ want, -1, 1))), 0.0)
            if ln.c >= ln.c_end - 1e-12 or arc <= 0.0:
                return
            dc = min(inc, arc, ln.c_end - ln.c)
            ln.c += dc
            arc -= dc
            free = max(float(ln.s[-1] - ln.c), self.step)

    def _clear_of_ground(self, ln: _Line, want: np.ndarray, free: float) -> np.ndarray:
        """``want``, tilted up where the free part along it would dip below the ground.

        The free part is straight from the contact: its end stays a cloth
        half-thickness above the ground when its direction rises at least
        ``need`` = (ground + r - contact height) / free length. A direction
        below that keeps its heading and rises just enough. Both the free
        part's direction and ``want`` then lie above that cone, and so does
        every direction the turn between them passes (the shorter arc
        between two directions of a spherical cap stays in it), so the free
        part never turns into the ground, under an overhang or a bulge
        either.
        """
        gh = self.world.ground_height
        if gh is None:
            return want
        base = _at(ln.O, ln.sO, ln.c)
        need = float(np.clip((gh + self.r - base[1]) / max(free, self.step), -1.0, 1.0))
        if want[1] >= need:
            return want
        heading = np.array([want[0], 0.0, want[2]])
        if np.linalg.norm(heading) < 1e-9:
            heading = np.array([ln.u[0], 0.0, ln.u[2]])
        heading /= max(np.linalg.norm(heading), 1e-12)
        return heading * np.sqrt(1.0 - need * need) + UP * need

    def _overlap(self, ln: _Line, x: np.ndarray) -> tuple[float, float]:
        """Mean and max distance (m) of the laid particles from the target line O."""
        from sandbox.geometry.mesh_geodesic import polyline_distance

        on = ln.s <= min(ln.c, ln.c_end) + 1e-9
        if not on.any():
            return 0.0, 0.0
        d = polyline_distance(x[ln.driven[on]].astype(np.float64), ln.O)
        return float(d.mean()), float(d.max())

    def metrics(self) -> dict[str, float]:
        if not self.lines:
            return {}
        x = self.world.positions()
        out = {}
        for ln in self.lines:
            mean, mx = self._overlap(ln, x)
            out[f"{ln.corner}_contact"] = round(ln.c, 5)
            out[f"{ln.corner}_overlap_mean"] = round(mean, 6)
            out[f"{ln.corner}_overlap_max"] = round(mx, 6)
        return out
