"""Fast solver: small-step XPBD in Taichi for every rope and cloth of a scene.

Per substep (each pass O(n) in particles or constraints):

0. where ropes collide, one rope contact pass and one chain step on the
   positions the substep starts from, before the prediction takes them as
   x_prev: the overlap and rod error the last substep left are removed
   without turning into velocity -- O(n)
1. predict: gravity, pulling and gripping hands, damping, kinematic targets (Control) -- O(n)
2. broad phase: spatial hash of rope segments -- O(n)
3. distance constraints (rods Eq. 2, bending Eq. 3, cloth edges), graph
   coloured Gauss-Seidel: each colour is one parallel loop with disjoint
   writes, so the result does not depend on thread order -- O(m)
4. exact inextensibility of ropes and cloth rows/columns: a tridiagonal
   Newton step per chain (``rope_chain.py``), repeated ``chain_sweeps`` times
   with the contacts in between (repeats only for chains still off) -- O(n)
5. rope capsule-capsule collisions (Eq. 5), Jacobi gather -- O(s k), k
   candidates per segment (bounded by the hash cell occupancy); a stretch
   of rope held at both ends and drawn taut is not pushed out past taut
   (``ChainProjection.taut_f``) -- O(n)
6. cloth self-collision, Jacobi gather over per-particle candidate lists
   (Verlet lists: patched or rebuilt from a spatial hash only when some
   particle has moved half their skin), rest neighbours excluded -- O(n k)
7. ground and object contacts with friction (analytic or grid SDF) -- O(n)
7b. optionally (``cloth_joint``), one Newton step on all rows and columns
   of each cloth together, by preconditioned CG (``cloth_joint.py``) --
   O(n) per CG iteration
7c. after the iterations, where ropes collide: the chain step once more
   (rod lengths have the last word after the capsule pushes), then up to
   ``FINAL_RESWEEPS`` more Newton steps of the chains still off by more
   than ``FINAL_TOLERANCE``, in a launch of their own with step 8 (fused
   into the substep they lengthened its compile by seconds) -- O(n)
8. velocities from positions; contacts inelastic (no velocity away from a
   surface, nor from what a self-collision or rope contact push added) and Coulomb
   friction -- O(n)

Steps 3-7b repeat ``iterations`` times. On the last substep of a frame,
the medial sheet of a cloth whose lines are knotted (``medial.py``) then
runs up to 3 passes, each followed by one more iteration with the particles
it moved held. Only the passes the scene needs are
compiled in (``self.stages``, fixed when the solver is built). A substep
runs as a few fused kernels: every pass is a ``@ti.func`` whose loops stay
parallel, and a kernel runs several in order: the passes before the
iterations, the iterations in chunks of ``FUSE_ITERATIONS``, and the passes
after them (or the whole substep in one kernel where it has no more
iterations than that). A fused kernel's compile time grows faster than its
length (a rope scene with 8 iterations in one kernel took minutes).
Launching each pass on its own (``profile_substep``) gives the per-pass
timings at the cost of one launch per pass.
"""

import dataclasses
import time

import numpy as np
import taichi as ti

from sandbox import runtime
from sandbox.collision.contacts import CONTACT_FLAG, Contacts, friction_velocity, inelastic_velocity, plane_push
from sandbox.collision.medial import PASSES as MEDIAL_PASSES
from sandbox.collision.medial import MedialSheet
from sandbox.collision.ropecollision import RopeCollision
from sandbox.collision.selfcollision import ClothSelfCollision
from sandbox.constraints.distance import xpbd_distance
from sandbox.model.model import GRIP_GIVE, Control, Model, State
from sandbox.solvers.cloth_joint import JointClothProjection, cloth_chain_groups
from sandbox.solvers.rope_chain import ChainProjection, build_chains, has_rope_chains

PREDICT, SELF_LISTS, ROPE_HASH, CONSTRAINTS, ROPE_COLLIDE, SELF_COLLIDE, CONTACTS, VELOCITIES, ROPE_INEXT, RESWEEP, \
    JOINT, SETTLE, FINAL_SWEEP = range(13)
# The joint cloth step's parts: a launch runs JOINT as JOINT_BEGIN, one JOINT_CG per CG iteration, JOINT_END
# (``XPBDSolver._runs``), each JOINT_CG a kernel of its own, launched once per iteration rather than unrolled.
JOINT_BEGIN, JOINT_CG, JOINT_END = range(13, 16)
# Most iterations one fused kernel unrolls. One: a substep is a launch for the
# passes before the iterations, one per iteration and one for the passes after
# them. A kernel's compile time grows faster than its length, and the unrolled
# passes compile once per copy: at 1 instead of 4, the rope levels' first frame
# compiles in 6-7 s instead of 15-31 s (docs/benchmarks.md, "Start"), and
# their frames take about as long (the kernels launch without a template
# instance lookup, ``_run_k``).
FUSE_ITERATIONS = 1
# Most passes one kernel runs; a longer run of passes is launched as several
# kernels in order. drape_box's substep (11 passes, one iteration) as 6 + 5:
# its first frame compiles in 7.8 s instead of 8.8 s, frames unchanged (and
# wrap_box_two's 90 -> 76 ms; docs/benchmarks.md, "Start").
MAX_PASSES = 6
# After the chain step that ends a substep (step 7c): up to FINAL_RESWEEPS
# more Newton steps of the rope chains with a rod still off its length by
# more than FINAL_TOLERANCE (relative). Each step moves particles along the
# rods only, so it may push a rope into another where the contacts have just
# separated them: they run only where a rod is off by half a percent or more,
# not down to the chain tolerance.
FINAL_RESWEEPS = 3
FINAL_TOLERANCE = 5e-3
STAGE_NAMES = {
    PREDICT: "predict",
    SELF_LISTS: "cloth_lists",
    ROPE_HASH: "rope_hash",
    CONSTRAINTS: "constraints",
    ROPE_COLLIDE: "rope_collision",
    SELF_COLLIDE: "self_collision",
    CONTACTS: "contacts",
    VELOCITIES: "velocities",
    ROPE_INEXT: "chains",
    RESWEEP: "chain_resweeps",
    FINAL_SWEEP: "chain_resweeps",
    JOINT: "cloth_joint",
    SETTLE: "settle",
}


def _segments(stages, optional: dict) -> tuple:
    """``stages`` cut into launches where a pass some substeps skip begins or ends.

    ``optional`` maps such a pass to its group (0: self-collision, 1: the
    joint step). Returns ((passes, group or None), ...): each run of passes
    of one group is a launch of its own, which a substep that skips the group
    leaves out; the runs between them stay fused. Equal runs are one kernel.
    """
    out: list = []
    for sid in stages:
        group = optional.get(sid)
        if out and out[-1][1] == group:
            out[-1] = (out[-1][0] + (sid,), group)
        else:
            out.append(((sid,), group))
    return tuple(out)


def _cut_before(segments, sid: int) -> tuple:
    """``segments`` ((passes, group), ...) with the one that holds pass ``sid`` cut in two before its first
    ``sid`` (the same passes in the same order, one launch more)."""
    out = []
    for stages, group in segments:
        k = stages.index(sid) if sid in stages else 0
        out += [(stages[:k], group), (stages[k:], group)] if k > 0 else [(stages, group)]
    return tuple(out)


def _without(stages, skip_self: bool, skip_joint: bool) -> tuple:
    """``stages`` less self-collision and/or the joint cloth step."""
    drop = ((SELF_LISTS, SELF_COLLIDE) if skip_self else ()) + ((JOINT,) if skip_joint else ())
    return tuple(sid for sid in stages if sid not in drop)


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """How a scene is stepped: everything the solver takes besides the model, its state and its control.

    Attributes:
        gravity: (3,) m/s^2.
        ground: (height m, friction) or None for no ground.
        iterations: constraint/collision sweeps per substep.
        self_collision_every: cloth self-collision on every k-th substep (and the last).
        chain_sweeps: times the chain step runs per iteration (rows and columns re-solved where they disagree).
        chain_tolerance: relative rod error below which a chain is not re-solved.
        fuse_iterations: most iterations fused into one substep kernel (None:
            ``FUSE_ITERATIONS``); more run as several launches (the same passes,
            in the same order).
        cloth_joint: conjugate-gradient iterations of the joint cloth step (0: none; a level's default is
            ``CLOTH_JOINT``); it runs only in frames where no hand holds a particle of a cloth.
        cloth_joint_every: the joint step on every k-th substep (and the last).
    """

    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    ground: tuple[float, float] | None = None
    iterations: int = 1
    self_collision_every: int = 1
    chain_sweeps: int = 1
    chain_tolerance: float = 1e-3
    fuse_iterations: int | None = None
    cloth_joint: int = 0
    cloth_joint_every: int = 1

    @classmethod
    def of_level(cls, scene, sim, iterations: int | None = None) -> "SolverConfig":
        """The configuration a level's ``scene`` and ``sim`` ask for (``iterations``: the level's, if None)."""
        from sandbox.levels.schema import CLOTH_CHAIN_SWEEPS  # noqa: PLC0415 (the level's own default)

        ground = None if scene.ground is None else (float(scene.ground.height), float(scene.ground.friction))
        return cls(
            gravity=tuple(float(g) for g in scene.gravity), ground=ground,
            iterations=int(sim.iterations if iterations is None else iterations),
            self_collision_every=sim.self_collision_every,
            chain_sweeps=sim.chain_sweeps or (CLOTH_CHAIN_SWEEPS if any(c.stretch_compliance == 0.0
                                                                       for c in scene.cloths) else 1),
            chain_tolerance=sim.chain_tolerance, cloth_joint=sim.cloth_joint,
            cloth_joint_every=sim.cloth_joint_every,
        )


@ti.data_oriented
class XPBDSolver:
    """Steps one State of a Model with small-step XPBD.

    Args:
        model: static scene data.
        state: the State it advances (bound: kernels read its fields directly).
        control: kinematic targets.
        config: how to step (``SolverConfig``).
        objects: an ObjectSet (collision queries) or None.

    Fields:
        w: (n,) f32, 1/kg, inverse mass for this frame (0 while driven).
        depth: (n,) f32, m, penetration into ground/objects (metrics).
        strain: (bodies,) f32, max |l - r| / r of each rope's rods; max
            (l - r) / r (stretch) of each cloth's structural edges.
        contacts: this substep's contacts (``collision.contacts.Contacts``:
            flag, normal, contact plane, friction budget, surface velocity, taut rope), made
            by the contact passes and read by the chains, the joint step and
            the velocity pass; None where nothing can touch a particle.
    """

    def __init__(self, model: Model, state: State, control: Control, config: SolverConfig = SolverConfig(),
                 *, objects=None) -> None:
        cfg = self.config = config
        gravity, ground, iterations = cfg.gravity, cfg.ground, cfg.iterations
        self_collision_every, chain_sweeps, chain_tolerance = cfg.self_collision_every, cfg.chain_sweeps, cfg.chain_tolerance
        fuse_iterations = cfg.fuse_iterations
        cloth_joint, cloth_joint_every = cfg.cloth_joint, cfg.cloth_joint_every
        self.model = model
        self.st = state
        self.ctl = control
        self._fused_kernels: dict = {}  # run of passes -> its kernel (``_run_k``)
        self._parts: dict = {}  # stage tuple -> its kernels, in order
        self.gravity = ti.math.vec3(*[float(g) for g in gravity])
        self.ground = ground
        self.objects = objects
        self.has_ground = ground is not None
        self.has_objects = objects is not None
        self.iterations = int(iterations)
        self.chain_tolerance = float(chain_tolerance)
        self.colors = [tuple(c) for c in model.colors if c[1] > c[0]]
        self.w = ti.field(ti.f32, shape=model.n)
        self.depth = ti.field(ti.f32, shape=model.n)
        self.strain = ti.field(ti.f32, shape=max(model.n_bodies, 1))
        # Rods of ropes must keep their length both ways; cloth may buckle
        # (compressed edges in folds), so only its stretch counts as strain.
        self.stretch_only = ti.field(ti.i32, shape=max(model.n_bodies, 1))
        runtime.defer(self.stretch_only.from_numpy, np.array(
            [0] * len(model.data.ropes) + [1] * len(model.data.cloths) + [0] * (model.n_bodies == 0), np.int32))
        # Contact normals are kept per substep wherever something can touch a
        # particle (ground, objects, other rope segments): the chain solve
        # then leaves the motion along them to the contacts.
        self.has_contact_normals = self.has_ground or self.has_objects or model.s >= 3
        groups = build_chains(model.data)
        # Rope contacts do not push a held stretch of rope out past taut
        # (ChainProjection.taut_f), refreshed before each contact pass.
        self.has_taut = model.s >= 3 and has_rope_chains(model.data)
        self.contacts = Contacts(model.n, taut=self.has_taut) if self.has_contact_normals else None
        contacts = self.contacts
        cloth_start = min((c.start for c in model.data.cloths), default=model.n)
        self.selfcol = ClothSelfCollision(model, state, self.w, cloth_start) if model.self_collision else None
        self.has_selfcol = self.selfcol is not None
        self.inext = ChainProjection(model, state, self.w, groups, contacts) if groups else None
        self.ropecol = RopeCollision(model, state, self.w, contacts) if model.s >= 3 else None
        self.has_ropecol = self.ropecol is not None
        cloth_groups = cloth_chain_groups(model.data) if int(cloth_joint) > 0 else []
        self.joint = JointClothProjection(model, state, self.w, cloth_groups, contacts, peeled=self.inext.peeled,
                                          iterations=int(cloth_joint), slots=int(iterations)) if cloth_groups else None
        self.has_joint = self.joint is not None
        # The joint step runs only in frames where no hand holds a cloth particle (``begin_frame``); a scene's
        # pins are not hands (a cloth hanging from them still has a length-keeping state).
        cloth_particles = (np.concatenate([np.arange(c.start, c.start + c.nx * c.nz) for c in model.data.cloths])
                           if self.has_joint else np.zeros(0, np.int64))
        self._cloth_particles = np.setdiff1d(cloth_particles, model.data.pins)
        self.cloth_held = False
        # ... and from the second frame on: a cloth is built at its rest lengths, and the first frame comes
        # before a level's FSM has taken hold of anything.
        self.frames_begun = 0
        self.joint_idle = True
        self.prestabilize = self.ropecol is not None and self.inext is not None
        # Step 0 (wherever ropes collide; the standard sweep of every rope
        # level: docs/benchmarks.md, "Rope contacts"): what overlap and rod error the last substep left is removed
        # before the prediction, which takes x_prev from the result: the
        # velocity the substep starts with is unchanged, so pushing ropes
        # apart where they already overlapped (a tight knot pulled into
        # itself by its held ends) adds no speed to them. A launch of its
        # own: fused, it would make every substep kernel longer, and their
        # compile time grows faster than their length (the knot levels' first
        # frame: 135 s with it fused, 11 s as a launch of its own, the rest of
        # the substep already compiled).
        self.stages_zero = (SETTLE, ROPE_HASH, ROPE_COLLIDE, ROPE_INEXT) if self.prestabilize else ()
        pre = [PREDICT]
        if self.ropecol is not None:
            pre.append(ROPE_HASH)
        it = []
        if self.colors:
            it.append(CONSTRAINTS)
        if self.has_ground or self.has_objects:
            it.append(CONTACTS)
        if self.inext is not None:
            it.append(ROPE_INEXT)
        if self.ropecol is not None:
            it.append(ROPE_COLLIDE)
        if self.selfcol is not None:
            it += [SELF_LISTS, SELF_COLLIDE]  # candidate lists checked against the positions the pass sees
        if self.inext is not None:
            for _ in range(int(chain_sweeps) - 1):
                # Rows and columns (and a chain and the surface it lies on)
                # disagree where cloth crosses a box vertex or a fold: one
                # alternation leaves tens of percent there, a few bring it
                # down; each re-solves only the chains still off.
                if self.has_ground or self.has_objects:
                    it.append(CONTACTS)
                it.append(RESWEEP)
        if self.has_ground or self.has_objects:
            it.append(CONTACTS)  # again: contacts have the last word in every iteration
        if self.joint is not None:
            # Rows and columns solved together where the sweeps leave them
            # disagreeing (a box's vertices; see cloth_joint.py), after the
            # contacts: it moves a particle in contact only along its surface,
            # and a contact pass after it would stretch the rods again where
            # it pushes the particles at a vertex outwards.
            it.append(JOINT)
        post = []
        if self.ropecol is not None and self.inext is not None:
            # Rope lengths have the last word: a capsule push leaves a rod
            # stretched by up to the overlap it removed, the chain step
            # restores Eq. 2 and moves particles only along the rods. Under
            # the contact restriction one Newton step can fall well short
            # where a rope bends onto another (a rod 3 % long after it):
            # up to FINAL_RESWEEPS more steps for chains still off by more
            # than FINAL_TOLERANCE.
            post += [ROPE_INEXT] + [FINAL_SWEEP] * FINAL_RESWEEPS
        self.stages = tuple(pre + it * self.iterations + post + [VELOCITIES])
        # The medial sheet of cloths whose lines are knotted (medial.py): on the last substep of a frame,
        # after the iterations, up to MEDIAL_PASSES passes, each followed by one more iteration with the
        # particles it moved held; then the passes after the iterations.
        self.medial = [MedialSheet(state, self.w, model.data.x0, c, list(c.medial_lines))
                       for c in model.data.cloths if c.medial_lines]
        self.stages_body = tuple(pre + it * self.iterations)
        self.stages_it = tuple(it)
        # Unfused: before; full chunks of `chunk` iterations, then the rest; after.
        chunk = max(1, FUSE_ITERATIONS if fuse_iterations is None else int(fuse_iterations))
        self.fused = self.iterations <= chunk
        self.chunks = (self.iterations // chunk, self.iterations % chunk)
        self.stages_pre = tuple(pre)
        self.stages_post = tuple(post + [VELOCITIES])
        # The same substep without cloth self-collision and/or the joint cloth
        # step, for substeps that skip them: (skip self-collision, skip joint)
        # -> (whole substep, a chunk of iterations, the rest of them).
        self.variants = {
            (ss, sj): tuple(_without(q, ss, sj) for q in (self.stages, it * chunk, it * self.chunks[1]))
            for ss in (False, True) for sj in (False, True)
        }
        self.self_collision_every = int(self_collision_every)
        self.cloth_joint_every = int(cloth_joint_every)
        # Fused, a substep that skips self-collision or the joint step would
        # be a kernel of its own, as long as the whole substep: two or three
        # copies of it to compile (and to load from the kernel cache). Cut
        # around the passes that some substeps skip instead, each part one
        # kernel: a launch or two more per substep, against frames of tens of
        # milliseconds where cloth is simulated.
        optional = {}
        if self.selfcol is not None and self.self_collision_every > 1:
            optional.update({SELF_LISTS: 0, SELF_COLLIDE: 0})
        if self.joint is not None:
            # The joint step is a launch of its own even on every substep: fused, it makes the substep
            # kernel compile 1.4 s longer (drape_box, empty cache) for one launch less.
            optional[JOINT] = 1
        segments = _segments(self.stages, optional) if optional else ((self.stages, None),)
        # The final Newton steps of the ropes (and the velocities after them) are a launch of their own:
        # unrolled into the fused substep they made its compile 2-4 s longer (the rope levels' cold start).
        self.segments = _cut_before(segments, FINAL_SWEEP)
        self.timings: dict[str, float] = {}

    # ------------------------------------------------------------ passes
    @ti.func
    def _predict(self, dt: ti.f32, frac: ti.f32):
        st = self.st
        ctl = self.ctl
        for i in range(st.x.shape[0]):
            st.x_prev[i] = st.x[i]
            mode = ctl.driven[i]
            if mode == 1:
                st.x[i] = ctl.src[i] + frac * (ctl.dst[i] - ctl.src[i])
            else:
                v = st.v[i] + dt * self.gravity
                if mode == 2:
                    # Pulled: force f and drag -b v, the drag implicit (backward
                    # Euler), so the particle also weighs m + b dt in the
                    # constraint passes of this substep.
                    wi = self.model.inv_mass[i]
                    v = (v + dt * wi * ctl.force[i]) / (1.0 + dt * wi * ctl.drag[i])
                    self.w[i] = wi / (1.0 + dt * wi * ctl.drag[i])
                elif mode == 3:
                    # Gripped (Control.grip): a spring k d back to its place, implicit
                    # as the drag is, up to the grip's force; beyond it that force.
                    wi = self.model.inv_mass[i]
                    d = ctl.dst[i] - st.x[i]
                    k = ctl.grip_force[i] / ti.static(GRIP_GIVE)
                    f = k * d
                    fn = f.norm()
                    if fn > ctl.grip_force[i]:
                        f *= ctl.grip_force[i] / fn
                        k = 0.0
                    den = 1.0 + dt * wi * (ctl.drag[i] + dt * k)
                    v = (v + dt * wi * f) / den
                    self.w[i] = wi / den
                v *= ti.max(1.0 - self.model.damping[i] * dt, 0.0)
                st.v[i] = v
                st.x[i] = st.x[i] + dt * v
        for e in range(st.lam.shape[0]):
            st.lam[e] = 0.0
        if ti.static(self.has_ropecol):
            self.ropecol.forget_f()

    @ti.func
    def _settle(self):
        # x_prev = x: the rope contact pass measures no slip (friction) in step 0.
        for i in range(self.st.x.shape[0]):
            self.st.x_prev[i] = self.st.x[i]

    @ti.func
    def _constraints(self, inv_dt2: ti.f32):
        st = self.st
        mdl = self.model
        for c in ti.static(range(len(self.colors))):
            for e in range(self.colors[c][0], self.colors[c][1]):
                a = mdl.edge[e][0]
                b = mdl.edge[e][1]
                dxa, dxb, dlam = xpbd_distance(
                    st.x[a], st.x[b], self.w[a], self.w[b], mdl.rest[e], mdl.compliance[e] * inv_dt2, st.lam[e]
                )
                st.x[a] = st.x[a] + dxa
                st.x[b] = st.x[b] + dxb
                st.lam[e] = st.lam[e] + dlam

    @ti.func
    def _contacts(self, dt: ti.f32, gh: ti.f32, gmu: ti.f32):
        st = self.st
        mdl = self.model
        for i in range(st.x.shape[0]):
            if self.w[i] > 0.0:
                x = st.x[i]
                r = mdl.radius[i]
                mu_p = mdl.friction[i]
                if ti.static(self.has_ground):
                    x, pen = plane_push(x, r, gh)
                    if pen > 0.0:
                        self.contacts.normal[i] = ti.math.vec3(0.0, 1.0, 0.0)
                        self.contacts.hit[i] = 1.0
                        self.contacts.dv[i] = ti.max(self.contacts.dv[i], 0.5 * (mu_p + gmu) * pen / dt, CONTACT_FLAG)
                        self.contacts.vel[i] = ti.math.vec3(0.0)
                        self.contacts.plane[i] = x[1]
                if ti.static(self.has_objects):
                    d, n, k = self.objects.query_within(x, r)
                    pen = r - d
                    if pen > 0.0:
                        x += pen * n
                        mu = 0.5 * (mu_p + self.objects.friction(k))
                        self.contacts.normal[i] = n
                        self.contacts.hit[i] = 1.0
                        self.contacts.dv[i] = ti.max(self.contacts.dv[i], mu * pen / dt, CONTACT_FLAG)
                        self.contacts.vel[i] = self.objects.velocity_at(k, x)
                        self.contacts.plane[i] = n.dot(x)
                st.x[i] = x

    @ti.func
    def _velocities(self, inv_dt: ti.f32):
        st = self.st
        for i in range(st.x.shape[0]):
            v = (st.x[i] - st.x_prev[i]) * inv_dt
            if ti.static(self.has_ground or self.has_objects):
                if self.contacts.dv[i] > 0.0:
                    v = inelastic_velocity(v, self.contacts.normal[i], self.contacts.vel[i])
                    v = friction_velocity(v, self.contacts.normal[i], self.contacts.dv[i], self.contacts.vel[i])
                    self.contacts.dv[i] = 0.0
            if ti.static(self.has_contact_normals):
                self.contacts.hit[i] = 0.0
            if ti.static(self.has_selfcol):
                v = self.selfcol.settle(i, v, inv_dt)
            if ti.static(self.has_ropecol):
                v = self.ropecol.settle(i, v, inv_dt)
            st.v[i] = v

    @ti.func
    def _stage(self, sid: ti.template(), dt: ti.f32, frac: ti.f32, gh: ti.f32, gmu: ti.f32):
        if ti.static(sid == SETTLE):
            self._settle()
        if ti.static(sid == PREDICT):
            if ti.static(self.has_joint):
                self.joint.begin_substep_f()
            self._predict(dt, frac)
        if ti.static(sid == SELF_LISTS):
            self.selfcol.refresh_f()
        if ti.static(sid == ROPE_HASH):
            self.ropecol.build_f()
        if ti.static(sid == CONSTRAINTS):
            self._constraints(1.0 / (dt * dt))
        if ti.static(sid == ROPE_COLLIDE):
            if ti.static(self.has_taut):
                self.inext.taut_f(self.contacts.taut, self.contacts.taut_n, self.contacts.room)
            self.ropecol.solve_f()
        if ti.static(sid == SELF_COLLIDE):
            self.selfcol.solve_f()
        if ti.static(sid == CONTACTS):
            self._contacts(dt, gh, gmu)
        if ti.static(sid == ROPE_INEXT):
            self.inext.solve_f()
        if ti.static(sid == RESWEEP):
            self.inext.resweep_f(self.chain_tolerance)
        if ti.static(sid == FINAL_SWEEP):
            self.inext.resweep_f(FINAL_TOLERANCE)
        if ti.static(sid == JOINT_BEGIN):
            self.joint.begin_f()
        if ti.static(sid == JOINT_CG):
            self.joint.cg_f()
        if ti.static(sid == JOINT_END):
            self.joint.end_f()
        if ti.static(sid == VELOCITIES):
            self._velocities(1.0 / dt)

    # ----------------------------------------------------------- kernels
    def _run_k(self, stages: tuple, dt: float, frac: float, gh: float, gmu: float) -> None:
        """The passes ``stages`` (a tuple of pass ids), fused into kernels of at most ``MAX_PASSES``.

        Each run of passes gets a kernel of its own, made on first use, rather
        than one kernel with the tuple as a template argument: Taichi then
        looks up no template instance at each launch (85 -> 58 us a launch on
        this machine, tens of launches a frame). The same passes in the same
        order, however launched: bitwise the same frames.
        """
        parts = self._parts.get(stages)
        if parts is None:
            parts = self._split(stages)
        for part in parts:
            part(dt, frac, gh, gmu)

    def _split(self, stages: tuple) -> list:
        """The kernels of ``stages`` (``_runs``), each kernel made once."""
        parts = []
        for run in self._runs(stages):
            if run not in self._fused_kernels:
                self._fused_kernels[run] = self._fused_kernel(run)
            parts.append(self._fused_kernels[run])
        self._parts[stages] = parts
        return parts

    def _runs(self, stages: tuple) -> list:
        """``stages`` cut into the runs of passes that are each one kernel, in order.

        A block of passes repeated back to back (the contacts and chain re-sweeps of a cloth, a rope's
        final Newton steps, the joint cloth step's CG iterations) is one kernel launched once per
        repeat, rather than copies unrolled into one kernel to compile: drape_box's (contacts,
        re-sweep) x 2 compiled in 1.8 s, one copy in 0.8 s. The other passes run in order, at most
        ``MAX_PASSES`` a kernel. The joint cloth step runs as its begin, one ``JOINT_CG`` per CG
        iteration and its end.
        """
        flat: list = []
        for sid in stages:
            flat += [JOINT_BEGIN] + [JOINT_CG] * self.joint.iterations + [JOINT_END] if sid == JOINT else [sid]
        runs: list = []
        run: tuple = ()
        i = 0
        while i < len(flat):
            block = next((flat[i:i + n] for n in range(1, MAX_PASSES + 1)
                          if i + 2 * n <= len(flat) and flat[i:i + n] == flat[i + n:i + 2 * n]), None)
            if block is not None:
                runs += [run] if run else []
                run = ()
                while flat[i:i + len(block)] == block:
                    runs.append(tuple(block))
                    i += len(block)
                continue
            if len(run) == MAX_PASSES:
                runs.append(run)
                run = ()
            run += (flat[i],)
            i += 1
        return runs + ([run] if run else [])

    def _fused_kernel(self, stages: tuple):
        """A kernel running the passes ``stages`` in order (``_stage``, each unrolled)."""
        solver = self

        @ti.kernel
        def fused(dt: ti.f32, frac: ti.f32, gh: ti.f32, gmu: ti.f32):
            for sid in ti.static(stages):
                solver._stage(sid, dt, frac, gh, gmu)

        return fused

    @ti.kernel
    def _begin_frame_k(self):
        for i in range(self.st.x.shape[0]):
            self.w[i] = self.model.inv_mass[i] * ti.cast(self.ctl.driven[i] != 1, ti.f32)
            self.ctl.src[i] = self.st.x[i]

    @ti.kernel
    def _measure_k(self, gh: ti.f32) -> ti.i32:
        bad = 0
        st = self.st
        mdl = self.model
        for g in range(self.strain.shape[0]):
            self.strain[g] = 0.0
        for e in range(mdl.kind.shape[0]):
            if mdl.kind[e] == 0 and mdl.rest[e] > 0.0:
                a = mdl.edge[e][0]
                b = mdl.edge[e][1]
                g = mdl.group[e]
                s = ((st.x[a] - st.x[b]).norm() - mdl.rest[e]) / mdl.rest[e]
                if self.stretch_only[g]:
                    s = ti.max(s, 0.0)
                ti.atomic_max(self.strain[g], ti.abs(s))
        for i in range(st.x.shape[0]):
            x = st.x[i]
            if x.norm() < 1e6:  # false for NaN and inf as well
                dep = 0.0
                if ti.static(self.has_ground):
                    dep = ti.max(dep, gh - x[1])
                if ti.static(self.has_objects):
                    d, n, k = self.objects.query_within(x, 0.0)
                    dep = ti.max(dep, -d)
                self.depth[i] = dep
            else:
                self.depth[i] = 1e30
                bad = 1
        return bad

    # -------------------------------------------------------- orchestration
    def _ground(self) -> tuple[float, float]:
        return self.ground if self.ground is not None else (0.0, 0.0)

    def begin_frame(self) -> None:
        """Latch kinematic targets for the coming frame."""
        if self.ctl.upload() and self.has_joint:
            self.cloth_held = bool(self.ctl.is_driven(self._cloth_particles).any())
        self.joint_idle = self.cloth_held or self.frames_begun == 0
        self.frames_begun += 1
        self._begin_frame_k()

    def _skips(self, k: int, substeps: int) -> tuple[bool, bool]:
        """Whether substep k of a frame skips cloth self-collision, and the joint cloth step (also skipped in
        a frame where a hand, not a pin, holds a cloth particle: a cloth held by hands and pressed by an object
        has no length-keeping state for it to converge to; and in the first frame, whose cloth is at its rest
        lengths and which comes before a level's FSM first takes hold of it)."""
        last = k == substeps - 1
        return (not (last or k % self.self_collision_every == 0),
                self.joint_idle or not (last or k % self.cloth_joint_every == 0))

    def substep(self, dt: float, frac: float, k: int = 0, substeps: int = 1) -> None:
        """One substep (k of ``substeps``); ``frac`` is how far through the frame it ends."""
        gh, gmu = self._ground()
        skips = self._skips(k, substeps)
        if self.stages_zero:
            self._run_k(self.stages_zero, dt, frac, gh, gmu)
        if self.medial and k == substeps - 1:
            if self.fused:
                self._run_k(self.stages_body, dt, frac, gh, gmu)
            else:  # the iterations in the same launches as any other substep's
                self._chunked(skips, dt, frac, gh, gmu)
            self._medial(dt, frac, gh, gmu, self._run_k)
            self._settle_joint(skips, dt, frac, gh, gmu)
            self._run_k(self.stages_post, dt, frac, gh, gmu)
            for m in self.medial:
                m.release(1.0 / dt)
            return
        if self.fused:
            last = len(self.segments) - 1
            for i, (stages, group) in enumerate(self.segments):
                if group is None or not skips[group]:
                    if i == last:  # the passes after the iterations (velocities)
                        self._settle_joint(skips, dt, frac, gh, gmu)
                    self._run_k(stages, dt, frac, gh, gmu)
            return
        self._chunked(skips, dt, frac, gh, gmu)
        self._settle_joint(skips, dt, frac, gh, gmu)
        self._run_k(self.stages_post, dt, frac, gh, gmu)

    def _settle_joint(self, skips, dt: float, frac: float, gh: float, gmu: float) -> None:
        """After a substep's iterations that ran the joint cloth step: more steps where it left the cloth
        stretched (``JointClothProjection.settle``)."""
        if self.has_joint and not skips[1]:
            self.joint.settle(lambda: self._run_k((JOINT,), dt, frac, gh, gmu))

    def _chunked(self, skips, dt: float, frac: float, gh: float, gmu: float) -> None:
        """An unfused substep up to its last iteration: the passes before, then the iterations in chunks."""
        _, chunk, rest = self.variants[skips]
        self._run_k(self.stages_pre, dt, frac, gh, gmu)
        for _ in range(self.chunks[0]):
            self._run_k(chunk, dt, frac, gh, gmu)
        if self.chunks[1]:
            self._run_k(rest, dt, frac, gh, gmu)

    def _medial(self, dt: float, frac: float, gh: float, gmu: float, run) -> int:
        """The medial-sheet passes, each followed by one iteration (``run(stages, ...)``) while any moved;
        returns how many passes moved a particle."""
        for n in range(MEDIAL_PASSES):
            t0 = time.perf_counter()
            moved = sum(m.run_pass() for m in self.medial)
            self.timings["medial_sheet"] = self.timings.get("medial_sheet", 0.0) + 1e3 * (time.perf_counter() - t0)
            if moved == 0:
                return n
            run(self.stages_it, dt, frac, gh, gmu)
        return MEDIAL_PASSES

    def _profiled(self, stages, dt: float, frac: float, gh: float, gmu: float) -> None:
        """``stages``, one launch per pass, each timed into ``self.timings`` (ms)."""
        for sid in stages:
            t0 = time.perf_counter()
            self._run_k((sid,), dt, frac, gh, gmu)
            ti.sync()
            name = STAGE_NAMES[sid]
            self.timings[name] = self.timings.get(name, 0.0) + 1e3 * (time.perf_counter() - t0)

    def profile_substep(self, dt: float, frac: float, k: int = 0, substeps: int = 1) -> None:
        """The same substep, one launch per pass, accumulating ``self.timings`` (ms)."""
        gh, gmu = self._ground()
        self._profiled(self.stages_zero, dt, frac, gh, gmu)
        if self.medial and k == substeps - 1:
            self._profiled(self.stages_body, dt, frac, gh, gmu)
            self._medial(dt, frac, gh, gmu, self._profiled)
            self._profiled_settle(self._skips(k, substeps), dt, frac, gh, gmu)
            self._profiled(self.stages_post, dt, frac, gh, gmu)
            for m in self.medial:
                m.release(1.0 / dt)
            return
        skips = self._skips(k, substeps)
        stages = self.variants[skips][0]
        cut = len(stages) - len(self.stages_post)
        self._profiled(stages[:cut], dt, frac, gh, gmu)
        self._profiled_settle(skips, dt, frac, gh, gmu)
        self._profiled(stages[cut:], dt, frac, gh, gmu)

    def _profiled_settle(self, skips, dt: float, frac: float, gh: float, gmu: float) -> None:
        """``_settle_joint`` one launch per step, timed into the joint step's entry of ``self.timings``."""
        if not self.has_joint or skips[1]:
            return
        t0 = time.perf_counter()
        self.joint.settle(lambda: self._run_k((JOINT,), dt, frac, gh, gmu))
        ti.sync()
        name = STAGE_NAMES[JOINT]
        self.timings[name] = self.timings.get(name, 0.0) + 1e3 * (time.perf_counter() - t0)

    def forget(self) -> None:
        """Drop what carries over from one substep to the next besides the State (after a rollback)."""
        if self.joint is not None:
            self.joint.forget()

    def measure(self) -> dict:
        """Strain per body, penetration per particle and a NaN flag (NumPy)."""
        bad = self._measure_k(self._ground()[0])
        return {"nan": bool(bad), "strain": self.strain.to_numpy()[: self.model.n_bodies], "depth": self.depth.to_numpy()}
