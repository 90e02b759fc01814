"""One Taichi runtime per process.

Taichi allows a single ``ti.init`` per process that matters: a second init
silently resets every field. ``init`` is therefore idempotent for the same
architecture and raises for a different one.
"""

from __future__ import annotations

import contextlib
import gc
import os
import pathlib
import time
import weakref

import taichi as ti

from sandbox import backends

ARCHES = ("auto", "cpu", "cuda", "vulkan", "metal")

_state: dict = {"arch": None, "requested": None, "fast_compile": False, "debug": False, "reason": None,
                "threads": None, "serial_loops": False}

_open: "weakref.WeakSet" = weakref.WeakSet()
"""The worlds built and not yet closed (``release`` refuses while any is open)."""


def opened(world) -> None:
    """Count ``world`` as open until ``closed(world)``."""
    _open.add(world)


def closed(world) -> None:
    """``world`` no longer holds Taichi fields."""
    _open.discard(world)


class RuntimeBusyError(RuntimeError):
    """The runtime was to be released while worlds still use it."""


def release() -> bool:
    """Free every kernel and field Taichi holds; the next world initialises it again.

    Taichi compiles a world's kernels for that world's own fields and keeps
    them until the runtime is reset: each load and close of a level leaves
    about 5 MB behind (docs/benchmarks.md, "Load and close"). A host that
    loads many levels in one process calls this between them, after closing
    every world; it costs about 0.15 s (kernels come back from the on-disk
    cache). The backend and compile settings stay what they were.

    Returns:
        True if a runtime was released, False if none was running.

    Raises:
        RuntimeBusyError: a world that can still be reached is open (its fields would be freed under it).
    """
    if _state["arch"] is None:
        return False
    gc.collect()  # a world nobody can reach any more is not in the way
    if len(_open):
        raise RuntimeBusyError(f"{len(_open)} world(s) still open; close them before releasing the runtime")
    ti.reset()
    _state["arch"] = None
    return True


_deferred: list | None = None


def defer(fn, *args) -> None:
    """Call ``fn(*args)`` now, or at the end of the enclosing ``batched`` block."""
    if _deferred is None:
        fn(*args)
    else:
        _deferred.append((fn, args))


class FieldTree:
    """The SNode tree that a ``batched`` block allocated (``tree`` is None if it declared no field)."""

    def __init__(self) -> None:
        self.tree = None

    def destroy(self) -> None:
        """Free the tree's memory and its slot; its fields must not be used again."""
        if self.tree is not None:
            self.tree.destroy()
            self.tree = None


@contextlib.contextmanager
def batched():
    """Allocate every field first, upload data last, into one SNode tree of its own.

    Taichi gathers the fields declared since its last kernel launch or field
    access into one SNode tree, and a process can hold at most 512 trees.
    Uploads (``from_numpy``, loading kernels) passed to ``defer`` inside this
    block run when it ends, after the block's fields have been finalised as
    one tree; the yielded ``FieldTree`` can destroy it, which frees its slot.

    Raises:
        RuntimeError: something materialised fields inside the block (a
            kernel launch or a field read not passed to ``defer``): it would
            have seen fields whose data had not been uploaded yet.
    """
    global _deferred
    holder = FieldTree()
    if _deferred is not None:  # nested: the outer block finalises and uploads
        yield holder
        return
    from taichi._snode.fields_builder import FieldsBuilder
    from taichi.lang import impl

    rt = impl.get_runtime()
    trees = rt.prog.get_snode_tree_size()
    _deferred = []
    try:
        yield holder
        pending = _deferred
    finally:
        _deferred = None
    if rt.prog.get_snode_tree_size() != trees:
        raise RuntimeError("fields were materialised inside runtime.batched() before their data was uploaded: "
                           "pass every upload and loading kernel of the block to runtime.defer")
    fb = impl._root_fb
    if not fb.finalized and not fb.empty:
        # Finalised here rather than at the next kernel launch, so that the
        # tree's handle is kept (Taichi's own materialisation drops it).
        holder.tree = fb.finalize(raise_warning=False)
        impl._root_fb = FieldsBuilder()
        rt.materialize()
    for fn, args in pending:
        fn(*args)


class RuntimeConfigError(RuntimeError):
    """A second, different Taichi initialisation was requested."""


_TI_ARCH = {"cpu": ti.cpu, "cuda": ti.cuda, "vulkan": ti.vulkan, "metal": ti.metal}


def _resolve(arch: str) -> tuple[tuple[str, ...], str]:
    """The backends to try, best first, and why (``auto``: ``sandbox.backends.choose_auto``)."""
    if arch != "auto":
        return (arch,), f"requested {arch}"
    choice = backends.choose_auto()
    backends.point_taichi_at(choice)
    return choice.candidates, choice.reason


def _memoize_source_positions() -> None:
    """Compute each kernel source position's error-message text, and read each function's source, once.

    Taichi formats a node's file, line and caret hint (``TextWrapper`` on its
    source line) for every node it turns into IR, in case an error needs it,
    and the fused substep kernel visits each pass's nodes once per place the
    pass is unrolled: 52,000 formattings, 3.2 s of rope_hang's 7.1 s warm
    first frame. The text depends only on the source, the function and the
    node's span, so it is kept by those; messages are unchanged.
    """
    from taichi.lang.ast import ast_transformer_utils as utils

    ctx_cls = getattr(utils, "ASTTransformerContext", None)
    original = getattr(ctx_cls, "get_pos_info", None)
    if original is None or getattr(original, "_memoized", False):
        return
    cache: dict = {}

    def get_pos_info(self, node):
        body = getattr(node, "body", None)
        key = (self.file, self.lineno_offset, self.indent, self.func.func.__name__, type(node).__name__,
               node.lineno, node.col_offset, node.end_lineno, node.end_col_offset,
               body[0].lineno if isinstance(body, list) and body else None)
        text = cache.get(key)
        if text is None:
            text = cache[key] = original(self, node)
        return text

    get_pos_info._memoized = True
    ctx_cls.get_pos_info = get_pos_info

    # The same for the source of each Taichi function, read (tokenised to
    # find where it ends) at every call site: 1,158 reads, 0.7 s.
    from taichi.lang import kernel_impl

    read = getattr(kernel_impl, "getsourcelines", None)
    if read is None or getattr(read, "_memoized", False):
        return
    sources: dict = {}

    def getsourcelines(obj):
        try:
            lines, start = sources[obj]
        except (KeyError, TypeError):  # TypeError: an object that cannot be a key is read each time
            lines, start = read(obj)
            with contextlib.suppress(TypeError):
                sources[obj] = (lines, start)
        return list(lines), start

    getsourcelines._memoized = True
    kernel_impl.getsourcelines = getsourcelines


_memoize_source_positions()


def _serialize_loops_when_asked() -> None:
    """Compile every loop to run in the thread that launches its kernel while ``_state["serial_loops"]`` is set.

    Taichi's CPU backend hands each top-level loop of a kernel to its thread
    pool, even with one thread, and waits for it: a wake-up of another
    thread per loop, 130-170 us on this 2-core virtual machine (docs/benchmarks.md,
    "CPU threads"). A substep runs dozens of loops over a few hundred
    particles, so a frame of a rope level spent most of its time waking
    threads. ``ti.loop_config(serialize=True)`` compiles a range loop to
    run in the launching thread (a launch of one such loop 17 us, each more
    loop in it about 7 us); this applies it to every range loop, of this
    process's kernels and of any other kernel it compiles,
    which is what one thread would do anyway. Taichi cannot serialize a
    loop over a field (``for i in field``): it is left as it is, and
    kernels loop over ``range(n)`` instead.
    """
    import ast

    from taichi.lang import misc
    from taichi.lang.ast import ast_transformer as at

    original = at.ASTTransformer.build_For
    if getattr(original, "_serial", False):
        return

    def build_for(ctx, node):
        it = node.iter
        ranged = isinstance(it, ast.Call) and isinstance(it.func, ast.Name) and it.func.id == "range"
        if _state["serial_loops"] and (ranged or at.ASTTransformer.get_decorator(ctx, it) == "ndrange"):
            misc._parallelize(1)  # what ti.loop_config(serialize=True) sets, for the loop built next
        return original(ctx, node)

    build_for._serial = True
    at.ASTTransformer.build_For = staticmethod(build_for)


_serialize_loops_when_asked()

KERNEL_CACHE_BYTES = 2**30
"""Size of Taichi's on-disk kernel cache (least recently used kernels go past it). Taichi's own 100 MB
holds about one level's kernels in both compile modes: a sweep over many levels and settings would
compile most runs afresh (tens of seconds each)."""


CPU_CFG_OPTIMIZATION = False
"""Taichi's control-flow-graph optimisation (store-to-load forwarding, dead stores) on the CPU. A
substep is one fused kernel, and that pass grows faster than the kernel's length: without it
rope_hang's first frame compiles in 14 s instead of 38 s and drape_box's in 17 s instead of 37 s
(beside a sweep), and frames take the same time within noise (docs/benchmarks.md, "Start"). With it and
fast-math off, fast compile gives the same frames bit for bit (square_knot's first 200). GPU backends keep it
(not measured there)."""


CPU_FAST_MATH = False
"""LLVM's fast-math on the CPU (reassociation, fused multiply-adds across statements). With loops
serialized, consecutive passes of one kernel compile into one function, and fast-math then rounds a
pass differently by what it is fused with: rope_hang's frames drifted apart from frame 13 between a
substep in one kernel and the same passes in kernels of two (1e-6 m, then 6 cm by frame 30). Without
it the frames are bitwise the same however the passes are grouped, and frames take the same time
within noise (rope_hang 26.0 against 31.2 ms, square_knot 28.4 against 25.2, wrap_box_two 108.8 against
112.4, p50 over 30 frames, one thread). GPU backends keep it (not measured there)."""


def init(arch: str = "auto", *, debug: bool = False, fast_compile: bool | None = None) -> str:
    """Initialise Taichi once for this process.

    Args:
        arch: one of ``auto|cpu|cuda|vulkan|metal``. ``auto`` picks a CUDA
            device, else a hardware Vulkan GPU, else Metal on macOS, else the
            CPU; never a software Vulkan device (``sandbox/backends.py``).
            ``reason()`` says what was chosen and why.
        debug: enable Taichi's bound checks (slow).
        fast_compile: skip Taichi's advanced IR optimisations: a world's
            kernels compile about 3x faster and its frames run about 1.1x
            slower (docs/how-it-works.md, "Compile time"). None reads the environment
            variable ``SANDBOX_FAST_COMPILE`` (``1`` for on, ``0`` or unset
            for off), so that the processes a run starts follow it.

    On the CPU, Taichi runs ``SANDBOX_THREADS`` threads (default 1). With
    one, every loop runs in the launching thread (``_serialize_loops_when_asked``):
    of five shipped levels measured against two threads of a 2-core machine,
    the rope levels ran 4-5x faster, the cloth levels from 5 % slower to
    1.3x faster (docs/benchmarks.md, "CPU threads"). More threads pay where
    loops are long (a cloth of tens of thousands of particles on a machine
    with many cores): measure with ``sandbox bench``.

    Returns:
        The name of the backend in use (``x64``, ``cuda``, ...).

    Raises:
        ValueError: ``arch`` is not one of the allowed names, or
            ``SANDBOX_FAST_COMPILE`` is set to something other than 0 or 1.
        RuntimeConfigError: Taichi is already running on a different backend
            or with the other ``fast_compile``.
    """
    if arch not in ARCHES:
        raise ValueError(f"arch {arch!r} is not allowed; allowed: {', '.join(ARCHES)}")
    if _state["arch"] is None and _state["requested"] is not None:  # released: the settings chosen before
        arch = _state["requested"] if arch == "auto" else arch
        fast_compile = _state["fast_compile"] if fast_compile is None else fast_compile
        debug = debug or _state["debug"]
    if fast_compile is None:
        fast_compile = _env_flag("SANDBOX_FAST_COMPILE")
    if _state["arch"] is not None:
        running = _state["arch"]
        if bool(fast_compile) != _state["fast_compile"]:
            raise RuntimeConfigError(
                f"Taichi already runs with fast_compile={_state['fast_compile']}; "
                f"a second init with fast_compile={bool(fast_compile)} is not allowed in the same process"
            )
        if arch in ("auto", _state["requested"]) or _matches(arch, running):
            return running
        raise RuntimeConfigError(
            f"Taichi already runs on {running!r} (requested {_state['requested']!r}); "
            f"a second init with arch={arch!r} is not allowed in the same process"
        )
    candidates, why = _resolve(arch)
    kwargs = {}
    threads = _threads()
    kwargs["cpu_max_num_threads"] = threads
    _clear_stale_cache_locks()
    if fast_compile:
        kwargs["advanced_optimization"] = False
    if candidates[0] == "cpu":
        kwargs["cfg_optimization"] = CPU_CFG_OPTIMIZATION
        kwargs["fast_math"] = CPU_FAST_MATH
    ti.init(
        arch=[_TI_ARCH[a] for a in candidates] if len(candidates) > 1 else _TI_ARCH[candidates[0]],
        debug=debug,
        random_seed=0,
        default_fp=ti.f32,
        offline_cache=True,
        offline_cache_max_size_of_files=KERNEL_CACHE_BYTES,
        log_level=os.environ.get("SANDBOX_TI_LOG", "warn"),
        **kwargs,
    )
    running = str(ti.lang.impl.current_cfg().arch).split(".")[-1]
    if arch not in ("auto", "cpu") and not _matches(arch, running):
        raise RuntimeConfigError(f"arch {arch!r} was requested but Taichi started on {running!r}")
    if not _matches(candidates[0], running):
        why += f"; {candidates[0]} did not start, running on the CPU"  # Taichi fell back
    _state["arch"] = running
    _state["requested"] = arch
    _state["reason"] = why
    _state["fast_compile"] = bool(fast_compile)
    _state["debug"] = bool(debug)
    _state["threads"] = threads
    _state["serial_loops"] = running in ("x64", "arm64") and threads == 1
    return running


STALE_LOCK_S = 60.0
"""Age (s) past which a lock file in Taichi's kernel cache is stale. Taichi holds it while it reads or
writes the cache's index (well under a second); a process killed meanwhile leaves it behind, and every
later process then neither reads nor writes the cache (it warns "Lock ... failed") and compiles every
kernel afresh: 10-40 s per start instead of about 1."""


def _clear_stale_cache_locks() -> list[pathlib.Path]:
    """Remove lock files older than ``STALE_LOCK_S`` from Taichi's kernel cache folder; returns those removed."""
    folder = pathlib.Path(os.environ.get("TI_OFFLINE_CACHE_FILE_PATH")
                          or pathlib.Path.home() / ".cache" / "taichi" / "ticache")
    removed = []
    for lock in [*folder.glob("*.lock"), *folder.glob("*/*.lock")]:
        with contextlib.suppress(OSError):  # gone meanwhile, or not ours to remove: Taichi says so itself
            if time.time() - lock.stat().st_mtime > STALE_LOCK_S:
                lock.unlink()
                removed.append(lock)
    return removed


def _threads() -> int:
    """CPU threads from ``SANDBOX_THREADS`` (default 1).

    Raises:
        ValueError: it is set to something other than a whole number of at least 1.
    """
    value = os.environ.get("SANDBOX_THREADS", "1").strip()
    if not value.isdecimal() or int(value) < 1:
        raise ValueError(f"SANDBOX_THREADS={value!r} is not allowed; allowed: a whole number of CPU threads, 1 or more")
    return int(value)


def threads() -> int | None:
    """CPU threads Taichi runs (``SANDBOX_THREADS``), or None before ``init``."""
    return _state["threads"] if _state["arch"] is not None else None


def serial_loops() -> bool:
    """Whether kernels compile their loops to run in the launching thread (the CPU, one thread)."""
    return _state["serial_loops"] and _state["arch"] is not None


def _env_flag(name: str) -> bool:
    """An on/off environment variable: ``1`` on, ``0`` or unset off.

    Raises:
        ValueError: any other value, naming the variable and what it allows.
    """
    value = os.environ.get(name, "0").strip()
    if value not in ("0", "1"):
        raise ValueError(f"{name}={value!r} is not allowed; allowed: 1 (on) or 0 (off)")
    return value == "1"


def _matches(arch: str, running: str) -> bool:
    return arch == running or (arch == "cpu" and running in ("x64", "arm64"))


def ensure_init() -> str:
    """Initialise on the CPU unless Taichi already runs; returns the backend."""
    return _state["arch"] or init("cpu")


def reason() -> str | None:
    """Why the running backend was chosen (``auto``: what the drivers reported), or None before ``init``."""
    return _state["reason"] if _state["arch"] is not None else None


def current_arch() -> str | None:
    """The backend in use, or None before ``init``."""
    return _state["arch"]


def fast_compile() -> bool:
    """Whether Taichi runs without its advanced optimisations (``init(fast_compile=...)``)."""
    return _state["fast_compile"]


def sync() -> None:
    """Wait for queued kernels (needed before stopping a timer on a GPU)."""
    ti.sync()
