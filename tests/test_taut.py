"""A held stretch of rope drawn taut is not pushed out past taut by rope contacts (rope_chain.taut_f)."""

import numpy as np
import taichi as ti

import sandbox.maneuvers  # noqa: F401
from sandbox.solvers.rope_chain import TAUT
from tests.levelkit import solver_masses, world_from_text as _world

# A rope pinned at both ends 0.4 m apart, 6.3 mm of sag at its middle particle, both halves straight: taut.
TAUT_ROPE = """    - {name: NAME, points: [[-0.2, 0.5, 0], [0.0, 0.4937, 0], [0.2, 0.5, 0]], rod_length: 0.01, radius: 0.006,
       pins: [start, end]}
"""

# V: taut. S: pinned at both ends 0.36 m apart with 0.4 m of rope: slack. F: pinned at its start only.
ROPES = """
version: 1
name: taut
scene:
  gravity: [0, -9.81, 0]
  ropes:
""" + TAUT_ROPE.replace("NAME", "V") + """    - {name: S, points: [[-0.18, 0.8, 0], [0.0, 0.7128, 0], [0.18, 0.8, 0]], rod_length: 0.01, radius: 0.006,
       pins: [start, end]}
    - {name: F, points: [[0.5, 0.8, 0], [0.5, 0.6, 0]], rod_length: 0.01, radius: 0.006, pins: [start]}
sim: {fps: 60, substeps: 20, iterations: 4}
fsm:
  - {run: Wait, with: {seconds: 1.0}}
"""


def _taut_fields(w):
    solver = w.solver

    @ti.kernel
    def fill():
        solver.inext.taut_f(solver.contacts.taut, solver.contacts.taut_n, solver.contacts.room)

    solver_masses(w)
    fill()
    return solver.contacts.taut.to_numpy(), solver.contacts.taut_n.to_numpy(), solver.contacts.room.to_numpy()


def _reference(x, x0, w, ropes):
    """NumPy: e = (|x - h1| + |x - h2|) / L between consecutive held particles: taut, outward normal
    and room (how far along the normal the focal sum reaches L, to first order)."""
    taut = np.zeros(len(x))
    normal = np.zeros((len(x), 3))
    room = np.full(len(x), 1e30)
    for r in ropes:
        held = [i for i in range(r.start, r.end) if w[i] == 0.0]
        for h1, h2 in zip(held, held[1:]):
            reach = np.linalg.norm(np.diff(x0[h1:h2 + 1], axis=0), axis=1).sum()
            for k in range(h1 + 1, h2):
                d1, d2 = x[k] - x[h1], x[k] - x[h2]
                e = (np.linalg.norm(d1) + np.linalg.norm(d2)) / reach
                n = d1 / np.linalg.norm(d1) + d2 / np.linalg.norm(d2)
                room[k] = max(reach * (1.0 - e), 0.0) / np.linalg.norm(n)
                normal[k] = n / np.linalg.norm(n)
                if e > TAUT:
                    taut[k] = min(1.0, (e - TAUT) / (1.0 - TAUT))
    return taut, normal, room


def test_taut_stretch_matches_the_closed_form_and_the_numpy_reference():
    w = _world(ROPES)
    for _ in range(3):
        w.step()
    taut, normal, room = _taut_fields(w)
    x = w.positions().astype(np.float64)
    inv = solver_masses(w)
    ref_taut, ref_normal, ref_room = _reference(x, w.data.x0.astype(np.float64), inv, w.data.ropes)
    v, s, f = (w.rope(n) for n in "VSF")
    # Closed form: the V's middle particle lies on the spheroid (both halves straight): fully taut,
    # its outward normal the bisector of the two halves, straight down (float32 lengths: e is 1 to
    # about 1e-4, a tenth of 1 - TAUT); the slack and the free rope: none.
    mid = v.start + 20
    assert taut[mid] > 0.8
    np.testing.assert_allclose(normal[mid], [0.0, -1.0, 0.0], atol=1e-3)
    assert (taut[v.start + 1:v.end - 1] > 0.5).all()
    assert not taut[s.start:s.end].any() and not taut[f.start:f.end].any()
    assert taut[v.start] == 0.0 and taut[v.end - 1] == 0.0  # the holds themselves
    # Next to no room out at the V's apex (e is 1 to about 1e-4: a fraction of a millimetre along a
    # near-straight V, less than a tenth of its 6.3 mm sag); the slack rope's middle can go out by
    # most of its sag; off held stretches (the free rope, the holds) there is no bound.
    assert room[mid] < 1e-3
    assert room[s.start + 20] > 0.005
    assert (room[f.start:f.end] == 1e30).all() and room[v.start] == 1e30 and room[v.end - 1] == 1e30
    # Kernel against NumPy (float32 positions; e within about 1e-6 of 1 near the boundary).
    np.testing.assert_allclose(taut, ref_taut, atol=2e-2)
    on = ref_taut > 0.1
    np.testing.assert_allclose(normal[on], ref_normal[on], atol=1e-3)
    inside = ref_room < 1.0
    np.testing.assert_array_equal(room >= 1e29, ~inside)
    np.testing.assert_allclose(room[inside], ref_room[inside], atol=2e-4)


# C pinned above the taut V and drawn down across it to the far side: it wraps over the V.
DRAWN = """
version: 1
name: drawn
scene:
  gravity: [0, -9.81, 0]
  ropes:
""" + TAUT_ROPE.replace("NAME", "T") + """    - {name: C, points: [[0.0, 0.6, 0.013], [0.0, 0.3, 0.013]], rod_length: 0.01, radius: 0.006, pins: [start]}
sim: {fps: 60, substeps: 20, iterations: 4}
fsm:
  - {run: MoveTo, with: {body: C, sites: [end], to: [0.0, 0.36, -0.08], speed: 0.3}}
  - {run: MoveTo, with: {body: C, sites: [end], to: [0.0, 0.33, -0.08], speed: 0.1}}
  - {run: Wait, with: {seconds: 0.5}}
"""


def test_a_rope_drawn_across_a_taut_held_rope_wraps_it_and_the_taut_rope_swings_but_does_not_stretch():
    w = _world(DRAWN)
    t, c = w.rope("T"), w.rope("C")
    worst_t = worst_c = swing = 0.0
    gap = np.inf
    for _ in range(90):
        w.step()
        x = w.positions().astype(np.float64)
        xt, xc = x[t.start:t.end], x[c.start:c.end]
        worst_t = max(worst_t, np.abs(np.linalg.norm(np.diff(xt, axis=0), axis=1) / 0.01 - 1).max())
        worst_c = max(worst_c, np.abs(np.linalg.norm(np.diff(xc, axis=0), axis=1) / 0.01 - 1).max())
        swing = max(swing, np.abs(xt[:, 2]).max())
        gap = min(gap, float(w.solver.ropecol.measure().min()))
    assert w.fsm.state == "success"
    assert worst_t < 1e-3 and worst_c < 1e-3  # the V starts 0.05 % short of straight; nothing stretches
    assert gap > -0.1 * 0.006  # no overlap past a tenth of a radius
    assert swing > 1e-3  # still free to swing about its holds: pushed sideways by millimetres
    xc = w.rope_positions("C")
    assert xc[np.abs(xc[:, 1] - 0.5).argmin(), 2] > 0.0  # C lies over T on its own side


# V taut as above; P a single rod pinned at both ends, 5 mm into the V's apex from the side of its holds.
PRESSED = """
version: 1
name: pressed
scene:
  gravity: [0, -9.81, 0]
  ropes:
""" + TAUT_ROPE.replace("NAME", "V") + """    - {name: P, points: [[-0.005, 0.5007, 0], [0.005, 0.5007, 0]], rod_length: 0.01, radius: 0.006,
       pins: [start, end]}
sim: {fps: 60, substeps: 20, iterations: 4}
fsm:
  - {run: Wait, with: {seconds: 0.1}}
"""


def test_a_contact_pass_moves_a_taut_stretch_no_further_out_than_its_room():
    """An immovable rod pressed 5 mm into a taut V: the whole push falls on the V, whose apex has a
    fraction of a millimetre of room; one contact pass moves no V particle out by more than its room
    (without the cap the apex would take millimetres), and the others no further than a rod."""
    w = _world(PRESSED)
    v = w.rope("V")
    taut, normal, room = _taut_fields(w)
    x0 = w.positions().astype(np.float64)
    w.solver.ropecol.solve()
    dx = w.positions().astype(np.float64) - x0
    out = (dx * normal).sum(axis=1)[v.start:v.end]
    inner = slice(1, v.end - v.start - 1)
    assert np.abs(dx[v.start:v.end]).max() > 1e-4  # the pass did push the V
    assert (out[inner] <= room[v.start:v.end][inner] + 1e-6).all(), (out, room[v.start:v.end])
    mid = 20
    assert out[mid] > 0.5 * room[v.start + mid]  # pushed out up to its room, not held in place
