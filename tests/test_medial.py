"""The medial-sheet pass (medial.py) against the brute-force NumPy rule (medial_np.py), its effect and its errors."""

import functools
import pathlib

import numpy as np
import pytest

from sandbox.collision.medial import MedialSheet, associate, line_segments
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

# Corners A and C lifted and carried past each other above the held centre: the two flaps cross.
FOLD = """
version: 1
name: fold
scene:
  gravity: [0, -9.81, 0]
  ground: {height: 0.0}
  cloths:
    - {name: c, resolution: [31, 31], size: [0.3, 0.3], center: [0, 0.3, 0], self_collision: false,
       MEDIAL pins: [center]}
sim: {fps: 60, substeps: 10}
fsm:
  - {run: MoveTo, with: {body: c, sites: [A], to: [0.06, 0.36, 0.06], via: [[-0.1, 0.4, -0.1]], speed: 0.15}}
  - {run: MoveTo, with: {body: c, sites: [C], to: [-0.06, 0.36, -0.06], via: [[0.1, 0.4, 0.1]], speed: 0.15}}
  - {run: Wait, with: {seconds: 0.5}}
success:
  - {metric: fsm_state, equals: success}
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


def test_medial_sheet_separates_crossing_flaps():
    """Two flaps carried across each other: the medial sheet leaves far fewer particles on the other line's side."""
    mean = {}
    for on in (False, True):
        w = world_from_text(FOLD.replace("MEDIAL", "medial_sheet: [1, 3]," if on else ""))
        c = w.cloths["c"]
        probe = w.solver.medial[0] if on else MedialSheet(w.state, w.solver.w, w.data.x0, c, _lines(c))
        counts = []
        for _ in range(200):
            w.step()
            counts.append(probe.wrong_side())
        mean[on] = float(np.mean(counts))
    assert mean[False] > 50.0, "the flaps should cross without the sheet"
    assert mean[True] < 0.75 * mean[False]


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
