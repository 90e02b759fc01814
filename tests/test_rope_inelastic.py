"""Inelastic rope contacts: a rope contact push moves particles apart but leaves
them no speed apart, as object contacts and cloth self-contacts already do."""

import numpy as np
import pytest
import taichi as ti

from sandbox.levels import LevelError, load_level_from_string
from tests.levelkit import world_from_text
from tests.test_prestabilize import CROSSED, without_step_zero


def _after_one_frame():
    w = without_step_zero(world_from_text(CROSSED))
    x0 = w.positions().astype(np.float64)
    w.step()
    return w, x0, w.positions().astype(np.float64), w.velocities().astype(np.float64), w.solver.ropecol.measure()


@pytest.fixture(scope="module")
def frame():
    return _after_one_frame()


def test_rope_contacts_push_apart_without_speed(frame):
    """Two ropes crossed 0.2 radius into each other, at rest, no gravity, no step 0: the first substep
    pushes each 0.6 mm out, which as speed would be 0.72 m/s (0.18 m/s measured at the fastest particle
    when the pushes were kept as speed). Inelastic, 0.033 m/s is left: it comes from the chain step after
    the contacts, which moves the particles next to the contact along their rods."""
    w, x0, x, v, gap = frame
    push_speed = 0.5 * 0.2 * 2 * 0.006 * w.fps * w.substeps
    assert np.linalg.norm(v, axis=1).max() < 0.07 * push_speed
    assert gap.min() > -0.02 * 0.006  # apart by the end of the frame all the same
    # Equal and opposite pushes (split contacts), equal masses: the centre of mass stays put, up to
    # 0.5 % of the 0.6 mm push (measured: 1.1e-6 m; each particle's velocity is settled on its own, not
    # pairwise, so the momentum it takes back is equal on both sides only to first order); rods keep length.
    np.testing.assert_allclose(x.mean(axis=0), x0.mean(axis=0), atol=3e-6)
    assert w.solver.measure()["strain"].max() < 1e-3


def test_rope_inelastic_is_engine_behaviour_not_an_option():
    with pytest.raises(LevelError, match="rope_inelastic"):
        load_level_from_string(CROSSED.replace("iterations: 4}", "iterations: 4, rope_inelastic: true}"))


@ti.kernel
def _settle_k(rc: ti.template(), v: ti.template(), out: ti.template(), inv_dt: ti.f32):
    for i in v:
        out[i] = rc.settle(i, v[i], inv_dt)


def test_settle_matches_the_numpy_reference(frame):
    """Per particle: the velocity less its part along the substep's summed push, at most the push over
    the step and never past zero; a velocity into the push, or no push, is kept."""
    rc = frame[0].solver.ropecol
    n = rc.push.shape[0]
    rng = np.random.default_rng(3)
    push = rng.normal(scale=1e-4, size=(n, 3)).astype(np.float32)
    push[rng.random(n) < 0.3] = 0.0
    vel = rng.normal(scale=0.2, size=(n, 3)).astype(np.float32)
    inv_dt = 1200.0
    rc.push.from_numpy(push)
    v = ti.Vector.field(3, ti.f32, shape=n)
    out = ti.Vector.field(3, ti.f32, shape=n)
    v.from_numpy(vel)
    _settle_k(rc, v, out, inv_dt)
    got = out.to_numpy().astype(np.float64)
    q = push.astype(np.float64)
    lq = np.linalg.norm(q, axis=1)
    d = np.divide(q, lq[:, None], out=np.zeros_like(q), where=lq[:, None] > 0)
    vn = (vel * d).sum(1)
    take = np.where(vn > 0, np.minimum(vn, lq * inv_dt), 0.0)
    want = vel - take[:, None] * d
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert ((take > 0) & (take < vn)).any() and (take == vn).any() and (vn < 0).any()  # every case is met
    rc.push.fill(0.0)
