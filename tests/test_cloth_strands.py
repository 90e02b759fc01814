"""Cloth control lines as strands: Crossing, Winding and Tightening take ``F.line1`` wherever they take a rope."""

import functools
import types

import numpy as np
import pytest

import sandbox.maneuvers  # noqa: F401
from sandbox.levels import LevelError, load_level_from_string
from sandbox.model.strands import Strand, base_name, gathered_radius, material_distance, parse_cloth_line
from tests.levelkit import ROOT
from tests.levelkit import world_from_text as _world

HEAD = """
version: 1
name: cloth_strands
scene:
  gravity: [0, -9.81, 0]
  ground: {height: 0.0, friction: 0.6}
  objects:
    - {name: box, shape: box, params: {size: [0.16, 0.12, 0.16]}, position: [0, 0.0, 0], friction: 0.6}
  cloths:
"""

SCENE = HEAD + """    - {name: F, resolution: [25, 25], size: [0.6, 0.6], center: [0, 0.13, 0], mass: 0.1, self_collision: true,
       bend_compliance: 0.5, friction: 0.6}
sim: {fps: 60, substeps: 10, iterations: 1, frames: 400}
fsm:
  - {run: Anchoring, with: {body: F, sites: [center], object: box}}
  - {run: Wait, with: {seconds: 0.5}}
  - {run: Crossing, with: {active: "ACTIVE", target: "TARGET", active_tip: end, target_tip: end, height: 0.12,
                           slack: 0.95}, timeout: 240}
  - {run: Winding, with: {active: "ACTIVE", target: "TARGET", theta: 45, w0: 1, handedness: 1, along: -1}, timeout: 240}
  - {run: Tightening, with: {pulls: [{body: "ACTIVE", site: end, direction: away}, {body: "TARGET", site: end,
                                      direction: away}], knot: ["ACTIVE", "TARGET"], distance: 0.05, speed: 0.2}}
success:
  - {metric: fsm_state, equals: success}
"""


def _scene(active="F.line1", target="F.line3"):
    return SCENE.replace("ACTIVE", active).replace("TARGET", target)


def test_cloth_line_names_parse():
    assert parse_cloth_line("F.line2") == ("F", "center", "B")
    assert parse_cloth_line("F.[3, 4]..center") == ("F", [3, 4], "center")
    assert parse_cloth_line("R[3:9]") is None and parse_cloth_line("R") is None
    assert base_name("F.line1") == "F" and base_name("F.A..[2,3]") == "F" and base_name("R[2:]") == "R"
    with pytest.raises(ValueError, match="line1"):
        parse_cloth_line("F.line5")
    with pytest.raises(ValueError, match="corner A-D"):
        parse_cloth_line("F.E..center")


@functools.cache
def _flat_world():
    return _world(_scene())


def test_a_control_line_is_a_strand_from_the_centre_to_its_corner():
    w = _flat_world()
    cloth = w.cloth("F")
    for k, corner in zip((1, 2, 3, 4), "ABCD"):
        st = w.strand(f"F.line{k}")
        np.testing.assert_array_equal(st.idx, cloth.control_line(k))
        assert st.cloth and st.body == "F" and len(st) == 13
        assert w.site_particles(f"F.line{k}", "start")[0] == cloth.site("center")
        assert w.site_particles(f"F.line{k}", "end")[0] == cloth.site(corner)
        # Diagonal lines: rest spacing sqrt(2) x the grid's 0.025 m.
        assert st.rod_length == pytest.approx(0.025 * np.sqrt(2), rel=1e-5)
    line = w.strand("F.[0,12]..[24,12]")  # the middle row, corner side to corner side
    assert len(line) == 25 and line.rod_length == pytest.approx(0.025, rel=1e-5)
    np.testing.assert_array_equal(w.site_particles("F.[0,12]..[24,12]", [10, 13]), cloth.index(np.arange(10, 13), 12))


def test_two_lines_of_one_cloth_meet_at_its_centre_in_the_material():
    """Their closest pair in the material is the shared centre (0 m); a rope and a cloth are not joined."""
    w = _flat_world()
    a, b = w.strand("F.line1"), w.strand("F.line3")
    m = material_distance(a, b, a.idx, b.idx)
    assert m[0, 0] == 0.0  # both start at the centre
    assert m[-1, -1] == pytest.approx(0.6 * np.sqrt(2), rel=1e-5)  # corner A to corner C
    part = a.part(3, 6)
    assert len(part) == 4 and part.has(int(a.idx[3])) and not part.has(int(a.idx[7]))
    assert part.local(int(a.idx[5])) == 2 and part.along(int(a.idx[5])) == 5
    rope = types.SimpleNamespace(body="R")
    assert material_distance(a, rope, a.idx, a.idx) is None


def _strip(nx=41, nz=11, spacing=0.01, thickness=0.002):
    """A flat strip's ClothRange-like grid, its rest positions and its middle row as a strand."""
    from sandbox.model.builder import ClothRange

    i, j = np.meshgrid(np.arange(nx), np.arange(nz))
    x0 = np.stack([i.ravel() * spacing, 0 * i.ravel(), j.ravel() * spacing - (nz - 1) * spacing / 2], 1).astype(float)
    cloth = ClothRange("S", 0, nx, nz, (spacing, spacing), thickness, np.zeros((0, 3), np.int32), (1, 1, 1),
                       (1, 1, 1), False)
    line = cloth.line_between([0, nz // 2], [nx - 1, nz // 2])
    st = Strand("S.row", "S", line, line, np.full(nx - 1, spacing), 0.5 * thickness, cloth=True,
                rest_pos=x0[line])
    return cloth, x0, st


def test_gathered_radius_of_a_flat_strip_and_of_one_rolled_around_its_line():
    """Closed forms: flat, the 90th percentile of the particles' distances across the strip (+ half the
    thickness); rolled into a cylinder of radius r about the line, r (+ half the thickness)."""
    cloth, x0, st = _strip()
    around = x0[st.idx[20]]
    v = x0[:, 2]  # signed distance across the strip, m
    # The middle row's band: within a quarter of its 0.4 m rest length, i.e. the whole 0.1 m wide strip;
    # of those, the ones within 0.1 m of ``around`` along the line (21 columns).
    flat = gathered_radius(x0, st, cloth, x0, around, length=0.2)
    cols = np.abs(x0[:, 0] - around[0]) <= 0.1 + 1e-9
    assert flat == pytest.approx(np.percentile(np.abs(v[cols]), 90) + 0.001, rel=1e-9)
    r = 0.012
    rolled = np.stack([x0[:, 0], r * np.cos(v / r), r * np.sin(v / r)], 1)
    rolled[st.idx] = np.stack([x0[st.idx, 0], 0 * st.idx, 0 * st.idx], 1)  # the line itself is the roll's axis
    assert gathered_radius(rolled, st, cloth, x0, around, length=0.2) == pytest.approx(r + 0.001, rel=1e-6)


def test_a_bad_cloth_line_is_caught_when_the_level_loads():
    for bad, said in (("G.line1", "unknown cloth 'G'"), ("F.[30,2]..center", "grid points [0, 24] x [0, 24]"),
                      ("F.line7", "F.line1"), ("F.A..A", "runs from a point to itself")):
        with pytest.raises(LevelError, match=said.replace("[", r"\[").replace("]", r"\]")):
            load_level_from_string(_scene(active=bad), base_dir=ROOT / "levels")


RIBBON = HEAD.replace("name: cloth_strands", "name: ribbon") + """    - {name: F, resolution: [121, 3], size: [1.2, 0.02], center: [0, 0.13, 0], mass: 0.05, self_collision: true,
       bend_compliance: 0.5, friction: 0.6}
sim: {fps: 60, substeps: 20, iterations: 2, frames: 400}
fsm:
  - {run: Anchoring, with: {body: F, sites: [center], object: box}}
  - {run: Wait, with: {seconds: 0.5}}
  - {run: Crossing, with: {active: "F.[60,1]..[120,1]", target: "F.[60,1]..[0,1]", active_tip: end, target_tip: end,
                           height: 0.12, slack: 0.95}, timeout: 240}
  - {run: Winding, with: {active: "F.[60,1]..[120,1]", target: "F.[60,1]..[0,1]", theta: 45, w0: 1, handedness: 1,
                          along: -1}, timeout: 240}
success:
  - {metric: fsm_state, equals: success}
"""


def test_a_ribbon_is_crossed_and_wound_by_its_middle_lines():
    """A 2 cm ribbon (121 x 3 particles) laid over a box, its two halves named as lines of its middle row:
    the Crossing brings them across above the box, and the Winding lays C's particles one at a time
    around the tube of the cloth gathered around T. At every frame the hands hold only the anchored
    centre and particles of the two lines, and no target lies within a particle's radius of the box; the
    tube's radii are the ribbon's (the 90th percentile of
    its particles' distances across, 1 cm, plus half the 1.5 cm thickness: 1.75 cm), over a part of T
    as long as a turn covers; the laid particles are C's."""
    w = _world(RIBBON)
    cloth = w.cloth("F")
    c, t = w.strand("F.[60,1]..[120,1]"), w.strand("F.[60,1]..[0,1]")
    lines = set(c.idx.tolist()) | set(t.idx.tolist())
    anchored, winding = None, None
    while w.frame < 300 and (winding is None or winding.k < 4):
        state = w.step().get("fsm_state")
        assert state != "failure", w.fsm.events[-2:]
        m = w.fsm._maneuver
        driven = set(np.flatnonzero(w.control.is_driven(np.arange(cloth.start, cloth.end))).tolist())
        if m is not None and m.name == "Crossing" and anchored is None:
            anchored = driven - lines
        if anchored is not None:
            assert driven - lines <= anchored, f"frame {w.frame}: {sorted(driven - lines - anchored)[:5]} held"
        if m is not None and m.name == "Winding":
            winding = m
            d, _, _ = w.objects.query_numpy(m.targets)
            assert d.min() >= m.c.radius - 1e-5, f"frame {w.frame}: a target {d.min():.4f} m from the box"
    assert anchored and winding is not None and winding.k >= 4
    assert winding.rc == pytest.approx(0.0175, abs=5e-4) and winding.rt == pytest.approx(0.0175, abs=5e-4)
    turn = 2 * np.pi * winding.R / np.tan(np.radians(45)) + 4 * winding.R
    assert len(winding.t) < len(t) and (len(winding.t) - 1) * t.rod_length == pytest.approx(turn, abs=3 * t.rod_length)
    laid = w.record.windings[("F.[60,1]..[120,1]", "F.[60,1]..[0,1]")].particles
    assert len(laid) >= 4 and np.isin(laid, c.idx).all()


def test_a_crossing_bottom_can_be_a_place_the_strand_passes():
    """``active_base`` given as a place (an object's site with an offset in its axes) is the strand's
    particle nearest it: 5 cm from the box's top centre towards corner A along both axes, on the top
    where the cloth lies flat, is control line 1's 2nd particle from the centre (diagonal steps of
    2.5 cm x 2.5 cm)."""
    text = _scene().replace("slack: 0.95}", "slack: 0.95, active_base: {object: box, site: top, offset: [-0.05, 0.0, -0.05]},\n"
                                            "                           target_base: start}")
    w = _world(text)
    while w.fsm._maneuver is None or w.fsm._maneuver.name != "Crossing":
        w.step()
    m = w.fsm._maneuver
    line = w.cloth("F").control_line(1)
    assert m.c_part.idx[0] == line[2] and m.c_part.idx[-1] == line[-1]
    assert m.t_part.idx[0] == w.cloth("F").site("center")


def test_gathered_radius_leaves_out_cloth_beside_the_line_that_is_far_from_it_in_the_material():
    """A strip (0.4 m x 0.1 m) whose line is its first half's middle row, folded so that the cloth past
    the line's end lies 5 cm above the line's middle: the 5 cm of it past the end belong to the line
    (within a quarter of its 0.2 m rest length), and their nearest point on the line is within the
    0.1 m measured about the middle, but they are 0.1 m from the middle in the material, so the bundle
    is the flat strip's (the closed form of the flat case)."""
    from sandbox.model.builder import ClothRange

    nx, nz, h = 41, 11, 0.01
    i, j = np.meshgrid(np.arange(nx), np.arange(nz))
    x0 = np.stack([i.ravel() * h, 0 * i.ravel(), j.ravel() * h - (nz - 1) * h / 2], 1).astype(float)
    cloth = ClothRange("S", 0, nx, nz, (h, h), 0.002, np.zeros((0, 3), np.int32), (1, 1, 1), (1, 1, 1), False)
    line = cloth.line_between([0, nz // 2], [20, nz // 2])
    st = Strand("S.half", "S", line, line, np.full(20, h), 0.001, cloth=True, rest_pos=x0[line])
    around = x0[line[10]]  # x = 0.1 m
    folded = x0.copy()
    past = x0[:, 0] > 0.2 + 1e-9  # columns 21-40: turned back to lie above x = 0.09 .. -0.1 (5 cm up)
    folded[past, 0] = 0.3 - x0[past, 0]
    folded[past, 1] = 0.05
    flat = gathered_radius(x0, st, cloth, x0, around, length=0.1)
    cols = np.abs(x0[:, 0] - around[0]) <= 0.05 + 1e-9
    assert flat == pytest.approx(np.percentile(np.abs(x0[cols, 2]), 90) + 0.001, rel=1e-9)
    assert gathered_radius(folded, st, cloth, x0, around, length=0.1) == pytest.approx(flat, rel=1e-9)


def test_knot_criteria_read_two_control_lines_joined_through_the_cloth_centre():
    """The knot between two lines of one cloth: each line runs from the shared centre to its corner, and
    the two are joined there (as two ropes at their standing ends) and closed far away. Two lines laid
    along a left granny (two left trefoils in a row, cut between them) are a granny_left; the level
    check takes cloth lines in a criterion's ``of`` and names an unknown cloth."""
    from sandbox.io import criteria
    from tests.test_knots import two_ropes

    a, b = two_ropes(first_left=True, second_left=True)
    centre = 0.5 * (a[0] + b[0])
    x = np.vstack([centre, a, b]).astype(np.float32)
    lines = {"F.line1": np.arange(0, len(a) + 1), "F.line3": np.concatenate([[0], len(a) + 1 + np.arange(len(b))])}
    world = types.SimpleNamespace(positions=lambda: x, ropes={}, cloths={"F": None},
                                  strand=lambda n: types.SimpleNamespace(idx=lines[n], radius=0.05))
    assert criteria._knot(world, ["F.line1", "F.line3"]) == "granny_left"
    assert criteria._knot(world, ["F.line3", "F.line1"]) == "granny_left"
    # Joined through the centre, the lines do not touch where they meet: two straight lines out of it have
    # no knot to measure (as two ropes from one point, their shared start would be a touch).
    out = np.array([[0.0, 0.0, 0.0]] + [[0.01 * k, 0.0, 0.0] for k in range(1, 40)]
                   + [[0.0, 0.0, 0.01 * k] for k in range(1, 40)], np.float32)
    x[:] = 0.0
    x[: len(out)] = out
    lines.update({"F.line1": np.arange(0, 40), "F.line3": np.concatenate([[0], 40 + np.arange(39)])})
    assert criteria._knot_size(world, ["F.line1", "F.line3"]) == 0.0
    assert criteria._knot_length(world, ["F.line1", "F.line3"]) == 0.0
    with pytest.raises(LevelError, match="'winding_number' does not read cloth lines"):
        load_level_from_string(_scene().replace(
            "success:\n", "success:\n  - {metric: winding_number, of: [F.line1, F.line3], min: 1}\n"),
            base_dir=ROOT / "levels")
    text = _scene().replace("success:\n", "success:\n  - {metric: knot, of: [F.line1, F.line3], equals: granny_left}\n")
    load_level_from_string(text, base_dir=ROOT / "levels")
    with pytest.raises(LevelError, match="unknown cloth 'G'"):
        load_level_from_string(text.replace("of: [F.line1", "of: [G.line1"), base_dir=ROOT / "levels")


def test_a_strand_crossed_with_or_wound_around_itself_is_caught_when_the_level_loads():
    """A Crossing or Winding whose active and target name one strand, written the same way or not
    (``F.line1`` is ``F.center..A``), is refused with the file position and the allowed forms."""
    text = _scene(active="F.line1", target="F.line1")
    with pytest.raises(LevelError, match="active and target are the same strand 'F.line1'") as err:
        load_level_from_string(text, base_dir=ROOT / "levels")
    assert "fsm[2].with: maneuver 'Crossing'" in str(err.value)
    with pytest.raises(LevelError, match="same strand"):
        load_level_from_string(_scene(active="F.line1", target="F.center..A"), base_dir=ROOT / "levels")
    winding_only = _scene().replace('active: "F.line1", target: "F.line3", theta', 'active: "F.line3", target: "F.line3", theta')
    with pytest.raises(LevelError, match="same strand 'F.line3'"):
        load_level_from_string(winding_only, base_dir=ROOT / "levels")


def test_rendered_frames_can_follow_the_knot_of_two_cloth_lines(tmp_path):
    """``--follow F.line1,F.line3`` (or a level camera's ``follow``): accepted for a level with cloth F,
    refused (with the allowed forms) for an unknown cloth; the API gives the followed lines' positions
    from the centre out and their radius."""
    from sandbox.api import Sandbox
    from sandbox.cli import _names
    from sandbox.runner import RunOptions, _follow_problem

    assert _names("F.[3,4]..center, F.line1") == ["F.[3,4]..center", "F.line1"]  # the comma in brackets stays

    level = load_level_from_string(_scene(), base_dir=ROOT / "levels")
    assert _follow_problem(level, RunOptions(out=tmp_path, follow=["F.line1", "F.line3"], frames_every=5)) is None
    said = _follow_problem(level, RunOptions(out=tmp_path, follow=["G.line1"], frames_every=5))
    assert "'G.line1' not a rope or a cloth line" in said and "F.line1-F.line4 or F.P..Q of F" in said
    cam = "scene:\n  camera: {position: [0, 1, 1], look_at: [0, 0.1, 0], follow: [F.line1, F.line3]}\n"
    assert load_level_from_string(_scene().replace("scene:\n", cam, 1),
                                  base_dir=ROOT / "levels").scene.camera.follow == ["F.line1", "F.line3"]
    sim = Sandbox(level, base_dir=ROOT / "levels")
    try:
        line = sim.world.cloth("F").control_line(1)
        np.testing.assert_array_equal(sim.strand_positions("F.line1"), sim.world.positions()[line])
        assert sim.strand_radius("F.line1") == pytest.approx(0.5 * sim.world.cloth("F").thickness)
    finally:
        sim.close()
