"""Bench tier: every shipped level soaked for 10,000 frames, and load-close cycles, with memory watched."""

import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
SHIPPED = sorted(ROOT.glob("levels/*.yaml"))


@pytest.mark.bench
@pytest.mark.parametrize("level", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_a_level_comes_through_ten_thousand_frames(level):
    """10,000 frames (the FSM, then the scene left alone): no NaN, no unrecovered instability, memory flat
    (under 1 MB per 1000 frames over the second half)."""
    from soak import soak

    r = soak(level, 10_000)
    assert r["unstable"] is None and r["nan_frames"] == 0 and r["finite_at_end"], r
    assert r["rss_slope_mb_per_1000_frames"] < 1.0, r


@pytest.mark.bench
@pytest.mark.parametrize("steps", [0, 1])
def test_load_and_close_cycles_do_not_leak(steps):
    """200 load (and step) and close cycles of a small level: resident memory flat after 20 (< 0.1 MB a cycle)."""
    from leak_cycles import cycles

    r = cycles(ROOT / "tests" / "data" / "levels" / "engine_small.yaml", 200, warmup=20, steps=steps)
    assert r["mb_per_cycle"] < 0.1, r
