"""Look-at pinhole camera, automatic framing and the key light's frame (NumPy)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shaders.scene import RenderScene

#: Default viewing direction of ``auto_camera`` (from the scene towards the camera).
DEFAULT_VIEW = (0.55, 0.6, 1.0)


@dataclass
class Camera:
    """A perspective look-at camera.

    Attributes:
        position: (3,) eye in m.
        look_at: (3,) point the camera looks at, in m.
        fov: vertical field of view in degrees.
        up: (3,) world up used to roll the camera.
        near: near clipping distance in m; triangles with a vertex closer are skipped.
    """

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    fov: float = 45.0
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    near: float = 1e-3

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Eye, right, up and forward unit vectors (each (3,) float64)."""
        eye = np.asarray(self.position, dtype=np.float64)
        fwd = np.asarray(self.look_at, dtype=np.float64) - eye
        norm = np.linalg.norm(fwd)
        if norm < 1e-12:
            raise ValueError("camera position and look_at coincide")
        fwd /= norm
        up = np.asarray(self.up, dtype=np.float64)
        right = np.cross(fwd, up)
        if np.linalg.norm(right) < 1e-6:  # looking along up: roll about z instead
            right = np.cross(fwd, [0.0, 0.0, -1.0 if fwd[1] > 0 else 1.0])
        right /= np.linalg.norm(right)
        return eye, right, np.cross(right, fwd), fwd

    def focal(self, height: int) -> float:
        """Focal length in pixels for an image ``height`` pixels tall."""
        return 0.5 * height / math.tan(math.radians(self.fov) * 0.5)

    def project(self, points: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (n, 2) (x right, y down, pixel centres at +0.5) and view depth (n,) in m."""
        eye, right, up, fwd = self.basis()
        d = np.asarray(points, dtype=np.float64).reshape(-1, 3) - eye
        z = d @ fwd
        f = self.focal(height)
        with np.errstate(divide="ignore", invalid="ignore"):
            px = 0.5 * width + f * (d @ right) / z
            py = 0.5 * height - f * (d @ up) / z
        return np.stack([px, py], axis=1), z


def from_level(camera: dict | None) -> Camera | None:
    """A camera from a level's ``camera`` mapping (``position``, ``look_at``, ``fov``)."""
    if not camera:
        return None
    return Camera(
        position=tuple(float(x) for x in camera["position"]),
        look_at=tuple(float(x) for x in camera["look_at"]),
        fov=float(camera.get("fov", 45.0)),
    )


def auto_camera(
    scene: RenderScene,
    aspect: float,
    *,
    fov: float = 45.0,
    direction: tuple[float, float, float] = DEFAULT_VIEW,
    margin: float = 1.08,
) -> Camera:
    """Frame the scene: the bounding sphere of all its vertices fits in the view frustum.

    Args:
        scene: what to frame (all mesh vertices count; the ground does not).
        aspect: image width / height.
        fov: vertical field of view in degrees.
        direction: from the scene centre towards the eye.
        margin: extra distance factor (> 1 leaves a border).
    """
    centre, radius = scene.bounding_sphere()
    return fit_sphere(centre, radius, aspect, fov=fov, direction=direction, margin=margin)


def fit_sphere(
    centre: np.ndarray,
    radius: float,
    aspect: float,
    *,
    fov: float = 45.0,
    direction: tuple[float, float, float] = DEFAULT_VIEW,
    margin: float = 1.08,
) -> Camera:
    """A camera looking at ``centre`` from ``direction``, just far enough to see the whole sphere.

    The sphere is tangent to the narrower pair of frustum planes (times ``margin``).
    """
    half_v = math.radians(fov) * 0.5
    half_h = math.atan(math.tan(half_v) * aspect)
    dist = margin * radius / math.sin(min(half_v, half_h))
    d = np.asarray(direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    eye = np.asarray(centre, dtype=np.float64) + dist * d
    return Camera(tuple(map(float, eye)), tuple(map(float, centre)), fov=fov, near=max(1e-4, 1e-3 * radius))


def light_frame(
    fwd: np.ndarray, right: np.ndarray, light_dir: tuple[float, float, float] | None
) -> np.ndarray:
    """Unit direction (3,) towards the key light.

    Args:
        fwd, right: the camera's forward and right unit vectors.
        light_dir: a fixed direction, or None to place the light above, behind
            and to the left of the camera so that shadows fall visibly onto the
            ground in front of the viewer.
    """
    if light_dir is not None:
        d = np.asarray(light_dir, dtype=np.float64)
        return d / np.linalg.norm(d)
    flat = np.array([fwd[0], 0.0, fwd[2]])
    flat = flat / np.linalg.norm(flat) if np.linalg.norm(flat) > 1e-6 else np.array([0.0, 0.0, -1.0])
    side = np.array([right[0], 0.0, right[2]])
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array([1.0, 0.0, 0.0])
    d = -0.75 * side - 0.25 * flat + np.array([0.0, 0.85, 0.0])
    return d / np.linalg.norm(d)
