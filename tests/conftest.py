"""Shared test set-up: one Taichi runtime (CPU) per test process."""

import os
import pathlib
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Each test process keeps its own compiled-kernel cache: two processes
# sharing one contend for its lock, and the loser skips writing its kernels.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    os.environ.setdefault("TI_OFFLINE_CACHE_FILE_PATH",
                          str(pathlib.Path.home() / ".cache" / "taichi" / f"ticache_{_WORKER}"))

# Tests compile far more than they run (most build a world for a few frames):
# without Taichi's advanced optimisations a world compiles about 3x faster.
# Subprocesses the tests start (the CLI) inherit it.
os.environ.setdefault("SANDBOX_FAST_COMPILE", "1")

from sandbox import runtime  # noqa: E402

runtime.init("cpu")


@pytest.fixture(scope="session")
def root() -> pathlib.Path:
    """The repository root."""
    return ROOT
