"""Objectives (focus measures, maximised) and their registry.

An :class:`Objective` is a per-pixel term (or its own reduce kernel) and a finalize function; the
built-ins are written with the blocks of ``kernels/blocks.py`` and declare what the fused pipeline
needs to compute them itself (:class:`FusedObjective`). A pixel term and a finalize are enough: the
generic chain's reduce kernel is derived from the pixel term. Built-ins are registered explicitly by
:func:`register_builtin_objectives`. Adding one: docs/RECIPE_OBJECTIVE.md.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

from cmax_taichi.core.registry import Registry
from cmax_taichi.kernels import blocks as kb
from cmax_taichi.kernels import objectives as ko

__all__ = [
    "FusedObjective",
    "Objective",
    "OBJECTIVES",
    "register_objective",
    "unregister_objective",
    "objective_names",
]


@dataclass(frozen=True)
class FusedObjective:
    """What the fused pipeline (``kernels/fused.py``) needs to compute an objective and its gradient.

    Parameters
    ----------
    pixel : ti.func
        ``pixel(v, gx, gy) -> ti.Vector`` of the ``slots_per_channel`` terms one pixel adds: ``v`` is the
        blurred IWE there, ``gx, gy`` its Sobel responses (unnormalised; 0 unless ``sobel``).
    finalize : ti.func
        ``finalize(acc_vector, channel, n_pixels) -> G_channel``; must be the objective's own finalize.
    adjoint : ti.func
        ``adjoint(acc_vector, channel, n_pixels) -> (scale, offset)`` such that the pixel adjoint is
        ``dG_c/dI(x) = scale * L(I_c)(x) + offset``, where ``L`` is the identity, or with ``sobel``
        ``Sobel_x^T Sobel_x + Sobel_y^T Sobel_y``. An objective whose adjoint is not of this form
        declares no fused path and takes the generic chain (Taichi autodiff). Without ``sobel`` this
        makes each pixel term a polynomial of degree at most 2 in ``v``, which the fused kernel uses:
        it sums the terms over the image from ``sum I`` and ``sum I^2`` (``pixel`` evaluated at 0, 1
        and -1 gives the polynomial), never pixel by pixel; a term of higher degree would be summed
        wrongly, which ``cm.check_objective`` reports as a value that differs from the reference.
    sobel : bool
        The pixel terms read the Sobel responses (the fused kernel then keeps the Sobel images).
    """

    pixel: Callable
    finalize: Callable
    adjoint: Callable
    sobel: bool = False


@dataclass(frozen=True)
class Objective:
    """A focus measure G of the IWE.

    Parameters
    ----------
    name : str
        Registry name.
    slots_per_channel : int
        Accumulator slots each IWE channel uses.
    make_reduce : callable or None
        ``make_reduce(width, height, n_channels) -> kernel(img, acc)`` adding per-pixel terms into the
        0-D accumulator vector (channel c at ``acc[slots_per_channel * c + s]``). None (the usual case):
        built from ``pixel`` (``kernels/objectives.make_pixel_reduce``).
    finalize : ti.func
        ``finalize(acc_vector, channel, n_pixels) -> G_channel``.
    description : str
        One line for listings.
    fused : FusedObjective, optional
        The declaration that lets the fused pipeline compute this objective; without it every problem
        with this objective takes the generic kernel chain (Taichi's autodiff of ``pixel`` and
        ``finalize``; docs/RECIPE_OBJECTIVE.md, "The fused path of an objective").
    pixel : ti.func, optional
        ``pixel(v, gx, gy) -> ti.Vector`` of the ``slots_per_channel`` terms one pixel adds (``v`` the
        blurred IWE there, ``gx, gy`` its unnormalised Sobel responses when ``sobel``, else 0). Default:
        the fused declaration's. With ``finalize`` it is all an objective needs.
    sobel : bool
        ``pixel`` reads the Sobel responses. Default: the fused declaration's, else False.
    """

    name: str
    slots_per_channel: int
    make_reduce: Callable | None = None
    finalize: Callable | None = None
    description: str = ""
    fused: FusedObjective | None = None
    pixel: Callable | None = None
    sobel: bool | None = None

    def __post_init__(self) -> None:
        if isinstance(self.slots_per_channel, bool) or not isinstance(self.slots_per_channel, int):
            raise TypeError(f"objective {self.name!r}: slots_per_channel must be an int")
        if self.slots_per_channel < 1:
            raise ValueError(f"objective {self.name!r}: slots_per_channel must be at least 1")
        if self.finalize is None:
            raise ValueError(f"objective {self.name!r} needs finalize(acc, c, n_pixels)")
        if self.fused is not None:
            if not isinstance(self.fused, FusedObjective):
                raise TypeError(f"fused must be a FusedObjective, got {type(self.fused).__name__}")
            if self.fused.finalize is not self.finalize:
                raise ValueError(
                    f"objective {self.name!r}: the fused declaration's finalize is not the objective's "
                    "finalize (declare fused=None to use the generic chain, or declare it with this finalize)"
                )
            if self.pixel is not None and self.pixel is not self.fused.pixel:
                raise ValueError(f"objective {self.name!r}: pixel is not the fused declaration's pixel")
            if self.sobel is not None and bool(self.sobel) != bool(self.fused.sobel):
                raise ValueError(f"objective {self.name!r}: sobel is not the fused declaration's sobel")
            object.__setattr__(self, "pixel", self.fused.pixel)
            object.__setattr__(self, "sobel", bool(self.fused.sobel))
        object.__setattr__(self, "sobel", bool(self.sobel))
        if self.make_reduce is None:
            if self.pixel is None:
                raise ValueError(
                    f"objective {self.name!r} needs a pixel term (pixel=...), a fused declaration or "
                    "make_reduce"
                )
            reduce = functools.partial(ko.make_pixel_reduce, self.pixel, self.slots_per_channel, self.sobel)
            object.__setattr__(self, "make_reduce", reduce)


OBJECTIVES: Registry[Objective] = Registry("objective")


def register_objective(objective: Objective, *, replace: bool = False) -> Objective:
    """Add an objective to the registry."""
    if not isinstance(objective, Objective):
        raise TypeError(f"expected an Objective, got {type(objective).__name__}")
    return OBJECTIVES.register(objective.name, objective, replace=replace)


def unregister_objective(name: str) -> Objective:
    """Remove the objective called ``name`` and return it (KeyError if absent)."""
    return OBJECTIVES.unregister(name)


def objective_names() -> list[str]:
    """Names of the registered objectives."""
    return OBJECTIVES.names()


def _builtin(name: str, slots: int, pixel, finalize, adjoint, sobel: bool, description: str) -> Objective:
    return Objective(
        name,
        slots,
        None,
        finalize,
        description,
        fused=FusedObjective(pixel=pixel, finalize=finalize, adjoint=adjoint, sobel=sobel),
    )


def register_builtin_objectives(registry: Registry[Objective]) -> None:
    registry.register(
        "variance",
        _builtin(
            "variance",
            kb.VARIANCE_SLOTS,
            kb.variance_pixel,
            kb.variance_finalize,
            kb.variance_adjoint,
            False,
            "image variance (Gallego et al. CVPR 2018)",
        ),
        builtin=True,
    )
    registry.register(
        "gradient_magnitude",
        _builtin(
            "gradient_magnitude",
            kb.GRADIENT_MAGNITUDE_SLOTS,
            kb.gradient_magnitude_pixel,
            kb.gradient_magnitude_finalize,
            kb.gradient_magnitude_adjoint,
            True,
            "mean squared Sobel/8 gradient (Gallego et al. CVPR 2019)",
        ),
        builtin=True,
    )
    registry.register(
        "mean_square",
        _builtin(
            "mean_square",
            kb.MEAN_SQUARE_SLOTS,
            kb.mean_square_pixel,
            kb.mean_square_finalize,
            kb.mean_square_adjoint,
            False,
            "mean of the squared IWE (Gallego et al. CVPR 2019)",
        ),
        builtin=True,
    )


register_builtin_objectives(OBJECTIVES)
