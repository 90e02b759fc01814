"""The generated reference pages are current and complete."""

import pathlib

from sandbox.maneuvers.base import REGISTRY
from sandbox.maneuvers.reference import markdown, parameter_texts, shipped

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_every_maneuver_parameter_has_a_text():
    missing = [f"{name}.{p}" for name, cls in shipped(REGISTRY)
               for p, text in parameter_texts(cls.Params).items() if not text.strip()]
    assert not missing, f"write a docstring entry or a comment for: {', '.join(missing)}"


def test_the_maneuver_reference_is_current():
    """docs/maneuvers.md is what the code generates (python -m sandbox.maneuvers.reference > docs/maneuvers.md)."""
    assert (ROOT / "docs" / "maneuvers.md").read_text() == markdown()


def test_a_continued_line_with_a_colon_stays_part_of_its_parameter():
    """A docstring entry's continuation line that holds ``words: text`` is more of that entry, not a new one
    (Wrapping's ``hull`` and ``angle`` have such lines)."""
    from sandbox.maneuvers.wrapping import WrapParams

    texts = parameter_texts(WrapParams)
    assert texts["hull"].endswith("the state's ``done`` event says which.")
    assert "a spiral around a bottle" in texts["angle"]
