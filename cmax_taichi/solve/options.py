"""The checks of :func:`cmax_taichi.maximize`'s options: one clear error naming the option, its unit and
the rule it breaks."""

from __future__ import annotations

import math
import numbers

import numpy as np

from cmax_taichi.models.warps import WarpModel
from cmax_taichi.pipeline.parameters import check_theta

__all__ = [
    "SEARCHABLE_U",
    "check_bounds",
    "check_searchable",
    "non_negative_number",
    "parameter_vector",
    "positive_number",
    "real_number",
]


def real_number(name: str, value, unit: str) -> float:
    """``value`` as a finite float (TypeError for a non-number or a bool, ValueError for inf / NaN)."""
    if not isinstance(value, numbers.Real) or isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a number ({unit}), got {value!r} ({type(value).__name__})")
    try:
        number = float(value)
    except OverflowError:
        raise ValueError(f"{name} must be a finite number ({unit}), got an int beyond float64") from None
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number ({unit}), got {number}")
    return number


def positive_number(name: str, value, unit: str) -> float:
    """``value`` as a finite float > 0."""
    number = real_number(name, value, unit)
    if not number > 0:
        raise ValueError(f"{name} must be a positive number ({unit}), got {number}")
    return number


def non_negative_number(name: str, value, unit: str) -> float:
    """``value`` as a finite float >= 0."""
    number = real_number(name, value, unit)
    if not number >= 0:
        raise ValueError(f"{name} must be a finite number >= 0 ({unit}), got {number}")
    return number


def parameter_vector(name: str, value, model: WarpModel) -> np.ndarray:
    """A parameter vector of ``model`` given by the user (``theta0``, a candidate, a bound), checked as
    the problem checks theta, with ``name`` in the message."""
    return check_theta(value, model.n_params, model.name, label=name)


#: the largest |u| (px over the window) the searches step through: they take differences and
#: midpoints of the box and round points to 1e-9 px to skip repeats (u * 1e9 overflows float64 from
#: 1.8e299)
SEARCHABLE_U = 1e290


def check_searchable(name: str, thetas: np.ndarray, scales: np.ndarray, model: WarpModel) -> None:
    """Refuse parameter values whose internal units (``theta * scale``, px) the searches cannot step
    through (differences of the box overflow float64), naming the parameter and the limit."""
    with np.errstate(over="ignore", invalid="ignore"):
        u = np.abs(thetas * scales)
    bad = np.argwhere(~(u <= SEARCHABLE_U))
    if bad.size:
        i = int(bad[0][1])
        limit = SEARCHABLE_U / scales[i]
        raise ValueError(
            f"{name}: {model.params[i]} = {thetas[tuple(bad[0])]:.6g} {model.units[i]} is beyond what the "
            f"search can step through for this problem: |{model.params[i]}| <= {limit:.3g} {model.units[i]}"
        )


def check_bounds(bounds, model: WarpModel) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` of a user-given search box: finite parameter vectors with ``lo < hi``."""
    P = model.n_params
    if isinstance(bounds, (str, bytes)) or not hasattr(bounds, "__len__") or len(bounds) != 2:
        raise TypeError(
            f"bounds must be a pair (lo, hi) of {P} numbers each for warp {model.name!r}, got {bounds!r}"
        )
    lo = parameter_vector("bounds lo", bounds[0], model)
    hi = parameter_vector("bounds hi", bounds[1], model)
    inverted = np.flatnonzero(~(lo < hi))
    if inverted.size:
        i = int(inverted[0])
        raise ValueError(
            f"bounds: lo[{i}] = {lo[i]:.6g} is not below hi[{i}] = {hi[i]:.6g} "
            f"(parameter {model.params[i]!r} of warp {model.name!r}); bounds are (lo, hi) with lo < hi"
        )
    return lo, hi
