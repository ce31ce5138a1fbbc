"""The two compiled tiers of the kernels with hand-written gradients, and the optimized tier compiled out
of the way.

Taichi compiles the fused kernels (``kernels/fused.py``, ``kernels/dense_flow.py``) with its advanced
IR optimizations (tier ``"full"``: the fastest kernels, 10-30 s to compile a configuration on a 2-core
machine) or without them (tier ``"fast"``: a few seconds, kernels slower; docs/performance.md).
Taichi's offline cache keeps both. The fast kernels read the sensor's size at run time: compiled once,
they serve every camera at once. The optimized fused kernels have the sensor compiled in (their image
indices fold: faster than run-time sizes), so each sensor has its own, compiled in the
background like the first. The compile mode (``cm.init(compile_mode=...)``,
``CMAX_TAICHI_COMPILE``, ``--compile`` on the command line) chooses:

* ``"auto"`` (the default): a configuration whose optimized kernels are in the offline cache runs on
  them; otherwise its windows start at once on fast kernels while a background process (low priority,
  one at a time per cache folder) compiles the optimized ones into the cache, and a run switches to
  them at the next window once they are there (:func:`current_tier`). A configuration that a fresh
  process cannot rebuild (a warp, objective or regularizer registered in the running script rather
  than by a plugin file or module) is compiled optimized in the process, as in ``"full"``;
* ``"full"``: the optimized kernels, compiled in the process where they are not in the cache (a
  benchmark's choice);
* ``"fast"``: fast kernels only (short runs, the test suite).

What is ready is recorded beside Taichi's cache, in ``<offline cache>/cmax-taichi/``: one file per
configuration (:class:`KernelConfig`, keyed with the library's code and Taichi's version), written by
the process that compiled it once Taichi has written its cache. :func:`warmup` (``cmax-taichi warmup``)
compiles a configuration's optimized kernels beforehand. Messages (what compiles, for how long) go to
the logger ``cmax_taichi.compile``, which the command line prints.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import taichi as ti

from cmax_taichi.core import backend

__all__ = [
    "KernelConfig",
    "cache_folder",
    "current_tier",
    "is_ready",
    "reproducible",
    "warmup",
]

LOG = logging.getLogger("cmax_taichi.compile")
TIERS = ("fast", "full")
#: what one optimized configuration took to compile on the 2-core reference machine (s), for the
#: messages before a measurement of this machine exists (docs/performance.md, "Compile time")
TYPICAL_FULL_SECONDS = (10, 60)
#: a background compile that has not finished after this long (s) is taken as dead: its configuration
#: may be requested again
PENDING_TIMEOUT_S = 1800.0


@dataclass(frozen=True)
class KernelConfig:
    """What a compiled fused kernel depends on, in terms a fresh process can rebuild it from.

    Attributes
    ----------
    kind : {"fused", "dense_flow"}
    warp : str
        The warp model ("" for the dense flow).
    objective : str
    regularizers : tuple of str
        The event-collapse regularizers, in the problem's order.
    radius : int
        The blur footprint's radius, px (the taps themselves are run-time values).
    polarity : str
    weighted : bool
        Per-event vote weights.
    references : int
        Reference times (dense flow).
    plugins : tuple of str
        Plugin files or modules that register the entries above (loaded before rebuilding).
    arch, precision : str
    slices : int
        CPU threads of the event passes (1 on a GPU).
    atomic : bool
        The event passes add atomically (a GPU; on a CPU only where a test forces it).
    kink_width : float
        The regularizers' kinks rounded over this width (the dense flow's optimizer; 0: exact).
    sensor : tuple
        ``(width, height)`` compiled into the optimized fused kernels, px; ``()`` where the kernels read
        it at run time (the dense flow).
    """

    kind: str
    warp: str
    objective: str
    regularizers: tuple
    radius: int
    polarity: str
    weighted: bool
    references: int = 1
    plugins: tuple = ()
    arch: str = "cpu"
    precision: str = "f64"
    slices: int = 1
    atomic: bool = False
    kink_width: float = 0.0
    sensor: tuple = ()
    rebuildable: bool = field(default=True, compare=False)

    def describe(self) -> str:
        """``rotation3 + variance + divergence, deformation on 240x180`` (what the messages name)."""
        head = self.warp if self.kind == "fused" else f"dense flow ({self.references} reference(s))"
        regs = f" + {', '.join(self.regularizers)}" if self.regularizers else ""
        on = f" on {self.sensor[0]}x{self.sensor[1]}" if self.sensor else ""
        return f"{head} + {self.objective}{regs}{on}"

    def key(self) -> str:
        """The configuration's key: its fields, the library's code and Taichi's version."""
        data = asdict(self)
        data.pop("rebuildable")
        text = json.dumps(data, sort_keys=True) + code_fingerprint() + ".".join(map(str, ti.__version__))
        return hashlib.sha256(text.encode()).hexdigest()[:24]

    def to_json(self) -> str:
        data = asdict(self)
        data.pop("rebuildable")
        return json.dumps(data, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> KernelConfig:
        data = json.loads(text)
        data["regularizers"] = tuple(data["regularizers"])
        data["plugins"] = tuple(data["plugins"])
        data["sensor"] = tuple(data.get("sensor", ()))
        return cls(**data)


_FINGERPRINT: list[str] = []


def code_fingerprint() -> str:
    """A hash of the library's and its kernels' Python sources (once per process): a kernel compiled by
    another version of the code is not taken as this version's."""
    if not _FINGERPRINT:
        root = Path(__file__).resolve().parents[1]
        kernels = Path(sys.modules["cmax_taichi.kernels"].__file__).resolve().parent
        digest = hashlib.sha256()
        for folder in (root, kernels):
            for path in sorted(folder.rglob("*.py")):
                with contextlib.suppress(OSError):
                    digest.update(path.read_bytes())
        _FINGERPRINT.append(digest.hexdigest()[:16])
    return _FINGERPRINT[0]


def reproducible(entries: Sequence[tuple]) -> tuple[bool, tuple]:
    """``(rebuildable, plugins)`` of registry entries ``(registry, entry)``: whether a fresh process can
    rebuild them by name (each registered under its name by the library, or by a plugin it loads first:
    ``Registry.origin``), and the plugins to load."""
    plugins: list[str] = []
    for registry, entry in entries:
        if entry.name not in registry or registry.get(entry.name) is not entry:  # not the one it holds
            return False, ()
        origin = registry.origin(entry.name)
        if origin is None:
            return False, ()
        if origin and origin not in plugins:
            plugins.append(origin)
    return True, tuple(plugins)


def _entries(model, objective, regs) -> list:
    """``(registry, entry)`` of a problem's warp model (None: a dense flow), objective, regularizers."""
    from cmax_taichi.models.objectives import OBJECTIVES
    from cmax_taichi.models.regularizers import REGULARIZERS
    from cmax_taichi.models.warps import WARPS

    base = [(REGULARIZERS, _exact(r)) for r in regs] + [(OBJECTIVES, objective)]
    return base + ([(WARPS, model)] if model is not None else [])


def _exact(reg):
    """The registered regularizer of ``reg`` (a rounded one is derived from it)."""
    from cmax_taichi.models.regularizers import REGULARIZERS

    return REGULARIZERS.get(reg.name) if reg.name in REGULARIZERS else reg


def fused_config(problem, regs: Sequence, weighted: bool, slices: int, atomic: bool) -> KernelConfig:
    """The :class:`KernelConfig` of a :class:`~cmax_taichi.ContrastMaximization`'s fused pipeline."""
    info = backend.info()
    model, objective = problem.model, problem.objective
    rebuildable, plugins = reproducible(_entries(model, objective, regs))
    return KernelConfig(
        kind="fused", warp=model.name, objective=objective.name, regularizers=tuple(r.name for r in regs),
        radius=int(problem.setup.radius), polarity=problem.polarity, weighted=bool(weighted), plugins=plugins,
        arch=info.arch, precision=info.precision, slices=int(slices), atomic=bool(atomic),
        sensor=(int(problem.width), int(problem.height)), rebuildable=rebuildable,
    )  # fmt: skip


def effective_kink_width(regs: Sequence, width: float) -> float:
    """``width``, or 0 where no regularizer of ``regs`` has a kink to round (the kernels are the exact
    ones)."""
    width = float(width)
    return width if any(r.with_rounded_kinks(width) is not r for r in regs) else 0.0


def dense_config(
    problem, setup, weighted: bool, slices: int, atomic: bool, kink_width: float = 0.0
) -> KernelConfig:
    """The :class:`KernelConfig` of a :class:`~cmax_taichi.flow.DenseFlowProblem` (``setup``: its
    ``ProblemSetup``)."""
    info = backend.info()
    regs = problem.regularizers
    rebuildable, plugins = reproducible(_entries(None, problem.objective, regs))
    return KernelConfig(
        kind="dense_flow", warp="", objective=problem.objective.name,
        regularizers=tuple(r.name for r in regs),
        radius=int(setup.radius), polarity=setup.polarity, weighted=bool(weighted),
        references=len(problem.fractions), plugins=plugins, arch=info.arch, precision=info.precision,
        slices=int(slices), atomic=bool(atomic), kink_width=effective_kink_width(regs, kink_width),
        rebuildable=rebuildable,
    )  # fmt: skip


def config_for(
    *,
    warp: str | None = "translation2",
    objective: str = "variance",
    regularizers: Sequence[str] = (),
    blur_sigma: float = 1.0,
    polarity: str = "ignore",
    weighted: bool = False,
    references: int = 1,
    kink_width: float | None = None,
    sensor_size: tuple[int, int] = (240, 180),
) -> KernelConfig:
    """The :class:`KernelConfig` of problems of these options on the running backend: a
    :class:`~cmax_taichi.ContrastMaximization` with ``warp`` on a sensor of ``sensor_size`` (width,
    height, px), or, with ``warp=None``, a dense flow (any sensor) of ``references`` reference times
    whose optimizer rounds the regularizers' kinks over ``kink_width`` (default the dense flow's,
    ``flow.solver.KINK_WIDTH``). Unknown names raise ValueError listing the valid ones."""
    from cmax_taichi.models.objectives import OBJECTIVES
    from cmax_taichi.models.regularizers import REGULARIZERS
    from cmax_taichi.models.warps import get_warp
    from cmax_taichi.pipeline.footprint import n_slices
    from cmax_taichi.pipeline.setup import POLARITY_MODES, gaussian_taps

    if polarity not in POLARITY_MODES:
        raise ValueError(f"unknown polarity mode {polarity!r}; valid: {', '.join(POLARITY_MODES)}")
    if not (isinstance(references, int) and references >= 1):
        raise ValueError(f"references must be a whole number >= 1, got {references!r}")
    sensor = ()
    if warp is not None:
        from cmax_taichi.core import limits
        from cmax_taichi.core.checks import sensor_size as checked_sensor_size

        sensor = checked_sensor_size(sensor_size)
        limits.check_sensor(*sensor, "this warmup")  # before a compile is started
    info = backend.info()
    obj = OBJECTIVES.get(objective)
    if obj.fused is None:
        raise ValueError(f"objective {objective!r} declares no fused path: nothing to compile beforehand")
    regs = [REGULARIZERS.get(name) for name in regularizers]
    model = get_warp(warp) if warp is not None else None
    name = model.name if model is not None else ""
    rebuildable, plugins = reproducible(_entries(model, obj, regs))
    atomic = info.arch != "cpu"
    width = 0.0
    if warp is None:
        from cmax_taichi.flow.solver import KINK_WIDTH

        width = effective_kink_width(regs, KINK_WIDTH if kink_width is None else kink_width)
    return KernelConfig(
        kind="fused" if warp is not None else "dense_flow", warp=name, objective=obj.name,
        regularizers=tuple(r.name for r in regs), radius=gaussian_taps(float(blur_sigma))[0],
        polarity=polarity, weighted=bool(weighted), references=int(references), plugins=plugins,
        arch=info.arch, precision=info.precision, slices=1 if atomic else n_slices(), atomic=atomic,
        kink_width=width, sensor=sensor, rebuildable=rebuildable,
    )  # fmt: skip


# --- what is ready ------------------------------------------------------------------------------------
def cache_folder() -> Path:
    """``<Taichi's offline cache>/cmax-taichi``: the records of the compiled configurations."""
    backend.ensure_initialized()
    return Path(ti.lang.impl.current_cfg().offline_cache_file_path).expanduser() / "cmax-taichi"


def _ready_file(config: KernelConfig, folder: Path | None = None) -> Path:
    return (folder or cache_folder()) / "ready" / f"{config.key()}.json"


def _pending_file(config: KernelConfig) -> Path:
    return cache_folder() / "pending" / config.key()


def is_ready(config: KernelConfig) -> bool:
    """Whether ``config``'s optimized kernels are in the offline cache (recorded by the process that
    compiled them)."""
    return _ready_file(config).is_file()


def ready_record(config: KernelConfig) -> dict | None:
    """What the compile of ``config`` recorded (seconds, peak memory), or None."""
    try:
        return json.loads(_ready_file(config).read_text())
    except (OSError, ValueError):
        return None


def _write_json(path: Path, data: Mapping) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True))
    os.replace(tmp, path)


def ready_records() -> list[tuple[KernelConfig, dict]]:
    """Every configuration recorded as compiled in this cache (any version of the code), with its record."""
    records = []
    folder = cache_folder() / "ready"
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else ():
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
            record = json.loads(path.read_text())
            records.append((KernelConfig.from_json(json.dumps(record["config"])), record))
    return records


def typical_seconds() -> str:
    """What an optimized compile takes here: the range of this cache's records, or the reference
    machine's."""
    seconds = []
    folder = cache_folder() / "ready"
    if folder.is_dir():
        for path in list(folder.glob("*.json"))[:50]:
            with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
                seconds.append(float(json.loads(path.read_text())["seconds"]))
    low, high = (min(seconds), max(seconds)) if seconds else TYPICAL_FULL_SECONDS
    return f"{low:.0f} s" if round(high) <= round(low) else f"{low:.0f}-{high:.0f} s"


def cache_summary() -> str:
    """One line on the offline cache: its folder, size, and how many optimized configurations it holds."""
    folder = cache_folder().parent
    size = 0
    if folder.is_dir():
        for path in folder.rglob("*"):
            with contextlib.suppress(OSError):
                if path.is_file():
                    size += path.stat().st_size
    ready = cache_folder() / "ready"
    n_ready = len(list(ready.glob("*.json"))) if ready.is_dir() else 0
    return f"cache {folder} ({size / 1e6:.1f} MB, {n_ready} optimized configuration(s) recorded)"


# --- the tier of a configuration ----------------------------------------------------------------------
_ANNOUNCED: set = set()


def current_tier(config: KernelConfig) -> str:
    """The tier that serves ``config`` now, by the compile mode; in ``"auto"`` a configuration not ready
    yet gets its background compile started (once) and the fast tier meanwhile."""
    mode = backend.info().compile_mode
    if mode == "fast":
        return "fast"
    if mode == "full" or is_ready(config):
        if mode == "full" and (config, "full") not in _ANNOUNCED and not is_ready(config):
            _ANNOUNCED.add((config, "full"))
            LOG.info(
                "compiling optimized kernels for %s (first use on this machine; about %s)",
                config.describe(),
                typical_seconds(),
            )
        return "full"
    if not config.rebuildable:
        if (config, "full") not in _ANNOUNCED:
            _ANNOUNCED.add((config, "full"))
            LOG.info(
                "compiling optimized kernels for %s in this process (registered in this script, so no "
                "background process can rebuild it; about %s; a plugin file lets it compile in the "
                "background)",
                config.describe(),
                typical_seconds(),
            )
        return "full"
    if (config, "fast") not in _ANNOUNCED:
        _ANNOUNCED.add((config, "fast"))
        started = request_background_compile(config)
        LOG.info(
            "compiling kernels for %s (first use on this machine: quick kernels now, about 1-5 s; %s)",
            config.describe(),
            "the optimized ones compile in the background and take over when ready"
            if started
            else "the optimized ones are being compiled by another process",
        )
    return "fast"


def _pending_alive(path: Path) -> bool:
    """Whether a background compile announced by ``path`` (its pid) still runs."""
    try:
        pid = int(path.read_text().split()[0])
        age = time.time() - path.stat().st_mtime
    except (OSError, ValueError, IndexError):
        return False
    if age > PENDING_TIMEOUT_S:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def request_background_compile(config: KernelConfig) -> bool:
    """Start a detached low-priority process that compiles ``config``'s optimized kernels into the
    offline cache, unless one runs for it already; returns whether one was started."""
    pending = _pending_file(config)
    try:
        pending.parent.mkdir(parents=True, exist_ok=True)
    except OSError:  # a cache that cannot be written (read-only HOME): the quick kernels serve the run
        return False
    if pending.exists() and _pending_alive(pending):
        return False
    with contextlib.suppress(FileNotFoundError):
        pending.unlink()
    try:
        fd = os.open(pending, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except OSError:  # another process asked in the same instant (FileExistsError), or not writable
        return False
    env = dict(os.environ)
    env["TI_OFFLINE_CACHE_FILE_PATH"] = str(cache_folder().parent)
    log = cache_folder() / "background.log"
    with open(log, "ab") as out:
        process = subprocess.Popen(
            [sys.executable, "-c", _WORKER, config.to_json()],
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,  # outlives the command that asked (its Ctrl-C does not reach it)
            close_fds=True,
        )
    with os.fdopen(fd, "w") as f:
        f.write(f"{process.pid}\n")
    return True


# --- compiling a configuration ------------------------------------------------------------------------
#: the background process's program: ``python -c _WORKER CONFIG_JSON``
_WORKER = "import sys; from cmax_taichi.pipeline.tiers import compile_in_background; " \
    "sys.exit(compile_in_background(sys.argv[1]))"
def _synthetic_events(n: int = 2000, size=(64, 48)):
    """A random window on a sensor of ``size`` (the optimized fused kernels' sensor; the others read it
    at run time: any serves)."""
    import numpy as np

    from cmax_taichi.core.events import Events

    rng = np.random.default_rng(0)
    W, H = size
    t = np.sort(rng.uniform(0.0, 0.02, n))
    return Events(rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n), t, rng.integers(0, 2, n), size)


def build_kernels(config: KernelConfig) -> None:
    """Compile (or load) ``config``'s kernels in this process, in the tier its compile mode gives: a small
    problem of the same options evaluated on each CPU loop schedule."""
    import numpy as np

    from cmax_taichi.core import registry
    from cmax_taichi.core.events import Camera

    for plugin in config.plugins:
        registry.load_plugin(plugin)
    size = tuple(config.sensor) or (64, 48)
    events = _synthetic_events(size=size)
    camera = Camera(fx=50.0, fy=50.0, cx=(size[0] - 1) / 2, cy=(size[1] - 1) / 2)
    weights = np.ones(len(events)) if config.weighted else None
    regs = dict.fromkeys(config.regularizers, 1.0)
    sigma = config.radius / 3.0  # a blur of this footprint (the taps are run-time values)
    if config.kind == "fused":
        from cmax_taichi.pipeline.fused import FusedPipeline
        from cmax_taichi.pipeline.problem import ContrastMaximization

        schedules = ("serial", "parallel") if config.arch == "cpu" else ("auto",)
        saved = FusedPipeline.loops
        try:
            for loops in schedules:
                FusedPipeline.loops = loops
                FusedPipeline.force_atomic = config.atomic and config.arch == "cpu"
                prob = ContrastMaximization(
                    events, config.warp, config.objective, regs, camera,
                    blur_sigma=sigma, polarity=config.polarity, weights=weights,
                )  # fmt: skip
                theta = np.full(prob.model.n_params, 1e-3)
                prob.value_and_grad(theta)
                prob.value(theta)
        finally:
            FusedPipeline.loops, FusedPipeline.force_atomic = saved, False
    else:
        from cmax_taichi.flow.problem import DenseFlowProblem

        references = "first" if config.references == 1 else tuple(np.linspace(0, 1, config.references))
        prob = DenseFlowProblem(
            events, (2, 2), objective=config.objective, references=references, regularizers=regs,
            blur_sigma=sigma, polarity=config.polarity, weights=weights, kink_width=config.kink_width,
        )  # fmt: skip
        prob.value_and_grad(np.zeros(prob.grid.shape))


def compile_in_background(config_json: str) -> int:
    """The background process: ``config``'s optimized kernels into the offline cache, one such process
    at a time per cache folder, then the record that they are ready."""
    import fcntl
    import resource

    config = KernelConfig.from_json(config_json)
    with contextlib.suppress(OSError):
        os.nice(10)  # the command that asked keeps the machine
    backend.init(arch=config.arch, precision=config.precision, compile_mode="full")
    folder = cache_folder()
    folder.mkdir(parents=True, exist_ok=True)
    try:
        with open(folder / "compile.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # one compile at a time: the machine stays usable
            if not is_ready(config):
                t0 = time.perf_counter()
                build_kernels(config)
                seconds = time.perf_counter() - t0
                backend.finish()  # Taichi writes its offline cache when its program ends
                peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
                _write_json(
                    _ready_file(config, folder),
                    {"config": json.loads(config.to_json()), "seconds": round(seconds, 1),
                     "peak_rss_mb": round(peak), "finished": time.strftime("%Y-%m-%dT%H:%M:%S")},
                )  # fmt: skip
                print(f"compiled {config.describe()} in {seconds:.1f} s (peak RSS {peak:.0f} MB)", flush=True)
    finally:
        with contextlib.suppress(OSError):
            (folder / "pending" / config.key()).unlink()
    return 0


def compile_configs(configs: Sequence[KernelConfig]) -> list[dict]:
    """Compile the optimized kernels of ``configs`` into the offline cache, each in a process of its own
    (this process's Taichi program is left as it is), one after the other; already compiled ones are
    skipped. Returns one record per configuration: ``config``, ``status`` ("ready", "compiled",
    "failed"), ``seconds``."""
    records = []
    for config in configs:
        if not config.rebuildable:
            raise ValueError(
                f"{config.describe()}: registered in this script, so no other process can rebuild it; "
                "register it in a plugin file (cmax-taichi ... --plugin FILE.py) to prebuild it"
            )
        if is_ready(config):
            records.append({"config": config, "status": "ready", "seconds": 0.0})
            continue
        LOG.info("compiling optimized kernels for %s (about %s)", config.describe(), typical_seconds())
        t0 = time.perf_counter()
        env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=str(cache_folder().parent))
        done = subprocess.run(
            [sys.executable, "-c", _WORKER, config.to_json()],
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            env=env,
        )
        seconds = time.perf_counter() - t0
        ok = done.returncode == 0 and is_ready(config)
        record = {"config": config, "status": "compiled" if ok else "failed", "seconds": seconds}
        if not ok:
            lines = [line for line in (done.stderr + done.stdout).strip().splitlines() if line.strip()]
            record["reason"] = lines[-1] if lines else f"exit code {done.returncode}"
            LOG.warning("compiling %s failed: %s", config.describe(), record["reason"])
        records.append(record)
    return records


def warmup(
    warp: str | None = "translation2",
    objective: str = "variance",
    regularizers: Mapping[str, float] | Sequence[str] | None = None,
    *,
    blur_sigma: float = 1.0,
    polarity: str = "ignore",
    weighted: bool = False,
    references: int = 1,
    sensor_size: tuple[int, int] = (240, 180),
) -> dict:
    """Compile the optimized kernels of problems of these options beforehand (``cmax-taichi warmup``).

    The kernels go into Taichi's offline cache (:func:`cache_folder`), where every later process on
    this machine finds them: it then starts on the optimized kernels at once. The optimized fused
    kernels have the sensor compiled in (one compile per sensor size); the dense flow's serve every
    sensor. The compile runs in a process of its own (this one's Taichi program is left as it is).

    Parameters
    ----------
    warp : str or None
        The warp model of a :class:`~cmax_taichi.ContrastMaximization`, or None for the dense flow
        (:class:`~cmax_taichi.flow.DenseFlowProblem`).
    objective : str
    regularizers : mapping or sequence of str, optional
        The event-collapse regularizers (names, in the problem's order; weights do not matter).
    blur_sigma : float
        The blur, px (its footprint is compiled in; its weights are not).
    polarity : {"ignore", "signed", "split"}
    weighted : bool
        Problems with per-event vote weights.
    references : int
        Reference times of the dense flow (1, or 3 for ``references="multi"``).
    sensor_size : (int, int)
        The sensor (width, height), px, of the fused kernels (ignored for the dense flow).

    Returns
    -------
    dict
        ``config`` (its description), ``status`` ("ready": already compiled, "compiled", "failed") and
        ``seconds``.

    Raises
    ------
    ValueError
        An unknown name, or an entry registered in the running script (no other process can rebuild
        it: register it in a plugin file).
    """
    names = list(regularizers or ())
    config = config_for(
        warp=warp, objective=objective, regularizers=names, blur_sigma=blur_sigma, polarity=polarity,
        weighted=weighted, references=references, sensor_size=sensor_size,
    )  # fmt: skip
    record = compile_configs([config])[0]
    return {"config": config.describe(), "status": record["status"], "seconds": record["seconds"]}
