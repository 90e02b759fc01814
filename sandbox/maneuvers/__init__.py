"""Maneuvers: importing this package registers every built-in maneuver."""

from sandbox.maneuvers import basic  # noqa: F401
from sandbox.maneuvers.base import REGISTRY, Maneuver, Status, register  # noqa: F401
from sandbox.maneuvers import winding  # noqa: F401,E402
from sandbox.maneuvers import knotting  # noqa: F401,E402
from sandbox.maneuvers import tightening  # noqa: F401,E402
from sandbox.maneuvers import wrapping  # noqa: F401,E402
