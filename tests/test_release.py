"""Releasing the Taichi runtime between levels (what a host that loads many levels does).

In a file of its own: a module that holds a world open (a module fixture)
would, rightly, make the release refuse.
"""

import pathlib

import numpy as np
import pytest

from sandbox.api import Sandbox

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_releasing_the_runtime_frees_kernels_and_a_level_runs_the_same_after():
    """release() refuses while a world is open; after it, the same level loads on the same backend and runs
    bitwise the same frames (its kernels come back from the disk cache)."""
    from sandbox import runtime

    level = ROOT / "tests" / "data" / "levels" / "engine_small.yaml"
    sim = Sandbox.from_level(level, arch="cpu")
    for _ in range(3):
        sim.step()
    before = sim.rope_positions("cord").copy()
    with pytest.raises(runtime.RuntimeBusyError, match=r"\d+ world\(s\) still open"):
        runtime.release()
    assert runtime.current_arch() is not None  # refused: nothing was released
    sim.close()
    arch, fast = runtime.current_arch(), runtime.fast_compile()
    assert runtime.release() is True
    assert runtime.current_arch() is None and runtime.release() is False  # nothing left to release
    with Sandbox.from_level(level) as again:  # no arch given: the backend chosen before
        assert runtime.current_arch() == arch and runtime.fast_compile() is fast
        for _ in range(3):
            again.step()
        np.testing.assert_array_equal(again.rope_positions("cord"), before)
