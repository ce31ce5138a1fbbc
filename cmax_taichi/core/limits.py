"""What one problem may allocate and compile: the limits, in one place, and the checks that read them.

Every problem, segmentation and dense flow estimates the bytes of its Taichi fields from its shape
(sensor, channels, clusters, regularizers, event capacity) *before* allocating them and refuses what
exceeds a limit with one clear error that names the parameter, the estimate and the limit:

* ``max_sensor_pixels``: ``W * H`` of the sensor (ValueError above it);
* ``max_bytes``: the estimated bytes of the fields of one problem (MemoryError above it);
* ``max_blur_sigma``: the blur footprint ``2 ceil(3 sigma) + 1`` is unrolled into the kernels at
  compile time, so compile time and compiler memory grow with sigma (ValueError above it);
* ``max_clusters``: the K-cluster kernels unroll the clusters and hold several vector fields of K
  components; compile time grows with K, and K = 100 exceeded Taichi's limit on fields per tree
  (ValueError above it).

The defaults come from the environment variables of :data:`ENV_VARS` where set, else from
:data:`DEFAULTS`; :func:`set_limits` changes them for the process.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass

from cmax_taichi.core import checks

__all__ = [
    "DEFAULTS",
    "ENV_VARS",
    "Limits",
    "check_blur_sigma",
    "check_bytes",
    "check_clusters",
    "check_dense_flow",
    "check_sensor",
    "clusters_bytes",
    "dense_flow_bytes",
    "get_limits",
    "problem_bytes",
    "set_limits",
]


def _half_the_memory() -> int:
    """Half the machine's physical memory in bytes (8 GiB where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")) // 2
    except (AttributeError, ValueError, OSError):
        return 8 * 2**30


@dataclass(frozen=True)
class Limits:
    """Limits on one problem, segmentation or dense flow (see the module docstring).

    Attributes
    ----------
    max_sensor_pixels : int
        Largest ``W * H`` (px); default 4096 x 4096, about 18 times the largest event sensors
        (1280 x 720 / 1280 x 960).
    max_bytes : int
        Largest estimated size of the Taichi fields of one problem (bytes); default half the physical
        memory of the machine. On a GPU the device memory may be smaller: an allocation that still
        fails is reported as a MemoryError and leaves the Python process usable.
    max_blur_sigma : float
        Largest ``blur_sigma`` (px); default 3. The fused kernel unrolls the footprint at compile time:
        sigma = 1, 3, 5, 8 px took 4.8, 8.3, 21.9, 40.7 s to compile cold on a 2-core machine at load 4
        (``benchmarks/compile_cost.py``; docs/estimation.md, limits).
    max_clusters : int
        Largest number of clusters K of a segmentation or :class:`MultiClusterCMax`; default 8 (the
        size of the candidate batches that ``segment`` compiles anyway). Compile time grows with K
        (docs/estimation.md, limits); K = 100 exceeded Taichi's limit on fields per tree.
    """

    max_sensor_pixels: int = 4096 * 4096
    max_bytes: int = dataclasses.field(default_factory=_half_the_memory)
    max_blur_sigma: float = 3.0
    max_clusters: int = 8

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"limit {f.name} must be a number, got {value!r}")
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"limit {f.name} must be a finite number > 0, got {value!r}")
            if f.type == "int":
                if value != int(value):
                    raise ValueError(f"limit {f.name} must be a whole number, got {value!r}")
                object.__setattr__(self, f.name, int(value))


#: the environment variable that sets each limit's default
ENV_VARS = {
    "max_sensor_pixels": "CMAX_TAICHI_MAX_SENSOR_PIXELS",
    "max_bytes": "CMAX_TAICHI_MAX_BYTES",
    "max_blur_sigma": "CMAX_TAICHI_MAX_BLUR_SIGMA",
    "max_clusters": "CMAX_TAICHI_MAX_CLUSTERS",
}

#: the built-in defaults (without environment variables)
DEFAULTS = Limits()


def _from_environment() -> Limits:
    changes = {}
    for name, var in ENV_VARS.items():
        text = os.environ.get(var, "").strip()
        if not text:
            continue
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"environment variable {var} must be a number, got {text!r}") from None
        whole = math.isfinite(value) and value == math.floor(value)
        changes[name] = int(value) if name != "max_blur_sigma" and whole else value
    try:
        return dataclasses.replace(DEFAULTS, **changes)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"bad limit in the environment ({', '.join(ENV_VARS.values())}): {exc}") from None


_current: Limits | None = None


def get_limits() -> Limits:
    """The limits in force (the environment's or the defaults until :func:`set_limits`)."""
    global _current
    if _current is None:
        _current = _from_environment()
    return _current


def set_limits(limits: Limits | None = None, **changes) -> Limits:
    """Change the limits for this process; return the previous ones (pass them back to restore).

    Parameters
    ----------
    limits : Limits, optional
        Limits to install as a whole (e.g. those an earlier call returned).
    **changes
        Single limits to change, by name: ``max_sensor_pixels``, ``max_bytes``, ``max_blur_sigma``,
        ``max_clusters``.

    Examples
    --------
    >>> previous = cm.set_limits(max_blur_sigma=8.0)  # doctest: +SKIP
    >>> cm.set_limits(previous)  # doctest: +SKIP
    """
    global _current
    previous = get_limits()
    if limits is not None and not isinstance(limits, Limits):
        raise TypeError(f"limits must be cmax_taichi.Limits, got {type(limits).__name__}")
    unknown = sorted(set(changes) - set(ENV_VARS))
    if unknown:
        raise TypeError(f"unknown limit(s) {', '.join(unknown)}; valid: {', '.join(ENV_VARS)}")
    _current = dataclasses.replace(limits if limits is not None else previous, **changes)
    return previous


def _gib(n_bytes: float) -> str:
    return f"{n_bytes / 2**30:.3g} GiB"


# --- estimates (bytes of the Taichi fields; upper bounds of what the pipelines allocate) ------------------
def _capacity(n_events: int) -> int:
    from cmax_taichi.core.workspace import capacity_for

    return capacity_for(n_events)


def problem_bytes(
    width: int, height: int, n_channels: int, n_regularizers: int, n_events: int, itemsize: int, n_slices: int
) -> int:
    """Bytes of the fields of one :class:`~cmax_taichi.ContrastMaximization`, both pipelines.

    Per pixel, the fused pipeline holds ``n_slices + 1`` accumulators of ``C + 1 + R`` channels and five
    images of C channels; the generic chain (built for ``maps()`` and where the fused kernels do not
    apply) three images with their gradients, the map count and numerators with gradients and the maps'
    images of every registered regularizer (counted as R + 2). Per event: five values (x, y, dt, weight,
    channel) of the capacity bucket.
    """
    C, R, pixels = n_channels, n_regularizers, width * height
    fused = (n_slices + 1) * (C + 1 + R) + 5 * C
    chain = 6 * C + 2 * (1 + R) + 3 * (R + 2) + 1
    return itemsize * (pixels * (fused + chain) + 5 * _capacity(n_events))


def clusters_bytes(
    width: int, height: int, n_clusters: int, n_regularizers: int, n_events: int, itemsize: int
) -> int:
    """Bytes of the fields of one K-cluster problem: per pixel three images of K channels with their
    gradients and K * R map numerators with gradients; per event three values and four of each
    cluster (membership, lookup, warped position)."""
    K, R = n_clusters, n_regularizers
    per_pixel = 6 * K + 2 * K * R
    return itemsize * (width * height * per_pixel + _capacity(n_events) * (3 + 4 * K))


def dense_flow_bytes(width: int, height: int, itemsize: int) -> int:
    """Bytes of a dense flow: the kernel's (3, H, W) NumPy output and its float64 copy (no Taichi field)."""
    return 3 * width * height * (itemsize + 8)


# --- checks -------------------------------------------------------------------------------------------
def check_sensor(width: int, height: int, what: str = "the problem") -> None:
    """ValueError when ``W * H`` exceeds ``max_sensor_pixels``."""
    limit = get_limits().max_sensor_pixels
    if width * height > limit:
        raise ValueError(
            f"sensor_size ({width}, {height}) = {width * height:,} pixels is above the limit "
            f"max_sensor_pixels = {limit:,} of {what}; raise it with "
            f"cmax_taichi.set_limits(max_sensor_pixels=...) or {ENV_VARS['max_sensor_pixels']}"
        )


def check_bytes(estimate: int, what: str, parameters: str) -> None:
    """MemoryError when ``estimate`` (bytes) exceeds ``max_bytes``; ``parameters`` names what sets it."""
    limit = get_limits().max_bytes
    if estimate > limit:
        raise MemoryError(
            f"{what} needs about {_gib(estimate)} of memory ({parameters}), above the limit "
            f"max_bytes = {_gib(limit)}; use a smaller sensor or fewer events/clusters, or raise the "
            f"limit with cmax_taichi.set_limits(max_bytes=...) or {ENV_VARS['max_bytes']}"
        )


def check_dense_flow(sensor_size, itemsize: int) -> tuple[int, int]:
    """``(W, H)`` of a dense flow: positive integers (ValueError, TypeError), within
    ``max_sensor_pixels`` (ValueError) and ``max_bytes`` (MemoryError)."""
    W, H = checks.sensor_size(sensor_size, "dense_flow")
    check_sensor(W, H, "the dense flow")
    check_bytes(dense_flow_bytes(W, H, itemsize), "the dense flow", f"sensor {W}x{H}")
    return W, H


def _unrolled_beyond(limit_name: str, value: str, limit: str, unrolled: str) -> ValueError:
    """The error of a value above a limit on what the kernels unroll at compile time."""
    return ValueError(
        f"{value} is above the limit {limit_name} = {limit}: {unrolled}; raise the limit with "
        f"cmax_taichi.set_limits({limit_name}=...) or {ENV_VARS[limit_name]}"
    )


def check_blur_sigma(blur_sigma: float) -> None:
    """ValueError when ``blur_sigma`` exceeds ``max_blur_sigma`` (compile cost grows with it)."""
    limit = get_limits().max_blur_sigma
    if blur_sigma > limit:
        taps = 2 * math.ceil(3 * blur_sigma) + 1
        why = f"the {taps}-tap footprint is unrolled at compile time (compile time and memory grow with it)"
        raise _unrolled_beyond("max_blur_sigma", f"blur_sigma = {blur_sigma:g} px", f"{limit:g} px", why)


def check_clusters(n_clusters: int) -> None:
    """ValueError when ``n_clusters`` exceeds ``max_clusters`` (compile cost grows with K)."""
    limit = get_limits().max_clusters
    if n_clusters > limit:
        why = (
            "the K-cluster kernels are unrolled over K (compile time grows with K; K = 100 exceeded "
            "Taichi's limit on fields)"
        )
        raise _unrolled_beyond("max_clusters", f"n_clusters = {n_clusters}", f"{limit}", why)
