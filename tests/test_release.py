"""Releasing the Taichi runtime between levels (what a host that loads many levels does).

Run in a process of its own: a world that another test keeps reachable
would, rightly, make the release refuse.
"""

import json
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]

SCRIPT = """
import json, sys
import numpy as np
from sandbox import runtime
from sandbox.api import Sandbox

level = sys.argv[1]
out = {}
sim = Sandbox.from_level(level, arch="cpu")
for _ in range(3):
    sim.step()
before = sim.rope_positions("cord").copy()
try:
    runtime.release()
except runtime.RuntimeBusyError as exc:
    out["refused"] = str(exc)
out["running_after_refusal"] = runtime.current_arch() is not None
sim.close()
arch, fast = runtime.current_arch(), runtime.fast_compile()
out["released"] = runtime.release()
out["arch_after_release"] = runtime.current_arch()
out["released_again"] = runtime.release()
with Sandbox.from_level(level) as again:  # no arch given: the backend chosen before
    out["same_settings"] = runtime.current_arch() == arch and runtime.fast_compile() is fast
    for _ in range(3):
        again.step()
    out["same_frames"] = bool(np.array_equal(again.rope_positions("cord"), before))
print(json.dumps(out))
"""


def test_releasing_the_runtime_frees_kernels_and_a_level_runs_the_same_after():
    """release() refuses while a world is open; after it, the same level loads on the same backend and runs
    bitwise the same frames (its kernels come back from the disk cache)."""
    level = ROOT / "tests" / "data" / "levels" / "engine_small.yaml"
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(level)], capture_output=True, text=True, cwd=ROOT,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["refused"] == "1 world(s) still open; close them before releasing the runtime"
    assert out["running_after_refusal"]  # refused: nothing was released
    assert out["released"] is True and out["arch_after_release"] is None and out["released_again"] is False
    assert out["same_settings"] and out["same_frames"]
