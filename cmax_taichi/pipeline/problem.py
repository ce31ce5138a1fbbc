"""The Contrast Maximization problem: events + warp + objective + regularizers -> value and gradient.

:class:`ContrastMaximization` owns the Taichi fields of one problem and runs the kernel chain

    splat (warp, IWE votes, map votes) -> blur x -> blur y -> objective reduce -> maps reduce -> loss

forward, then the same kernels' ``.grad`` in reverse order for dJ/dtheta. Fields are allocated once;
repeated evaluations allocate nothing. Formulas: docs/FORMULAS.md.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import taichi as ti

from cmax_taichi.core import backend, workspace
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.kernels import blocks as kblocks
from cmax_taichi.kernels import events as kevents
from cmax_taichi.kernels import iwe as kiwe
from cmax_taichi.kernels import loss as kloss
from cmax_taichi.kernels import maps as kmaps
from cmax_taichi.kernels import tiles as ktiles
from cmax_taichi.kernels import whitening as kwhite
from cmax_taichi.models.regularizers import REGULARIZERS, Regularizer, penalty_value
from cmax_taichi.models.warps import WarpModel, get_warp
from cmax_taichi.pipeline.flow_field import dense_flow
from cmax_taichi.pipeline.footprint import n_slices
from cmax_taichi.pipeline.fused import ChainPathWarning, FusedPipeline
from cmax_taichi.pipeline.parameters import all_finite as _all_finite
from cmax_taichi.pipeline.parameters import check_theta as _check_theta
from cmax_taichi.pipeline.parameters import float_limit as _float_limit
from cmax_taichi.pipeline.parameters import require_finite as _require_finite
from cmax_taichi.pipeline.setup import (
    POLARITY_MODES,
    RX,
    RXY,
    ProblemSetup,
    SetupOptions,
    SetupView,
    allocate_images,
    check_limits,
    image_kernels,
    images_key,
    make_clear,
    run_chain,
    run_chain_backward,
    upload,
)
from cmax_taichi.pipeline.setup import cached_kernel as _cached

__all__ = ["ContrastMaximization", "POLARITY_MODES", "Evaluation"]

# reasons already warned about in this process (ChainPathWarning is issued once per reason)
_WARNED_REASONS: set[str] = set()


def _warn_chain_path(reason: str) -> None:
    if reason not in _WARNED_REASONS:
        _WARNED_REASONS.add(reason)
        warnings.warn(reason, ChainPathWarning, stacklevel=3)


@dataclass(frozen=True)
class Evaluation:
    """Everything one evaluation computed (all floats; R values dimensionless).

    Attributes
    ----------
    J : float
        Augmented objective ``G - sum lambda_r R_r``.
    G : float
        Objective used in J (normalised by ``G0`` when the problem normalises).
    G_raw : float
        Raw objective of the IWE.
    G0 : float
        Raw objective of the identity warp.
    R : dict
        Penalty of every registered regularizer (computed whether or not it is weighted in J).
    """

    J: float
    G: float
    G_raw: float
    G0: float
    R: dict


class ContrastMaximization(SetupView):
    """A CMax problem on one window of events.

    Parameters
    ----------
    events : Events
        The window (at least 2 events spanning a positive time).
    warp : str or WarpModel
        Motion model; see :func:`cmax_taichi.warp_names`.
    objective : str
        Focus measure; see :func:`cmax_taichi.objective_names`.
    regularizers : mapping of str to float, optional
        Weights ``lambda`` of the regularizers, e.g. ``{"divergence": 1.0, "deformation": 1.0}``.
        A weight of 0 keeps the map but not its penalty.
    camera : Camera, optional
        Intrinsics (required by ``rotation3``). Its principal point is the centre of the zoom /
        rotation models; events are undistorted with it unless ``events.undistorted``.
    t_ref : {"first", "middle", "last"} or float
        Reference time (a float is seconds on the events' clock, within the window's span give or
        take its duration: :func:`~cmax_taichi.pipeline.setup.resolve_t_ref`).
    blur_sigma : float
        Gaussian blur of the IWE, px (0 = none).
    polarity : {"ignore", "signed", "split"}
        How polarity enters the IWE.
    weights : array_like, optional
        Per-event vote weights (finite); default 1.
    normalize : bool
        Use ``G(theta) / G(0)`` (default) rather than the raw objective in J.
    whitening : bool
        Whitening baseline: build the IWE from whitened warped positions. A baseline, not a remedy:
        it does not prevent collapse, and with ``rotation3`` it has a collapse of its own (a rotation
        that throws a few events far away inflates their covariance, and whitening shrinks the rest
        into a few pixels: docs/results-real.md).

    Attributes
    ----------
    path : {"fused", "chain"}
        Which pipeline computes value and gradient: the fused kernels (one launch) or the generic
        autodiff kernel chain (slower; same values).
    path_reason : str
        Why the chain serves this problem ("" on the fused path). When the reason is a missing
        declaration (a warp without ``param_jac``, a regularizer without quantity kind or
        ``penalty_grad``, ...), a :class:`~cmax_taichi.ChainPathWarning` says it once per process.

    Notes
    -----
    ``value_and_grad(theta)`` returns ``(J, dJ/dtheta)`` for ``theta`` in the model's physical units.
    """

    def __init__(
        self,
        events: Events,
        warp: str | WarpModel = "mitrokhin4",
        objective: str = "variance",
        regularizers: Mapping[str, float] | None = None,
        camera: Camera | None = None,
        t_ref: str | float = "first",
        blur_sigma: float = 1.0,
        polarity: str = "ignore",
        weights: Sequence[float] | np.ndarray | None = None,
        normalize: bool = True,
        whitening: bool = False,
    ) -> None:
        self._backend = backend.ensure_initialized()
        if not isinstance(events, Events):
            raise TypeError(f"events must be cmax_taichi.Events, got {type(events).__name__}")
        self.model: WarpModel = get_warp(warp)
        # what set_events needs to check and derive the next window as this one
        self._options = SetupOptions(objective, regularizers, camera, t_ref, blur_sigma, normalize, polarity)
        self.whitening = bool(whitening)
        self._fused = None
        self._theta_limit = _float_limit()  # holds for this backend generation (_check_alive)
        self._take_window(self._setup_for(events, weights))

    def _setup_for(self, events: Events, weights) -> ProblemSetup:
        setup = self._options.build(events, [self.model], weights)
        check_limits(setup, "this problem", n_slices=n_slices())  # before anything is allocated
        return setup

    def set_events(self, events: Events, weights: Sequence[float] | np.ndarray | None = None) -> None:
        """Take another window of events in place, with this problem's warp, objective, regularizers,
        camera and options (the next window of a recording).

        Equivalent to building a new problem with the same arguments, but it keeps this object and its
        pooled fields and compiled kernels: per window it only checks and uploads the events and
        evaluates the identity warp (``G0``). :func:`cmax_taichi.solve.sequence.process` uses it.

        Parameters
        ----------
        events : Events
            The new window (at least 2 events spanning a positive time; any count and sensor).
        weights : array_like, optional
            Per-event vote weights of the new window (finite); default 1.

        Raises
        ------
        TypeError, ValueError
            As the constructor, for the new window; the problem then still holds its previous window.
        """
        self._check_alive()
        if not isinstance(events, Events):
            raise TypeError(f"events must be cmax_taichi.Events, got {type(events).__name__}")
        setup = self._setup_for(events, weights)
        previous = self.setup
        try:
            self._take_window(setup)
        except ValueError:  # e.g. a flat identity image: keep serving the previous window
            self._take_window(previous)
            raise

    def _take_window(self, setup: ProblemSetup) -> None:
        """Adopt a checked window: its derived values, the pipeline that serves it, its ``G0``."""
        self.setup = setup  # events, camera, objective, t_ref, ... (SetupView)
        self._weighted = setup.vote_weights is not None
        # The fused kernels (cmax_taichi/fused.py) serve value and gradient where they apply; the
        # generic chain's fields are then allocated only if maps(), evaluate() or jacobians need them.
        if self._fused is not None and self._fused.can_take(self, setup.vote_weights):
            self._fused.load_window(self, setup.vote_weights)
        else:
            choice = FusedPipeline.for_problem(self, setup.vote_weights)
            self._fused = choice.pipeline
            self.path = "fused" if self._fused is not None else "chain"
            self.path_reason = choice.reason
            if choice.undeclared:
                _warn_chain_path(choice.reason)
        if getattr(self, "_generic_ready", False):
            self._ws.release()  # the generic chain takes the new window at its next use
        self._generic_ready = False
        if self._fused is None:
            self._ensure_generic()
        self.G0 = 1.0
        if self._fused is not None:
            self._fused.set_g0(1.0)
        self._identity_value = None
        j0, g0 = self._forward(np.zeros(self.model.n_params))
        if not (math.isfinite(g0) and g0 > 0):
            raise ValueError(self._flat_identity(g0))
        self.G0 = g0 if self.normalize else 1.0
        self._identity_objective = g0
        if self._fused is not None:
            # J at the identity is known now: the optimizers' evaluation of it there costs nothing
            self._identity_value = self._fused.self_normalized_value() if self.normalize else j0
            self._fused.set_g0(self.G0)

    def _flat_identity(self, g0: float) -> str:
        """Why the identity's objective is ``g0`` (0 or not finite): a warp that does not keep the
        events on the image at theta = 0 (a user's model returning NaN), or truly a flat image."""
        img = self._fused.image() if self._fused is not None else self._img.to_numpy()
        weights = self.setup.vote_weights
        expected = float(np.sum(weights)) if weights is not None else float(self.n_events)
        votes = float(np.sum(img[np.isfinite(img)]))
        if not np.all(np.isfinite(img)) or votes < 0.5 * expected:
            return (
                f"warp {self.model.name!r} at the identity (every parameter 0) puts {votes:.0f} of "
                f"{expected:.0f} event votes in the image (the others at non-finite positions or off the "
                f"sensor): a warp must leave the events where they are at theta = 0; check the model with "
                f"cmax_taichi.check_model({self.model.name!r})"
            )
        return (
            f"the identity warp's {self.objective.name} is {g0}: the events give a flat image "
            "(nothing to maximise)"
        )

    @property
    def kernels(self) -> str:
        """The kernels that compute value and gradient now: ``"full"`` (the optimized fused kernels),
        ``"fast"`` (fused kernels compiled quickly, while the optimized ones compile in the background:
        ``pipeline/tiers.py``) or ``"chain"`` (the generic autodiff kernels)."""
        return "chain" if self._fused is None else self._fused.tier

    # --- fields and kernels ----------------------------------------------------------------------
    def _ensure_generic(self) -> None:
        """Allocate and load the generic kernel chain's fields and kernels (once)."""
        if self._generic_ready:
            return
        self._generic_ready = True
        self._allocate()
        self._build_kernels()

    def _allocate(self) -> None:
        """Take the pooled fields of this problem's shape and load this problem into them."""
        setup = self.setup
        self._reg_names = list(self.regularizer_weights)
        key = (
            "problem",
            self._backend.generation,
            workspace.capacity_for(self.n_events),
            self.width,
            self.height,
            self.n_channels,
            self.model.n_params,
            len(self._reg_names),
            setup.radius,
            self.objective.slots_per_channel,
            self._weighted,
            self.polarity == "split",
            self.whitening,
            images_key(setup, self.n_channels),
        )
        self._ws = workspace.acquire(key, self._build_fields, f"a {self.width}x{self.height} problem")
        ev = self.events
        self._per_event = {
            "ex": ev.x,
            "ey": ev.y,
            "edt": ev.t - self.t_ref,
            "ew": setup.vote_weights,
            "ech": (ev.p < 0).astype(np.int8) if self.polarity == "split" else None,
        }
        if self.whitening:
            mu0 = np.array([ev.x.mean(), ev.y.mean()])
            S0 = np.cov(np.stack([ev.x, ev.y]), bias=True)
            evals, evecs = np.linalg.eigh(S0)
            L0 = evecs @ np.diag(np.sqrt(np.maximum(evals, 0.0))) @ evecs.T
            self._wconst = [float(self.n_events), mu0[0], mu0[1], L0[0, 0], L0[0, 1], L0[1, 1]]
        for name in (
            "ex",
            "ey",
            "edt",
            "ew",
            "ech",
            "th",
            "ctx",
            "vote",
            "tmp",
            "img",
            "taps",
            "count",
            "numer",
            "macc",
            "lam",
            "acc",
            "loss",
            "diag",
            "wmom",
            "tiles",
            "part",
            "mpart",
        ):
            setattr(self, "_" + name, getattr(self._ws, name))
        self._load()

    def _build_fields(self, ws) -> None:
        """Allocate the fields of a workspace (called once per problem shape)."""
        real = backend.real()
        setup = self.setup
        cap = workspace.capacity_for(self.n_events)
        C, W, H, n_r = self.n_channels, self.width, self.height, len(self.regularizer_weights)
        ws.ex = ti.field(real, shape=cap)
        ws.ey = ti.field(real, shape=cap)
        ws.edt = ti.field(real, shape=cap)
        ws.ew = ti.field(real, shape=cap) if self._weighted else workspace.dummy(real)
        ws.ech = ti.field(ti.i8, shape=cap) if self.polarity == "split" else workspace.dummy(ti.i8)
        ws.th = ti.Vector.field(self.model.n_params, real, shape=(), needs_grad=True)
        ws.ctx = ti.Vector.field(5, real, shape=())
        allocate_images(ws, self.setup, C)
        if n_r:
            ws.count = ti.field(real, shape=(H, W), needs_grad=True)
            ws.numer = ti.field(real, shape=(n_r, H, W), needs_grad=True)
        else:
            ws.count = workspace.dummy(real, (1, 1))
            ws.numer = workspace.dummy(real, (1, 1, 1))
        ws.macc = ti.Vector.field(1 + n_r, real, shape=(), needs_grad=True)
        ws.lam = ti.Vector.field(max(2 * n_r, 1), real, shape=())
        ws.acc = ti.Vector.field(self.objective.slots_per_channel * C, real, shape=(), needs_grad=True)
        ws.loss = ti.field(real, shape=(), needs_grad=True)
        ws.diag = ti.Vector.field(1 + max(n_r, 1), real, shape=())
        n_w = kwhite.N_SLOTS if self.whitening else 1
        ws.wmom = ti.Vector.field(n_w, real, shape=(), needs_grad=True)
        n_entries = H * ws.tiles.n_segments
        ws.mpart = (
            ti.field(real, shape=(n_entries, 1 + n_r), needs_grad=True)
            if n_r
            else workspace.dummy(real, (1, 1))
        )
        ws.maps = {}
        images = [ws.vote, ws.vote.grad] + (
            [ws.tmp, ws.tmp.grad, ws.img, ws.img.grad] if setup.radius else []
        )
        if n_r:
            images += [ws.count, ws.count.grad, ws.numer, ws.numer.grad]
        rows = ((ws.mpart, 0), (ws.mpart.grad, 0)) if n_r else ()
        scalars = (
            ws.acc,
            ws.macc,
            ws.loss,
            ws.acc.grad,
            ws.macc.grad,
            ws.loss.grad,
            ws.th.grad,
            ws.wmom.grad,
        )
        ws.clear = make_clear(ws, tuple(images), rows, scalars)

    def _load(self) -> None:
        """Upload this problem's events and constants into the shared workspace if needed."""
        self._ensure_generic()
        ws = self._ws
        if ws.owned_by(self):
            return
        upload(ws, self.setup, self._per_event)
        ws.take(self)

    def _splat_kernel(self, regs: list[Regularizer], *, do_iwe: bool, whiten: bool = False):
        """The (cached) splat kernel voting the IWE (``do_iwe``) and the maps of ``regs``."""
        m = self.model
        flags = dict(
            width=self.width,
            height=self.height,
            n_channels=self.n_channels,
            split_polarity=self.polarity == "split",
            weighted=self._weighted,
            do_iwe=do_iwe,
            whiten=whiten,
        )
        reg_key = tuple((r.name, id(r)) for r in regs)
        return _cached(
            ("splat", m.name, id(m), reg_key, tuple(sorted(flags.items()))),
            lambda: kiwe.make_splat_kernel(m.warp, tuple(r.quantity_fn(m) for r in regs), **flags),
        )

    def _build_kernels(self) -> None:
        m, W, H, C = self.model, self.width, self.height, self.n_channels
        regs: list[Regularizer] = [REGULARIZERS.get(n) for n in self._reg_names]
        penalties = tuple(r.penalty for r in regs)
        reg_key = tuple((r.name, id(r)) for r in regs)
        self._k_splat = self._splat_kernel(regs, do_iwe=not self.whitening)
        if self.whitening:
            self._k_wsplat = self._splat_kernel([], do_iwe=True, whiten=True)
            self._k_moments = _cached(("moments", m.name, id(m)), lambda: kwhite.make_moments_kernel(m.warp))
        self._k_mark = self._mark_kernel(iwe=True, maps=bool(regs))
        self._kimg = image_kernels(self.setup, C, self._ws)
        obj = self.objective
        if regs:
            self._k_maps = _cached(("maps", reg_key, W, H), lambda: kmaps.make_maps_reduce(penalties, W, H))
        self._k_loss = _cached(
            ("loss", obj.name, id(obj), C, W * H, tuple(r.one_sided for r in regs)),
            lambda: kloss.make_loss_kernel(obj.finalize, C, W * H, tuple(r.one_sided for r in regs)),
        )

    # --- evaluation ------------------------------------------------------------------------------
    def _check_alive(self) -> None:
        if backend.info().generation != self._backend.generation:
            raise RuntimeError(
                "this problem was built before the Taichi backend was reset (by cmax_taichi.init() or "
                "after a failed allocation); build it again"
            )

    def _args_splat(self, count=None, numer=None):
        """Arguments of a splat kernel; ``count``, ``numer``: other map fields than the chain's."""
        return (
            self.n_events,
            self._warp_inputs(),
            self._ew,
            self._ech,
            self._wmom,
            self._vote,
            self._count if count is None else count,
            self._numer if numer is None else numer,
        )

    def _mark_kernel(self, *, iwe: bool, maps: bool):
        """The (cached) forward-only kernel marking the segments the splats vote (``kernels/tiles.py``)."""
        m, W, H = self.model, self.width, self.height
        flags = dict(width=W, height=H, iwe=iwe, maps=maps, whiten=self.whitening)
        return _cached(
            ("mark", m.name, id(m), tuple(sorted(flags.items()))),
            lambda: kiwe.make_mark_kernel(m.warp, **flags),
        )

    def _args_mark(self, tiles):
        return (self.n_events, self._warp_inputs(), self._wmom, tiles)

    def _warp_inputs(self) -> kevents.WarpInputs:
        """The events, parameters and context that the per-event kernels read."""
        return kevents.WarpInputs(self._ex, self._ey, self._edt, self._th, self._ctx)

    def _kernel_chain(self):
        """The forward kernels with their arguments, in order."""
        chain = []
        if self.whitening:
            chain.append((self._k_moments, (self.n_events, self._warp_inputs(), self._wmom)))
            chain.append((self._k_wsplat, self._args_splat()))
        chain.append((self._k_splat, self._args_splat()))
        # forward only: the touched segments and the regions of the passes
        chain.append((self._k_mark, self._args_mark(self._tiles)))
        chain.append((self._kimg.compact, (self._tiles,)))
        if self.blur_sigma > 0:
            chain.append((self._kimg.blur_x, (self._vote, self._tmp, self._taps, self._tiles, RX)))
            chain.append((self._kimg.blur_y, (self._tmp, self._img, self._taps, self._tiles, RXY)))
        chain.append((self._kimg.reduce, self._kimg.reduce_args(self._ws, self._img, self._acc)))
        if self._reg_names:
            chain.append((self._k_maps, (self._count, self._numer, self._macc, self._tiles, self._mpart)))
        chain.append(
            (
                self._k_loss,
                (self._acc, self._macc, self._lam, float(self.G0), self._loss, self._diag),
            )
        )
        return chain

    def _forward(self, theta: np.ndarray) -> tuple[float, float]:
        """``(J, G_raw)`` at ``theta``."""
        if self._fused is not None:
            return self._fused.evaluate(theta)
        self._load()
        self._th[None] = theta.tolist()
        self._ws.clear()  # what the last evaluation wrote (images, gradients, sums), over its regions
        if self.whitening:
            self._wmom[None] = [0.0] * 5 + self._wconst
        run_chain(self._kernel_chain())
        return float(self._loss[None]), float(self._diag[None][0])

    def _backward(self) -> np.ndarray:
        # the gradients were cleared with the forward pass's fields; an objective's own reduce kernel
        # (no declared pixel terms) writes its image gradient everywhere
        if not self._kimg.tiled:
            self._img.grad.fill(0)
        self._loss.grad[None] = 1.0
        run_chain_backward(
            self._kernel_chain(), self._kimg.blur_adjoints(), (self._k_mark, self._kimg.compact)
        )
        return self._th.grad.to_numpy().astype(np.float64).reshape(-1)

    # value and value_and_grad run once per evaluation of an optimizer: their Python is kept to a few
    # us (docs/performance.md). On the fused path a launch-ready kernel stands for the alive
    # check: it holds the Taichi program it was compiled in, and a reset or re-initialisation makes a new
    # one (then the full check below runs and raises).
    def value(self, theta) -> float:
        """Augmented objective J at ``theta`` (physical units).

        The value of :meth:`value_and_grad` to the last bit, except where the CPU's fused kernel stores
        the per-event terms of a warp that declares ``store_event_terms`` (rotation3;
        ``FusedPipeline.stores_event_terms``): there the two agree to a few ulps (the value-only launch
        compiles the warped positions without their Jacobians).
        """
        fused = self._fused
        if fused is None or not fused.launch_ready():
            self._check_alive()
        theta = _check_theta(theta, self.model.n_params, self.model.name, limit=self._theta_limit)
        if fused is not None:
            if self._identity_value is not None and not any(theta.tolist()):
                return self._identity_value  # computed with G0 by the window's set-up
            value = fused.value(theta)
        else:
            value = self._forward(theta)[0]
        if not math.isfinite(value):
            _require_finite(self.model, theta, "J", value)
        return value

    def value_and_grad(self, theta) -> tuple[float, np.ndarray]:
        """``(J, dJ/dtheta)`` at ``theta`` (physical units): the fused kernels' hand-written backward, or
        Taichi's reverse-mode autodiff on the generic chain."""
        fused = self._fused
        if fused is None or not fused.launch_ready():
            self._check_alive()
        theta = _check_theta(theta, self.model.n_params, self.model.name, limit=self._theta_limit)
        if fused is not None:
            value, grad = fused.value_and_grad(theta)
        else:
            value = self._forward(theta)[0]
            grad = self._backward()
        if not (math.isfinite(value) and _all_finite(grad.tolist())):
            _require_finite(self.model, theta, "J or dJ/dtheta", value, grad)
        return value, grad

    def evaluate(self, theta) -> Evaluation:
        """J, G, G_raw, G0 and the penalty of every registered regularizer at ``theta``."""
        self._check_alive()
        theta = _check_theta(theta, self.model.n_params, self.model.name)
        value, g_raw = self._forward(theta)
        penalties = self._all_penalties(theta)
        _require_finite(self.model, theta, "J", value, g_raw, list(penalties.values()))
        return Evaluation(J=value, G=g_raw / self.G0, G_raw=g_raw, G0=self._identity_objective, R=penalties)

    # --- images -----------------------------------------------------------------------------------
    def iwe(self, theta) -> np.ndarray:
        """The blurred IWE at ``theta``: (H, W), or (2, H, W) for per-polarity images."""
        self._check_alive()
        theta = _check_theta(theta, self.model.n_params, self.model.name)
        self._forward(theta)
        if self._fused is not None:
            img = self._fused.image()
        else:
            img = self._img.to_numpy().astype(np.float64)
        _require_finite(self.model, theta, "the IWE", img)
        return img[0] if self.n_channels == 1 else img

    def _map_fields(self, theta: np.ndarray):
        """Vote every registered regularizer's quantity; return the (count, out) images as NumPy."""
        self._ensure_generic()
        names = REGULARIZERS.names()
        regs = [REGULARIZERS.get(n) for n in names]
        W, H = self.width, self.height
        key = tuple(names)
        if key not in self._ws.maps:
            real = backend.real()
            with workspace.allocating(f"the maps of a {W}x{H} problem"):
                fields = (
                    ti.field(real, shape=(H, W)),
                    ti.field(real, shape=(len(regs), H, W)),
                    ti.field(real, shape=(2 * len(regs), H, W)),
                    ktiles.TileFields(W, H, [(0, 0)], lists=True),
                )
            tiles = fields[3]
            self._ws.maps[key] = fields + (ktiles.make_clear_kernel(tiles, 0, images=fields[:3]),)
        count, numer, out, tiles, clear = self._ws.maps[key]
        self._load()
        reg_key = tuple((r.name, id(r)) for r in regs)
        splat = self._splat_kernel(regs, do_iwe=False)
        images = _cached(
            ("map_images", reg_key, W, H),
            lambda: kmaps.make_maps_image_kernel(tuple(r.penalty for r in regs), W, H),
        )
        self._th[None] = theta.tolist()
        clear()  # the last call's maps, at its touched pixels
        splat(*self._args_splat(count, numer))
        self._mark_kernel(iwe=False, maps=True)(*self._args_mark(tiles))
        ktiles.ops_for(tiles).compact(tiles)
        images(count, numer, out, tiles)
        return names, count.to_numpy().astype(np.float64), out.to_numpy().astype(np.float64)

    def _penalties_of(self, names: list[str], count: np.ndarray, out: np.ndarray) -> dict[str, float]:
        """R of every named regularizer from its pixel penalties: the support-weighted mean
        (``m = C / (C + kappa)``), scaled (and hinged) as in J."""
        support = count / (count + kblocks.SUPPORT_KAPPA)
        total = support.sum()
        result = {}
        for r, name in enumerate(names):
            mean = float((support * out[2 * r + 1]).sum() / total) if total > 0 else 0.0
            result[name] = penalty_value(REGULARIZERS.get(name), mean, self.duration, self.orientation)
        return result

    def _all_penalties(self, theta: np.ndarray) -> dict[str, float]:
        return self._penalties_of(*self._map_fields(theta))

    def maps(self, theta) -> dict[str, np.ndarray | float]:
        """Regularizer maps at ``theta`` as (H, W) NumPy images.

        A map is the vote-weighted average of a per-event quantity, so it is undefined where no
        warped event landed (``count == 0``): every map and pixel penalty is **NaN** there (the
        "no event here" convention of the library; ``plt.imshow`` leaves NaN pixels blank, and
        ``np.nanmean`` / ``np.isnan`` select the defined pixels). 0 would be a value: for
        ``"deformation"`` it means total collapse (its neutral value is 1), for ``"divergence"``
        it is the neutral value.

        Returns
        -------
        dict
            ``"count"``: the vote count C(x) (>= 0 everywhere, 0 where no event landed); for each
            registered regularizer ``name``: its map (``"divergence"`` in 1/s, ``"deformation"``
            unitless), ``name + "_penalty"``: the pixel penalty (both NaN where ``count == 0``), and
            ``"R_" + name``: the scalar penalty (finite).

        Raises
        ------
        NonFiniteResultError
            (a ValueError) when the parameters overflow the float type where events landed.
        """
        self._check_alive()
        theta = _check_theta(theta, self.model.n_params, self.model.name)
        names, count, out = self._map_fields(theta)
        penalties = self._penalties_of(names, count, out)
        hit = count > 0
        _require_finite(self.model, theta, "a regularizer map", out[:, hit], list(penalties.values()))
        result: dict[str, np.ndarray | float] = {"count": count}
        for r, name in enumerate(names):
            result[name] = np.where(hit, out[2 * r], np.nan)
            result[name + "_penalty"] = np.where(hit, out[2 * r + 1], np.nan)
        for name, value in penalties.items():
            result["R_" + name] = value
        return result

    def dense_flow(self, theta, dt: float = 0.0) -> np.ndarray:
        """Flow implied by ``theta`` on the pixel grid, shape (2, H, W); see :func:`dense_flow`.

        ``dt = 0``: the instantaneous flow (px/s); else the displacement over ``dt`` seconds (px).
        """
        self._check_alive()
        theta = _check_theta(theta, self.model.n_params, self.model.name)
        return dense_flow(
            self.model,
            theta,
            self.events.sensor_size,
            camera=self.camera,
            duration=self.duration,
            dt=dt,
        )

    def timed_value_and_grad(self, theta, repeats: int = 10) -> float:
        """Median seconds of one ``value_and_grad`` over ``repeats`` runs (after one warm-up)."""
        self.value_and_grad(theta)
        times = []
        for _ in range(max(1, int(repeats))):
            t0 = time.perf_counter()
            self.value_and_grad(theta)
            times.append(time.perf_counter() - t0)
        return float(np.median(times))

    def __repr__(self) -> str:
        regs = ", ".join(f"{k}={v:g}" for k, v in self.regularizer_weights.items()) or "none"
        return (
            f"ContrastMaximization(warp={self.model.name}, objective={self.objective.name}, "
            f"regularizers={regs}, events={self.n_events}, sensor={self.width}x{self.height}, "
            f"T={self.duration * 1e3:.3f} ms)"
        )
