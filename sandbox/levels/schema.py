"""Level schema v1: what a level YAML file holds (SPEC §7).

Every model rejects unknown keys; numbers are strict (a string or a boolean
is not a number) and finite; ranges are checked with messages that state
them. Cross-references (duplicate names, maneuvers, macros, transitions,
criterion targets, mesh files) need the whole level and are checked by
``sandbox.levels.loader``, which also knows line numbers.

Units are SI (m, s, kg); angles are degrees; times in the FSM are ticks
(one tick = one rendered frame).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal, Union

from pydantic import (
    AfterValidator,
    AllowInfNan,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Strict,
    Tag,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from sandbox.model.sites import MAX_COORD, ClothLine, ClothSite, RopeSite


def fail(kind: str, message: str) -> PydanticCustomError:
    """A validation error of type ``kind`` with a fully formatted message."""
    return PydanticCustomError(kind, message)

SCHEMA_VERSION = 1
TERMINAL_STATES = ("success", "failure")
"""Names of the FSM's two terminal states."""


Float = Annotated[float, Strict(), AllowInfNan(False)]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]


def _range_text(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is not None:
        return f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    return f"{'<' if hi_open else '<='} {hi:g}"


def between(
    kind: type,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
) -> Any:
    """A strict ``int`` or ``float`` type limited to a range, whose error states the range."""
    text = _range_text(lo, hi, lo_open, hi_open)

    def check(value: float) -> float:
        below = lo is not None and (value <= lo if lo_open else value < lo)
        above = hi is not None and (value >= hi if hi_open else value > hi)
        if below or above:
            raise fail("out_of_range", f"{value!r} is out of range; allowed {text}")
        return value

    base = Int if kind is int else Float
    return Annotated[base, AfterValidator(check)]


MAX_VALUE = 1.0e6
"""Largest other quantity (masses, compliances, times in s, budgets in ms)."""

Positive = between(float, 0, MAX_VALUE, lo_open=True)
NonNegative = between(float, 0, MAX_VALUE)
Length = between(float, 0, MAX_COORD, lo_open=True)
Coord = between(float, -MAX_COORD, MAX_COORD)
Unit = between(float, 0, 1)
Friction = between(float, 0, 2)
Vec3 = tuple[Coord, Coord, Coord]
Color = tuple[Unit, Unit, Unit]


def _identifier(value: str) -> str:
    if not value.isidentifier():
        raise fail(
            "identifier",
            f"{value!r} is not a valid name; allowed: letters, digits and '_', "
            "not starting with a digit",
        )
    return value


Name = Annotated[Str, AfterValidator(_identifier)]

Shape = Literal[
    "box", "sphere", "cylinder", "capsule", "torus",
    "wine_bottle", "basket", "jeep", "statue", "mesh",
]
Solver = Literal["xpbd", "projection"]
Arch = Literal["auto", "cpu", "cuda", "vulkan", "metal"]
Tier = Literal["accurate", "interactive"]
Event = Literal["done", "failed", "timeout"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)


class Ground(_Model):
    """An infinite horizontal plane.

    Attributes:
        height: y of the plane (m).
        friction: Coulomb coefficient.
    """

    height: Coord = 0.0
    friction: Friction = 0.5


class Camera(_Model):
    """Viewpoint of rendered frames (m, degrees, s).

    With ``follow`` the camera tracks the knot of those ropes (or strands
    ``R[i0:i1]``, or cloth lines ``F.line1`` / ``F.P..Q``): it looks at
    where they touch (the median of their touching points; of one rope,
    where parts of it more than half a turn apart touch) from the direction
    of ``position`` seen from ``look_at``, ``distance`` away (default: as far
    as ``position`` is from ``look_at``). The point it looks at moves
    towards the knot with time constant ``smoothing`` (0: at once), so that
    a tail brushing past does not jerk the view; before anything touches it
    stays at ``look_at``.
    """

    position: Vec3
    look_at: Vec3
    fov: between(float, 1, 170, lo_open=True, hi_open=True) = 45.0
    follow: list[Str] = []
    distance: Length | None = None
    smoothing: NonNegative = 0.5


class Keyframe(_Model):
    """A pose of a kinematic object at a time (s)."""

    time: NonNegative
    position: Vec3
    rotation: Vec3 = (0.0, 0.0, 0.0)


class Motion(_Model):
    """A kinematic script: poses interpolated between keyframes."""

    keyframes: Annotated[list[Keyframe], Field(min_length=2)]
    loop: Bool = False

    @field_validator("keyframes")
    @classmethod
    def _increasing(cls, keyframes: list[Keyframe]) -> list[Keyframe]:
        for i in range(1, len(keyframes)):
            if keyframes[i].time <= keyframes[i - 1].time:
                raise fail(
                    "keyframe_order",
                    f"keyframe times must increase strictly; keyframe {i} "
                    f"({keyframes[i].time:g} s) does not come after keyframe {i - 1} "
                    f"({keyframes[i - 1].time:g} s)",
                )
        return keyframes


class ObjectSpec(_Model):
    """A rigid obstacle (static, or kinematic when ``motion`` is given).

    ``params`` are the builder's shape parameters; their names are checked
    against ``sandbox.objects.builders.SHAPES`` by the loader.
    Pose: position (m) and XYZ Euler rotation (degrees, R = Rz Ry Rx).
    """

    name: Name
    shape: Shape
    params: dict[Str, Any] = {}
    position: Vec3 = (0.0, 0.0, 0.0)
    rotation: Vec3 = (0.0, 0.0, 0.0)
    friction: Friction = 0.5
    motion: Motion | None = None


class ClothSpec(_Model):
    """A rectangular cloth, flat in the xz plane at rest.

    Attributes:
        resolution: particles along x and z, ``[nx, nz]``; particle (i, j) has
            index ``j * nx + i``.
        size: extent along x and z (m).
        center: position of the cloth's centre (m).
        yaw: turn of the cloth about the vertical through ``center`` (degrees,
            counter-clockwise seen from above, as an object's y rotation);
            grid axes, corners and control lines turn with it.
        mass: total mass (kg).
        thickness: collision thickness (m); None means 1.5 x particle spacing.
        stretch_compliance, shear_compliance, bend_compliance: XPBD
            compliances (inverse stiffness). Rows and columns at stretch
            compliance 0 are inextensible (the chain steps); shear is soft
            by default (1e-3 m/N): the fast projection the method builds on
            constrains warp and weft only. A cloth laid over a vertex must
            shear there, and a stiff shear (1e-6: all but rigid for
            drape_box's 19 mg particles) locks against the rows and columns
            (the particle over a box vertex thrown back and forth at
            0.45-1.3 m/s while the cloth lies still). Set it lower for a
            cloth that resists shear (paper, felt).
        damping: fraction of velocity lost per second (each substep scales it
            by 1 - damping * dt), in [0, 1].
        pins: particles held in place.
        medial_sheet: cloth lines (control lines 1-4, or [P, Q] between two
            sites) whose gathered cloth keeps to its own line's side, as
            when two corners are knotted (paper §5.2; docs/how-it-works.md,
            "Medial sheet"). Empty: the pass is not built.
        color, back_color: RGB of the two sides, in [0, 1].
    """

    name: Name
    resolution: tuple[between(int, 2, 1024), between(int, 2, 1024)]
    size: tuple[Length, Length]
    center: Vec3
    yaw: Coord = 0.0
    mass: Positive = 0.5
    thickness: Length | None = None
    stretch_compliance: NonNegative = 0.0
    shear_compliance: NonNegative = 1e-3
    bend_compliance: NonNegative = 1e-3
    damping: Unit = 0.01
    friction: Friction = 0.5
    self_collision: Bool = True
    pins: list[ClothSite] = []
    medial_sheet: list[ClothLine] = []
    color: Color = (0.8, 0.25, 0.2)
    back_color: Color = (0.9, 0.8, 0.6)

    @field_validator("pins")
    @classmethod
    def _pins_in_grid(cls, pins: list, info: ValidationInfo) -> list:
        res = info.data.get("resolution")
        if res is None:
            return pins
        for k, pin in enumerate(pins):
            if isinstance(pin, tuple) and not (0 <= pin[0] < res[0] and 0 <= pin[1] < res[1]):
                raise fail(
                    "pin_range",
                    f"pin {k} {list(pin)} is outside the grid; allowed i in [0, {res[0] - 1}], "
                    f"j in [0, {res[1] - 1}]",
                )
        return pins


class RopeSpec(_Model):
    """A rope: a chain of particles along a polyline, as rods of equal length.

    Exactly one of ``segments`` (number of rods) and ``rod_length`` (m) is
    given; ``segment_count`` resolves either into a number of rods.
    ``motion`` moves the pins like a hand that holds them: each keyframe's
    pose (position, XYZ Euler degrees about the world origin) is applied to
    the pins' initial positions; pins released by a maneuver stop following.
    """

    name: Name
    points: Annotated[list[Vec3], Field(min_length=2)]
    segments: between(int, 1, 4096) | None = None
    rod_length: Length | None = None
    radius: Length
    mass: Positive = 0.05
    stretch_compliance: NonNegative = 0.0
    bend_compliance: NonNegative = 1e-2
    damping: Unit = 0.01
    friction: Friction = 0.5
    pins: list[RopeSite] = []
    motion: Motion | None = None
    color: Color = (0.2, 0.4, 0.9)

    @field_validator("rod_length")
    @classmethod
    def _not_both(cls, value: float | None, info: ValidationInfo) -> float | None:
        if value is not None and info.data.get("segments") is not None:
            raise fail("segments_and_rod_length", "give either 'segments' or 'rod_length', not both")
        return value

    @model_validator(mode="after")
    def _one_of(self) -> RopeSpec:
        if self.motion is not None and not self.pins:
            raise fail("motion_without_pins", "a rope's 'motion' moves its pins: give 'pins' as well")
        if self.segments is None and self.rod_length is None:
            raise fail("segments_or_rod_length", "give one of 'segments' or 'rod_length'")
        if not self.length > 0.0:
            raise fail("rope_length", "the rope's points are all at one place; allowed: points that span a length")
        n = self.segment_count
        for k, pin in enumerate(self.pins):
            if isinstance(pin, int) and not -(n + 1) <= pin <= n:
                raise fail(
                    "pin_range",
                    f"pin {k} ({pin}) is outside the rope; allowed indices in [{-(n + 1)}, {n}]",
                )
        return self

    @property
    def length(self) -> float:
        """Length of the rest polyline (m)."""
        return sum(math.dist(a, b) for a, b in zip(self.points, self.points[1:]))

    @property
    def segment_count(self) -> int:
        """Number of rods: ``segments``, or ``max(1, round(length / rod_length))``."""
        if self.segments is not None:
            return self.segments
        return max(1, round(self.length / self.rod_length))


def _ground(value: Any) -> Any:
    if value is False:
        return None
    if value is True:
        return {}
    return value


class Scene(_Model):
    """What is simulated: gravity (m/s^2), the ground, objects, cloths, ropes."""

    gravity: Vec3 = (0.0, -9.81, 0.0)
    ground: Annotated[Ground | None, BeforeValidator(_ground)] = Ground()
    camera: Camera | None = None
    objects: list[ObjectSpec] = []
    cloths: list[ClothSpec] = []
    ropes: list[RopeSpec] = []

    def names(self) -> dict[str, str]:
        """Name -> kind ("object", "cloth" or "rope") of every simulated body."""
        out: dict[str, str] = {}
        for kind, items in (("object", self.objects), ("cloth", self.cloths), ("rope", self.ropes)):
            for item in items:
                out.setdefault(item.name, kind)
        return out


CLOTH_CHAIN_SWEEPS = 3
"""Chain sweeps per iteration in a scene with an inextensible cloth, unless ``sim.chain_sweeps`` says otherwise."""

CLOTH_JOINT = 4
"""Conjugate-gradient iterations of the joint cloth step, unless ``sim.cloth_joint`` says otherwise."""

ADAPTIVE_SUBSTEPS = 4
"""Unless ``sim.max_substeps`` says otherwise, a frame may take up to this many times ``sim.substeps``."""


def default_max_substeps(substeps: int) -> int:
    """The most substeps a frame takes when ``sim.max_substeps`` is unset."""
    return min(200, ADAPTIVE_SUBSTEPS * int(substeps))


class Sim(_Model):
    """Time stepping: frames per second, substeps per frame, solver iterations.

    ``max_retries`` is the number of stability rollbacks allowed per frame.
    ``self_collision_every`` runs cloth self-collision on every k-th substep
    only (and always on the last substep of a frame). ``chain_sweeps`` is how
    many times each iteration alternates the exact chain step (ropes, cloth
    rows and columns) with the contacts; sweeps after the first re-solve
    only the chains with a rod still off its length by more than
    ``chain_tolerance`` (relative). Unset, a scene with an inextensible
    cloth takes ``CLOTH_CHAIN_SWEEPS`` (rows and columns disagree where the
    cloth crosses an object's edges and vertices) and a scene of ropes one
    (a rope's chain is solved exactly in one); 1 trades cloth stretch for
    frame time. How rope contacts are solved is the engine's, not a
    level's: mass splitting, inelastic, with the overlap a substep left
    pushed apart before the next one's prediction
    (``sandbox/collision/ropecollision.py``, ``sandbox/solvers/xpbd.py``
    step 0). ``cloth_joint`` is the number of
    conjugate-gradient iterations of a Newton step that solves all rows and
    columns of each inextensible cloth together, after the chain sweeps of
    every iteration (``CLOTH_JOINT`` unless set; 0: none, see
    ``sandbox/solvers/cloth_joint.py``), on every ``cloth_joint_every``-th
    substep of a frame and on its last one. It runs from the second frame
    on (the first starts from the rest lengths, before a level's FSM has
    taken hold of anything), in frames where no hand (a maneuver's hold; a
    scene's pins are not hands) holds a particle of a cloth: a cloth left to fall and drape, or hanging from pins, keeps
    its length where it lies over sharp vertices (drape_box: 17 % stretch
    without it, under 2 % with it, at about twice the frame time), while a
    cloth held by hands as well as pressed by an object has no
    length-keeping state to converge to (wrap_box_corner: 30 % to 11 % at
    3 x the frame time; wrap_bottle: 82 % to 108 %, with 2.4 x the
    substeps). A user sets 0 to trade a free cloth's stretch for frame time.
    The substep count adapts to the motion: each frame takes as many as
    keep the fastest particle (its speed at the end of the last frame plus
    gravity over one frame) within a quarter of the finest rest length (a
    cloth's spacing, a rope's rod) per substep, never fewer than
    ``substeps`` nor more than ``max_substeps`` (unset: 4 x ``substeps``,
    at most 200). A host that must bound a frame's cost sets
    ``max_substeps`` lower; ``max_substeps: <substeps>`` fixes the count.
    ``tier`` is the level's trade of frame time against accuracy:
    ``accurate`` (the default for ``sandbox run``, ``sweep`` and ``bench``)
    simulates every cloth at its own resolution; ``interactive`` (the
    default for ``sandbox play`` where a level states no tier) simulates a
    cloth of more than ``sandbox.world.INTERACTIVE_CLOTH_PARTICLES``
    particles on a coarser grid of the same size (drape_box's 163 x 163 on
    69 x 69), its ``[i, j]`` sites taken to the nearest point of that grid,
    and ``substeps`` and ``max_substeps`` scaled by the finest rest length
    of the scene before over after (a particle crosses the same fraction of
    it per substep at the same speed; a rope whose rods are no longer than
    the level's cloth spacing keeps them). Ropes are simulated alike in both.
    """

    fps: between(int, 1, 1000) = 60
    substeps: between(int, 1, 200) = 10
    iterations: between(int, 1, 100) = 1
    solver: Solver = "xpbd"
    arch: Arch = "auto"
    frames: between(int, 1, 1_000_000) = 240
    max_retries: between(int, 0, 10) = 3
    self_collision_every: between(int, 1, 16) = 1
    chain_sweeps: between(int, 1, 16) | None = None
    chain_tolerance: between(float, 0.0, 1.0) = 1e-3
    cloth_joint: between(int, 0, 64) = CLOTH_JOINT
    cloth_joint_every: between(int, 1, 200) = 1
    max_substeps: between(int, 1, 200) | None = None
    tier: Tier | None = None


class Budget(_Model):
    """Frame-time limits (ms) checked by ``sandbox bench``."""

    frame_ms_p50: Positive | None = None
    frame_ms_p95: Positive | None = None


def _known_metrics() -> list[str]:
    from sandbox.io.criteria import METRICS  # noqa: PLC0415  (the one list of metric names)

    return list(METRICS)


class Criterion(_Model):
    """A success condition checked at the end of a run.

    Attributes:
        metric: a name from ``sandbox.io.criteria.METRICS``.
        of: the rope(s), cloth(s), object(s) or FSM state(s) it applies to.
        min, max: inclusive bounds on the metric's value.
        equals: the exact value (a number, or a name such as a knot type).
    """

    metric: Str
    of: Str | list[Str] | None = None
    min: Float | None = None
    max: Float | None = None
    equals: Str | Float | None = None

    @field_validator("metric")
    @classmethod
    def _known(cls, value: str) -> str:
        known = _known_metrics()
        if value not in known:
            raise fail("unknown_metric", f"unknown metric {value!r}; allowed: {', '.join(known)}")
        return value

    @model_validator(mode="after")
    def _bounded(self) -> Criterion:
        if self.min is None and self.max is None and self.equals is None:
            raise fail("criterion_bound", "give at least one of 'min', 'max' or 'equals'")
        if self.min is not None and self.max is not None and self.min > self.max:
            raise fail("criterion_bound", f"min ({self.min:g}) is greater than max ({self.max:g})")
        return self

    def targets(self) -> list[str]:
        """``of`` as a list (empty when not given)."""
        if self.of is None:
            return []
        return [self.of] if isinstance(self.of, str) else list(self.of)


Ticks = between(int, 1)


class Step(_Model):
    """One link of a chain: run a maneuver or macro with parameters.

    ``with_`` is written ``with`` in YAML. ``timeout`` is in ticks (frames).
    """

    run: Str
    with_: dict[Str, Any] = Field(default={}, alias="with")
    timeout: Ticks | None = None
    name: Str | None = None


class State(_Model):
    """A named FSM state.

    Attributes:
        run: a registered maneuver name or a macro name.
        with_: its parameters (``with`` in YAML).
        timeout: ticks (frames) before the ``timeout`` transition fires.
        on: event -> destination (a state, ``success`` or ``failure``);
            missing entries default to done -> success, failed/timeout -> failure.
    """

    run: Str
    with_: dict[Str, Any] = Field(default={}, alias="with")
    timeout: Ticks | None = None
    on: dict[Event, Str] = {}


class FSMGraph(_Model):
    """An FSM written as named states and their transitions."""

    initial: Str
    states: Annotated[dict[Str, State], Field(min_length=1)]


def _fsm_form(value: Any) -> str | None:
    if isinstance(value, (list, tuple)):
        return "chain"
    if isinstance(value, (dict, FSMGraph)):
        return "graph"
    return None


FSM = Annotated[
    Union[
        Annotated[Annotated[list[Step], Field(min_length=1)], Tag("chain")],
        Annotated[FSMGraph, Tag("graph")],
    ],
    Discriminator(
        _fsm_form,
        custom_error_type="fsm_form",
        custom_error_message="the FSM must be a list of steps (a chain) or a mapping "
        "with 'initial' and 'states'",
    ),
]
"""A chain (list of Steps, each ``done`` leading to the next) or an FSMGraph."""


class Macro(_Model):
    """A named, parameterised chain of steps.

    Inside ``steps``, a string value ``"$P"`` in ``with`` is replaced by the
    argument ``P`` of the state that runs the macro.
    """

    params: list[Name] = []
    steps: Annotated[list[Step], Field(min_length=1)]

    @field_validator("params")
    @classmethod
    def _unique(cls, params: list[str]) -> list[str]:
        seen = [p for i, p in enumerate(params) if p in params[:i]]
        if seen:
            raise fail("duplicate_param", f"parameter {seen[0]!r} is declared twice")
        return params


class Level(_Model):
    """A level: a scene, how to simulate it, and the FSM of maneuvers to run.

    ``include`` names macro library files (``sandbox/levels/include.py``): the
    loader reads them and puts their macros in ``macros``, so the ``include``
    of a loaded level is empty.
    """

    version: Literal[1]
    name: Str
    description: Str = ""
    scene: Scene
    sim: Sim = Sim()
    include: list[Str] = []
    macros: dict[Str, Macro] = {}
    fsm: FSM
    success: list[Criterion] = []
    budget: Budget = Budget()
