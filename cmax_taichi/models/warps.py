"""Warp models: metadata and capabilities around the Taichi functions of ``kernels/warps/``, and their
registry.

Each built-in model is one module of ``kernels/warps/``: its ``warp``, ``det``, ``div``, ``flow`` and
``param_jac``, and its declarations ``MODEL`` (name, parameters, units, capabilities); the modules named
in ``kernels/warps.BUILTIN_MODELS`` are registered by :func:`register_builtin_warps`, each with exactly
what it declares. Users add models with :func:`register_warp` (recipe: docs/RECIPE_WARP.md); a built-in
and a user model are the same :class:`WarpModel`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from types import ModuleType

import taichi as ti

from cmax_taichi.core.registry import Registry
from cmax_taichi.kernels import warps as kw

__all__ = [
    "QUANTITY_KINDS",
    "SCALE_KINDS",
    "WarpModel",
    "WARPS",
    "register_warp",
    "unregister_warp",
    "get_warp",
    "warp_names",
]

#: per-event quantities of a warp that regularizers vote into maps: ``div v`` (1/s) and
#: ``|det dx'/dx|`` (unitless)
QUANTITY_KINDS = ("div", "absdet")

#: how one unit of a parameter moves pixels over a window of T seconds (the optimizer's scaling):
#: "velocity" T px (px/s), "rate" T r px (1/s, or rad/s about the centre; r = RMS pixel radius),
#: "focal" T f px (rad/s about an axis in the image plane; f = focal length)
SCALE_KINDS = ("velocity", "rate", "focal")
_KIND_OF_UNIT = {"px/s": "velocity", "1/s": "rate", "rad/s": "rate"}


#: the optional Taichi functions of a model module (besides warp and flow) that from_module reads
_MODULE_FUNCTIONS = ("det", "div", "param_jac", "warp_terms")


@dataclass(frozen=True)
class WarpModel:
    """A motion model that warps events to the reference time, with its declared capabilities.

    Parameters
    ----------
    name : str
        Registry name.
    params : tuple of str
        Parameter names, in the order of ``theta``.
    units : tuple of str
        Physical unit of each parameter (px/s, 1/s, rad/s, ...).
    warp : ti.func
        ``warp(p, dt, th, ctx) -> vec2`` (signatures: ``kernels/warps/__init__.py``).
    flow : ti.func
        ``flow(p, th, ctx) -> vec2``, the instantaneous flow (px/s), ``v = -dW/d(dt)`` at ``dt = 0``.
    det, div : ti.func, optional
        Closed forms of ``det dx'/dx`` and ``div v``; when omitted, central differences of ``warp`` and
        ``flow`` stand in (approximate; check them with :func:`cmax_taichi.event_jacobians`).
    param_jac : ti.func, optional
        ``param_jac(p, dt, th, ctx) -> (jx, ddet, ddiv)``: ``d x'/d theta`` (2 x P matrix) and the
        P-vectors ``d det/d theta``, ``d div/d theta`` of the closed forms (needs ``det`` and ``div``).
        Declaring it puts the model on the fused pipeline (one kernel launch per value-and-gradient);
        without it, value and gradient run on the generic autodiff chain (slower, and
        :class:`~cmax_taichi.ChainPathWarning` says so once).
    warp_terms : ti.func, optional
        ``warp_terms(p, dt, th, ctx) -> (warp, det, jx, ddet, ddiv)``: the four above computed together,
        for a model whose functions share costly intermediate values (``rotation3`` rotates the ray
        once); the fused kernels then call it in place of ``warp``, ``det`` and ``param_jac``. It must
        return exactly what those return. Default: the fused kernels call them side by side.
    constant_quantities : tuple of str
        Which of :data:`QUANTITY_KINDS` do not depend on the event (e.g. ``("div",)`` when ``div v``
        depends on theta only): the fused pipeline then does not vote their maps. Declare only what
        holds for every ``p`` and ``dt``.
    positive_det : bool
        ``det dx'/dx > 0`` wherever an event can be warped, for every theta. The fused backward then
        differentiates ``|det|`` as ``det``; otherwise it multiplies ``d det/d theta`` by the sign of
        ``det`` (one more ``det`` per event when a deformation regularizer is used).
    store_event_terms : bool
        A performance declaration for a model whose ``warp_terms`` is costly per event (``rotation3``):
        the fused CPU kernel on the thread pool's schedule (not the serial one of small windows, where
        the stored terms cost more than they save) evaluates it once per event and call, stores the
        position, quantities and Jacobians (``2 + 2 P`` to ``4 + 4 P`` numbers per event, by the voted
        regularizers) and reads them in the splat and in the gradient's gather, rather than evaluating
        it in both. Values and gradients agree with the unstored kernel to rounding. Declare it only
        where it is measured faster: for a cheap warp the stored terms' memory traffic costs more than
        the arithmetic they save (benchmarks/NOTES.md). GPUs (atomic adds) ignore it.
    scale_kinds : tuple of str, optional
        One of :data:`SCALE_KINDS` per parameter, for the optimizer's scaling and search box. Default:
        from ``units`` (px/s: "velocity"; 1/s, rad/s: "rate"); a model with any other unit gets its
        scales numerically from its flow.
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
    param_jac: Callable | None = None
    warp_terms: Callable | None = None
    constant_quantities: tuple[str, ...] = ()
    positive_det: bool = False
    store_event_terms: bool = False
    scale_kinds: tuple[str, ...] | None = None
    needs_camera: bool = False
    collapse_enabled: bool = False
    description: str = ""
    _fallbacks: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        if len(self.params) != len(self.units) or not self.params:
            raise ValueError(f"warp {self.name!r}: params and units must be non-empty, same length")
        object.__setattr__(self, "constant_quantities", tuple(self.constant_quantities))
        unknown = [k for k in self.constant_quantities if k not in QUANTITY_KINDS]
        if unknown:
            raise ValueError(
                f"warp {self.name!r}: constant_quantities {unknown} are not among {QUANTITY_KINDS}"
            )
        if self.warp_terms is not None and self.param_jac is None:
            raise ValueError(f"warp {self.name!r}: warp_terms joins warp, det and param_jac; pass them too")
        if self.param_jac is not None and (self.det is None or self.div is None):
            raise ValueError(
                f"warp {self.name!r}: param_jac differentiates the closed forms det and div; pass them too"
            )
        if self.scale_kinds is not None:
            object.__setattr__(self, "scale_kinds", tuple(self.scale_kinds))
            if len(self.scale_kinds) != len(self.params) or any(
                k not in SCALE_KINDS for k in self.scale_kinds
            ):
                raise ValueError(f"warp {self.name!r}: scale_kinds needs one of {SCALE_KINDS} per parameter")

    @classmethod
    def from_module(cls, module: ModuleType, **overrides) -> WarpModel:
        """The model of a module of Taichi functions: its ``warp``, ``flow`` and (those present) ``det``,
        ``div``, ``param_jac``, ``warp_terms``, with the fields its dict ``MODEL`` declares (``name``,
        ``params``, ``units`` and any other field of this class); ``overrides`` replace declared fields."""
        declared = getattr(module, "MODEL", None)
        if not isinstance(declared, dict):
            raise TypeError(f"module {module.__name__} declares no MODEL dict (kernels/warps/__init__.py)")
        allowed = {f.name for f in fields(cls) if f.init and not f.name.startswith("_")}
        allowed -= {"warp", "flow", *_MODULE_FUNCTIONS}
        metadata = {**declared, **overrides}
        unknown = sorted(set(metadata) - allowed)
        if unknown:
            raise TypeError(
                f"module {module.__name__}: MODEL declares {unknown}, which WarpModel does not have "
                f"(valid: {', '.join(sorted(allowed))})"
            )
        missing = [k for k in ("warp", "flow") if not hasattr(module, k)]
        if missing:
            raise TypeError(f"module {module.__name__} has no {' or '.join(missing)} function")
        fns = {k: getattr(module, k) for k in _MODULE_FUNCTIONS if hasattr(module, k)}
        for key in ("params", "units", "constant_quantities", "scale_kinds"):
            if metadata.get(key) is not None:
                metadata[key] = tuple(metadata[key])
        return cls(warp=module.warp, flow=module.flow, **fns, **metadata)

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

    def quantity(self, kind: str) -> Callable:
        """The per-event quantity ``q(p, dt, th, ctx)`` of ``kind``: "div" (``div v``, 1/s) or "absdet"
        (``|det dx'/dx|``), from the closed forms or their stand-ins; one Taichi function per model and
        kind (kernels compiled for it are cached by function)."""
        key = "quantity_" + kind
        if key not in self._fallbacks:
            if kind == "div":
                div = self.div_fn

                @ti.func
                def q(p, dt, th, ctx):
                    return div(p, th, ctx)

            elif kind == "absdet":
                det = self.det_fn

                @ti.func
                def q(p, dt, th, ctx):
                    return ti.abs(det(p, dt, th, ctx))

            else:
                raise ValueError(f"unknown quantity {kind!r}; valid: {', '.join(QUANTITY_KINDS)}")
            self._fallbacks[key] = q
        return self._fallbacks[key]

    @property
    def parameter_kinds(self) -> tuple[str, ...] | None:
        """One of :data:`SCALE_KINDS` per parameter (declared, or from the units), or None when a unit
        is not one of px/s, 1/s, rad/s (the optimizer then scales numerically)."""
        if self.scale_kinds is not None:
            return self.scale_kinds
        if all(u in _KIND_OF_UNIT for u in self.units):
            return tuple(_KIND_OF_UNIT[u] for u in self.units)
        return None


WARPS: Registry[WarpModel] = Registry("warp")


def register_warp(model: WarpModel, *, replace: bool = False) -> WarpModel:
    """Add a warp model to the registry (``replace=True`` to overwrite a name)."""
    if not isinstance(model, WarpModel):
        raise TypeError(f"expected a WarpModel, got {type(model).__name__}")
    return WARPS.register(model.name, model, replace=replace)


def unregister_warp(name: str) -> WarpModel:
    """Remove the model called ``name`` from the registry and return it (KeyError if absent)."""
    return WARPS.unregister(name)


def get_warp(name_or_model: str | WarpModel) -> WarpModel:
    """The registered model called ``name`` (a WarpModel passes through)."""
    if isinstance(name_or_model, WarpModel):
        return name_or_model
    return WARPS.get(name_or_model)


def warp_names() -> list[str]:
    """Names of the registered warp models."""
    return WARPS.names()


def register_builtin_warps(registry: Registry[WarpModel]) -> None:
    """Register the built-in models: the modules of ``kernels/warps/`` named in
    ``kernels/warps.BUILTIN_MODELS``, each with exactly what its ``MODEL`` declares."""
    for module_name in kw.BUILTIN_MODELS:
        model = WarpModel.from_module(importlib.import_module(f"{kw.__name__}.{module_name}"))
        registry.register(model.name, model, builtin=True)


register_builtin_warps(WARPS)
