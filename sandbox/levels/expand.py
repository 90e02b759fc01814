"""Macro expansion: a level's FSM as a flat graph of maneuver states.

A chain becomes named states (``step.name`` or ``<i>:<run>``, 0-based). A
state that runs a macro becomes a sub-chain of states named
``<state>/<i>:<run>`` (or ``<state>/<step name>``); macros may call macros.
Inside a macro, a whole-string value ``"$P"`` of a step's ``with`` is
replaced by the argument ``P`` of the call. Maneuver parameters are
validated after substitution, and each problem is reported at the document
position its value came from, with the chain of macro calls that led there.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping, Sequence
from typing import Any

import pydantic

from sandbox.levels.diagnostics import Finding, convert
from sandbox.levels.issues import Severity, format_path
from sandbox.levels.schema import TERMINAL_STATES, FSMGraph, Macro, Step
from sandbox.levels.yamlio import Path
from sandbox.maneuvers.base import Maneuver, Params

_REF = re.compile(r"^\$([A-Za-z_][A-Za-z0-9_]*)$")
_EVENTS = ("done", "failed", "timeout")
_DEFAULT_ON = {"done": "success", "failed": "failure", "timeout": "failure"}


@dataclasses.dataclass(frozen=True)
class Scope:
    """A state that runs a macro: its timeout counts every tick spent inside it.

    Attributes:
        name: the state's name (prefix of the names of its sub-states).
        macro: the macro it runs.
        timeout: ticks allowed inside the macro, or None.
        on_timeout: where to go when they run out.
    """

    name: str
    macro: str
    timeout: int | None
    on_timeout: str


@dataclasses.dataclass(frozen=True)
class FlatState:
    """A state of the expanded FSM: one maneuver.

    Attributes:
        name: unique state name.
        maneuver: registered maneuver name.
        params: its parameters after macro substitution (plain data).
        model: ``params`` validated by the maneuver's ``Params`` (None if invalid).
        timeout: ticks allowed in this state, or None.
        on: event (done, failed, timeout) -> destination node: a state, a
            macro-running state (entered at its first sub-state), or a terminal.
        scopes: the macro calls enclosing it, outermost first.
        path: where its step is written in the document.
    """

    name: str
    maneuver: str
    params: dict[str, Any]
    model: Params | None
    timeout: int | None
    on: dict[str, str]
    scopes: tuple[Scope, ...]
    path: Path


@dataclasses.dataclass
class FlatFSM:
    """The expanded FSM.

    Attributes:
        initial: the node entered first.
        states: maneuver states by name.
        entries: node name -> the maneuver state it starts with.
        scopes: macro-running states by name.
        top: the FSM's own state names, in order.
    """

    initial: str
    states: dict[str, FlatState]
    entries: dict[str, str]
    scopes: dict[str, Scope]
    top: list[str]

    def entry(self, node: str) -> str:
        """The maneuver state (or terminal) that entering ``node`` starts."""
        return node if node in TERMINAL_STATES else self.entries[node]

    def names(self) -> set[str]:
        """Every state name: top-level, macro-running and maneuver states."""
        return set(self.top) | set(self.states) | set(self.scopes)


@dataclasses.dataclass(frozen=True)
class Located:
    """A value with the document paths its parts came from.

    ``origins`` maps a path inside ``value`` to a document path; a part's
    position is that of its longest recorded prefix, extended by the rest.
    """

    value: Any
    origins: Mapping[Path, Path]

    def where(self, rel: Path) -> Path:
        """Document path of the part of ``value`` at ``rel``."""
        for n in range(len(rel), -1, -1):
            if rel[:n] in self.origins:
                return tuple(self.origins[rel[:n]]) + tuple(rel[n:])
        return tuple(rel)

    def sub(self, key: Any) -> Located:
        """The part at ``key``, with its origins."""
        origins = {(): self.where((key,))}
        for rel, doc in self.origins.items():
            if rel[:1] == (key,) and len(rel) > 1:
                origins[rel[1:]] = doc
        return Located(self.value[key], origins)


@dataclasses.dataclass(frozen=True)
class _Call:
    name: str
    run: str
    args: Located
    timeout: int | None
    on: dict[str, str]
    path: Path
    trace: tuple[tuple[str, Path], ...]


def substitute(template: Any, base: Path, args: Mapping[str, Located]) -> Located:
    """Replace whole-string ``"$P"`` values of ``template`` by ``args[P]``.

    Args:
        template: the ``with`` data of a macro step.
        base: its document path.
        args: the call's arguments.
    """
    origins: dict[Path, Path] = {(): base}

    def walk(value: Any, rel: Path) -> Any:
        if isinstance(value, str):
            ref = _REF.match(value)
            if ref and ref.group(1) in args:
                arg = args[ref.group(1)]
                for sub, doc in arg.origins.items():
                    origins[rel + sub] = doc
                return arg.value
            return value
        if isinstance(value, dict):
            return {k: walk(v, rel + (k,)) for k, v in value.items()}
        if isinstance(value, list):
            return [walk(v, rel + (i,)) for i, v in enumerate(value)]
        return value

    return Located(walk(template, ()), origins)


def _references(value: Any, rel: Path = ()) -> list[tuple[Path, str]]:
    if isinstance(value, str):
        ref = _REF.match(value)
        return [(rel, ref.group(1))] if ref else []
    if isinstance(value, dict):
        return [r for k, v in value.items() for r in _references(v, rel + (k,))]
    if isinstance(value, list):
        return [r for i, v in enumerate(value) for r in _references(v, rel + (i,))]
    return []


def _listing(names: Sequence[str]) -> str:
    return ", ".join(names) if names else "(none)"


class _Expander:
    def __init__(
        self,
        macros: Mapping[str, Macro],
        registry: Mapping[str, type[Maneuver]],
        unchecked: set[str],
    ) -> None:
        self.macros = macros
        self.registry = registry
        self.unchecked = unchecked
        self.findings: list[Finding] = []
        self.states: dict[str, FlatState] = {}
        self.entries: dict[str, str] = {}
        self.scopes: dict[str, Scope] = {}

    def error(self, path: Path, message: str, **kw: Any) -> None:
        self.findings.append(Finding(path=path, message=message, **kw))

    def unknown_run(self, run: str) -> str:
        return (
            f"unknown maneuver or macro {run!r}; registered maneuvers: "
            f"{_listing(sorted(self.registry))}; macros: "
            f"{_listing(sorted(set(self.macros) | self.unchecked))}"
        )

    def known(self, run: str) -> bool:
        return run in self.macros or run in self.unchecked or run in self.registry

    def check_name(self, name: str, path: Path, *, key: bool) -> None:
        if name in TERMINAL_STATES or "/" in name or not name:
            self.error(
                path,
                f"state name {name!r} is not allowed: 'success' and 'failure' are the "
                "terminal states, and '/' separates the states of a macro",
                key=key,
            )

    # -- macros, on their own -------------------------------------------------

    def check_macros(self) -> None:
        for name, macro in self.macros.items():
            base = ("macros", name)
            if name in self.registry:
                self.error(base, f"macro {name!r} has the name of a registered maneuver", key=True)
            used: set[str] = set()
            seen: dict[str, int] = {}
            for j, step in enumerate(macro.steps):
                path = base + ("steps", j)
                if not self.known(step.run):
                    self.error(path + ("run",), self.unknown_run(step.run))
                for rel, ref in _references(step.with_):
                    used.add(ref)
                    if ref not in macro.params:
                        self.error(
                            path + ("with",) + rel,
                            f"'${ref}' refers to an undeclared parameter of macro {name!r}; "
                            f"declared: {_listing(macro.params)}",
                        )
                if step.name is not None:
                    self.check_name(step.name, path + ("name",), key=False)
                    if step.name in seen:
                        self.error(
                            path + ("name",),
                            f"step name {step.name!r} is already used by step {seen[step.name]}",
                        )
                    seen.setdefault(step.name, j)
            for param in macro.params:
                if param not in used:
                    self.findings.append(Finding(
                        base + ("params",), f"parameter {param!r} of macro {name!r} is never used",
                        severity=Severity.WARNING,
                    ))
        self._check_recursion()

    def _check_recursion(self) -> None:
        done: set[str] = set()

        def visit(name: str, stack: tuple[str, ...]) -> None:
            path = stack + (name,)
            for j, step in enumerate(self.macros[name].steps):
                if step.run not in self.macros:
                    continue
                if step.run in path:
                    cycle = path[path.index(step.run):] + (step.run,)
                    self.error(
                        ("macros", name, "steps", j, "run"),
                        f"macro recursion: {' -> '.join(cycle)}",
                    )
                elif step.run not in done:
                    visit(step.run, path)
            done.add(name)

        for name in self.macros:
            if name not in done:
                visit(name, ())

    # -- the FSM's own states -------------------------------------------------

    def top_level(self, fsm: Sequence[Step] | FSMGraph) -> tuple[str, list[_Call]]:
        if isinstance(fsm, FSMGraph):
            return self._graph(fsm)
        names: list[str] = []
        for i, step in enumerate(fsm):
            name = step.name if step.name is not None else f"{i}:{step.run}"
            if step.name is not None:
                self.check_name(name, ("fsm", i, "name"), key=False)
            if name in names:
                self.error(
                    ("fsm", i, "name"),
                    f"state name {name!r} is already used by step {names.index(name)}",
                )
            names.append(name)
        calls = []
        for i, step in enumerate(fsm):
            nxt = names[i + 1] if i + 1 < len(names) else "success"
            on = {"done": nxt, "failed": "failure", "timeout": "failure"}
            calls.append(self._call(names[i], step, on, ("fsm", i)))
        return names[0], calls

    def _graph(self, fsm: FSMGraph) -> tuple[str, list[_Call]]:
        names = list(fsm.states)
        allowed = _listing(names + list(TERMINAL_STATES))
        calls = []
        for name, state in fsm.states.items():
            path = ("fsm", "states", name)
            self.check_name(name, path, key=True)
            for event, dest in state.on.items():
                if dest not in names and dest not in TERMINAL_STATES:
                    self.error(
                        path + ("on", event),
                        f"unknown destination {dest!r} for {event!r}; allowed: {allowed}",
                    )
            calls.append(self._call(name, state, {**_DEFAULT_ON, **state.on}, path))
        if fsm.initial not in names:
            self.error(("fsm", "initial"), f"unknown initial state {fsm.initial!r}; allowed: "
                       f"{_listing(names)}")
            return fsm.initial, calls
        reached, todo = {fsm.initial}, [fsm.initial]
        while todo:
            state = fsm.states[todo.pop()]
            for dest in {**_DEFAULT_ON, **state.on}.values():
                if dest in fsm.states and dest not in reached:
                    reached.add(dest)
                    todo.append(dest)
        for name in names:
            if name not in reached:
                self.findings.append(Finding(
                    ("fsm", "states", name),
                    f"state {name!r} cannot be reached from {fsm.initial!r}",
                    severity=Severity.WARNING, key=True,
                ))
        return fsm.initial, calls

    def _call(self, name: str, step: Any, on: dict[str, str], path: Path) -> _Call:
        args = Located(step.with_, {(): path + ("with",)})
        if not self.known(step.run):
            self.error(path + ("run",), self.unknown_run(step.run))
        return _Call(name, step.run, args, step.timeout, on, path, ())

    # -- expansion ------------------------------------------------------------

    def expand(self, call: _Call, scopes: tuple[Scope, ...], stack: tuple[str, ...]) -> None:
        if call.run in self.macros:
            if call.run not in stack:  # recursion is reported by check_macros
                self._macro(call, scopes, stack)
        elif call.run in self.registry:
            self._leaf(call, scopes)

    def _leaf(self, call: _Call, scopes: tuple[Scope, ...]) -> None:
        cls = self.registry[call.run]
        model = None
        try:
            model = cls.Params.model_validate(call.args.value)
        except pydantic.ValidationError as exc:
            for f in convert(exc, cls.Params, call.args.value):
                self.error(
                    call.args.where(f.path), f"maneuver {call.run!r}: {f.message}",
                    key=f.key, trace=call.trace,
                )
        self.states[call.name] = FlatState(
            name=call.name, maneuver=call.run, params=call.args.value, model=model,
            timeout=call.timeout, on=call.on, scopes=scopes, path=call.path,
        )
        self.entries[call.name] = call.name

    def _macro(self, call: _Call, scopes: tuple[Scope, ...], stack: tuple[str, ...]) -> None:
        macro = self.macros[call.run]
        given = call.args.value
        ok = True
        for arg in given:
            if arg not in macro.params:
                ok = False
                self.error(
                    call.args.where((arg,)),
                    f"unknown argument {arg!r} of macro {call.run!r}; declared parameters: "
                    f"{_listing(macro.params)}",
                    key=True, trace=call.trace,
                )
        missing = [p for p in macro.params if p not in given]
        if missing:
            ok = False
            self.error(
                call.args.where(()),
                f"macro {call.run!r} needs argument(s) {_listing(missing)} in 'with' "
                f"(declared: {_listing(macro.params)})",
                trace=call.trace,
            )
        if not ok:
            return
        scope = Scope(call.name, call.run, call.timeout, call.on["timeout"])
        self.scopes[call.name] = scope
        args = {p: call.args.sub(p) for p in macro.params}
        names = [
            f"{call.name}/{step.name if step.name is not None else f'{j}:{step.run}'}"
            for j, step in enumerate(macro.steps)
        ]
        for j, step in enumerate(macro.steps):
            path = ("macros", call.run, "steps", j)
            on = {
                "done": names[j + 1] if j + 1 < len(names) else call.on["done"],
                "failed": call.on["failed"],
                "timeout": call.on["timeout"],
            }
            trace = (
                (f"in macro {call.run!r} step {j}", path),
                (f"called from {format_path(call.path)}", call.path),
            )
            child = _Call(
                names[j], step.run, substitute(step.with_, path + ("with",), args),
                step.timeout, on, path, trace + call.trace,
            )
            self.expand(child, scopes + (scope,), stack + (call.run,))
        if names[0] in self.entries:
            self.entries[call.name] = self.entries[names[0]]


def expand(
    fsm: Sequence[Step] | FSMGraph | None,
    macros: Mapping[str, Macro],
    registry: Mapping[str, type[Maneuver]],
    *,
    unchecked: set[str] | None = None,
) -> tuple[FlatFSM, list[Finding]]:
    """Expand an FSM's macros into a flat graph and check it.

    Args:
        fsm: the level's FSM (a chain or a graph); None checks the macros only.
        macros: the level's macros.
        registry: maneuver name -> class.
        unchecked: names of macros that exist but failed their own validation
            (calls to them are neither expanded nor reported).

    Returns:
        The flat FSM (complete only when no error was found) and the findings.
    """
    ex = _Expander(macros, registry, set(unchecked or ()))
    ex.check_macros()
    if fsm is None:
        return FlatFSM("", {}, {}, {}, []), ex.findings
    initial, calls = ex.top_level(fsm)
    for call in calls:
        ex.expand(call, (), ())
    flat = FlatFSM(initial, ex.states, ex.entries, ex.scopes, [c.name for c in calls])
    return flat, ex.findings
