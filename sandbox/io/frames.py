"""Rendered outputs of a headless run: PNG frames, MP4/GIF and a contact sheet.

Rendering is optional: nothing here allocates Taichi memory until a
``FrameRecorder`` renders its first frame.
"""

from __future__ import annotations

import hashlib
import math
import os
import pathlib
import time
from typing import Any

import numpy as np

from shaders.camera import DEFAULT_VIEW, Camera, fit_sphere, from_level
from shaders.scene import MeshItem, RenderScene, crease_split, ground_cell_for, tube_mesh

ROPE_COLORS = ((0.90, 0.55, 0.15), (0.20, 0.45, 0.85), (0.25, 0.70, 0.35), (0.80, 0.25, 0.60), (0.90, 0.85, 0.30))
CLOTH_COLORS = (((0.80, 0.18, 0.20), (0.95, 0.82, 0.50)), ((0.20, 0.40, 0.75), (0.85, 0.88, 0.95)))
OBJECT_COLOR = (0.66, 0.60, 0.52)
ROPE_SIDES = 10

_crease_cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def _object_item(name: str, verts: np.ndarray, faces: np.ndarray) -> MeshItem:
    """An object's mesh with vertices unmerged along creases (cached per shape)."""
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    key = (name, len(verts), hashlib.blake2b(faces.tobytes(), digest_size=16).digest())
    if key not in _crease_cache:
        if len(_crease_cache) > 64:
            _crease_cache.clear()
        _crease_cache[key] = crease_split(verts, faces)
    source, split = _crease_cache[key]
    # two-sided in one colour: open meshes (bowls) and meshes wound inside out still look right
    verts = np.asarray(verts, dtype=np.float32)[source]
    return MeshItem(verts, split, color=OBJECT_COLOR, back_color=OBJECT_COLOR, two_sided=True)


def _color(value, default) -> tuple[float, float, float]:
    """An RGB triple in [0, 1], or ``default`` when value is missing."""
    if value is None:
        return default
    return tuple(float(c) for c in value)[:3]


def scene_from_sim(sim: Any) -> RenderScene:
    """What to draw for a ``sandbox.api.Sandbox``: ropes as tubes, cloth two-sided, objects, ground.

    Colours come from ``sim.rope_color(name)`` / ``sim.cloth_colors(name)`` where
    the sim offers them, else from a fixed palette.
    """
    items: list[MeshItem] = []
    for name in sim.object_names:
        verts, faces = sim.object_mesh(name)
        items.append(_object_item(name, verts, faces))
    for k, name in enumerate(sim.cloth_names):
        front, back = CLOTH_COLORS[k % len(CLOTH_COLORS)]
        if hasattr(sim, "cloth_colors"):
            given = sim.cloth_colors(name) or (None, None)
            front, back = _color(given[0], front), _color(given[1], back)
        items.append(
            MeshItem(sim.cloth_positions(name), sim.cloth_faces(name), color=front, back_color=back, two_sided=True)
        )
    for k, name in enumerate(sim.rope_names):
        color = ROPE_COLORS[k % len(ROPE_COLORS)]
        if hasattr(sim, "rope_color"):
            color = _color(sim.rope_color(name), color)
        verts, faces = tube_mesh(sim.rope_positions(name), sim.rope_radius(name), sides=ROPE_SIDES)
        items.append(MeshItem(verts, faces, color=color))
    return RenderScene(items=items, ground_height=sim.ground_height)


class _Framing:
    """Automatic camera that stays put while the scene stays in view.

    The bounding sphere only grows (to the smallest sphere holding the old one
    and the new one), so a video does not jitter as cloth and ropes move.
    """

    def __init__(self, aspect: float) -> None:
        self.aspect = aspect
        self.centre: np.ndarray | None = None
        self.radius = 0.0
        self.camera: Camera | None = None

    def update(self, scene: RenderScene) -> Camera:
        centre, radius = scene.bounding_sphere()
        if self.centre is None:
            self.centre, self.radius = centre, radius
        else:
            d = float(np.linalg.norm(centre - self.centre))
            if d + radius > self.radius * (1.0 + 1e-6):
                new_r = 0.5 * (d + radius + self.radius)
                if d > 1e-12:
                    self.centre = self.centre + (new_r - self.radius) / d * (centre - self.centre)
                self.radius = new_r
                self.camera = None
        if self.camera is None:
            self.camera = fit_sphere(self.centre, self.radius, self.aspect)
        return self.camera


class KnotTracker:
    """A point that follows a knot: it moves towards ``knot_centre`` of some ropes
    with time constant ``smoothing`` (s of simulated time), and stays where it is
    while nothing touches.

    Args:
        ropes: names of the ropes (or strands, or cloth lines ``F.line1``) whose knot is followed.
        look_at: (3,) m, where it is before anything touches (None: the
            followed ropes' centroid when it is first asked).
        smoothing: s; 0 jumps to the knot at once.
        start_time: s of simulated time since which it has been at ``look_at``.
    """

    def __init__(self, ropes: list[str], *, look_at=None, smoothing: float = 0.5, start_time: float = 0.0) -> None:
        if not ropes:
            raise ValueError("a knot to follow needs at least one rope")
        self.ropes = list(ropes)
        self.look = None if look_at is None else np.asarray(look_at, dtype=np.float64).copy()
        self.smoothing = float(smoothing)
        self._time = float(start_time)

    def update(self, sim: Any) -> np.ndarray:
        """The point for the simulation's current state, (3,) m (call once per drawn frame)."""
        from sandbox.geometry.knots import knot_centre
        from sandbox.model.strands import joined_at_centre

        radius = max(float(sim.strand_radius(n)) for n in self.ropes)
        ropes = [np.asarray(sim.strand_positions(n), dtype=np.float64) for n in self.ropes]
        centre = knot_centre(joined_at_centre(self.ropes, ropes), radius=radius)
        now = float(sim.time)
        if self.look is None:
            self.look = np.vstack(ropes).mean(axis=0) if centre is None else centre
        if centre is not None:
            dt = max(now - self._time, 0.0)
            blend = 1.0 if self.smoothing <= 0.0 else 1.0 - math.exp(-dt / self.smoothing)
            self.look = self.look + blend * (centre - self.look)
        self._time = now
        return self.look


class KnotFollower:
    """A camera that keeps a knot in the middle of the frame (level ``camera.follow``).

    It looks at a ``KnotTracker``'s point from a fixed direction and distance.

    Args:
        ropes, look_at, smoothing: as for ``KnotTracker``.
        direction: (3,) from the point looked at towards the eye (any length).
        distance: m from the point looked at to the eye.
        fov: vertical field of view in degrees.
    """

    def __init__(self, ropes: list[str], *, look_at, direction, distance: float, fov: float = 45.0,
                 smoothing: float = 0.5) -> None:
        d = np.asarray(direction, dtype=np.float64)
        if not np.linalg.norm(d) > 0.0 or not distance > 0.0:
            raise ValueError(f"direction must be non-zero and distance > 0 (got {direction!r}, {distance!r})")
        self.tracker = KnotTracker(ropes, look_at=look_at, smoothing=smoothing)
        self.offset = d / np.linalg.norm(d) * float(distance)
        self.fov = float(fov)

    @property
    def ropes(self) -> list[str]:
        return self.tracker.ropes

    @property
    def look(self) -> np.ndarray | None:
        return self.tracker.look

    @property
    def smoothing(self) -> float:
        return self.tracker.smoothing

    @classmethod
    def from_camera(cls, camera: dict | None, ropes: list[str] | None = None, *,
                    distance: float | None = None) -> KnotFollower | None:
        """The follower a level's camera asks for (or that ``ropes`` asks for over it); None if none.

        Without a level camera it looks from ``DEFAULT_VIEW``, 0.4 m away (or
        ``distance``), at the ropes' centroid until they touch.
        """
        camera = camera or {}
        ropes = ropes or camera.get("follow") or []
        if not ropes:
            return None
        if "position" in camera:
            look = np.asarray(camera["look_at"], dtype=np.float64)
            direction = np.asarray(camera["position"], dtype=np.float64) - look
            default = float(np.linalg.norm(direction))
        else:
            look, direction, default = None, np.asarray(DEFAULT_VIEW, dtype=np.float64), 0.4
        return cls(ropes, look_at=look, direction=direction,
                   distance=float(distance or camera.get("distance") or default),
                   fov=float(camera.get("fov", 45.0)), smoothing=float(camera.get("smoothing", 0.5)))

    def update(self, sim: Any) -> Camera:
        """The camera for the simulation's current state (call once per rendered frame)."""
        look = self.tracker.update(sim)
        eye = look + self.offset
        near = max(1e-4, 1e-3 * float(np.linalg.norm(self.offset)))
        return Camera(tuple(map(float, eye)), tuple(map(float, look)), fov=self.fov, near=near)


def _downscale(img: np.ndarray, factor: int) -> np.ndarray:
    """Box-filter an (H, W, 3) uint8 image by an integer factor."""
    if factor <= 1:
        return img
    h, w = (img.shape[0] // factor) * factor, (img.shape[1] // factor) * factor
    blocks = img[:h, :w].reshape(h // factor, factor, w // factor, factor, 3).astype(np.float32)
    return (blocks.mean(axis=(1, 3)) + 0.5).astype(np.uint8)


class FrameRecorder:
    """Renders a running simulation to PNG frames, an optional MP4/GIF and a contact sheet.

    Args:
        out_dir: output folder (``frames/``, ``anim.mp4``, ``anim.gif``, ``sheet.png``).
        every: write every k-th frame (frame_index % every == 0).
        video: append written frames to ``anim.mp4`` (H.264 through imageio's ffmpeg).
        gif: append written frames, at half size, to ``anim.gif``.
        width, height: image size in pixels.
        fps: playback rate of the video and GIF.
        follow: a camera that follows a knot, used instead of the level's
            camera (``KnotFollower.from_camera``).
    """

    def __init__(
        self,
        out_dir: pathlib.Path,
        *,
        every: int = 1,
        video: bool = False,
        gif: bool = False,
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        follow: KnotFollower | None = None,
    ) -> None:
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        self.out_dir = pathlib.Path(out_dir)
        self.frames_dir = self.out_dir / "frames"
        self.every, self.video, self.gif = int(every), bool(video), bool(gif)
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self._renderer = None
        self._framing = _Framing(self.width / self.height)
        self._mp4 = None
        self._gif = None
        self._render_ms: list[float] = []
        self._tiles: list[tuple[str, np.ndarray]] = []
        self._last: tuple[int, str, np.ndarray] | None = None
        self._ground_cell: float | None = None
        self._follow = follow

    # ------------------------------------------------------------------ rendering
    def render(self, sim: Any) -> np.ndarray:
        """Render the simulation's current state (timed); returns (H, W, 3) uint8."""
        t0 = time.perf_counter()
        if self._renderer is None:
            from shaders.renderer import Renderer

            self._renderer = Renderer(self.width, self.height)
        scene = scene_from_sim(sim)
        if self._ground_cell is None:  # fixed from the first frame: the checker must not jump in a video
            self._ground_cell = ground_cell_for(scene.bounding_sphere()[1])
        scene.ground_cell = self._ground_cell
        if self._follow is not None:
            camera = self._follow.update(sim)
        else:
            camera = from_level(sim.camera) or self._framing.update(scene)
        img = self._renderer.render(scene, camera)
        self._render_ms.append((time.perf_counter() - t0) * 1e3)
        return img

    def on_frame(self, sim: Any, frame_index: int, fsm_state: str, state_changed: bool) -> None:
        """Called by the runner after each simulated frame.

        Renders when the frame is due (every ``every`` frames) or the FSM state
        changed; due frames go to ``frames/NNNNN.png`` and the video/GIF, a state
        change (and the first frame, showing the initial state) keeps a tile for
        the contact sheet.
        """
        if self._follow is not None:
            # the follow camera glides every simulated frame, so where it looks does not depend on
            # how often frames are written (a second update in the same frame changes nothing)
            self._follow.tracker.update(sim)
        due = frame_index % self.every == 0
        state_changed = state_changed or self._last is None
        if not (due or state_changed):
            return
        img = self.render(sim)
        self._last = (frame_index, fsm_state, img)
        if state_changed:
            self._tiles.append((f"{fsm_state}  (frame {frame_index})", _downscale(img, 2)))
        if due:
            self._write(frame_index, img)

    def _write(self, frame_index: int, img: np.ndarray) -> None:
        import imageio.v2 as imageio

        self.frames_dir.mkdir(parents=True, exist_ok=True)
        path = self.frames_dir / f"{frame_index:05d}.png"
        tmp = path.with_name(path.stem + ".tmp.png")
        imageio.imwrite(tmp, img)  # a frame on disk is whole: written aside, then renamed
        os.replace(tmp, path)
        if self.video:
            if self._mp4 is None:
                self._mp4 = imageio.get_writer(
                    self.out_dir / "anim.mp4", fps=self.fps, codec="libx264", quality=7,
                    macro_block_size=2, ffmpeg_log_level="error",
                )  # fmt: skip
            self._mp4.append_data(img[: img.shape[0] // 2 * 2, : img.shape[1] // 2 * 2])
        if self.gif:
            if self._gif is None:
                self._gif = imageio.get_writer(self.out_dir / "anim.gif", mode="I", duration=1000.0 / self.fps, loop=0)
            self._gif.append_data(_downscale(img, 2))

    # ------------------------------------------------------------------ closing
    def close(self, sim: Any) -> dict[str, Any]:
        """Finish the video/GIF, write ``sheet.png`` (the state tiles and the last frame) and return render timings.

        Returns:
            ``render_ms_p50`` and ``render_ms_p95`` over the rendered frames after
            the first (which pays the kernels' compilation, reported apart as
            ``render_ms_first``), and ``frames_rendered``.
        """
        if self._last is None or self._last[0] != sim.frame:
            self._last = (sim.frame, sim.fsm_state, self.render(sim))
        frame, state, img = self._last
        tiles = self._tiles + [(f"last: {state}  (frame {frame})", _downscale(img, 2))]
        self.out_dir.mkdir(parents=True, exist_ok=True)
        write_sheet(self.out_dir / "sheet.png", tiles)
        for writer in (self._mp4, self._gif):
            if writer is not None:
                writer.close()
        self._mp4 = self._gif = None
        ms = np.asarray(self._render_ms[1:] if len(self._render_ms) > 1 else self._render_ms)
        return {
            "render_ms_p50": float(np.percentile(ms, 50)),
            "render_ms_p95": float(np.percentile(ms, 95)),
            "render_ms_first": float(self._render_ms[0]),
            "frames_rendered": len(self._render_ms),
        }


def write_sheet(path: pathlib.Path, tiles: list[tuple[str, np.ndarray]], *, columns: int = 4) -> None:
    """Write a contact sheet: the tiles in a grid, each labelled in its top-left corner."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    th, tw = tiles[0][1].shape[:2]
    cols = min(columns, len(tiles))
    rows = math.ceil(len(tiles) / cols)
    dpi = 100.0
    fig = Figure(figsize=(cols * tw / dpi, rows * th / dpi), dpi=dpi, facecolor="black")
    FigureCanvasAgg(fig)
    for k, (label, tile) in enumerate(tiles):
        r, c = divmod(k, cols)
        ax = fig.add_axes((c / cols, 1.0 - (r + 1) / rows, 1.0 / cols, 1.0 / rows))
        ax.imshow(tile, interpolation="nearest")
        ax.set_axis_off()
        ax.text(
            0.02, 0.97, label, transform=ax.transAxes, va="top", ha="left", fontsize=9, color="white",
            bbox={"facecolor": "black", "alpha": 0.6, "pad": 2, "edgecolor": "none"},
        )  # fmt: skip
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=dpi, facecolor="black")
    os.replace(tmp, path)
