"""Rigid poses: Euler angles, keyframe interpolation."""

import numpy as np


def euler_matrix(degrees) -> np.ndarray:
    """Rotation matrix R = Rz Ry Rx from XYZ Euler angles in degrees."""
    ax, ay, az = np.radians(np.asarray(degrees, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def keyframe_pose(motion, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose (position, rotation matrix) of a ``Motion`` script at time t (s).

    Positions and Euler angles are interpolated linearly between keyframes;
    before the first / after the last keyframe the pose is held (or the
    script repeats when ``loop`` is set).
    """
    keys = motion.keyframes
    t0, t1 = keys[0].time, keys[-1].time
    if motion.loop and t1 > t0:
        t = t0 + (t - t0) % (t1 - t0)
    times = np.array([k.time for k in keys])
    pos = np.array([k.position for k in keys], dtype=np.float64)
    rot = np.array([k.rotation for k in keys], dtype=np.float64)
    p = np.array([np.interp(t, times, pos[:, a]) for a in range(3)])
    r = np.array([np.interp(t, times, rot[:, a]) for a in range(3)])
    return p, euler_matrix(r)
