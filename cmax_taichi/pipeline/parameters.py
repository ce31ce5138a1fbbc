"""Parameter vectors of a warp: the checks every evaluation runs on ``theta``, and the error for
results that overflow the backend's float type.

``check_theta`` runs on every evaluation, so its common case (finite values that the float type can
hold) is plain Python; the slow paths only build the messages.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.models.warps import WarpModel

__all__ = ["NonFiniteResultError", "all_finite", "check_theta", "float_limit", "require_finite"]


class NonFiniteResultError(ValueError):
    """A result (J, its gradient, a map, a flow) would not be finite: the parameters overflow the
    backend's float type. The message names theta and the float type; the optimizers read it as a
    point outside the usable range."""


def _describe_number(value) -> str:
    """A short text for a number, also for Python ints too large to format as a float."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 10**300:
        return f"{'-' if value < 0 else ''}1e{len(str(abs(value))) - 1} (approximately)"
    try:
        return f"{float(value):.6g}"
    except (OverflowError, TypeError, ValueError):
        return repr(value)


#: the largest finite value of each backend float type
_LARGEST = {"f32": float(np.finfo(np.float32).max), "f64": float(np.finfo(np.float64).max)}


def _format_vector(values: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in np.asarray(values, dtype=np.float64).reshape(-1)) + "]"


def float_limit() -> float:
    """The largest finite value of the backend's float type (a problem keeps it: it holds until the
    backend is re-initialised, which the problem detects)."""
    return _LARGEST[backend.info().precision]


def check_theta(theta, n: int, name: str, label: str = "theta", limit: float | None = None) -> np.ndarray:
    """``theta`` as ``n`` finite float64 values that the backend's float type can hold.

    Raises TypeError for what is not a sequence of real numbers (None, a string, a complex number, a
    bool) and ValueError for the wrong length, a non-finite value, or a value beyond the largest float
    of the backend (a Python int such as ``10**400``, or above 3.4e38 with ``precision="f32"``).
    ``label`` names the argument in the messages (``theta0``, ``bounds lo``, ...); ``limit`` is
    :func:`float_limit` where the caller holds it (the evaluations: no backend look-up per call)."""
    if (
        limit is not None
        and type(theta) is np.ndarray
        and theta.dtype == np.float64
        and theta.shape == (n,)
        and all(map(limit.__ge__, map(abs, theta.tolist())))  # NaN fails
    ):
        return theta  # the optimizers' case, in plain Python (a few us per evaluation)
    what = f"{label} of warp {name!r} ({n} parameter(s))"
    if theta is None or isinstance(theta, (str, bytes, Mapping)):
        raise TypeError(f"{what} must be a sequence of {n} real numbers, got {theta!r}")
    if isinstance(theta, np.ndarray) and theta.dtype.kind in "fiu":
        arr = np.asarray(theta, dtype=np.float64).reshape(-1)
    else:
        try:
            items = np.asarray(theta, dtype=object).reshape(-1)
        except (TypeError, ValueError):
            raise TypeError(f"{what} must be a sequence of {n} real numbers, got {theta!r}") from None
        arr = np.empty(items.size)
        for i, v in enumerate(items):
            if not isinstance(v, numbers.Real) or isinstance(v, (bool, np.bool_)):
                raise TypeError(f"{what}: {label}[{i}] = {v!r} ({type(v).__name__}) is not a real number")
            try:
                arr[i] = float(v)
            except OverflowError:
                raise ValueError(
                    f"{what}: {label}[{i}] = {_describe_number(v)} is beyond the largest float64 "
                    f"({np.finfo(np.float64).max:.3g})"
                ) from None
    if arr.size != n:
        raise ValueError(f"warp {name!r} takes {n} parameter(s), got {label} of length {arr.size}")
    if limit is None:
        limit = _LARGEST[backend.info().precision]
    if all(-limit <= v <= limit for v in arr.tolist()):  # the common case, in plain Python (NaN fails)
        return arr
    finite = np.isfinite(arr)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise ValueError(
            f"{what} has a non-finite value: {label}[{i}] = {arr[i]} ({label} = {_format_vector(arr)})"
        )
    big = np.flatnonzero(np.abs(arr) > limit)
    if big.size:
        raise ValueError(
            f"{what}: {label}[{big[0]}] = {arr[big[0]]:.6g} is beyond the largest "
            f"{backend.info().precision} value ({limit:.3g}) of this backend; use cm.init(precision='f64')"
        )
    return arr


def _all_finite(value) -> bool:
    if isinstance(value, float):
        return math.isfinite(value)
    value = np.asarray(value, dtype=np.float64)
    if value.size <= 64:  # a gradient, a few penalties: plain Python is faster than NumPy here
        return all(map(math.isfinite, value.reshape(-1).tolist()))
    return bool(np.isfinite(value).all())


def all_finite(values: list) -> bool:
    """Whether every number of a list is finite (the hot path of the evaluations: plain Python)."""
    return all(map(math.isfinite, values))


def require_finite(model: WarpModel, theta: np.ndarray, what: str, *values) -> None:
    """Raise :class:`NonFiniteResultError` naming theta when a result is not finite (an overflow)."""
    if all(_all_finite(v) for v in values):
        return
    precision = backend.info().precision
    hint = " (or use cm.init(precision='f64'))" if precision == "f32" else ""
    raise NonFiniteResultError(
        f"{what} is not finite at theta = {_format_vector(theta)} of warp {model.name!r}: the parameters "
        f"overflow {precision} arithmetic (values beyond {np.finfo(backend.numpy_real()).max:.3g}); "
        f"use smaller parameters{hint}"
    )
