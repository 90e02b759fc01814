"""The World: one level's scene, solver, FSM and metrics, stepped frame by frame.

``World`` is what maneuvers see (``world`` in :mod:`sandbox.maneuvers.base`):
named ropes, cloths and objects, the Control they write, and read-back of
positions. :class:`sandbox.api.Sandbox` wraps it for hosts.
"""

from __future__ import annotations

import collections
import pathlib
import time

import numpy as np

from sandbox import runtime
from sandbox.levels.schema import default_max_substeps
from sandbox.model.builder import ClothRange, ModelBuilder, RopeRange
from sandbox.model.pose import euler_matrix, keyframe_pose
from sandbox.record import ManeuverRecord


SUBSTEP_TRAVEL = 0.25
# Frames between two counts of cloth through cloth (``ClothCrossings``).
CROSSINGS_EVERY = 5
"""The farthest a particle may move in one substep, in rest lengths (a cloth's spacing, a rope's rod): a frame
takes more substeps while something moves faster (see ``World.frame_substeps``)."""

STRAIN_BLOWUP = 4.0
"""Relative stretch of a rod or cloth edge (a length five times its rest) that makes a frame count as blown up."""

INTERACTIVE_CLOTH_PARTICLES = 5000
"""Most particles the interactive tier simulates a cloth with (``sim.tier``); a cloth of more is simulated on a
coarser grid of the same size (``builder.coarse_grid``). drape_box's 163 x 163 cloth then takes 69 x 69
(docs/benchmarks.md, "Tiers")."""


class SimulationUnstable(RuntimeError):
    """The step kept producing NaN or exploding velocities after every retry."""



class _Closed:
    """Stands in for the fields of a closed world: any use raises."""

    def __init__(self, level: str) -> None:
        self._level = level

    def __getattr__(self, name: str):
        raise RuntimeError(f"world of level {self._level!r} is closed (its fields are freed); "
                           "load the level again to run or read it")


class World:
    """A running level.

    Args:
        level: a validated ``sandbox.levels.schema.Level``.
        base_dir: folder of the level file (for mesh assets).
        arch: Taichi backend; None uses the level's ``sim.arch``.
        tier: "accurate" or "interactive"; None uses the level's ``sim.tier`` (accurate if unset).
    """

    def __init__(self, level, *, base_dir: pathlib.Path | None = None, arch: str | None = None,
                 tier: str | None = None) -> None:
        self.level = level
        self.base_dir = pathlib.Path(base_dir) if base_dir is not None else pathlib.Path.cwd()
        self.arch = runtime.init(arch or level.sim.arch)
        sim = level.sim
        self.fps = int(sim.fps)
        self.dt = 1.0 / self.fps
        self.substeps = int(sim.substeps)
        self.iterations = int(sim.iterations)
        self.max_retries = int(sim.max_retries)
        self.max_substeps = max(self.substeps, int(sim.max_substeps or default_max_substeps(self.substeps)))
        self.explode_speed = 200.0  # m/s: faster than anything a level should do
        scene = level.scene
        self.ground_height = None if scene.ground is None else float(scene.ground.height)
        self.record = ManeuverRecord()  # what maneuvers record for later ones and for the criteria
        self.surfaces: dict = {}  # (object, hull) -> (pose, SurfaceGeodesics): geodesic surfaces at a pose

        from sandbox.model.model import Model
        from sandbox.solvers.xpbd import SolverConfig, XPBDSolver

        if tier not in (None, "accurate", "interactive"):
            raise ValueError(f"tier {tier!r} is not allowed; allowed: accurate, interactive")
        self.tier = tier or sim.tier or "accurate"
        builder = ModelBuilder()
        for spec in scene.ropes:
            builder.add_rope(spec)
        for spec in scene.cloths:
            builder.add_cloth(spec, max_particles=INTERACTIVE_CLOTH_PARTICLES if self.tier == "interactive" else None)
        self.data = builder.finalize_data()
        self.ropes: dict[str, RopeRange] = {r.name: r for r in self.data.ropes}
        self.cloths: dict[str, ClothRange] = {c.name: c for c in self.data.cloths}
        self._coarser_substeps(scene)
        # Every field of the world first, their data after (one SNode tree per world, see runtime.batched).
        with runtime.batched() as self._fields:
            self.objects = self._build_objects(scene.objects)
            self.object_specs = {o.name: o for o in scene.objects}
            self.model = Model(self.data)
            self.state = self.model.state()
            self.control = self.model.control()
            self.solver = XPBDSolver(self.model, self.state, self.control,
                                     SolverConfig.of_level(scene, sim, self.iterations), objects=self.objects)
        runtime.opened(self)
        self.moving = [k for k, o in enumerate(scene.objects) if o.motion is not None]
        # Ropes whose pins follow a script: (motion, pin indices, initial pin positions).
        self.rope_motions = []
        self.attachments: list[dict] = []  # held particles that ride on a rope (see attach)
        self.carried_ropes = {spec.name: spec.motion for spec in scene.ropes if spec.motion is not None}
        """Ropes whose pins a scripted motion carries, and that motion: a hold placed relative to one rides on it."""
        for spec, rng in zip(scene.ropes, self.data.ropes):
            if spec.motion is not None:
                pins = self.data.pins[(self.data.pins >= rng.start) & (self.data.pins < rng.end)]
                self.rope_motions.append((spec.motion, pins, self.data.x0[pins].copy()))
        self.reference = None
        if sim.solver == "projection":
            from sandbox.solvers.reference import ReferenceRopeSolver

            self.reference = ReferenceRopeSolver(self, iterations=max(1, min(3, self.iterations)))
        self.frame = 0
        self.ticks = 0
        self.time = 0.0
        self.retries_total = 0
        self.last_retries = 0
        self.last_substeps = self.substeps
        self.substep_frames: collections.Counter[int] = collections.Counter()  # substeps -> frames that took them
        self._finest = min([r.rod_length for r in self.data.ropes]
                           + [min(c.spacing) for c in self.data.cloths] or [np.inf])
        self._gravity = float(np.linalg.norm(scene.gravity))
        # Deepest a particle's centre may sink into an object or the ground before the frame counts as blown up:
        # a rope's radius, a cloth's thickness (m).
        self._deepest = np.zeros(self.model.n)
        for r in self.data.ropes:
            self._deepest[r.start:r.end] = r.radius
        for c in self.data.cloths:
            self._deepest[c.start:c.end] = c.thickness
        self.systems_ms: dict[str, float] = {}
        self.stage_ms: dict[str, float] = {}
        self.profile_every = 0  # frames; 0 = never run the per-pass profile
        self.fsm = None
        self.run_max = {"strain": {}, "penetration": {}, "interpenetration": {}}
        # Cloth through cloth (interpenetration.py), counted every CROSSINGS_EVERY frames for the cloths whose
        # lines are knotted (a medial sheet) and for those a success criterion checks.
        counted = {c.name for c in self.data.cloths if c.medial_lines}
        for crit in level.success:
            if crit.metric == "cloth_interpenetration":
                counted |= set(self.cloths) if crit.of is None else (
                    {crit.of} if isinstance(crit.of, str) else set(crit.of)) & set(self.cloths)
        self.crossings = {}
        if counted:
            from sandbox.collision.interpenetration import ClothCrossings

            self.crossings = {n: ClothCrossings(self.state, self.cloths[n]) for n in sorted(counted)}

    # ----------------------------------------------------------- building
    def _build_objects(self, specs):
        if not specs:
            return None
        from sandbox.collision.sdf import ObjectInstance, ObjectSet
        from sandbox.objects.builders import build_mesh

        inst = []
        for o in specs:
            mesh = build_mesh(o.shape, dict(o.params), base_dir=self.base_dir)
            pos, rot = np.asarray(o.position, float), euler_matrix(o.rotation)
            if o.motion is not None:
                pos, rot = keyframe_pose(o.motion, 0.0)
            inst.append(ObjectInstance(o.name, o.shape, dict(o.params), mesh, pos, rot, float(o.friction)))
        return ObjectSet(inst)

    def attach_fsm(self) -> None:
        """Create the FSM runner (after the maneuvers are registered)."""
        from sandbox.levels.fsm import FSMRunner

        self.fsm = FSMRunner(self.level, self)

    # ---------------------------------------------------------- read-back
    def rope_positions(self, name: str) -> np.ndarray:
        r = self.rope(name)
        return self.state.x.to_numpy()[r.start : r.end]

    def cloth_positions(self, name: str) -> np.ndarray:
        c = self.cloth(name)
        return self.state.x.to_numpy()[c.start : c.end]

    def positions(self) -> np.ndarray:
        """All particle positions (n, 3) float32, m."""
        return self.state.x.to_numpy()

    def velocities(self) -> np.ndarray:
        """All particle velocities (n, 3) float32, m/s."""
        return self.state.v.to_numpy()

    def rope(self, name: str) -> RopeRange:
        """A rope, or a strand of one: ``"R"`` or ``"R[i0:i1]"`` (see ``sandbox.model.strands``)."""
        from sandbox.model.strands import parse_strand, strand_range

        base = parse_strand(name)[0] if "[" in name else name
        if base not in self.ropes:
            raise KeyError(f"no rope named {base!r}; ropes: {', '.join(self.ropes) or '(none)'}")
        return self.ropes[base] if base == name else strand_range(self.ropes[base], name)

    def strand(self, name: str):
        """A ``Strand`` (see ``sandbox.model.strands``): a rope ``R``, a run ``R[i0:i1]`` of one, or a cloth
        line ``F.line1``-``F.line4`` / ``F.P..Q``."""
        from sandbox.model.strands import base_name, cloth_strand, parse_cloth_line, rope_strand

        line = parse_cloth_line(name)
        if line is None:
            return rope_strand(self.rope(name), self.rope(base_name(name)))
        return cloth_strand(name, self.cloth(line[0]), self.data.x0)

    def cloth(self, name: str) -> ClothRange:
        if name not in self.cloths:
            raise KeyError(f"no cloth named {name!r}; cloths: {', '.join(self.cloths) or '(none)'}")
        return self.cloths[name]

    def object_index(self, name: str) -> int:
        if self.objects is None or name not in self.object_specs:
            raise KeyError(f"no object named {name!r}; objects: {', '.join(self.object_specs) or '(none)'}")
        return self.objects.index(name)

    def object_sites(self, name: str) -> dict[str, np.ndarray]:
        """An object's named sites (``sandbox.objects.sites``) at its pose now, world frame (m)."""
        import trimesh

        from sandbox.objects.sites import named_sites

        verts, faces = self.objects.world_mesh(self.object_index(name))
        return named_sites(trimesh.Trimesh(verts, faces, process=False))

    def site_particles(self, body: str, site) -> np.ndarray:
        """Global particle indices of a named site of a rope or cloth.

        Rope (or strand ``R[i0:i1]``) sites: ``start``, ``end``, ``all``, an
        index, or ``[i0, i1]`` (a range, end exclusive); a cloth line ``F.line1`` takes the same sites,
        counted from its first point (``start``: the cloth's centre, ``end``: the corner). Cloth sites: a corner ``A``-``D``, ``center``, ``[i, j]``,
        ``line1``-``line4`` (a control line) or an area ``a``-``d`` (the quadrant of that corner).
        """
        from sandbox.model.strands import parse_cloth_line

        if parse_cloth_line(body) is not None:  # a cloth line: its sites count along it, as a rope's
            from sandbox.model.strands import rope_site_span

            st = self.strand(body)
            lo, hi = rope_site_span(body, len(st), site)
            return st.idx[lo:hi]
        if body in self.ropes or "[" in body:
            r = self.rope(body)  # a rope or a strand R[i0:i1]; indices count from the strand's start
            from sandbox.model.strands import rope_site_span

            lo, hi = rope_site_span(body, r.end - r.start, site)
            return np.arange(r.start + lo, r.start + hi)
        if body in self.cloths:
            c = self.cloths[body]
            if isinstance(site, str) and site.startswith("line"):
                return c.control_line(int(site[4:]))
            if site in ("a", "b", "c", "d"):
                return c.area(site)
            if site == "all":
                return np.arange(c.start, c.end)
            return np.array([c.site(site)])
        raise KeyError(f"no rope or cloth named {body!r}; ropes: {', '.join(self.ropes) or '(none)'}; "
                       f"cloths: {', '.join(self.cloths) or '(none)'}")

    def _coarser_substeps(self, scene) -> None:
        """Where the tier simulates a cloth on a coarser grid, the substep bounds scale with the finest rest
        length: a particle crosses the same fraction of it per substep (``SUBSTEP_TRAVEL``), at the same speed."""
        rods = [r.rod_length for r in self.data.ropes]
        simulated = min(rods + [min(c.spacing) for c in self.data.cloths] or [np.inf])
        level = min(rods + [min(w / (n - 1) for w, n in zip(spec.size, spec.resolution)) for spec in scene.cloths]
                    or [np.inf])
        if np.isfinite(simulated) and simulated > level * (1 + 1e-9):
            ratio = level / simulated
            self.substeps = max(1, int(round(self.substeps * ratio)))
            self.max_substeps = max(self.substeps, int(round(self.max_substeps * ratio)))

    # ------------------------------------------------------------- stepping
    def _move_objects(self, t: float, dt: float) -> None:
        for k in self.moving:
            pos, rot = keyframe_pose(self.level.scene.objects[k].motion, t)
            self.objects.set_pose(k, pos, rot, dt)

    def _physics(self, substeps: int, profile: bool) -> None:
        dt = self.dt / substeps
        if self.reference is not None:
            if self.moving:
                self._move_objects(self.time + self.dt, self.dt)
            self.reference.frame(substeps)
            return
        self.solver.begin_frame()
        if profile:
            self.solver.timings = {}
        for k in range(substeps):
            if self.moving:
                self._move_objects(self.time + (k + 1) * dt, dt)
            if profile:
                self.solver.profile_substep(dt, (k + 1) / substeps, k, substeps)
            else:
                self.solver.substep(dt, (k + 1) / substeps, k, substeps)
        if profile:
            self.stage_ms = dict(self.solver.timings)

    @property
    def mean_substeps(self) -> float:
        """Substeps per frame over the frames run (``sim.substeps`` before the first)."""
        frames = sum(self.substep_frames.values())
        return sum(k * f for k, f in self.substep_frames.items()) / frames if frames else float(self.substeps)

    def frame_substeps(self, v: np.ndarray) -> int:
        """Substeps for the frame that starts with velocities ``v``: as many as keep the fastest
        particle's travel per substep within ``SUBSTEP_TRAVEL`` of the finest rest length (a cloth's
        spacing, a rope's rod), clamped to [``sim.substeps``, ``max_substeps``].

        The speed is the largest now plus gravity over the frame; O(n) over the velocities that the
        frame's snapshot reads back anyway.
        """
        if self.max_substeps == self.substeps or not np.isfinite(self._finest) or not len(v):
            return self.substeps
        vmax = float(np.sqrt((np.asarray(v, np.float64) ** 2).sum(axis=1).max()))
        if not np.isfinite(vmax):
            return self.max_substeps
        reach = (vmax + self._gravity * self.dt) * self.dt
        want = int(np.ceil(reach / (SUBSTEP_TRAVEL * self._finest)))
        return min(self.max_substeps, max(self.substeps, want))

    def step_physics(self) -> dict:
        """Advance the physics one frame, rolling back and retrying on blow-up.

        Each retry doubles the substeps. Raises :class:`SimulationUnstable`
        after ``sim.max_retries`` failed retries (the state is left at the
        start of the frame, which is valid).
        """
        self._follow_attachments()
        for motion, pins, rest in self.rope_motions:
            held = self.control.is_kinematic(pins)  # a grip is not turned into a drive
            if held.any():
                self._drive_carried(motion, pins[held], rest[held])
        snap = self.state.save()
        obj_snap = [self.objects.pose(k) for k in self.moving] if self.moving else []
        substeps = self.frame_substeps(snap[1])
        profile = self.profile_every > 0 and self.frame % self.profile_every == 0
        self.last_retries = 0
        for attempt in range(self.max_retries + 1):
            self._physics(substeps, profile)
            m = self.solver.measure()
            vmax = float(np.sqrt((self.state.v.to_numpy() ** 2).sum(axis=1).max())) if not m["nan"] else np.inf
            blown = m["nan"] or vmax >= self.explode_speed or self._blown_up(m)
            if not blown:
                self.frame += 1
                self.time = self.frame * self.dt
                m["vmax"] = vmax
                self.last_substeps = substeps
                self.substep_frames[substeps] += 1
                return m
            self.state.restore(snap)
            self.solver.forget()
            for (k, (p, r)) in zip(self.moving, obj_snap):
                self.objects.place(k, p, r)
            if attempt < self.max_retries:  # a retry follows
                self.last_retries += 1
                self.retries_total += 1
            substeps *= 2
        raise SimulationUnstable(
            f"frame {self.frame}: NaN, speed above {self.explode_speed:g} m/s, a rod or edge stretched past "
            f"{1 + STRAIN_BLOWUP:g}x its rest length or a particle sunk deeper than its radius or thickness after "
            f"{self.max_retries} retries (up to {substeps // 2} substeps); last good state kept"
        )

    def close(self) -> None:
        """Free this world's fields (its one field tree); it cannot step or be read afterwards.

        What held the fields is replaced by a stand-in that raises on use, so a
        late read is a clear error instead of a read of freed memory.
        """
        if self._fields is not None:
            self._fields.destroy()
            self._fields = None
            runtime.closed(self)
            gone = _Closed(self.level.name)
            self.model = self.state = self.control = self.solver = gone
            if self.objects is not None:
                self.objects = gone

    @property
    def closed(self) -> bool:
        return self._fields is None

    def step(self) -> dict:
        """One frame: physics (with rollback), FSM tick, metrics. Returns the frame's metrics.

        A KeyboardInterrupt anywhere inside puts the state back to the start of
        the frame before it propagates, so the state always is a whole frame.
        """
        if self.closed:
            raise RuntimeError(f"world of level {self.level.name!r} is closed; load the level again to run it")
        snap = (self.state.save(), self.frame, self.time, self.control.snapshot(),
                [self.objects.pose(k) for k in self.moving] if self.moving else [])
        try:
            return self._step()
        except KeyboardInterrupt:
            self.state.restore(snap[0])
            self.frame, self.time = snap[1], snap[2]
            self.control.restore(snap[3])
            for k, (p, r) in zip(self.moving, snap[4]):
                self.objects.place(k, p, r)
            raise

    def _step(self) -> dict:
        t0 = time.perf_counter()
        m = self.step_physics()
        t1 = time.perf_counter()
        if self.fsm is not None and not self.fsm.finished:
            self.fsm.tick()
        t2 = time.perf_counter()
        self.ticks += 1
        row = self._frame_metrics(m)
        t3 = time.perf_counter()
        self.systems_ms = {"physics": 1e3 * (t1 - t0), "fsm": 1e3 * (t2 - t1), "metrics": 1e3 * (t3 - t2)}
        row["ms"] = {k: round(v, 3) for k, v in self.systems_ms.items()}
        if self.stage_ms and self.profile_every and (self.frame - 1) % self.profile_every == 0:
            row["stage_ms"] = {k: round(v, 3) for k, v in self.stage_ms.items()}
        return row

    def _blown_up(self, m: dict) -> bool:
        """A strain or penetration blow-up: a stretch past ``STRAIN_BLOWUP``, or a particle's centre deeper in an
        object or the ground than its rope's radius or its cloth's thickness."""
        if len(m["strain"]) and float(np.max(m["strain"])) > STRAIN_BLOWUP:
            return True
        depth = m["depth"][: len(self._deepest)]
        deep = depth > self._deepest
        if not deep.any():
            return False
        deep[self.data.pins] = False  # a hand may hold a particle where it likes
        deep[self.control.driven_indices] = False
        return bool(deep.any())

    # -------------------------------------------------------------- metrics
    def _frame_metrics(self, m: dict) -> dict:
        strain = {}
        pen = {}
        depth = m["depth"]
        bodies = list(self.ropes.values()) + list(self.cloths.values())
        for b, body in enumerate(bodies):
            strain[body.name] = float(m["strain"][b])
            pen[body.name] = float(depth[body.start : body.end].max()) if body.end > body.start else 0.0
        if self.solver.ropecol is not None:
            gap = self.solver.ropecol.measure()
            seg_rope = self.data.segment_rope
            for r_i, r in enumerate(self.data.ropes):
                g = gap[seg_rope == r_i]
                pen[r.name] = max(pen[r.name], float(max(0.0, -g.min())) if len(g) else 0.0)
        for name, v in strain.items():
            self.run_max["strain"][name] = max(self.run_max["strain"].get(name, 0.0), v)
        for name, v in pen.items():
            self.run_max["penetration"][name] = max(self.run_max["penetration"].get(name, 0.0), v)
        # A count costs about a third of a drape_box frame at 163 x 163 (docs/benchmarks.md): every
        # CROSSINGS_EVERY-th frame, and once more at the end for a criterion.
        through = {name: cc.count() for name, cc in self.crossings.items()} \
            if self.frame % CROSSINGS_EVERY == 0 else {}
        for name, v in through.items():
            self.run_max["interpenetration"][name] = max(self.run_max["interpenetration"].get(name, 0), v)
        row = {
            "frame": self.frame,
            "time": round(self.time, 6),
            "strain": strain,
            "penetration": pen,
            **({"interpenetration": through} if through else {}),
            "max_speed": m["vmax"],
            "retries": self.last_retries,
            "substeps": self.last_substeps,
        }
        if self.fsm is not None:
            row["fsm_state"] = self.fsm.state
            row["progress"] = float(self.fsm.progress)
            man = self.fsm.maneuver
            if man is not None:
                row["maneuver"] = man.metrics()
        return row

    def clear_of_solids(self, points, clearance: float) -> np.ndarray:
        """Points (n, 3) m moved out of the objects and above the ground to ``clearance`` m of their surfaces.

        Where a hand carries a held particle of a rope of radius r, it must
        keep the particle r clear of every surface: a driven particle takes
        no contacts, so a path that cuts an object's edge drags the rope
        through it. A point closer than ``clearance`` to an object moves out
        along that object's surface normal (one step: exact for a point near
        a face or an edge); points already clear are returned unchanged.
        """
        p = np.array(points, dtype=np.float64).reshape(-1, 3)
        if self.objects is not None and len(self.objects):
            d, n, _ = self.objects.query_numpy(p)
            near = d < clearance
            p[near] += (clearance - d[near].astype(np.float64))[:, None] * n[near].astype(np.float64)
        if self.ground_height is not None:
            p[:, 1] = np.maximum(p[:, 1], self.ground_height + clearance)
        return p

    def shadow_distance(self, name: str, points) -> np.ndarray:
        """Signed distance (m, > 0 outside) in the ground plane from points to an object's convex shadow.

        The shadow is the convex hull of the object's vertices at its current
        pose projected along y; the distance is the largest edge-line distance
        (exact outside a vertex region, a lower bound there).
        """
        from scipy.spatial import ConvexHull

        verts, _ = self.objects.world_mesh(self.object_index(name))
        eq = ConvexHull(np.asarray(verts, float)[:, [0, 2]]).equations  # n . p + c <= 0 inside, |n| = 1
        P = np.asarray(points, float)[:, [0, 2]]
        return (P @ eq[:, :2].T + eq[:, 2]).max(axis=1)

    def surface_samples(self, name: str, count: int = 4000) -> np.ndarray:
        """Area-uniform points (count, 3) on an object's surface at its current pose (m), fixed seed."""
        import trimesh

        k = self.object_index(name)
        verts, faces = self.objects.world_mesh(k)
        mesh = trimesh.Trimesh(np.asarray(verts, float), faces, process=False)
        area = mesh.area_faces
        rng = np.random.default_rng(0)
        f = rng.choice(len(faces), size=count, p=area / area.sum())
        a, b = rng.random((2, count))
        flip = a + b > 1.0
        a[flip], b[flip] = 1.0 - a[flip], 1.0 - b[flip]
        tri = mesh.vertices[mesh.faces[f]]
        return tri[:, 0] + a[:, None] * (tri[:, 1] - tri[:, 0]) + b[:, None] * (tri[:, 2] - tri[:, 0])

    def attach(self, particle: int, rope: str) -> None:
        """Let a held particle ride on a rope that a scripted motion carries: its target moves with that motion.

        The particle's place is stored in the motion's frame now; each frame it
        is driven to that place under the motion's pose, as the rope's pins are.
        It rides on the motion, not on the rope's rods: a target carried by the
        rod it holds on to pushes that rod, which carries the target on, and
        the loop ran away (a wound turn's end thrown at 27 m/s). The
        attachment ends when a maneuver releases the particle.
        """
        motion = self.carried_ropes.get(rope)
        if motion is None:
            carried = ", ".join(sorted(self.carried_ropes)) or "(none)"
            raise ValueError(f"attach: rope {rope!r} is not carried by a motion; carried ropes: {carried}")
        pos, rot = keyframe_pose(motion, self.time)
        local = (self.positions()[particle].astype(np.float64) - pos) @ rot
        self.attachments = [a for a in self.attachments if a["particle"] != particle]
        self.attachments.append({"particle": int(particle), "rope": rope, "local": local})

    def _follow_attachments(self) -> None:
        """Drive each attached particle to its place under its carrier's pose at the end of the coming frame."""
        kept = []
        for a in self.attachments:
            if not self.control.is_kinematic([a["particle"]])[0]:
                continue  # released: the attachment ends
            self._drive_carried(self.carried_ropes[a["rope"]], [a["particle"]], a["local"][None])
            kept.append(a)
        self.attachments = kept

    def _drive_carried(self, motion, idx, local: np.ndarray) -> None:
        """Drive particles ``idx`` to their places ``local`` (m, in the motion's frame) under the motion's pose
        at the end of the coming frame: a rope's pins, and the holds that ride on it."""
        pos, rot = keyframe_pose(motion, self.time + self.dt)
        self.control.drive(idx, local @ rot.T + pos)

    def body_scale(self, name: str) -> float:
        """Length scale of a body for relative penetration: rope radius or cloth thickness (m)."""
        if name in self.ropes or "[" in name:
            return self.rope(name).radius
        return self.cloth(name).thickness

    def pin_drift(self) -> float:
        """Largest distance of a driven particle from its target at frame end (m)."""
        idx = self.control.driven_indices
        if len(idx) == 0:
            return 0.0
        x = self.state.x.to_numpy()[idx]
        return float(np.linalg.norm(x - self.control.target(idx), axis=1).max())
