"""``sandbox play LEVEL``: watch a level in an interactive Taichi GGUI window.

Controls: left drag (or Left / Right) orbits, right drag (or z / x) zooms,
space pauses, n steps one frame while paused, r rebuilds the level, Up / Down
or the HUD's "speed +" / "speed -" buttons double / halve the speed (GGUI
reports letters and named keys only, not "+" or "-"), Esc quits. Where there
is no display or no Vulkan it prints one line saying so and returns 2.
"""

from __future__ import annotations

import ctypes
import math
import os
import sys
import time
from typing import Any

import numpy as np

EXIT_NO_WINDOW = 2
SPEEDS = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)


def headless_reason() -> str | None:
    """Why no window can open here (Linux without a display or a Vulkan loader), or None.

    Checked before Taichi starts so that the answer is one line; GGUI's own
    failure is still caught when the window opens.
    """
    if not sys.platform.startswith("linux"):
        return None
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (DISPLAY and WAYLAND_DISPLAY are unset)"
    try:
        ctypes.CDLL("libvulkan.so.1")
    except OSError:
        return "no Vulkan (libvulkan.so.1 cannot be loaded), which Taichi's GGUI needs"
    return None


def _no_window(level_path: str, reason: str) -> int:
    print(
        f"sandbox play: cannot open a window: {reason}; "
        f"render it headless instead: sandbox run {level_path} --frames-every K --video",
        flush=True,
    )
    return EXIT_NO_WINDOW


def play_tier(level, asked: str | None = None) -> str:
    """The tier a level plays at: ``asked``, else the level's ``sim.tier``, else interactive."""
    return asked or level.sim.tier or "interactive"


def main(level_path: str, *, arch: str = "auto", tier: str | None = None) -> int:
    """Open the viewer on a level; returns the process exit code (0, or 2 without a window)."""
    reason = headless_reason()
    if reason is not None:
        return _no_window(level_path, reason)
    import taichi as ti

    from sandbox.api import Sandbox
    from sandbox.levels import load_level

    def build():
        level = load_level(level_path)
        return Sandbox(level, base_dir=os.path.dirname(os.path.abspath(level_path)), arch=arch,
                       tier=play_tier(level, tier))

    sim = build()
    from sandbox import runtime

    print(f"physics on {runtime.current_arch()} ({runtime.reason()}), {sim.world.tier} tier", flush=True)
    try:
        window = ti.ui.Window(f"sandbox play {os.path.basename(level_path)}", (1280, 720), vsync=True)
    except Exception as exc:  # GGUI raises RuntimeError without Vulkan, others on odd drivers
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return _no_window(level_path, f"GGUI/Vulkan is not available ({first})")
    Viewer(window, sim, build).run()
    return 0


class OrbitCamera:
    """Yaw/pitch/distance about a target point, driven by the mouse and keys."""

    def __init__(self, target: np.ndarray, distance: float, yaw: float, pitch: float, fov: float = 45.0) -> None:
        self.target = np.asarray(target, dtype=np.float64)
        self.distance, self.yaw, self.pitch, self.fov = distance, yaw, pitch, fov
        self._last: tuple[float, float] | None = None

    @classmethod
    def from_look(cls, position, look_at, fov: float) -> OrbitCamera:
        d = np.asarray(position, dtype=np.float64) - np.asarray(look_at, dtype=np.float64)
        dist = float(np.linalg.norm(d)) or 1.0
        return cls(np.asarray(look_at), dist, math.atan2(d[0], d[2]), math.asin(np.clip(d[1] / dist, -1, 1)), fov)

    def eye(self) -> np.ndarray:
        cp = math.cos(self.pitch)
        d = np.array([cp * math.sin(self.yaw), math.sin(self.pitch), cp * math.cos(self.yaw)])
        return self.target + self.distance * d

    def track(self, window, ti) -> None:
        """Update from this frame's mouse drag and held keys."""
        x, y = window.get_cursor_pos()
        lmb, rmb = window.is_pressed(ti.ui.LMB), window.is_pressed(ti.ui.RMB)
        if self._last is not None and (lmb or rmb):
            dx, dy = x - self._last[0], y - self._last[1]
            if lmb:
                self.yaw -= 4.0 * dx
                self.pitch = float(np.clip(self.pitch - 3.0 * dy, -1.45, 1.45))
            else:
                self.distance *= math.exp(-3.0 * dy)
        self._last = (x, y) if (lmb or rmb) else None
        if window.is_pressed("z"):
            self.distance *= 0.97
        if window.is_pressed("x"):
            self.distance *= 1.03
        if window.is_pressed(ti.ui.LEFT):
            self.yaw -= 0.03
        if window.is_pressed(ti.ui.RIGHT):
            self.yaw += 0.03

    def apply(self, camera) -> None:
        camera.position(*self.eye())
        camera.lookat(*self.target)
        camera.up(0.0, 1.0, 0.0)
        camera.fov(self.fov)


class GguiMeshes:
    """GGUI vertex/index fields for the items of a ``RenderScene``.

    Fields are (re)allocated only when an item's size changes: vertices
    (n,) vec3 f32 in m, indices (3m,) i32.
    """

    def __init__(self, ti) -> None:
        self.ti = ti
        self.slots: list[tuple[Any, Any, int, int]] = []

    def update(self, items) -> list:
        ti = self.ti
        out = []
        for k, item in enumerate(items):
            nv, nf = len(item.verts), len(item.faces)
            if k >= len(self.slots) or self.slots[k][2:] != (nv, nf):
                verts = ti.Vector.field(3, ti.f32, shape=nv)
                idx = ti.field(ti.i32, shape=3 * nf)
                slot = (verts, idx, nv, nf)
                if k < len(self.slots):
                    self.slots[k] = slot
                else:
                    self.slots.append(slot)
                idx.from_numpy(item.faces.reshape(-1))
            verts, idx = self.slots[k][:2]
            verts.from_numpy(item.verts)
            out.append((verts, idx, item))
        return out


def ground_mesh(ti, centre: np.ndarray, radius: float, height: float, cells: int = 24):
    """A checker-coloured square of cells x cells quads around the scene (fields for GGUI)."""
    half = 2.5 * radius
    edges = np.linspace(-half, half, cells + 1)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    x0, x1, z0, z1 = edges[i], edges[i + 1], edges[j], edges[j + 1]
    corners = np.stack(
        [np.stack([x0, z0], -1), np.stack([x0, z1], -1), np.stack([x1, z1], -1), np.stack([x1, z0], -1)], axis=2
    ).reshape(-1, 2)
    verts = np.column_stack([corners[:, 0] + centre[0], np.full(len(corners), height), corners[:, 1] + centre[2]])
    shade = np.where(((i + j) % 2).reshape(-1) == 0, 0.72, 0.55)
    colors = np.repeat(shade, 4)[:, None] * np.ones(3)
    base = 4 * np.arange(cells * cells)[:, None]
    faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1)
    fv = ti.Vector.field(3, ti.f32, shape=len(verts))
    fc = ti.Vector.field(3, ti.f32, shape=len(verts))
    fi = ti.field(ti.i32, shape=len(faces))
    fv.from_numpy(verts.astype(np.float32))
    fc.from_numpy(colors.astype(np.float32))
    fi.from_numpy(faces.astype(np.int32))
    return fv, fi, fc


class Viewer:
    """The window's loop: input, stepping at the chosen speed, drawing and the heads-up text."""

    def __init__(self, window, sim, build) -> None:
        import taichi as ti

        from sandbox.io.frames import scene_from_sim
        from shaders.camera import auto_camera

        self.ti, self.window, self.sim, self.build = ti, window, sim, build
        self.scene_from_sim = scene_from_sim
        self.canvas = window.get_canvas()
        self.scene = window.get_scene()
        self.camera = ti.ui.Camera()
        self.meshes = GguiMeshes(ti)
        scene = scene_from_sim(sim)
        w, h = window.get_window_shape()
        if sim.camera:
            c = sim.camera
            self.orbit = OrbitCamera.from_look(c["position"], c["look_at"], float(c.get("fov", 45.0)))
        else:
            cam = auto_camera(scene, w / h)
            self.orbit = OrbitCamera.from_look(cam.position, cam.look_at, cam.fov)
        centre, radius = scene.bounding_sphere()
        self.ground = None
        if sim.ground_height is not None:
            self.ground = ground_mesh(ti, centre, radius, float(sim.ground_height) - 1e-4 * radius)
        self.paused, self.speed_index, self.acc = False, SPEEDS.index(1.0), 0.0
        self.frame_ms = 16.7
        # "f" follows the knot of the level camera's ropes (or of every rope): the orbit's
        # centre glides to where they touch while the mouse keeps turning and zooming.
        follow = list((sim.camera or {}).get("follow") or [])
        self.follow_ropes = follow or list(sim.rope_names)
        self.tracker = None
        self.following = False
        if follow:
            self._toggle_follow()

    def _keys(self) -> None:
        ti = self.ti
        for e in self.window.get_events(ti.ui.PRESS):
            if e.key == ti.ui.ESCAPE:
                self.window.running = False
            elif e.key == ti.ui.SPACE:
                self.paused = not self.paused
            elif e.key == "n" and self.paused:
                self.sim.step()
            elif e.key == "r":
                self.sim.close()  # its field tree goes back before the new level takes one
                self.sim = self.build()
            elif e.key == "f":
                self._toggle_follow()
            elif e.key == ti.ui.UP:
                self._speed(+1)
            elif e.key == ti.ui.DOWN:
                self._speed(-1)

    def _toggle_follow(self) -> None:
        """Start following the knot from where the orbit looks now, or stop (the orbit stays put)."""
        from sandbox.io.frames import KnotTracker

        if self.following or not self.follow_ropes:
            self.following = False
            return
        smoothing = float((self.sim.camera or {}).get("smoothing", 0.5))
        self.tracker = KnotTracker(self.follow_ropes, look_at=self.orbit.target, smoothing=smoothing,
                                   start_time=float(self.sim.time))
        self.following = True

    def _speed(self, step: int) -> None:
        self.speed_index = int(np.clip(self.speed_index + step, 0, len(SPEEDS) - 1))

    def _hud(self) -> None:
        sim = self.sim
        timings = sim.timings() if hasattr(sim, "timings") else {}
        with self.window.get_gui().sub_window("sandbox", 0.01, 0.01, 0.32, 0.2 + 0.035 * len(timings)) as g:
            g.text(f"state: {sim.fsm_state}")
            g.text(f"frame {sim.frame}  t = {sim.time:.2f} s  speed x{SPEEDS[self.speed_index]:g}")
            g.text(f"{1000.0 / max(self.frame_ms, 1e-3):.0f} fps" + ("  PAUSED" if self.paused else ""))
            for name, ms in timings.items():
                g.text(f"  {name}: {ms:.2f} ms")
            if g.button("speed +"):
                self._speed(+1)
            if g.button("speed -"):
                self._speed(-1)
            g.text("drag/arrows: orbit, speed  z/x: zoom  space: pause  n: step  r: reset  f: follow knot"
                   + ("  FOLLOWING" if self.following else ""))

    def run(self) -> None:
        """Loop until the window closes."""
        while self.window.running:
            t0 = time.perf_counter()
            self._keys()
            if not self.paused:
                self.acc += SPEEDS[self.speed_index]
                for _ in range(int(self.acc)):
                    self.sim.step()
                self.acc -= int(self.acc)
            if self.following:
                self.orbit.target = self.tracker.update(self.sim).copy()
            self.orbit.track(self.window, self.ti)
            self.orbit.apply(self.camera)
            self.scene.set_camera(self.camera)
            self.scene.ambient_light((0.35, 0.35, 0.38))
            self.scene.point_light(pos=tuple(self.orbit.eye() + [0.0, self.orbit.distance, 0.0]), color=(0.9, 0.9, 0.9))
            if self.ground is not None:
                fv, fi, fc = self.ground
                self.scene.mesh(fv, indices=fi, per_vertex_color=fc)
            for verts, idx, item in self.meshes.update(self.scene_from_sim(self.sim).items):
                self.scene.mesh(verts, indices=idx, color=tuple(map(float, item.color)), two_sided=item.two_sided)
            self.canvas.set_background_color((0.72, 0.76, 0.82))
            self.canvas.scene(self.scene)
            self._hud()
            self.window.show()
            self.frame_ms = 0.9 * self.frame_ms + 0.1 * (time.perf_counter() - t0) * 1e3
