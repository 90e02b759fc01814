"""The FSM runner: chains, transitions, macros, timeouts in ticks, events."""

from __future__ import annotations

import pathlib

import pydantic
import pytest

from sandbox.levels import FSMRunner, Level, LevelError, load_level, load_level_from_string
from sandbox.maneuvers.base import REGISTRY, Maneuver, Params, Status, register

DATA = pathlib.Path(__file__).parent / "data" / "levels"


def _register(cls: type[Maneuver]) -> type[Maneuver]:
    return REGISTRY[cls.name] if cls.name in REGISTRY else register(cls)


class _CountParams(Params):
    n: int = pydantic.Field(1, ge=1)
    tag: str = ""


class _FailParams(Params):
    after: int = 1
    message: str = "it broke"


class _Recording(Maneuver):
    """Appends (call, state tag, ...) to the world when the world is a list."""

    def _log(self, *entry) -> None:
        if isinstance(self.world, list):
            self.world.append(entry)

    def start(self) -> None:
        self._log("start", self.name, getattr(self.params, "tag", ""))

    def stop(self) -> None:
        self._log("stop", self.name, getattr(self.params, "tag", ""))


@_register
class _Count(_Recording):
    """Done after ``n`` updates; progress counts them."""

    name = "fsm_count"
    Params = _CountParams

    def update(self) -> Status:
        self.ticks += 1
        self.progress = self.ticks / self.params.n
        return Status.DONE if self.ticks >= self.params.n else Status.RUNNING


@_register
class _Fail(_Recording):
    """Fails after ``after`` updates with ``message``."""

    name = "fsm_fail"
    Params = _FailParams

    def update(self) -> Status:
        self.ticks += 1
        if self.ticks >= self.params.after:
            self.message = self.params.message
            return Status.FAILED
        return Status.RUNNING


@_register
class _Hold(_Recording):
    """Never finishes."""

    name = "fsm_hold"

    def update(self) -> Status:
        return Status.RUNNING


HEAD = "version: 1\nname: t\nscene: {}\n"


def run(runner: FSMRunner, limit: int = 1000) -> int:
    """Tick until the FSM finishes; returns the number of ticks."""
    for _ in range(limit):
        if runner.finished:
            break
        runner.tick()
    assert runner.finished
    return runner.ticks


def visited(runner: FSMRunner) -> list[str]:
    """Names of the states entered, in order."""
    return [e["state"] for e in runner.events if e["type"] == "enter"]


def test_chain_runs_in_order_to_success():
    """A list FSM runs its steps in order, one state each, and ends in success."""
    runner = FSMRunner(load_level(DATA / "chain.yaml"), None)
    assert runner.state == "0:fsm_count" and runner.succeeded is None
    assert run(runner) == 3 + 2 + 4
    assert runner.state == "success" and runner.succeeded is True and runner.progress == 1.0
    assert visited(runner) == ["0:fsm_count", "second", "2:fsm_count"]
    assert runner.durations == {"0:fsm_count": 3, "second": 2, "2:fsm_count": 4}


def test_start_update_stop_protocol():
    """Each state's maneuver is created and started on entry and stopped on exit, once."""
    world: list = []
    level = load_level_from_string(HEAD + "fsm:\n  - {run: fsm_count, with: {n: 2, tag: a}}\n"
                                   "  - {run: fsm_count, with: {n: 1, tag: b}}\n")
    runner = FSMRunner(level, world)
    runner.tick()
    assert world == [("start", "fsm_count", "a")]
    assert runner.maneuver.params.tag == "a" and runner.progress == 0.5
    runner.tick()  # a finishes; b starts at once, before the next physics step
    assert world[1:] == [("stop", "fsm_count", "a"), ("start", "fsm_count", "b")]
    runner.tick()
    assert world[3:] == [("stop", "fsm_count", "b")] and runner.maneuver is None
    assert [(e["tick"], e["type"], e["state"]) for e in runner.events] == [
        (1, "enter", "0:fsm_count"), (2, "done", "0:fsm_count"), (2, "exit", "0:fsm_count"),
        (2, "enter", "1:fsm_count"), (3, "done", "1:fsm_count"), (3, "exit", "1:fsm_count"),
    ]
    runner.tick()  # ticking a finished FSM does nothing
    assert runner.ticks == 3


def test_failure_message_and_failed_transition():
    """A failed maneuver's message is in the event and `on.failed` is followed."""
    level = load_level_from_string(HEAD + """\
fsm:
  initial: try
  states:
    try:
      run: fsm_fail
      with: {after: 2, message: lost grip}
      on: {failed: recover}
    recover:
      run: fsm_count
      with: {n: 1}
      on: {done: failure}
""")
    runner = FSMRunner(level, None)
    run(runner)
    failed = [e for e in runner.events if e["type"] == "failed"]
    assert failed == [{"tick": 2, "type": "failed", "state": "try", "maneuver": "fsm_fail",
                       "message": "lost grip"}]
    assert visited(runner) == ["try", "recover"]
    assert runner.state == "failure" and runner.succeeded is False


def test_failed_chain_goes_to_failure():
    """In a chain, any failure ends the FSM in `failure` without running later steps."""
    level = load_level_from_string(HEAD + "fsm:\n  - {run: fsm_fail}\n  - {run: fsm_count}\n")
    runner = FSMRunner(level, None)
    assert run(runner) == 1
    assert runner.state == "failure" and visited(runner) == ["0:fsm_fail"]


def test_timeout_counts_ticks():
    """A state with `timeout: 5` leaves on its 5th tick through `on.timeout`."""
    level = load_level_from_string(HEAD + """\
fsm:
  initial: wait
  states:
    wait: {run: fsm_hold, timeout: 5, on: {timeout: after}}
    after: {run: fsm_count, with: {n: 2}}
""")
    runner = FSMRunner(level, None)
    for _ in range(4):
        runner.tick()
    assert runner.state == "wait"
    runner.tick()
    assert runner.state == "after"
    timeout = [e for e in runner.events if e["type"] == "timeout"]
    assert [(e["tick"], e["state"]) for e in timeout] == [(5, "wait")]
    assert run(runner) == 7 and runner.succeeded
    assert runner.durations["wait"] == 5


def test_done_on_the_last_tick_beats_timeout():
    """A maneuver that is done on the tick its timeout expires counts as done."""
    level = load_level_from_string(HEAD + "fsm:\n  - {run: fsm_count, with: {n: 3}, timeout: 3}\n")
    runner = FSMRunner(level, None)
    run(runner)
    assert runner.succeeded and [e["type"] for e in runner.events] == ["enter", "done", "exit"]


def test_timeout_without_transition_fails():
    """A timeout with no `on.timeout` ends in failure."""
    level = load_level_from_string(HEAD + "fsm:\n  - {run: fsm_hold, timeout: 3}\n")
    runner = FSMRunner(level, None)
    assert run(runner) == 3 and runner.state == "failure"


MACROS = HEAD + """\
macros:
  pair:
    params: [A, B]
    steps:
      - {run: fsm_count, with: {n: $A, tag: first}}
      - {run: fsm_count, with: {n: $B, tag: second}}
  nested:
    params: [N]
    steps:
      - {run: pair, with: {A: 1, B: $N}}
      - {run: fsm_count, with: {n: 1, tag: last}, name: tail}
"""


def test_macro_expands_into_named_sub_states():
    """A macro state runs its steps as `<state>/<i>:<maneuver>` with arguments substituted."""
    level = load_level_from_string(MACROS + "fsm:\n  - {run: pair, with: {A: 2, B: 3}, name: knot}\n")
    runner = FSMRunner(level, None)
    assert run(runner) == 5 and runner.succeeded
    assert visited(runner) == ["knot/0:fsm_count", "knot/1:fsm_count"]
    assert runner.durations == {"knot/0:fsm_count": 2, "knot/1:fsm_count": 3, "knot": 5}
    assert runner.flat.states["knot/1:fsm_count"].params == {"n": 3, "tag": "second"}


def test_nested_macros():
    """Macros may call macros; names nest and arguments pass through."""
    level = load_level_from_string(MACROS + "fsm:\n  - {run: nested, with: {N: 4}, name: k}\n"
                                   "  - {run: fsm_count}\n")
    runner = FSMRunner(level, None)
    assert run(runner) == 1 + 4 + 1 + 1
    assert visited(runner) == ["k/0:pair/0:fsm_count", "k/0:pair/1:fsm_count", "k/tail",
                               "1:fsm_count"]
    assert runner.durations["k/0:pair"] == 5 and runner.durations["k"] == 6
    assert runner.flat.states["k/0:pair/1:fsm_count"].model.n == 4


def test_macro_timeout_covers_all_its_steps():
    """A macro state's timeout counts the ticks of all its sub-states together."""
    level = load_level_from_string(MACROS + """\
fsm:
  initial: k
  states:
    k: {run: pair, with: {A: 3, B: 10}, timeout: 6, on: {timeout: rescue}}
    rescue: {run: fsm_count}
""")
    runner = FSMRunner(level, None)
    for _ in range(5):
        runner.tick()
    assert runner.state == "k/1:fsm_count" and runner.scopes == ["k"]
    runner.tick()
    assert runner.state == "rescue"
    assert [(e["tick"], e["state"]) for e in runner.events if e["type"] == "timeout"] == [(6, "k")]
    assert run(runner) == 7 and runner.succeeded


def test_macro_failure_follows_the_macro_state():
    """A failing step inside a macro follows the `on.failed` of the state running the macro."""
    level = load_level_from_string(HEAD + """\
macros:
  m:
    steps: [{run: fsm_count}, {run: fsm_fail, with: {message: torn}}, {run: fsm_count}]
fsm:
  initial: a
  states:
    a: {run: m, on: {failed: b}}
    b: {run: fsm_count}
""")
    runner = FSMRunner(level, None)
    run(runner)
    assert visited(runner) == ["a/0:fsm_count", "a/1:fsm_fail", "b"] and runner.succeeded
    assert [e["message"] for e in runner.events if e["type"] == "failed"] == ["torn"]


def test_loop_reenters_with_a_fresh_maneuver_and_scope():
    """Re-entering a macro state creates new maneuvers and restarts its timeout count."""
    world: list = []
    level = load_level_from_string(HEAD + """\
macros:
  m:
    steps: [{run: fsm_count, with: {n: 2}}]
fsm:
  initial: a
  states:
    a: {run: m, timeout: 3, on: {done: b}}
    b: {run: fsm_fail, on: {failed: c}}
    c: {run: m, timeout: 3, on: {done: success}}
""")
    runner = FSMRunner(level, world)
    run(runner)
    assert runner.succeeded and world.count(("start", "fsm_count", "")) == 2
    level = load_level_from_string(HEAD + """\
macros:
  m:
    steps: [{run: fsm_count, with: {n: 2}}]
fsm:
  initial: a
  states:
    a: {run: m, timeout: 3, on: {done: z}}
    z: {run: fsm_fail, on: {failed: a}, timeout: 100}
""")
    runner = FSMRunner(level, None)
    for _ in range(12):
        runner.tick()
    assert not runner.finished  # 2 ticks in `a` per visit never reach its timeout of 3
    assert visited(runner)[:4] == ["a/0:fsm_count", "z", "a/0:fsm_count", "z"]


def test_runner_rejects_an_unchecked_level():
    """A level built in code with an unknown maneuver does not run."""
    level = Level.model_validate({"version": 1, "name": "x", "scene": {},
                                  "fsm": [{"run": "fsm_nothing"}]})
    with pytest.raises(LevelError, match="unknown maneuver or macro 'fsm_nothing'"):
        FSMRunner(level, None)


def test_runner_uses_the_given_registry():
    """The registry argument decides which class runs a maneuver name."""

    class Quick(_Count):
        def update(self) -> Status:
            return Status.DONE

    level = load_level_from_string(HEAD + "fsm:\n  - {run: fsm_count, with: {n: 50}}\n")
    runner = FSMRunner(level, None, registry={"fsm_count": Quick})
    assert run(runner) == 1 and runner.succeeded
