"""Physics of the XPBD world: closed forms, invariants on the shipped levels, and rollback on blow-up."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from sandbox.api import Sandbox
from sandbox.levels import load_level_from_string
from sandbox.model.model import GRIP_GIVE
from sandbox.world import SimulationUnstable

ROOT = pathlib.Path(__file__).resolve().parents[1]
LEVELS = ROOT / "levels"
G = 9.81


def _rod_level(p0, p1, *, pins=(), ground="false", gravity=(0.0, -G, 0.0), fps=60, substeps=10,
               max_retries=3, radius=1e-3, adaptive: str | None = None) -> str:
    """YAML of a one-rod rope (two particles) without damping or objects; a fixed substep count unless
    ``adaptive`` gives the ``sim`` keys that make it adaptive ("" for the engine's default)."""
    if adaptive is None:
        adaptive = f", max_substeps: {substeps}"
    pins_yaml = "[" + ", ".join(pins) + "]"
    return f"""
version: 1
name: rod
scene:
  gravity: [{gravity[0]!r}, {gravity[1]!r}, {gravity[2]!r}]
  ground: {ground}
  ropes:
    - name: rod
      points: [[{p0[0]!r}, {p0[1]!r}, {p0[2]!r}], [{p1[0]!r}, {p1[1]!r}, {p1[2]!r}]]
      segments: 1
      radius: {radius!r}
      damping: 0.0
      pins: {pins_yaml}
sim: {{fps: {fps}, substeps: {substeps}, iterations: 1, max_retries: {max_retries}, frames: 10{adaptive}}}
fsm:
  - {{run: Wait, with: {{ticks: 100000}}}}
"""


def _sandbox(text: str) -> Sandbox:
    return Sandbox(load_level_from_string(text, base_dir=ROOT), arch="cpu")


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


# ------------------------------------------------------------------ closed forms
def test_free_fall_matches_symplectic_euler_error():
    """A free particle falls g T^2/2 plus exactly the symplectic-Euler excess g h T/2, up to float32 rounding."""
    fps, substeps, frames = 60, 2, 60
    sim = _sandbox(_rod_level((0.0, 0.0, 0.0), (0.01, 0.0, 0.0), fps=fps, substeps=substeps))
    y0 = sim.rope_positions("rod")[:, 1].astype(np.float64)
    for _ in range(frames):
        sim.step()
    x = sim.rope_positions("rod")
    v = sim.world.velocities()
    h = 1.0 / (fps * substeps)
    n = frames * substeps
    T = frames / fps
    assert sim.time == pytest.approx(T)

    err = (y0 - 0.5 * G * T * T) - x[:, 1]          # how much further than the exact fall (m)
    predicted = 0.5 * G * h * T                      # v_k = -g k h, y_N = -g h^2 N (N + 1) / 2
    # Worst-case float32 rounding: every substep rounds the position (<= ulp/2) and the
    # velocity re-read from it; an error made at step k shifts all later positions by
    # (N - k + 1) times itself.
    yk = -0.5 * G * h * h * np.arange(1, n + 1) * np.arange(2, n + 2)
    bound32 = float(np.sum((n - np.arange(1, n + 1) + 1) * np.spacing(np.abs(yk).astype(np.float32))))
    assert bound32 < 0.1 * predicted, "the float32 bound must leave the scheme's error visible"
    np.testing.assert_allclose(err, predicted, atol=bound32)
    # Symplectic Euler gets the velocity of a constant force exactly: v_N = -g T.
    np.testing.assert_allclose(v[:, 1], -G * T, atol=n * float(np.spacing(np.float32(abs(yk[-1])))) / h)
    np.testing.assert_array_equal(v[:, 0], 0.0)


def _spy_substeps(monkeypatch, world) -> list[int]:
    """The substep count of every ``_physics`` call (attempts and retries alike)."""
    tried = []
    physics = world._physics

    def spy(substeps, profile):
        tried.append(substeps)
        physics(substeps, profile)

    monkeypatch.setattr(world, "_physics", spy)
    return tried


def test_adaptive_substeps_follow_the_speed_and_keep_free_fall_exact(monkeypatch):
    """A frame takes ceil((v + g dt) dt / (travel h)) substeps, clamped to [substeps, max_substeps]
    (v: the largest speed at the frame's start, h: the rod length, travel: a quarter): a falling 2 mm rod
    (v = g t) goes 8 (the floor), 11, 17, ..., 39, then 40 (the cap). Each frame is then symplectic Euler
    with its own step, which the fall matches up to float32 rounding. Unset, the cap is 4 x substeps;
    ``max_substeps: substeps`` keeps the count fixed."""
    from sandbox.world import SUBSTEP_TRAVEL

    fps, h, frames = 60, 0.002, 12
    dt = 1.0 / fps
    sim = _sandbox(_rod_level((0.0, 0.0, 0.0), (h, 0.0, 0.0), fps=fps, substeps=8, adaptive=", max_substeps: 40"))
    tried = _spy_substeps(monkeypatch, sim.world)
    want, rows = [], []
    y, v, bound, steps = 0.0, 0.0, 0.0, []
    for f in range(frames):
        n = min(40, max(8, math.ceil((abs(v) + G * dt) * dt / (SUBSTEP_TRAVEL * h))))
        want.append(n)
        for _ in range(n):  # symplectic Euler with step dt / n: v -= g h', y += v h'
            v -= G * dt / n
            y += v * dt / n
            steps.append(abs(y))
        rows.append(sim.step())
    assert want[:3] == [8, 11, 17] and want[5:8] == [33, 39, 40] and want[-1] == 40
    assert tried == want and [r["substeps"] for r in rows] == want
    # Float32 rounding of every position, carried by all later steps (as in the fixed-step test).
    N = len(steps)
    bound = float(np.sum((N - np.arange(N)) * np.spacing(np.asarray(steps, np.float32))))
    T = frames * dt
    y_fixed = -0.5 * G * T * T - 0.5 * G * (dt / 8) * T  # the fixed floor's fall (its Euler excess is larger)
    assert bound < abs(y_fixed - y) / 3, "the float32 bound must tell the adaptive steps from fixed ones"
    np.testing.assert_allclose(sim.rope_positions("rod")[:, 1], y, atol=bound)
    np.testing.assert_allclose(sim.world.velocities()[:, 1], -G * frames * dt, rtol=1e-3)  # re-read from rounded positions
    assert sim.world.substep_frames == {n: want.count(n) for n in set(want)}
    assert sim.world.mean_substeps == pytest.approx(sum(want) / frames)

    default = _sandbox(_rod_level((0.0, 0.0, 0.0), (h, 0.0, 0.0), fps=fps, substeps=8, adaptive=""))
    tried = _spy_substeps(monkeypatch, default.world)
    for _ in range(frames):
        default.step()
    assert tried == [min(n, 32) for n in want]  # the default cap: 4 x 8

    fixed = _sandbox(_rod_level((0.0, 0.0, 0.0), (h, 0.0, 0.0), fps=fps, substeps=8, adaptive=", max_substeps: 8"))
    tried = _spy_substeps(monkeypatch, fixed.world)
    for _ in range(frames):
        fixed.step()
    assert tried == [8] * frames


def test_retries_double_the_adaptive_count(monkeypatch):
    """A frame that blows up is retried from its adaptive count: 16 (the cap, at 1000 m/s^2), 32, 64, 128."""
    sim = _sandbox(_rod_level((0.0, 1.0, 0.0), (0.01, 1.0, 0.0), gravity=(0.0, -1e3, 0.0), substeps=10,
                              max_retries=3, adaptive=", max_substeps: 16"))
    tried = _spy_substeps(monkeypatch, sim.world)
    monkeypatch.setattr(sim.world, "_blown_up", lambda m: True)  # every attempt blows up
    with pytest.raises(SimulationUnstable):
        sim.step()
    assert tried == [16, 32, 64, 128]


@pytest.mark.parametrize("solver", ["xpbd", "projection"])
def test_pulled_rod_approaches_force_over_drag(solver):
    """A rod pulled along itself by f and held back by a drag b per particle: v_k = (f/b)(1 - r^k).

    Backward Euler on m dv/dt = f - b v gives v_{k+1} = (v_k + h f/m) r with
    r = 1 / (1 + h b / m): the speed approaches the terminal f / b geometrically
    and never passes it. The rod's constraint has nothing to do (both ends
    feel the same force), so the solvers must reproduce the closed form.
    """
    fps, substeps, frames = 60, 4, 30
    text = _rod_level((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), gravity=(0.0, 0.0, 0.0), fps=fps, substeps=substeps)
    sim = _sandbox(text.replace("iterations: 1,", f"iterations: 1, solver: {solver},"))
    m = 1.0 / float(sim.world.data.inv_mass[0])
    f, b = 0.02, 0.4  # N, N s/m: terminal speed 0.05 m/s
    sim.world.control.pull([0, 1], [[f, 0.0, 0.0]] * 2, b)
    assert sim.world.control.is_pulled([0, 1]).all() and not sim.world.control.is_driven([0, 1]).any()
    x0 = sim.rope_positions("rod").astype(np.float64)
    h = 1.0 / (fps * substeps)
    r = 1.0 / (1.0 + h * b / m)
    k = np.arange(1, frames * substeps + 1)
    v = (f / b) * (1.0 - r ** k)
    for _ in range(frames):
        sim.step()
    got_v = sim.world.velocities()[:, 0]
    got_x = sim.rope_positions("rod")[:, 0] - x0[:, 0]
    np.testing.assert_allclose(got_v, v[-1], rtol=2e-4)
    np.testing.assert_allclose(got_x, h * v.sum(), rtol=2e-4)
    assert got_v.max() < f / b
    # Released, the rod keeps its speed (no force, no drag).
    sim.world.control.release([0, 1])
    sim.step()
    np.testing.assert_allclose(sim.world.velocities()[:, 0], v[-1], rtol=2e-4)


def test_rod_pulled_at_one_end_moves_as_one_body():
    """A rod pulled at one end only moves as a body of mass 2m under f and b: u_k = (f/b)(1 - r2^k).

    With the drag implicit the pulled particle weighs m + b h in the
    substep's constraint projection; the projection then conserves
    (m + b h) v' + m u and the rod follows backward Euler on 2m du/dt = f - b u,
    r2 = 1 / (1 + h b / (2m)). Weighing the pulled end m instead would split
    the correction evenly and lag behind this. (The reference projection,
    paper Eq. 6, has no masses: it lags by about 0.7% here.)
    """
    fps, substeps, frames = 60, 4, 20
    text = _rod_level((0.0, 0.0, 0.0), (0.1, 0.0, 0.0), gravity=(0.0, 0.0, 0.0), fps=fps, substeps=substeps)
    sim = _sandbox(text)
    m = 1.0 / float(sim.world.data.inv_mass[0])
    f, b = 0.02, 0.4
    sim.world.control.pull([1], [[f, 0.0, 0.0]], b)
    h = 1.0 / (fps * substeps)
    k = frames * substeps
    u = (f / b) * (1.0 - (1.0 / (1.0 + h * b / (2.0 * m))) ** k)
    for _ in range(frames):
        sim.step()
    x = sim.rope_positions("rod")
    assert abs(float(np.linalg.norm(x[1] - x[0])) - 0.1) < 1e-4  # the rod holds
    np.testing.assert_allclose(sim.world.velocities()[:, 0], u, rtol=1e-3)


@pytest.mark.parametrize("solver", ["xpbd", "projection"])
@pytest.mark.parametrize("hold", [True, False])
def test_gripped_rod_hangs_within_the_grip_or_slips_at_the_closed_form_speed(solver, hold):
    """A hanging rod (weight W = 2 m g) gripped at its top (``Control.grip``: a spring of F / GRIP_GIVE back to
    its place, at most F, and a drag b).

    F = 2 W holds it: at rest the spring carries W, so the top hangs W GRIP_GIVE / F = GRIP_GIVE / 2 below its
    place (XPBD; the reference projection has no masses: within the give). F = W / 2 lets it slip: the rod
    falls as one body under W - F - b v, at the terminal speed (W - F) / b (XPBD; the projection, 17 %
    faster).
    """
    text = _rod_level((0.0, 0.5, 0.0), (0.0, 0.4, 0.0), fps=60, substeps=10)
    sim = _sandbox(text.replace("iterations: 1,", f"iterations: 1, solver: {solver},"))
    m = 1.0 / float(sim.world.data.inv_mass[0])
    w_rod = 2.0 * m * G
    top = sim.rope_positions("rod")[0].astype(np.float64)
    f = 2.0 * w_rod if hold else 0.5 * w_rod
    b = f / 0.2 if hold else 2.0 * m / 0.02  # N s/m: the spring's motion dies out in 0.1 s; terminal in 0.1 s
    sim.world.control.grip([0], top[None], f, b)
    ctl = sim.world.control
    assert ctl.is_gripped([0]).all() and ctl.is_driven([0]).all() and not ctl.is_kinematic([0]).any()
    for _ in range(60):
        sim.step()
    x = sim.rope_positions("rod").astype(np.float64)
    v = sim.world.velocities()
    if hold:
        drop = top[1] - x[0, 1]
        if solver == "xpbd":
            assert drop == pytest.approx(0.5 * GRIP_GIVE, rel=0.02)
        assert 0.0 < drop < GRIP_GIVE
        assert np.abs(v).max() < 1e-3
    else:
        vt = (w_rod - f) / b
        if solver == "xpbd":
            np.testing.assert_allclose(v[:, 1], -vt, rtol=0.02)
        else:  # no masses in the projection: the free end does not drag the gripped one as a body would
            assert np.all((-v[:, 1] > vt) & (-v[:, 1] < 1.25 * vt))
            assert abs(float(v[0, 1] - v[1, 1])) < 1e-4
        assert abs(float(np.linalg.norm(x[1] - x[0])) - 0.1) < 1e-3  # the rod holds while it slips


def test_a_grip_needs_a_force():
    sim = _sandbox(_rod_level((0.0, 0.5, 0.0), (0.0, 0.4, 0.0)))
    for force, drag in ((0.0, 1.0), (-1.0, 1.0), (1.0, -0.5)):
        with pytest.raises(ValueError, match="a grip needs a force > 0 N and a drag >= 0"):
            sim.world.control.grip([0], [[0.0, 0.5, 0.0]], force, drag)
    assert not sim.world.control.is_driven([0, 1]).any()  # nothing half set


def test_simple_pendulum_period():
    """A pinned one-rod rope swings with the simple pendulum's finite-amplitude period 2 pi sqrt(L/g) (1 + theta0^2/16)."""
    L, theta0, fps = 0.5, math.radians(8.0), 60
    bob0 = (L * math.sin(theta0), -L * math.cos(theta0), 0.0)
    sim = _sandbox(_rod_level((0.0, 0.0, 0.0), bob0, pins=("start",), fps=fps, substeps=10))
    T0 = 2.0 * math.pi * math.sqrt(L / G)
    frames = int(3.5 * T0 * fps) + 10
    xs = [sim.rope_positions("rod")[1].astype(np.float64)]
    for _ in range(frames):
        sim.step()
        xs.append(sim.rope_positions("rod")[1].astype(np.float64))
    xs = np.array(xs)
    x = xs[:, 0]
    t = np.arange(len(x)) / fps
    k = np.flatnonzero(np.sign(x[:-1]) * np.sign(x[1:]) < 0)
    crossings = t[k] + (t[k + 1] - t[k]) * x[k] / (x[k] - x[k + 1])  # linear interpolation
    assert len(crossings) >= 7
    period = (crossings[6] - crossings[0]) / 3.0
    expected = T0 * (1.0 + theta0**2 / 16.0)
    # Error budget (relative): interpolating a sine at its zero crossing errs by
    # O((w dt)^3) ~ 1e-5; the symplectic step shifts the frequency by (w h)^2 / 24 ~ 2e-6;
    # the numerical damping (amplitude loss < 10 % below, zeta < 3e-3) by zeta^2 / 2 < 1e-5;
    # float32 positions re-read as velocities every substep add ~1e-4 of phase noise.
    # 5e-4 covers these and stays below the amplitude correction theta0^2/16 = 1.2e-3,
    # so the small-angle period T0 alone would fail.
    assert period == pytest.approx(expected, rel=5e-4)
    assert abs(period / T0 - 1.0) > 5e-4
    first = np.abs(x[: int(T0 * fps)]).max()
    last = np.abs(x[-int(T0 * fps):]).max()
    assert 0.9 * first < last <= first * (1.0 + 1e-6), "numerical damping is small and never adds energy"
    np.testing.assert_allclose(np.linalg.norm(xs, axis=1), L, rtol=1e-5)


# ------------------------------------------------------------------ invariants on rope_hang
@pytest.fixture(scope="module")
def rope_hang_run():
    """rope_hang for 120 frames: per-frame metrics rows, minimum capsule gaps and pinned positions."""
    frames = 120
    sim = Sandbox.from_level(LEVELS / "rope_hang.yaml", arch="cpu", overrides={"sim.frames": frames})
    world = sim.world
    pins = np.asarray(world.data.pins)
    x0 = world.positions()[pins].copy()
    rows, gaps, pinned, seg_gaps = [], [], [], []
    for _ in range(frames):
        rows.append(sim.step())
        gap = world.solver.ropecol.measure()
        gaps.append(float(gap.min()))
        seg_gaps.append(gap.copy())
        pinned.append(world.positions()[pins].copy())
    return {"sim": sim, "rows": rows, "gaps": np.array(gaps), "seg_gaps": np.array(seg_gaps),
            "pins": pins, "x0": x0, "pinned": np.array(pinned)}


def test_pinned_particles_stay_bitwise_put(rope_hang_run):
    """Pinned rope ends keep their start positions bit for bit through 120 frames of contacts."""
    run = rope_hang_run
    world = run["sim"].world
    line = world.ropes["line"]
    # The pinned 'line' rope is really hit: some of its segments come within half a radius of another capsule.
    seg_of_line = world.data.segment_rope == list(world.ropes).index("line")
    assert run["seg_gaps"][:, seg_of_line].min() < 0.5 * line.radius
    assert len(run["pins"]) == 3
    for f in range(len(run["pinned"])):
        np.testing.assert_array_equal(_bits(run["pinned"][f]), _bits(run["x0"]), err_msg=f"frame {f + 1}")


def test_rope_hang_strain_within_one_percent(rope_hang_run):
    """Every rod of every rope of rope_hang stays within 1 % of its rest length at every frame."""
    for row in rope_hang_run["rows"]:
        for rope in ("line", "swing", "free"):
            assert row["strain"][rope] <= 0.01, (row["frame"], rope, row["strain"][rope])
    assert max(max(r["strain"].values()) for r in rope_hang_run["rows"]) > 0.0


def test_rope_hang_no_capsule_pass_through(rope_hang_run):
    """No two rope capsules of rope_hang overlap by more than 10 % of a radius at any frame."""
    radius = min(r.radius for r in rope_hang_run["sim"].world.ropes.values())
    gaps = rope_hang_run["gaps"]
    worst = int(np.argmin(gaps))
    assert gaps.min() >= -0.1 * radius, f"frame {worst + 1}: overlap {-gaps[worst]:.2e} m"
    assert gaps.min() < 0.5 * radius, "the ropes never touched: nothing was tested"


# ------------------------------------------------------------------ invariants on drape_box
def _box_sdf_from_mesh(sim: Sandbox, points: np.ndarray) -> np.ndarray:
    """Signed distance (m) to the axis-aligned box spanned by the object's world mesh."""
    verts, _ = sim.object_mesh("box")
    lo, hi = verts.min(axis=0).astype(np.float64), verts.max(axis=0).astype(np.float64)
    c, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    q = np.abs(points - c) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return outside + np.minimum(q.max(axis=1), 0.0)


def _drape_penetration(overrides: dict, frames: int) -> tuple[float, float, float]:
    """(deepest box penetration, thickness, closest approach) over every 5th frame of drape_box."""
    sim = Sandbox.from_level(LEVELS / "drape_box.yaml", arch="cpu", overrides={**overrides, "sim.frames": frames})
    thickness = sim.world.cloths["cloth"].thickness
    deepest, closest = -np.inf, np.inf
    for f in range(1, frames + 1):
        sim.step()
        if f % 5:
            continue
        x = sim.cloth_positions("cloth")
        d, _, _ = sim.world.objects.query_numpy(x)
        np.testing.assert_allclose(d, _box_sdf_from_mesh(sim, x.astype(np.float64)), atol=1e-5)
        deepest = max(deepest, float((-d).max()))
        closest = min(closest, float(d.min()))
    return deepest, thickness, closest


def test_drape_box_no_penetration_reduced():
    """A 41 x 41 drape_box cloth never sinks into the box deeper than 10 % of its thickness (every 5th frame)."""
    deepest, thickness, closest = _drape_penetration({"scene.cloths.0.resolution": [41, 41]}, 60)
    assert deepest <= 0.1 * thickness
    assert closest < 0.75 * thickness, "the cloth never reached the box: nothing was tested"


def _cloth_stretch(sim: Sandbox, res: int, size: float) -> np.ndarray:
    """Stretch (l - r) / r of every structural edge of the cloth."""
    x = sim.cloth_positions("cloth").astype(np.float64).reshape(res, res, 3)
    h = size / (res - 1)
    rows = np.linalg.norm(x[:, 1:] - x[:, :-1], axis=2) / h - 1.0
    cols = np.linalg.norm(x[1:] - x[:-1], axis=2) / h - 1.0
    return np.concatenate([rows.ravel(), cols.ravel()])


def test_chain_sweeps_bring_cloth_over_box_edges_and_vertices_to_length():
    """An 81 x 81 cloth (1 cm spacing) draped over drape_box's box: three chain sweeps bring every edge
    crossing its top edges and vertices within 3 % at the end (one leaves tens of percent: docs/benchmarks.md), but
    leave 20 % at impact; the joint step after them (rows and columns solved together, settled where a
    substep leaves more than 1 %) brings every edge within 0.5 % at the end and 2 % at impact;
    adaptive substeps (up to 40 while the cloth moves fast) do it with fewer than half the settle
    steps; the cloth still rests on the box without sinking in."""
    res, size = 81, 0.8
    worst, run_worst, substeps, settle = {}, {}, {}, {}
    for sweeps, joint, most in ((3, 0, 10), (3, 3, 10), (3, 3, 40)):
        key = sweeps, joint, most
        overrides = {"scene.cloths.0.resolution": [res, res], "scene.cloths.0.size": [size, size],
                     "sim.chain_sweeps": sweeps, "sim.cloth_joint": joint, "sim.frames": 90,
                     "sim.max_substeps": most}
        with Sandbox.from_level(LEVELS / "drape_box.yaml", arch="cpu", overrides=overrides) as sim:
            run_worst[key] = 0.0
            for f in range(90):
                sim.step()
                if f % 3 == 0:
                    run_worst[key] = max(run_worst[key], float(_cloth_stretch(sim, res, size).max()))
            worst[key] = float(_cloth_stretch(sim, res, size).max())
            substeps[key] = sim.world.substep_frames
            settle[key] = sim.world.solver.joint.extra_steps if joint else 0
            x = sim.cloth_positions("cloth").astype(np.float64)
            d = _box_sdf_from_mesh(sim, x)
            thickness = sim.world.cloths["cloth"].thickness
            assert d.min() > -0.1 * thickness
            assert (d < thickness).sum() > 0.2 * res * res  # draped over the top, not slid off
    assert worst[3, 0, 10] < 0.03
    assert worst[3, 3, 10] < min(0.005, worst[3, 0, 10] / 4)
    assert run_worst[3, 3, 10] < 0.02 < 0.2 < run_worst[3, 0, 10]
    assert worst[3, 3, 40] < 0.005 and run_worst[3, 3, 40] < 0.02
    assert settle[3, 3, 40] < settle[3, 3, 10] / 2
    assert substeps[3, 3, 10] == {10: 90}
    assert max(substeps[3, 3, 40]) > 20 and substeps[3, 3, 40][10] > 45  # more only while it moves fast


@pytest.mark.slow
def test_drape_box_no_penetration_full():
    """The full 163 x 163 drape_box cloth never sinks into the box deeper than 10 % of its thickness."""
    deepest, thickness, closest = _drape_penetration({}, 150)
    assert deepest <= 0.1 * thickness
    assert closest < 0.75 * thickness


def test_vertical_rope_pinned_at_both_ends_is_stable():
    """A straight vertical rope pinned at both ends (collinear rods: one redundant constraint) stays put, rods within 1 %."""
    text = _rod_level((0.0, 1.0, 0.0), (0.0, 0.6, 0.0), pins=("start", "end"), substeps=4)
    sim = _sandbox(text.replace("segments: 1", "segments: 8"))
    x0 = sim.rope_positions("rod")
    for _ in range(10):
        row = sim.step()
        assert row["retries"] == 0 and row["strain"]["rod"] <= 0.01
    np.testing.assert_allclose(sim.rope_positions("rod"), x0, atol=1e-3)


REACH_LEVEL = """
version: 1
name: reach
scene:
  gravity: [0, -9.81, 0]
  ground: {{height: 0.0}}
  ropes:
    - {{name: cord, points: [[0, 1, 0], [0.5, 1, 0]], rod_length: 0.02, radius: 0.004, pins: [start]}}
sim: {{fps: 60, substeps: 20, iterations: 3, max_retries: 0, frames: 200}}
fsm:
  - {{run: MoveTo, with: {{body: cord, sites: [end], to: [{far}, 1.0, 0.2], speed: 1.5, tolerance: 0.002}}}}
  - {{run: Wait, with: {{seconds: 0.3}}}}
  - {{run: MoveTo, with: {{body: cord, sites: [end], to: [0.3, 1.0, 0.1], speed: 1.0, tolerance: 0.002}}}}
  - {{run: Wait, with: {{seconds: 0.5}}}}
"""


def test_rope_driven_beyond_its_reach_stretches_evenly_and_recovers():
    """A pinned rope whose other end is driven 60 % beyond its length stretches evenly along the straight line, then comes back to its length."""
    far = 0.78
    sim = _sandbox(REACH_LEVEL.format(far=far))
    length = 0.5
    span = math.hypot(far, 0.2)
    held = {"strain": 0.0}
    while sim.fsm_state.startswith("0") or sim.fsm_state.startswith("1"):
        row = sim.step()  # max_retries 0: a blow-up raises at once
        x = sim.rope_positions("cord")
        if sim.fsm_state.startswith("1"):  # held at full stretch
            rods = np.linalg.norm(np.diff(x, axis=0), axis=1)
            # Every rod carries the same share of the excess ...
            np.testing.assert_allclose(rods / 0.02 - 1.0, span / length - 1.0, atol=1e-3)
            # ... and the rope lies on the straight line from pin to hand.
            d = x - x[0]
            u = (x[-1] - x[0]) / np.linalg.norm(x[-1] - x[0])
            off = np.linalg.norm(d - np.outer(d @ u, u), axis=1)
            assert off.max() < 2e-3
            held["strain"] = row["strain"]["cord"]
    assert held["strain"] > 0.5
    while sim.fsm_state != "success":
        row = sim.step()
    assert row["strain"]["cord"] < 0.01  # back within reach: the rods have their length again
    assert np.isfinite(sim.rope_positions("cord")).all()


# ------------------------------------------------------------------ stability
def test_explosion_rolls_back_and_raises(monkeypatch):
    """A frame that keeps blowing up is retried with doubled substeps, then raises SimulationUnstable and keeps the last good state."""
    sim = _sandbox(_rod_level((0.0, 1.0, 0.0), (0.01, 1.0, 0.0), gravity=(0.0, -1e3, 0.0), substeps=10,
                              max_retries=3))
    world = sim.world
    tried = _spy_substeps(monkeypatch, world)
    monkeypatch.setattr(world, "_blown_up", lambda m: True)  # every attempt blows up
    x0, v0 = world.positions().copy(), world.velocities().copy()
    with pytest.raises(SimulationUnstable) as info:
        sim.step()
    assert tried == [10, 20, 40, 80]
    message = str(info.value)
    assert "frame 0" in message and "3 retries" in message and "80 substeps" in message
    assert "200 m/s" in message
    x, v = world.positions(), world.velocities()
    assert np.isfinite(x).all() and np.isfinite(v).all()
    np.testing.assert_array_equal(_bits(x), _bits(x0))
    np.testing.assert_array_equal(_bits(v), _bits(v0))
    assert sim.frame == 0 and sim.time == 0.0


def test_one_retry_is_enough():
    """A landing that leaves too much speed with 1 substep succeeds on its single retry with 2, keeping the retried result."""
    fps, r = 60, 1e-3
    dt = 1.0 / fps
    # A drop of 0.3 g dt^2 lands within the frame: with 1 substep it ends at 0.3 g dt,
    # with 2 substeps (first half in the air) at 0.1 g dt.
    y0 = r + 0.3 * G * dt * dt
    sim = _sandbox(_rod_level((0.0, y0, 0.0), (0.01, y0, 0.0), ground="{height: 0.0, friction: 0.5}",
                              fps=fps, substeps=1, max_retries=1, radius=r))
    sim.world.explode_speed = 0.2 * G * dt
    row = sim.step()
    assert row["retries"] == 1
    assert sim.world.retries_total == 1
    v = sim.world.velocities()
    np.testing.assert_allclose(v[:, 1], -0.1 * G * dt, rtol=1e-3)
    np.testing.assert_allclose(sim.rope_positions("rod")[:, 1], r, rtol=1e-5)
    assert row["max_speed"] < sim.world.explode_speed
    row = sim.step()
    assert row["retries"] == 0 and sim.frame == 2


def test_unfused_iterations_step_like_the_fused_substep(monkeypatch):
    """Past FUSE_ITERATIONS a substep runs as several launches instead of one unrolled kernel (whose
    compile time grows too fast: a rope scene at 8 iterations compiled for minutes). At 3 iterations
    on rope_hang (ropes, an object, the ground), the whole substep in one kernel and in chunks of 1
    (the shipped chunk) give the same result: the same passes in the same order. So does each launch
    cut into kernels of at most 2 passes (``MAX_PASSES``)."""
    from sandbox.solvers import xpbd

    overrides = {"sim.iterations": 3}
    finals = []
    for fuse, chunks, most in ((3, (1, 0), 99), (1, (3, 0), xpbd.MAX_PASSES), (3, (1, 0), 2)):
        monkeypatch.setattr(xpbd, "FUSE_ITERATIONS", fuse)
        monkeypatch.setattr(xpbd, "MAX_PASSES", most)
        with Sandbox.from_level(LEVELS / "rope_hang.yaml", arch="cpu", overrides=overrides) as sim:
            assert sim.world.solver.fused == (fuse == 3)
            assert sim.world.solver.chunks == chunks
            if most == 2:
                stages = sim.world.solver.stages
                runs = sim.world.solver._runs(stages)
                assert sum(runs, ()) == stages
                assert all(len(r) <= 2 for r in runs)
                assert len(runs) < len(stages)  # passes are still fused
            start = sim.world.positions().astype(np.float64)
            for _ in range(30):
                sim.step()
            finals.append(sim.world.positions().astype(np.float64))
    moved = np.abs(finals[0] - start).max()
    assert moved > 0.01
    for other in finals[1:]:
        np.testing.assert_allclose(other, finals[0], rtol=0, atol=1e-6)


def test_a_block_of_passes_repeated_back_to_back_is_one_kernel_launched_per_repeat():
    """(contacts, re-sweep) twice is one kernel launched twice, not two copies in one kernel; the passes
    around it fuse as before, in the same order."""
    from sandbox.solvers import xpbd as x

    with Sandbox.from_level(LEVELS / "rope_hang.yaml", arch="cpu") as sim:
        s = sim.world.solver
        stages = (x.PREDICT, x.CONTACTS, x.RESWEEP, x.CONTACTS, x.RESWEEP, x.CONTACTS, x.VELOCITIES)
        assert s._runs(stages) == [(x.PREDICT,), (x.CONTACTS, x.RESWEEP), (x.CONTACTS, x.RESWEEP),
                                   (x.CONTACTS, x.VELOCITIES)]
        assert s._runs((x.ROPE_INEXT,) + (x.FINAL_SWEEP,) * 3 + (x.VELOCITIES,)) == \
            [(x.ROPE_INEXT,)] + [(x.FINAL_SWEEP,)] * 3 + [(x.VELOCITIES,)]
        parts = s._split(stages)
        assert parts[1] is parts[2]
        assert s._runs((x.PREDICT, x.CONSTRAINTS, x.CONTACTS)) == [(x.PREDICT, x.CONSTRAINTS, x.CONTACTS)]


# ------------------------------------------------------------------ inelastic contacts
def test_particle_pushed_out_of_the_ground_keeps_no_velocity():
    """A rod started 4 mm inside the ground ends on it at rest: the push is a position fix, not a launch (4 mm per 1/600 s = 2.4 m/s)."""
    r = 0.01
    y0 = r - 0.004
    sim = _sandbox(_rod_level((0.0, y0, 0.0), (0.01, y0, 0.0), ground="{height: 0.0}", radius=r))
    for _ in range(3):
        sim.step()
        x = sim.rope_positions("rod")
        v = sim.world.velocities()
        np.testing.assert_allclose(x[:, 1], r, atol=1e-6)
        # Each substep: fall by g h^2, pushed back, no velocity left along the normal.
        np.testing.assert_allclose(v, 0.0, atol=1e-6)


def _stacked_cloths_level(gap: float) -> str:
    """Two 4 x 4 cloths (1 cm spacing, 1.5 cm thickness), one ``gap`` above the other, no gravity."""
    cloth = """
    - name: {name}
      resolution: [4, 4]
      size: [0.03, 0.03]
      center: [0.0, {y!r}, 0.0]
      mass: 0.01
      damping: 0.0
      self_collision: true"""
    return f"""
version: 1
name: stacked
scene:
  gravity: [0.0, 0.0, 0.0]
  cloths:{cloth.format(name="low", y=0.5)}{cloth.format(name="high", y=0.5 + gap)}
sim: {{fps: 60, substeps: 10, iterations: 1, frames: 10}}
fsm:
  - {{run: Wait, with: {{ticks: 100000}}}}
"""


def test_self_collision_separates_layers_without_throwing_them():
    """Two layers 5 mm apart (thickness 15 mm) are pushed apart and not thrown apart.

    Read back as velocity, the pushes of the first substep (5 mm each way in
    1/600 s) would part the layers at about 1.3 m/s each: 0.17 m apart after
    three frames. Made inelastic, only what the cloth's own constraints pass on
    from pushed to unpushed particles is left: 0.085 m/s with one chain sweep,
    0.105 m/s with the three an inextensible cloth gets (the later sweeps
    re-solve the rows and columns the pushes bent).
    """
    sim = _sandbox(_stacked_cloths_level(0.005))
    target = sim.world.solver.selfcol.target
    assert target == pytest.approx(0.015, rel=1e-3)
    for _ in range(3):
        sim.step()
    low, high = sim.cloth_positions("low"), sim.cloth_positions("high")
    v = sim.world.velocities()
    gap = high[:, 1].min() - low[:, 1].max()
    assert 0.99 * target < gap < 1.5 * target
    n = len(low)
    assert v[n:, 1].mean() - v[:n, 1].mean() < 0.15  # parting speed (1.3 m/s each way if thrown)
    assert np.abs(v).max() < 0.2
    # The scene is its own mirror image across the mid-plane, and so is the motion.
    np.testing.assert_allclose(v[:n, 1].mean(), -v[n:, 1].mean(), atol=1e-4)


def test_segments_cut_a_substep_around_the_passes_some_substeps_skip():
    """``_segments`` (closed form): runs of passes of one optional group become launches of their own, the
    passes between them stay fused, and nothing is reordered."""
    from sandbox.solvers import xpbd as x

    stages = (x.PREDICT, x.CONSTRAINTS, x.SELF_LISTS, x.SELF_COLLIDE, x.CONTACTS, x.JOINT, x.VELOCITIES)
    got = x._segments(stages, {x.SELF_LISTS: 0, x.SELF_COLLIDE: 0, x.JOINT: 1})
    assert got == (((x.PREDICT, x.CONSTRAINTS), None), ((x.SELF_LISTS, x.SELF_COLLIDE), 0),
                   ((x.CONTACTS,), None), ((x.JOINT,), 1), ((x.VELOCITIES,), None))
    assert sum((s for s, _ in got), ()) == stages
    assert x._segments(stages, {}) == ((stages, None),)


@pytest.mark.parametrize("every", [1, 3])
def test_a_substep_launches_exactly_its_variants_passes(every):
    """Whatever a substep skips (self-collision on all but every k-th and the last), the segments it launches are,
    in order, the passes of its variant; with nothing skipped the substep is one fused kernel but for the joint
    step, a launch of its own."""
    with Sandbox.from_level(LEVELS / "drape_box.yaml", arch="cpu",
                            overrides={"sim.self_collision_every": every, "sim.cloth_joint_every": every}) as sim:
        s = sim.world.solver
        from sandbox.solvers.xpbd import JOINT

        if every == 1:
            assert [p for p, g in s.segments if g is not None] == [(JOINT,)] and len(s.segments) == 3
        for k in range(5):
            skips = s._skips(k, 5)
            launched = sum((p for p, g in s.segments if g is None or not skips[g]), ())
            assert launched == s.variants[skips][0]


@pytest.mark.parametrize("over", ["rope", "sphere"])
def test_a_frictionless_rope_over_a_rope_or_a_solid_slides_at_the_closed_form_speed(over):
    """A rope hung half a turn over a held rope or a fixed sphere, its ends pulled with F1 and 1.5 F1 against
    drags b (``tools/capstan.py``), frictionless: it slides at (F2 - F1) / (2 b), within 10 % (the contacts
    and the chain step take no speed out of a rope drawn round a curve). With friction the capstan equation's
    threshold is not met yet, and the speeds turn on rounding: docs/benchmarks.md, "Rope friction" and
    "On a solid"."""
    import sys

    sys.path.insert(0, str(ROOT / "tools"))
    import capstan

    v = capstan.slide_speed(0.0, 1.5, 4.0, "cpu", over=over)
    assert v == pytest.approx(capstan.closed_form(0.0, 1.5), rel=0.1)
