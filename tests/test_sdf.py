"""Object signed distances: closed forms, grid against igl, poses and velocities."""

import math

import numpy as np
import pytest
import trimesh

from sandbox.collision.sdf import FAR, ObjectInstance, ObjectSet
from sandbox.objects import build_mesh

pytestmark = pytest.mark.keeps_runtime  # the module's ObjectSets hold fields outside a world

SPACING = 2.0  # m between objects, far more than their size: each point sees its own object
FD_STEP = 1e-6  # m, central differences of the float64 closed forms
TRILINEAR_BOUND = math.sqrt(3.0) / 2.0
"""Trilinear interpolation is a convex combination of the 8 corner samples; the
signed distance is 1-Lipschitz, so the error is at most sum_i w_i |p - c_i|,
which peaks at the cell centre: sqrt(3) / 2 cell sizes."""


def _rot(axis, angle_deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return trimesh.transformations.rotation_matrix(math.radians(angle_deg), axis)[:3, :3]


def _instance(name, shape, params, position, rotation=None, friction=0.4):
    return ObjectInstance(name, shape, params, build_mesh(shape, params), np.asarray(position, float),
                          np.eye(3) if rotation is None else rotation, friction)


# Closed forms written independently of the Taichi code, local frame at the base.
def _box(q, size):
    b = np.asarray(size) / 2
    a = np.abs(q - [0, b[1], 0]) - b
    return np.linalg.norm(np.maximum(a, 0), axis=1) + np.minimum(a.max(axis=1), 0)


def _sphere(q, r):
    return np.linalg.norm(q - [0, r, 0], axis=1) - r


def _cylinder(q, r, h):
    a = np.stack([np.hypot(q[:, 0], q[:, 2]) - r, np.abs(q[:, 1] - h / 2) - h / 2], axis=1)
    return np.linalg.norm(np.maximum(a, 0), axis=1) + np.minimum(a.max(axis=1), 0)


def _capsule(q, r, h):
    y = np.clip(q[:, 1], r, h - r)
    return np.linalg.norm(q - np.stack([0 * y, y, 0 * y], axis=1), axis=1) - r


def _torus(q, big, small):
    return np.hypot(np.hypot(q[:, 0], q[:, 2]) - big, q[:, 1] - small) - small


PRIMITIVES = [
    ("box", {"size": [0.3, 0.2, 0.4]}, lambda q: _box(q, [0.3, 0.2, 0.4])),
    ("sphere", {"radius": 0.15}, lambda q: _sphere(q, 0.15)),
    ("cylinder", {"radius": 0.1, "height": 0.3}, lambda q: _cylinder(q, 0.1, 0.3)),
    ("capsule", {"radius": 0.08, "height": 0.4}, lambda q: _capsule(q, 0.08, 0.4)),
    ("torus", {"major_radius": 0.15, "minor_radius": 0.05}, lambda q: _torus(q, 0.15, 0.05)),
]


@pytest.fixture(scope="module")
def primitives():
    """The five primitives side by side along x, identity rotation."""
    return ObjectSet([_instance(s, s, p, [k * SPACING, 0, 0]) for k, (s, p, _) in enumerate(PRIMITIVES)])


@pytest.fixture(scope="module")
def sculpted():
    """A statue and a basket (grid SDFs) side by side, grid 48 along the longest side."""
    return ObjectSet([_instance("statue", "statue", {"height": 0.4, "seed": 3}, [0, 0, 0]),
                      _instance("basket", "basket", {}, [SPACING, 0, 0])], grid_resolution=48)


@pytest.mark.parametrize("k", range(len(PRIMITIVES)))
def test_primitive_matches_closed_form(primitives, k):
    """Analytic distance equals the closed form inside and outside; normals are unit and equal the gradient."""
    shape, _, exact = PRIMITIVES[k]
    rng = np.random.default_rng(k)
    lo, hi = primitives.instances[k].mesh.bounds
    local = rng.uniform(lo - 0.1, hi + 0.1, (4000, 3))
    d, n, idx = primitives.query_numpy(local + [k * SPACING, 0, 0])
    ref = exact(local)
    assert (ref < 0).sum() > 200 and (ref > 0).sum() > 200, "need points on both sides"
    assert np.all(idx == k)
    assert np.abs(d - ref).max() < 2e-6, shape
    assert np.abs(np.linalg.norm(n, axis=1) - 1).max() < 1e-5
    grad = np.stack([(exact(local + FD_STEP * e) - exact(local - FD_STEP * e)) / (2 * FD_STEP)
                     for e in np.eye(3)], axis=1)
    smooth = np.abs(np.linalg.norm(grad, axis=1) - 1) < 1e-6  # off the kinks of the distance
    assert smooth.sum() > 3000
    assert np.abs(n[smooth] - grad[smooth]).max() < 1e-4, shape


def test_empty_set_is_far():
    """With no objects the query returns a large positive distance and index -1."""
    d, n, k = ObjectSet([]).query_numpy(np.zeros((3, 3)))
    assert np.all(d >= FAR * 0.99) and np.all(k == -1) and np.allclose(n, [0, 1, 0])


def _near_surface(mesh, count, spread, seed):
    pts, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    offset = np.random.default_rng(seed).uniform(-spread, spread, (count, 1))
    return pts + offset * mesh.face_normals[faces]


@pytest.mark.parametrize("k", [0, 1])
def test_grid_matches_exact_distance_near_surface(sculpted, k):
    """Grid distance stays within the trilinear bound sqrt(3)/2 h of igl's exact value; sign right beyond it."""
    inst = sculpted.instances[k]
    h = sculpted.grid_cell[k]
    local = _near_surface(inst.mesh, 4000, 3 * h, seed=k)
    world = local + [k * SPACING, 0, 0]
    d, n, idx = sculpted.query_numpy(world)
    ref, ref_n, ref_k = sculpted.reference_numpy(world)
    assert np.all(idx == k) and np.all(ref_k == k)
    err = np.abs(d - ref)
    assert err.max() <= TRILINEAR_BOUND * h + 1e-6, (inst.shape, err.max() / h)
    # A systematic fault (e.g. a half-cell shift) would move the typical error to ~h/2.
    assert np.median(err) < 0.05 * h, (inst.shape, np.median(err) / h)
    clear = np.abs(ref) > TRILINEAR_BOUND * h
    assert clear.sum() > 500
    assert np.all(np.sign(d[clear]) == np.sign(ref[clear]))
    assert np.abs(np.linalg.norm(n, axis=1) - 1).max() < 1e-4
    # Normals agree with the exact direction away from the thin parts and kinks.
    assert np.median(np.einsum("ij,ij->i", n[clear], ref_n[clear])) > 0.99


def test_grid_far_points_point_away(sculpted):
    """Outside the grid the distance stays positive, bounds the exact one from above and the normal points away."""
    rng = np.random.default_rng(5)
    dirs = rng.normal(size=(500, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    centre = np.array([0.0, 0.2, 0.0])
    world = centre + 0.6 * dirs  # well outside the statue's padded box, nearer it than the basket
    d, n, idx = sculpted.query_numpy(world)
    ref, _, _ = sculpted.reference_numpy(world)
    assert np.all(idx == 0)
    assert np.all(d > 0) and np.all(d >= ref - 1e-5)
    assert np.all(np.einsum("ij,ij->i", n, dirs) > 0)


def test_posed_object_equals_transformed_points():
    """A rotated and translated object answers like the unposed one queried at the transformed points."""
    rot = _rot([1, 2, 0.5], 40)
    pos = np.array([0.3, 0.5, -0.2])
    objs = ObjectSet([_instance("statue", "statue", {"seed": 1}, pos, rot),
                      _instance("box", "box", {"size": [0.2, 0.1, 0.3]}, pos + [3, 0, 0], rot)],
                     grid_resolution=32)
    rng = np.random.default_rng(7)
    for k in range(2):
        lo, hi = objs.instances[k].mesh.bounds
        local = rng.uniform(lo - 0.05, hi + 0.05, (2000, 3))
        offset = np.array([3.0 * k, 0, 0])
        world = (local @ rot.T) + pos + offset
        d_posed, n_posed, _ = objs.query_numpy(world)
        objs.place(k, offset, np.eye(3))
        d_local, n_local, _ = objs.query_numpy(local + offset)
        objs.place(k, pos + offset, rot)
        assert np.abs(d_posed - d_local).max() < 2e-5
        assert np.abs(n_posed - n_local @ rot.T).max() < 2e-3


def test_velocity_matches_finite_difference_of_surface_points():
    """After set_pose, velocity_at at a surface point equals that point's displacement over dt."""
    r0, p0 = _rot([0, 1, 0], 10), np.array([0.0, 0.0, 0.0])
    r1, p1 = _rot([0.3, 1, 0.2], 10) @ r0, np.array([0.02, 0.01, -0.03])
    dt = 1.0 / 60.0
    objs = ObjectSet([_instance("jeep", "jeep", {}, p0, r0, friction=0.7),
                      _instance("ball", "sphere", {}, [5, 0, 0])], grid_resolution=16)
    verts = np.asarray(objs.instances[0].mesh.vertices)
    assert np.allclose(objs.velocity_numpy(0, verts), 0.0)
    objs.set_pose(0, p1, r1, dt)
    x0, x1 = verts @ r0.T + p0, verts @ r1.T + p1
    v = objs.velocity_numpy(0, x1)
    fd = (x1 - x0) / dt
    assert np.abs(v - fd).max() < 1e-4 * np.abs(fd).max()
    lin, omega = objs.velocity(0)
    assert np.allclose(lin, (p1 - p0) / dt)
    assert np.isclose(np.linalg.norm(omega), math.radians(10) / dt)
    assert np.allclose(objs.velocity_numpy(1, x1), 0.0)
    pos, rot = objs.pose(0)
    assert np.allclose(pos, p1) and np.allclose(rot, r1)
    wv, wf = objs.world_mesh(0)
    assert wv.dtype == np.float32 and wf.dtype == np.int32 and np.allclose(wv, x1, atol=1e-6)


def test_grid_normal_is_gradient_of_interpolant(sculpted):
    """Grid normals equal the normalised finite-difference gradient of the interpolated distance."""
    inst, h = sculpted.instances[0], sculpted.grid_cell[0]
    origin = sculpted.grid_origin.to_numpy()[0].astype(float)
    step = 0.02 * h
    local = _near_surface(inst.mesh, 3000, 2 * h, seed=11)
    cell = (local - origin) / h
    frac = cell - np.floor(cell)
    inner = np.all((frac > 0.05) & (frac < 0.95), axis=1)  # p +- step stays in one cell
    pts = local[inner]
    _, n, _ = sculpted.query_numpy(pts)
    # Central differences of a multilinear function are exact up to rounding.
    grad = np.stack([(sculpted.query_numpy(pts + step * e)[0].astype(float)
                      - sculpted.query_numpy(pts - step * e)[0]) / (2 * step) for e in np.eye(3)], axis=1)
    grad /= np.linalg.norm(grad, axis=1, keepdims=True)
    assert len(pts) > 1000
    assert np.percentile(np.linalg.norm(n - grad, axis=1), 99) < 5e-3
