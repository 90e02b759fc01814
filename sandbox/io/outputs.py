"""Headless outputs: summary.json, metrics.jsonl, state.npz, meshes.

Every file is valid at every moment: the summary is written atomically
(temporary file + rename) at the start (status ``running``) and at the end,
metrics lines are flushed per frame.
"""

from __future__ import annotations

import json
import os
import pathlib
from typing import Any

import numpy as np


def _default(o: Any):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (set, tuple)):
        return list(o)
    return str(o)


def _clean(o: Any):
    """Replace non-finite floats with None (JSON has no NaN/inf)."""
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (float, np.floating)) and not np.isfinite(o):
        return None
    return o


SUMMARY_RESERVE = 256 * 1024
"""Bytes the first summary.json of a run takes (padded with spaces): the final one can be written
into that place when the disk is full."""


def _json_text(data: dict) -> str:
    return json.dumps(_clean(data), indent=2, default=_default)


def write_json_atomic(path: pathlib.Path, data: dict, *, reserve: int = 0) -> None:
    """Write JSON through a temporary file and a rename, padded with spaces to ``reserve`` bytes."""
    text = _json_text(data)
    text += " " * max(0, reserve - len(text.encode()) - 1) + "\n"
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise


def write_json_in_place(path: pathlib.Path, data: dict) -> None:
    """Overwrite ``path`` in place with JSON no longer than it (needs no free space); what does not fit is cut.

    Bulky entries (FSM events, per-pass timings) go first, then all but the
    status and its message.

    Raises:
        OSError: the file cannot be written even so.
    """
    size = path.stat().st_size
    slim = {k: v for k, v in data.items() if k not in ("fsm", "stage_ms_per_frame", "systems_ms", "traceback")}
    least = {k: data[k] for k in ("level", "status", "success", "frames_run", "message", "output_error") if k in data}
    for candidate in (data, slim, least):
        raw = _json_text(candidate).encode()
        if len(raw) < size:
            with open(path, "r+b") as f:
                f.write(raw + b" " * (size - len(raw) - 1) + b"\n")
                f.flush()
                os.fsync(f.fileno())
            return
    raise OSError(28, "no room for the summary", str(path))


class MetricsLog:
    """metrics.jsonl: one JSON object per frame, flushed as it goes; never a partial line.

    A line that cannot be written whole (a full disk) is cut back off the
    file before the error goes on.
    """

    def __init__(self, path: pathlib.Path) -> None:
        self.file = open(path, "wb", buffering=0)  # each line goes to the file at once: nothing held back

    def write(self, row: dict) -> None:
        line = (json.dumps(_clean(row), default=_default) + "\n").encode()
        start = self.file.tell()
        try:
            done = 0
            while done < len(line):
                n = self.file.write(line[done:])
                if not n:
                    raise OSError(28, "No space left on device", str(self.file.name))
                done += n
        except OSError:
            os.ftruncate(self.file.fileno(), start)
            self.file.seek(start)
            raise

    def close(self) -> None:
        try:
            self.file.close()
        except OSError:  # what was buffered past the last whole line was cut already
            pass


def write_state(path: pathlib.Path, world) -> None:
    """state.npz: ``rope_<name>`` and ``cloth_<name>`` (n, 3) float32 positions (m),
    ``object_<name>`` (4, 4) float64 world pose, ``frame`` and ``time`` (s)."""
    x = world.positions()
    arrays: dict[str, np.ndarray] = {"frame": np.array(world.frame), "time": np.array(world.time)}
    for name, r in world.ropes.items():
        arrays[f"rope_{name}"] = x[r.start : r.end]
    for name, c in world.cloths.items():
        arrays[f"cloth_{name}"] = x[c.start : c.end]
    for name in world.object_specs:
        p, rot = world.objects.pose(world.object_index(name))
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rot, p
        arrays[f"object_{name}"] = m
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def _export(mesh, path: pathlib.Path) -> None:
    """trimesh export through a temporary file and a rename."""
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    mesh.export(tmp)
    os.replace(tmp, path)


def write_meshes(folder: pathlib.Path, world) -> list[str]:
    """meshes/<name>.ply for every cloth (its grid triangles), rope (polyline) and object."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    x = world.positions()
    for name, c in world.cloths.items():
        _export(trimesh.Trimesh(x[c.start : c.end], c.faces, process=False), folder / f"cloth_{name}.ply")
        written.append(f"cloth_{name}.ply")
    for name, r in world.ropes.items():
        _export(trimesh.PointCloud(x[r.start : r.end]), folder / f"rope_{name}.ply")
        written.append(f"rope_{name}.ply")
    for name in world.object_specs:
        v, f = world.objects.world_mesh(world.object_index(name))
        _export(trimesh.Trimesh(v, f, process=False), folder / f"object_{name}.ply")
        written.append(f"object_{name}.ply")
    return written
