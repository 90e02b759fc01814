"""Taichi rendering kernels: a software rasterizer that runs on CPU and GPU.

Importing this package allocates nothing and does not import Taichi until
``Renderer`` is first used; Taichi buffers exist only inside a ``Renderer``.
"""

from shaders.camera import Camera, auto_camera, fit_sphere, from_level
from shaders.scene import (
    MeshItem,
    RenderScene,
    crease_split,
    ground_cell_for,
    rotation_minimising_frames,
    tube_mesh,
)

__all__ = [
    "Camera",
    "MeshItem",
    "RenderScene",
    "Renderer",
    "auto_camera",
    "crease_split",
    "fit_sphere",
    "from_level",
    "ground_cell_for",
    "rotation_minimising_frames",
    "tube_mesh",
]


def __getattr__(name: str):
    if name == "Renderer":
        from shaders.renderer import Renderer

        return Renderer
    raise AttributeError(f"module 'shaders' has no attribute {name!r}")
