"""Tiers (``sim.tier``): the interactive tier simulates a large cloth on a coarser grid of the same size."""

import numpy as np
import pytest

from sandbox.levels import LevelError, load_level_from_string
from sandbox.model.builder import coarse_grid
from tests.levelkit import world_from_text

SHEET = """
version: 1
name: sheet
scene:
  gravity: [0, -9.81, 0]
  cloths:
    - {name: sheet, resolution: [41, 21], size: [0.8, 0.4], center: [0.1, 1, -0.2], yaw: 30,
       self_collision: false, pins: [A, [13, 7]], medial_sheet: [[[0, 10], [40, 10]]]}
sim: {fps: 60, substeps: 4, TIER}
fsm:
  - {run: Wait, with: {seconds: 0.1}}
success:
  - {metric: fsm_state, equals: success}
"""


@pytest.mark.parametrize("nx,nz,budget", [(163, 163, 7000), (41, 21, 300), (201, 51, 2000), (300, 2, 50)])
def test_coarse_grid_is_the_finest_of_the_same_spacing_multiple_within_the_budget(nx, nz, budget):
    cx, cz = coarse_grid(nx, nz, budget)
    assert cx * cz <= budget and cx >= 2 and cz >= 2
    fx, fz = (nx - 1) / (cx - 1), (nz - 1) / (cz - 1)  # spacing multiples along x and z
    if cz > 2:
        assert fx == pytest.approx(fz, rel=0.1)  # the same proportions, within one row's rounding
    # An odd count stays odd (a middle row); one step finer (by two rows where odd) no longer fits.
    assert nx % 2 == 0 or cx % 2 == 1 or cx == 2
    finer = (cx + (2 if nx % 2 else 1), cz + (2 if nz % 2 and cz > 2 else 1 if cz > 2 else 0))
    assert finer[0] * finer[1] > budget or finer[0] > nx
    assert coarse_grid(nx, nz, None) == (nx, nz) and coarse_grid(nx, nz, nx * nz) == (nx, nz)
    assert coarse_grid(163, 163, 5000) == (69, 69)


def _sheet(tier: str, budget: int | None, monkeypatch):
    import sandbox.world

    if budget is not None:
        monkeypatch.setattr(sandbox.world, "INTERACTIVE_CLOTH_PARTICLES", budget)
    return world_from_text(SHEET.replace("TIER", f"tier: {tier}"))


def test_interactive_tier_simulates_a_large_cloth_coarser_with_its_sites_in_place(monkeypatch):
    import sandbox.world

    fine = _sheet("accurate", 300, monkeypatch)
    coarse = _sheet("interactive", 300, monkeypatch)
    c, f = coarse.cloth("sheet"), fine.cloth("sheet")
    assert (f.nx, f.nz, f.level_grid) == (41, 21, None) and coarse.tier == "interactive" == coarse.level.sim.tier
    assert c.nx * c.nz <= 300 and c.level_grid == (41, 21) and (c.nx, c.nz) == coarse_grid(41, 21, 300)
    xf, xc = fine.data.x0, coarse.data.x0
    # The same cloth: corners and centre where the level puts them, the same mass.
    for site in ("A", "B", "C", "D", "center"):  # an odd count stays odd: the middle row stays
        np.testing.assert_allclose(xc[c.site(site)], xf[f.site(site)], atol=1e-9)
    assert c.site([20, 10]) == c.site("center") and c.nx % 2 == 1 and c.nz % 2 == 1
    mass = lambda w, r: float((1.0 / w.data.inv_mass[r.start:r.end]).sum())  # noqa: E731
    assert mass(coarse, c) == pytest.approx(mass(fine, f))
    # A grid site names the level's grid: it is the nearest point of the coarser one.
    p = xf[f.site([13, 7])]
    nearest = np.linalg.norm(xc[c.start:c.end] - p, axis=1).min()
    assert np.linalg.norm(xc[c.site([13, 7])] - p) == pytest.approx(nearest)
    assert nearest <= 0.5 * np.hypot(*c.spacing)
    pins = set(coarse.data.pins.tolist())
    assert {c.site("A"), c.site([13, 7])} <= pins and len(pins) == 2
    # The medial line from [0, 10] to [40, 10] runs along the middle row of the coarse grid, end to end.
    (line,) = c.medial_lines
    np.testing.assert_allclose(xc[line[[0, -1]]], xf[[f.site([0, 10]), f.site([40, 10])]], atol=0.5 * max(c.spacing))
    # The substep bounds scale with the finest rest length (the spacing here: no rope).
    ratio = min(f.spacing) / min(c.spacing)
    assert fine.substeps == 4 and coarse.substeps == max(1, round(4 * ratio)) < 4
    assert coarse.max_substeps == max(coarse.substeps, round(fine.max_substeps * ratio))
    # Two level sites that fall on one coarse point cannot make a line there: said as such.
    with pytest.raises(ValueError, match="shorter than one spacing.*sim.tier: accurate"):
        c.line_between([18, 10], [19, 10])
    # Out of the level's grid is out, on either grid.
    with pytest.raises(ValueError, match=r"outside \[0,40\]x\[0,20\]"):
        c.site([41, 0])
    # A small cloth stays as it is.
    small = _sheet("interactive", 10_000, monkeypatch)
    assert (small.cloth("sheet").nx, small.cloth("sheet").level_grid, small.substeps) == (41, None, 4)
    # A rope whose rods are no longer than the level's cloth spacing keeps the substeps its rods need.
    monkeypatch.setattr(sandbox.world, "INTERACTIVE_CLOTH_PARTICLES", 300)
    roped = world_from_text(SHEET.replace("TIER", "tier: interactive").replace(
        "  cloths:", "  ropes:\n    - {name: R, points: [[0, 2, 0], [0.3, 2, 0]], rod_length: 0.01, radius: 0.003}\n  cloths:"))
    assert roped.cloth("sheet").level_grid == (41, 21) and roped.substeps == 4


def test_a_tier_the_engine_lacks_is_refused_with_the_allowed_ones():
    with pytest.raises(LevelError, match="accurate.*interactive"):
        load_level_from_string(SHEET.replace("TIER", "tier: fast"))
    from sandbox.api import Sandbox

    level = load_level_from_string(SHEET.replace("TIER", "tier: accurate"))
    with pytest.raises(ValueError, match="allowed: accurate, interactive"):
        Sandbox(level, tier="fast")


def test_play_takes_the_asked_tier_then_the_levels_then_interactive():
    from sandbox.viewer.play import play_tier

    stated = load_level_from_string(SHEET.replace("TIER", "tier: accurate"))
    unstated = load_level_from_string(SHEET.replace(", TIER", ""))
    assert play_tier(stated) == "accurate" and play_tier(stated, "interactive") == "interactive"
    assert play_tier(unstated) == "interactive" and play_tier(unstated, "accurate") == "accurate"
    assert unstated.sim.tier is None


def test_run_and_bench_take_a_tier_and_say_it(tmp_path, monkeypatch):
    """``run --tier`` over the level's stated tier: the summary says the tier and the grid it simulated;
    ``bench --tier`` keys its results by level and tier."""
    import json

    import sandbox.world
    from sandbox.cli import build_parser, main

    monkeypatch.setattr(sandbox.world, "INTERACTIVE_CLOTH_PARTICLES", 300)
    path = tmp_path / "sheet.yaml"
    path.write_text(SHEET.replace("TIER", "tier: accurate"))
    main(["run", str(path), "--tier", "interactive", "--frames", "1", "--quiet", "--out", str(tmp_path / "run")])
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s["status"] == "completed" and s["tier"] == "interactive"
    assert s["cloth_grids"] == {"sheet": list(coarse_grid(41, 21, 300))}
    saved = tmp_path / "b.json"
    main(["bench", str(path), "--frames", "2", "--tier", "interactive", "--save", str(saved)])
    r = json.loads(saved.read_text())["levels"]
    assert list(r) == ["sheet@interactive"] and r["sheet@interactive"]["tier"] == "interactive"
    assert r["sheet@interactive"]["particles"] == np.prod(coarse_grid(41, 21, 300))
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", str(path), "--tier", "fast"])
