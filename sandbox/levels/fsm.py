"""The FSM runner: steps a level's maneuvers, one tick per rendered frame.

The host calls ``tick()`` once per frame, after the physics step. Entering a
state creates its maneuver (``cls(params, world)``) and calls ``start()``;
every tick calls ``update()`` and counts the tick; ``done``, ``failed`` or a
timeout leaves the state (``stop()``) and follows its transition. The first
state is entered on the first tick; later states are entered on the tick
their predecessor ends, so that ``start()`` can set targets before the next
physics step, and get their first ``update()`` on the following tick.

A state that runs a macro is a scope over its sub-states: its timeout counts
every tick spent in any of them.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from typing import Any

from sandbox.levels.expand import FlatFSM, FlatState, expand
from sandbox.levels.issues import LevelError, Severity
from sandbox.levels.loader import issues_from_findings
from sandbox.levels.schema import Level
from sandbox.maneuvers.base import REGISTRY, Maneuver, Status


class EventType(str, enum.Enum):
    """Kinds of entries in ``FSMRunner.events``."""

    ENTER = "enter"
    EXIT = "exit"
    DONE = "done"
    FAILED = "failed"
    TIMEOUT = "timeout"


class FSMRunner:
    """Runs the FSM of a level against a world.

    Args:
        level: a validated level.
        world: passed to each maneuver, unread here.
        registry: maneuver name -> class.

    Raises:
        LevelError: when the FSM does not expand (a level built in code
            without ``load_level``'s checks).
    """

    def __init__(
        self,
        level: Level,
        world: Any,
        *,
        registry: Mapping[str, type[Maneuver]] = REGISTRY,
    ) -> None:
        flat, findings = expand(level.fsm, level.macros, registry)
        errors = [f for f in findings if f.severity is Severity.ERROR]
        if errors:
            raise LevelError(issues_from_findings(errors, f"<level {level.name}>"))
        self.flat: FlatFSM = flat
        """The expanded FSM."""
        self.world = world
        self._registry = registry
        self._state = flat.entry(flat.initial)
        self._maneuver: Maneuver | None = None
        self._entered = False
        self._tick = 0
        self._ticks_in_state = 0
        self._scope_ticks: dict[str, int] = {}
        self.events: list[dict[str, Any]] = []
        """``{"tick", "type", "state", "maneuver", "message"}`` in order."""
        self.durations: dict[str, int] = {}
        """State name (maneuver states and macro-running states) -> ticks spent, summed."""
        if self._state in ("success", "failure"):
            self._entered = True

    # -- read-only view ---------------------------------------------------------

    @property
    def state(self) -> str:
        """Current state's name, or ``success`` / ``failure`` once finished."""
        return self._state

    @property
    def finished(self) -> bool:
        """Whether a terminal state has been reached."""
        return self._state in ("success", "failure")

    @property
    def succeeded(self) -> bool | None:
        """True on ``success``, False on ``failure``, None while running."""
        return None if not self.finished else self._state == "success"

    @property
    def maneuver(self) -> Maneuver | None:
        """The running maneuver instance, or None."""
        return self._maneuver

    @property
    def progress(self) -> float:
        """The running maneuver's progress in [0, 1] (1 after success, 0 after failure)."""
        if self.finished:
            return 1.0 if self._state == "success" else 0.0
        return float(self._maneuver.progress) if self._maneuver is not None else 0.0

    @property
    def ticks(self) -> int:
        """Number of ``tick()`` calls so far."""
        return self._tick

    @property
    def scopes(self) -> list[str]:
        """Names of the macro-running states enclosing the current state, outermost first."""
        if self.finished:
            return []
        return [s.name for s in self.flat.states[self._state].scopes]

    # -- stepping -----------------------------------------------------------------

    def tick(self) -> None:
        """Advance the FSM by one frame (call after the physics step)."""
        if self.finished:
            return
        self._tick += 1
        if not self._entered:
            self._enter(self._state, set())
        flat = self.flat.states[self._state]
        assert self._maneuver is not None
        status = Status(self._maneuver.update())
        self._ticks_in_state += 1
        self.durations[flat.name] = self.durations.get(flat.name, 0) + 1
        for scope in flat.scopes:
            self._scope_ticks[scope.name] += 1
            self.durations[scope.name] = self.durations.get(scope.name, 0) + 1

        if status is Status.DONE:
            self._leave(EventType.DONE, flat.name, flat.on["done"], self._maneuver.note)
        elif status is Status.FAILED:
            self._leave(EventType.FAILED, flat.name, flat.on["failed"], self._maneuver.message)
        elif flat.timeout is not None and self._ticks_in_state >= flat.timeout:
            self._leave(EventType.TIMEOUT, flat.name, flat.on["timeout"],
                        f"no result after {flat.timeout} ticks")
        else:
            for scope in flat.scopes:  # the outermost expired scope wins
                if scope.timeout is not None and self._scope_ticks[scope.name] >= scope.timeout:
                    self._leave(EventType.TIMEOUT, scope.name, scope.on_timeout,
                                f"macro {scope.macro!r} took {scope.timeout} ticks")
                    break

    def close(self) -> None:
        """Stop the running maneuver (a run cut short); the state is kept."""
        if self._maneuver is not None:
            self._exit(self.flat.states[self._state], "stopped")

    # -- transitions ----------------------------------------------------------------

    def _event(self, kind: EventType, state: str, maneuver: str | None, message: str = "") -> None:
        self.events.append({
            "tick": self._tick, "type": kind.value, "state": state,
            "maneuver": maneuver, "message": message,
        })

    def _enter(self, name: str, entered_scopes: set[str]) -> None:
        self._state = name
        self._entered = True
        if self.finished:
            self._maneuver = None
            return
        flat: FlatState = self.flat.states[name]
        for scope in flat.scopes:
            if scope.name in entered_scopes or scope.name not in self._scope_ticks:
                self._scope_ticks[scope.name] = 0
        self._ticks_in_state = 0
        cls = self._registry[flat.maneuver]
        params = flat.model if flat.model is not None else cls.Params.model_validate(flat.params)
        self._maneuver = cls(params, self.world)
        self._event(EventType.ENTER, name, flat.maneuver)
        self._maneuver.start()

    def _exit(self, flat: FlatState, message: str = "") -> None:
        assert self._maneuver is not None
        self._maneuver.stop()
        self._event(EventType.EXIT, flat.name, flat.maneuver, message)
        self._maneuver = None

    def _leave(self, kind: EventType, source: str, dest: str, message: str = "") -> None:
        flat = self.flat.states[self._state]
        self._event(kind, source, flat.maneuver, message)
        self._exit(flat)
        entered = {dest} if dest in self.flat.scopes else set()
        target = self.flat.entry(dest)
        if target not in ("success", "failure"):
            # every scope of the target at or below ``dest`` is entered afresh
            entered |= {
                s.name for s in self.flat.states[target].scopes
                if s.name == dest or s.name.startswith(dest + "/")
            }
        self._enter(target, entered)
