"""Success criteria: the metrics a level can check at the end of a run.

Each metric is a function ``(world, of) -> value``; ``of`` names the bodies
(ropes, cloths) it applies to, or None for all of them. A criterion holds
when ``min <= value <= max`` and ``value == equals`` for the bounds given.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from sandbox.model.strands import base_name


def _bodies(world, of) -> list[str]:
    """Body names (ropes, cloths) or strands (``R[i0:i1]``) that ``of`` names; all bodies for None."""
    names = list(world.ropes) + list(world.cloths)
    if of is None:
        return names
    return [of] if isinstance(of, str) else list(of)


def _whole(names: list[str]) -> list[str]:
    """The bodies behind strands: per-body run maxima are kept per whole rope."""
    return list(dict.fromkeys(base_name(n) for n in names))


def _max_strain(world, of) -> float:
    return max((world.run_max["strain"].get(n, 0.0) for n in _whole(_bodies(world, of))), default=0.0)


def _max_penetration(world, of) -> float:
    return max((world.run_max["penetration"].get(n, 0.0) for n in _whole(_bodies(world, of))), default=0.0)


def _max_penetration_ratio(world, of) -> float:
    return max(
        (world.run_max["penetration"].get(n, 0.0) / world.body_scale(n) for n in _whole(_bodies(world, of))),
        default=0.0
    )


def _final_strain(world, of) -> float:
    m = world.solver.measure()
    bodies = list(world.ropes) + list(world.cloths)
    return max((float(m["strain"][bodies.index(n)]) for n in _whole(_bodies(world, of))), default=0.0)


def _fsm_state(world, of) -> str:
    return world.fsm.state if world.fsm is not None else "none"


def _pin_drift(world, of) -> float:
    return world.pin_drift()


def _max_speed(world, of) -> float:
    v = world.velocities()
    return float(np.sqrt((v**2).sum(axis=1)).max()) if len(v) else 0.0


def _min_height(world, of) -> float:
    x = world.positions()
    idx = np.concatenate([world.site_particles(n, "all") for n in _bodies(world, of)])
    return float(x[idx, 1].min())


def _rope_min_gap_ratio(world, of) -> float:
    if world.solver.ropecol is None:
        return float("inf")
    gap = world.solver.ropecol.measure()
    seg_rope = world.data.segment_rope
    best = np.inf
    for i, r in enumerate(world.data.ropes):
        if of is None or r.name in _bodies(world, of):
            g = gap[seg_rope == i]
            if len(g):
                best = min(best, float(g.min()) / r.radius)
    return best


def _winding_number(world, of) -> float:
    """Eq. 1 winding of the wound part of rope C around rope T (``of: [C, T]``): the laid turns from
    the first to the last particle within one radius of C of touching T (``wound_turns``)."""
    from sandbox.geometry.winding import wound_turns

    names = _bodies(world, of)
    if len(names) != 2:
        raise ValueError("winding_number needs 'of: [active_rope, target_rope]'")
    rec = world.record.windings.get(tuple(names))
    if rec is None:
        raise ValueError(f"no winding of {names[0]!r} around {names[1]!r} was made")
    x = world.positions()
    c = x[rec.particles].astype(np.float64)
    t = world.rope_positions(names[1]).astype(np.float64)
    rc, rt = world.strand(names[0]).radius, world.strand(names[1]).radius
    return wound_turns(c, t, rec.x_hat, touch=rt + 2.0 * rc)


def _linking_number(world, of) -> float:
    """Gauss linking number of two ropes, each closed far away (an integer)."""
    from sandbox.geometry.knots import linking_number

    names = _bodies(world, of)
    if len(names) != 2:
        raise ValueError("linking_number needs 'of: [rope_a, rope_b]'")
    return float(linking_number(world.rope_positions(names[0]).astype(np.float64),
                                world.rope_positions(names[1]).astype(np.float64)))


def _strand_points(world, name: str) -> np.ndarray:
    """Positions along a rope, a strand ``R[i0:i1]`` of one, or a cloth line (from its start: a control line's
    centre), float64."""
    from sandbox.model.strands import parse_cloth_line

    if parse_cloth_line(name) is None:
        return world.rope_positions(name).astype(np.float64)
    return world.positions()[world.strand(name).idx].astype(np.float64)


def _knot(world, of) -> str:
    """Name of the knot tied in one rope, or between two ropes (or two cloth lines) joined at their standing
    ends: two control lines of one cloth are joined through its centre, where both start."""
    from sandbox.geometry.knots import identify_knot, identify_two_ropes

    names = _bodies(world, of)
    if len(names) == 1:
        return identify_knot(_strand_points(world, names[0])).name
    if len(names) == 2:
        return identify_two_ropes(_strand_points(world, names[0]), _strand_points(world, names[1]),
                                  join="standing").name
    raise ValueError("knot needs 'of: rope' (a knot in one rope) or 'of: [rope_a, rope_b]' (a knot between two)")


def _knot_curves(world, names: list[str]) -> tuple[list[np.ndarray], float]:
    """The curves of a knot in one strand or between two (ropes or cloth lines; two lines of one cloth are one
    curve through its centre, ``joined_at_centre``), and the radius they touch at (a cloth line's: half the
    cloth's thickness)."""
    from sandbox.model.strands import joined_at_centre, parse_cloth_line

    pts = joined_at_centre(names, [_strand_points(world, n) for n in names])
    radius = max(world.strand(n).radius if parse_cloth_line(n) is not None else world.body_scale(base_name(n))
                 for n in names)
    return pts, radius


def _touch_measure(world, of, metric: str, measure) -> float:
    """``measure(a, b or None, radius=...)`` of the knot in one rope or between two (``_knot_curves``)."""
    names = _bodies(world, of)
    if len(names) not in (1, 2):
        raise ValueError(f"{metric} needs 'of: rope' (a knot in one rope) or 'of: [rope_a, rope_b]'")
    pts, radius = _knot_curves(world, names)
    return measure(pts[0], pts[1] if len(pts) == 2 else None, radius=radius)


def knot_centre(world, strands: list[str]) -> np.ndarray | None:
    """Where the knot in one strand, or between two, lies now: the mean of the places where its strands touch
    (``touch_points``), world frame (m), float64; None where they touch nowhere."""
    from sandbox.geometry.knots import touch_points

    pts, radius = _knot_curves(world, list(strands))
    p, _, _ = touch_points(pts[0], pts[1] if len(pts) == 2 else None, radius=radius)
    return p.mean(axis=0) if len(p) else None


def _knot_from_top(world, of) -> float:
    """Horizontal distance (m) from the knot's centre (``knot_centre``) to an object's ``top`` site (where the
    vertical line through its bounding box's centre leaves it): how far the knot lies from the middle of the
    top, whatever the knot's height."""
    names = _bodies(world, of)
    objects = [n for n in names if n in world.object_specs]
    strands = [n for n in names if n not in world.object_specs]
    if len(objects) != 1 or len(strands) not in (1, 2):
        raise ValueError("knot_from_top needs 'of: [rope, object]' (a knot in one rope) or "
                         "'of: [rope_a, rope_b, object]'")
    centre = knot_centre(world, strands)
    if centre is None:
        raise ValueError(f"{' and '.join(strands)} touch nowhere: there is no knot to place")
    off = centre - world.object_sites(objects[0])["top"]
    return float(np.hypot(off[0], off[2]))  # y is up


def _knot_size(world, of) -> float:
    """Largest distance between two places where the knot's ropes touch (m)."""
    from sandbox.geometry.knots import touch_extent

    return _touch_measure(world, of, "knot_size", touch_extent)


def _knot_length(world, of) -> float:
    """Rope held in the knot: along each rope, from its first to its last touch (m)."""
    from sandbox.geometry.knots import touch_length

    return _touch_measure(world, of, "knot_length", touch_length)


def _wraps(world, of) -> list[tuple[tuple[str, str], Any]]:
    names = _bodies(world, of)
    wraps = [(key, rec) for key, rec in world.record.wraps.items() if key[0] in names]
    if not wraps:
        raise ValueError(f"no control line of {', '.join(names)} was wrapped")
    return wraps


def _overlap_distances(world, of) -> np.ndarray:
    """Distances (m) of every wrapped control line's laid particles from their target lines."""
    from sandbox.geometry.mesh_geodesic import polyline_distance

    x = world.positions().astype(np.float64)
    d = [polyline_distance(x[rec.laid()], rec.line)
         for _, rec in _wraps(world, of)]
    return np.concatenate(d) if d else np.zeros(0)


def _overlap_error(world, of) -> float:
    """Largest distance (m) of a wrapped control line's laid particles from their target line."""
    d = _overlap_distances(world, of)
    return float(d.max()) if len(d) else 0.0


def _overlap_error_mean(world, of) -> float:
    d = _overlap_distances(world, of)
    return float(d.mean()) if len(d) else 0.0


def _overlap_error_ratio(world, of) -> float:
    return _overlap_error(world, of) / min(world.body_scale(key[0]) for key, _ in _wraps(world, of))


def _wrap_turns(world, of) -> float:
    """Largest |turns| of a wrapped control line's laid particles about the vertical through its object."""
    from sandbox.geometry.mesh_geodesic import turns_about

    x = world.positions().astype(np.float64)
    best = 0.0
    for _, rec in _wraps(world, of):
        k = world.object_index(rec.object)
        verts, _ = world.objects.world_mesh(k)
        centre = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
        laid = rec.laid()
        if len(laid) > 1:
            best = max(best, abs(turns_about(x[laid], axis=(0.0, 1.0, 0.0), origin=centre)))
    return best


def _cloth_interpenetration(world, of) -> int:
    names = [n for n in _bodies(world, of) if n in world.cloths]
    if not names:
        raise ValueError("cloth_interpenetration needs 'of' to name a cloth (or nothing, for every cloth)")
    now = {n: world.crossings[n].count() for n in names if n in world.crossings}  # the last frame too
    return max(max(world.run_max["interpenetration"].get(n, 0), now.get(n, 0)) for n in names)


def _coverage(world, of) -> float:
    """Fraction of an object's surface with a cloth particle within half a thickness plus one spacing."""
    from scipy.spatial import cKDTree

    names = [of] if isinstance(of, str) else list(of or [])
    objects = [n for n in names if n in world.object_specs]
    cloths = [n for n in names if n in world.cloths]
    if len(objects) != 1 or not cloths:
        raise ValueError("coverage needs 'of: [cloth, object]' (one object, one or more cloths)")
    pts = world.surface_samples(objects[0])
    x = world.positions()
    covered = np.zeros(len(pts), bool)
    for name in cloths:
        c = world.cloths[name]
        reach = 0.5 * c.thickness + max(c.spacing)
        d, _ = cKDTree(x[c.start : c.end]).query(pts, distance_upper_bound=reach)
        covered |= np.isfinite(d)
    return float(covered.mean())


METRICS: dict[str, tuple[str, Callable[[Any, Any], Any]]] = {
    "max_strain": ("largest relative rod/edge stretch |l - r| / r over the run", _max_strain),
    "final_strain": ("largest relative rod/edge stretch at the end", _final_strain),
    "max_penetration": ("deepest penetration over the run (m): into ground, objects, other capsules", _max_penetration),
    "max_penetration_ratio": ("max_penetration / (rope radius or cloth thickness)", _max_penetration_ratio),
    "cloth_interpenetration": ("most structural edges of a cloth passing through one of its own triangles in "
                               "one frame (every 5th frame and the last), over the run: cloth through cloth",
                               _cloth_interpenetration),
    "rope_min_gap_ratio": ("smallest capsule distance minus radii, over the radius, at the end", _rope_min_gap_ratio),
    "pin_drift": ("largest distance of a held particle from its target at the end (m)", _pin_drift),
    "max_speed": ("fastest particle at the end (m/s): small when settled", _max_speed),
    "min_height": ("lowest particle of the bodies at the end (m)", _min_height),
    "fsm_state": ("the FSM's state at the end (success, failure or a state name)", _fsm_state),
    "winding_number": ("turns of the wound part of rope C around rope T (paper Eq. 1; the laid turns that touch T), of: [C, T]", _winding_number),
    "linking_number": ("Gauss linking number of two ropes closed far away, of: [A, B]", _linking_number),
    "knot": ("knot tied in a rope closed far away (unknot, trefoil_left/right, figure_eight, granny_left/right, "
             "square, unknown), of: R; or between two ropes joined at their first particles, of: [A, B]", _knot),
    "knot_size": ("largest distance (m) between two places where the knot's ropes touch (axes within 2.5 "
                  "radii): a few diameters for a tight knot, the whole stretch for half knots tied apart; "
                  "of: R (parts of R a half turn apart) or [A, B]", _knot_size),
    "knot_length": ("rope held in the knot (m): along each rope, from its first to its last place touching the "
                    "other (or, of one rope, itself); a tight overhand knot in a 12 mm rope holds about 0.2 m, "
                    "a loop never pulled through adds its length; of: R or [A, B]", _knot_length),
    "knot_from_top": ("horizontal distance (m) from the knot's centre (the mean of the places where its strands "
                      "touch) to the object's top site: near 0 for a knot tied on the middle of its top, more than "
                      "the top's half width for one that slid off; of: [R, object] or [A, B, object]",
                      _knot_from_top),
    "overlap_error": ("largest distance (m) of a wrapped control line's laid particles from its target line "
                      "(offset by half the cloth thickness), of: cloth", _overlap_error),
    "overlap_error_mean": ("mean of the same distances (m), of: cloth", _overlap_error_mean),
    "overlap_error_ratio": ("overlap_error / cloth thickness, of: cloth", _overlap_error_ratio),
    "wrap_turns": ("largest |turns| of a wrapped control line about the vertical axis through its object, "
                   "of: cloth", _wrap_turns),
    "coverage": ("fraction of an object's surface (area-uniform samples) with a cloth particle within half "
                 "the thickness plus one grid spacing, of: [cloth, object]", _coverage),
}
"""Metric name -> (description, function)."""


def evaluate(criteria, world) -> list[dict]:
    """Evaluate a level's ``success`` list; one dict per criterion."""
    out = []
    for c in criteria:
        desc, fn = METRICS[c.metric]
        try:
            value = fn(world, c.of)
            error = None
        except Exception as exc:  # a metric that cannot be computed fails its criterion
            value, error = None, f"{type(exc).__name__}: {exc}"
        ok = error is None
        if ok and c.min is not None:
            ok = value >= c.min
        if ok and c.max is not None:
            ok = value <= c.max
        if ok and c.equals is not None:
            ok = value == c.equals
        row = {"metric": c.metric, "of": c.of, "value": value, "min": c.min, "max": c.max, "equals": c.equals,
               "ok": bool(ok)}
        if error:
            row["error"] = error
        out.append(row)
    return out
