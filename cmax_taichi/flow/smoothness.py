"""Smoothness regularizers of a dense flow, computed on its grid, and their registry.

The event-collapse regularizers (``divergence``, ``deformation``; ``cmax_taichi.models.regularizers``)
are maps of per-event quantities and run in the kernels. A smoothness term depends on the node values
only, so it is computed on the host, in float64, with its exact gradient: a :class:`Smoothness` entry
maps the node displacements over the window ``D = U T`` (px, array ``(ny + 1, nx + 1, 2)``) and the grid
to ``(value, dvalue/dD)``. Both built-ins measure the *strain* of the displacement field, the
difference of neighbouring nodes divided by their distance (px of displacement per px, dimensionless),
so that a weight means the same on every level of a coarse-to-fine run and on every sensor:

* ``total_variation``: the mean over the grid's edges and both components of the Charbonnier function
  ``sqrt(e^2 + eps^2) - eps`` (``eps = 1e-3``: an L1 total variation with a differentiable kink), the
  anisotropic TV of tub-rip/event_based_optical_flow (``src/costs/total_variation.py``, L1 of the Sobel
  responses of the flow) written for a grid;
* ``quadratic``: the mean of ``e^2`` over the same terms (a Tikhonov / H1 prior).

``J`` subtracts ``lambda * value``. Register another with :func:`register_smoothness`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from cmax_taichi.core.registry import Registry
from cmax_taichi.flow.grid import FlowGrid

__all__ = [
    "CHARBONNIER_EPS",
    "SMOOTHNESS",
    "Smoothness",
    "register_smoothness",
    "smoothness_names",
    "strains",
]

#: the Charbonnier constant of ``total_variation`` (dimensionless strain)
CHARBONNIER_EPS = 1e-3


@dataclass(frozen=True)
class Smoothness:
    """A prior on the node values of a dense flow.

    Parameters
    ----------
    name : str
        Registry name (the key in ``regularizers={...}``).
    value_and_grad : callable
        ``value_and_grad(D, grid) -> (value, dvalue/dD)``: ``D`` the node displacements over the window,
        px, of shape ``grid.shape``; the gradient has the same shape.
    description : str
        One line for listings.
    """

    name: str
    value_and_grad: Callable[[np.ndarray, FlowGrid], tuple[float, np.ndarray]]
    description: str = ""


SMOOTHNESS: Registry[Smoothness] = Registry("smoothness regularizer")


def register_smoothness(entry: Smoothness, *, replace: bool = False) -> Smoothness:
    """Add a smoothness regularizer to the registry."""
    if not isinstance(entry, Smoothness):
        raise TypeError(f"expected a Smoothness, got {type(entry).__name__}")
    return SMOOTHNESS.register(entry.name, entry, replace=replace)


def smoothness_names() -> list[str]:
    """Names of the registered smoothness regularizers."""
    return SMOOTHNESS.names()


def strains(D: np.ndarray, grid: FlowGrid) -> tuple[np.ndarray, np.ndarray]:
    """``(ex, ey)``: differences of the node displacements along x (``(ny + 1, nx, 2)``) and along y
    (``(ny, nx + 1, 2)``) divided by the node spacing."""
    sx, sy = grid.spacing
    return (D[:, 1:] - D[:, :-1]) / sx, (D[1:] - D[:-1]) / sy


def _from_strains(D: np.ndarray, grid: FlowGrid, rho, drho) -> tuple[float, np.ndarray]:
    """Mean of ``rho(e)`` over every strain term, and its gradient in ``D``."""
    sx, sy = grid.spacing
    ex, ey = strains(D, grid)
    n = ex.size + ey.size
    value = (float(np.sum(rho(ex))) + float(np.sum(rho(ey)))) / n
    gx = drho(ex) / (n * sx)
    gy = drho(ey) / (n * sy)
    grad = np.zeros_like(D)
    grad[:, 1:] += gx
    grad[:, :-1] -= gx
    grad[1:] += gy
    grad[:-1] -= gy
    return value, grad


def total_variation(D: np.ndarray, grid: FlowGrid) -> tuple[float, np.ndarray]:
    """Charbonnier total variation of the strain (see the module docstring)."""
    eps = CHARBONNIER_EPS
    return _from_strains(
        D, grid, lambda e: np.sqrt(e * e + eps * eps) - eps, lambda e: e / np.sqrt(e * e + eps * eps)
    )


def quadratic(D: np.ndarray, grid: FlowGrid) -> tuple[float, np.ndarray]:
    """Mean squared strain."""
    return _from_strains(D, grid, lambda e: e * e, lambda e: 2.0 * e)


def curvature(D: np.ndarray, grid: FlowGrid) -> tuple[float, np.ndarray]:
    """Mean squared second derivative of the displacement field (the Frobenius norm of its Hessian,
    ``D_xx^2 + 2 D_xy^2 + D_yy^2``, by second differences on the grid), times the squared larger sensor
    side so that it is dimensionless: 0 for every affine field (translation, expansion, rotation,
    shear), so it does not bias a flow towards rigid motion, while a local contraction or fold (a bump
    of the flow) costs in proportion to its curvature."""
    sx, sy = grid.spacing
    L2 = float(max(grid.width, grid.height)) ** 2
    grad = np.zeros_like(D)
    value = 0.0
    terms = []
    if grid.nx >= 2:
        terms.append(("xx", (D[:, 2:] - 2 * D[:, 1:-1] + D[:, :-2]) / (sx * sx), 1.0))
    if grid.ny >= 2:
        terms.append(("yy", (D[2:] - 2 * D[1:-1] + D[:-2]) / (sy * sy), 1.0))
    terms.append(("xy", (D[1:, 1:] - D[1:, :-1] - D[:-1, 1:] + D[:-1, :-1]) / (sx * sy), 2.0))
    for kind, c, w in terms:
        n = c.size
        value += w * L2 * float(np.sum(c * c)) / n
        g = 2.0 * w * L2 * c / n
        if kind == "xx":
            g = g / (sx * sx)
            grad[:, 2:] += g
            grad[:, 1:-1] -= 2 * g
            grad[:, :-2] += g
        elif kind == "yy":
            g = g / (sy * sy)
            grad[2:] += g
            grad[1:-1] -= 2 * g
            grad[:-2] += g
        else:
            g = g / (sx * sy)
            grad[1:, 1:] += g
            grad[1:, :-1] -= g
            grad[:-1, 1:] -= g
            grad[:-1, :-1] += g
    return value, grad


def register_builtin_smoothness(registry: Registry[Smoothness]) -> None:
    registry.register(
        "total_variation",
        Smoothness(
            "total_variation",
            total_variation,
            "Charbonnier total variation of the displacement field's strain (L1, as the reference's TV)",
        ),
    )
    registry.register(
        "quadratic",
        Smoothness("quadratic", quadratic, "mean squared strain of the displacement field (Tikhonov)"),
    )
    registry.register(
        "curvature",
        Smoothness(
            "curvature",
            curvature,
            "mean squared second derivative of the displacement field (0 for every affine flow)",
        ),
    )


register_builtin_smoothness(SMOOTHNESS)
