"""Model (static), State (changes every step) and Control (kinematic targets).

A :class:`Model` is made once per level from :class:`ModelData`; ``state()``
and ``control()`` allocate the per-run data. Fields are float32 on every
backend.
"""


import numpy as np
import taichi as ti

from sandbox import runtime
from sandbox.model.builder import ModelData


@ti.data_oriented
class Model:
    """Static particle data of a scene.

    Fields (n particles, m distance constraints, s rope segments):
        inv_mass: (n,) f32, 1/kg.
        radius: (n,) f32, m; rope radius or half the cloth thickness.
        friction: (n,) f32, Coulomb coefficient against ground and objects.
        damping: (n,) f32, fraction of velocity lost per second.
        cloth_id: (n,) i32, cloth index or -1 for ropes.
        grid_ij: (n,) ivec2, cloth grid coordinates.
        edge: (m,) ivec2, particle pairs sorted by colour.
        rest: (m,) f32, m.
        compliance: (m,) f32, m/N (XPBD alpha).
        kind: (m,) i32, STRETCH | SHEAR | BEND.
        group: (m,) i32, body index of each edge (for strain metrics).
        segment: (s,) ivec2, rope segments; segment_rope: (s,) i32.
    """

    def __init__(self, data: ModelData) -> None:
        self.data = data
        n, m, s = data.n_particles, len(data.edges), len(data.segments)
        self.n, self.m, self.s = n, m, s
        self.n_bodies = len(data.ropes) + len(data.cloths)
        self.colors = data.colors
        self.x0 = np.asarray(data.x0, np.float32)
        self.inv_mass = ti.field(ti.f32, shape=n)
        self.radius = ti.field(ti.f32, shape=n)
        self.friction = ti.field(ti.f32, shape=n)
        self.damping = ti.field(ti.f32, shape=n)
        self.cloth_id = ti.field(ti.i32, shape=n)
        self.grid_ij = ti.Vector.field(2, ti.i32, shape=n)
        runtime.defer(self.inv_mass.from_numpy, data.inv_mass.astype(np.float32))
        runtime.defer(self.radius.from_numpy, data.radius.astype(np.float32))
        runtime.defer(self.friction.from_numpy, data.friction.astype(np.float32))
        runtime.defer(self.damping.from_numpy, data.damping.astype(np.float32))
        runtime.defer(self.cloth_id.from_numpy, data.cloth_id.astype(np.int32))
        runtime.defer(self.grid_ij.from_numpy, data.grid_ij.astype(np.int32))
        mm = max(m, 1)
        self.edge = ti.Vector.field(2, ti.i32, shape=mm)
        self.rest = ti.field(ti.f32, shape=mm)
        self.compliance = ti.field(ti.f32, shape=mm)
        self.kind = ti.field(ti.i32, shape=mm)
        self.group = ti.field(ti.i32, shape=mm)
        if m:
            runtime.defer(self.edge.from_numpy, data.edges.astype(np.int32))
            runtime.defer(self.rest.from_numpy, data.rest.astype(np.float32))
            runtime.defer(self.compliance.from_numpy, data.compliance.astype(np.float32))
            runtime.defer(self.kind.from_numpy, data.kind.astype(np.int32))
            runtime.defer(self.group.from_numpy, data.group.astype(np.int32))
        ss = max(s, 1)
        self.segment = ti.Vector.field(2, ti.i32, shape=ss)
        self.segment_rope = ti.field(ti.i32, shape=ss)
        if s:
            runtime.defer(self.segment.from_numpy, data.segments.astype(np.int32))
            runtime.defer(self.segment_rope.from_numpy, data.segment_rope.astype(np.int32))
        self.max_thickness = max([c.thickness for c in data.cloths], default=0.0)
        self.self_collision = any(c.self_collision for c in data.cloths)

    def state(self) -> "State":
        """A new State at the rest configuration, at rest."""
        st = State(self.n, self.m)
        runtime.defer(st.x.from_numpy, self.x0)
        return st

    def control(self) -> "Control":
        """A new Control with the model's pins held at their rest positions."""
        ctl = Control(self.n, self.x0)
        if len(self.data.pins):
            ctl.drive(self.data.pins, self.x0[self.data.pins])
        return ctl


@ti.data_oriented
class State:
    """Positions and velocities.

    Fields:
        x: (n,) vec3 f32, m.
        v: (n,) vec3 f32, m/s.
        x_prev: (n,) vec3 f32, m, positions at the start of the substep.
        dx: (n,) vec3 f32, m, Jacobi correction accumulator.
        lam: (m,) f32, XPBD multipliers of the distance constraints.
    """

    def __init__(self, n: int, m: int) -> None:
        self.n = n
        self.x = ti.Vector.field(3, ti.f32, shape=n)
        self.v = ti.Vector.field(3, ti.f32, shape=n)
        self.x_prev = ti.Vector.field(3, ti.f32, shape=n)
        self.dx = ti.Vector.field(3, ti.f32, shape=n)
        self.lam = ti.field(ti.f32, shape=max(m, 1))

    def save(self) -> tuple[np.ndarray, np.ndarray]:
        """Copy of (x, v) for rollback."""
        return self.x.to_numpy(), self.v.to_numpy()

    def restore(self, snap: tuple[np.ndarray, np.ndarray]) -> None:
        """Restore a copy made by :meth:`save`."""
        self.x.from_numpy(snap[0])
        self.v.from_numpy(snap[1])


GRIP_GIVE = 0.002
"""m from its place at which a gripping hand (``Control.grip``) pulls with all its force: within it, a
spring of grip / GRIP_GIVE N/m (1 N: 500 N/m) that the rope's own tension displaces by less than that."""


@ti.data_oriented
class Control:
    """Kinematic targets written by maneuvers (paper Eq. 4).

    A driven particle moves on a straight line from ``src`` (its position at
    the start of the frame) to ``dst`` during the frame's substeps and has no
    inverse mass for the solver. Maneuvers pass intermediate targets, so
    ``dst`` is never far away. A pulled particle stays dynamic and feels a
    constant force ``f`` and a drag ``-b v`` (a hand that pulls with a given
    tension instead of moving to a given place, at most at speed |f| / b).
    A gripped particle is held at ``dst`` by a hand that gives: it stays
    dynamic and is drawn back towards ``dst`` with a force that grows
    linearly to ``grip_force`` N at ``GRIP_GIVE`` from it and stays there,
    against the same drag. A rope pulling harder than the grip slips
    through the hand; one pulling less sits within ``GRIP_GIVE`` of its
    place. (Held kinematically, a tightened knot between four hands has no
    way to give: it snapped through itself, 5 mm deep within three frames.)

    Fields:
        driven: (n,) i32, 1 if kinematic, 2 if pulled by ``force``, 3 if gripped, else 0.
        src, dst: (n,) vec3 f32, m (``dst``: a gripped particle's place).
        force: (n,) vec3 f32, N, on pulled particles.
        drag: (n,) f32, N s/m, on pulled and gripped particles.
        grip_force: (n,) f32, N, the most a gripping hand pulls with.
    """

    def __init__(self, n: int, x0: np.ndarray) -> None:
        self.n = n
        self.driven = ti.field(ti.i32, shape=n)
        self.src = ti.Vector.field(3, ti.f32, shape=n)
        self.dst = ti.Vector.field(3, ti.f32, shape=n)
        self.force = ti.Vector.field(3, ti.f32, shape=n)
        self.drag = ti.field(ti.f32, shape=n)
        self.grip_force = ti.field(ti.f32, shape=n)
        self._driven = np.zeros(n, np.int32)
        self._dst = np.asarray(x0, np.float32).copy()
        self._force = np.zeros((n, 3), np.float32)
        self._drag = np.zeros(n, np.float32)
        self._grip = np.zeros(n, np.float32)
        self._dirty = True

    def drive(self, idx, targets) -> None:
        """Drive particles ``idx`` to ``targets`` (m) by the end of the next frame."""
        idx = np.atleast_1d(np.asarray(idx, np.int64))
        self._driven[idx] = 1
        self._dst[idx] = np.asarray(targets, np.float32).reshape(len(idx), 3)
        self._force[idx] = 0.0
        self._drag[idx] = 0.0
        self._grip[idx] = 0.0
        self._dirty = True

    def pull(self, idx, forces, drag) -> None:
        """Let particles ``idx`` move under gravity, constant ``forces`` (N, one
        per particle) and a drag of ``drag`` N s/m (their speed stays below |f| / drag)."""
        idx = np.atleast_1d(np.asarray(idx, np.int64))
        self._driven[idx] = 2
        self._force[idx] = np.asarray(forces, np.float32).reshape(len(idx), 3)
        self._drag[idx] = drag
        self._grip[idx] = 0.0
        self._dirty = True

    def grip(self, idx, places, force, drag) -> None:
        """Hold particles ``idx`` at ``places`` (m) by a hand that pulls each back with at most ``force`` N
        (``GRIP_GIVE`` from its place and beyond) against a drag of ``drag`` N s/m: a hand that holds an end
        as hard as it pulled it, and lets it slip when the rope pulls harder."""
        if not force > 0 or not drag >= 0:
            raise ValueError(f"a grip needs a force > 0 N and a drag >= 0 N s/m, got {force} and {drag}")
        idx = np.atleast_1d(np.asarray(idx, np.int64))
        self._driven[idx] = 3
        self._dst[idx] = np.asarray(places, np.float32).reshape(len(idx), 3)
        self._force[idx] = 0.0
        self._drag[idx] = drag
        self._grip[idx] = force
        self._dirty = True

    def release(self, idx) -> None:
        """Let particles ``idx`` move freely again (neither driven nor pulled)."""
        idx = np.atleast_1d(np.asarray(idx, np.int64))
        self._driven[idx] = 0
        self._force[idx] = 0.0
        self._drag[idx] = 0.0
        self._grip[idx] = 0.0
        self._dirty = True

    def is_driven(self, idx) -> np.ndarray:
        """Whether particles ``idx`` are held by a hand: kinematic, or gripped."""
        return np.isin(self._driven[np.asarray(idx)], (1, 3))

    def is_kinematic(self, idx) -> np.ndarray:
        """Whether particles ``idx`` are driven kinematically (``drive``), not gripped."""
        return self._driven[np.asarray(idx)] == 1

    def is_gripped(self, idx) -> np.ndarray:
        """Whether particles ``idx`` are gripped (held by a hand that gives, ``grip``)."""
        return self._driven[np.asarray(idx)] == 3

    def is_pulled(self, idx) -> np.ndarray:
        """Whether particles ``idx`` are pulled by a force."""
        return self._driven[np.asarray(idx)] == 2

    def forces(self) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) forces (N) and (n,) drags (N s/m) on pulled particles (drags on gripped ones too), zero elsewhere."""
        return self._force.astype(np.float64), self._drag.astype(np.float64)

    def grips(self) -> np.ndarray:
        """(n,) most force (N) of the hand that grips each particle, zero elsewhere."""
        return self._grip.astype(np.float64)

    def target(self, idx) -> np.ndarray:
        """Current targets of particles ``idx`` (m)."""
        return self._dst[np.asarray(idx)].copy()

    def snapshot(self) -> tuple:
        """Copy of the host-side targets and forces (for rollback)."""
        return self._driven.copy(), self._dst.copy(), self._force.copy(), self._drag.copy(), self._grip.copy()

    def restore(self, snap: tuple) -> None:
        """Restore a :meth:`snapshot`; uploaded at the next frame."""
        self._driven[:], self._dst[:], self._force[:], self._drag[:], self._grip[:] = snap
        self._dirty = True

    @property
    def driven_indices(self) -> np.ndarray:
        """Particles driven kinematically (``is_kinematic``)."""
        return np.flatnonzero(self._driven == 1)

    def upload(self) -> bool:
        """Send changed targets to the device; True if anything changed."""
        if not self._dirty:
            return False
        self.driven.from_numpy(self._driven)
        self.dst.from_numpy(self._dst)
        self.force.from_numpy(self._force)
        self.drag.from_numpy(self._drag)
        self.grip_force.from_numpy(self._grip)
        self._dirty = False
        return True
