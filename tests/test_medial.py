"""The medial-sheet pass (medial.py) against the brute-force NumPy rule (medial_np.py), its effect and its errors."""

import functools
import pathlib

import numpy as np
import pytest

from sandbox.collision.medial import associate, line_segments
from sandbox.collision.medial_np import associate_brute, pass_brute, point_segment
from tests.levelkit import world_from_text

N = 25
SHEET = f"""
version: 1
name: sheet
scene:
  gravity: [0, 0, 0]
  cloths:
    - {{name: c, resolution: [{N}, {N}], size: [0.24, 0.24], center: [0, 1, 0], self_collision: false,
        medial_sheet: [1, 3]}}
fsm:
  - {{run: Wait}}
success:
  - {{metric: fsm_state, equals: success}}
"""



@functools.cache
def _sheet():
    return world_from_text(SHEET)


def _lines(cloth):
    return [cloth.control_line(1), cloth.control_line(3)]


def _free(cloth, lines):
    on = np.zeros(cloth.end - cloth.start, bool)
    on[np.concatenate(lines) - cloth.start] = True
    return cloth.start + np.flatnonzero(~on)


def test_association_at_rest_matches_brute_force():
    """Each free particle's 3 segments are centred on its nearest at rest, as a brute force over all segments finds."""
    w = _sheet()
    c = w.cloths["c"]
    lines = _lines(c) + [c.line_between([0, 5], [24, 9])]  # and a line between two sites, crossing the others
    segs = line_segments(lines)
    free = _free(c, lines)
    own = associate(w.data.x0, free, *segs)
    assert np.array_equal(own, associate_brute(w.data.x0, free, *segs))
    assert np.all(own[:, 1] - own[:, 0] == 3)
    # Closed form on the flat sheet: the nearest of a particle's own segments is as near as any segment.
    d, _ = point_segment(w.data.x0[free], w.data.x0[segs[0]], w.data.x0[segs[1]])
    mine = np.array([d[q, lo:hi].min() for q, (lo, hi) in enumerate(own)])
    assert np.allclose(mine, d.min(axis=1))


def test_pass_matches_numpy_rule():
    """On a crumpled sheet, the Taichi pass moves exactly the particles the NumPy rule moves, to the same places."""
    w = _sheet()
    c = w.cloths["c"]
    lines = _lines(c)
    ms = w.solver.medial[0]
    rng = np.random.default_rng(3)
    x = w.data.x0.copy()
    x[:, 1] += 0.02 * np.sin(40.0 * x[:, 0]) + 0.003 * rng.standard_normal(len(x))
    x[:, 0] *= 0.3  # squeezed: the two lines' cloth lies close together
    x = x.astype(np.float32)
    w.state.x.from_numpy(x)
    w.solver.w.from_numpy(np.full(len(x), 50.0, np.float32))
    free = ms.free_np
    seg_a, seg_b = ms.seg_np
    # Leave out near-ties (float32 against float64): their nearest segment is a coin toss.
    d, _ = point_segment(x.astype(np.float64)[free], x[seg_a], x[seg_b])
    s = np.arange(len(seg_a))[None]
    mine = (s >= ms.own_np[:, :1]) & (s < ms.own_np[:, 1:])
    clear = np.abs(np.where(mine, d, np.inf).min(1) - np.where(mine, np.inf, d).min(1)) > 1e-5
    want, wrong = pass_brute(x.astype(np.float64), free, ms.own_np, seg_a, seg_b, ms.step, ms.reach)
    n_wrong = ms.wrong_side()
    moved = ms.run_pass()
    got = w.state.x.to_numpy()[free]
    assert wrong.sum() > 20, "the set-up should put particles on the wrong side"
    assert abs(moved - wrong.sum()) <= (~clear).sum() and n_wrong == moved
    assert np.allclose(got[clear], want[clear], atol=1e-6)
    held = w.solver.w.to_numpy()[free] == 0.0
    assert np.array_equal(held[clear], wrong[clear])
    # Moved particles step by at most `step`, towards their own segments.
    step = np.linalg.norm(got - x[free], axis=1)
    assert step.max() <= ms.step * (1 + 1e-4)
    ms.release(60.0)
    assert np.all(w.solver.w.to_numpy()[free] == 50.0)


def test_repeated_passes_bring_every_particle_back_to_its_side():
    """Passes alone (no simulation between) walk every crossed particle back until none is on the wrong side."""
    w = _sheet()
    ms = w.solver.medial[0]
    x = w.data.x0.copy()
    x[:, 1] += 0.02 * np.sin(40.0 * x[:, 0])
    x[:, 0] *= 0.3
    w.state.x.from_numpy(x.astype(np.float32))
    w.solver.w.from_numpy(np.full(len(x), 50.0, np.float32))
    counts = [ms.wrong_side()]
    for _ in range(400):
        if ms.run_pass() == 0:
            break
        ms.release(60.0)
        counts.append(ms.wrong_side())
    assert counts[0] > 20
    assert counts[-1] == 0
    assert all(b <= a for a, b in zip(counts, counts[1:]))


def test_bad_medial_line_is_rejected(tmp_path: pathlib.Path):
    """A medial-sheet line that is not 1-4 or two sites is refused with the allowed values."""
    from sandbox.levels.loader import LevelError, load_level

    bad = tmp_path / "bad.yaml"
    bad.write_text(SHEET.replace("medial_sheet: [1, 3]", "medial_sheet: [1, 5]"))
    with pytest.raises(LevelError, match=r"control line 1, 2, 3 or 4"):
        load_level(bad)
    bad.write_text(SHEET.replace("medial_sheet: [1, 3]", "medial_sheet: [[A, A]]"))
    with pytest.raises(Exception, match=r"two different points"):
        world_from_text(bad.read_text())


CROSS = """
version: 1
name: cross
scene:
  gravity: [0, 0, 0]
  cloths:
    - {name: c, resolution: [21, 21], size: [0.2, 0.2], center: [0, 1, 0], self_collision: false}
fsm:
  - {run: Wait, with: {seconds: 0.05}}
success:
  - {metric: cloth_interpenetration, of: c, max: 0}
"""


def test_cloth_interpenetration_matches_brute_force():
    """Edges through the cloth's own triangles: none when flat; on a half folded through the other, as NumPy finds."""
    from sandbox.collision.interpenetration import crossings_brute, structural_edges

    w = world_from_text(CROSS)
    c = w.cloths["c"]
    cc = w.crossings["c"]
    assert cc.count() == 0
    rng = np.random.default_rng(2)
    x = w.data.x0.copy()
    right = x[:, 0] > 0.0
    x[right, 0] = -x[right, 0] + 0.0031  # the right half laid back over the left, wavy, so it passes through it,
    x[right, 2] += 0.0037  # off the grid lines of the left half (no edge grazes a triangle's side)
    x[right, 1] += 0.002 * np.sin(90.0 * x[right, 2]) + 0.001 * rng.standard_normal(right.sum())
    x = x.astype(np.float32)
    w.state.x.from_numpy(x)
    n = cc.count()
    want = crossings_brute(x.astype(np.float64), structural_edges(c.nx, c.nz) + c.start, np.asarray(c.faces) + c.start)
    assert n == want.sum() > 20
    assert np.array_equal(cc.crossing.to_numpy().astype(bool), want)


def test_cloth_interpenetration_criterion():
    """A level that checks cloth_interpenetration gets the count of its last frame (a flat sheet: 0)."""
    from sandbox.io.criteria import METRICS

    w = world_from_text(CROSS)
    for _ in range(3):
        w.step()
    assert METRICS["cloth_interpenetration"][1](w, "c") == 0
    x = w.state.x.to_numpy()
    right = x[:, 0] > 0.0
    x[right, 0] = -x[right, 0] + 0.003
    x[right, 1] += 0.002 * np.sin(90.0 * x[right, 2])
    w.state.x.from_numpy(x)
    assert METRICS["cloth_interpenetration"][1](w, "c") > 0


def test_medial_sheet_cost_is_in_the_per_pass_timings():
    """A profiled frame of a cloth with a medial sheet reports the passes' time as ``medial_sheet``."""
    w = world_from_text(SHEET)
    w.profile_every = 1
    w.step()
    assert w.stage_ms.get("medial_sheet", 0.0) > 0.0
    plain = world_from_text(CROSS)
    plain.profile_every = 1
    plain.step()
    assert "medial_sheet" not in plain.stage_ms and not plain.solver.medial


def test_medial_sheet_runs_with_unfused_iterations():
    """Past the fused iteration count the last substep runs its iterations in chunks, then the medial passes."""
    w = world_from_text(SHEET.replace("fsm:", "sim: {iterations: 6}\nfsm:"))
    assert not w.solver.fused
    w.solver.timings = {}
    w.step()  # not profiled: the launches a run makes
    assert w.solver.timings.get("medial_sheet", 0.0) > 0.0
    assert np.isfinite(w.state.x.to_numpy()).all()
