"""Resource limits checked before a level runs, and the folders mesh files may come from.

A level that would need millions of particles, more substeps than a day
of computing, or more memory than the machine has says so at ``check``,
before anything is allocated. The limits are defaults a user can raise:
``--limit particles=2000000`` on ``sandbox run`` and ``check``, or the
environment variable ``SANDBOX_LIMITS="particles=2e6,steps=1e9,memory_gb=32"``.

Mesh files are read from the level's folder (and below) and from folders
a user allows: ``--allow-dir DIR`` or ``SANDBOX_MESH_DIRS`` (folders
separated by ``os.pathsep``).
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
from typing import Any

BYTES_PER_PARTICLE = 1024
"""Upper estimate of the field memory a particle takes with its constraints, contacts and hash cells."""


@dataclasses.dataclass(frozen=True)
class Limits:
    """What a level may ask for.

    Attributes:
        particles: rope and cloth particles in all.
        steps: frames x substeps (the largest substep count when adaptive).
        memory_gb: estimated field memory (GiB), ``BYTES_PER_PARTICLE`` per particle.
    """

    particles: int = 1_000_000
    steps: int = 100_000_000
    memory_gb: float = 8.0

    @classmethod
    def parse(cls, text: str, base: Limits | None = None) -> Limits:
        """``"particles=2e6,steps=1e9"`` over ``base`` (default: the defaults).

        Raises:
            ValueError: an unknown key or a value that is not a positive number.
        """
        values = dataclasses.asdict(base or cls())
        for item in filter(None, (t.strip() for t in text.split(","))):
            key, sep, raw = item.partition("=")
            key = key.strip()
            if not sep or key not in values:
                raise ValueError(f"limit {item!r}: give KEY=VALUE with KEY one of {', '.join(values)}")
            try:
                value = float(raw)
            except ValueError:
                value = math.nan
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"limit {item!r}: the value must be a positive number")
            values[key] = value if key == "memory_gb" else int(value)
        return cls(**values)

    @classmethod
    def from_env(cls) -> Limits:
        """The defaults, raised or lowered by ``SANDBOX_LIMITS``."""
        return cls.parse(os.environ.get("SANDBOX_LIMITS", ""))


def mesh_dirs() -> list[pathlib.Path]:
    """Folders allowed by ``SANDBOX_MESH_DIRS`` besides a level's own."""
    return [pathlib.Path(p).resolve() for p in os.environ.get("SANDBOX_MESH_DIRS", "").split(os.pathsep) if p]


def allow(env_key: str, value: str) -> None:
    """Add ``value`` to the ``os.pathsep`` list in environment variable ``env_key`` (this process and its children)."""
    old = [p for p in os.environ.get(env_key, "").split(os.pathsep) if p]
    os.environ[env_key] = os.pathsep.join([*old, value])


def _rope_particles(rope: dict) -> int:
    """Particles of one rope's data (``segments`` + 1, or its polyline over ``rod_length``); raises on bad values."""
    if rope.get("segments") is not None:
        return int(rope["segments"]) + 1
    pts = [[float(a) for a in p] for p in rope["points"]]
    length = sum(math.dist(a, b) for a, b in zip(pts, pts[1:]))
    return max(1, round(length / float(rope["rod_length"]))) + 1


def body_sizes(data: Any) -> tuple[dict[str, int], dict[str, tuple[int, int]]]:
    """Particles of each rope and (nx, nz) of each cloth that the level's data asks for; bodies whose size
    cannot be told (bad values, which the schema reports) are left out."""
    ropes: dict[str, int] = {}
    cloths: dict[str, tuple[int, int]] = {}
    scene = data.get("scene") if isinstance(data, dict) else None
    if not isinstance(scene, dict):
        return ropes, cloths
    rope_specs, cloth_specs = scene.get("ropes"), scene.get("cloths")
    for rope in rope_specs if isinstance(rope_specs, list) else []:
        try:
            ropes[str(rope["name"])] = _rope_particles(rope)
        except (TypeError, KeyError, ValueError, ZeroDivisionError, OverflowError, AttributeError):
            continue
    for cloth in cloth_specs if isinstance(cloth_specs, list) else []:
        try:
            nx, nz = (int(v) for v in cloth["resolution"])
            cloths[str(cloth["name"])] = (nx, nz)
        except (TypeError, KeyError, ValueError, OverflowError, AttributeError):
            continue
    return ropes, cloths


def particle_count(data: Any) -> int | None:
    """Rope and cloth particles the level's data asks for (None if it cannot tell)."""
    scene = data.get("scene") if isinstance(data, dict) else None
    if not isinstance(scene, dict):
        return None
    total = 0
    try:
        ropes, cloths = scene.get("ropes") or [], scene.get("cloths") or []
        if not isinstance(ropes, list) or not isinstance(cloths, list):
            return None  # the schema reports the bad value
        for rope in ropes:
            total += _rope_particles(rope)
        for cloth in cloths:
            nx, nz = (int(v) for v in cloth["resolution"])
            if not (2 <= nx <= 1024 and 2 <= nz <= 1024):
                return None  # out of the schema's range: reported there
            total += nx * nz
    except (TypeError, KeyError, ValueError, ZeroDivisionError, OverflowError, AttributeError):
        return None  # the schema reports the bad value
    return total
