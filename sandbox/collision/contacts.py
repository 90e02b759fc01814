"""Contact projections shared by ropes and cloth: ground, objects, friction.

Contacts are resolved on positions (the particle's sphere is pushed out of
the ground or object). Friction acts on velocities at the end of the
substep: the tangential velocity relative to the surface loses at most
mu times the normal velocity change that the push produced (Coulomb's law
at velocity level). Acting on velocities, friction never fights the
distance constraints inside a substep, so a cloth held by friction over a
box edge cannot lock into a stretched state.
"""

import taichi as ti


@ti.func
def friction_velocity(v, n, dv_max, v_surface):
    """Coulomb friction on a velocity.

    Args:
        v: particle velocity (m/s).
        n: contact normal (unit).
        dv_max: mu * (normal velocity change of the contact), m/s.
        v_surface: velocity of the surface at the contact (m/s).

    Returns:
        The new velocity: tangential slip reduced by at most ``dv_max``.
    """
    rel = v - v_surface
    vt = rel - rel.dot(n) * n
    lt = vt.norm()
    out = v
    if lt > 1e-12:
        out = v - vt * ti.min(dv_max / lt, 1.0)
    return out


@ti.func
def plane_push(x, radius, height):
    """Push a sphere of ``radius`` above the ground plane y = height.

    Returns:
        (corrected position, penetration depth >= 0 in m).
    """
    pen = ti.max(height + radius - x[1], 0.0)
    return x + ti.math.vec3(0.0, pen, 0.0), pen
