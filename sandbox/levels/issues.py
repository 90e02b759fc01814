"""Problems found in a level, with where they are."""

from __future__ import annotations

import dataclasses
import enum
from typing import Any


class Severity(str, enum.Enum):
    """An error stops the level from loading; a warning does not."""

    ERROR = "error"
    WARNING = "warning"


@dataclasses.dataclass(frozen=True)
class LevelIssue:
    """One problem in a level file.

    Attributes:
        file: the source (a path, or ``<string>``).
        line: 1-based line (0 when the problem has no place in the file).
        column: 1-based column (0 as for ``line``).
        path: dotted position in the document, e.g. ``scene.ropes[0].radius``.
        message: what is wrong and what is allowed.
        severity: error or warning.
    """

    file: str
    line: int
    column: int
    path: str
    message: str
    severity: Severity = Severity.ERROR

    def __str__(self) -> str:
        tag = "warning: " if self.severity is Severity.WARNING else ""
        if self.line < 1:  # about the file as a whole (missing, not a file): no place in it to point at
            return f"{self.file}: {self.path + ': ' if self.path else ''}{tag}{self.message}"
        return f"{self.file}:{self.line}:{self.column}: {self.path or '<root>'}: {tag}{self.message}"


class LevelError(ValueError):
    """A level failed validation; ``errors`` holds every problem found.

    Attributes:
        errors: the errors, in file order.
        warnings: the warnings found along with them.
    """

    def __init__(self, errors: list[LevelIssue], warnings: list[LevelIssue] | None = None):
        self.errors = list(errors)
        self.warnings = list(warnings or [])
        super().__init__(str(self))

    def __str__(self) -> str:
        return "\n".join(str(e) for e in self.errors)

    def __reduce__(self) -> tuple:
        return (type(self), (self.errors, self.warnings))


class LevelWarning(UserWarning):
    """Issued (through ``warnings.warn``) for each warning of a level that loads."""


def format_path(path: tuple[Any, ...]) -> str:
    """``('scene', 'ropes', 0, 'radius')`` -> ``scene.ropes[0].radius``."""
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def syntax_issue(exc: Any, source: str) -> LevelIssue:
    """The issue for a YAML syntax error (a ``yaml.MarkedYAMLError``), at its line and column."""
    mark = exc.problem_mark or exc.context_mark
    line, col = (mark.line + 1, mark.column + 1) if mark else (1, 1)
    problem = " ".join(p for p in (exc.context, exc.problem) if p)
    from sandbox.levels.yamlio import LimitError  # noqa: PLC0415

    return LevelIssue(source, line, col, "", problem if isinstance(exc, LimitError) else f"YAML syntax: {problem}")
