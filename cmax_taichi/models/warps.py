"""Warp models: metadata around the Taichi functions of ``kernels/warps.py``, and their registry.

The six built-in models are registered explicitly by :func:`register_builtin_warps`, called once at the
bottom of this module. Users add models with :func:`register_warp`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from cmax_taichi.core.registry import Registry
from cmax_taichi.kernels import warps as kw

__all__ = ["WarpModel", "WARPS", "register_warp", "get_warp", "warp_names"]


@dataclass(frozen=True)
class WarpModel:
    """A motion model that warps events to the reference time.

    Parameters
    ----------
    name : str
        Registry name.
    params : tuple of str
        Parameter names, in the order of ``theta``.
    units : tuple of str
        Physical unit of each parameter (px/s, 1/s, rad/s).
    warp : ti.func
        ``warp(p, dt, th, ctx) -> vec2`` (see ``kernels/warps.py`` for the signature).
    flow : ti.func
        ``flow(p, th, ctx) -> vec2``, the instantaneous flow (px/s), ``v = -dW/d(dt)`` at ``dt = 0``.
    det, div : ti.func, optional
        Closed forms of ``det dx'/dx`` and ``div v``; when omitted, central differences of ``warp`` and
        ``flow`` stand in (approximate; check them with :func:`cmax_taichi.event_jacobians`).
    needs_camera : bool
        The model needs intrinsics (``rotation3``).
    collapse_enabled : bool
        The model can shrink areas (zoom components), so CMax can collapse without a regularizer.
    description : str
        One line for listings.
    """

    name: str
    params: tuple[str, ...]
    units: tuple[str, ...]
    warp: Callable
    flow: Callable
    det: Callable | None = None
    div: Callable | None = None
    needs_camera: bool = False
    collapse_enabled: bool = False
    description: str = ""
    _fallbacks: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(self.params) != len(self.units) or not self.params:
            raise ValueError(f"warp {self.name!r}: params and units must be non-empty, same length")

    @property
    def n_params(self) -> int:
        return len(self.params)

    @property
    def det_fn(self) -> Callable:
        """The closed-form determinant, or its finite-difference stand-in."""
        if self.det is not None:
            return self.det
        return self._fallbacks.setdefault("det", kw.make_fd_det(self.warp))

    @property
    def div_fn(self) -> Callable:
        """The closed-form divergence, or its finite-difference stand-in."""
        if self.div is not None:
            return self.div
        return self._fallbacks.setdefault("div", kw.make_fd_div(self.flow))


WARPS: Registry[WarpModel] = Registry("warp")


def register_warp(model: WarpModel, *, replace: bool = False) -> WarpModel:
    """Add a warp model to the registry (``replace=True`` to overwrite a name)."""
    if not isinstance(model, WarpModel):
        raise TypeError(f"expected a WarpModel, got {type(model).__name__}")
    return WARPS.register(model.name, model, replace=replace)


def get_warp(name_or_model: str | WarpModel) -> WarpModel:
    """The registered model called ``name`` (a WarpModel passes through)."""
    if isinstance(name_or_model, WarpModel):
        return name_or_model
    return WARPS.get(name_or_model)


def warp_names() -> list[str]:
    """Names of the registered warp models."""
    return WARPS.names()


def register_builtin_warps(registry: Registry[WarpModel]) -> None:
    """Register the six models of docs/FORMULAS.md."""
    builtins = [
        WarpModel(
            "zoom1",
            ("h_z",),
            ("1/s",),
            kw.zoom1_warp,
            kw.zoom1_flow,
            kw.zoom1_det,
            kw.zoom1_div,
            collapse_enabled=True,
            description="1-DOF zoom in/out about the centre (forward/backward camera motion)",
        ),
        WarpModel(
            "translation2",
            ("v_x", "v_y"),
            ("px/s", "px/s"),
            kw.translation2_warp,
            kw.translation2_flow,
            kw.translation2_det,
            kw.translation2_div,
            description="2-DOF constant feature flow",
        ),
        WarpModel(
            "rotation3",
            ("w_x", "w_y", "w_z"),
            ("rad/s", "rad/s", "rad/s"),
            kw.rotation3_warp,
            kw.rotation3_flow,
            kw.rotation3_det,
            kw.rotation3_div,
            needs_camera=True,
            description="3-DOF camera rotation (SO(3), needs intrinsics)",
        ),
        WarpModel(
            "se2",
            ("v_x", "v_y", "w"),
            ("px/s", "px/s", "rad/s"),
            kw.se2_warp,
            kw.se2_flow,
            kw.se2_det,
            kw.se2_div,
            description="3-DOF planar Euclidean motion (SE(2) exponential)",
        ),
        WarpModel(
            "sim2",
            ("v_x", "v_y", "w", "s"),
            ("px/s", "px/s", "rad/s", "1/s"),
            kw.sim2_warp,
            kw.sim2_flow,
            kw.sim2_det,
            kw.sim2_div,
            collapse_enabled=True,
            description="4-DOF similarity (Sim(2) exponential)",
        ),
        WarpModel(
            "mitrokhin4",
            ("h_x", "h_y", "h_z", "theta"),
            ("px/s", "px/s", "1/s", "rad/s"),
            kw.mitrokhin4_warp,
            kw.mitrokhin4_flow,
            kw.mitrokhin4_det,
            kw.mitrokhin4_div,
            collapse_enabled=True,
            description="4-DOF in-plane camera motion of Mitrokhin et al. (IROS 2018)",
        ),
    ]
    for model in builtins:
        registry.register(model.name, model)


register_builtin_warps(WARPS)
