"""Procedural object meshes (local frame, resting on y = 0) and their named sites."""

from sandbox.objects.builders import ANALYTIC_SHAPES, SHAPES, build_mesh, is_analytic, resolve_params
from sandbox.objects.sites import SITE_NAMES, named_sites

__all__ = [
    "ANALYTIC_SHAPES",
    "SHAPES",
    "SITE_NAMES",
    "build_mesh",
    "is_analytic",
    "named_sites",
    "resolve_params",
]
