"""The results table of a sweep: one CSV file per level, one row per run, appended as runs finish.

Each row is written whole, flushed and synced before the next, so a sweep
that is killed leaves every finished run's row; a line cut short by the kill
is skipped on reading (its run is then run again). Cells are JSON (numbers,
``true``/``false``, lists), bare text, or empty (no value). The header holds
everything a report needs: criterion columns carry their bar in their name
(``value:max_strain(R) <= 0.01``, ``ok:max_strain(R) <= 0.01``).
"""

from __future__ import annotations

import csv
import json
import os
import pathlib
from typing import Any

FIRST = ("run", "level", "level_sha", "variant")
LAST = ("frame_ms_p50", "wall_s", "frames_run", "error", "backend", "host")
OUTCOME = ("status", "exit_code", "success")
TEXT = ("run", "level", "level_sha", "variant", "status", "error", "backend", "host")
"""Columns read back as text, whatever they look like (a run id such as ``1234e56`` is not a number)."""
FILE = "runs.csv"


def criterion_column(name: str, c) -> str:
    """``name`` with the criterion's bar: ``<= x``, ``>= x``, ``in [a, b]`` or ``= v``."""
    lo, hi, eq = (c.min, c.max, c.equals) if hasattr(c, "metric") else (c.get("min"), c.get("max"), c.get("equals"))
    if eq is not None:
        return f"{name} = {eq}"
    if lo is not None and hi is not None:
        return f"{name} in [{lo:g}, {hi:g}]"
    return f"{name} >= {lo:g}" if lo is not None else f"{name} <= {hi:g}"


def columns(axes: list[str], criteria: list[str]) -> list[str]:
    """Header of a level's table: ids, axes, outcome, criteria (value and ok), timing and error."""
    crit = [f"{p}:{c}" for c in criteria for p in ("value", "ok")]
    return [*FIRST, *axes, *OUTCOME, *crit, *LAST]


def encode(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, str):
        return value
    return json.dumps(value)


def decode(cell: str) -> Any:
    if cell == "":
        return None
    if cell[0] in "[{-0123456789tfn" or cell in ("NaN", "Infinity"):
        try:
            return json.loads(cell)
        except ValueError:
            pass
    return cell


def read(path: pathlib.Path) -> tuple[list[str], list[dict[str, Any]]]:
    """Header and rows of a table; rows cut short (a killed writer) are skipped; a later row of a run wins."""
    path = pathlib.Path(path)
    if not path.exists():
        return [], []
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.reader(f)
        header = next(reader, [])
        rows: dict[str, dict] = {}
        for cells in reader:
            if len(cells) != len(header):
                continue
            row = {k: (v if k in TEXT else decode(v)) for k, v in zip(header, cells)}
            if row.get("status") is None:
                continue
            rows[str(row["run"])] = row
    return header, list(rows.values())


def _cut_to_whole_rows(path: pathlib.Path, width: int) -> None:
    """Truncate ``path`` after its last whole row of ``width`` cells (a kill can leave half a row, whose open
    quotes would swallow the rows appended after it)."""
    text = path.read_bytes().decode("utf-8", errors="replace")
    lines = text.splitlines(keepends=True)
    used = [0]

    def feed():
        for line in lines:
            used[0] += len(line)
            yield line

    good = 0
    reader = csv.reader(feed())
    for cells in reader:
        if len(cells) == width and text[:used[0]].endswith(("\n", "\r")):
            good = used[0]
    if good < len(text):
        with open(path, "r+b") as f:
            f.truncate(len(text[:good].encode("utf-8")))


class Table:
    """Appends rows to ``path``; creates it with ``header``, or checks that an existing one matches.

    Raises:
        ValueError: the file exists with another header (another sweep's table).
    """

    def __init__(self, path: pathlib.Path, header: list[str]):
        self.path = pathlib.Path(path)
        self.header = list(header)
        old, _ = read(self.path)
        if old and old != self.header:
            missing = [c for c in self.header if c not in old]
            extra = [c for c in old if c not in self.header]
            raise ValueError(
                f"{self.path} holds a table of another sweep (columns only here: {', '.join(missing) or '-'}; "
                f"only there: {', '.join(extra) or '-'}); give another --out or remove it")
        new = not old
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not new:
            _cut_to_whole_rows(self.path, len(self.header))
        self._file = open(self.path, "w" if new else "a", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        if new:
            self._write(self.header)

    def _write(self, cells: list[str]) -> None:
        self._writer.writerow(cells)
        self._file.flush()
        os.fsync(self._file.fileno())

    def append(self, row: dict[str, Any]) -> None:
        """Write one row (missing columns empty); it is on disk when this returns."""
        self._write([encode(row.get(c)) for c in self.header])

    def close(self) -> None:
        self._file.close()
