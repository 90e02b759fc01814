"""Contact projections shared by ropes and cloth: ground, objects, friction.

Contacts are resolved on positions (the particle's sphere is pushed out of
the ground or object). Friction acts on velocities at the end of the
substep: the tangential velocity relative to the surface loses at most
mu times the normal velocity change that the push produced (Coulomb's law
at velocity level). Acting on velocities, friction never fights the
distance constraints inside a substep, so a cloth held by friction over a
box edge cannot lock into a stretched state.

Contacts are inelastic: at the end of a substep a particle that touched a
surface keeps no velocity away from it (relative to the surface). The push
out of the surface is a position correction; read back as velocity it
would throw the particle off again (a cloth lying over a box's vertex,
pushed out by its own shear every substep, then jittered at ~0.5 m/s, at
a shear compliance of 1e-6).
"""

import taichi as ti

# The friction budget (m/s) a contact records at least, so that a
# frictionless contact is still seen (and made inelastic) by the velocity pass.
CONTACT_FLAG = 1e-12


@ti.func
def inelastic_velocity(v, n, v_surface):
    """``v`` less its velocity away from the surface along the normal ``n`` (relative to ``v_surface``)."""
    vn = (v - v_surface).dot(n)
    out = v
    if vn > 0.0:
        out = v - vn * n
    return out


@ti.func
def push_settled_velocity(v, push, inv_dt: ti.f32):
    """``v`` less what a substep's summed contact ``push`` (m) put into it: its part along the push, at most
    |push| / dt and never past zero; a velocity into the push, or no push, is kept (inelastic particle
    contacts: cloth self-collision, rope capsules)."""
    out = v
    lq = push.norm()
    if lq > 0.0:
        d = push / lq
        vn = v.dot(d)
        if vn > 0.0:
            out = v - ti.min(vn, lq * inv_dt) * d
    return out


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


@ti.data_oriented
class Contacts:
    """What a substep's contact passes found, per particle, for the passes after them.

    The ground, object and rope contact passes write it; the chain step, the
    joint cloth step and the velocity pass read it. One structure, allocated
    by the solver only where something can touch a particle, and passed to
    every pass that needs it.

    Fields (n particles):
        hit: (n,) f32, > 0 where the particle touched something this substep.
        normal: (n,) vec3 f32, the direction it was pushed (the chains leave motion along it to the contacts).
        dv: (n,) f32, m/s, friction budget of its ground and object contacts (``CONTACT_FLAG`` at least when touched).
        vel: (n,) vec3 f32, m/s, velocity of the surface it touched.
        plane: (n,) f32, m, ``normal . x`` where its last ground or object push left it: how far it has
            since moved off that surface is ``normal . x - plane`` (the joint cloth step frees a particle
            that has left it). Written by the ground and object passes only, so it holds only where they
            wrote ``normal`` last: for cloth, not for a rope particle a rope contact pushed.
        taut, taut_n, room: (n,) f32, vec3, f32, only with ``taut``: how much of a particle's inverse mass a rope
            contact takes away along ``taut_n``, and how far along it a pass may move it (a held stretch of rope
            drawn taut; ``rope_chain.ChainProjection.taut_f``).
    """

    def __init__(self, n: int, *, taut: bool = False) -> None:
        self.hit = ti.field(ti.f32, shape=n)
        self.normal = ti.Vector.field(3, ti.f32, shape=n)
        self.dv = ti.field(ti.f32, shape=n)
        self.vel = ti.Vector.field(3, ti.f32, shape=n)
        self.plane = ti.field(ti.f32, shape=n)
        self.has_taut = bool(taut)
        self.taut = ti.field(ti.f32, shape=n) if taut else None
        self.taut_n = ti.Vector.field(3, ti.f32, shape=n) if taut else None
        self.room = ti.field(ti.f32, shape=n) if taut else None
