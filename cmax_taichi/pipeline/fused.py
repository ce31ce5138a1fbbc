"""Driver of the fused pipeline (``kernels/fused.py``) for :class:`~cmax_taichi.ContrastMaximization`.

The fused pipeline computes the same J and dJ/dtheta as the generic kernel chain of ``problem.py`` in
one kernel launch per value-and-gradient, with no atomics on the CPU, no per-call fills and no
per-call allocation. It serves every problem whose parts declare what its hand-written backward needs
(all polarity modes, weights and blur widths):

* the warp model: its closed-form parameter Jacobian ``WarpModel.param_jac`` (the built-ins' are in
  their modules of ``kernels/warps/``), at most ``MAX_PARAMS`` parameters, and optionally
  ``constant_quantities`` and ``positive_det``;
* each regularizer: its quantity kind (``Regularizer.kind``, "div" or "absdet") and
  ``Regularizer.penalty_grad``;
* the objective: its fused declaration ``Objective.fused`` (a :class:`FusedObjective`);
* no whitening.

The choice reads these declarations only (never the identity of a function). Where one is missing,
:meth:`FusedPipeline.for_problem` says why and the generic chain of ``problem.py`` serves the problem.

The image fields are pooled per shape (``workspace.py``): problems of the same sensor, channel count,
regularizer count, parameter count and blur footprint share them and the compiled kernels; the events
of each problem live in its own ndarray, whose length is not compiled in (a window of another size
reuses the kernels).

On the CPU each kernel comes in two schedules of the same code (:class:`_Schedules`): its loops on
Taichi's thread pool, or all on the calling thread. Taichi 1.7.4 wakes the pool's workers for every
parallel loop (six per value-and-gradient), 40-100 us each on the 2-core reference machine: more than a
small window's whole work (a 1,000-event window's value-and-gradient: 0.07 ms on one thread, 0.4 ms on
the pool; benchmarks/NOTES.md). A window runs on one thread while its first call costs less than the
pool would save; J and dJ/dtheta of the two differ by rounding only (the compiler's code for each
schedule), and a window keeps one schedule for all its calls.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import taichi as ti

from cmax_taichi.core import backend, workspace
from cmax_taichi.kernels import fused as kfused
from cmax_taichi.kernels import fused_common as kcommon
from cmax_taichi.models.regularizers import REGULARIZERS, Regularizer
from cmax_taichi.models.warps import WarpModel
from cmax_taichi.pipeline import tiers
from cmax_taichi.pipeline.footprint import image_layout, kernels_key
from cmax_taichi.pipeline.launch import DirectLaunch, HostArray, array_bytes, kernel_arrays, plain

__all__ = ["ChainPathWarning", "FusedPipeline", "PathChoice"]

MAX_PARAMS = kfused.MAX_PARAMS


class ChainPathWarning(UserWarning):
    """A problem runs on the generic autodiff chain because a part of it does not declare what the fused
    pipeline needs (e.g. a warp model without ``param_jac``); value and gradient are the same, only
    slower. Issued once per distinct reason per process; ``ContrastMaximization.path_reason`` says it."""


@dataclass(frozen=True)
class PathChoice:
    """The outcome of :meth:`FusedPipeline.for_problem`.

    Attributes
    ----------
    pipeline : FusedPipeline or None
        The fused pipeline, or None where the generic chain serves the problem.
    reason : str
        Why the chain serves the problem ("" on the fused path).
    undeclared : bool
        The reason is a missing declaration (a :class:`ChainPathWarning` is due), not a choice of the
        user (whitening) or a limit of the kernels.
    """

    pipeline: FusedPipeline | None
    reason: str = ""
    undeclared: bool = False


_REGULARIZER_RECIPE = "docs/RECIPE_OBJECTIVE.md, section 'The fused path of a regularizer'"


def model_gap(model: WarpModel) -> str:
    """Why ``model`` cannot take the fused pipeline ("" when it can)."""
    if model.param_jac is None:
        return (
            f"warp {model.name!r} declares no param_jac (closed-form d x'/d theta, d det/d theta, "
            "d div/d theta): value and gradient run on the generic autodiff chain (declare it: "
            "docs/RECIPE_WARP.md, section 'The fused path: param_jac')"
        )
    return ""


def regularizer_gap(reg: Regularizer) -> str:
    """Why ``reg`` cannot take the fused pipeline ("" when it can)."""
    if reg.kind is None:
        return (
            f"regularizer {reg.name!r} declares no quantity kind (quantity='div' or 'absdet'): the fused "
            "backward differentiates those two only; value and gradient run on the generic autodiff chain "
            f"({_REGULARIZER_RECIPE})"
        )
    if reg.penalty_grad is None:
        return (
            f"regularizer {reg.name!r} declares no penalty_grad (d penalty / d map value): value and "
            f"gradient run on the generic autodiff chain (declare it: {_REGULARIZER_RECIPE})"
        )
    return ""


LOOP_SCHEDULES = ("auto", "serial", "parallel")


def stores_terms(declared: bool, serial: bool, n_voted: int) -> bool:
    """Whether the CPU kernel of a loop schedule stores a model's per-event terms: where the model
    declares ``store_event_terms`` (``declared``), on the thread pool always, and on the calling thread
    where no quantity is voted (``n_voted``). On one thread the stored position and its Jacobian (8
    rows for rotation3) cost less than the second warp they save (-5% to -11% per value_and_grad at
    1,000-10,000 rotation3 events, and on ECD boxes_rotation's windows), but with voted quantities (16
    rows with both regularizers) their traffic costs more (+1% to +15%; ``benchmarks/ab_rows.py
    --stored-terms``, benchmarks/NOTES.md)."""
    return bool(declared) and (not serial or n_voted == 0)


class _Schedules:
    """The fused kernel of one kernel key in its CPU schedules and compiled tiers, each built when first
    used, and what "auto" has learnt about where the calling thread alone is slower than the thread pool.

    Each (schedule, tier) is a Taichi kernel of its own: Taichi 1.7.4 compiles a kernel object once, with
    the compile options in force then, and never again, so the optimized tier cannot be a recompile of
    the fast tier's kernel. The fast tier's kernel reads the sensor's size at run time (one kernel for
    every sensor); the optimized tier's has it compiled in (a kernel per sensor: the image indices fold,
    faster than run-time sizes).

    ``parallel_from``: the smallest event count whose window ran on the pool because its timed calls
    on one thread exceeded the limit (:attr:`FusedPipeline.serial_limit_s`) and the same call on the pool
    was faster; windows of that many events or more go to the pool directly (no serial call, no second
    compile). ``serial_upto``: the largest window that stayed serial after its timed calls (under the
    limit, or over it and still faster than the pool); windows up to ``serial_probe_growth`` times it
    are not timed again.
    """

    def __init__(self, build) -> None:
        self._build = build
        self._kernels: dict[tuple, object] = {}
        self.parallel_from = None
        self.serial_upto = 0  # the largest window whose first serial call was under the limit

    def kernel(self, serial: bool, tier: str, sensor: tuple[int, int]):
        """The kernel of a schedule and tier (``sensor``: the sensor compiled into the optimized tier)."""
        key = (serial, tier, tuple(sensor) if tier == "full" else None)
        if key not in self._kernels:
            self._kernels[key] = self._build(serial, key[2])
        return self._kernels[key]


def _row_keys(y: np.ndarray, height: int) -> np.ndarray:
    """The pixel row of each event as the smallest integer type (int16 sorts by radix), clipped into
    the image (events outside it keep their place among the rows at the border)."""
    dtype = np.int16 if height < np.iinfo(np.int16).max else np.int32
    return np.clip(y, 0, height - 1).astype(dtype)


class FusedPipeline:
    """J and dJ/dtheta of one problem by the fused kernels.

    Build it with :meth:`for_problem`, which says why where the fused kernels do not apply.
    """

    #: switches for tests and the benchmark: ``enabled = False`` builds every problem on the generic
    #: kernel chain; ``force_atomic`` runs the atomic (GPU-style) splat on the CPU
    enabled = True
    force_atomic = False
    #: CPU loop schedule of the kernels: "parallel" (Taichi's thread pool), "serial" (the calling
    #: thread), or "auto": a window of at most ``serial_max_events`` events runs serially unless its
    #: first two calls there each take more than ``serial_limit_s`` of thread time (half that for a call
    #: without gradient) and the same call on the pool is faster (wall time, best of two), after which
    #: windows of that size and more run on the pool. A GPU has one schedule.
    loops = "auto"
    serial_max_events = 20_000
    #: the calling thread's time of one value-and-gradient above which the pool may be faster on the
    #: 2-core reference machine (its six loops' dispatch: 0.4-0.7 ms; benchmarks/NOTES.md): a window
    #: over it is timed on the pool too
    serial_limit_s = 1.0e-3
    #: a window is timed only when it has more than this many times the events of the largest window
    #: that passed: a stream of windows of about one size (undistortion drops a few events of each) is
    #: timed once, and a timing blip on a later window cannot move the stream to the pool, whose kernel
    #: a process then loads or compiles (0.8 s measured: a stalled window of a real-time stream)
    serial_probe_growth = 1.25

    @classmethod
    def for_problem(cls, problem, vote_w: np.ndarray | None) -> PathChoice:
        """The fused pipeline of ``problem`` (a ContrastMaximization being built), or why not.

        Decided from the declarations of the model, the regularizers and the objective only.
        """
        if not cls.enabled:
            return PathChoice(None, "the fused pipeline is switched off (FusedPipeline.enabled = False)")
        if problem.whitening:
            return PathChoice(None, "whitening runs on the generic autodiff chain only")
        model = problem.model
        if model.n_params > MAX_PARAMS:
            return PathChoice(
                None,
                f"warp {model.name!r} has {model.n_params} parameters; the fused kernels take {MAX_PARAMS}",
            )
        gap = model_gap(model)
        if gap:
            return PathChoice(None, gap, undeclared=True)
        regs = [REGULARIZERS.get(name) for name in problem.regularizer_weights]
        for reg in regs:
            gap = regularizer_gap(reg)
            if gap:
                return PathChoice(None, gap, undeclared=True)
        objective = problem.objective.fused  # the objective's declaration (models/objectives.py)
        if objective is None:
            reason = (
                f"objective {problem.objective.name!r} declares no fused path (fused=cm.FusedObjective): "
                "value and gradient run on the generic autodiff chain (declare it: docs/RECIPE_OBJECTIVE.md, "
                "section 'The fused path of an objective')"
            )
            return PathChoice(None, reason, undeclared=True)
        return PathChoice(cls(problem, objective, regs, vote_w))

    def __init__(self, problem, objective, regs: list, vote_w: np.ndarray | None) -> None:
        model = problem.model
        P = model.n_params
        weighted = vote_w is not None
        split = problem.polarity == "split"
        atomic = backend.info().arch != "cpu" or self.force_atomic
        layout = image_layout(
            n_channels=problem.n_channels,
            radius=problem.setup.radius,
            shared_count=bool(regs) and not weighted and not split,
            objective_slots=problem.objective.slots_per_channel,
            sobel=objective.sobel,
            atomic=atomic,
        )
        self.n_params = P
        # the declared capabilities (for_problem checked that they are there)
        kinds = tuple(r.kind for r in regs)
        constant = tuple(k in model.constant_quantities for k in kinds)
        n_voted = len(regs) - sum(constant)
        shape = self.shape = kfused.FusedShape(layout, len(regs), n_voted, P)
        W, H = problem.width, problem.height
        # the arrays of this sensor, shared by the problems of this shape and sensor (the regions the
        # last call wrote are in them: they go together)
        self._ws = workspace.acquire(
            ("fused", problem._backend.generation, shape, W, H),
            lambda ws: setattr(ws, "arrays", kernel_arrays(shape.array_sizes(W, H), atomic)),
            f"a {W}x{H} problem (fused pipeline)",
        )
        # the kernels of this configuration, whatever the sensor
        kkey = (
            "fused",
            problem._backend.generation,
            shape,
            model.name,
            id(model),
            *kernels_key(problem.objective.name, objective, regs, weighted, split, atomic, constant),
        )

        def build_kernel(serial: bool, sizes: tuple[int, int] | None):
            return kfused.make_fused_kernels(
                shape,
                model.warp,
                tuple(r.quantity_fn(model) for r in regs),
                tuple(r.penalty for r in regs),
                tuple(r.penalty_grad for r in regs),
                tuple(bool(getattr(r, "one_sided", False)) for r in regs),
                objective=objective,
                events=kcommon.EventLayout(weighted, split, atomic),
                param_jac=model.param_jac,
                quantity_kinds=kinds,
                constant=constant,
                det_fn=model.det,
                warp_terms=model.warp_terms,
                positive_det=model.positive_det,
                serial=serial,
                store_terms=stores_terms(model.store_event_terms, serial, n_voted),
                sizes=sizes,
            )

        self._schedules = workspace.compiled(kkey, lambda: _Schedules(build_kernel))
        self.kernel_config = tiers.fused_config(problem, regs, weighted, layout.n_slices, atomic)
        self.tier = "full"  # the compiled tier of the current window's kernels (load_window)
        self._launchers: dict[tuple[bool, str], DirectLaunch | None] = {}
        self._serial = False  # the schedule of the current window (load_window)
        self._probe = False  # the window's first call on one thread is still to be timed

        self._weighted, self._split, self._atomic = weighted, split, atomic
        self._sensor = (W, H)
        self._layout = kfused.params_layout(len(regs), layout.radius)
        self._params = HostArray(np.zeros(self._layout["size"]))  # theta and the window's constants
        self._out = HostArray(np.zeros(shape.out_size()))  # J, G_raw, dJ/dtheta, J with G0 = G_raw, slices
        self._event_buffer = None  # GPU: the pooled device buffer of the events
        self._packed = None
        # the kernel's stored event terms (kernels/fused.py, stage 1): a (rows, capacity) host array
        # where the model declares store_event_terms on the CPU (the kernels that store, stores_terms,
        # write it); otherwise a (1, 1) placeholder
        self._terms_rows = kfused.terms_width(P, n_voted) if model.store_event_terms and not atomic else 0
        self._n_voted = n_voted
        if atomic:  # an ndarray on a GPU (one per workspace: Taichi frees no ndarray it made)
            if getattr(self._ws, "no_terms", None) is None:
                self._ws.no_terms = ti.ndarray(backend.real(), shape=(1, 1))
            self._no_terms = self._ws.no_terms
        else:
            self._no_terms = HostArray(np.zeros((1, 1), dtype=backend.numpy_real()))
        self._terms = self._no_terms
        self.load_window(problem, vote_w)

    def can_take(self, problem, vote_w: np.ndarray | None) -> bool:
        """Whether :meth:`load_window` can serve ``problem``'s new window with these fields and kernels
        (same options: the same sensor and use of vote weights; on a GPU also the same event capacity
        bucket of the device buffer)."""
        return (
            (problem.width, problem.height) == self._sensor
            and (vote_w is not None) == self._weighted
            and (
                self._event_buffer is None
                or workspace.capacity_for(problem.n_events) == self._event_buffer.capacity
            )
        )

    def load_window(self, problem, vote_w: np.ndarray | None) -> None:
        """Take ``problem``'s current window: its constants and events.

        The window's constants go into ``params`` (read by the kernel at each launch); the events are
        packed into a host array: on the CPU the kernel reads that array in place (no upload, no device
        copy), on a GPU it is uploaded into a pooled device buffer at the next run.
        """
        setup = problem.setup  # pipeline/setup.py: the same constants as the generic chain's
        lay, params = self._layout, self._params.array
        params[lay["ctx"] : lay["ctx"] + 5] = setup.ctx
        lam = setup.lam
        params[lay["lam"] : lay["lam"] + len(lam)] = lam
        params[lay["g0"]] = 1.0
        if setup.taps is not None:  # (without blur the kernel's one tap is 1)
            params[lay["taps"] : lay["taps"] + len(setup.taps)] = setup.taps.astype(backend.numpy_real())
        self.n_events = n = problem.n_events
        self.tier = tiers.current_tier(self.kernel_config)  # (the optimized kernels from when they are ready)
        self._choose_schedule(n)

        # the events as (x, y, dt[, w][, channel]) vectors
        ev = problem.events
        cols = [ev.x, ev.y, ev.t - problem.t_ref]
        if self._weighted:
            cols.append(vote_w)
        if self._split:
            cols.append((ev.p < 0).astype(np.float64))
        capacity = workspace.capacity_for(n)  # host arrays by powers of two too: few reallocations
        if self._packed is None or self._packed.shape[0] != capacity:
            self._packed = np.zeros((capacity, len(cols)), dtype=backend.numpy_real())
        elif self._atomic:
            self._packed[n:] = 0.0  # the device buffer is uploaded whole
        # the events ordered by their pixel row (a stable radix sort: time order within a row), so that
        # consecutive events vote into, and gather the adjoints from, the same few rows of the images,
        # which stay in the L1 cache: 10-30% less CPU time per call at 1M events (benchmarks/NOTES.md).
        # J and dJ/dtheta are sums over events: the order changes their rounding only.
        # (on the CPU only: on a GPU, neighbouring events would contend for the same atomic adds)
        order = slice(None) if self._atomic else np.argsort(_row_keys(ev.y, self._sensor[1]), kind="stable")
        for j, col in enumerate(cols):
            self._packed[:n, j] = col[order]
        if self._atomic:
            # a pooled device buffer (workspace.event_buffer: vector ndarrays are never freed), padded to
            # its capacity; uploaded when another problem (or window) used it in between
            if self._event_buffer is None or self._event_buffer.capacity != capacity:
                self._event_buffer = workspace.event_buffer(backend.real(), len(cols), n)
            self._event_buffer.release()
            self.events = self._event_buffer.array
        else:
            self.events = HostArray(self._packed[:n])
            if self._terms_rows and self._terms.shape[1] != capacity:
                rows = self._terms_rows
                self._terms = HostArray(np.zeros((rows, capacity), dtype=backend.numpy_real()))
        self.event_bytes = self._packed.nbytes + (self._terms.nbytes if self._terms_rows else 0)

    def _choose_schedule(self, n: int) -> None:
        """The loop schedule of a window of ``n`` events (class attribute :attr:`loops`)."""
        loops = self.loops
        if loops not in LOOP_SCHEDULES:
            raise ValueError(f"FusedPipeline.loops must be one of {', '.join(LOOP_SCHEDULES)}, got {loops!r}")
        if self._atomic:
            self._serial = self._probe = False
        elif loops == "auto":
            learnt = self._schedules.parallel_from
            self._serial = n <= self.serial_max_events and (learnt is None or n < learnt)
            # probed only above the largest window that passed: a stream of similar windows is timed
            # once, and does not switch (and load the pool's kernel) late on a slow call
            self._probe = self._serial and n > self.serial_probe_growth * self._schedules.serial_upto
        else:
            self._serial, self._probe = loops == "serial", False

    @property
    def serial(self) -> bool:
        """Whether the current window's kernel runs all its loops on the calling thread."""
        return self._serial

    @property
    def stores_event_terms(self) -> bool:
        """Whether the current window's kernel stores per-event terms (:func:`stores_terms`): then
        ``value`` agrees with the value of ``value_and_grad`` to a few ulps rather than to the last
        bit."""
        return stores_terms(bool(self._terms_rows), self._serial, self._n_voted)

    # --- state -----------------------------------------------------------------------------------
    def set_g0(self, g0: float) -> None:
        """Divide G by ``g0`` in J from now on."""
        self._params.array[self._layout["g0"]] = float(g0)

    def _load(self) -> None:
        if self._event_buffer is not None:
            self._event_buffer.load(self, self._packed)

    def _run(self, theta: np.ndarray, grad: int) -> np.ndarray:
        self._load()
        params = self._params.array
        params[: theta.size] = theta  # the other parameter slots stay 0
        if not self._probe:
            return self._launch(grad)
        # the window's first call on one thread: timed (thread time: what the other processes on the
        # machine do does not count); above the limit the window moves to the pool, before any of its
        # results is used, so that all its calls come from one schedule
        self._probe = False
        t0 = time.thread_time()
        out = self._launch(grad)
        if self._compiling:  # that call compiled the kernel (or loaded it): time the launch alone
            t0 = time.thread_time()
            out = self._launch(grad)
        limit = self.serial_limit_s * (1.0 if grad & 1 else 0.5)
        elapsed = time.thread_time() - t0
        if elapsed > limit:
            # a window's first launch also pays for what it touches first (its new events, image rows
            # cold in the cache): a second launch decides, before the window moves (and loads a kernel)
            t0 = time.thread_time()
            out = self._launch(grad)
            elapsed = time.thread_time() - t0
        if elapsed <= limit:
            self._schedules.serial_upto = max(self._schedules.serial_upto, self.n_events)
            return out
        # over the limit on one thread: time the pool on the same call (its kernel is needed from here on
        # if it wins, and the limit alone misjudged windows near it: 5,000 events on 1280x720 moved to
        # the pool at 1.18 ms a call against 0.86 ms serially) and keep the faster; wall time for the
        # pool, whose calling thread sleeps while the workers run
        out = out.copy()  # the next launches write the same output array
        self._serial = False
        pool_out = self._launch(grad)
        pool = math.inf
        for _ in range(2):  # (the first may compile or load the kernel, or find the slices cold)
            t0 = time.perf_counter()
            pool_out = self._launch(grad)
            pool = min(pool, time.perf_counter() - t0)
        if pool < elapsed:
            learnt = self._schedules.parallel_from
            self._schedules.parallel_from = self.n_events if learnt is None else min(learnt, self.n_events)
            return pool_out
        self._serial = True
        self._schedules.serial_upto = max(self._schedules.serial_upto, self.n_events)
        return out

    def _launch(self, grad: int) -> np.ndarray:
        serial = self._serial
        launcher = self._launchers.get((serial, self.tier))
        self._compiling = False
        if launcher is not None and launcher.valid():
            ctx = launcher.ctx
            ctx.set_arg_int((0,), self.n_events)
            ctx.set_arg_int((4,), grad)
            # the arrays and sizes: on the CPU (host arrays, read in place) set when they change (a new
            # window's events and terms are new host arrays, load_window; the workspace's arrays go with
            # the sensor); a GPU launch replaces a device array in the context by its pointer, so there
            # they are set each time
            arrays = (self._ws, self.events, self._terms)  # (compared by identity: none defines ==)
            if self._atomic or launcher.set_for != arrays:
                launcher.set_array(1, self.events)
                launcher.set_array(2, self._terms)
                launcher.set_array(3, self._params)
                launcher.set_array(5, self._out)
                ctx.set_arg_int((6,), self._sensor[0])
                ctx.set_arg_int((7,), self._sensor[1])
                for index, array in enumerate(self._ws.arrays.values(), start=8):
                    launcher.set_array(index, array)
                launcher.set_for = arrays
            launcher.launch()
            return self._out.array
        self._compiling = True  # (or loading from the offline cache: not a measure of the window)
        kernel = self._schedules.kernel(serial, self.tier, self._sensor)
        call = self.kernel_call(grad)
        # the tier's compile settings (read when it compiles): one Taichi kernel serves both tiers, Taichi
        # compiles (or loads) it per configuration
        with backend.hand_written_gradient_kernels(self.tier):
            kernel(*call)
            # the next calls launch the compiled kernel directly
            self._launchers[(serial, self.tier)] = DirectLaunch.make(kernel, call)
        return self._out.array

    def kernel_call(self, grad: int) -> tuple:
        """The arguments of an ordinary call of the window's kernel (``Kernel.__call__``), in the order
        that the direct launch sets them."""
        return (
            self.n_events,
            plain(self.events),
            plain(self._terms),
            self._params.array,
            grad,
            self._out.array,
            *self._sensor,
            *(plain(a) for a in self._ws.arrays.values()),
        )

    # --- evaluation ------------------------------------------------------------------------------
    def launch_ready(self) -> bool:
        """Whether the next call launches the compiled kernel directly (compiled, and Taichi still runs
        the program it was compiled in)."""
        launcher = self._launchers.get((self._serial, self.tier))
        return launcher is not None and launcher.valid()

    def value(self, theta: np.ndarray) -> float:
        """J at ``theta`` (float64 array of the model's length)."""
        return float(self._run(theta, 0)[0])

    def evaluate(self, theta: np.ndarray) -> tuple[float, float]:
        """``(J, G_raw)`` at ``theta``."""
        out = self._run(theta, 0)
        return float(out[0]), float(out[1])

    def value_and_grad(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """``(J, dJ/dtheta)`` at ``theta``: one kernel launch."""
        out = self._run(theta, 1)
        return float(out[0]), out[2 : 2 + self.n_params].copy()

    def self_normalized_value(self) -> float:
        """J of the last evaluation as if G0 were its own G: evaluated at the identity, the normalised J
        that every later evaluation there gives (bit for bit: the kernel's own operations)."""
        return float(self._out.array[2 + self.n_params])

    def event_array(self) -> np.ndarray:
        """The packed events of the window as the kernel reads them, ``(n_events, columns)`` (tests)."""
        return self._packed[: self.n_events]

    def image(self) -> np.ndarray:
        """The blurred IWE of the last evaluation, (C, H, W) float64 (one more launch at its theta, which
        keeps the image: the evaluations do not store it unless the objective reads it)."""
        self._run(self._params.array[: self.n_params].copy(), 2)  # theta: the last call's
        W, H = self._sensor
        C = self.shape.layout.n_channels
        images = self._ws.arrays["images"]
        flat = images.array if isinstance(images, HostArray) else images.to_numpy()
        img = flat[2 * C * W * H : 3 * C * W * H]  # the planes tmp, tmp2, then img (FusedShape.image_planes)
        return img.reshape(C, H, W).astype(np.float64)

    def nbytes(self) -> int:
        """Bytes of the shared arrays plus this problem's event array."""
        return array_bytes(self._ws.arrays) + self.event_bytes
