"""Embedding API: a host game loop drives a level through :class:`Sandbox`.

Example::

    sim = Sandbox.from_level("levels/rope_hang.yaml", arch="cpu")
    while running:
        sim.advance(frame_seconds)          # or sim.step() for exactly one frame
        draw(sim.rope_positions("left"))
"""

from __future__ import annotations

import math
import numbers

import pathlib
import time
from typing import Callable

import numpy as np

from sandbox.world import World


class Sandbox:
    """A level running in a host program. The host owns the loop.

    Args:
        level: a validated ``Level``.
        base_dir: folder that relative asset paths are resolved against.
        arch: Taichi backend (``auto|cpu|cuda|vulkan|metal``); None = the level's.
        tier: ``accurate`` or ``interactive`` (``sim.tier``); None = the level's, accurate if it states none.
        clock: monotonic time source in seconds for :meth:`advance` without an
            argument (injectable for tests and replays).
        max_frames_per_advance: cap on frames run by one ``advance`` call, so a
            slow host does not spiral (the rest of the debt is dropped).
    """

    def __init__(self, level, *, base_dir=None, arch: str | None = None, tier: str | None = None,
                 clock: Callable[[], float] = time.perf_counter, max_frames_per_advance: int = 4) -> None:
        import sandbox.maneuvers  # noqa: F401  (registers the built-in maneuvers)

        self.world = World(level, base_dir=base_dir, arch=arch, tier=tier)
        self.world.attach_fsm()
        self.level = level
        self._clock = clock
        self._last_clock: float | None = None
        self._accum = 0.0
        self.max_frames_per_advance = int(max_frames_per_advance)
        self.dropped_time = 0.0

    @classmethod
    def from_level(cls, path: str | pathlib.Path, *, arch: str | None = None, overrides: dict | None = None,
                   **kwargs) -> "Sandbox":
        """Load, validate and build a level file (raises ``LevelError`` if invalid)."""
        from sandbox.levels import load_level

        path = pathlib.Path(path)
        level = load_level(path, overrides)
        return cls(level, base_dir=path.parent, arch=arch, **kwargs)

    def close(self) -> None:
        """Free the level's fields (Taichi holds at most 512 field trees per process; each level takes one).

        The kernels compiled for it stay until ``sandbox.runtime.release()``, which frees them once every
        level is closed.
        """
        self.world.close()

    def __enter__(self) -> "Sandbox":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ stepping
    def step(self) -> dict:
        """Advance exactly one frame (1 / fps seconds); returns its metrics row."""
        return self.world.step()

    def advance(self, wall_dt: float | None = None) -> int:
        """Accumulate wall time and run as many whole frames as it covers.

        Args:
            wall_dt: seconds since the previous call; None reads the clock.

        Returns:
            The number of frames run (0 if less than a frame has accumulated).

        Raises:
            ValueError: ``wall_dt`` (or the clock's step) is negative, NaN or
                infinite; the accumulator is left as it was.
        """
        if wall_dt is None:
            now = self._clock()
            wall_dt = 0.0 if self._last_clock is None else now - self._last_clock
            if not math.isfinite(now):
                raise ValueError(f"the clock read {now!r}; it must give finite seconds (nothing was run)")
            self._last_clock = now
        if isinstance(wall_dt, bool) or not isinstance(wall_dt, numbers.Real) or not math.isfinite(wall_dt) \
                or wall_dt < 0:
            raise ValueError(f"wall_dt must be a finite number of seconds >= 0, got {wall_dt!r} (nothing was run; "
                             "the next valid call goes on)")
        self._accum += wall_dt
        n = 0
        while self._accum >= self.world.dt and n < self.max_frames_per_advance:
            self.step()
            self._accum -= self.world.dt
            n += 1
        if self._accum >= self.world.dt:
            self.dropped_time += self._accum - self._accum % self.world.dt
            self._accum %= self.world.dt
        return n

    @property
    def alpha(self) -> float:
        """Fraction of a frame accumulated but not yet simulated (for interpolation)."""
        return self._accum / self.world.dt

    # ----------------------------------------------------------- read-back
    @property
    def frame(self) -> int:
        return self.world.frame

    @property
    def time(self) -> float:
        """Simulated time (s)."""
        return self.world.time

    @property
    def rope_names(self) -> list[str]:
        return list(self.world.ropes)

    @property
    def cloth_names(self) -> list[str]:
        return list(self.world.cloths)

    @property
    def object_names(self) -> list[str]:
        return list(self.world.object_specs)

    def rope_positions(self, name: str) -> np.ndarray:
        """(n, 3) float32 particle positions of a rope (m), start to end."""
        return self.world.rope_positions(name)

    def rope_radius(self, name: str) -> float:
        return self.world.rope(name).radius

    def strand_positions(self, name: str) -> np.ndarray:
        """(k, 3) float32 positions along a rope, a strand ``R[i0:i1]`` of one, or a cloth line ``F.line1`` /
        ``F.P..Q`` (m), from its start (a control line's start is the cloth's centre)."""
        return self.world.positions()[self.world.strand(name).idx]

    def strand_radius(self, name: str) -> float:
        """A rope's radius, or half a cloth line's cloth thickness (m)."""
        return float(self.world.strand(name).radius)

    def rope_color(self, name: str) -> tuple[float, float, float]:
        return self.world.rope(name).color

    def cloth_positions(self, name: str) -> np.ndarray:
        """(nx * nz, 3) float32 positions of a cloth (m); particle (i, j) at j * nx + i."""
        return self.world.cloth_positions(name)

    def cloth_faces(self, name: str) -> np.ndarray:
        """(m, 3) int32 triangles of a cloth, indices into ``cloth_positions``."""
        return self.world.cloth(name).faces

    def cloth_shape(self, name: str) -> tuple[int, int]:
        c = self.world.cloth(name)
        return c.nx, c.nz

    def cloth_colors(self, name: str) -> tuple[tuple, tuple]:
        c = self.world.cloth(name)
        return c.color, c.back_color

    def object_mesh(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(verts (n, 3) float32 in world space, faces (m, 3) int32) of an object."""
        return self.world.objects.world_mesh(self.world.object_index(name))

    @property
    def positions_field(self):
        """The Taichi field of all particle positions (n,) vec3, zero-copy.

        Ropes and cloths occupy ranges given by :meth:`body_range`.
        """
        return self.world.state.x

    def body_range(self, name: str) -> tuple[int, int]:
        """[start, end) of a rope or cloth in ``positions_field``."""
        b = self.world.ropes.get(name) or self.world.cloths.get(name)
        if b is None:
            raise KeyError(f"no rope or cloth named {name!r}")
        return b.start, b.end

    @property
    def camera(self) -> dict | None:
        cam = self.level.scene.camera
        if cam is None:
            return None
        return {"position": tuple(cam.position), "look_at": tuple(cam.look_at), "fov": float(cam.fov),
                "follow": list(cam.follow), "distance": cam.distance, "smoothing": float(cam.smoothing)}

    @property
    def ground_height(self) -> float | None:
        return self.world.ground_height

    @property
    def fsm_state(self) -> str:
        return self.world.fsm.state if self.world.fsm is not None else ""

    @property
    def finished(self) -> bool:
        return self.world.fsm is not None and self.world.fsm.finished

    @property
    def events(self) -> list[dict]:
        """FSM events so far: enter/exit/done/failed/timeout with their tick."""
        return list(self.world.fsm.events) if self.world.fsm is not None else []

    def timings(self) -> dict[str, float]:
        """Milliseconds per system of the last frame."""
        return dict(self.world.systems_ms)
