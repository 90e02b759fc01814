"""Taichi collision kernels against NumPy / SciPy brute-force references."""

import pathlib

import numpy as np
import pytest
import taichi as ti
from scipy.spatial import cKDTree

from sandbox.api import Sandbox
from sandbox.collision.capsule_np import segment_segment_closest
from sandbox.collision.contacts import friction_velocity, inelastic_velocity
from sandbox.collision.hashgrid import HashGrid, cell_of, hash_cell, neighbor_offset
from sandbox.constraints.capsule import segment_closest
from sandbox.levels import load_level_from_string
from tests.levelkit import world_from_text as _world

ROOT = pathlib.Path(__file__).resolve().parents[1]
MAX_NEIGHBOURS = 256


@ti.kernel
def _segment_closest_k(p0: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                       p1: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                       q0: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                       q1: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                       st: ti.types.ndarray(dtype=ti.math.vec2, ndim=1),
                       dist: ti.types.ndarray(dtype=ti.f32, ndim=1)):
    for i in range(p0.shape[0]):
        s, t = segment_closest(p0[i], p1[i], q0[i], q1[i])
        c1 = p0[i] + s * (p1[i] - p0[i])
        c2 = q0[i] + t * (q1[i] - q0[i])
        st[i] = ti.math.vec2(s, t)
        dist[i] = (c1 - c2).norm()


@ti.kernel
def _hash_neighbours_k(grid: ti.template(), pts: ti.template(), n: ti.i32, radius: ti.f32,
                       nbr: ti.types.ndarray(dtype=ti.i32, ndim=2), cnt: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    for i in range(n):
        home = cell_of(pts[i], grid.inv_cell)
        k = 0
        for o in range(27):
            c = home + neighbor_offset(o)
            h = hash_cell(c, grid.mask)
            for slot in range(grid.start[h], grid.start[h + 1]):
                j = grid.entries[slot]
                if j != i and (grid.item_cell[j] == c).all() and (pts[i] - pts[j]).norm() < radius:
                    if k < nbr.shape[1]:
                        nbr[i, k] = j
                    k += 1
        cnt[i] = k


# ------------------------------------------------------------------ segment_closest
def _segment_cases(rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """(p0, p1, q0, q1) float32: random pairs plus parallel, collinear, crossing and degenerate families.

    Nearly parallel pairs are left to ``test_segment_closest_nearly_parallel``.
    """
    n = 2000
    groups = []
    groups.append(rng.uniform(-1, 1, (4, n, 3)))                                 # general position
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    p0 = rng.uniform(-1, 1, (n, 3))
    a = rng.uniform(0.05, 1.0, (n, 1))
    b = rng.uniform(-1.0, 1.0, (n, 1))                                           # anti-parallel when < 0
    off = rng.normal(size=(n, 3)) * rng.uniform(0, 0.5, (n, 1))
    groups.append(np.stack([p0, p0 + a * u, p0 + off, p0 + off + b * u]))       # parallel
    along = rng.uniform(-1.5, 1.5, (n, 1)) * u
    groups.append(np.stack([p0, p0 + a * u, p0 + along, p0 + along + b * u]))   # collinear
    s = rng.uniform(0, 1, (n, 1))
    w = rng.normal(size=(n, 3))
    hit = p0 + s * a * u
    groups.append(np.stack([p0, p0 + a * u, hit - 0.3 * w, hit + 0.7 * w]))     # crossing (distance 0)
    q0 = rng.uniform(-1, 1, (n, 3))
    q1 = rng.uniform(-1, 1, (n, 3))
    groups.append(np.stack([p0, p0, q0, q1]))                                    # first is a point
    groups.append(np.stack([q0, q1, p0, p0]))                                    # second is a point
    groups.append(np.stack([p0, p0, q0, q0]))                                    # both are points
    tiny = 1e-7 * u
    groups.append(np.stack([p0, p0 + tiny, q0, q1]))                             # first shorter than 1 um
    groups.append(np.stack([q0, q1, p0, p0 - tiny]))                             # second shorter than 1 um
    allp = np.concatenate(groups, axis=1).astype(np.float32)
    return tuple(np.ascontiguousarray(allp[k]) for k in range(4))


def test_segment_closest_matches_numpy_reference():
    """Taichi segment_closest gives the NumPy reference distance within 1e-5 m, parallel and degenerate pairs included."""
    p0, p1, q0, q1 = _segment_cases(np.random.default_rng(7))
    n = len(p0)
    st = np.zeros((n, 2), np.float32)
    dist = np.zeros(n, np.float32)
    _segment_closest_k(p0, p1, q0, q1, st, dist)
    ref = segment_segment_closest(*(a.astype(np.float64) for a in (p0, p1, q0, q1)))[4]
    assert np.isfinite(dist).all()
    assert ((st >= 0.0) & (st <= 1.0)).all()
    err = np.abs(dist.astype(np.float64) - ref)
    worst = int(np.argmax(err))
    assert err.max() <= 1e-5, (f"pair {worst}: taichi {dist[worst]!r} numpy {ref[worst]!r}",
                               p0[worst], p1[worst], q0[worst], q1[worst])
    assert (ref < 1e-6).sum() >= 2000, "the crossing family must be present"


def _closest_distance(p0, p1, q0, q1) -> np.ndarray:
    n = len(p0)
    st = np.zeros((n, 2), np.float32)
    dist = np.zeros(n, np.float32)
    _segment_closest_k(*(np.ascontiguousarray(a, dtype=np.float32) for a in (p0, p1, q0, q1)), st, dist)
    return dist


def test_segment_closest_nearly_parallel():
    """For 1 m segments 1e-3 rad from parallel, Taichi segment_closest matches the reference distance within 1e-5 m."""
    rng = np.random.default_rng(19)
    n, length, tilt = 4000, 1.0, 1e-3
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = u + tilt * rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    p0 = rng.uniform(-1, 1, (n, 3))
    q0 = p0 + 0.01 * rng.normal(size=(n, 3)) + 0.3 * length * u
    pts = [a.astype(np.float32) for a in (p0, p0 + length * u, q0, q0 + length * v)]
    dist = _closest_distance(*pts)
    ref = segment_segment_closest(*(a.astype(np.float64) for a in pts))[4]
    assert np.abs(dist - ref).max() <= 1e-5


# ------------------------------------------------------------------ spatial hash
def _point_sets(rng: np.random.Generator) -> dict[str, np.ndarray]:
    uniform = rng.uniform(-0.5, 0.5, (3000, 3))
    centres = rng.uniform(-0.3, 0.3, (20, 3))
    clusters = (centres[:, None, :] + 0.02 * rng.normal(size=(20, 100, 3))).reshape(-1, 3)
    clusters[::50] = clusters[1::50]                                              # exact duplicates
    far = rng.uniform(-0.4, 0.4, (1500, 3)) + np.array([-37.3, 12.1, 5.5])      # negative cells, far away
    return {"uniform": uniform, "clusters": clusters, "far": far}


@pytest.mark.parametrize("which", ["uniform", "clusters", "far"])
def test_hashgrid_finds_every_close_pair(which):
    """A 27-cell scan of the HashGrid finds exactly the point pairs closer than one cell (brute-force KD-tree)."""
    pts64 = _point_sets(np.random.default_rng(3))[which]
    pts = pts64.astype(np.float32)
    n, cell = len(pts), 0.05
    field = ti.Vector.field(3, ti.f32, shape=n)
    field.from_numpy(pts)
    grid = HashGrid(n, cell)
    grid.build(field, 0, n)
    nbr = np.full((n, MAX_NEIGHBOURS), -1, np.int32)
    cnt = np.zeros(n, np.int32)
    _hash_neighbours_k(grid, field, n, cell, nbr, cnt)
    assert cnt.max() <= MAX_NEIGHBOURS
    found = {(min(i, int(j)), max(i, int(j))) for i in range(n) for j in nbr[i, : cnt[i]]}

    p = pts.astype(np.float64)
    ref = cKDTree(p).query_pairs(cell * (1 + 1e-5))
    sure = {(i, j) for i, j in ref if np.linalg.norm(p[i] - p[j]) < cell * (1 - 1e-5)}
    assert len(sure) > 100, "too few close pairs for the test to mean anything"
    assert sure <= found, f"missed pairs: {sorted(sure - found)[:5]}"
    assert found <= ref, f"pairs farther than a cell: {sorted(found - ref)[:5]}"
    # each pair is seen from both ends
    seen = {(i, int(j)) for i in range(n) for j in nbr[i, : cnt[i]]}
    assert all((j, i) in seen for i, j in seen)


def test_hashgrid_buckets_sorted_by_id():
    """HashGrid buckets partition the items, each bucket's entries sorted by id, and a rebuild is bitwise identical."""
    pts = _point_sets(np.random.default_rng(5))["clusters"].astype(np.float32)
    n = len(pts)
    field = ti.Vector.field(3, ti.f32, shape=n)
    field.from_numpy(pts)
    grid = HashGrid(n, 0.01)
    grid.build(field, 0, n)
    start = grid.start.to_numpy()
    entries = grid.entries.to_numpy()
    bucket = grid.item_bucket.to_numpy()
    cells = grid.item_cell.to_numpy()
    assert start[0] == 0 and start[-1] == n and (np.diff(start) >= 0).all()
    np.testing.assert_array_equal(np.sort(entries), np.arange(n))
    multi = 0
    for b in np.flatnonzero(np.diff(start) > 0):
        ids = entries[start[b] : start[b + 1]]
        assert (np.diff(ids) > 0).all(), f"bucket {b} not sorted: {ids}"
        assert (bucket[ids] == b).all()
        multi += len(ids) > 1
    assert multi > 50, "too few shared buckets for the order to matter"
    # items of one cell share a bucket
    _, inverse = np.unique(cells, axis=0, return_inverse=True)
    for c in np.unique(inverse.ravel())[:200]:
        assert len(np.unique(bucket[inverse.ravel() == c])) == 1
    grid.build(field, 0, n)
    np.testing.assert_array_equal(grid.entries.to_numpy(), entries)


# ------------------------------------------------------------------ rope capsule broad + narrow phase
ROPES_YAML = """
version: 1
name: capsules
scene:
  ground: false
  ropes:
    - {name: a, points: [[0, 1, 0], [2, 1, 0]], segments: 40, radius: 0.015}
    - {name: b, points: [[0, 2, 0], [2, 2, 0]], segments: 40, radius: 0.02}
    - {name: c, points: [[0, 3, 0], [2, 3, 0]], segments: 40, radius: 0.025}
sim: {fps: 60, substeps: 1, frames: 1}
fsm:
  - {run: Wait, with: {ticks: 1}}
"""


def test_rope_collision_gaps_match_brute_force():
    """RopeCollision.measure gives, for every touching segment, the brute-force minimum capsule gap over all allowed pairs."""
    sim = Sandbox(load_level_from_string(ROPES_YAML, base_dir=ROOT), arch="cpu")
    world = sim.world
    data = world.data
    rng = np.random.default_rng(11)
    x = world.positions().astype(np.float64)
    for r in data.ropes:
        k = r.end - r.start
        steps = rng.normal(size=(k - 1, 3))
        steps *= r.rod_length / np.linalg.norm(steps, axis=1, keepdims=True)
        x[r.start : r.end] = rng.uniform(0, 0.3, 3) + np.concatenate([np.zeros((1, 3)), np.cumsum(steps, 0)])
    world.state.x.from_numpy(x.astype(np.float32))
    gap = world.solver.ropecol.measure()

    xs = world.positions().astype(np.float64)
    seg = data.segments
    rope = data.segment_rope
    rad = np.array([r.radius for r in data.ropes])[rope]
    rod = np.array([r.rod_length for r in data.ropes])
    skip = np.maximum(2, np.ceil(1.0 + 2.0 * np.array([r.radius for r in data.ropes]) / rod - 1e-9))
    s_idx, t_idx = np.meshgrid(np.arange(len(seg)), np.arange(len(seg)), indexing="ij")
    s_idx, t_idx = s_idx.ravel(), t_idx.ravel()
    ok = (s_idx != t_idx) & ((rope[s_idx] != rope[t_idx]) | (np.abs(s_idx - t_idx) >= skip[rope[s_idx]]))
    s_idx, t_idx = s_idx[ok], t_idx[ok]
    d = segment_segment_closest(xs[seg[s_idx, 0]], xs[seg[s_idx, 1]], xs[seg[t_idx, 0]], xs[seg[t_idx, 1]])[4]
    g = d - rad[s_idx] - rad[t_idx]
    brute = np.full(len(seg), 1e30)
    np.minimum.at(brute, s_idx, g)

    touching = brute < 0.0
    assert touching.sum() > 10, "too few contacts for the test to mean anything"
    np.testing.assert_allclose(gap[touching], brute[touching], atol=2e-6)
    assert (gap >= brute - 2e-6).all(), "a gap smaller than any allowed pair: a forbidden pair was counted"


# ------------------------------------------------------------------ cloth self-collision candidate lists
CLOTHS_YAML = """
version: 1
name: folds
scene:
  ground: false
  cloths:
    - {name: a, resolution: [24, 20], size: [0.23, 0.19], center: [0, 1, 0], pins: [A, [5, 7]]}
    - {name: b, resolution: [16, 16], size: [0.15, 0.15], center: [0, 0, 0], mass: 2.0}
sim: {fps: 60, substeps: 1, frames: 1}
fsm:
  - {run: Wait, with: {ticks: 1}}
"""


@ti.kernel
def _self_refresh_k(sc: ti.template()):
    sc.refresh_f()


@ti.kernel
def _self_solve_k(sc: ti.template()):
    sc.solve_f()


def _folded_cloths(rng: np.random.Generator, world) -> np.ndarray:
    """Cloth a folded over onto itself (layer gap from half to three thicknesses across the fold) with
    cloth b crossing between its layers, all jittered by 2 mm: non-neighbour pairs at every distance."""
    a, b = world.cloths["a"], world.cloths["b"]
    t = a.thickness
    x = world.positions().astype(np.float64)
    ia, ja = np.meshgrid(np.arange(24), np.arange(20), indexing="xy")
    u, v = 0.01 * ia.ravel(), 0.01 * ja.ravel()
    top = v > 0.095
    gap = t * (0.5 + 2.5 * u / u.max())
    x[a.start : a.end] = np.stack([u, np.where(top, gap, 0.0), np.where(top, 0.19 - v, v)], axis=1)
    ib, jb = np.meshgrid(np.arange(16), np.arange(16), indexing="xy")
    s, r = 0.01 * ib.ravel(), 0.01 * jb.ravel()
    x[b.start : b.end] = np.stack([0.05 + 0.7 * s + 0.7 * r, 0.5 * t + 0.02 * s, 0.7 * r - 0.7 * s + 0.05], axis=1)
    return x + 0.002 * rng.normal(size=x.shape)


def _self_collision_reference(x: np.ndarray, w: np.ndarray, cloth: np.ndarray, ij: np.ndarray, target: float):
    """Averaged-Jacobi sphere pushes over all non-excluded pairs (float64 brute force); and the pair distances."""
    d = x[:, None, :] - x[None, :, :]
    dist = np.linalg.norm(d, axis=2)
    near = (cloth[:, None] == cloth[None, :]) & (np.abs(ij[:, None, :] - ij[None, :, :]) <= 2).all(axis=2)
    touch = ~near & (dist < target) & (dist > 1e-9)
    wsum = np.where(touch, w[:, None] + w[None, :], 1.0)
    f = np.where(touch, w[:, None] / wsum * (target - dist) / np.where(touch, dist, 1.0), 0.0)
    acc = (f[:, :, None] * d).sum(axis=1)
    cnt = touch.sum(axis=1)
    return np.where((w > 0)[:, None], acc / np.maximum(cnt, 1)[:, None], 0.0), dist, near


def test_self_collision_lists_miss_no_contact():
    """Cloth self-collision over Verlet lists gives the brute-force corrections of all non-neighbour pairs:
    after moves just under half the skin (lists kept), after larger moves of a few particles (lists
    patched), of most (rebuilt) and with lists overflowing."""
    sim = Sandbox(load_level_from_string(CLOTHS_YAML, base_dir=ROOT), arch="cpu")
    world = sim.world
    solver = world.solver
    sc = solver.selfcol
    solver.begin_frame()
    w = solver.w.to_numpy().astype(np.float64)
    cloth = world.model.cloth_id.to_numpy()
    ij = world.model.grid_ij.to_numpy()
    assert (w == 0).sum() == 2 and len(np.unique(w[w > 0])) == 2
    rng = np.random.default_rng(17)

    def check(x: np.ndarray) -> np.ndarray:
        world.state.x.from_numpy(x.astype(np.float32))
        _self_refresh_k(sc)
        x32 = world.positions().astype(np.float64)
        _self_solve_k(sc)
        ref, dist, near = _self_collision_reference(x32, w, cloth, ij, sc.target)
        assert (np.abs(ref).max(axis=1) > 1e-4).sum() > 40, "too few contacts for the test to mean anything"
        np.testing.assert_allclose(world.positions() - x32, ref, atol=2e-6)
        return dist, near

    xa = _folded_cloths(rng, world)
    check(xa)
    built = sc.rebuilds[None]
    dist_a = check(xa)[0]
    assert sc.rebuilds[None] == built and sc.overflows[None] == 0

    # Each particle moves just under half the skin on top of a common shift (the mean move): the lists stay.
    step = rng.normal(size=xa.shape)
    step *= 0.46 * sc.skin / np.linalg.norm(step, axis=1, keepdims=True)
    step -= step.mean(axis=0)
    assert np.linalg.norm(step, axis=1).max() < 0.499 * sc.skin
    xb = xa + np.array([0.05, -0.03, 0.02]) + step
    dist_b, near = check(xb)
    assert (sc.rebuilds[None], sc.patches[None]) == (built, 0), "lists remade: the kept-lists case was not tested"
    closer = ~near & (dist_b < sc.target) & (dist_a >= sc.target)
    assert closer.sum() > 20, "too few pairs came into contact since the lists were built"

    # Lists made afresh here; then a few particles move more than half the skin: only their lists and
    # their partners' entries are redone (a patch), not every list.
    sc.valid[None] = 0
    check(xb)
    built = sc.rebuilds[None]
    patched = sc.patches[None]
    movers = np.array([100, 101, 250, 300, 301, 302])
    jolt = rng.normal(size=(len(movers), 3))
    xb[movers] += sc.skin * (np.array([0.0, 0.8, 0.0]) + 0.25 * jolt / np.linalg.norm(jolt, axis=1, keepdims=True))
    check(xb)
    assert (sc.rebuilds[None], sc.patches[None]) == (built, patched + 1)
    assert sc.n_dirty[None] == len(movers)

    # Patches in a row, each moving a random tenth of the particles by up to 1.5 skins and all of them by a
    # common shift of 2-4 cm (dirty pairs, dirty partners dropped and found again, references of different
    # patches): the lists still give the brute-force corrections.
    for _ in range(6):
        movers = rng.choice(len(xb), len(xb) // 10, replace=False)
        xb[movers] += 1.5 * sc.skin * rng.uniform(-1.0, 1.0, size=(len(movers), 3)) / np.sqrt(3.0)
        xb += rng.uniform(0.02, 0.04) * rng.choice([-1.0, 1.0], size=3)
        check(xb)
    assert sc.rebuilds[None] == built and sc.patches[None] >= patched + 5

    # More than half the particles move that far: all lists are rebuilt.
    movers = rng.choice(len(xb), int(0.6 * len(xb)), replace=False)
    xb[movers] += rng.normal(size=(len(movers), 3)) * sc.skin
    check(xb)
    assert sc.rebuilds[None] == built + 1

    # Cloth b crumpled into a 2 cm cube: more candidates than a list holds.
    b = world.cloths["b"]
    xb[b.start : b.end] = xb[b.start] + rng.uniform(0.0, 0.02, (b.end - b.start, 3))
    check(xb)
    assert sc.overflows[None] > 10


def _contact_pass_reference(x, w, seg, rope, rad, skip, rods=None):
    """One rope contact pass (mass splitting) in float64 NumPy, brute force over every allowed pair (no slip:
    no friction).

    ``rods``: each segment's rest length (m); a particle then moves at most
    THROW of its shortest one. Returns the positions after the pass, the
    number of contacts and, per particle, whether a pair of its segments
    lies at the contact distance within 1e-5 of it: whether that pair is a
    contact at all then turns on the last bits of float32 arithmetic (and
    Taichi's optimisations may order them differently), and a contact of
    zero depth still counts in the mass split.
    """
    from sandbox.collision.ropecollision import THROW

    s_idx, t_idx = np.meshgrid(np.arange(len(seg)), np.arange(len(seg)), indexing="ij")
    s_idx, t_idx = s_idx.ravel(), t_idx.ravel()
    ok = (s_idx != t_idx) & ((rope[s_idx] != rope[t_idx]) | (np.abs(s_idx - t_idx) >= skip[rope[s_idx]]))
    s_idx, t_idx = s_idx[ok], t_idx[ok]
    a0, a1, b0, b1 = seg[s_idx, 0], seg[s_idx, 1], seg[t_idx, 0], seg[t_idx, 1]
    u, v, c1, c2, dist = segment_segment_closest(x[a0], x[a1], x[b0], x[b1])
    target = rad[s_idx] + rad[t_idx]
    wa0, wa1 = w[a0] * (1 - u), w[a1] * u
    wsum = wa0 * (1 - u) + wa1 * u + w[b0] * (1 - v) ** 2 + w[b1] * v**2
    hit = (dist < target) & (dist > 1e-9) & (wsum > 1e-12)
    fragile_pair = np.abs(dist - target) < 1e-5 * target
    fragile = np.zeros(len(x), bool)
    for q in (a0, a1, b0, b1):
        fragile[q[fragile_pair]] = True
    a0, a1, b0, b1, u, v, c1, c2, dist, target, wa0, wa1, wsum = (
        q[hit] for q in (a0, a1, b0, b1, u, v, c1, c2, dist, target, wa0, wa1, wsum))
    count = np.zeros(len(x))
    np.add.at(count, a0, wa0 > 0)
    np.add.at(count, a1, wa1 > 0)
    # each particle weighs its mass over its count in every contact
    wsum = (wa0 * (1 - u) * count[a0] + wa1 * u * count[a1]
            + w[b0] * (1 - v) ** 2 * count[b0] + w[b1] * v**2 * count[b1])
    corr = ((target - dist) / dist / wsum)[:, None] * (c1 - c2)
    acc = np.zeros_like(x)
    np.add.at(acc, a0, wa0[:, None] * corr * (wa0 > 0)[:, None])
    np.add.at(acc, a1, wa1[:, None] * corr * (wa1 > 0)[:, None])
    if rods is not None:
        cap = np.full(len(x), np.inf)
        np.minimum.at(cap, seg[:, 0], THROW * rods)
        np.minimum.at(cap, seg[:, 1], THROW * rods)
        move = np.linalg.norm(acc, axis=1)
        over = move > cap
        acc[over] *= (cap[over] / move[over])[:, None]
    return x + acc, int(hit.sum()), fragile


def test_rope_contact_pass_matches_reference_and_conserves_momentum():
    """One contact pass on a random tangle of three ropes of different masses, against a NumPy brute force.

    Split-mass contacts push each pair equally and oppositely: the momentum sum_i m_i dx_i of the free
    particles stays zero.
    """
    text = ROPES_YAML.replace("radius: 0.015}", "radius: 0.015, mass: 0.02}").replace(
        "radius: 0.025}", "radius: 0.025, mass: 0.3}")
    sim = Sandbox(load_level_from_string(text, base_dir=ROOT), arch="cpu")
    world = sim.world
    data = world.data
    rng = np.random.default_rng(5)
    x = world.positions().astype(np.float64)
    for r in data.ropes:  # random walks in one 0.2 m box: many contacts, 1-6 per particle
        k = r.end - r.start
        steps = rng.normal(size=(k - 1, 3))
        steps *= r.rod_length / np.linalg.norm(steps, axis=1, keepdims=True)
        x[r.start: r.end] = rng.uniform(0, 0.2, 3) + np.concatenate([np.zeros((1, 3)), np.cumsum(steps, 0)])
    x32 = x.astype(np.float32)
    world.state.x.from_numpy(x32)
    world.state.x_prev.from_numpy(x32)  # no slip: the friction term is zero
    world.solver.begin_frame()
    w = world.solver.w.to_numpy().astype(np.float64)
    world.solver.ropecol.solve()
    got = world.positions().astype(np.float64)

    rad = np.array([r.radius for r in data.ropes])[data.segment_rope]
    rod = np.array([r.rod_length for r in data.ropes])
    skip = np.maximum(2, np.ceil(1.0 + 2.0 * np.array([r.radius for r in data.ropes]) / rod - 1e-9))
    rods = rod[data.segment_rope]
    want, contacts, fragile = _contact_pass_reference(x32.astype(np.float64), w, data.segments, data.segment_rope,
                                                      rad, skip, rods)
    assert contacts > 50, "too few contacts for the test to mean anything"
    # rope c (rods twice its radius) touches itself at the contact distance at every bend
    assert fragile.mean() < 0.3, "too many borderline contacts for the test to mean anything"
    moved = np.abs(want - x32).max()
    assert moved > 1e-3
    np.testing.assert_allclose(got[~fragile], want[~fragile], atol=2e-6 + 1e-4 * moved)
    # where a contact is borderline, the particle still moves by about as much as the reference says
    np.testing.assert_allclose(np.linalg.norm(got - x32, axis=1)[fragile], np.linalg.norm(want - x32, axis=1)[fragile],
                               atol=0.5 * moved)

    dx = got - x32
    momentum = np.linalg.norm((dx / w[:, None]).sum(0))
    scale = (np.linalg.norm(dx, axis=1) / w).sum()
    assert momentum < 1e-4 * scale, (momentum, scale)


LEVER = """
version: 1
name: lever
scene:
  gravity: [0, 0, 0]
  ropes:
    - {name: A, points: [[0, 0.5, 0], [0.1, 0.5, 0]], rod_length: 0.01, radius: 0.006, pins: [start, end]}
    - {name: B, points: [[X, 0.49, 0.007], [X, 0.51, 0.007]], rod_length: 0.01, radius: 0.006, pins: [0, 1, 2]}
sim: {fps: 60, substeps: 1, frames: 1}
fsm:
  - {run: Wait, with: {seconds: 1.0}}
"""


@pytest.mark.parametrize("x_cross", [0.098, 0.099])
def test_rope_contact_next_to_held_particles_moves_a_particle_at_most_a_rod(x_cross):
    """A held rope B presses 5 mm into A's last segment, whose far end is held: pushing the contact out
    through the lever (1 - u) would move A's particle 9 by pen / (1 - u), 2.5 and 5 cm; one pass moves
    it one rod, away from B, and no held particle moves."""
    from sandbox.collision.ropecollision import THROW

    w = _world(LEVER.replace("X", str(x_cross)))
    a = w.rope("A")
    x0 = w.positions().astype(np.float64)
    w.solver.begin_frame()
    w.solver.ropecol.solve()
    x1 = w.positions().astype(np.float64)
    u = (x_cross - 0.09) / 0.01
    pen = 0.012 - 0.007
    assert pen / (1.0 - u) > 2 * THROW * 0.01  # what the uncapped step would be: two rods or more
    step = x1[a.start + 9] - x0[a.start + 9]
    np.testing.assert_allclose(np.linalg.norm(step), THROW * 0.01, rtol=1e-5)
    # Away from B (its axis is 7 mm in +z; A's segment before also touches B's end, hence a little -x).
    assert step[2] < -0.95 * np.linalg.norm(step) and abs(step[1]) < 1e-6
    held = [a.start, a.end - 1] + list(range(w.rope("B").start, w.rope("B").end))
    np.testing.assert_array_equal(x1[held], x0[held])


@ti.kernel
def _contact_velocity_k(v: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                        n: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                        vs: ti.types.ndarray(dtype=ti.math.vec3, ndim=1),
                        dv: ti.types.ndarray(dtype=ti.f32, ndim=1),
                        out: ti.types.ndarray(dtype=ti.math.vec3, ndim=1)):
    for i in range(v.shape[0]):
        out[i] = friction_velocity(inelastic_velocity(v[i], n[i], vs[i]), n[i], dv[i], vs[i])


def _contact_velocity_reference(v, n, vs, dv):
    """Inelastic normal (no separation relative to the surface), then Coulomb friction on the slip (float64)."""
    rel = v - vs
    vn = np.einsum("ij,ij->i", rel, n)
    out = v - np.maximum(vn, 0.0)[:, None] * n
    rel = out - vs
    vt = rel - np.einsum("ij,ij->i", rel, n)[:, None] * n
    lt = np.linalg.norm(vt, axis=1)
    cut = np.where(lt > 1e-12, np.minimum(dv / np.maximum(lt, 1e-30), 1.0), 0.0)
    return out - cut[:, None] * vt


def test_contact_velocity_matches_numpy_reference():
    """Inelastic contact and friction on random velocities, normals and moving surfaces, against float64 NumPy."""
    rng = np.random.default_rng(7)
    m = 2000
    v = rng.normal(size=(m, 3)).astype(np.float32)
    n = rng.normal(size=(m, 3))
    n = (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(np.float32)
    vs = (0.5 * rng.normal(size=(m, 3))).astype(np.float32)
    dv = rng.uniform(0.0, 1.5, size=m).astype(np.float32)
    out = np.zeros((m, 3), np.float32)
    _contact_velocity_k(v, n, vs, dv, out)
    ref = _contact_velocity_reference(*(a.astype(np.float64) for a in (v, n, vs, dv)))
    np.testing.assert_allclose(out, ref, atol=2e-6)
    # Invariants: nothing leaves the surface; the slip never grows and never reverses.
    rel = out.astype(np.float64) - vs
    assert (np.einsum("ij,ij->i", rel, n) <= 1e-6).all()
    slip_before = (v - vs) - np.einsum("ij,ij->i", v - vs, n)[:, None] * n
    slip_after = rel - np.einsum("ij,ij->i", rel, n)[:, None] * n
    assert (np.einsum("ij,ij->i", slip_after, slip_before) >= -1e-6).all()
    assert (np.linalg.norm(slip_after, axis=1) <= np.linalg.norm(slip_before, axis=1) + 1e-6).all()
