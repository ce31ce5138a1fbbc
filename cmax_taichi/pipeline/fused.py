"""Driver of the fused pipeline (``kernels/fused.py``) for :class:`~cmax_taichi.ContrastMaximization`.

The fused pipeline computes the same J and dJ/dtheta as the generic kernel chain of ``problem.py`` in
one kernel launch per value-and-gradient, with no atomics on the CPU, no per-call fills and no
per-call allocation. It serves the objectives that declare a fused path (``Objective.fused``), the
built-in regularizers and warp models (their
closed-form parameter Jacobians are in ``kernels/param_jac.py``), all polarity modes, weights and
blur widths; the generic chain serves the rest (whitening, user warps, objectives or penalties).

The image fields are pooled per shape (``workspace.py``): problems of the same sensor, channel count,
regularizer count, parameter count and blur footprint share them and the compiled kernels; the events
of each problem live in its own ndarray, whose length is not compiled in (a window of another size
reuses the kernels).
"""

from __future__ import annotations

import numpy as np
import taichi as ti

from cmax_taichi.core import backend, workspace
from cmax_taichi.kernels import fused as kfused
from cmax_taichi.kernels import maps as kmaps
from cmax_taichi.kernels import param_jac as kpj
from cmax_taichi.models.regularizers import REGULARIZERS, _deformation_quantity, _divergence_quantity

__all__ = ["FusedPipeline"]

MAX_PARAMS = kfused.MAX_PARAMS

#: per-event quantities of the built-in regularizers, as the hand-written backward names them
_QUANTITY_KINDS = {_divergence_quantity: "div", _deformation_quantity: "absdet"}


def n_slices() -> int:
    """Accumulation slices of the splat: one per CPU thread; 1 (atomics) on a GPU."""
    if backend.info().arch != "cpu":
        return 1
    return max(1, int(ti.lang.impl.current_cfg().cpu_max_num_threads))


class FusedPipeline:
    """J and dJ/dtheta of one problem by the fused kernels.

    Build it with :meth:`for_problem`, which returns None where the fused kernels do not apply.
    """

    #: switches for tests and the benchmark: ``enabled = False`` builds every problem on the generic
    #: kernel chain; ``force_atomic`` runs the atomic (GPU-style) splat on the CPU
    enabled = True
    force_atomic = False

    @classmethod
    def for_problem(cls, problem, vote_w: np.ndarray | None) -> FusedPipeline | None:
        """The fused pipeline of ``problem`` (a ContrastMaximization being built), or None."""
        if not cls.enabled or problem.whitening or problem.model.n_params > MAX_PARAMS:
            return None
        objective = problem.objective.fused  # the objective's declaration (models/objectives.py)
        if objective is None:
            return None
        regs = [REGULARIZERS.get(name) for name in problem.regularizer_weights]
        if any(r.penalty not in kmaps.PENALTY_GRADS for r in regs):
            return None
        model = problem.model
        if (model.warp, model.det, model.div) not in kpj.PARAM_JACOBIANS:
            return None  # a user warp: no closed-form parameter Jacobian
        if any(r.quantity not in _QUANTITY_KINDS for r in regs):
            return None
        return cls(problem, objective, regs, vote_w)

    def __init__(self, problem, objective, regs: list, vote_w: np.ndarray | None) -> None:
        self.problem = problem
        model = problem.model
        C, W, H, P = problem.n_channels, problem.width, problem.height, model.n_params
        weighted = vote_w is not None
        split = problem.polarity == "split"
        radius = problem.setup.radius
        slots = problem.objective.slots_per_channel
        atomic = backend.info().arch != "cpu" or self.force_atomic
        slices = 1 if atomic else n_slices()
        shared = bool(regs) and not weighted and not split
        real = backend.real()
        self.n_params = P
        self.n_events = problem.n_events
        # closed-form parameter Jacobians (for_problem checked that the model and quantities have them)
        param_jac = kpj.PARAM_JACOBIANS[(model.warp, model.det, model.div)]
        kinds = tuple(_QUANTITY_KINDS[r.quantity] for r in regs)
        const_kinds = kpj.CONSTANT_QUANTITIES.get((model.warp, model.det, model.div), ())
        constant = tuple(k in const_kinds for k in kinds)
        n_voted = len(regs) - sum(constant)

        key = (
            "fused",
            problem._backend.generation,
            W,
            H,
            C,
            len(regs),
            n_voted,
            P,
            radius,
            slots,
            objective.sobel,
            slices,
            shared,
        )

        def build(ws):
            ws.fields = kfused.FusedFields(
                real,
                width=W,
                height=H,
                n_channels=C,
                n_regs=len(regs),
                n_voted=n_voted,
                n_params=P,
                radius=radius,
                n_slices=slices,
                shared_count=shared,
                objective_slots=slots,
                sobel=objective.sobel,
            )
            ws.kernels = {}

        self._ws = workspace.acquire(key, build)
        self.fields = self._ws.fields
        penalties = tuple(r.penalty for r in regs)
        kkey = (
            model.name,
            id(model),
            tuple((r.name, id(r)) for r in regs),
            problem.objective.name,
            id(objective),
            weighted,
            split,
            atomic,
            constant,
        )
        if kkey not in self._ws.kernels:
            self._ws.kernels[kkey] = kfused.make_fused_kernels(
                self.fields,
                model.warp,
                tuple(r.quantity(model) for r in regs),
                penalties,
                tuple(kmaps.PENALTY_GRADS[pf] for pf in penalties),
                tuple(bool(getattr(r, "one_sided", False)) for r in regs),
                pixel_fn=objective.pixel,
                finalize_fn=objective.finalize,
                adjoint_fn=objective.adjoint,
                objective_slots=slots,
                sobel=objective.sobel,
                width=W,
                height=H,
                n_channels=C,
                n_params=P,
                radius=radius,
                n_slices=slices,
                atomic_scatter=atomic,
                weighted=weighted,
                split_polarity=split,
                shared_count=shared,
                real=real,
                param_jac=param_jac,
                quantity_kinds=kinds,
                constant=constant,
            )
        self._run_k = self._ws.kernels[kkey]

        # constants, uploaded whenever another problem used the shared fields in between
        setup = problem.setup  # pipeline/setup.py: the same constants as the generic chain's
        self._ctx = setup.ctx
        self._taps = None if setup.taps is None else setup.taps.astype(backend.numpy_real())
        self._lam = setup.lam
        self._g0 = 1.0

        # the events as one ndarray of (x, y, dt[, w][, channel]) vectors
        ev = problem.events
        cols = [ev.x, ev.y, ev.t - problem.t_ref]
        if weighted:
            cols.append(vote_w)
        if split:
            cols.append((ev.p < 0).astype(np.float64))
        packed = np.stack(cols, axis=1).astype(backend.numpy_real())
        self.events = ti.ndarray(ti.types.vector(len(cols), real), shape=self.n_events)
        self.events.from_numpy(packed)
        self.event_bytes = packed.nbytes
        del packed
        self._theta = np.zeros(MAX_PARAMS)
        self._out = np.zeros(2 + P)  # J, G_raw, dJ/dtheta

    # --- state -----------------------------------------------------------------------------------
    def set_g0(self, g0: float) -> None:
        """Divide G by ``g0`` in J from now on."""
        self._g0 = float(g0)
        self._ws._owner = None  # upload again at the next call

    def _load(self) -> None:
        ws = self._ws
        if ws.owned_by(self):
            return
        f = self.fields
        f.ctx[None] = self._ctx
        if self._taps is not None:
            f.taps.from_numpy(self._taps)
        if self._lam:
            f.lam[None] = self._lam
        f.g0[None] = self._g0
        ws.take(self)

    def _run(self, theta: np.ndarray, grad: int) -> np.ndarray:
        self._load()
        args = self._theta
        args[: theta.size] = theta
        self._run_k(self.n_events, self.events, *args.tolist(), grad, self._out)
        return self._out

    # --- evaluation ------------------------------------------------------------------------------
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
        return float(out[0]), out[2:].copy()

    def image(self) -> np.ndarray:
        """The blurred IWE of the last evaluation, (C, H, W) float64."""
        return np.moveaxis(self.fields.img.to_numpy().astype(np.float64), -1, 0)

    def nbytes(self) -> int:
        """Bytes of the shared fields plus this problem's event array."""
        return self.fields.nbytes() + self.event_bytes
