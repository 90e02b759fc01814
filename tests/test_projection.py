"""Reference rope projection (paper §4.3, Eq. 2-8): closed forms, invariants and oracles."""

import numpy as np
import pytest
import scipy.sparse as sp

from sandbox.collision.capsule_np import segment_segment_closest
from sandbox.solvers.projection import (ProjectionParams, ProjectionRopeSolver, RopeProjection,
                                        RopeSystem, kkt_matrix, project, solve_kkt)
from sandbox.solvers.projection_rows import (bend_rows, broad_phase_pairs, capsule_rows,
                                             stretch_rows)

R, RAD = 0.02, 0.008  # rod length and rope radius (m)


def _line(start, direction, n, r=R):
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    return np.asarray(start, float) + np.arange(n)[:, None] * r * d


def _crossing(n=60, gap=0.005, shift=0.0):
    """Rope A along x, rope B along z crossing it ``gap`` above at particle n // 2 (+ shift, m)."""
    s0 = -(n // 2) * R
    xa = _line([s0 + shift, 0.1, 0.0], [1, 0, 0], n)
    xb = _line([0.0, 0.1 + gap, s0 + 0.37 * shift], [0, 0, 1], n)
    return RopeSystem(np.concatenate([xa, xb]), [(0, n), (n, 2 * n)], [R, R], [RAD, RAD])


def _min_clearance(system, x):
    """Brute force: min over all non-adjacent segment pairs of D - (r_i + r_j) (m)."""
    segs, rope = [], []
    for k, (a, b) in enumerate(system.rope_ranges):
        segs += [(i, i + 1) for i in range(a, b - 1)]
        rope += [k] * (b - a - 1)
    segs, rope = np.array(segs), np.array(rope)
    i, j = np.triu_indices(len(segs), 1)
    keep = (rope[i] != rope[j]) | (np.abs(i - j) >= 2)
    i, j = i[keep], j[keep]
    d = segment_segment_closest(x[segs[i, 0]], x[segs[i, 1]], x[segs[j, 0]], x[segs[j, 1]])[4]
    return np.min(d - system.radius[rope[i]] - system.radius[rope[j]])


def test_stretched_two_rod_chain_returns_to_rod_length():
    """A 3-particle chain stretched by 10% returns to rod length r after 3 Gauss-Newton steps."""
    x = _line([0, 0, 0], [1, 0.3, 0.2], 3, r=1.1 * R)
    sysm = RopeSystem(x, [(0, 3)], [R], [RAD])
    # Stretch only: the uniform-stretch mode of J_e J_e^T has eigenvalue 4 l^2 >= 4 r^2 and
    # a >= 1, so each step scales C_e by at most 1 / (1 + 4) (plus a second-order term).
    for k in (1, 3):
        _, rep = project(sysm, params=ProjectionParams(iterations=k, b=0.0))
        assert rep.max_stretch < 0.1 / 5 ** k
    # Paper weights: the bending row (Eq. 3) pulls the same way, b = 2000 makes it converge fast.
    x3, rep3 = project(sysm, params=ProjectionParams(iterations=3))
    assert rep3.max_stretch < 1e-9
    np.testing.assert_allclose(x3.mean(axis=0), x.mean(axis=0), atol=1e-12)  # symmetric pull


def _arc(n, angle):
    """n particles on a circular arc with chords R, turning by ``angle`` (rad) per joint."""
    heading = np.arange(n - 1) * angle
    steps = R * np.stack([np.cos(heading), np.sin(heading), 0 * heading], axis=1)
    return np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])


def test_bend_residual_scales_as_one_over_one_plus_2b():
    """Stretch off, middle pinned: one step maps C_b to C_b / (1 + 2 b) exactly (Eq. 3)."""
    x = np.array([[-R, 0.3 * R, 0], [0, 0, 0], [R, 0.3 * R, 0]])
    pinned = np.array([False, True, False])
    c0 = np.linalg.norm(x[2] - x[0]) - 2 * R
    for b in (1.0, 10.0, 2000.0):
        sysm = RopeSystem(x, [(0, 3)], [R], [RAD], pinned)
        xn, rep = project(sysm, params=ProjectionParams(iterations=1, a_scale=0.0, b=b))
        c1 = np.linalg.norm(xn[2] - xn[0]) - 2 * R
        assert c1 == pytest.approx(c0 / (1 + 2 * b), rel=1e-9)


def test_bent_chain_straightens_with_default_weights():
    """An arc bent by 20 deg per joint loses >= 95% of its bend residual in one step, rods kept."""
    sysm = RopeSystem(_arc(12, np.radians(20.0)), [(0, 12)], [R], [RAD])
    before = RopeProjection(sysm).residuals(sysm.x).max_bend
    assert before > 1e-4
    _, rep = project(sysm, params=ProjectionParams(iterations=1))
    assert rep.max_bend < 0.05 * before and rep.max_stretch < 0.05


@pytest.mark.parametrize("shift", [0.0, 0.0073])
def test_crossing_ropes_are_separated(shift):
    """Interpenetrating crossing ropes end with capsule distance >= r_i + r_j - 1e-6 m."""
    sysm = _crossing(shift=shift)
    assert _min_clearance(sysm, sysm.x) < -0.01
    xn, rep = project(sysm, params=ProjectionParams(iterations=2))
    assert _min_clearance(sysm, xn) >= -1e-6
    assert rep.max_penetration <= 1e-6 and rep.n_active >= 1
    # Without the contact-only polish, the linearised rows still remove >= 90% of the overlap.
    xl, _ = project(sysm, params=ProjectionParams(iterations=2, contact_polish=0))
    assert _min_clearance(sysm, xl) > -0.001


def _figure_eight(n_dense=4000, scale=0.15, lift=0.003):
    """Rope along a Gerono lemniscate crossing itself at the origin, lobes ``2 lift`` apart in y."""
    u = np.linspace(0.3, 2 * np.pi - 0.3, n_dense)
    dense = np.stack([scale * np.cos(u), 0.1 + lift * (u - np.pi) / (np.pi / 2),
                      scale * np.sin(u) * np.cos(u)], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    s_k = np.arange(0.0, arc[-1], R)
    return np.stack([np.interp(s_k, arc, dense[:, c]) for c in range(3)], axis=1)


def test_self_collision_separates_a_rope_crossing_itself():
    """A rope whose two lobes interpenetrate at its self-crossing ends separated (|i - j| >= 2)."""
    x = _figure_eight()
    sysm = RopeSystem(x, [(0, len(x))], [R], [RAD])
    assert _min_clearance(sysm, x) < -0.005
    xn, rep = project(sysm, params=ProjectionParams(iterations=2))
    assert _min_clearance(sysm, xn) >= -1e-6 and rep.n_active >= 1


def test_straight_rope_at_rest_stays_put():
    """A straight rope at rod length does not move (adjacent capsules are skipped)."""
    sysm = RopeSystem(_line([0, 0.1, 0], [1, 0, 0], 30), [(0, 30)], [R], [RAD])
    xn, rep = project(sysm)
    np.testing.assert_allclose(xn, sysm.x, atol=1e-15)
    assert rep.n_active == 0 and rep.n_candidates > 0       # gap-2 pairs are 4 mm apart


def test_broad_phase_finds_every_close_pair():
    """cKDTree candidates contain every brute-force segment pair closer than the margin."""
    rng = np.random.default_rng(2)
    steps = rng.normal(size=(3, 40, 3))
    ropes = [np.cumsum(R * st / np.linalg.norm(st, axis=1, keepdims=True), axis=0) * 0.3
             + 0.01 * k for k, st in enumerate(steps)]
    sysm = RopeSystem(np.concatenate(ropes), [(0, 40), (40, 80), (80, 120)], [0.3 * R] * 3,
                      [0.002, 0.003, 0.004])
    proj = RopeProjection(sysm)
    topo, margin = proj.topology, 0.002
    found = {tuple(p) for p in broad_phase_pairs(sysm.x, topo, sysm.radius, margin)}
    i, j = np.triu_indices(len(topo.rods), 1)
    same = topo.rod_rope[i] == topo.rod_rope[j]
    gap = np.abs(topo.seg_local[i] - topo.seg_local[j])
    keep = ~same | (gap >= topo.self_gap[topo.rod_rope[i]])
    i, j = i[keep], j[keep]
    x = sysm.x
    d = segment_segment_closest(x[topo.rods[i, 0]], x[topo.rods[i, 1]],
                                x[topo.rods[j, 0]], x[topo.rods[j, 1]])[4]
    close = d - sysm.radius[topo.rod_rope[i]] - sysm.radius[topo.rod_rope[j]] < margin
    assert close.sum() > 20
    assert {(a, b) for a, b in zip(i[close], j[close])} <= found
    assert len(found) < 0.5 * len(i)                          # culling, not all pairs


def test_pinned_particles_do_not_move():
    """Pinned particles keep their exact positions under stretch, collision and targets."""
    sysm = _crossing(n=20, gap=0.0)
    sysm.pinned[[0, 10, 19, 20, 39]] = True
    sysm.x[5] += (0.0, 0.01, 0.0)
    targets = [(10, sysm.x[10] + 0.05), (25, sysm.x[25] + (0.0, 0.02, 0.0))]
    xn, _ = project(sysm, targets, params=ProjectionParams(iterations=3), ground_height=0.095)
    np.testing.assert_array_equal(xn[sysm.pinned], sysm.x[sysm.pinned])
    assert np.abs(xn[~sysm.pinned] - sysm.x[~sysm.pinned]).max() > 1e-3


def test_kinematic_target_reached_within_one_over_one_plus_c():
    """A perpendicular target pull d leaves exactly d / (1 + c) after one step (Eq. 4, c = 3000)."""
    x = _line([0, 0.5, 0], [1, 0, 0], 10)
    d = np.array([0.0, 0.0, 0.004])
    sysm = RopeSystem(x, [(0, 10)], [R], [RAD])
    x1, rep1 = project(sysm, [(9, x[9] + d)], ProjectionParams(iterations=1))
    # J_e d = J_b d = 0 for a straight chain, so (1 + c) dp_c = c d and the rest stays put.
    assert rep1.max_target_error == pytest.approx(np.linalg.norm(d) / 3001, rel=1e-9)
    np.testing.assert_allclose(x1[:9], x[:9], atol=1e-15)
    _, rep3 = project(sysm, [(9, x[9] + d)], ProjectionParams(iterations=3))
    assert rep3.max_target_error <= np.linalg.norm(d) / 3001
    single = RopeSystem(np.zeros((1, 3)), [(0, 1)], [R], [RAD])
    _, rep = project(single, [(0, np.array([0.0, 0.03, 0.0]))], ProjectionParams(iterations=2))
    assert rep.max_target_error == pytest.approx(0.03 / 3001 ** 2, rel=1e-6)


def test_active_set_adds_predicted_contact_and_releases_pulling_row():
    """A target pushing rope A into B creates a contact row; pulling A away activates none."""
    sysm = _crossing(n=30, gap=0.018)                         # 2 mm clearance, within the margin
    mid = 15
    down_push = [(30 + mid, sysm.x[30 + mid] - (0.0, 0.01, 0.0))]
    xn, rep = project(sysm, down_push, ProjectionParams(iterations=2))
    assert rep.n_active >= 1 and _min_clearance(sysm, xn) >= -1e-6
    up_pull = [(30 + mid, sysm.x[30 + mid] + (0.0, 0.01, 0.0))]
    xu, rep_u = project(sysm, up_pull, ProjectionParams(iterations=2))
    assert rep_u.n_active == 0 and rep_u.max_target_error < 0.01 * 1e-3


def test_active_set_releases_row_that_would_pull():
    """A row added by prediction that would pull is released: only the ground row stays."""
    s_, rho, c = 0.01, 0.005, 3000.0
    p0 = np.array([0.0, 0.1, 0.0])
    n = np.array([1.0, 0.5, 0.0]) / np.hypot(1.0, 0.5)        # plane row: x + y / 2 >= -1.3 s_

    def plane(p):
        return (p - p0) @ n + 1.3 * s_ / np.hypot(1.0, 0.5) + rho, np.tile(n, (len(p), 1))

    single = RopeSystem(p0[None], [(0, 1)], [R], [rho])
    target = p0 + np.array([-1.0, -1.0, 0.0]) * s_ * (1 + c) / c   # unconstrained step (-s_, -s_)
    params = ProjectionParams(iterations=1, contact_polish=0, collision_margin=0.05)
    ground = p0[1] - rho - 0.5 * s_
    xn, rep = project(single, [(0, target)], params, ground_height=ground, sdf=plane)
    # Both rows are violated by the free step; at their vertex (-1.05 s_, -0.5 s_) the plane row
    # pulls, so it is dropped and the answer is the projection onto the ground row alone.
    # (the regularisation d = 1e-10 shifts the contact by d lam ~ 1e-9 m here)
    np.testing.assert_allclose(xn[0] - p0, [-s_, -0.5 * s_, 0.0], atol=1e-8)
    assert rep.n_active == 1 and rep.active_rounds == 3


def test_ground_and_object_contacts():
    """Particles below the ground or inside a sphere SDF end at d >= radius."""
    x = _line([-0.2, 0.004, 0.0], [1, 0, 0], 20)
    x[:, 1] -= 0.01 * np.sin(np.linspace(0, np.pi, 20))
    sysm = RopeSystem(x, [(0, 20)], [R], [RAD])
    xn, rep = project(sysm, params=ProjectionParams(iterations=2), ground_height=0.0)
    assert xn[:, 1].min() >= RAD - 1e-9 and rep.max_penetration <= 1e-9
    centre, rs = np.array([0.0, -0.05, 0.0]), 0.06

    def sphere(p):
        v = p - centre
        n = np.linalg.norm(v, axis=1)
        return n - rs, v / n[:, None]

    xs, _ = project(sysm, params=ProjectionParams(iterations=2), sdf=sphere)
    assert np.linalg.norm(xs - centre, axis=1).min() >= rs + RAD - 1e-9


def test_constraint_jacobians_match_finite_differences():
    """Stretch, bend and capsule rows (Eq. 2, 3, 5) have the Jacobians of their values."""
    rng = np.random.default_rng(1)
    sysm = _crossing(n=8, gap=0.004)
    x0 = sysm.x + rng.normal(scale=0.002, size=sysm.x.shape)
    proj = RopeProjection(sysm)
    topo, r = proj.topology, sysm.rest_length
    pairs = broad_phase_pairs(x0, topo, sysm.radius, 0.01)
    fns = [lambda x: stretch_rows(x, topo, r), lambda x: bend_rows(x, topo, r),
           lambda x: capsule_rows(x, topo, sysm.radius, pairs)]
    for fn in fns:
        rows = fn(x0)
        assert len(rows)
        dense = np.zeros((len(rows), x0.size))
        for k in range(rows.idx.shape[1]):
            for c in range(3):
                np.add.at(dense, (np.arange(len(rows)), 3 * rows.idx[:, k] + c), rows.coef[:, k, c])
        h = 1e-7
        for j in range(x0.size):
            e = np.zeros(x0.size)
            e[j] = h
            fd = (fn(x0 + e.reshape(-1, 3)).value - fn(x0 - e.reshape(-1, 3)).value) / (2 * h)
            np.testing.assert_allclose(dense[:, j], fd, atol=1e-6)


def _random_linearisation():
    """A noisy, feasible two-rope system with pins, contacts, ground and a target."""
    rng = np.random.default_rng(7)
    sysm = _crossing(n=9, gap=0.002)
    sysm.x += rng.normal(scale=0.003, size=sysm.x.shape)
    sysm.pinned[[0, 12]] = True
    proj = RopeProjection(sysm, ProjectionParams(iterations=1), ground_height=0.085)
    xs = sysm.x / proj.scale
    return proj, xs, [(4, (sysm.x[4] + 0.01) / proj.scale)]


def test_sparse_kkt_matches_dense_oracle():
    """splu, spsolve and dense numpy.linalg.solve of Eq. 8 give the same dp on a random system."""
    proj, xs, tg = _random_linearisation()
    dps = {}
    for method in ("dense", "splu", "spsolve"):
        proj.params = ProjectionParams(linear_solver=method)
        dps[method] = proj.iterate(xs, tg)
    assert np.abs(dps["dense"]).max() > 1e-3
    np.testing.assert_allclose(dps["splu"], dps["dense"], atol=1e-10)
    np.testing.assert_allclose(dps["spsolve"], dps["dense"], atol=1e-10)


def test_solution_satisfies_kkt_conditions():
    """dp is stationary for Eq. 6 with the paper's weights and meets J_c dp = -C_c (Eq. 7-8)."""
    proj, xs, tg = _random_linearisation()
    dp = proj.iterate(xs, tg)
    lin = proj.linearise(xs, tg)
    contacts, lam = proj.last_contacts, proj.last_multipliers
    assert len(contacts) >= 2
    assert np.all(lam[contacts.value >= 0] <= 0)              # rows added by prediction push
    n_e = len(proj.topology.rods)
    n_b = len(proj.topology.bends)
    a = np.exp(10.0 * np.abs(lin.soft.value[:n_e]))
    w = np.concatenate([a, np.full(n_b, 2000.0), np.full(len(lin.soft) - n_e - n_b, 3000.0)])
    # Gradient of 1/2|dp|^2 + 1/2 sum w (J dp + C)^2 + lam^T (J_c dp + C_c), scattered row by row.
    grad = dp.copy()
    for rows, coeff in ((lin.soft, w * (lin.soft.apply(dp) + lin.soft.value)), (contacts, lam)):
        for k in range(rows.idx.shape[1]):
            np.add.at(grad, rows.idx[:, k], coeff[:, None] * rows.coef[:, k])
    free = ~proj.system.pinned
    np.testing.assert_allclose(grad[free], 0.0, atol=1e-8)
    np.testing.assert_array_equal(dp[~free], 0.0)
    reg = proj.params.regularization
    np.testing.assert_allclose(contacts.apply(dp), -contacts.value + reg * lam, atol=1e-12)
    assert np.all(lin.hard.apply(dp) + lin.hard.value >= -1e-8)   # no candidate left violated
    H, Jc = sp.identity(4, format="csr"), sp.csr_matrix(np.ones((1, 4)))
    K = kkt_matrix(H, Jc, reg).toarray()
    np.testing.assert_allclose(K, [[1, 0, 0, 0, 1], [0, 1, 0, 0, 1], [0, 0, 1, 0, 1],
                                   [0, 0, 0, 1, 1], [1, 1, 1, 1, -reg]])
    dp4, lam4 = solve_kkt(H, np.zeros(4), Jc, np.array([2.0]), regularization=0.0)
    np.testing.assert_allclose(dp4, 0.5)                       # min |dp|^2 s.t. sum dp = 2
    assert lam4[0] == pytest.approx(-0.5)


def test_hanging_rope_pendulum():
    """A rope released at 20 deg: strain < 1%, no energy gain, compound-pendulum half period."""
    n, r = 21, 0.05
    th = np.radians(20.0)
    axis = np.array([np.sin(th), -np.cos(th), 0.0])
    x = np.array([0.0, 1.5, 0.0]) + np.arange(n)[:, None] * r * axis
    pinned = np.zeros(n, bool)
    pinned[0] = True
    solver = ProjectionRopeSolver(RopeSystem(x, [(0, n)], [r], [0.01], pinned),
                                  ProjectionParams(iterations=2))
    v, dt = np.zeros_like(x), 1.0 / 60.0
    energy, com_x, strain = [], [], []
    for _ in range(110):
        x, v = solver.step(x, v, dt)
        energy.append(0.5 * (v ** 2).sum() + 9.81 * x[:, 1].sum())     # unit masses (J/kg)
        com_x.append(x[1:, 0].mean())
        strain.append(solver.last_report.max_stretch)
    assert max(strain) < 0.01 and x[0] == pytest.approx([0.0, 1.5, 0.0], abs=0)
    assert np.diff(energy).max() <= 1e-9                                 # projection dissipates
    # Compound pendulum of point masses at k r: omega^2 = g sum k / (r sum k^2).
    k = np.arange(1, n)
    half_period = np.pi / np.sqrt(9.81 * k.sum() / (r * (k ** 2).sum()))
    sign = np.sign(com_x)
    crossings = (np.flatnonzero(sign[1:] != sign[:-1]) + 1) * dt
    assert len(crossings) >= 2
    assert np.diff(crossings)[0] == pytest.approx(half_period, rel=0.05)


def test_invalid_linear_solver_lists_allowed_values():
    """An unknown linear solver is rejected with the allowed values."""
    with pytest.raises(ValueError, match="splu"):
        ProjectionParams(linear_solver="cholesky")
