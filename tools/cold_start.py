"""Cold and warm start of shipped levels: seconds from a fresh process to its first frame.

    python tools/cold_start.py [LEVEL.yaml ...] [--fast-compile] [--out cold.json]

Each level runs twice in fresh processes that share one kernel cache made
empty for it: the first (cold) compiles every kernel, the second (warm)
loads them from the cache. A process times importing the sandbox, loading
the level, building its world and its first frame (the FSM's first step
included), and counts the kernels Taichi compiled. Default: every shipped
level, full compile optimisation, CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent

CHILD = r"""
import json, sys, time
t0 = time.perf_counter()
from sandbox import runtime
from sandbox.api import Sandbox
t_import = time.perf_counter()
runtime.init("cpu")
t_init = time.perf_counter()
sim = Sandbox.from_level(sys.argv[1], arch="cpu")
t_build = time.perf_counter()
sim.step()
runtime.sync()
t_frame = time.perf_counter()
sim.step()
runtime.sync()
t_second = time.perf_counter()
print(json.dumps({"import": t_import - t0, "init": t_init - t_import, "build": t_build - t_init,
                  "first_frame": t_frame - t_build, "total": t_frame - t0, "second_frame": t_second - t_frame}))
"""


def start(level: pathlib.Path, cache: pathlib.Path, fast: bool) -> dict:
    """One fresh process on ``level`` with ``cache`` as Taichi's kernel cache; its timings in seconds."""
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache), PYTHONPATH=str(ROOT))
    env["SANDBOX_FAST_COMPILE"] = "1" if fast else "0"
    out = subprocess.run([sys.executable, "-c", CHILD, str(level)], env=env, capture_output=True, text=True,
                         check=False, cwd=ROOT)
    if out.returncode != 0:
        raise RuntimeError(f"{level.name}: {out.stderr.strip().splitlines()[-1:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("levels", nargs="*", type=pathlib.Path)
    ap.add_argument("--fast-compile", action="store_true", help="skip Taichi's advanced optimisations")
    ap.add_argument("--out", type=pathlib.Path, help="write every timing to this JSON file")
    a = ap.parse_args(argv)
    levels = a.levels or sorted((ROOT / "levels").glob("*.yaml"))
    rows = {}
    print(f"{'level':>18}  {'cold s':>7} {'warm s':>7}  (cold: import, build, first frame)")
    for level in levels:
        cache = pathlib.Path(tempfile.mkdtemp(prefix="cold_cache_"))
        try:
            cold = start(level, cache, a.fast_compile)
            warm = start(level, cache, a.fast_compile)
        finally:
            shutil.rmtree(cache, ignore_errors=True)
        rows[level.stem] = {"cold": cold, "warm": warm}
        print(f"{level.stem:>18}  {cold['total']:7.1f} {warm['total']:7.1f}  "
              f"({cold['import']:.1f}, {cold['build']:.1f}, {cold['first_frame']:.1f})", flush=True)
    if a.out:
        a.out.write_text(json.dumps({"fast_compile": a.fast_compile, "levels": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
