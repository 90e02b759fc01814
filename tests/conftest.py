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

from sandbox import runtime  # noqa: E402


def pytest_configure(config):
    """Start Taichi once per process, after the options are read.

    The default run compiles far more than it runs (most tests build a world
    for a few frames): without Taichi's advanced optimisations a world
    compiles about 3x faster, and subprocesses the tests start inherit it.
    Runs that select the slow or benchmark tests keep full optimisation:
    those run long chaotic scenes (a held knot, a fold) whose outcome turns
    on the last bits of rounding, measured and recorded as shipped.
    """
    expr = config.getoption("markexpr") or ""
    default_run = "not slow" in expr and "not bench" in expr
    os.environ.setdefault("SANDBOX_FAST_COMPILE", "1" if default_run else "0")
    runtime.init("cpu")


@pytest.fixture(scope="session")
def root() -> pathlib.Path:
    """The repository root."""
    return ROOT
