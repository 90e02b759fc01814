"""Procedural object meshes (trimesh) for the scenes.

Every builder returns a mesh in its local frame: y is up and the origin is at
the centre of the base, so that the object rests on y = 0 at the identity
pose. Lengths are in meters. Closed shapes are watertight with outward
normals; shapes made of several parts (basket, jeep) are unions of closed,
overlapping parts (each part watertight, the whole not self-intersection
free), which the collision grid handles as the union of their volumes.
"""

from __future__ import annotations

import math
import numbers
import pathlib
from typing import Any, Callable

import numpy as np
import trimesh

# Parameter names and defaults of each shape (meters unless stated).
# ``None`` marks a parameter without a usable default (it must be given).
SHAPES: dict[str, dict[str, Any]] = {
    "box": {"size": [0.3, 0.3, 0.3]},
    "sphere": {"radius": 0.15},
    "cylinder": {"radius": 0.1, "height": 0.3},
    "capsule": {"radius": 0.1, "height": 0.4},
    "torus": {"major_radius": 0.15, "minor_radius": 0.05},
    "wine_bottle": {
        "height": 0.32,
        "radius": 0.04,
        "neck_radius": 0.014,
        "body_fraction": 0.55,  # share of the height that is the straight body
        "neck_fraction": 0.3,  # share of the height that is the neck (lip included)
        "lip_scale": 1.2,  # lip radius / neck radius
        "sections": 48,  # segments around the axis
    },
    "basket": {
        "radius": 0.15,
        "height": 0.12,
        "wall": 0.012,
        "handle_radius": 0.008,
        "handle_height": 0.15,
        "base_scale": 0.75,  # bottom outer radius / rim radius
        "sections": 48,
    },
    "jeep": {"length": 0.4, "width": 0.2, "height": 0.18},
    "statue": {"height": 0.4, "seed": 0},
    "mesh": {"path": None, "scale": 1.0},
}

LENGTH_PARAMS: dict[str, tuple[str, ...]] = {
    "box": ("size",),
    "sphere": ("radius",),
    "cylinder": ("radius", "height"),
    "capsule": ("radius", "height"),
    "torus": ("major_radius", "minor_radius"),
    "wine_bottle": ("height", "radius", "neck_radius"),
    "basket": ("radius", "height", "wall", "handle_radius", "handle_height"),
    "jeep": ("length", "width", "height"),
    "statue": ("height",),
    "mesh": ("scale",),
}
"""Shape parameters that are lengths (m; a mesh's ``scale`` multiplies its file's lengths)."""

ANALYTIC_SHAPES = ("box", "sphere", "cylinder", "capsule", "torus")

_Y_UP = trimesh.transformations.rotation_matrix(-math.pi / 2.0, [1.0, 0.0, 0.0])
"""Homogeneous 4x4 rotation taking the z axis onto the y axis."""


def is_analytic(shape: str) -> bool:
    """True for shapes whose signed distance has a closed form (primitives)."""
    return shape in ANALYTIC_SHAPES


def resolve_params(shape: str, params: dict | None) -> dict[str, Any]:
    """Checks ``params`` of ``shape`` and fills the defaults.

    Raises:
        ValueError: unknown shape, unknown parameter name or a bad value; the
            message names the allowed shapes or parameter names.
    """
    if shape not in SHAPES:
        raise ValueError(f"unknown shape {shape!r}; allowed shapes: {', '.join(SHAPES)}")
    params = dict(params or {})
    allowed = SHAPES[shape]
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise ValueError(
            f"shape {shape!r}: unknown parameter(s) {', '.join(unknown)}; "
            f"allowed: {', '.join(allowed)}"
        )
    out = {name: params.get(name, default) for name, default in allowed.items()}
    for name, value in out.items():
        if value is None:
            raise ValueError(f"shape {shape!r}: parameter {name!r} is required")
    return out


def _positive(shape: str, p: dict, *names: str) -> None:
    for name in names:
        v = p[name]
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v <= 0:
            raise ValueError(f"shape {shape!r}: {name} must be a positive number (got {v!r})")


def _fraction(shape: str, p: dict, *names: str) -> None:
    for name in names:
        v = p[name]
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not 0.0 < v < 1.0:
            raise ValueError(f"shape {shape!r}: {name} must be in (0, 1) (got {v!r})")


def _integer(shape: str, p: dict, name: str, lo: int) -> None:
    v = p[name]
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < lo:
        raise ValueError(f"shape {shape!r}: {name} must be an integer >= {lo} (got {v!r})")


def _require(shape: str, ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(f"shape {shape!r}: {message}")


def _rest_on_ground(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Moves the mesh so that its bounds centre is on the y axis and min y = 0."""
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2.0, -lo[1], -(lo[2] + hi[2]) / 2.0])
    return mesh


def _outward(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Flips the winding of a closed mesh whose volume came out negative."""
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
    return mesh


def _revolve_y(profile: np.ndarray, sections: int) -> trimesh.Trimesh:
    """Revolves a (radius, y) profile, first and last points on the axis, about y."""
    mesh = trimesh.creation.revolve(np.asarray(profile, float), sections=sections)
    mesh.apply_transform(_Y_UP)
    return _outward(mesh)


def _chaikin(points: np.ndarray, iterations: int) -> np.ndarray:
    """Corner-cutting smoothing of an open polyline; the end points stay put."""
    pts = np.asarray(points, float)
    for _ in range(iterations):
        a, b = pts[:-1], pts[1:]
        q = 0.75 * a + 0.25 * b
        r = 0.25 * a + 0.75 * b
        mid = np.empty((2 * len(a), pts.shape[1]))
        mid[0::2], mid[1::2] = q, r
        pts = np.vstack([pts[:1], mid[1:-1], pts[-1:]])
    return pts


# --- primitives ---------------------------------------------------------------


def _box(p: dict) -> trimesh.Trimesh:
    size = p["size"]
    ok = (
        isinstance(size, (list, tuple, np.ndarray))
        and len(size) == 3
        and all(isinstance(s, numbers.Real) and not isinstance(s, bool) and s > 0 for s in size)
    )
    _require("box", ok, f"size must be three positive numbers [sx, sy, sz] (got {size!r})")
    mesh = trimesh.creation.box(extents=[float(s) for s in size])
    mesh.apply_translation([0.0, float(size[1]) / 2.0, 0.0])
    return mesh


def _sphere(p: dict) -> trimesh.Trimesh:
    _positive("sphere", p, "radius")
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=p["radius"])
    mesh.apply_translation([0.0, p["radius"], 0.0])
    return mesh


def _cylinder(p: dict) -> trimesh.Trimesh:
    _positive("cylinder", p, "radius", "height")
    mesh = trimesh.creation.cylinder(radius=p["radius"], height=p["height"], sections=64)
    mesh.apply_transform(_Y_UP)
    mesh.apply_translation([0.0, p["height"] / 2.0, 0.0])
    return mesh


def _capsule(p: dict) -> trimesh.Trimesh:
    _positive("capsule", p, "radius", "height")
    r, h = p["radius"], p["height"]
    _require("capsule", h >= 2 * r, f"height ({h}) must be at least 2 * radius ({2 * r})")
    mesh = trimesh.creation.capsule(height=h - 2 * r, radius=r, count=[48, 48])
    mesh.apply_transform(_Y_UP)
    mesh.apply_translation([0.0, h / 2.0, 0.0])
    return mesh


def _torus(p: dict) -> trimesh.Trimesh:
    _positive("torus", p, "major_radius", "minor_radius")
    big, small = p["major_radius"], p["minor_radius"]
    _require("torus", small < big, f"minor_radius ({small}) must be below major_radius ({big})")
    mesh = trimesh.creation.torus(big, small, major_sections=64, minor_sections=32)
    mesh.apply_transform(_Y_UP)
    mesh.apply_translation([0.0, small, 0.0])
    return mesh


# --- procedural models ----------------------------------------------------------


def _wine_bottle(p: dict) -> trimesh.Trimesh:
    s = "wine_bottle"
    _positive(s, p, "height", "radius", "neck_radius", "lip_scale")
    _fraction(s, p, "body_fraction", "neck_fraction")
    _integer(s, p, "sections", 8)
    h, r, rn = p["height"], p["radius"], p["neck_radius"]
    body, neck = p["body_fraction"] * h, p["neck_fraction"] * h
    rl = rn * p["lip_scale"]
    _require(s, rn < r, f"neck_radius ({rn}) must be below radius ({r})")
    _require(s, rl < r, f"lip radius (neck_radius * lip_scale = {rl}) must be below radius ({r})")
    _require(s, p["body_fraction"] + p["neck_fraction"] < 0.95,
             "body_fraction + neck_fraction must stay below 0.95 (room for the shoulder)")
    edge = min(0.15 * r, 0.05 * h)  # rounded base edge
    lip = min(0.25 * neck, 0.03 * h)
    shoulder_top = h - neck
    t = np.linspace(0.0, math.pi, 24)
    shoulder = np.stack([
        rn + (r - rn) * 0.5 * (1 + np.cos(t)),
        body + (shoulder_top - body) * t / math.pi,
    ], axis=1)
    corner = np.linspace(0.0, math.pi / 2, 8)
    base = np.stack([r - edge + edge * np.sin(corner), edge - edge * np.cos(corner)], axis=1)
    profile = np.vstack([
        [[0.0, 0.0]],
        base,
        [[r, body]],
        shoulder[1:],
        [[rn, h - lip], [rl, h - lip], [rl, h], [0.0, h]],
    ])
    return _revolve_y(profile, p["sections"])


def _tube(centerline: np.ndarray, radius: float, sides: int = 16) -> trimesh.Trimesh:
    """Closed tube (capped ends) around a centreline lying in the z = 0 plane."""
    c = np.asarray(centerline, float)
    tangent = np.gradient(c, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    binormal = np.array([0.0, 0.0, 1.0])
    normal = np.cross(tangent, binormal)
    a = np.linspace(0.0, 2 * math.pi, sides, endpoint=False)
    ring = np.cos(a)[None, :, None] * normal[:, None, :] + np.sin(a)[None, :, None] * binormal
    verts = (c[:, None, :] + radius * ring).reshape(-1, 3)
    n = len(c)
    faces = []
    for i in range(n - 1):
        for j in range(sides):
            a0, a1 = i * sides + j, i * sides + (j + 1) % sides
            b0, b1 = a0 + sides, a1 + sides
            faces += [[a0, a1, b1], [a0, b1, b0]]
    start, end = len(verts), len(verts) + 1
    verts = np.vstack([verts, c[0], c[-1]])
    for j in range(sides):
        faces.append([start, (j + 1) % sides, j])
        faces.append([end, (n - 1) * sides + j, (n - 1) * sides + (j + 1) % sides])
    return _outward(trimesh.Trimesh(verts, np.array(faces), process=False))


def _basket(p: dict) -> trimesh.Trimesh:
    s = "basket"
    _positive(s, p, "radius", "height", "wall", "handle_radius", "handle_height")
    _fraction(s, p, "base_scale")
    _integer(s, p, "sections", 8)
    r, h, w = p["radius"], p["height"], p["wall"]
    _require(s, w < 0.5 * r and w < 0.5 * h, f"wall ({w}) must be below half the radius and half the height")
    _require(s, p["handle_radius"] < 0.5 * p["handle_height"],
             "handle_radius must be below half of handle_height")
    rb = p["base_scale"] * r
    t = np.linspace(0.0, 1.0, 24)
    # Outer wall flares from rb at the bottom to r at the rim (quarter-sine).
    y_out = w + (h - w) * t
    r_out = rb + (r - rb) * np.sin(0.5 * math.pi * t)
    corner = np.linspace(0.0, math.pi / 2, 8)[1:-1]
    base = np.stack([rb - w + w * np.sin(corner), w - w * np.cos(corner)], axis=1)
    rim_a = np.linspace(0.0, math.pi, 10)[1:-1]
    rim = np.stack([r - 0.5 * w + 0.5 * w * np.cos(rim_a), h + 0.5 * w * np.sin(rim_a)], axis=1)
    y_in = h - (h - w) * t  # inner wall, rim down to the floor (floor thickness = wall)
    r_in = rb + (r - rb) * np.sin(0.5 * math.pi * (y_in - w) / (h - w)) - w
    profile = np.vstack([
        [[0.0, 0.0], [rb - w, 0.0]],
        base,
        np.stack([r_out, y_out], axis=1),
        rim,
        np.stack([r_in, y_in], axis=1),
        [[0.0, w]],
    ])
    bowl = _revolve_y(profile, p["sections"])
    # Handle: half ellipse over the bowl from rim to rim, ends sunk into the rim.
    a = r - 0.5 * w
    phi = np.linspace(0.0, math.pi, 40)
    arc = np.stack([a * np.cos(phi), h + p["handle_height"] * np.sin(phi), 0 * phi], axis=1)
    sink = min(2.0 * p["handle_radius"], 0.5 * h)
    line = np.vstack([[[a, h - sink, 0.0]], arc, [[-a, h - sink, 0.0]]])
    handle = _tube(line, p["handle_radius"])
    return trimesh.util.concatenate([bowl, handle])


def _jeep(p: dict) -> trimesh.Trimesh:
    """Jeep-like car, length along x (front at +x), width along z."""
    s = "jeep"
    _positive(s, p, "length", "width", "height")
    ln, wd, ht = p["length"], p["width"], p["height"]
    wheel_r, wheel_w = 0.25 * ht, 0.18 * wd
    side = wd / 2 - 0.9 * wheel_w  # body half width; wheels overlap it by 10 %
    body_lo, body_hi = wheel_r, 0.62 * ht
    body = trimesh.creation.box(bounds=[[-ln / 2, body_lo, -side], [ln / 2, body_hi, side]])
    cabin = trimesh.creation.box(bounds=[[-0.45 * ln, body_hi - 0.05 * ht, -0.85 * side],
                                         [0.1 * ln, ht, 0.85 * side]])
    parts = [body, cabin]
    for x in (-0.3 * ln, 0.3 * ln):
        for z in (-(wd - wheel_w) / 2, (wd - wheel_w) / 2):
            wheel = trimesh.creation.cylinder(radius=wheel_r, height=wheel_w, sections=32)
            wheel.apply_translation([x, wheel_r, z])
            parts.append(wheel)
    return _rest_on_ground(trimesh.util.concatenate(parts))


def _statue(p: dict) -> trimesh.Trimesh:
    """Pedestal, legs, torso, neck and head: a deformed surface of revolution.

    Each horizontal ring is scaled by smooth seeded noise and shifted by a
    smooth lean, which keeps the surface a single closed manifold while
    making it irregular and non-convex (waist and neck are concave).
    """
    s = "statue"
    _positive(s, p, "height")
    _integer(s, p, "seed", 0)
    h = p["height"]
    rng = np.random.default_rng(int(p["seed"]))
    key = np.array([  # (radius, y) in units of the height
        [0.0, 0.0], [0.2, 0.0], [0.21, 0.1], [0.14, 0.12], [0.09, 0.16], [0.07, 0.3],
        [0.08, 0.36], [0.13, 0.48], [0.16, 0.58], [0.05, 0.66], [0.05, 0.7], [0.095, 0.76],
        [0.1, 0.84], [0.06, 0.94], [0.0, 0.955],
    ])
    key[3:-1, 0] *= 1.0 + rng.uniform(-0.15, 0.15, len(key) - 4)
    prof = _chaikin(key, 3)
    prof[:, 1] *= 1.0 / prof[-1, 1]
    sides = 64
    theta = np.linspace(0.0, 2 * math.pi, sides, endpoint=False)
    t = prof[1:-1, 1][:, None]
    above = np.clip((t - 0.12) / 0.2, 0.0, 1.0)  # no noise on the pedestal
    noise = np.zeros((len(t), sides))
    for m in (2, 3, 5):
        amp, freq = rng.uniform(0.03, 0.08), rng.uniform(2.0, 6.0)
        phase_a, phase_y = rng.uniform(0.0, 2 * math.pi, 2)
        noise += amp * np.sin(m * theta[None, :] + phase_a) * np.sin(freq * math.pi * t + phase_y)
    shoulders = 0.35 * np.exp(-((t - 0.56) / 0.08) ** 2) * np.cos(2 * theta[None, :])
    scale = 1.0 + above * (noise + shoulders)
    lean = rng.uniform(-0.06, 0.06, 2) * above ** 2 * t
    rad = prof[1:-1, 0][:, None] * scale
    ring = np.stack([lean[:, :1] + rad * np.cos(theta), np.broadcast_to(t, rad.shape),
                     lean[:, 1:] + rad * np.sin(theta)], axis=2).reshape(-1, 3)
    n_rings = len(t)
    top = [lean[-1, 0], 1.0, lean[-1, 1]]
    verts = np.vstack([[[0.0, 0.0, 0.0]], ring, [top]]) * h
    faces = []
    for j in range(sides):
        faces.append([0, 1 + j, 1 + (j + 1) % sides])
    for i in range(n_rings - 1):
        for j in range(sides):
            a0, a1 = 1 + i * sides + j, 1 + i * sides + (j + 1) % sides
            b0, b1 = a0 + sides, a1 + sides
            faces += [[a0, b0, b1], [a0, b1, a1]]
    last, pole = 1 + (n_rings - 1) * sides, len(verts) - 1
    for j in range(sides):
        faces.append([pole, last + (j + 1) % sides, last + j])
    mesh = _outward(trimesh.Trimesh(verts, np.array(faces), process=False))
    return _rest_on_ground(mesh)


def _mesh_file(p: dict, base_dir: pathlib.Path | None) -> trimesh.Trimesh:
    _positive("mesh", p, "scale")
    raw = p["path"]
    _require("mesh", isinstance(raw, (str, pathlib.Path)), f"path must be a string (got {raw!r})")
    path = pathlib.Path(raw)
    if not path.is_absolute():
        path = pathlib.Path(base_dir or pathlib.Path.cwd()) / path
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    stat = path.stat()
    key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size, float(p["scale"]))
    if key not in _MESH_FILES:
        try:
            mesh = trimesh.load(str(path), force="mesh")
        except Exception as err:  # trimesh raises many kinds for unreadable files
            raise ValueError(f"shape 'mesh': cannot read {path}: {err}") from err
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise ValueError(f"shape 'mesh': {path} holds no triangles")
        mesh.apply_scale(float(p["scale"]))
        _MESH_FILES[key] = _rest_on_ground(_outward(mesh))
        while len(_MESH_FILES) > MESH_FILES_KEPT:
            _MESH_FILES.pop(next(iter(_MESH_FILES)))
    else:
        _MESH_FILES[key] = _MESH_FILES.pop(key)  # most recently used last
    return _MESH_FILES[key].copy()


MESH_FILES_KEPT = 8
"""Mesh files kept read (a level is checked, then built: its files are read once)."""
_MESH_FILES: dict[tuple, trimesh.Trimesh] = {}


_BUILDERS: dict[str, Callable[[dict], trimesh.Trimesh]] = {
    "box": _box,
    "sphere": _sphere,
    "cylinder": _cylinder,
    "capsule": _capsule,
    "torus": _torus,
    "wine_bottle": _wine_bottle,
    "basket": _basket,
    "jeep": _jeep,
    "statue": _statue,
}


def build_mesh(shape: str, params: dict | None = None, *,
               base_dir: pathlib.Path | None = None) -> trimesh.Trimesh:
    """Builds an object mesh in its local frame (origin at the base centre, y up).

    Args:
        shape: one of ``SHAPES`` (box, sphere, cylinder, capsule, torus,
            wine_bottle, basket, jeep, statue, mesh).
        params: shape parameters (see ``SHAPES`` for names and defaults);
            lengths in meters.
        base_dir: folder that a relative ``mesh`` path is resolved against
            (default: the working directory).

    Returns:
        The mesh; it rests on y = 0 (min y = 0).

    Raises:
        ValueError: unknown shape, unknown parameter or bad value (the message
            names the allowed shapes, parameters or range).
        FileNotFoundError: the ``mesh`` file does not exist (names the path).
    """
    p = resolve_params(shape, params)
    if shape == "mesh":
        return _mesh_file(p, base_dir)
    return _BUILDERS[shape](p)
