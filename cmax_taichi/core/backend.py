"""Taichi backend selection: architecture and floating-point precision.

``init()`` may be called explicitly; any public API initialises the default backend (CPU, f64 unless
``CMAX_TAICHI_PRECISION`` says otherwise, arch from ``CMAX_TAICHI_ARCH``) on first use. Calling
``init()`` again with other settings resets Taichi: every problem built before becomes invalid and
says so when used.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
import warnings
from collections.abc import Iterator
from dataclasses import dataclass

import taichi as ti

ARCH_ENV = "CMAX_TAICHI_ARCH"
PRECISION_ENV = "CMAX_TAICHI_PRECISION"
COMPILE_ENV = "CMAX_TAICHI_COMPILE"
ARCHS = ("cpu", "gpu", "cuda", "vulkan", "metal")
PRECISIONS = ("f32", "f64")
# How the kernels with hand-written gradients (the fused kernels, the dense flow's) compile
# (pipeline/tiers.py): "full" with Taichi's advanced IR optimizations (the fastest kernels, 10-60 s to
# compile a configuration), "fast" without them (1-5 s, kernels 1.4-3.7x slower), "auto" (the default)
# fast kernels at once and the optimized ones compiled by a background process, taken over when ready.
# The kernels that Taichi's autodiff differentiates keep the optimizations in every mode: without them
# its reverse mode is wrong (hand_written_gradient_kernels). The offline cache keeps the tiers apart (the
# option is part of Taichi's cache key).
COMPILE_MODES = ("auto", "full", "fast")


@dataclass(frozen=True)
class BackendInfo:
    """What the running backend is.

    Attributes
    ----------
    requested_arch : str
        The arch that was asked for.
    arch : str
        The arch Taichi actually runs on (``"cpu"`` after a fallback).
    precision : str
        ``"f32"`` or ``"f64"``.
    generation : int
        Incremented at every (re-)initialisation; problems remember the generation they were built in.
    compile_mode : str
        ``"auto"``, ``"full"`` or ``"fast"``: how the kernels with hand-written gradients compile; see
        :func:`init`.
    """

    requested_arch: str
    arch: str
    precision: str
    generation: int
    compile_mode: str = "auto"


_state: BackendInfo | None = None
_ended_generation = 0  # of the program that finish() ended (generations never repeat)
_reset_hooks: list = []
_options: dict = {}  # the keyword options of the last init(), kept by recover()


def _arch_of(name: str):
    return {
        "cpu": ti.cpu,
        "gpu": ti.gpu,
        "cuda": ti.cuda,
        "vulkan": ti.vulkan,
        "metal": ti.metal,
    }[name]


def _running_arch_name() -> str:
    arch = ti.lang.impl.current_cfg().arch
    name = str(arch).split(".")[-1]
    return "cpu" if name in ("x64", "arm64") else name


def init(
    arch: str | None = None,
    precision: str | None = None,
    *,
    quiet: bool = True,
    kernel_profiler: bool = False,
    compile_mode: str | None = None,
) -> BackendInfo:
    """Initialise (or re-initialise) Taichi for cmax-taichi.

    Parameters
    ----------
    arch : {"cpu", "gpu", "cuda", "vulkan", "metal"}, optional
        Backend. Defaults to the environment variable ``CMAX_TAICHI_ARCH``, else ``"cpu"``. A GPU arch
        that is not available falls back to the CPU with a warning.
    precision : {"f32", "f64"}, optional
        Floating-point type of every field and kernel. Defaults to ``CMAX_TAICHI_PRECISION``, else
        ``"f64"`` on the CPU and ``"f32"`` on a GPU (GPUs are much faster in f32; Vulkan and Metal have
        no f64 at all).
    quiet : bool
        Show only Taichi's errors (not its info logs and compiler warnings).
    kernel_profiler : bool
        Time every task of every kernel launch (``ti.profiler``; used by ``benchmarks/profile_stages.py``).
    compile_mode : {"auto", "full", "fast"}, optional
        How the kernels with hand-written gradients (the fused kernels and the dense flow's) compile;
        ``CMAX_TAICHI_COMPILE`` sets it when the argument is omitted. ``"auto"`` (default): a configuration
        whose optimized kernels are in Taichi's offline cache runs on them; otherwise it starts at once on
        kernels compiled without Taichi's advanced IR optimizations (1-5 s; 1.4-3.7x slower) while a
        background process compiles the optimized ones (10-60 s on this project's 2-core reference
        machine), which the next windows take over (``pipeline/tiers.py``). ``"full"``: the optimized
        kernels, compiled in this process where the cache lacks them (benchmarks). ``"fast"``: the quick
        kernels only (short runs on a cold cache, the test suite). Kernels that Taichi's autodiff
        differentiates (the generic chain, clusters, whitening) are optimized in every mode.

    Returns
    -------
    BackendInfo
        The arch really used, the precision and the generation number.
    """
    global _state, _ended_generation
    arch = (arch or os.environ.get(ARCH_ENV) or "cpu").strip().lower()
    if arch not in ARCHS:
        raise ValueError(f"unknown arch {arch!r}; valid archs are {', '.join(ARCHS)}")
    precision = (precision or os.environ.get(PRECISION_ENV) or "").strip().lower()
    if not precision:
        precision = "f64" if arch == "cpu" else "f32"
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; valid precisions are f32, f64")
    if arch in ("vulkan", "metal") and precision == "f64":
        raise ValueError(f"arch {arch!r} has no f64 support; use precision='f32'")
    compile_mode = (compile_mode or os.environ.get(COMPILE_ENV) or "auto").strip().lower()
    if compile_mode not in COMPILE_MODES:
        raise ValueError(f"unknown compile mode {compile_mode!r}; valid modes are {', '.join(COMPILE_MODES)}")

    if _state is not None:
        _end_program()
    generation = (_ended_generation if _state is None else _state.generation) + 1
    fp = ti.f64 if precision == "f64" else ti.f32
    # quiet: Taichi's compiler warnings (e.g. thousands of "Loading variable ... before anything is
    # stored" lines while differentiating rotation3's matrix code, offline-cache lock notices when two
    # processes compile at once) are noise to a user; errors still show.
    log_level = ti.ERROR if quiet else ti.INFO
    # nor Taichi's "[Taichi] Starting on arch=..." line, which it prints to stdout whatever the level
    banner = contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext()
    with warnings.catch_warnings(), banner:
        warnings.simplefilter("ignore", DeprecationWarning)
        ti.init(
            arch=_arch_of(arch),
            default_fp=fp,
            default_ip=ti.i32,
            log_level=log_level,
            kernel_profiler=kernel_profiler,
            **_offline_cache_options(),
        )
    used = _running_arch_name()
    if arch != "cpu" and used == "cpu":
        warnings.warn(
            f"cmax_taichi: arch {arch!r} is not available on this machine; running on the CPU",
            RuntimeWarning,
            stacklevel=2,
        )
    _state = BackendInfo(
        requested_arch=arch,
        arch=used,
        precision=precision,
        generation=generation,
        compile_mode=compile_mode,
    )
    _options.update(quiet=quiet, kernel_profiler=kernel_profiler, compile_mode=compile_mode)
    return _state


def _offline_cache_options() -> dict:
    """Where Taichi keeps its offline cache: its own folder where it can be written, else a folder in
    the temporary directory (said once). Taichi creates that folder when the program ends, whether the
    cache is on or not, and crashes (SIGSEGV, after a complete run) where it cannot, e.g. under a
    read-only HOME."""
    path = os.environ.get("TI_OFFLINE_CACHE_FILE_PATH") or ti.lang.impl.default_cfg().offline_cache_file_path
    if _writable(path):
        return {"offline_cache": True}
    fallback = os.path.join(tempfile.gettempdir(), f"cmax-taichi-ticache-{os.getuid()}")
    usable = _writable(fallback)
    warnings.warn(
        f"cmax_taichi: Taichi's kernel cache {path} cannot be written: "
        + (f"using {fallback}" if usable else "kernels are compiled in every process")
        + " (set TI_OFFLINE_CACHE_FILE_PATH to a writable folder)",
        RuntimeWarning,
        stacklevel=4,
    )
    return {"offline_cache": usable, "offline_cache_file_path": fallback}


def _writable(path: str) -> bool:
    """Whether ``path`` (a folder) can be written, or created where it does not exist yet."""
    folder = os.path.abspath(os.path.expanduser(path))
    while not os.path.exists(folder) and os.path.dirname(folder) != folder:
        folder = os.path.dirname(folder)
    return os.path.isdir(folder) and os.access(folder, os.W_OK | os.X_OK)


def recover() -> BackendInfo:
    """Re-initialise Taichi with the arch, precision and options in use (after a failed allocation).

    A field allocation that fails leaves Taichi's field builder finalized: every later field fails
    with "FieldsBuilder finalized" until a reset. The reset drops the pooled workspaces and compiled
    kernels (the :func:`on_reset` hooks); problems built before raise a clear error when used.
    """
    if _state is None:
        return init()
    return init(arch=_state.requested_arch, precision=_state.precision, **_options)


def is_broken() -> bool:
    """Whether an earlier failure left Taichi's field builder finalized (no new field can be made), or
    Taichi was reset behind cmax-taichi's back (``ti.reset()``)."""
    if _state is None:
        return False
    if ti.lang.impl.get_runtime().prog is None:  # ti.reset() without ti.init()
        return True
    try:
        return bool(ti.root.finalized)
    except RuntimeError:  # "Please call init() first"
        return True


def init_if_needed(
    arch: str | None = None, precision: str | None = None, compile_mode: str | None = None
) -> BackendInfo:
    """Initialise Taichi unless it already runs with the requested arch, precision and compile mode
    (None: any).

    A reset would throw away every compiled kernel of the process, so drivers that may run several
    times in one process (the command line, batch workers) call this instead of :func:`init`.
    """
    current = info() if is_initialized() else None
    if (
        current is not None
        and arch in (None, current.requested_arch)
        and precision in (None, current.precision)
        and compile_mode in (None, current.compile_mode)
    ):
        return current
    return init(arch=arch, precision=precision, compile_mode=compile_mode)


def _end_program() -> None:
    """The reset hooks (pooled workspaces, compiled kernels), then Taichi's reset."""
    for hook in list(_reset_hooks):
        hook()
    ti.reset()


def finish() -> None:
    """End this process's Taichi program as the interpreter's normal exit does: the kernels compiled
    in this process are written to the offline cache (Taichi writes it when its program is finalized,
    not in an ``atexit`` function). For a process about to end without the interpreter's teardown
    (:func:`cmax_taichi.cli.console_main`); nothing to do when the backend never started."""
    global _state, _ended_generation
    if _state is None:
        return
    _end_program()  # as a re-initialisation does: nothing pooled outlives the program
    _ended_generation, _state = _state.generation, None


def is_initialized() -> bool:
    """Whether :func:`init` has run (explicitly or on first use)."""
    return _state is not None


def ensure_initialized() -> BackendInfo:
    """Initialise the default backend once; return the current backend.

    Where a failure outside cmax-taichi's allocation guard left Taichi unable to make fields (see
    :func:`recover`), re-initialise it with the same settings, with a warning.
    """
    if _state is None:
        return init()
    if is_broken():
        warnings.warn(
            "cmax_taichi: Taichi was left unable to make new fields (a failed allocation outside "
            "cmax-taichi, or ti.reset()); the backend was re-initialised with the same arch and "
            "precision (problems built before it must be built again)",
            RuntimeWarning,
            stacklevel=2,
        )
        return recover()
    return _state


def info() -> BackendInfo:
    """The current backend (initialising the default one if needed)."""
    return ensure_initialized()


def real():
    """The Taichi float type of the current precision (``ti.f32`` or ``ti.f64``)."""
    return ti.f64 if ensure_initialized().precision == "f64" else ti.f32


def numpy_real():
    """The NumPy float type matching :func:`real`."""
    import numpy as np

    return np.float64 if ensure_initialized().precision == "f64" else np.float32


def on_reset(hook) -> None:
    """Register a callable run before Taichi is reset by a later ``init()`` (clears kernel caches)."""
    _reset_hooks.append(hook)


@contextlib.contextmanager
def per_thread_loops() -> Iterator[None]:
    """Compile the kernels launched inside with Taichi's earlier CPU loop scheduling, which gives each
    iteration of a ``ti.loop_config(block_dim=1)`` loop its own task.

    Taichi 1.7.4's CPU multithreading pass (``make_cpu_multithreading_loop``, on by default) runs a
    range-for of fewer than about 512 iterations on one thread whatever its ``block_dim``, so the fused
    kernels' loops over their per-thread slices (``range(2)`` on two cores) ran serially: one core
    for the whole event pass. Only the fused kernels take the earlier scheme: with it, the generic
    chain's autodiff gradients came out wrong on small windows (a race not located; benchmarks/NOTES.md).
    The setting is read when a kernel compiles; launching an already compiled kernel inside costs two
    attribute writes.
    """
    cfg = ti.lang.impl.current_cfg()
    previous = cfg.make_cpu_multithreading_loop
    cfg.make_cpu_multithreading_loop = False
    try:
        yield
    finally:
        cfg.make_cpu_multithreading_loop = previous


@contextlib.contextmanager
def hand_written_gradient_kernels(tier: str = "full") -> Iterator[None]:
    """Compile the kernels launched inside (kernels whose gradient is written by hand, never
    differentiated by Taichi's autodiff: the fused kernels, the dense flow's) as they need:
    :func:`per_thread_loops`, and in ``tier`` ``"fast"`` (``pipeline/tiers.py``; any tier in compile mode
    ``"fast"``) without Taichi's advanced IR optimizations.

    Only these kernels may skip the optimizations: Taichi 1.7.4's reverse mode depends on them. Without
    them (or with ``cfg_optimization`` alone off) a local accumulated in a differentiated kernel
    (``t = 0.0; t += 2 x``) got a zero adjoint in f32, and the whitening kernels got gradients of
    1e+200 in f64 (taichi-dev/taichi#1384 is the same family). Read when a kernel compiles.
    """
    if tier not in ("fast", "full"):
        raise ValueError(f"unknown kernel tier {tier!r}; valid tiers are fast, full")
    cfg = ti.lang.impl.current_cfg()
    previous = cfg.advanced_optimization
    if tier == "fast" or (_state is not None and _state.compile_mode == "fast"):
        cfg.advanced_optimization = False
    try:
        with per_thread_loops():
            yield
    finally:
        cfg.advanced_optimization = previous


# --- Taichi's front end: the source position of every AST node ---------------------------------------
#: set to 1 to keep Taichi's own source positions (a wrapped excerpt of the line per node)
FULL_SOURCE_INFO_ENV = "CMAX_TAICHI_FULL_SOURCE_INFO"


def _front_end_patches_wanted() -> bool:
    """Whether to patch Taichi's front end: only the version the patches were written for, and not with
    ``CMAX_TAICHI_FULL_SOURCE_INFO=1``."""
    return os.environ.get(FULL_SOURCE_INFO_ENV, "").strip() != "1" and ti.__version__ == (1, 7, 4)


def _short_source_positions() -> bool:
    """Give Taichi 1.7.4's AST builder the short position of each node (``File "...", line N, in f:``).

    Taichi runs its Python front end on every kernel in every process, warm offline cache or not (the
    cache skips LLVM only), and it formats, for every node of the kernel's tree, the source line with
    a caret under the node through ``textwrap`` (``ASTTransformerContext.get_pos_info``, which the
    builders also call for the debug information of every name and loop): a quarter of the 0.7 s of
    CPU time that building a fused kernel takes. The excerpt only labels the IR's debug
    information (runtime messages in debug mode). A compile error still gets the full excerpt (the
    error path below calls ``get_pos_info`` as Taichi does); the offline cache keys do not change.
    Applied only to the Taichi version it was written for, and not with ``CMAX_TAICHI_FULL_SOURCE_INFO=1``.
    Returns whether it was applied.
    """
    if not _front_end_patches_wanted():
        return False
    try:
        import ast
        import traceback

        from taichi.lang import impl
        from taichi.lang.ast import ast_transformer_utils as utils
        from taichi.lang.exception import TaichiCompilationError, TaichiSyntaxError, handle_exception_from_cpp
    except ImportError:  # pragma: no cover - another layout than 1.7.4's
        return False
    if getattr(utils.Builder.__call__, "_cmax_short_positions", False):
        return True

    def build_node(self, ctx, node):  # Taichi 1.7.4's Builder.__call__ but for the position string
        method = getattr(self, "build_" + node.__class__.__name__, None)
        try:
            if method is None:
                error_msg = f'Unsupported node "{node.__class__.__name__}"'
                raise TaichiSyntaxError(error_msg)
            info = ""
            if isinstance(node, (ast.stmt, ast.expr)):
                line = node.lineno + ctx.lineno_offset
                info = f'File "{ctx.file}", line {line}, in {ctx.func.func.__name__}:\n'
            with impl.get_runtime().src_info_guard(info):
                return method(ctx, node)
        except Exception as e:
            if impl.get_runtime().print_full_traceback:
                raise e
            if ctx.raised or not isinstance(node, (ast.stmt, ast.expr)):
                raise e.with_traceback(None)  # noqa: B904 - as Taichi raises it
            ctx.raised = True
            e = handle_exception_from_cpp(e)
            if not isinstance(e, TaichiCompilationError):
                msg = full_pos_info(ctx, node) + traceback.format_exc()
                raise TaichiCompilationError(msg) from None
            msg = full_pos_info(ctx, node) + str(e)
            raise type(e)(msg) from None

    full_pos_info = utils.ASTTransformerContext.get_pos_info

    def short_pos_info(self, node):  # what the builders put into each name's and loop's debug info
        return f'File "{self.file}", line {node.lineno + self.lineno_offset}, in {self.func.func.__name__}:\n'

    build_node._cmax_short_positions = True
    utils.Builder.__call__ = build_node
    utils.ASTTransformerContext.get_pos_info = short_pos_info
    return True


SHORT_SOURCE_POSITIONS = _short_source_positions()


def _cached_function_sources() -> bool:
    """Read the source of each ``ti.func`` / kernel once per process, not at every call site.

    Taichi 1.7.4's front end inlines a ``ti.func`` at each of its calls, and for each call it looks the
    function's source up again (``inspect.getsourcelines``: ``inspect.getmodule`` over ``sys.modules``
    and a tokenizer pass over the module) and wraps every line through ``textwrap``
    (``kernel_impl._get_tree_and_ctx``): the fused kernel calls ti.funcs some 450 times, and those
    lookups were about half of the 1.2 s its front end takes in every process, warm offline cache or
    not. Here the file, lines and dedented text are kept per code object (closures of one factory share
    it, and so their source); the tree is still parsed afresh at each call (Taichi's builders write
    into its nodes). What Taichi builds from it is unchanged (the offline cache keys included).
    Applied only to the Taichi version it was written for, and not with ``CMAX_TAICHI_FULL_SOURCE_INFO=1``.
    Returns whether it was applied.
    """
    if not _front_end_patches_wanted():
        return False
    try:
        import ast
        import textwrap

        from taichi.lang import kernel_impl
    except ImportError:  # pragma: no cover - another layout than 1.7.4's
        return False
    if getattr(kernel_impl._get_tree_and_ctx, "_cmax_cached_sources", False):
        return True
    context_class = kernel_impl.ASTTransformerContext
    sources: dict = {}

    def source_of(func) -> tuple:
        code = getattr(func, "__code__", None)
        found = sources.get(code) if code is not None else None
        if found is None:  # as Taichi 1.7.4 reads it
            file = kernel_impl.getsourcefile(func)
            src, start_lineno = kernel_impl.getsourcelines(func)
            src = [textwrap.fill(line, tabsize=4, width=9999) for line in src]
            found = (file, tuple(src), start_lineno, textwrap.dedent("\n".join(src)))
            if code is not None:
                sources[code] = found
        return found

    def get_tree_and_ctx(  # Taichi 1.7.4's _get_tree_and_ctx but for the source lookup
        self,
        excluded_parameters=(),
        is_kernel=True,
        arg_features=None,
        args=None,
        ast_builder=None,
        is_real_function=False,
    ):
        file, src, start_lineno, text = source_of(self.func)
        tree = ast.parse(text)
        tree.body[0].decorator_list = []
        global_vars = kernel_impl._get_global_vars(self.func)
        if is_kernel or is_real_function:  # template parameters into the globals
            for i in self.template_slot_locations:
                global_vars[self.arguments[i].name] = args[i]
        return tree, context_class(
            excluded_parameters=excluded_parameters,
            is_kernel=is_kernel,
            func=self,
            arg_features=arg_features,
            global_vars=global_vars,
            argument_data=args,
            src=list(src),
            start_lineno=start_lineno,
            file=file,
            ast_builder=ast_builder,
            is_real_function=is_real_function,
        )

    get_tree_and_ctx._cmax_cached_sources = True
    kernel_impl._get_tree_and_ctx = get_tree_and_ctx
    return True


CACHED_FUNCTION_SOURCES = _cached_function_sources()


def _quick_class_test() -> bool:
    """Taichi 1.7.4's test, at every ``@ti.func`` / ``@ti.kernel``, of whether it decorates a method
    (``kernel_impl._inside_class``: the decorating frame's line matches ``class `` or
    ``@data_oriented``), with the line read from ``linecache`` instead of ``inspect.getframeinfo``.

    ``getframeinfo`` resolves the frame's module through ``inspect.getmodule``, a walk over
    ``sys.modules``, each time: the kernel factories decorate some 260 functions per fused kernel, and
    those walks took about 0.3 s of every process. Same frame, same line (the current instruction's,
    as ``getframeinfo`` reads it), same patterns. Applied only to Taichi 1.7.4, and not with
    ``CMAX_TAICHI_FULL_SOURCE_INFO=1``. Returns whether it was applied.
    """
    if not _front_end_patches_wanted():
        return False
    try:
        import inspect
        import linecache

        from taichi.lang import kernel_impl

        patterns = kernel_impl._KERNEL_CLASS_STACKFRAME_STMT_RES
        position = inspect._get_code_position
    except (ImportError, AttributeError):  # pragma: no cover - another layout than 1.7.4's
        return False
    if getattr(kernel_impl._inside_class, "_cmax_quick", False):
        return True

    def inside_class(level_of_class_stackframe):
        try:
            # called where Taichi calls its own: the same frame depth
            frame = sys._getframe(level_of_class_stackframe)
            line = position(frame.f_code, frame.f_lasti)[0] or frame.f_lineno
            first_statement = linecache.getline(frame.f_code.co_filename, line, frame.f_globals).strip()
            return any(pattern.match(first_statement) for pattern in patterns)
        except Exception:  # as Taichi's: anything unreadable is not a class
            return False

    inside_class._cmax_quick = True
    kernel_impl._inside_class = inside_class
    return True


QUICK_CLASS_TEST = _quick_class_test()
