"""What maneuvers record for later maneuvers and for the success criteria.

A ``World`` holds one ``ManeuverRecord`` (``world.record``). Maneuvers write
to it; criteria and later maneuvers read it. Keys name the strands or the
cloth and line involved, as the level writes them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

Pair = tuple[str, str]
"""(active strand, target strand), or (cloth, control line) for wraps."""


@dataclasses.dataclass
class WindingRecord:
    """One strand wound around another (paper §4.2).

    Attributes:
        particles: global indices of the wound particles (the turns, not the exit).
        x_hat: unit vector of the crossing frame (Eq. 1's reference direction).
    """

    particles: np.ndarray
    x_hat: np.ndarray


@dataclasses.dataclass
class WrapRecord:
    """One control line laid onto an object (paper §5.1).

    Attributes:
        object: the object's name.
        line: (k, 3) target line of the particle centres (m).
        surface_line: (k', 3) target line on the surface (m).
        particles: global indices of the line's driven particles, contact first.
        arc: (len(particles),) rest arc length of each from the contact (m).
        c_end: arc length laid when the line is done (m).
    """

    object: str
    line: np.ndarray
    surface_line: np.ndarray
    particles: np.ndarray
    arc: np.ndarray
    c_end: float

    def laid(self) -> np.ndarray:
        """Indices of the particles that lie on the target line when the wrap is done."""
        return self.particles[self.arc <= self.c_end + 1e-9]


@dataclasses.dataclass
class ManeuverRecord:
    """Everything maneuvers recorded in one run.

    Attributes:
        crossings: (active, target) -> (3,) point X where they cross (m).
        windings: (active, target) -> the winding, oldest first.
        wraps: (cloth, control line) -> the wrap.
        knots: the knot's ropes and cloth lines, sorted (a run R[i0:i1] counts as its rope R) -> (3,) place (m) where the last Tightening of them left the knot
            (the median of the places its strands touch, ``geometry.knots.knot_centre``).
    """

    crossings: dict[Pair, np.ndarray] = dataclasses.field(default_factory=dict)
    windings: dict[Pair, WindingRecord] = dataclasses.field(default_factory=dict)
    wraps: dict[Pair, WrapRecord] = dataclasses.field(default_factory=dict)
    knots: dict[tuple[str, ...], np.ndarray] = dataclasses.field(default_factory=dict)
