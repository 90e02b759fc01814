"""Contact projections shared by ropes and cloth: ground, objects, friction."""

import taichi as ti


@ti.func
def friction_correction(x, x_prev, n, pen, mu, v_surface, dt):
    """Position-based Coulomb friction after a contact push of depth ``pen``.

    The tangential displacement relative to the surface this substep is
    removed if it is below mu * pen (static), otherwise reduced by mu * pen.

    Returns:
        The correction (m) to add to x.
    """
    dp = (x - x_prev) - v_surface * dt
    dt_vec = dp - dp.dot(n) * n
    lt = dt_vec.norm()
    corr = ti.math.vec3(0.0)
    if lt > 1e-12:
        corr = -dt_vec * ti.min(mu * pen / lt, 1.0)
    return corr


@ti.func
def plane_contact(x, x_prev, radius, height, mu, dt):
    """Keep a sphere of ``radius`` above the ground plane y = height (with friction).

    Returns:
        The corrected position.
    """
    out = x
    pen = height + radius - x[1]
    if pen > 0.0:
        n = ti.math.vec3(0.0, 1.0, 0.0)
        out = x + pen * n
        out += friction_correction(out, x_prev, n, pen, mu, ti.math.vec3(0.0), dt)
    return out
