"""Maneuver protocol and registry.

A maneuver is one discrete step of a level's FSM (paper Tables 1-2). It reads
the simulation through a ``World`` and writes kinematic targets into its
Control; the FSM calls ``update`` once per frame until it reports ``done`` or
``failed``. Parameters are a pydantic model so that levels are validated
before anything runs.
"""

from __future__ import annotations

import enum
from typing import Any, ClassVar

import pydantic


class Status(str, enum.Enum):
    """What a maneuver reports after each frame."""

    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"


class Params(pydantic.BaseModel):
    """Base of every maneuver's parameters: unknown keys are errors, numbers are finite."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Maneuver:
    """One maneuver instance, created when its FSM state is entered.

    Subclasses set ``name`` and ``Params`` and implement ``start`` and
    ``update``. ``progress`` is in [0, 1], ``message`` explains a failure and
    ``note`` records a choice the maneuver made for itself (written on the
    state's ``done`` event).
    """

    name: ClassVar[str] = ""
    Params: ClassVar[type[Params]] = Params

    def __init__(self, params: Params, world: Any) -> None:
        self.params = params
        self.world = world
        self.progress = 0.0
        self.message = ""
        self.note = ""
        self.ticks = 0

    def start(self) -> None:
        """Called once when the FSM enters the state."""

    def update(self) -> Status:
        """Called once per frame; returns the maneuver's status."""
        raise NotImplementedError

    def stop(self) -> None:
        """Called once when the FSM leaves the state (release what it holds)."""

    def metrics(self) -> dict[str, float]:
        """Per-frame numbers for metrics.jsonl (progress is added by the FSM)."""
        return {}


REGISTRY: dict[str, type[Maneuver]] = {}


def register(cls: type[Maneuver]) -> type[Maneuver]:
    """Class decorator: make a maneuver available to levels by its ``name``."""
    if not cls.name:
        raise ValueError(f"{cls.__qualname__} has no name")
    if cls.name in REGISTRY and REGISTRY[cls.name] is not cls:
        raise ValueError(f"maneuver {cls.name!r} is registered twice")
    REGISTRY[cls.name] = cls
    return cls


def allowed_maneuvers() -> list[str]:
    """Sorted names of the registered maneuvers."""
    return sorted(REGISTRY)
