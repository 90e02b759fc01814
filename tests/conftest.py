"""Shared test set-up: one Taichi runtime (CPU) per test process, started afresh between tests."""

import contextlib
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
    benchmarks time frames as shipped.
    """
    expr = config.getoption("markexpr") or ""
    default_run = "not slow" in expr and "not bench" in expr
    os.environ.setdefault("SANDBOX_FAST_COMPILE", "1" if default_run else "0")
    runtime.init("cpu")


@pytest.fixture(scope="session")
def root() -> pathlib.Path:
    """The repository root."""
    return ROOT


@pytest.fixture(autouse=True)
def _fresh_runtime(request):
    """After each test, the runtime is started afresh when no world is open any more (``runtime.release``).

    Taichi's kernel cache keys a kernel by the fields it names, and fields are
    numbered in the order a process makes them: the n-th world a process builds
    finds its kernels in the cache only if an earlier process built the same
    world n-th. Started afresh, every test's first world is numbered as the
    first, and a world of the same scene as an earlier test's loads its kernels
    instead of compiling them (tests/test_knotting.py: 226 s instead of 320 s,
    empty cache). A module whose fixtures hold Taichi fields outside a world
    (``pytestmark = pytest.mark.keeps_runtime``) keeps its runtime.
    """
    yield
    if request.node.get_closest_marker("keeps_runtime"):
        return
    with contextlib.suppress(runtime.RuntimeBusyError):  # a module's fixture still holds a world
        if runtime.release():
            runtime.init("cpu")
