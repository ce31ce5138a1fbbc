"""Warp models as Taichi functions (docs/FORMULAS.md, "Warp models"): one module per model.

Every model module provides the same ``@ti.func`` set, so that kernels are generic over the model:

* ``warp(p, dt, th, ctx) -> vec2``  the event at pixel ``p`` (px) and time offset ``dt`` (s) moved to t_ref;
* ``det(p, dt, th, ctx) -> scalar`` ``det dx'/dx`` (signed) at the event;
* ``div(p, th, ctx) -> scalar``     divergence of the flow at ``p`` (1/s);
* ``flow(p, th, ctx) -> vec2``      instantaneous flow ``v(p)`` (px/s), ``v = -dW/d(dt)`` at ``dt = 0``;
* ``param_jac(p, dt, th, ctx) -> (jx, ddet, ddiv)``: closed-form derivatives in theta for the fused
  pipeline's hand-written backward: ``jx`` (2 x P matrix) ``d x' / d theta`` of ``warp`` (px per
  parameter unit), ``ddet`` (P-vector) ``d det / d theta`` of ``det``, ``ddiv`` (P-vector)
  ``d div / d theta`` of ``div``. They differentiate exactly the expressions of ``warp``/``det``/``div``
  (same series branches); the tests hold them against Taichi autodiff and finite differences. Their
  trigonometric factors depend on theta only, so the compiler hoists them out of the serial event loop;
* optionally ``warp_terms(p, dt, th, ctx) -> (warp, det, jx, ddet, ddiv)``: all of the above for one
  event from one evaluation, for a model whose functions share costly intermediate values (``rotation3``
  rotates the ray once); the fused kernels call it in place of ``warp``, ``det`` and ``param_jac``;

and the declarations ``MODEL``, a dict of plain values (kernels import nothing from ``cmax_taichi``):
``name``, ``params`` and ``units`` (one per parameter: px/s, 1/s, rad/s, ...), and any of
``constant_quantities`` (which of the per-event quantities ``"div"`` (``div v``) and ``"absdet"``
(``|det dx'/dx|``) do not depend on the event: their regularizer map is that one value on every pixel
with votes, so the fused pipeline does not vote them), ``positive_det`` (``det > 0`` wherever an event
is warped, for every theta), ``store_event_terms`` (a costly ``warp_terms``: the fused CPU kernel
evaluates it once per event and stores it for the gradient; ``pipeline/fused.py``'s ``stores_terms``
says on which loop schedule), ``scale_kinds``,
``needs_camera``, ``collapse_enabled``, ``description``:
the fields of :class:`cmax_taichi.WarpModel`, which ``WarpModel.from_module`` builds from the module.

``th`` is the parameter vector (physical units). ``ctx`` is the 5-vector ``(cx, cy, fx, fy, T)``: the
centre of the coordinates (principal point or image centre, px), the focal lengths (px, used by
``rotation3`` only) and the window duration ``T`` (s, used by ``mitrokhin4`` only). The functions use no
dynamic loops, so they work in reverse-mode autodiff (``rotation3``'s angle reduction beyond
``phi = pi / 2`` uses ``floor``, whose adjoint Taichi's reverse mode takes as zero; its forward mode
refuses ``floor``, and nothing here uses forward mode). No event-loop function should call the maths
library per event (``sin``, ``cos``, ``exp`` of an event's ``dt``): such a call is an opaque function
call in both event loops (rotation3's 300,000-event call went from 36 to 15 ms when series replaced
them, benchmarks/NOTES.md); ``common.taylor_terms`` and ``common.polynomial`` build truncated
series exact to the precision in use (``rotation3`` is the example).

Shared helpers (complex arithmetic, constants, finite-difference stand-ins, the dense-flow kernel) are
in ``common.py``. The built-in models are the modules named in :data:`BUILTIN_MODELS`, registered in
that order by ``cmax_taichi/models/warps.py``; docs/RECIPE_WARP.md says how to add a model.
"""

from .common import make_dense_flow_kernel, make_fd_det, make_fd_div

#: the built-in warp models: one module of this package each, registered in this order
BUILTIN_MODELS = ("zoom1", "translation2", "rotation3", "se2", "sim2", "mitrokhin4")

__all__ = ["BUILTIN_MODELS", "make_dense_flow_kernel", "make_fd_det", "make_fd_div"]
