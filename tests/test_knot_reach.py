"""Crossing's contact_spread, and Winding's straightened run and pinch kept within the rope's reach."""

import numpy as np
import pytest

from sandbox.levels import LevelError, load_level_from_string

import sandbox.maneuvers  # noqa: F401
from tests.levelkit import shipped_world, world_from_text as _world
from tests.test_cloth_strands import HEAD
from tests.test_knotting import TOUCHING, TWO_ROPES

# rope_wind with its crossing pinched for the whole winding (and the time that takes).
PINCHED = {"fsm.1.with.pinch": True, "fsm.1.timeout": 300}


TOUCHING_SLACK = (TOUCHING.replace("OFFSET", "0.1, contact_spread: 0.12")
                  .replace("[[-0.3, 0.5, 0], [0.3, 0.5, 0]]", "[[-0.3, 0.5, 0], [0.2, 0.5, 0], [0.2, 0.7, 0]]")
                  .replace("[[0, 0.512, -0.3], [0, 0.512, 0.3]]", "[[0, 0.512, -0.3], [0, 0.512, 0.2], [0, 0.712, 0.2]]"))


def test_crossing_contact_spread_carries_the_bottoms_apart_within_reach():
    """contact_spread: the pinched bottoms go to either side of the knot, each on its own tip's side,
    never further from its contact than the pinched rope or from its tip than the rope between them,
    and no rod stretches on the way."""
    w = _world(TOUCHING_SLACK)
    w.step()
    m = w.fsm._maneuver
    a, b = w.rope("A"), w.rope("B")
    bases = [idx for idx, _, ways in m.moves if len(ways) == 1]  # the carried bottoms: C's (B), then T's (A)
    goals = [ways[0] for _, _, ways in m.moves if len(ways) == 1]
    assert len(bases) == 2
    tips = [b.end - 1, a.end - 1]
    x0 = w.positions().astype(np.float64)
    axis = x0[tips[1]] - x0[tips[0]]
    axis[1] = 0.0
    centre = 0.5 * (m.contacts[0] + m.contacts[1])
    assert float((goals[0] - centre) @ axis) < 0 < float((goals[1] - centre) @ axis)
    # Carried apart by about the spread (C's is drawn a little towards its lifted tip, whose reach binds).
    assert 0.10 < float(np.linalg.norm((goals[1] - goals[0])[[0, 2]])) < 0.125
    for base, goal, contact, tip in zip(bases, goals, m.contacts, tips):
        assert np.linalg.norm(goal - contact) <= 0.95 * 0.1 + 1e-9
        lifted = x0[tip] + m.params.lift * np.array([0.0, 1.0, 0.0])
        assert np.linalg.norm(goal - lifted) <= m.params.slack * 0.01 * abs(tip - int(base[0])) + 1e-9
    worst = 0.0
    for _ in range(120):
        w.step()
        for r in (a, b):
            seg = np.linalg.norm(np.diff(w.positions()[r.start:r.end], axis=0), axis=1)
            worst = max(worst, float(np.abs(seg / 0.01 - 1).max()))
        if w.fsm.finished:
            break
    x = w.positions().astype(np.float64)
    for base, goal in zip(bases, goals):
        assert w.control.is_driven(base).all()
        np.testing.assert_allclose(x[base[0]], goal, atol=1e-5)
    assert worst < 0.01


def test_crossing_keeps_its_tips_within_reach_of_where_their_bottoms_end():
    """A bottom carried apart whose place lies in an object ends a radius clear of it (here 1 cm lower,
    away from its tip): its tip's waypoints are kept within the rope's reach of that end, not of the
    place first planned (from there they were 8.5 mm past it, and the tail was drawn taut from its pinch)."""
    text = TOUCHING_SLACK.replace(
        "  ropes:", "  objects:\n    - {name: lid, shape: box, params: {size: [0.05, 0.055, 0.05]}, "
                    "position: [-0.035, 0.545, 0.055]}\n  ropes:")
    w = _world(text)
    w.step()
    m = w.fsm._maneuver
    tips, bottoms = m.moves[:2], m.moves[2:]
    moved = bottoms[0][2][-1]
    assert abs(moved[1] - (0.545 - 0.006)) < 1e-4  # out through the lid's underside, a radius clear
    for (idx, _, ways), (bottom, _, end) in zip(tips, bottoms):
        rope = w.strand("A") if w.strand("A").has(int(np.atleast_1d(idx)[0])) else w.strand("B")
        reach = m.params.slack * rope.rod_length * abs(float(rope.along(idx).mean() - rope.along(bottom).mean()))
        over = max(float(np.linalg.norm(q - end[-1])) for q in ways) - reach
        assert over <= 1e-9, over


def test_crossing_contact_spread_on_taut_ropes_keeps_the_bottoms_within_reach():
    """Ropes pinned taut: no place apart is within reach of both the contact and the tip, so the
    bottoms move only as far as keeps them within both, and nothing stretches."""
    w = _world(TOUCHING.replace("OFFSET", "0.1, contact_spread: 0.12"))
    w.step()
    m = w.fsm._maneuver
    x0 = w.positions().astype(np.float64)
    tips = [w.rope("B").end - 1, w.rope("A").end - 1]
    carried = [(idx, ways[0]) for idx, _, ways in m.moves if len(ways) == 1]
    for (base, goal), contact, tip in zip(carried, m.contacts, tips):
        lifted = x0[tip] + m.params.lift * np.array([0.0, 1.0, 0.0])
        now = x0[base[0]]
        assert np.linalg.norm(goal - contact) <= max(0.095, np.linalg.norm(now - contact)) + 1e-7
        assert np.linalg.norm(goal - lifted) <= max(0.9 * 0.01 * (tip - base[0]), np.linalg.norm(now - lifted)) + 1e-7


@pytest.mark.parametrize("extra, message", [
    ("contact_spread: 0.1", "contact_spread carries two pinched bottoms apart"),
    ("contact_offset: 0.04, contact_spread: 0.1", "more than the rope between the two pinches allows"),
])
def test_contact_spread_needs_two_pinched_contacts_and_the_rope_for_it(extra, message):
    text = TOUCHING.replace("contact_offset: OFFSET", extra)
    if "contact_offset" not in extra:
        text = text.replace("active_base: contact, target_base: contact,", "")
    with pytest.raises(LevelError) as err:
        load_level_from_string(text)
    assert message in str(err.value)


def test_winding_pinch_keeps_the_next_particle_one_rod_from_the_crossing():
    """A pinched crossing particle stays where G was traced; as T moves G is traced again, and the next
    particle's command is put one rod from the held one rather than on the new G (which compressed that
    rod by ~5 % here before): over the whole winding that rod stays within 1 %."""
    w = shipped_world("rope_wind.yaml", PINCHED)
    worst, m = 0.0, None
    while w.fsm.state != "2:Wait" and not w.fsm.finished:
        w.step()
        if w.fsm.state == "1:Winding":
            m = w.fsm._maneuver
            x = w.positions()
            worst = max(worst, abs(float(np.linalg.norm(x[m._particle(0)] - x[m._particle(1)])) / m.c.rod_length - 1))
    assert w.fsm.state == "2:Wait"
    assert worst < 0.01
    held = m._particle(0)
    assert w.control.is_driven([held])[0]
    x = w.positions().astype(np.float64)
    np.testing.assert_allclose(m._keep_holds(held + 1, x[held] + [0.0, 0.003, 0.0]),
                               x[held] + [0.0, m.c.rod_length, 0.0], atol=1e-7)
    free = m._particle(m.n - 1) + 3  # its neighbours are not held: the command is left alone
    assert not w.control.is_driven([free - 1, free + 1]).any()
    np.testing.assert_array_equal(m._keep_holds(free, x[free] + 0.003), x[free] + 0.003)


def test_winding_keeps_the_driven_particle_within_reach_of_holds_further_along_the_rope():
    """With the crossing pinched, a particle k >= 2 rods past it is commanded at most 1.005 k rods from
    it (a command past that, here 0.3 m away, is pulled back along the line onto that reach); a command
    within reach, or with no hold on the rope but its own, is left alone."""
    w = shipped_world("rope_wind.yaml", PINCHED)

    def handed_over(m) -> bool:  # the particle laid last let go (the frame after it is laid)
        return m.k >= 4 and not w.control.is_driven([m._particle(m.k - 1)])[0]

    while not (w.fsm.state == "1:Winding" and handed_over(w.fsm._maneuver)):
        w.step()
    m = w.fsm._maneuver
    held, idx = m._particle(0), m._particle(m.k)
    assert w.control.is_driven([held])[0] and not w.control.is_driven([idx - 1, idx + 1]).any()
    k = idx - held
    assert k >= 4
    x = w.positions().astype(np.float64)
    hand = w.control.target([held])[0].astype(np.float64)
    far = hand + np.array([0.0, 0.3, 0.0])
    np.testing.assert_allclose(m._keep_holds(idx, far), hand + np.array([0.0, 1.005 * k * m.c.rod_length, 0.0]),
                               atol=1e-7)
    near = hand + np.array([0.0, 1.004 * k * m.c.rod_length, 0.0])
    np.testing.assert_array_equal(m._keep_holds(idx, near), near)
    w.control.release([held])
    np.testing.assert_array_equal(m._keep_holds(idx, far), far)
    assert np.linalg.norm(x[idx] - hand) < 0.3


BENT = """
version: 1
name: bent
scene:
  ropes:
    - {name: T, points: [[-0.5, 0.5, 0], [0, 0.5, 0], [0, 0.5, 0.5]], rod_length: 0.02, radius: 0.01,
       pins: [start, end, 31]}
    - {name: C, points: [[0.02, 0.8, -0.05], [0.02, 0.517, -0.05], [0.02, 0.2, 0.85]], rod_length: 0.01,
       radius: 0.005, pins: [start]}
sim: {fps: 60, substeps: 20, iterations: 4}
fsm:
  - {run: Winding, with: {active: C, target: T, theta: 45, w0: 1, straighten: 0.2, start: 31}, timeout: 60}
"""
# C passes 2 cm beside T's bend, clear of it: its particle 31 is nearest T's particle 25, the bend, by
# 8 mm over the next. (Laid through T's axis, C was pushed out of T up or down by rounding, and X_T
# moved between particles 25 and 31 with the compile settings.)


def test_straightened_run_stops_short_of_a_held_particle_it_cannot_reach():
    """T bends at X_T (its particle 25) and is held 6 rods past it: straightening 5 rods on each
    side along the chord would put the run's end far from the held particle 31, or on it. The run
    is cut back on that side instead (never
    over a held particle), each end within reach of the held particle beyond it, and once the hands
    have brought the run there no rod of T stretches."""
    w = _world(BENT)
    t = w.rope("T")
    w.step()
    m = w.fsm._maneuver
    assert m.j0 == 25
    run = m.straight - t.start
    assert run.min() < m.j0 <= run.max() < 30  # the held side cut back, short of 31
    from sandbox.maneuvers.winding import REACH_SLACK

    laid = w.control.target(m.straight)
    for end, h in ((0, 0), (-1, 31)):  # the pinned start, the held particle 31
        gap = float(np.linalg.norm(laid[end] - w.control.target([t.start + h])[0]))
        assert gap <= REACH_SLACK * abs(int(run[end]) - h) * t.rod_length + 1e-6
    w.step()  # the first frame carries the run up to 2 cm onto the chord in one step
    x = w.rope_positions("T").astype(np.float64)
    np.testing.assert_allclose(x[31], [0.0, 0.5, 0.12], atol=1e-6)
    seg = np.linalg.norm(np.diff(x, axis=0), axis=1)
    assert np.abs(seg / 0.02 - 1).max() < 0.01


# -- every hold of the rope ------------------------------------------------------------------------

# Hands also hold each rope three rods below its tip.
HELD_NEAR_TIP = (TWO_ROPES.replace("sites: [start, end]", "sites: [start, 22, end]")
                 .replace(", timeout: 300", "").replace("SIGN", "1"))


def test_within_holds_projects_onto_the_reach_of_every_hold():
    from sandbox.maneuvers.knotting import within_holds
    now = np.zeros(3)
    holds = [(10, np.array([0.0, 0.0, 0.0])), (0, np.array([0.0, -0.2, 0.0]))]
    # Particle 13 (3 rods of 0.02 m from particle 10, 13 from particle 0); slack 1.
    p, limit = within_holds(np.array([0.5, 0.0, 0.0]), 13.0, holds, 0.02, 1.0, now)
    assert limit == 10
    np.testing.assert_allclose(p, [0.06, 0.0, 0.0], atol=1e-12)  # onto the near ball, along the line
    q = np.array([0.01, 0.02, 0.0])
    same, none = within_holds(q, 13.0, holds, 0.02, 1.0, now)
    assert none is None and same is q
    # A particle now farther than its reach keeps that distance (a near-taut rope is not pulled in).
    far_now = np.array([0.08, 0.0, 0.0])
    p, _ = within_holds(np.array([0.0, 0.5, 0.0]), 13.0, holds[:1], 0.02, 1.0, far_now)
    np.testing.assert_allclose(np.linalg.norm(p - holds[0][1]), 0.08, atol=1e-9)
    # Two balls that meet: the result lies in both.
    p, limit = within_holds(np.array([0.0, 0.3, 0.0]), 13.0, [(10, np.zeros(3)), (16, np.array([0.1, 0.0, 0.0]))],
                            0.02, 1.0, np.array([0.05, 0.0, 0.0]))
    assert np.linalg.norm(p) <= 0.06 + 1e-6 and np.linalg.norm(p - [0.1, 0.0, 0.0]) <= 0.06 + 1e-6


def test_crossing_keeps_its_tips_within_reach_of_particles_other_hands_hold():
    """Hands hold A and B three rods below their tips: the Crossing moves each tip only as far as that
    rope reaches, nothing stretches, and as the strands then cannot meet, the failure names the holds."""
    w = _world(HELD_NEAR_TIP)
    a = w.rope("A")
    tip, held = a.end - 1, a.start + 22
    w.step()  # A's Anchoring: the hands hold where the particles are
    hand, tip0 = w.control.target([held])[0], w.control.target([tip])[0]
    for _ in range(2):
        w.step()
    m = w.fsm._maneuver
    (idx, pos, ways), = [mv for mv in m.moves if tip in np.atleast_1d(mv[0])]
    reach = max(0.95 * 3 * 0.02, float(np.linalg.norm(tip0 - hand)))  # 3 rods, or as far as it is
    assert np.linalg.norm(ways[-1] - tip0) > 0.02  # it does move
    for q in ways:
        assert np.linalg.norm(q - hand) <= reach + 1e-6
    worst = 0.0
    for _ in range(400):
        w.step()
        for r in (a, w.rope("B")):
            seg = np.linalg.norm(np.diff(w.positions()[r.start:r.end], axis=0), axis=1)
            worst = max(worst, float(np.abs(seg / 0.02 - 1).max()))
        if w.fsm.finished:
            break
    assert worst < 0.01
    assert w.fsm.finished and not w.fsm.succeeded
    failed = [e["message"] for e in w.fsm.events if e["type"] == "failed"]
    assert "held back by A's particle 22" in failed[-1], failed
    assert "B's particle 22" in failed[-1], failed


def test_straightened_run_keeps_a_rod_to_a_held_particle_next_to_it_at_its_length():
    """On a straight T the run's end (30) lands next to T's particle 31, which a hand holds: where the
    hand holds it closer or farther than a rod (by more than half a percent), the rod between them
    would be compressed or stretched between two held particles, so the run stops one particle earlier;
    within that it reaches 30. Where the hand holds 31 counts, not where 31 is on its way there."""
    w = _world(BENT)
    t = w.rope("T")
    w.step()
    m = w.fsm._maneuver
    m.j0 = 25  # the rule is about a run ending next to 31, wherever the first frame put X_T
    assert w.control.is_driven([t.start + 31])[0]
    w.control.release(m.straight)  # each run below is laid afresh: no earlier run held
    rod = t.rod_length
    line = np.array([-0.5, 0.5, 0.0]) + np.arange(t.end - t.start)[:, None] * np.array([rod, 0.0, 0.0])
    for gap, end in ((0.9, 29), (0.994, 29), (1.0, 30), (1.004, 30), (1.006, 29)):
        xt = line.copy()
        w.control.drive([t.start + 31], (xt[30] + gap * np.array([rod, 0.0, 0.0]))[None, :])
        xt[31] = xt[30] + np.array([0.0, 0.0, 0.3])  # the hand's target counts, not where 31 is now
        laid = m._straighten(xt)
        w.control.release(laid)
        run = laid - t.start
        assert run.max() == end, (gap, run)


def test_nothing_is_straightened_where_x_t_is_out_of_reach_of_a_held_particle():
    """X_T two rods from T's particle 31, which a hand holds 2 % farther than that: holding X_T where it is
    would stretch the rods between, so no run is held straight; within reach the run is laid as before."""
    w = _world(BENT)
    t = w.rope("T")
    w.step()
    m = w.fsm._maneuver
    w.control.release(m.straight)
    rod = t.rod_length
    line = np.array([-0.5, 0.5, 0.0]) + np.arange(t.end - t.start)[:, None] * np.array([rod, 0.0, 0.0])
    m.j0 = 29
    for gap, laid_any in ((2.04, False), (2.0, True)):
        w.control.drive([t.start + 31], (line[29] + gap * np.array([rod, 0.0, 0.0]))[None, :])
        laid = m._straighten(line.copy())
        w.control.release(laid)
        assert (len(laid) > 0) == laid_any, gap
        if laid_any:
            assert (laid - t.start).max() == 30 and (laid - t.start).min() < 29


def _winding_world(**extra):
    w = shipped_world("rope_wind.yaml", {"fsm.1.timeout": 300, **{f"fsm.1.with.{k}": v for k, v in extra.items()}})
    while not (w.fsm.state == "1:Winding" and w.fsm._maneuver.k >= 2):
        w.step()
    return w, w.fsm._maneuver


def test_winding_retrace_keeps_the_count_of_targets_on_g_within_one():
    """G traced again: a count of samples one off the count before is brought back to it (the last
    sample dropped, or one more rod along G's last tangent); two off, the new count stands."""
    from sandbox.geometry.tube import sample_targets

    w, m = _winding_world()
    xt = w.rope_positions("T").astype(np.float64)
    natural = m._targets(xt)
    n = m.n_turns
    assert n == len(sample_targets(m.geodesic, m.c.rod_length)) == len(natural)
    fewer = m._targets(xt, keep=n - 1)
    assert m.n_turns == n - 1
    np.testing.assert_allclose(fewer, natural[: n - 1])
    more = m._targets(xt, keep=n + 1)
    assert m.n_turns == n + 1
    np.testing.assert_allclose(more[:n], natural)
    np.testing.assert_allclose(np.linalg.norm(more[n] - more[n - 1]), m.c.rod_length)
    np.testing.assert_allclose((more[n] - more[n - 1]) / m.c.rod_length,
                               (natural[-1] - natural[-2]) / np.linalg.norm(natural[-1] - natural[-2]), atol=1e-9)
    m._targets(xt, keep=n + 2)
    assert m.n_turns == n


def test_winding_exit_keeps_its_line_once_the_turns_are_laid_while_t_moves():
    """T moved by 2 cm: G and every target are traced again while turns are being laid; once they are
    (the particle to drive is on the exit), the exit line stays where it was."""
    w, m = _winding_world(exit=0.05)
    read = w.positions
    t_idx = m.t.idx

    def moved():
        x = read().copy()
        x[t_idx] += 0.02
        return x

    w.positions = moved
    before = m.targets.copy()
    m.update()
    assert np.linalg.norm(m.targets - before, axis=1).max() > 0.01  # re-traced on the moved T
    w.positions = read
    m.update()  # back where it was
    m.k = m.n_turns  # the turns laid: the next particle goes to the first exit target
    before = m.targets.copy()
    w.positions = moved
    m.update()
    np.testing.assert_array_equal(m.targets, before)


def test_crossing_takes_a_waypoint_inside_an_object_out_to_its_clearance():
    """A box holds the place A's tip is sent to: a hand keeps its particle a radius clear of every
    surface, so it would never reach that waypoint (the Crossing would wait for it until the level ran
    out of frames). The waypoints are taken out of the box to the radius instead (the nearest face, x
    min; the box stands on its position), and the crossing is made."""
    text = TWO_ROPES.replace("SIGN", "1").replace(
        "  ropes:", "  objects:\n    - {name: lid, shape: box, params: {size: [0.06, 0.06, 0.06]}, position: [0.2, 0.604, 0.02]}\n"
                    "  ropes:")
    w = _world(text)
    for _ in range(3):
        w.step()  # the Anchorings, then the Crossing plans
    m = w.fsm._maneuver
    ways = np.array([q for _, _, wp in m.moves for q in wp])
    d, _, _ = w.objects.query_numpy(ways)
    assert d.min() >= 0.008 - 1e-5
    a_tip = w.rope("A").end - 1
    goal = [wp[-1] for idx, _, wp in m.moves if a_tip in np.atleast_1d(idx)][0]
    assert abs(goal[0] - (0.17 - 0.008)) < 1e-4  # out through the nearest face, not left in the box
    for _ in range(300):
        w.step()
        if w.fsm.finished:
            break
    assert w.fsm.succeeded, w.fsm.events[-3:]


STRIP_FROM_UNDER = HEAD.replace("name: cloth_strands", "name: strip_from_under") + """    - {name: F, resolution: [161, 5], size: [1.6, 0.04], center: [0, 0.13, 0], mass: 0.05, self_collision: true,
       bend_compliance: 0.5, friction: 0.6}
sim: {fps: 60, substeps: 20, iterations: 2, frames: 300}
fsm:
  - {run: Anchoring, with: {body: F, sites: [center], object: box}}
  - {run: Wait, with: {seconds: 0.5}}
  - {run: Crossing, with: {active: "F.[80,2]..[160,2]", target: "F.[80,2]..[0,2]", active_tip: end, target_tip: end,
                           height: 0.12, slack: 0.95}, timeout: 240}
success:
  - {metric: fsm_state, equals: success}
"""


def test_crossing_hand_stops_short_where_its_strand_is_drawn_taut_round_an_edge():
    """A 4 cm strip under a box set on its middle: each half leaves from under the box (held there by its
    weight) and goes round the box's edge to its tip, while the Crossing plans the tips' reach as a straight
    line from the hold. Where a half is drawn taut (a rod past ``TAUT_STRAIN``) its hand goes back a frame and
    stops there: the strip is stretched past that in one frame at most, not pulled on (it was stretched
    20-60 % frame after frame, and blew up once wound), and the Crossing ends done, saying so."""
    from sandbox.maneuvers.knotting import TAUT_STRAIN

    w = _world(STRIP_FROM_UNDER)
    halves = [w.strand("F.[80,2]..[160,2]"), w.strand("F.[80,2]..[0,2]")]
    over, crossing = 0, None
    while not w.fsm.finished and w.frame < 300:
        w.step()
        m = w.fsm._maneuver
        if m is not None and m.name == "Crossing":
            crossing = m
            x = w.positions().astype(np.float64)
            over += max(float(h.strain(x).max()) for h in halves) > TAUT_STRAIN
    assert w.fsm.succeeded, w.fsm.events[-2:]
    assert crossing is not None and sum(crossing.taut) >= 1
    assert over <= sum(crossing.taut)
    assert "its strand drawn taut" in crossing.note
    x = w.positions().astype(np.float64)
    assert max(float(h.strain(x).max()) for h in halves) < 0.005
