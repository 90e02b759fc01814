"""Named sites of an object: surface points that levels refer to by name.

All sites are in the object's local frame (meters, y up, origin at the base
centre). With ``c`` the centre of the mesh bounds and ``lo``/``hi`` its
corners, each surface site is the first hit of a ray shot from outside the
bounds towards ``c`` along one axis; where that ray misses the surface (the
hole of a torus), it is the vertex farthest out along the ray's side that is
closest to the ray's line (ties go to the larger z, then the larger x).

- ``top``: ray straight down the vertical line through ``c`` (the highest
  surface point above the centre), entering at ``(c.x, hi.y, c.z)``.
- ``bottom``: ray straight up the same line, entering at ``(c.x, lo.y, c.z)``.
- ``front``: ray along -z at the centre's height, from ``(c.x, c.y, hi.z)``.
- ``back``: ray along +z, from ``(c.x, c.y, lo.z)``.
- ``left``: ray along +x, from ``(lo.x, c.y, c.z)`` (the -x side).
- ``right``: ray along -x, from ``(hi.x, c.y, c.z)`` (the +x side).
- ``center``: ``c`` itself, the bounds centre (not on the surface).
"""

from __future__ import annotations

import numpy as np
import trimesh

SITE_NAMES = ("top", "bottom", "front", "back", "left", "right", "center")

# site -> (axis index, sign of the outward side)
_AXES = {
    "top": (1, 1.0),
    "bottom": (1, -1.0),
    "front": (2, 1.0),
    "back": (2, -1.0),
    "left": (0, -1.0),
    "right": (0, 1.0),
}


def _first_hit(mesh: trimesh.Trimesh, origin: np.ndarray, direction: np.ndarray) -> np.ndarray | None:
    """Nearest ray-triangle intersection (Moller-Trumbore), or None on a miss."""
    tri = mesh.triangles
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    pvec = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, pvec)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origin - tri[:, 0]
    u = np.einsum("ij,ij->i", tvec, pvec) * inv
    qvec = np.cross(tvec, e1)
    v = (qvec @ direction) * inv
    t = np.einsum("ij,ij->i", e2, qvec) * inv
    eps = 1e-9
    hit = ok & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t >= 0)
    if not hit.any():
        return None
    return origin + t[hit].min() * direction


def _extreme_vertex(mesh: trimesh.Trimesh, axis: int, sign: float, line_point: np.ndarray) -> np.ndarray:
    """Outermost vertex along ``sign * axis`` nearest to the line through ``line_point``."""
    v = np.asarray(mesh.vertices, float)
    scale = max(float(np.ptp(v, axis=0).max()), 1e-12)
    along = sign * v[:, axis]
    candidates = v[along >= along.max() - 1e-6 * scale]
    off = candidates - line_point
    off[:, axis] = 0.0
    dist = np.round(np.linalg.norm(off, axis=1) / scale, 6)
    best = np.lexsort((-candidates[:, 0], -candidates[:, 2], dist))[0]
    return candidates[best].copy()


def named_sites(mesh: trimesh.Trimesh) -> dict[str, np.ndarray]:
    """Named sites of a mesh in its local frame (see the module docstring).

    Args:
        mesh: the object's mesh, local frame.

    Returns:
        ``{name: point (3,) float64 in m}`` for every name in ``SITE_NAMES``.
    """
    lo, hi = np.asarray(mesh.bounds, float)
    c = 0.5 * (lo + hi)
    sites: dict[str, np.ndarray] = {}
    for name, (axis, sign) in _AXES.items():
        entry = c.copy()
        entry[axis] = hi[axis] if sign > 0 else lo[axis]
        direction = np.zeros(3)
        direction[axis] = -sign
        margin = 1e-3 * max(float(np.max(hi - lo)), 1e-9)
        hit = _first_hit(mesh, entry - margin * direction, direction)
        sites[name] = hit if hit is not None else _extreme_vertex(mesh, axis, sign, c)
    sites["center"] = c
    return sites
