"""Reference rope projection of paper §4.3 (Eq. 2-8), sparse KKT solve with SciPy.

One projection step linearises all constraints at the current positions p
(C(p + dp) ~ C + J dp) and solves

    min_dp 1/2 |dp|^2 + 1/2 sum_e a_e (J_e dp + C_e)^2
                      + 1/2 b |J_b dp + C_b|^2 + 1/2 c |J_k dp + C_k|^2     (Eq. 6)
    s.t.   J_c dp + C_c = 0   for the active collision rows                  (Eq. 7)

with a_e = exp(10 |C_e|) per row, b = 2000, c = 3000. The kinematic term uses
the vector form p_c - p_k = 0 of Eq. 4 (J_k = identity rows): its squared norm
is exactly C_k^2, so the penalty is unchanged while the Jacobian of the norm,
undefined at C_k = 0, is avoided. Its KKT system is

    [ H    J_c^T ] [ dp  ]   [ -(a J_e^T C_e + b J_b^T C_b + c J_k^T C_k) ]
    [ J_c  -d I  ] [ lam ] = [ -C_c                                         ],
    H = I + J_e^T A J_e + b J_b^T J_b + c J_k^T J_k,                         (Eq. 8)

where A = diag(a_e) and d = 1e-10 is a tiny regularisation that keeps the
matrix non-singular when contact rows are redundant (quasi-definite). Eq. 8
as printed drops a, b, c from the J^T J blocks and writes the residuals as
J dp - alpha (so that the right-hand side has the opposite sign); both are
inconsistent with Eq. 6 and corrected above.

Units: the weights 1, a, b, c are only meaningful when lengths are measured
in rod lengths (in the paper's scenes r ~ 1); the solver therefore divides all
lengths by ``length_scale`` (default: mean rod length), so C_e is in r^2,
C_b, C_k, C_c in r, and returns displacements in metres.

Active set (Eq. 7): a collision row is imposed when violated (C_c < 0); after
each solve, candidate rows whose linearised value C_c + J_c dp falls below 0
are added, and added rows (not violated at p) whose multiplier pulls are
released; this repeats at most ``max_active_rounds`` times. Gauss-Newton:
the step is re-linearised and re-solved ``iterations`` times, each time with
the displacement penalty 1/2 |dp|^2 about the new iterate, which is the
paper's "iterated until all the constraints are satisfied" (a proximal
iteration that drives the soft residuals down by ~1/(1 + w |J|^2) per step).
Linearising Eq. 5 leaves a second-order penetration where segments rotate a
lot in one step (e.g. 1 mm after a 5 mm push); up to ``contact_polish``
contact-only steps (H = I, no soft rows) remove it with Newton's quadratic
convergence, so the hard constraints hold to ``contact_tol``.

Behaviour of the paper's model worth knowing: C_b (Eq. 3) does not involve
p_i and vanishes on any zig-zag whose rods are stretched by 1/cos(theta/2), and
a = exp(10 |C_e|) stays ~1 for strains below a few percent while b = 2000, so
strong bends relax partly into zig-zags with 1-2% rod strain that later steps
remove slowly (raise ``a_scale`` when strain matters). The linearised rows
also leave a lone particle free to move perpendicular to its rods, so a
contact push is taken first by the touching particle alone. Contacts that
pinned particles make infeasible are only bounded by the regularisation.

Complexity: for a chain of m rods, assembly is O(m) (vectorised rows, COO ->
CSC), and H is banded (bending couples p_{i-1} and p_{i+1}), so the minimum
degree ordered LU of the KKT matrix has O(m) fill and work. Collision rows
add local couplings; with a bounded number of contacts per segment the cost
stays O(m). The broad phase is a cKDTree on segment midpoints, O(m log m).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from sandbox.solvers.projection_rows import (RopeSystem, Rows, SdfFn, Topology,
                                             bend_rows, broad_phase_pairs, capsule_rows,
                                             concat_rows, ground_rows, kinematic_rows,
                                             sdf_rows, stretch_rows)

__all__ = ["LINEAR_SOLVERS", "Linearisation", "ProjectionParams", "ProjectionReport",
           "ProjectionRopeSolver", "RopeProjection", "RopeSystem", "kkt_matrix", "project",
           "solve_kkt"]

LINEAR_SOLVERS = ("splu", "spsolve", "dense")
"""Allowed values of ``ProjectionParams.linear_solver``."""

Target = tuple[int, np.ndarray]
"""A kinematic target: (particle index, intermediate target point p_k in metres), Eq. 4."""


@dataclass(frozen=True)
class ProjectionParams:
    """Weights and numerics of the projection (paper §4.3 defaults).

    Attributes:
        iterations: Gauss-Newton re-linearisations per projection (1-3).
        a_gain: stretch weight a = a_scale * exp(a_gain |C_e|), C_e in r^2 units.
        a_scale: factor on a; 0 turns the stretch term off.
        a_max: cap on a (the exponential overflows for large stretch).
        b: bending weight.
        c: kinematic weight.
        collision_margin: distance (m) under which a contact becomes a candidate
            row; ``None`` for the largest rope radius.
        max_active_rounds: bound on active-set re-solves per iteration.
        active_tol: linearised violation (scaled units) that triggers a new row.
        regularization: d in the (2, 2) block of the KKT matrix.
        length_scale: metres per solver unit; ``None`` for the mean rod length.
        linear_solver: one of ``LINEAR_SOLVERS``.
        permc_spec: SuperLU column ordering ("MMD_AT_PLUS_A", "COLAMD", ...).
        self_collision: test capsules of the same rope (|i - j| >= 2).
        contact_polish: at most this many contact-only steps after the
            Gauss-Newton iterations (H = I, no soft terms), each taken only while
            some contact is violated by more than ``contact_tol``; they remove
            the second-order penetration left by linearising Eq. 5.
        contact_tol: penetration (m) accepted without a polish step.
    """

    iterations: int = 2
    a_gain: float = 10.0
    a_scale: float = 1.0
    a_max: float = 1e6
    b: float = 2000.0
    c: float = 3000.0
    collision_margin: float | None = None
    max_active_rounds: int = 8
    active_tol: float = 1e-9
    regularization: float = 1e-10
    length_scale: float | None = None
    linear_solver: str = "splu"
    permc_spec: str = "MMD_AT_PLUS_A"
    self_collision: bool = True
    contact_polish: int = 3
    contact_tol: float = 1e-9

    def __post_init__(self) -> None:
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"linear_solver={self.linear_solver!r}; allowed: {LINEAR_SOLVERS}")
        if self.iterations < 1 or self.max_active_rounds < 1 or self.contact_polish < 0:
            raise ValueError("iterations and max_active_rounds must be >= 1, "
                             "contact_polish >= 0")


@dataclass
class ProjectionReport:
    """Diagnostics of one projection, residuals measured at the returned positions.

    Attributes:
        max_stretch: max relative rod strain |l - r| / r.
        max_bend: max |C_b| = | |p_{i+1} - p_{i-1}| - 2 r | (m).
        max_penetration: deepest capsule-capsule, ground or object overlap (m, >= 0).
        max_target_error: max |p_c - p_k| over kinematic targets (m).
        n_active: contact rows imposed in the last solve (iteration or polish).
        n_candidates: candidate contact rows in the last solve.
        active_rounds: active-set solves summed over iterations.
        iterations: Gauss-Newton iterations run.
        polish_steps: contact-only steps run after them.
        t_collision: broad + narrow phase time (s).
        t_assembly: constraint rows and sparse matrix assembly time (s).
        t_solve: factorisation + triangular solves time (s).
        iteration_times: wall time per iteration (s).
    """

    max_stretch: float = 0.0
    max_bend: float = 0.0
    max_penetration: float = 0.0
    max_target_error: float = 0.0
    n_active: int = 0
    n_candidates: int = 0
    active_rounds: int = 0
    iterations: int = 0
    polish_steps: int = 0
    t_collision: float = 0.0
    t_assembly: float = 0.0
    t_solve: float = 0.0
    iteration_times: list[float] = field(default_factory=list)


@dataclass
class Linearisation:
    """Eq. 6-7 at one iterate, in solver units.

    Attributes:
        soft: stretch, bending and kinematic rows (Eq. 2-4).
        weights: (m_soft,) a_e, b, c per soft row.
        hard: candidate contact rows (Eq. 5, ground, objects), C >= 0 wanted.
    """

    soft: Rows
    weights: np.ndarray
    hard: Rows


def kkt_matrix(H: sp.spmatrix, Jc: sp.spmatrix, regularization: float = 1e-10) -> sp.csc_matrix:
    """The Eq. 8 matrix [[H, Jc^T], [Jc, -d I]] in CSC, assembled from one COO list."""
    n, q = H.shape[0], Jc.shape[0]
    Hc, Jo = H.tocoo(), Jc.tocoo()
    rows = np.concatenate([Hc.row, Jo.col, n + Jo.row, n + np.arange(q)])
    cols = np.concatenate([Hc.col, n + Jo.row, Jo.col, n + np.arange(q)])
    vals = np.concatenate([Hc.data, Jo.data, Jo.data, np.full(q, -regularization)])
    return sp.csc_matrix((vals, (rows, cols)), shape=(n + q, n + q))


def solve_kkt(H: sp.spmatrix, g: np.ndarray, Jc: sp.spmatrix, rhs_c: np.ndarray, *,
              regularization: float = 1e-10, method: str = "splu",
              permc_spec: str = "MMD_AT_PLUS_A") -> tuple[np.ndarray, np.ndarray]:
    """Solve [[H, Jc^T], [Jc, -d I]] [dp; lam] = [g; rhs_c] (Eq. 8).

    Args:
        H: (N, N) symmetric positive definite block.
        g: (N,) right-hand side of the stationarity rows.
        Jc: (q, N) active hard rows.
        rhs_c: (q,) right-hand side -C_c of the hard rows.
        regularization: d >= 0.
        method: one of ``LINEAR_SOLVERS``.
        permc_spec: SuperLU column ordering for "splu" and "spsolve".

    Returns:
        (dp (N,), lam (q,)).
    """
    if method not in LINEAR_SOLVERS:
        raise ValueError(f"method={method!r}; allowed: {LINEAR_SOLVERS}")
    rhs = np.concatenate([g, rhs_c])
    # Two contact rows that are (nearly) the same constraint, e.g. one pair of
    # capsules found from both sides, leave the Schur block J H^-1 J^T + d I
    # singular up to d; SuperLU then meets an exactly zero pivot. The
    # regularisation is raised, relative to H's scale, until it factors.
    scale = float(np.abs(H.diagonal()).max(initial=1.0))
    for d in (regularization, 1e-9 * scale, 1e-6 * scale):
        K = kkt_matrix(H, Jc, max(d, regularization))
        try:
            if method == "dense":
                sol = np.linalg.solve(K.toarray(), rhs)
            elif method == "spsolve":
                sol = spla.spsolve(K, rhs, permc_spec=permc_spec)
            else:
                sol = spla.splu(K, permc_spec=permc_spec).solve(rhs)
        except (RuntimeError, np.linalg.LinAlgError):
            continue
        if np.all(np.isfinite(sol)):
            break
    else:
        raise RuntimeError(f"the Eq. 8 system stays singular with regularisation up to {1e-6 * scale:.3g} "
                           f"({Jc.shape[0]} active contact rows)")
    n = H.shape[0]
    return sol[:n], sol[n:]


class RopeProjection:
    """Projection of rope particles onto the constraint manifold (paper §4.3).

    Holds the static part (topology, radii, pins, ground, object SDF); each
    :meth:`project` call takes new positions and kinematic targets. After each
    solve, ``last_contacts`` holds the imposed contact rows and
    ``last_multipliers`` their multipliers (lam < 0 pushes; solver units).

    Args:
        system: ropes; ``system.x`` is only the default for :meth:`project`.
        params: weights and numerics.
        ground_height: y of a ground plane (m), or ``None``.
        sdf: object signed distance in metres, or ``None``.
    """

    def __init__(self, system: RopeSystem, params: ProjectionParams | None = None, *,
                 ground_height: float | None = None, sdf: SdfFn | None = None) -> None:
        self.system = system
        self.params = params or ProjectionParams()
        self.topology: Topology = system.topology()
        p = self.params
        self.scale = float(p.length_scale if p.length_scale else np.mean(system.rest_length))
        self.r = system.rest_length / self.scale
        self.radius = system.radius / self.scale
        rope = np.maximum(self.topology.particle_rope, 0)
        self.prad = np.where(self.topology.particle_rope >= 0, self.radius[rope], 0.0)
        margin = p.collision_margin if p.collision_margin is not None else system.radius.max()
        self.margin = float(margin) / self.scale
        self.ground = None if ground_height is None else float(ground_height) / self.scale
        self.sdf = sdf
        pinned = system.pinned
        self.free = np.flatnonzero(~pinned)
        self.free_map = np.full(system.n_particles, -1, dtype=np.int64)
        self.free_map[self.free] = np.arange(len(self.free))
        self.last_contacts: Rows = Rows.empty(1)
        self.last_multipliers = np.zeros(0)
        if not p.self_collision:
            self.topology = replace(self.topology, self_gap=np.full_like(
                self.topology.self_gap, np.iinfo(np.int64).max))

    # -- linearisation -------------------------------------------------------------
    def linearise(self, xs: np.ndarray, targets_s: Sequence[Target]) -> Linearisation:
        """Rows and weights of Eq. 6-7 at positions ``xs`` (solver units)."""
        soft, hard = self._soft(xs, targets_s), self._hard(xs, self.margin)
        return Linearisation(soft[0], soft[1], hard)

    def _soft(self, xs: np.ndarray, targets_s: Sequence[Target]) -> tuple[Rows, np.ndarray]:
        p = self.params
        e = stretch_rows(xs, self.topology, self.r)
        b = bend_rows(xs, self.topology, self.r)
        k = kinematic_rows(xs, targets_s, self.system.pinned)
        a = p.a_scale * np.minimum(np.exp(np.minimum(p.a_gain * np.abs(e.value), 700.0)),
                                   p.a_max)
        w = np.concatenate([a, np.full(len(b), p.b), np.full(len(k), p.c)])
        return concat_rows([e, b, k]), w

    def _hard(self, xs: np.ndarray, margin: float) -> Rows:
        topo, blocks = self.topology, []
        pairs = broad_phase_pairs(xs, topo, self.radius, margin)
        cap = capsule_rows(xs, topo, self.radius, pairs)
        blocks.append(cap.take(cap.value < margin))
        if self.ground is not None:
            gr = ground_rows(xs, self.free, self.prad, self.ground)
            blocks.append(gr.take(gr.value < margin))
        if self.sdf is not None and len(self.free):
            sr = sdf_rows(xs, self.free, self.prad, self.sdf, self.scale)
            blocks.append(sr.take(sr.value < margin))
        return concat_rows(blocks)

    # -- one Gauss-Newton iteration --------------------------------------------------
    def iterate(self, xs: np.ndarray, targets_s: Sequence[Target],
                report: ProjectionReport | None = None, *, hard_only: bool = False,
                skip_above: float | None = None) -> np.ndarray | None:
        """One linearise + active-set KKT solve; returns dp (n, 3) in solver units.

        Args:
            xs: (n, 3) positions in solver units.
            targets_s: kinematic targets in solver units.
            report: accumulates timings and active-set counts.
            hard_only: drop the soft terms (H = I): the step is the smallest
                displacement that satisfies the linearised contacts.
            skip_above: return ``None`` (no solve) when every contact value is
                above this (solver units).
        """
        p, rep = self.params, report or ProjectionReport()
        n_free = len(self.free)
        t0 = time.perf_counter()
        soft, w = (Rows.empty(1), np.zeros(0)) if hard_only else self._soft(xs, targets_s)
        t1 = time.perf_counter()
        hard = self._hard(xs, self.margin)
        t2 = time.perf_counter()
        rep.t_collision += t2 - t1
        if skip_above is not None and hard.value.min(initial=np.inf) >= skip_above:
            rep.t_assembly += t1 - t0
            return None
        N, fm = 3 * n_free, self.free_map
        hr, hc, hv = soft.gram_triplets(w, fm)
        H = sp.csc_matrix((np.concatenate([np.ones(N), hv]),
                           (np.concatenate([np.arange(N), hr]),
                            np.concatenate([np.arange(N), hc]))), shape=(N, N))
        g = -soft.rmatvec(w * soft.value, fm, n_free)
        jr, jc, jv = hard.triplets(fm)
        usable = np.bincount(jr, minlength=len(hard)) > 0
        t3 = time.perf_counter()
        rep.t_assembly += (t1 - t0) + (t3 - t2)

        violated = usable & (hard.value < 0.0)            # Eq. 7: imposed if sigma < 0
        active = violated.copy()
        rounds = 0
        for rounds in range(1, p.max_active_rounds + 1):
            ta = time.perf_counter()
            pos = np.cumsum(active) - 1                   # row of each active contact in Jc
            sel = active[jr]
            Jc = sp.coo_matrix((jv[sel], (pos[jr[sel]], jc[sel])), shape=(int(active.sum()), N))
            tb = time.perf_counter()
            dp, lam = solve_kkt(H, g, Jc, -hard.value[active],
                                regularization=p.regularization, method=p.linear_solver,
                                permc_spec=p.permc_spec)
            tc = time.perf_counter()
            rep.t_assembly += tb - ta
            rep.t_solve += tc - tb
            pred = hard.value + np.bincount(jr, weights=jv * dp[jc], minlength=len(hard))
            new = usable & ~active & (pred < -p.active_tol)
            mult = np.zeros(len(hard))
            mult[active] = lam
            # lam > 0 means the row pulls the capsules together (H dp + Jc^T lam = g).
            release = active & ~violated & (mult > 0.0)
            if (not new.any() and not release.any()) or rounds == p.max_active_rounds:
                break
            active = (active | new) & ~release
        rep.active_rounds += rounds
        self.last_contacts, self.last_multipliers = hard.take(active), lam
        rep.n_active = int(active.sum())
        rep.n_candidates = len(hard)
        out = np.zeros_like(xs)
        out[self.free] = dp.reshape(-1, 3)
        return out

    # -- public ------------------------------------------------------------------------
    def project(self, x: np.ndarray | None = None, targets: Sequence[Target] = ()
                ) -> tuple[np.ndarray, ProjectionReport]:
        """Project positions onto the constraints (Eq. 6-8, ``iterations`` times).

        Args:
            x: (n, 3) positions (m); ``None`` for ``system.x``.
            targets: kinematic targets (particle index, p_k in m), Eq. 4.

        Returns:
            (x_new (n, 3) in m, report).
        """
        x = self.system.x if x is None else np.asarray(x, dtype=np.float64).reshape(-1, 3)
        xs = x / self.scale
        tg = [(int(i), np.asarray(q, dtype=np.float64) / self.scale) for i, q in targets]
        rep = ProjectionReport()
        if len(self.free):
            for _ in range(self.params.iterations):
                t0 = time.perf_counter()
                xs = xs + self.iterate(xs, tg, rep)
                rep.iteration_times.append(time.perf_counter() - t0)
                rep.iterations += 1
            tol = -self.params.contact_tol / self.scale
            for _ in range(self.params.contact_polish):
                dp = self.iterate(xs, tg, rep, hard_only=True, skip_above=tol)
                if dp is None:
                    break
                xs = xs + dp
                rep.polish_steps += 1
        x_new = xs * self.scale
        x_new[self.system.pinned] = x[self.system.pinned]
        self.residuals(x_new, targets, rep)
        return x_new, rep

    def residuals(self, x: np.ndarray, targets: Sequence[Target] = (),
                  report: ProjectionReport | None = None) -> ProjectionReport:
        """Fill the residual fields of ``report`` at positions ``x`` (m)."""
        rep = report or ProjectionReport()
        topo, sysm = self.topology, self.system
        t0 = time.perf_counter()
        if len(topo.rods):
            ln = np.linalg.norm(x[topo.rods[:, 1]] - x[topo.rods[:, 0]], axis=1)
            r = sysm.rest_length[topo.rod_rope]
            rep.max_stretch = float(np.max(np.abs(ln - r) / r))
        if len(topo.bends):
            d = np.linalg.norm(x[topo.bends[:, 2]] - x[topo.bends[:, 0]], axis=1)
            rep.max_bend = float(np.max(np.abs(d - 2.0 * sysm.rest_length[topo.bend_rope])))
        hard = self._hard(x / self.scale, 0.0)
        rep.max_penetration = float(max(0.0, -hard.value.min(initial=0.0)) * self.scale)
        errs = [np.linalg.norm(x[int(i)] - np.asarray(q)) for i, q in targets
                if not sysm.pinned[int(i)]]
        rep.max_target_error = float(max(errs, default=0.0))
        rep.t_collision += time.perf_counter() - t0
        return rep


def project(system: RopeSystem, targets: Sequence[Target] = (),
            params: ProjectionParams | None = None, *, ground_height: float | None = None,
            sdf: SdfFn | None = None) -> tuple[np.ndarray, ProjectionReport]:
    """Project ``system.x`` onto the constraints of paper §4.3; see :class:`RopeProjection`."""
    return RopeProjection(system, params, ground_height=ground_height, sdf=sdf).project(
        system.x, targets)


class ProjectionRopeSolver:
    """Time stepping by prediction + projection (the paper's Fast-Projection-like scheme).

    x* = x + dt v + dt^2 g for free particles, x_new = project(x*),
    v_new = (x_new - x) / dt. Pinned particles keep x and get v = 0.

    Args:
        system: rope topology, rod lengths, radii and pins (its ``x`` is unused).
        params: projection parameters.
        ground_height: ground plane y (m), or ``None``.
        sdf: object signed distance (m), or ``None``.
    """

    def __init__(self, system: RopeSystem, params: ProjectionParams | None = None, *,
                 ground_height: float | None = None, sdf: SdfFn | None = None) -> None:
        self.projection = RopeProjection(system, params, ground_height=ground_height, sdf=sdf)
        self.last_report: ProjectionReport | None = None

    def step(self, x: np.ndarray, v: np.ndarray, dt: float,
             gravity: Sequence[float] = (0.0, -9.81, 0.0), targets: Sequence[Target] = ()
             ) -> tuple[np.ndarray, np.ndarray]:
        """Advance one step of ``dt`` seconds.

        Args:
            x, v: (n, 3) positions (m) and velocities (m/s).
            dt: time step (s).
            gravity: acceleration (m/s^2).
            targets: kinematic targets (particle, intermediate target p_k in m), Eq. 4.

        Returns:
            (x_new, v_new).
        """
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
        pinned = self.projection.system.pinned
        pred = x + dt * v + dt * dt * np.asarray(gravity, dtype=np.float64)
        pred[pinned] = x[pinned]
        x_new, self.last_report = self.projection.project(pred, targets)
        v_new = (x_new - x) / dt
        v_new[pinned] = 0.0
        return x_new, v_new
