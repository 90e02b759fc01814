"""The joint row-and-column cloth step (cloth_joint.py) against a SciPy reference, and its invariants."""

import functools

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spl

from sandbox.solvers.cloth_joint import THROW
from tests.levelkit import random_contacts, solver_masses, world_from_text

NX, NZ = 14, 11
SHEET = f"""
version: 1
name: sheet
scene:
  gravity: [0, 0, 0]
  ground: {{height: -10.0}}
  cloths:
    - {{name: sheet, resolution: [{NX}, {NZ}], size: [0.26, 0.2], center: [0, 1, 0], self_collision: false,
        pins: [[0, 0]]}}
sim: {{cloth_joint: ITER}}
fsm:
  - {{run: Wait}}
success:
  - {{metric: fsm_state, equals: success}}
"""


@functools.cache
def _sheet(iterations: int):
    """One world per CG iteration count for the whole module (``_prepare`` resets what a test sets)."""
    return world_from_text(SHEET.replace("ITER", str(iterations)))


def _chains() -> list[np.ndarray]:
    """Rows, then columns, as the joint step orders its links."""
    idx = np.arange(NX * NZ).reshape(NZ, NX)
    return [idx[j] for j in range(NZ)] + [idx[:, i] for i in range(NX)]


def joint_step_reference(x, w, rest, touching, normal, iterations=None, lam0=None):
    """One Newton step of all rows and columns together (float64); returns positions and multipliers.

    Links in chain order; J_j = (-n_j at a, +n_j at b); W_i = w_i (I - n n^T) in
    contact, w_i I otherwise; A = J W J^T + diag(1e-6 (w_a + w_b)), rows whose
    diagonal is at most 1e-9 (w_a + w_b) left out; A lam = -C solved by CG
    preconditioned with A's tridiagonal blocks (one per chain), from lam0 (the
    last step's multipliers; zero if None), for ``iterations`` iterations
    (None: exactly, by a sparse direct solve);
    dx = W J^T lam, scaled back as a whole to at most THROW of a rod.
    """
    chains = _chains()
    a = np.concatenate([c[:-1] for c in chains])
    b = np.concatenate([c[1:] for c in chains])
    chain_of = np.concatenate([np.full(len(c) - 1, k) for k, c in enumerate(chains)])
    m, n = len(a), len(x)
    d = x[b] - x[a]
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    C = length - rest
    P = w[:, None, None] * np.repeat(np.eye(3)[None], n, axis=0)
    P[touching] -= w[touching, None, None] * np.einsum("ki,kj->kij", normal[touching], normal[touching])
    cols = np.concatenate([3 * a[:, None] + np.arange(3), 3 * b[:, None] + np.arange(3)], axis=1).ravel()
    J = sp.csr_matrix((np.concatenate([-u, u], axis=1).ravel(), (np.repeat(np.arange(m), 6), cols)), shape=(m, 3 * n))
    Wm = sp.bsr_matrix((P, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n))
    A = (J @ Wm @ J.T).tocsr() + sp.diags(1e-6 * (w[a] + w[b]))
    live = A.diagonal() > 1e-9 * (w[a] + w[b] + 1e-30)
    A = A[live][:, live]
    rhs = -C[live]
    if iterations is None:
        lam_live = spl.spsolve(A.tocsc(), rhs)
    else:
        same = chain_of[live][:, None] == chain_of[live][None, :]
        band = np.abs(np.arange(live.sum())[:, None] - np.arange(live.sum())[None, :]) <= 1
        M = sp.csr_matrix(np.where(same & band, A.toarray(), 0.0))
        lam_live = np.zeros(len(rhs)) if lam0 is None else lam0[live].copy()
        r = rhs - A @ lam_live
        z = spl.spsolve(M.tocsc(), r)
        p = z.copy()
        rz = r @ z
        for _ in range(iterations):
            ap = A @ p
            alpha = rz / (p @ ap)
            lam_live += alpha * p
            r -= alpha * ap
            z = spl.spsolve(M.tocsc(), r)
            rz, rz_old = r @ z, rz
            p = z + rz / rz_old * p
    lam = np.zeros(m)
    lam[live] = lam_live
    dx = (Wm @ (J.T @ lam)).reshape(n, 3)
    limit = THROW * rest.min()
    biggest = np.linalg.norm(dx, axis=1).max()
    if biggest > limit:
        dx *= limit / biggest
    return x + dx, lam


def _stretched_frame(w, noise=0.004):
    """Start a frame of ``w``, not its first (the joint step sits that one out), with every edge of the sheet
    off its length."""
    x0 = w.model.data.x0
    w.state.x.from_numpy((x0 + np.random.default_rng(5).normal(scale=noise, size=x0.shape)).astype(np.float32))
    if w.solver.frames_begun == 0:
        w.solver.begin_frame()
    w.solver.begin_frame()


def _prepare(w, rng, noise=0.004, contacts=True, lift=None):
    """A sheet with every edge off its length (noise m), the solver's masses and some contacts set, each
    touching particle on its surface (its contact plane through it) or, with ``lift`` (n,) m, that far off
    it along its normal."""
    solver = w.solver
    solver.forget()
    x0 = w.model.data.x0.astype(np.float64)
    x = x0 + rng.normal(scale=noise, size=x0.shape)
    w.state.x.from_numpy(x.astype(np.float32))
    inv_mass = solver_masses(w)
    touching, normal = random_contacts(rng, len(x), 0.25 if contacts else 0.0)
    solver.contacts.hit.from_numpy(touching.astype(np.float32))
    solver.contacts.normal.from_numpy(normal.astype(np.float32))
    x32 = x.astype(np.float32).astype(np.float64)
    _on_surface(w, x32, normal)
    if lift is not None:
        solver.contacts.plane.from_numpy((solver.contacts.plane.to_numpy() - lift).astype(np.float32))
    rest = np.full(sum(len(c) - 1 for c in _chains()), 0.0)
    rest[: NZ * (NX - 1)] = 0.26 / (NX - 1)
    rest[NZ * (NX - 1):] = 0.2 / (NZ - 1)
    return x32, inv_mass, rest, touching, normal


def _on_surface(w, x, normal):
    """Contact planes through the particles at ``x`` (as if the contacts had just pushed them there)."""
    w.solver.contacts.plane.from_numpy(np.einsum("ij,ij->i", x, normal).astype(np.float32))


def _strain(x, rest):
    chains = _chains()
    a = np.concatenate([c[:-1] for c in chains])
    b = np.concatenate([c[1:] for c in chains])
    return np.linalg.norm(x[b] - x[a], axis=1) / rest - 1.0


def test_joint_step_matches_the_scipy_reference():
    """Three PCG iterations in Taichi give the float64 reference's step, contacts and a pin included."""
    w = _sheet(3)
    x, inv_mass, rest, touching, normal = _prepare(w, np.random.default_rng(7))
    expect = joint_step_reference(x, inv_mass, rest, touching, normal, iterations=3)[0]
    w.solver.joint.joint()
    got = w.positions().astype(np.float64)
    assert np.abs(got - x).max() > 1e-3  # the step moved the particles
    np.testing.assert_allclose(got, expect, atol=3e-6)
    # Not yet the exact Newton step, which the reference reaches with a direct solve.
    exact = joint_step_reference(x, inv_mass, rest, touching, normal)[0]
    assert np.abs(exact - expect).max() > 1e-5


def test_a_particle_that_has_left_its_surface_is_free_in_the_step():
    """A particle that touched a surface in the substep but has since moved off it along the normal by more
    than LIFT of its radius is not held to the surface's tangent plane: the step is the reference's with
    those particles free; one lifted by less stays held."""
    from sandbox.solvers.cloth_joint import LIFT

    w = _sheet(3)
    radius = float(w.model.data.radius[0])
    rng = np.random.default_rng(7)
    lift = np.where(rng.random(NX * NZ) < 0.5, 2.0 * LIFT * radius, 0.5 * LIFT * radius)
    x, inv_mass, rest, touching, normal = _prepare(w, np.random.default_rng(7), lift=lift)
    held = touching & (lift < LIFT * radius)
    assert 0 < held.sum() < touching.sum()
    expect = joint_step_reference(x, inv_mass, rest, held, normal, iterations=3)[0]
    w.solver.joint.joint()
    got = w.positions().astype(np.float64)
    np.testing.assert_allclose(got, expect, atol=3e-6)
    all_held = joint_step_reference(x, inv_mass, rest, touching, normal, iterations=3)[0]
    assert np.abs(all_held - expect).max() > 1e-4  # the lifted particles make a difference


def test_a_particle_the_chain_step_peeled_is_free_in_the_step_and_its_flags_are_only_read():
    """Particles on their surface but peeled by the chain step are free in the step (the reference with
    them free), and the step leaves the chain step's flags as they were."""
    w = _sheet(3)
    x, inv_mass, rest, touching, normal = _prepare(w, np.random.default_rng(9))
    peel = touching & (np.random.default_rng(10).random(NX * NZ) < 0.5)
    assert 0 < peel.sum() < touching.sum()
    w.solver.inext.peeled.from_numpy(peel.astype(np.int32))
    expect = joint_step_reference(x, inv_mass, rest, touching & ~peel, normal, iterations=3)[0]
    w.solver.joint.joint()
    np.testing.assert_allclose(w.positions().astype(np.float64), expect, atol=3e-6)
    np.testing.assert_array_equal(w.solver.inext.peeled.to_numpy(), peel.astype(np.int32))
    w.solver.inext.peeled.fill(0)


def test_the_solver_launches_the_step_as_begin_one_cg_kernel_per_iteration_and_end():
    """The solver runs the joint pass as its begin, one kernel launched once per CG iteration, and its
    end: the same kernel object each time (compiled once, not unrolled), and the same step as
    ``joint()`` and as the SciPy reference."""
    from sandbox.solvers import xpbd

    w = _sheet(3)
    s = w.solver
    runs = s._runs((xpbd.JOINT,))
    assert runs == [(xpbd.JOINT_BEGIN,)] + [(xpbd.JOINT_CG,)] * 3 + [(xpbd.JOINT_END,)]
    parts = s._split((xpbd.JOINT,))
    assert parts[1] is parts[2] is parts[3] and len({id(p) for p in parts}) == 3
    x, inv_mass, rest, touching, normal = _prepare(w, np.random.default_rng(7))
    s._run_k((xpbd.JOINT,), 1.0 / 600, 1.0, -10.0, 0.0)
    got = w.positions().astype(np.float64)
    expect = joint_step_reference(x, inv_mass, rest, touching, normal, iterations=3)[0]
    np.testing.assert_allclose(got, expect, atol=3e-6)


def test_joint_step_converges_to_the_exact_newton_step():
    """More PCG iterations approach the exact Newton step of all rows and columns together (here 16
    leave 0.4 % of the step); the pin stays and particles in contact move only along their surface."""
    w = _sheet(16)
    x, inv_mass, rest, touching, normal = _prepare(w, np.random.default_rng(8))
    exact = joint_step_reference(x, inv_mass, rest, touching, normal)[0]
    w.solver.joint.joint()
    got = w.positions().astype(np.float64)
    np.testing.assert_allclose(got, joint_step_reference(x, inv_mass, rest, touching, normal, iterations=16)[0],
                               atol=2e-6)
    step = np.abs(exact - x).max()
    assert np.abs(got - exact).max() < 5e-3 * step
    assert np.abs(joint_step_reference(x, inv_mass, rest, touching, normal, iterations=4)[0] - exact).max() > 0.1 * step
    assert (got[inv_mass == 0] == x[inv_mass == 0]).all()
    along = np.einsum("ij,ij->i", got - x, normal)[touching]
    assert np.abs(along).max() < 1e-6


def test_repeated_joint_steps_bring_every_edge_to_its_length():
    """Newton steps from edges up to ~70 % off bring every edge within 1e-5 in six steps, each step
    better than the last; repeating from the same state is bitwise the same."""
    w = _sheet(16)
    rng = np.random.default_rng(9)
    x, inv_mass, rest, *_ = _prepare(w, rng, noise=0.003, contacts=False)
    worst = [np.abs(_strain(x, rest)).max()]
    assert worst[0] > 0.3
    for _ in range(6):
        w.solver.joint.joint()
        worst.append(np.abs(_strain(w.positions().astype(np.float64), rest)).max())
    assert worst[-1] < 1e-5, worst
    assert all(b < a for a, b in zip(worst, worst[1:])), worst
    end = w.positions()
    w.state.x.from_numpy(x.astype(np.float32))
    w.solver.forget()
    for _ in range(6):
        w.solver.joint.joint()
    np.testing.assert_array_equal(w.positions(), end)


def test_a_step_that_would_throw_a_particle_is_scaled_back():
    """A sheet crumpled far beyond linearisation: no particle moves by more than THROW of a rod."""
    w = _sheet(16)
    x, inv_mass, rest, touching, normal = _prepare(w, np.random.default_rng(10), noise=0.03, contacts=False)
    w.solver.joint.joint()
    moved = np.linalg.norm(w.positions().astype(np.float64) - x, axis=1)
    assert moved.max() <= THROW * rest.min() * (1 + 1e-5)
    assert moved.max() > 0.9 * THROW * rest.min()


def test_a_step_starts_from_the_last_steps_multipliers():
    """The second step is warm-started from WARM_START of the first one's multipliers (as the reference
    with lam0 so scaled, not with the whole of them); after ``forget`` a step starts cold again."""
    from sandbox.solvers.cloth_joint import WARM_START

    w = _sheet(3)
    rng = np.random.default_rng(11)
    x, inv_mass, rest, touching, normal = _prepare(w, rng)
    first, lam = joint_step_reference(x, inv_mass, rest, touching, normal, iterations=3)
    w.solver.joint.joint()
    np.testing.assert_allclose(w.positions(), first, atol=3e-6)
    np.testing.assert_allclose(w.solver.joint.lam.to_numpy(), lam, atol=1e-7)
    moved = (first + rng.normal(scale=0.002, size=first.shape)).astype(np.float32)
    w.state.x.from_numpy(moved)
    moved = moved.astype(np.float64)
    _on_surface(w, moved, normal)
    warm = joint_step_reference(moved, inv_mass, rest, touching, normal, iterations=3, lam0=WARM_START * lam)[0]
    whole = joint_step_reference(moved, inv_mass, rest, touching, normal, iterations=3, lam0=lam)[0]
    cold = joint_step_reference(moved, inv_mass, rest, touching, normal, iterations=3)[0]
    assert 0.0 < WARM_START < 1.0
    assert np.abs(warm - cold).max() > 1e-4 and np.abs(warm - whole).max() > 2e-5
    w.solver.joint.joint()
    np.testing.assert_allclose(w.positions(), warm, atol=3e-6)
    w.state.x.from_numpy(moved.astype(np.float32))
    w.solver.forget()
    w.solver.joint.joint()
    np.testing.assert_allclose(w.positions(), cold, atol=3e-6)


def test_joint_step_runs_on_every_kth_substep_and_the_last():
    """``sim.cloth_joint_every: 3`` over 5 substeps: the joint step on substeps 0, 3 and 4 only; a
    substep without it keeps every other pass in the same order; ``cloth_joint: 0`` builds no step."""
    from sandbox.solvers.xpbd import JOINT

    w = world_from_text(SHEET.replace("ITER", "2, cloth_joint_every: 3, substeps: 5"))
    s = w.solver
    _stretched_frame(w)
    runs = [JOINT in s.variants[s._skips(k, 5)][0] for k in range(5)]
    assert runs == [True, False, False, True, True]
    full, lite = s.variants[False, False][0], s.variants[False, True][0]
    assert full.count(JOINT) == 1 and tuple(x for x in full if x != JOINT) == lite
    assert world_from_text(SHEET.replace("ITER", "0")).solver.joint is None


def test_each_call_of_a_substep_starts_from_the_same_call_of_the_last_substep():
    """With two solver iterations the step runs twice per substep: the first call meets a substep's
    whole stretch, the second what the passes between left. Each starts from WARM_START of the
    multipliers of the same call one substep earlier, not of the call just before it."""
    from sandbox.solvers.cloth_joint import WARM_START

    w = world_from_text(SHEET.replace("ITER", "3, iterations: 2"))
    j = w.solver.joint
    assert j.slots == 2
    rng = np.random.default_rng(5)
    x, inv_mass, rest, touching, normal = _prepare(w, rng)
    lams = []
    for k in range(2):  # one substep: both calls cold
        if k:
            x = (w.positions() + rng.normal(scale=0.001, size=x.shape)).astype(np.float32).astype(np.float64)
            w.state.x.from_numpy(x.astype(np.float32))
            _on_surface(w, x, normal)
        if k == 0:
            j.begin_substep()
        expect, lam = joint_step_reference(x, inv_mass, rest, touching, normal, iterations=3)
        j.joint()
        np.testing.assert_allclose(w.positions(), expect, atol=3e-6)
        lams.append(lam)
    j.begin_substep()
    for k in range(2):  # the next substep: call k from call k of the last one
        x = (w.positions() + rng.normal(scale=0.002 if k == 0 else 0.001, size=x.shape)).astype(np.float32)
        w.state.x.from_numpy(x)
        x = x.astype(np.float64)
        _on_surface(w, x, normal)
        expect = joint_step_reference(x, inv_mass, rest, touching, normal, iterations=3, lam0=WARM_START * lams[k])[0]
        other = joint_step_reference(x, inv_mass, rest, touching, normal, iterations=3,
                                     lam0=WARM_START * lams[1 - k])[0]
        assert np.abs(expect - other).max() > 2e-5
        j.joint()
        np.testing.assert_allclose(w.positions(), expect, atol=3e-6)


def test_settle_steps_again_from_zero_until_no_edge_is_stretched_past_its_bound():
    """Where one step leaves an edge stretched by more than SETTLE_STRETCH, ``settle`` runs more Newton
    steps, each from zero multipliers (the reference with lam0 = 0), until none is, at most SETTLE_STEPS;
    ``stretch`` is the largest stretch a step left, as NumPy measures it; the next substep's warm start is untouched;
    on a cloth within the bound it moves nothing."""
    from sandbox.solvers.cloth_joint import SETTLE_STEPS, SETTLE_STRETCH

    w = _sheet(2)
    j = w.solver.joint
    rng = np.random.default_rng(3)
    x, inv_mass, rest, touching, normal = _prepare(w, rng, noise=0.006)
    j.begin_substep()
    x1, lam = joint_step_reference(x, inv_mass, rest, touching, normal, iterations=2)
    j.joint()
    np.testing.assert_allclose(w.positions(), x1, atol=3e-6)
    assert j.stretch[None] == pytest.approx(_strain(w.positions().astype(np.float64), rest).max(), abs=1e-5)
    assert j.stretch[None] > SETTLE_STRETCH
    expect, steps = x1, 0
    while _strain(expect, rest).max() > SETTLE_STRETCH and steps < SETTLE_STEPS:
        expect = joint_step_reference(expect.astype(np.float32).astype(np.float64), inv_mass, rest, touching,
                                      normal, iterations=2)[0]
        steps += 1
    assert steps >= 1
    assert j.settle(j.joint) == steps
    np.testing.assert_allclose(w.positions(), expect, atol=2e-5)
    assert j.stretch[None] <= SETTLE_STRETCH or steps == SETTLE_STEPS
    np.testing.assert_allclose(j.keep.to_numpy()[0], lam, atol=1e-7)  # the next substep starts from the first step
    if j.stretch[None] <= SETTLE_STRETCH:
        before = w.positions().copy()
        assert j.settle(j.joint) == 0
        np.testing.assert_array_equal(w.positions(), before)


def test_a_substep_settles_after_its_joint_steps_and_only_when_they_ran(monkeypatch):
    """``sim.cloth_joint_every: 3`` over 5 substeps: the settle follows the joint steps of substeps 0, 3
    and 4, after the iterations (here two, so two steps in each), in the fused and the profiled launch."""
    w = world_from_text(SHEET.replace("ITER", "2, cloth_joint_every: 3, substeps: 5, iterations: 2"))
    s = w.solver
    calls = []
    monkeypatch.setattr(s.joint, "settle", lambda step: calls.append(int(s.joint.call[None])) or 0)
    _stretched_frame(w)
    dt = w.dt / 5
    for k in range(5):
        s.substep(dt, (k + 1) / 5, k, 5)
    assert calls == [2, 2, 2]
    calls.clear()
    for k in range(5):
        s.profile_substep(dt, (k + 1) / 5, k, 5)
    assert calls == [2, 2, 2]


def test_a_scene_without_the_joint_step_reports_no_time_for_it():
    """The profiled substep times the settle into the joint step's entry only where there is a joint step."""
    for iters, expect in ((0, False), (2, True)):
        w = world_from_text(SHEET.replace("ITER", str(iters)))
        s = w.solver
        s.timings = {}
        _stretched_frame(w)
        s.profile_substep(w.dt / 10, 0.1, 0, 10)
        assert ("cloth_joint" in s.timings) == expect, s.timings


def test_the_joint_step_runs_only_where_no_hand_holds_the_cloth_and_not_in_the_first_frame(monkeypatch):
    """A level's joint step (``CLOTH_JOINT`` iterations unless set) is left out of a frame where a hand holds
    a particle of the cloth, and of the first frame (the cloth at its rest lengths, before a level's FSM
    first takes hold); such a frame steps exactly as in a scene without the step. It runs in a later
    frame where only the scene's pins hold the cloth; each frame decides from the hands at its start."""
    from sandbox.levels.schema import CLOTH_JOINT

    w = world_from_text(SHEET.replace("sim: {cloth_joint: ITER}", "sim: {}"))
    plain = world_from_text(SHEET.replace("ITER", "0"))
    s = w.solver
    assert s.joint.iterations == CLOTH_JOINT and plain.solver.joint is None
    calls = []
    monkeypatch.setattr(s.joint, "settle", lambda step: calls.append(1) or 0)
    x = (w.positions() + np.random.default_rng(3).normal(0.0, 2e-3, w.positions().shape)).astype(np.float32)
    for world in (w, plain):  # the first frame, then one where a hand holds a particle
        world.state.x.from_numpy(x)
        world.solver.begin_frame()
        world.solver.substep(world.dt, 1.0, 0, 1)
        assert world.solver.joint_idle and not world.solver.cloth_held
        world.control.drive([NX + 3], world.positions()[[NX + 3]])
        world.solver.begin_frame()
        world.solver.substep(world.dt, 1.0, 0, 1)
    assert s.cloth_held and calls == []
    np.testing.assert_array_equal(w.positions(), plain.positions())
    w.control.release([NX + 3])
    s.begin_frame()
    assert not s.cloth_held and not s.joint_idle  # the pin at [0, 0] is not a hand
    s.substep(w.dt, 1.0, 0, 1)
    assert calls == [1]
