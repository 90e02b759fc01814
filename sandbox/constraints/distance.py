"""Distance constraints: rods, cloth edges and Jakobsen skip-one bending.

All three are the same XPBD distance projection with different rest lengths
and compliances:

* inextensibility (paper Eq. 2, written here as |p_i+1 - p_i| - r = 0, which
  has the same zero set as the squared form and a unit-length gradient),
* bending (paper Eq. 3, |p_i+1 - p_i-1| - 2r = 0),
* cloth structural, shear and skip-one bending edges.
"""

import taichi as ti


@ti.func
def xpbd_distance(xa, xb, wa, wb, rest, alpha_tilde, lam):
    """One XPBD projection of C = |xa - xb| - rest.

    Args:
        xa, xb: positions (m).
        wa, wb: inverse masses (1/kg); 0 for pinned or driven particles.
        rest: rest length (m).
        alpha_tilde: compliance / dt^2 (1/kg).
        lam: the constraint's accumulated multiplier this substep.

    Returns:
        (dxa, dxb, dlam): position corrections (m) and multiplier increment.
    """
    dxa = ti.math.vec3(0.0)
    dxb = ti.math.vec3(0.0)
    dlam = 0.0
    d = xa - xb
    length = d.norm()
    wsum = wa + wb + alpha_tilde
    if length > 1e-9 and wsum > 0.0:
        n = d / length
        c = length - rest
        dlam = (-c - alpha_tilde * lam) / wsum
        dxa = wa * dlam * n
        dxb = -wb * dlam * n
    return dxa, dxb, dlam
