"""Geodesic Control sandbox: ropes and cloth manipulated by Geodesic Control."""

__version__ = "0.1.0"
