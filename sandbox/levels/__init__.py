"""Levels: the YAML schema, the strict loader, macros and the FSM runner (SPEC §7).

Typical use::

    level = load_level("levels/basket_wrap.yaml", {"sim.frames": 10})
    fsm = FSMRunner(level, world)
    while not fsm.finished:
        world.step()
        fsm.tick()
"""

from sandbox.levels.expand import FlatFSM, FlatState, Scope, expand
from sandbox.levels.fsm import EventType, FSMRunner
from sandbox.levels.issues import LevelError, LevelIssue, LevelWarning, Severity
from sandbox.levels.loader import (
    LevelCheck,
    apply_overrides,
    check_level,
    check_level_text,
    dump_level,
    load_level,
    load_level_from_string,
    parse_overrides,
)
from sandbox.levels.schema import (
    FSM,
    Budget,
    Camera,
    ClothSpec,
    Criterion,
    FSMGraph,
    Ground,
    Keyframe,
    Level,
    Macro,
    Motion,
    ObjectSpec,
    RopeSpec,
    Scene,
    Sim,
    State,
    Step,
)

__all__ = [
    "FSM", "Budget", "Camera", "ClothSpec", "Criterion", "EventType", "FSMGraph", "FSMRunner",
    "FlatFSM", "FlatState", "Ground", "Keyframe", "Level", "LevelCheck", "LevelError",
    "LevelIssue", "LevelWarning", "Macro", "Motion", "ObjectSpec", "RopeSpec", "Scene",
    "Scope", "Severity", "Sim", "State", "Step", "apply_overrides", "check_level",
    "check_level_text", "dump_level", "expand", "load_level", "load_level_from_string",
    "parse_overrides",
]
