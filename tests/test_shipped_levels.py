"""Every shipped level (and every draft in levels/drafts) is valid, round-trips through dump and load, and builds."""

import pathlib

import pytest

from sandbox.levels import dump_level, load_level, load_level_from_string

import sandbox.maneuvers  # noqa: F401  (registers the maneuvers levels use)

LEVELS = sorted((pathlib.Path(__file__).resolve().parents[1] / "levels").glob("*.yaml"))
DRAFTS = sorted((pathlib.Path(__file__).resolve().parents[1] / "levels" / "drafts").glob("*.yaml"))


@pytest.mark.parametrize("path", LEVELS + DRAFTS, ids=[p.stem for p in LEVELS] + ["drafts/" + p.stem for p in DRAFTS])
def test_shipped_level_is_valid_and_round_trips(path):
    """A shipped level loads without errors and its dump loads back to an equal level."""
    level = load_level(path)
    again = load_level_from_string(dump_level(level), base_dir=path.parent)
    assert again == level


def test_levels_folder_is_not_empty():
    """The README's main level and the rope levels are shipped."""
    names = {p.stem for p in LEVELS}
    assert {"drape_box", "rope_hang", "rope_wind", "rope_wind_2", "rope_wind_3", "self_knot", "granny_knot", "square_knot"} <= names
