"""Perturbations of a level's data: rigid placements of bodies and object swaps.

Everything here works on the plain data of a level file (what
``yaml.safe_load`` gives) and returns dotted overrides, the same keys that
``sandbox run --set`` takes, so that a perturbed run is an ordinary run of
the level with overrides, recorded in its ``spec.json``.

A placement moves bodies rigidly: a shift (m) and a turn (degrees about the
vertical through a pivot, counter-clockwise seen from above, the sense of an
object's y rotation). ``scene`` places every object, rope and cloth and the
camera together, about the centre of the scene's bodies; a body's name
places that body alone, about its own centre. Points written in the FSM
(maneuver parameters) are not moved: a level whose maneuvers find their
places from the geometry moves with its scene; one with written coordinates
does not, and the sweep measures that.
"""

from __future__ import annotations

import math
import pathlib
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from sandbox.objects.builders import LENGTH_PARAMS, SHAPES, build_mesh

SCENE = "scene"
"""The placement target that moves every body of the level and its camera."""

SWAP_SHAPES = tuple(s for s in SHAPES if s != "mesh")
"""Procedural shapes an object may be swapped for by name."""


def _yaw(degrees: float) -> np.ndarray:
    """Rotation about +y by ``degrees`` (the y factor of an object's R = Rz Ry Rx)."""
    return Rotation.from_euler("y", degrees, degrees=True).as_matrix()


def _euler(matrix: np.ndarray, near=(0.0, 0.0, 0.0)) -> list[float]:
    """XYZ Euler degrees (R = Rz Ry Rx) of a rotation matrix, each angle the turn nearest to ``near``'s
    (keyframes interpolate their angles: a spin of 360 degrees must stay one)."""
    got = Rotation.from_matrix(matrix).as_euler("xyz", degrees=True)
    return [float(a + 360.0 * round((float(b) - a) / 360.0)) for a, b in zip(got, near)]


def _turned(euler, turn: float) -> list[float]:
    """An object's XYZ Euler angles turned by ``turn`` degrees about the world's vertical (Q R)."""
    rx, ry, rz = (float(a) for a in euler)
    if rx == 0.0 and rz == 0.0:  # a turn about y alone: exact, and interpolates as the level's does
        return [rx, ry + float(turn), rz]
    return _euler(_yaw(turn) @ _matrix(euler), (rx, ry + float(turn), rz))


def _matrix(euler) -> np.ndarray:
    return Rotation.from_euler("xyz", [float(a) for a in euler], degrees=True).as_matrix()


def _vec(v) -> list[float]:
    return [float(a) for a in v]


def bodies(data: dict) -> dict[str, tuple[str, int]]:
    """Name -> (kind, index) of every object, rope and cloth in level data."""
    out: dict[str, tuple[str, int]] = {}
    scene = data.get("scene") or {}
    for kind, key in (("object", "objects"), ("cloth", "cloths"), ("rope", "ropes")):
        for k, item in enumerate(scene.get(key) or []):
            if isinstance(item, dict) and isinstance(item.get("name"), str):
                out.setdefault(item["name"], (kind, k))
    return out


def _anchor_points(data: dict, names: list[str]) -> np.ndarray:
    """Reference points of the named bodies: objects' positions, rope points, cloth centres."""
    scene = data.get("scene") or {}
    index = bodies(data)
    pts = []
    for name in names:
        kind, k = index[name]
        if kind == "object":
            pts.append(scene["objects"][k].get("position", [0, 0, 0]))
        elif kind == "cloth":
            pts.append(scene["cloths"][k]["center"])
        else:
            pts.extend(scene["ropes"][k]["points"])
    return np.asarray(pts, float).reshape(-1, 3)


def pivot(data: dict, names: list[str]) -> np.ndarray:
    """Centre (m) of the horizontal bounds of the named bodies' reference points, at y = 0."""
    pts = _anchor_points(data, names)
    c = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    return np.array([c[0], 0.0, c[2]])


def placement_overrides(data: dict, target: str, shift=(0.0, 0.0, 0.0), turn: float = 0.0) -> dict[str, Any]:
    """Overrides that move ``target`` (a body's name, or ``scene``) rigidly.

    Args:
        data: the level's plain data.
        target: ``scene`` (every body and the camera) or the name of an object,
            rope or cloth.
        shift: translation (m).
        turn: rotation about the vertical through the pivot (degrees).

    Returns:
        Dotted keys -> new values (positions, rope points, cloth centres and
        yaws, object rotations, motion keyframes, camera).

    Raises:
        KeyError: ``target`` is neither ``scene`` nor a body of the level.
    """
    index = bodies(data)
    names = list(index) if target == SCENE else [target]
    if target != SCENE and target not in index:
        raise KeyError(target)
    if not names:
        return {}
    c = pivot(data, names)
    s = np.asarray(shift, float)
    q = _yaw(turn)

    def move(p) -> list[float]:
        return _vec(q @ (np.asarray(p, float) - c) + c + s)

    scene = data["scene"]
    out: dict[str, Any] = {}
    for name in names:
        kind, k = index[name]
        if kind == "object":
            obj = scene["objects"][k]
            base = f"scene.objects.{k}"
            out[f"{base}.position"] = move(obj.get("position", [0, 0, 0]))
            if turn:
                out[f"{base}.rotation"] = _turned(obj.get("rotation", [0, 0, 0]), turn)
            for j, key in enumerate((obj.get("motion") or {}).get("keyframes", [])):
                out[f"{base}.motion.keyframes.{j}.position"] = move(key["position"])
                if turn:
                    out[f"{base}.motion.keyframes.{j}.rotation"] = _turned(key.get("rotation", [0, 0, 0]), turn)
        elif kind == "cloth":
            cloth = scene["cloths"][k]
            out[f"scene.cloths.{k}.center"] = move(cloth["center"])
            if turn:
                out[f"scene.cloths.{k}.yaw"] = float(cloth.get("yaw", 0.0)) + float(turn)
        else:
            rope = scene["ropes"][k]
            out[f"scene.ropes.{k}.points"] = [move(p) for p in rope["points"]]
            # A pin's script poses its initial position about the world origin: x = R x0 + p.
            # Moved, x' = R' x0' + p' with R' = Q R Q^T and p' = Q(R c + p - c) + c + s - R'(c + s).
            for j, key in enumerate((rope.get("motion") or {}).get("keyframes", [])):
                r = _matrix(key.get("rotation", [0, 0, 0]))
                r2 = q @ r @ q.T
                p2 = q @ (r @ c + np.asarray(key["position"], float) - c) + c + s - r2 @ (c + s)
                out[f"scene.ropes.{k}.motion.keyframes.{j}.position"] = _vec(p2)
                if turn:
                    out[f"scene.ropes.{k}.motion.keyframes.{j}.rotation"] = _euler(r2, key.get("rotation", [0, 0, 0]))
    camera = scene.get("camera")
    if target == SCENE and isinstance(camera, dict):
        for key in ("position", "look_at"):
            if key in camera:
                out[f"scene.camera.{key}"] = move(camera[key])
    return out


def object_extent(obj: dict, base_dir: pathlib.Path) -> np.ndarray:
    """Extents (m) of an object's mesh bounds in its own frame."""
    mesh = build_mesh(obj["shape"], obj.get("params") or {}, base_dir=base_dir)
    lo, hi = mesh.bounds
    return hi - lo


def scaled_params(shape: str, params: dict, factor: float) -> dict:
    """``params`` with every length of ``shape`` (defaults included) multiplied by ``factor``."""
    full = {**{k: v for k, v in SHAPES[shape].items() if v is not None}, **params}
    out = dict(params)
    for name in LENGTH_PARAMS[shape]:
        value = full[name]
        out[name] = [float(v) * factor for v in value] if isinstance(value, (list, tuple)) else float(value) * factor
    return out


def swap_overrides(data: dict, name: str, swap: str, base_dir: pathlib.Path) -> dict[str, Any]:
    """Overrides that replace object ``name`` by ``swap``, of similar size.

    ``swap`` is a shape name (``SWAP_SHAPES``) or ``mesh:PATH`` (a mesh file;
    a relative PATH is relative to the working directory). The new object
    keeps the name, position, rotation, friction and motion of the old one;
    it is scaled uniformly so that its bounding box has the volume of the
    old one's (the geometric mean of the three extents is kept).

    Raises:
        KeyError: ``name`` is not an object of the level.
        ValueError: ``swap`` is not a shape or a readable mesh file.
    """
    index = bodies(data)
    if index.get(name, ("", 0))[0] != "object":
        raise KeyError(name)
    k = index[name][1]
    obj = data["scene"]["objects"][k]
    if swap.startswith("mesh:"):
        shape, params = "mesh", {"path": str(pathlib.Path(swap[5:]).resolve()), "scale": 1.0}
    elif swap in SWAP_SHAPES:
        shape, params = swap, {}
    else:
        raise ValueError(f"{swap!r} is not a shape; allowed: {', '.join(SWAP_SHAPES)} or mesh:PATH")
    old = object_extent(obj, base_dir)
    new = object_extent({"shape": shape, "params": params}, base_dir)
    factor = float(np.cbrt(np.prod(old) / np.prod(new)))
    if not math.isfinite(factor) or factor <= 0:
        raise ValueError(f"cannot size {swap!r} like object {name!r} (extents {new} against {old})")
    return {f"scene.objects.{k}.shape": shape, f"scene.objects.{k}.params": scaled_params(shape, params, factor)}
