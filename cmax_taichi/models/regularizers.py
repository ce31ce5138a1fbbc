"""Event-collapse regularizers (Shiba et al. 2022) and their registry.

A :class:`Regularizer` says which per-event quantity is voted into its map (a kind the warp model
provides, "div" or "absdet", or a user function of the model), how a pixel's map value becomes a
penalty (and, for the fused pipeline, the penalty's derivative), and how the penalty is scaled.
Built-ins: ``divergence`` (R_Div) and ``deformation`` (R_Def), registered explicitly by
:func:`register_builtin_regularizers`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

from cmax_taichi.core.registry import Registry
from cmax_taichi.kernels import maps as km
from cmax_taichi.models.warps import QUANTITY_KINDS, WarpModel

__all__ = [
    "RECOMMENDED_LAMBDA",
    "Regularizer",
    "REGULARIZERS",
    "register_regularizer",
    "unregister_regularizer",
    "regularizer_names",
    "penalty_value",
]

#: The weight lambda of each regularizer that the project's experiments use (the paper's weights are
#: not known). Selected by ``python -m cmax_taichi.lab.experiments_real``: the smallest weight of its grid
#: (1, 2, 5, 10, 20) at which none of the 12 regularized configurations (zoom1 and mitrokhin4; variance
#: and gradient magnitude; divergence, deformation, both) collapses on the real MVSEC cut (re-derived
#: with the cut's corrected, rectified camera on 2026-12-01: still 10); then used
#: unchanged on the ECD rotation cuts and the simulated tables (``cmax-taichi reproduce``). The
#: objective is normalised by the identity warp's, so it is comparable across windows; it is not a
#: universal constant: README.md, "Results on real recordings", shows how the outcome depends on it
#: (at this weight the penalties also move well-posed rotation estimates and over-regularize a strong
#: true approach). Motion segmentation (``segment_eval``) keeps its own ``--lam`` (default 1).
RECOMMENDED_LAMBDA = 10.0


@dataclass(frozen=True)
class Regularizer:
    """A penalty computed from a map of per-event quantities.

    Parameters
    ----------
    name : str
        Registry name (the key in ``regularizers={...}``).
    quantity : {"div", "absdet"} or callable
        The per-event value voted into the map: a kind every warp model provides (``div v`` in 1/s, or
        ``|det dx'/dx|``; see :meth:`WarpModel.quantity`), or
        ``quantity(model: WarpModel) -> ti.func(p, dt, th, ctx) -> scalar`` for anything else (such a
        regularizer runs on the generic autodiff chain: the fused backward knows the two kinds only).
    penalty : ti.func
        ``penalty(map_value) -> scalar``, the pixel penalty.
    scale : callable
        ``scale(duration_s, orientation) -> float`` multiplying R (orientation is +1 when t_ref is
        before the mean event time, else -1).
    one_sided : bool
        ``R = max(0, scale * mean)``: penalise only one direction (the divergence penalises net
        contraction and must not reward expansion).
    map_unit : str
        Unit of the map (for plots).
    neutral : float
        Map value of an area-preserving warp (0 for divergence, 1 for deformation).
    description : str
        One line for listings.
    penalty_grad : ti.func, optional
        ``d penalty / d map_value`` as a Taichi function, for the fused pipeline's hand-written backward
        (at a kink, the side Taichi's autodiff of ``penalty`` takes). Without it (or with a callable
        ``quantity``) problems using this regularizer run on the generic autodiff chain.
    rounded_penalty : callable, optional
        ``rounded_penalty(width) -> (penalty, penalty_grad)``: the pixel penalty with its kinks rounded
        over a band of ``width`` (for gradient-based optimizers, :meth:`with_rounded_kinks`); None when
        the pixel penalty has no kink.
    kink_width : float
        The width of the rounded kinks (0: the exact penalty); set by :meth:`with_rounded_kinks`.
    """

    name: str
    quantity: str | Callable[[WarpModel], Callable]
    penalty: Callable
    scale: Callable[[float, float], float]
    one_sided: bool = False
    map_unit: str = ""
    neutral: float = 0.0
    description: str = ""
    penalty_grad: Callable | None = None
    rounded_penalty: Callable[[float], tuple[Callable, Callable]] | None = None
    kink_width: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.quantity, str):
            if self.quantity not in QUANTITY_KINDS:
                raise ValueError(
                    f"regularizer {self.name!r}: quantity {self.quantity!r} is not one of {QUANTITY_KINDS} "
                    "(or pass a function of the warp model)"
                )
        elif not callable(self.quantity):
            raise TypeError(f"regularizer {self.name!r}: quantity must be a kind name or a callable")

    @property
    def kind(self) -> str | None:
        """The declared quantity kind ("div" or "absdet"), or None for a user quantity function."""
        return self.quantity if isinstance(self.quantity, str) else None

    @property
    def hinge(self) -> bool | float:
        """The hinge flag the kernels take (``blocks.scaled_penalty``): False (none), True (the exact
        ``max(0, R)``) or the width of its rounded kink."""
        if not self.one_sided:
            return False
        return self.kink_width if self.kink_width > 0 else True

    def with_rounded_kinks(self, width: float) -> Regularizer:
        """This regularizer with the kinks of its penalty rounded over a band of ``width``
        (dimensionless, > 0; 0 returns it unchanged): the hinge of a one-sided one
        (``blocks.scaled_penalty``) and the pixel penalty's own (:attr:`rounded_penalty`). The rounded
        penalty equals the exact one outside the band and exceeds it by at most ``width / 4`` inside
        (docs/FORMULAS.md, "Rounded kinks"). One instance per ``(regularizer, width)``: compiled
        kernels are keyed by it."""
        return _rounded(self, float(width))

    def quantity_fn(self, model: WarpModel) -> Callable:
        """The per-event Taichi function ``q(p, dt, th, ctx)`` of this regularizer for ``model``."""
        if isinstance(self.quantity, str):
            return model.quantity(self.quantity)
        return self.quantity(model)


REGULARIZERS: Registry[Regularizer] = Registry("regularizer")


@functools.cache
def _rounded(reg: Regularizer, width: float) -> Regularizer:
    if not (math.isfinite(width) and width >= 0.0):
        raise ValueError(f"the width of the rounded kinks must be finite and >= 0, got {width!r}")
    if reg.kink_width == width:
        return reg
    if reg.kink_width > 0.0:
        raise ValueError(f"regularizer {reg.name!r} has its kinks rounded already: round the exact one")
    if width == 0.0:
        return reg
    changes: dict = {"kink_width": width}
    if reg.rounded_penalty is not None:
        changes["penalty"], changes["penalty_grad"] = reg.rounded_penalty(width)
    return dataclasses.replace(reg, **changes)


def penalty_value(reg: Regularizer, support_mean: float, duration: float, orientation: float) -> float:
    """R of ``reg`` from the support-weighted mean of its pixel penalty (the loss kernel's formula)."""
    value = reg.scale(duration, orientation) * support_mean
    return max(0.0, value) if reg.one_sided else value


def register_regularizer(reg: Regularizer, *, replace: bool = False) -> Regularizer:
    """Add a regularizer to the registry."""
    if not isinstance(reg, Regularizer):
        raise TypeError(f"expected a Regularizer, got {type(reg).__name__}")
    return REGULARIZERS.register(reg.name, reg, replace=replace)


def unregister_regularizer(name: str) -> Regularizer:
    """Remove the regularizer called ``name`` and return it (KeyError if absent)."""
    return REGULARIZERS.unregister(name)


def regularizer_names() -> list[str]:
    """Names of the registered regularizers."""
    return REGULARIZERS.names()


def register_builtin_regularizers(registry: Registry[Regularizer]) -> None:
    registry.register(
        "divergence",
        Regularizer(
            "divergence",
            "div",
            km.divergence_penalty,
            scale=lambda duration, orientation: orientation * duration,
            one_sided=True,
            map_unit="1/s",
            neutral=0.0,
            description="net flow divergence per window when events contract, else 0 (R_Div)",
            penalty_grad=km.divergence_penalty_grad,
        ),
        builtin=True,
    )
    registry.register(
        "deformation",
        Regularizer(
            "deformation",
            "absdet",
            km.deformation_penalty,
            scale=lambda duration, orientation: 1.0,
            one_sided=False,
            map_unit="",
            neutral=1.0,
            description="mean of max(DEF, 1/DEF) - 1 of the area deformation map (R_Def)",
            penalty_grad=km.deformation_penalty_grad,
            rounded_penalty=km.rounded_deformation_penalty,
        ),
        builtin=True,
    )


register_builtin_regularizers(REGULARIZERS)
