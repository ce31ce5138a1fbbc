"""The flow field a parametric warp implies on the pixel grid (the predicted flow that AEE scores)."""

from __future__ import annotations

import numpy as np

from cmax_taichi.core import backend, checks, limits
from cmax_taichi.core.events import Camera
from cmax_taichi.kernels import warps as kwarps
from cmax_taichi.models.warps import WarpModel, get_warp
from cmax_taichi.pipeline.parameters import check_theta, require_finite
from cmax_taichi.pipeline.setup import cached_kernel

__all__ = ["dense_flow"]


def dense_flow(
    warp: str | WarpModel,
    theta,
    sensor_size: tuple[int, int],
    *,
    camera: Camera | None = None,
    duration: float = 1.0,
    dt: float = 0.0,
) -> np.ndarray:
    """Flow field of a parametric warp on the pixel grid, shape (2, H, W) (x then y component).

    Parameters
    ----------
    warp : str or WarpModel
        The model.
    theta : array_like
        Parameters, physical units.
    sensor_size : (int, int)
        ``(W, H)``.
    camera : Camera, optional
        Centre (and intrinsics for ``rotation3``); default the image centre.
    duration : float
        Window duration T (s) for ``mitrokhin4``.
    dt : float
        0: instantaneous flow (px/s). Otherwise the displacement ``-(W(x, dt) - x)`` in px over ``dt``
        seconds (finite; a negative ``dt`` gives the displacement backwards in time).

    Returns
    -------
    ndarray
        ``(2, H, W)`` float64. NaN (the library's "no value here") where the warp sends the pixel
        nowhere: a ``rotation3`` ray rotated behind the camera over ``dt``.

    Raises
    ------
    TypeError, ValueError
        For a ``dt``, ``duration`` or ``theta`` that is not a finite number (``dt = NaN`` would give
        an all-NaN field).
    NonFiniteResultError
        (a ValueError) when the parameters overflow the float type on the grid.
    """
    backend.ensure_initialized()
    model = get_warp(warp)
    theta = check_theta(theta, model.n_params, model.name)
    W, H = limits.check_dense_flow(sensor_size, np.dtype(backend.numpy_real()).itemsize)
    if model.needs_camera and camera is None:
        raise ValueError(f"warp {model.name!r} needs a camera (intrinsics): pass camera=")
    duration = checks.seconds("duration", duration, positive=True)
    dt = checks.seconds("dt", dt)
    if camera is not None:
        ctx = [camera.cx, camera.cy, camera.fx, camera.fy, duration]
    else:
        ctx = [(W - 1) / 2.0, (H - 1) / 2.0, 1.0, 1.0, duration]
    real = backend.numpy_real()
    params = np.array([*theta.tolist(), *ctx, dt], dtype=real)
    try:
        out = np.empty((3, H, W), dtype=real)  # x, y and "sent nowhere"
    except MemoryError:
        raise MemoryError(f"no memory for the dense flow of a {W}x{H} sensor ({3 * W * H} values)") from None
    kernel = cached_kernel(
        ("dense_flow", model.name, id(model), W, H),
        lambda: kwarps.make_dense_flow_kernel(model.flow, model.warp, W, H, model.n_params),
    )
    kernel(params, out)
    planes = out.astype(np.float64, copy=False)
    flow, nowhere = planes[:2], planes[2] > 0
    require_finite(model, theta, "the dense flow", flow[:, ~nowhere])
    flow[:, nowhere] = np.nan
    return flow
