"""The paper's projection (Eq. 6-8) as a level's solver: ``sim.solver: projection``.

Ropes only: each substep predicts with gravity and projects onto the
constraints with the sparse KKT solve of :mod:`sandbox.solvers.projection`
on the host (SciPy). Particles pinned by the level stay fixed (eliminated
unknowns); particles driven by maneuvers are kinematic targets (Eq. 4, weight
c) moving to their frame targets in equal steps. It is slow and exact-ish:
the accuracy oracle for the fast XPBD path, selectable per level.
"""

from __future__ import annotations

import numpy as np

from sandbox.model.model import GRIP_GIVE
from sandbox.solvers.projection import ProjectionParams, ProjectionRopeSolver, RopeSystem


class ReferenceRopeSolver:
    """Steps the ropes of a World with the paper's projection.

    Args:
        world: the World (its model, state, control, objects and ground).
        iterations: Gauss-Newton iterations per projection (1-3 in the paper).
    """

    def __init__(self, world, iterations: int = 2) -> None:
        data = world.data
        if data.cloths:
            raise ValueError(
                "solver 'projection' simulates ropes only; this level has cloths: "
                + ", ".join(c.name for c in data.cloths) + " (allowed for cloth: xpbd)")
        self.world = world
        pinned = np.zeros(data.n_particles, bool)
        pinned[data.pins] = True
        self.pinned = pinned
        self.inv_mass = np.asarray(data.inv_mass, np.float64)
        system = RopeSystem(
            x=data.x0, rope_ranges=[(r.start, r.end) for r in data.ropes],
            rest_length=np.array([r.rod_length for r in data.ropes]),
            radius=np.array([r.radius for r in data.ropes]), pinned=pinned,
        )
        sdf = None
        if world.objects is not None:
            objects = world.objects

            def sdf(points):
                d, n, _ = objects.query_numpy(np.asarray(points, np.float32))
                return d.astype(np.float64), n.astype(np.float64)

        self.solver = ProjectionRopeSolver(system, ProjectionParams(iterations=iterations),
                                           ground_height=world.ground_height, sdf=sdf)
        self.gravity = np.asarray(world.level.scene.gravity, np.float64)

    def frame(self, substeps: int) -> None:
        """Advance the World's state one frame."""
        w = self.world
        ctl = w.control
        ctl.upload()
        x = w.state.x.to_numpy().astype(np.float64)
        v = w.state.v.to_numpy().astype(np.float64)
        driven = np.setdiff1d(ctl.driven_indices, np.flatnonzero(self.pinned))
        src = x[driven].copy()
        dst = ctl.target(driven).astype(np.float64)
        dt = w.dt / substeps
        # Pulled particles (Control.pull): force f and drag -b v on top of
        # gravity, the drag implicit as in the fast solver. The projection
        # (Eq. 6) has no masses, so a pulled particle does not weigh m + b h
        # in it as it does in the fast solver.
        force, drag = ctl.forces()
        pulled = np.flatnonzero(ctl.is_pulled(np.arange(len(x))))
        gripped = np.flatnonzero(ctl.is_gripped(np.arange(len(x))))
        grip, place = ctl.grips()[gripped, None], ctl.target(gripped).astype(np.float64)
        for k in range(substeps):
            frac = (k + 1) / substeps
            targets = [(int(i), src[j] + frac * (dst[j] - src[j])) for j, i in enumerate(driven)]
            if len(pulled):
                wi = self.inv_mass[pulled, None]
                v[pulled] = (v[pulled] + dt * self.gravity + dt * wi * force[pulled]) / (1.0 + dt * wi * drag[pulled, None])
                v[pulled] -= dt * self.gravity  # the step adds gravity itself
            if len(gripped):  # Control.grip: a spring to the place, implicit, up to the grip's force
                wi = self.inv_mass[gripped, None]
                stiff = grip / GRIP_GIVE
                f = stiff * (place - x[gripped])
                fn = np.linalg.norm(f, axis=1, keepdims=True)
                over = fn > grip
                f = np.where(over, f * grip / np.maximum(fn, 1e-30), f)
                stiff = np.where(over, 0.0, stiff)
                den = 1.0 + dt * wi * (drag[gripped, None] + dt * stiff)
                v[gripped] = (v[gripped] + dt * self.gravity + dt * wi * f) / den
                v[gripped] -= dt * self.gravity
            x, v = self.solver.step(x, v, dt, self.gravity, targets)
        w.state.x.from_numpy(x.astype(np.float32))
        w.state.v.from_numpy(v.astype(np.float32))

    @property
    def report(self):
        """The last projection's residuals and timings (``ProjectionReport``)."""
        return self.solver.last_report
