"""Capsule-capsule distance (paper Eq. 5) as Taichi functions."""

import taichi as ti


@ti.func
def segment_closest(p0, p1, q0, q1):
    """Closest points of segments [p0, p1] and [q0, q1].

    Ericson, Real-Time Collision Detection, 5.1.9, with clamping; robust for
    parallel and zero-length segments.

    Returns:
        (s, t): parameters in [0, 1] of the closest points p0 + s (p1 - p0)
        and q0 + t (q1 - q0).
    """
    # The 2x2 solve runs in float64: for nearly parallel segments its
    # denominator a e - b^2 is below float32 round-off.
    d1 = ti.cast(p1 - p0, ti.f64)
    d2 = ti.cast(q1 - q0, ti.f64)
    r = ti.cast(p0 - q0, ti.f64)
    a = d1.dot(d1)
    e = d2.dot(d2)
    f = d2.dot(r)
    s = ti.f64(0.0)
    t = ti.f64(0.0)
    eps = 1e-14
    if a <= eps and e <= eps:
        s = 0.0
        t = 0.0
    elif a <= eps:
        s = 0.0
        t = ti.math.clamp(f / e, 0.0, 1.0)
    else:
        c = d1.dot(r)
        if e <= eps:
            t = 0.0
            s = ti.math.clamp(-c / a, 0.0, 1.0)
        else:
            b = d1.dot(d2)
            denom = a * e - b * b
            if denom > 1e-12 * a * e:
                s = ti.math.clamp((b * f - c * e) / denom, 0.0, 1.0)
            else:
                s = 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = ti.math.clamp(-c / a, 0.0, 1.0)
            elif t > 1.0:
                t = 1.0
                s = ti.math.clamp((b - c) / a, 0.0, 1.0)
    return ti.cast(s, ti.f32), ti.cast(t, ti.f32)
