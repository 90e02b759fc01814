"""Mesh geodesics for cloth-wrapping target lines (SPEC §5, paper §5.1, §7)."""

import numpy as np
import pytest
import trimesh

from sandbox.geometry.mesh_geodesic import (
    SurfaceGeodesics,
    polyline_distance,
    polyline_length,
    resample,
    turns_about,
)
from sandbox.geometry.mesh_prep import insert_point, prepare_mesh

R_CYL, H_CYL, N_CYL = 0.5, 2.0, 128  # cylinder radius (m), height (m), side facets
R_SPH = 0.3  # sphere radius (m)


def _y_up(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Rotate a trimesh primitive whose axis is z so that its axis is y."""
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return mesh


@pytest.fixture(scope="module")
def cylinder() -> SurfaceGeodesics:
    """Capped cylinder, axis y through the origin, 128 side facets."""
    mesh = _y_up(trimesh.creation.cylinder(radius=R_CYL, height=H_CYL, sections=N_CYL))
    return SurfaceGeodesics(mesh, target_edge=0.2)


@pytest.fixture(scope="module")
def sphere() -> SurfaceGeodesics:
    """Icosphere of radius R_SPH (5120 faces)."""
    return SurfaceGeodesics(trimesh.creation.icosphere(subdivisions=4, radius=R_SPH))


def _helix_tangent(alpha: float) -> np.ndarray:
    """Tangent at (R, y, 0) at angle alpha to +y, winding positively about +y."""
    azimuthal = np.array([0.0, 0.0, -1.0])  # d/dphi of (R cos phi, y, -R sin phi)
    return np.cos(alpha) * np.array([0.0, 1.0, 0.0]) + np.sin(alpha) * azimuthal


def _helix_point(turns: float, y0: float, pitch: float) -> np.ndarray:
    """Point of the helix through (R, y0, 0) after ``turns`` turns about +y."""
    phi = 2.0 * np.pi * turns
    return np.array([R_CYL * np.cos(phi), y0 + turns * pitch, -R_CYL * np.sin(phi)])


def _l_prism() -> trimesh.Trimesh:
    """L-shaped prism: arms [0,2]x[0,1] and [0,1]x[0,2] in (x, z), y in [0, 0.5]."""
    ring = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)
    n = len(ring)
    bottom = np.column_stack([ring[:, 0], np.zeros(n), ring[:, 1]])
    top = bottom + [0.0, 0.5, 0.0]
    vertices = np.vstack([bottom, top])
    reflex = 3  # the L is star-shaped from its reflex corner: fan the caps from it
    fan = [(reflex, i, (i + 1) % n) for i in range(n) if reflex not in (i, (i + 1) % n)]
    faces = [(a, c, b) for a, b, c in fan] + [(a + n, b + n, c + n) for a, b, c in fan]
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, j + n), (i, j + n, i + n)]
    mesh = trimesh.Trimesh(vertices, np.array(faces), process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


def test_box_geodesic_is_straight_line_on_unfolded_faces():
    """A box geodesic across an edge equals the straight segment on the unfolded faces."""
    g = SurfaceGeodesics(trimesh.creation.box(extents=[2.0, 2.0, 2.0]), target_edge=0.2)
    p = np.array([0.3, 1.0, -0.2])  # top face (y = 1)
    q = np.array([-0.4, 0.1, 1.0])  # front face (z = 1)
    path = g.between(p, q)
    q_flat = np.array([q[0], 1.0, 1.0 + (1.0 - q[1])])  # front face rotated up about y=z=1
    flat = path.copy()
    on_front = path[:, 2] > 1.0 - 1e-9
    flat[on_front, 2] = 1.0 + (1.0 - path[on_front, 1])
    flat[on_front, 1] = 1.0
    assert np.allclose(path[[0, -1]], [p, q], atol=1e-9)
    assert polyline_length(path) == pytest.approx(np.linalg.norm(q_flat - p), rel=1e-3)
    assert polyline_distance(flat, np.array([p, q_flat])).max() < 1e-3 * 2.0


def test_box_geodesic_takes_the_shorter_side_of_a_corner():
    """On a cube, between finds the right-then-back route (unfolded length), not a 30% longer one.

    Dijkstra on the mesh edges of a right-triangle grid overestimates some
    directions by up to 41% and leads the shortening to a longer route around
    the other side of a corner; the routing graph with flipped diagonals does not.
    """
    g = SurfaceGeodesics(trimesh.creation.box(extents=[1.0, 1.0, 1.0]), target_edge=0.1)
    p = np.array([0.5, 0.176, -0.383])  # right face (x = 0.5)
    q = np.array([-0.365, -0.5, -0.5])  # on the bottom-back edge
    # back face unfolded beside the right face about their shared edge
    unfolded = np.hypot((0.5 - q[0]) + (p[2] + 0.5), p[1] - q[1])
    assert polyline_length(g.between(p, q)) == pytest.approx(unfolded, rel=1e-6)


def test_trace_to_with_nearly_the_right_tangent_is_the_shortest_geodesic():
    """A tangent 10 degrees off the shortest route's start direction still gives that geodesic."""
    g = SurfaceGeodesics(trimesh.creation.box(extents=[2.0, 2.0, 2.0]), target_edge=0.2)
    p, q = np.array([0.3, 1.0, -0.2]), np.array([-0.4, 0.1, 1.0])
    short = g.between(p, q)
    start = short[1] - short[0]
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    # rotate about the top face's normal (+y)
    tangent = np.array([c * start[0] - s * start[2], 0.0, s * start[0] + c * start[2]])
    line = g.trace_to(p, tangent, q)
    assert np.linalg.norm(line[-1] - q) < 1e-9
    assert polyline_length(line) == pytest.approx(polyline_length(short), rel=1e-6)
    assert polyline_distance(line, short).max() < 1e-6
    with pytest.raises(ValueError, match="normal to the surface"):
        g.trace_to(p, [0.0, 1.0, 0.0], q)


def test_cylinder_trace_is_analytic_helix(cylinder):
    """A trace from the side at angle alpha to the axis is the helix of pitch 2 pi R / tan(alpha).

    The side is a prism of N flat facets (developable), so the traced geodesic
    unrolls to a straight line: the perimeter shrinks by sin(pi/N)/(pi/N) and the
    start tangent projected onto a facet changes tan(alpha) by at most cos(pi/N),
    so the relative pitch error is below (pi/N)^2, and the radius lies in
    [R cos(pi/N), R].
    """
    alpha = np.radians(70.0)
    pitch = 2.0 * np.pi * R_CYL / np.tan(alpha)
    p = np.array([R_CYL, -0.8, 0.0])
    length = 1.2 * pitch / np.cos(alpha)  # 1.2 turns, stays on the side
    line = cylinder.trace(p, _helix_tangent(alpha), length)
    h = (np.pi / N_CYL) ** 2
    radius = np.hypot(line[:, 0], line[:, 2])
    assert radius.min() >= R_CYL * np.cos(np.pi / N_CYL) - 1e-9
    assert radius.max() <= R_CYL + 1e-9
    assert polyline_length(line) == pytest.approx(length, rel=1e-9)
    assert turns_about(line) == pytest.approx(1.2, abs=0.01)
    phi = np.unwrap(np.arctan2(-line[:, 2], line[:, 0]))
    slope = np.polyfit(phi, line[:, 1], 1)[0]
    assert abs(2.0 * np.pi * slope / pitch - 1.0) < h


def test_hull_line_stays_on_hull_and_differs_from_mesh_geodesic():
    """On an L-prism the hull geodesic crosses the notch; the mesh one bends round the corner."""
    mesh = _l_prism()
    hull = mesh.convex_hull
    on_mesh = SurfaceGeodesics(mesh, target_edge=0.1)
    on_hull = SurfaceGeodesics(mesh, hull=True, target_edge=0.1)
    p, q = np.array([1.9, 0.5, 0.9]), np.array([0.9, 0.5, 1.9])  # tips of the two arms, on top
    line_h = on_hull.between(p, q)
    line_m = on_mesh.between(p, q)
    dist_to_hull = np.abs(trimesh.proximity.signed_distance(hull, line_h))
    assert dist_to_hull.max() < 1e-9
    assert polyline_length(line_h) == pytest.approx(np.sqrt(2.0), rel=1e-6)
    corner = np.array([1.0, 0.5, 1.0])
    assert polyline_distance(corner, line_m)[0] < 1e-6
    assert polyline_length(line_m) == pytest.approx(2.0 * np.hypot(0.9, 0.1), rel=1e-6)
    assert polyline_distance(line_m, line_h).max() > 0.3


def test_trace_to_keeps_the_long_way_round_on_a_cylinder(cylinder):
    """trace_to ends at q after 1.4 turns along the helix, while between takes the 0.4-turn arc."""
    alpha = np.radians(70.0)
    pitch = 2.0 * np.pi * R_CYL / np.tan(alpha)
    p = np.array([R_CYL, -0.9, 0.0])
    q = _helix_point(1.4, p[1], pitch)
    line = cylinder.trace_to(p, _helix_tangent(alpha), q)
    q_on = cylinder.project(q)[0][0]
    assert np.linalg.norm(line[-1] - q_on) < 1e-9
    assert np.linalg.norm(line[0] - cylinder.project(p)[0][0]) < 1e-9
    assert turns_about(line) == pytest.approx(1.4, abs=0.01)
    assert polyline_length(line) == pytest.approx(1.4 * pitch / np.cos(alpha), rel=2e-3)
    short = cylinder.between(p, q)
    assert turns_about(short) == pytest.approx(0.4, abs=0.01)
    assert polyline_length(short) < 0.5 * polyline_length(line)


def test_trace_to_turns_hint_selects_the_passage(cylinder):
    """A flat helix passes q's azimuth after 1.4 and 2.4 turns: the hint picks the one used."""
    alpha = np.radians(80.0)
    pitch = 2.0 * np.pi * R_CYL / np.tan(alpha)
    p = np.array([R_CYL, -0.9, 0.0])
    q = _helix_point(1.4, p[1], pitch)
    q_on = cylinder.project(q)[0][0]
    for hint, turns in ((None, 1.4), (1.4, 1.4), (2.4, 2.4)):
        line = cylinder.trace_to(p, _helix_tangent(alpha), q, turns_hint=hint)
        assert np.linalg.norm(line[-1] - q_on) < 1e-9
        assert turns_about(line) == pytest.approx(turns, abs=0.01)
        assert np.abs(line[:, 1]).max() < H_CYL / 2, "stays on the side"
        rise = q[1] - p[1]  # the geodesic to q after n turns is the helix of that rise
        helix = np.hypot(turns * 2 * np.pi * R_CYL, rise)
        assert polyline_length(line) == pytest.approx(helix, rel=2e-3)


def test_sphere_short_and_long_great_circle_arcs(sphere):
    """between gives the short great-circle arc; trace_to, tangent reversed, gives 2 pi R - arc.

    The icosphere is inscribed: lengths shrink by O((h/R)^2) for edge length h.
    """
    rel = (sphere.mean_edge / R_SPH) ** 2
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 3))
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    p, q = R_SPH * a, R_SPH * b
    arc = R_SPH * np.arccos(a @ b)
    short = sphere.between(p, q)
    assert polyline_length(short) == pytest.approx(arc, rel=rel)
    towards_q = b - (a @ b) * a
    for sideways in (0.0, 0.3):  # off-plane tangents still reach q by the long way
        tangent = -towards_q + sideways * np.cross(a, towards_q)
        long = sphere.trace_to(p, tangent, q)
        assert polyline_length(long) == pytest.approx(2 * np.pi * R_SPH - arc, rel=rel)
        assert np.linalg.norm(long[-1] - sphere.project(q)[0][0]) < 1e-9
        normal = np.cross(a, b) / np.linalg.norm(np.cross(a, b))
        assert np.abs(long @ normal).max() < 0.02 * R_SPH, "stays on the great circle"


def test_named_points_and_projection():
    """Named sites are the face centres of an off-centre box; project's barycentrics agree."""
    box = trimesh.creation.box(extents=[2.0, 1.0, 4.0])
    box.apply_translation([1.0, 0.5, -2.0])
    g = SurfaceGeodesics(box, target_edge=0.5)
    expected = {
        "top": [1, 1, -2],
        "bottom": [1, 0, -2],
        "front": [1, 0.5, 0],
        "back": [1, 0.5, -4],
        "left": [0, 0.5, -2],
        "right": [2, 0.5, -2],
    }
    for name, point in expected.items():
        assert np.allclose(g.named_point(name), point, atol=1e-9), name
    with pytest.raises(ValueError, match="allowed: top, bottom"):
        g.named_point("middle")
    points, faces, bary = g.project([[1.2, 3.0, -1.0], [-1.0, 0.2, -3.0]])
    assert np.allclose(points, [[1.2, 1.0, -1.0], [0.0, 0.2, -3.0]], atol=1e-9)
    corners = g.mesh.vertices[g.mesh.faces[faces]]
    assert np.allclose(np.einsum("ij,ijk->ik", bary, corners), points, atol=1e-12)


def test_named_point_falls_back_when_the_axis_ray_misses():
    """The top site of a torus (ray through the hole) is on the top rim of the ring."""
    torus = _y_up(trimesh.creation.torus(major_radius=1.0, minor_radius=0.25))
    g = SurfaceGeodesics(torus, target_edge=0.2)
    top = g.named_point("top")
    assert abs(trimesh.proximity.signed_distance(g.mesh, top[None])[0]) < 1e-9
    assert top[1] == pytest.approx(g.mesh.bounds[1, 1], abs=1e-3)
    assert np.hypot(top[0], top[2]) == pytest.approx(1.0, abs=0.05)


def test_prepare_mesh_refines_conformingly():
    """Refinement bounds every edge, keeps the box watertight and its area and volume exact."""
    box = trimesh.creation.box(extents=[1.0, 2.0, 3.0])
    mesh = prepare_mesh(box, target_edge=0.15)
    assert mesh.edges_unique_length.max() <= 0.15
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.area == pytest.approx(box.area, rel=1e-12)
    assert mesh.volume == pytest.approx(box.volume, rel=1e-12)


def test_insert_point_on_edge_splits_both_faces():
    """A point on a shared edge becomes one vertex that both adjacent faces use; area is kept."""
    box = trimesh.creation.box()
    V, F = np.asarray(box.vertices, float), np.asarray(box.faces, np.int64)
    face = 0
    bary = np.array([0.5, 0.5, 0.0])  # midpoint of the face's first edge
    V2, F2, vid, touched = insert_point(V, F, face, bary, snap=1e-9)
    assert len(F2) == len(F) + 2 and vid == len(V) and len(touched) == 4
    out = trimesh.Trimesh(V2, F2, process=False)
    assert out.is_watertight and out.area == pytest.approx(box.area, rel=1e-12)
    assert (F2 == vid).any(axis=1).sum() == 4


def test_a_mesh_of_separate_parts_is_joined_by_its_hull():
    """Two disjoint boxes: no geodesic leads from one to the other on the mesh, so the surface is their
    convex hull, and says why. Between the tops the geodesic is then the straight line across the hull's
    flat top (closed form: 3 m); a one-part mesh keeps its own surface."""
    a = trimesh.creation.box()
    b = trimesh.creation.box()
    b.apply_translation([3.0, 0.0, 0.0])
    g = SurfaceGeodesics(trimesh.util.concatenate([a, b]), target_edge=0.5)
    assert g.is_hull and "2 separate parts" in g.hull_reason
    line = g.between([0.0, 0.5, 0.0], [3.0, 0.5, 0.0])
    assert polyline_length(line) == pytest.approx(3.0, rel=1e-9)
    np.testing.assert_allclose(line[:, 1], 0.5, atol=1e-12)
    one = SurfaceGeodesics(a, target_edge=0.5)
    assert not one.is_hull and one.hull_reason == ""


def test_resample_and_polyline_distance():
    """resample keeps both ends at the given spacing; polyline_distance matches dense sampling."""
    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.55, 0.0]])
    pts = resample(line, 0.1)
    steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert np.allclose(pts[[0, -1]], line[[0, -1]])
    assert np.allclose(steps[:-1], 0.1) and 0.0 < steps[-1] <= 0.1 + 1e-12
    assert len(pts) == 17
    rng = np.random.default_rng(0)
    queries = rng.uniform(-0.5, 1.5, size=(50, 3))
    dense = resample(line, 1e-4)
    brute = np.linalg.norm(queries[:, None] - dense[None], axis=2).min(axis=1)
    assert np.allclose(polyline_distance(queries, line, chunk=7), brute, atol=1e-4)


def test_turns_about_counts_signed_turns():
    """turns_about gives +2.25 for a helix winding right-handedly about +y, and -2.25 reversed."""
    phi = np.linspace(0.0, 2.25 * 2 * np.pi, 400)
    helix = np.column_stack([np.cos(phi), 0.1 * phi, -np.sin(phi)])
    assert turns_about(helix) == pytest.approx(2.25)
    assert turns_about(helix[::-1]) == pytest.approx(-2.25)


def test_polyline_distance_gives_the_arc_length_of_the_nearest_point():
    """An L of two 1 m legs: a point beside the first leg at x = 0.3 is 0.3 m along it; one beside the
    second leg at z = 0.6 is 1.6 m along; one past the far end is at the end (2 m)."""
    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 1.0]])
    pts = np.array([[0.3, 0.2, 0.0], [1.1, 0.0, 0.6], [1.0, 0.0, 1.5]])
    d, arc = polyline_distance(pts, line, with_arc=True, chunk=2)
    np.testing.assert_allclose(d, [0.2, 0.1, 0.5], atol=1e-12)
    np.testing.assert_allclose(arc, [0.3, 1.6, 2.0], atol=1e-12)
    np.testing.assert_array_equal(polyline_distance(pts, line), d)
