"""Objectives (focus measures, maximised) and their registry.

An :class:`Objective` pairs a reduce-kernel factory and a finalize function of
``kernels/objectives.py``. Built-ins are registered explicitly by :func:`register_builtin_objectives`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from cmax_taichi.core.registry import Registry
from cmax_taichi.kernels import objectives as ko

__all__ = ["Objective", "OBJECTIVES", "register_objective", "objective_names"]


@dataclass(frozen=True)
class Objective:
    """A focus measure G of the IWE.

    Parameters
    ----------
    name : str
        Registry name.
    slots_per_channel : int
        Accumulator slots each IWE channel uses.
    make_reduce : callable
        ``make_reduce(width, height, n_channels) -> kernel(img, acc)`` adding per-pixel terms.
    finalize : ti.func
        ``finalize(acc_vector, channel, n_pixels) -> G_channel``.
    description : str
        One line for listings.
    """

    name: str
    slots_per_channel: int
    make_reduce: Callable
    finalize: Callable
    description: str = ""


OBJECTIVES: Registry[Objective] = Registry("objective")


def register_objective(objective: Objective, *, replace: bool = False) -> Objective:
    """Add an objective to the registry."""
    if not isinstance(objective, Objective):
        raise TypeError(f"expected an Objective, got {type(objective).__name__}")
    return OBJECTIVES.register(objective.name, objective, replace=replace)


def objective_names() -> list[str]:
    """Names of the registered objectives."""
    return OBJECTIVES.names()


def register_builtin_objectives(registry: Registry[Objective]) -> None:
    registry.register(
        "variance",
        Objective(
            "variance",
            ko.VARIANCE_SLOTS,
            ko.make_variance_reduce,
            ko.variance_finalize,
            "image variance (Gallego et al. CVPR 2018)",
        ),
    )
    registry.register(
        "gradient_magnitude",
        Objective(
            "gradient_magnitude",
            ko.GRADIENT_MAGNITUDE_SLOTS,
            ko.make_gradient_magnitude_reduce,
            ko.gradient_magnitude_finalize,
            "mean squared Sobel/8 gradient (Gallego et al. CVPR 2019)",
        ),
    )
    registry.register(
        "mean_square",
        Objective(
            "mean_square",
            ko.MEAN_SQUARE_SLOTS,
            ko.make_mean_square_reduce,
            ko.mean_square_finalize,
            "mean of the squared IWE (Gallego et al. CVPR 2019)",
        ),
    )


register_builtin_objectives(OBJECTIVES)
