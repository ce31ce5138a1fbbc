"""Plotting helpers for CMax: IWEs, flow colours, regularizer maps and objective landscapes.

Matplotlib only, imported inside the functions (``import cmax_taichi`` never imports matplotlib, and
``from cmax_taichi import viz`` imports no pyplot either). Every ``show_*`` / ``plot_*`` function draws
into the :class:`matplotlib.axes.Axes` given as its first argument ``ax`` and returns the artist it
made, so that interactive code can update it in place (``artist.set_data(...)``) instead of redrawing.

Conventions (docs/FORMULAS.md): images are ``(H, W)`` arrays indexed ``[y, x]`` and drawn with the
origin at the top left, as the sensor sees them; flows are ``(2, H, W)`` arrays (x then y component) in
px/s or px; parameters are in the physical units of the warp model.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from cmax_taichi.models.regularizers import REGULARIZERS
from cmax_taichi.models.warps import WarpModel, get_warp

if TYPE_CHECKING:  # pragma: no cover - typing only, keeps matplotlib out of the import path
    from matplotlib.axes import Axes
    from matplotlib.colors import Normalize
    from matplotlib.image import AxesImage

    from cmax_taichi.core.events import Events
    from cmax_taichi.pipeline.problem import ContrastMaximization

__all__ = [
    "param_label",
    "iwe_limits",
    "show_iwe",
    "flow_to_rgb",
    "flow_wheel",
    "show_flow",
    "map_norm",
    "show_map",
    "show_regularizer_map",
    "regularizer_variants",
    "landscape_1d",
    "landscape_2d",
    "plot_landscape_1d",
    "plot_landscape_2d",
]

#: colour of pixels without a value: no event landed there in a regularizer map (NaN in
#: ``ContrastMaximization.maps``), or a NaN flow (distinct from the white neutral value)
NO_EVENT_COLOR = "0.80"


def _colorbar(ax: Axes, mappable, label: str):
    """A colour bar beside ``ax`` that keeps the image's aspect (fraction/pad tuned for small panels)."""
    return ax.figure.colorbar(mappable, ax=ax, fraction=0.046, pad=0.03, label=label)


def _label_image_axes(ax: Axes, title: str) -> None:
    ax.set_title(title)
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")


def _fmt(value: float) -> str:
    """Short number for labels: no exponent below 1e5."""
    return f"{value:.0f}" if 100 <= abs(value) < 1e5 else f"{value:.3g}"


def param_label(model: str | WarpModel, index: int) -> str:
    """Axis label of parameter ``index`` of a warp model, e.g. ``"h_z [1/s]"``."""
    m = get_warp(model)
    return f"{m.params[index]} [{m.units[index]}]"


# --- images of warped events -----------------------------------------------------------------------------
def iwe_limits(image: np.ndarray, percentile: float = 99.5) -> tuple[float, float]:
    """Colour limits for an IWE: ``(0, p)`` for counts, ``(-p, p)`` for signed images.

    ``p`` is the ``percentile`` of the absolute values of the pixels that received events (empty pixels
    would pull any percentile to 0), so that a few saturated pixels do not wash out the edges.
    """
    values = np.abs(np.asarray(image, dtype=np.float64))
    nonzero = values[values > 0]
    top = float(np.percentile(nonzero, percentile)) if nonzero.size else 1.0
    top = top if top > 0 else 1.0
    return (-top, top) if np.any(np.asarray(image) < 0) else (0.0, top)


def show_iwe(
    ax: Axes,
    image: np.ndarray,
    *,
    title: str = "Image of warped events",
    percentile: float = 99.5,
    colorbar: bool = True,
) -> AxesImage:
    """Draw an image of warped events.

    Parameters
    ----------
    image : ndarray
        ``(H, W)`` IWE (event votes per pixel), or ``(2, H, W)`` per-polarity images, drawn as positive
        minus negative. Counts are drawn dark on white (``gray_r``); images with negative values (signed
        polarity) with a diverging map centred on 0.
    title : str
        Axes title.
    percentile : float
        Upper colour limit as a percentile of the non-empty pixels (see :func:`iwe_limits`).
    colorbar : bool
        Add a colour bar labelled in events per pixel.

    Returns
    -------
    AxesImage
        The image artist (update it with ``set_data`` and ``set_clim(*iwe_limits(new))``).
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 3 and img.shape[0] == 2:
        img = img[0] - img[1]
    if img.ndim != 2:
        raise ValueError(f"image must be (H, W) or (2, H, W), got shape {np.shape(image)}")
    vmin, vmax = iwe_limits(img, percentile)
    cmap = "RdBu_r" if vmin < 0 else "gray_r"
    artist = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    _label_image_axes(ax, title)
    if colorbar:
        _colorbar(ax, artist, "events / px (blurred votes)")
    return artist


# --- flow ------------------------------------------------------------------------------------------------
def flow_to_rgb(flow: np.ndarray, max_magnitude: float | None = None) -> np.ndarray:
    """Colour-code a flow field: hue = direction, value (brightness) = magnitude.

    Parameters
    ----------
    flow : ndarray
        ``(2, H, W)`` flow (x then y component; px/s or px), or ``(2, ...)`` of any shape.
    max_magnitude : float, optional
        Magnitude drawn at full brightness (same unit as ``flow``); default the largest magnitude.

    Returns
    -------
    ndarray
        RGB in [0, 1], shape ``flow.shape[1:] + (3,)``.

    Notes
    -----
    Hue is ``atan2(v_y, v_x) / 2 pi`` (mod 1) in image coordinates (y points down): flow to the right is
    red (hue 0), down is yellow-green (hue 1/4), left is cyan (hue 1/2), up is violet (hue 3/4).
    Saturation is 1; zero flow is black. NaN pixels (the library's "no value here", e.g.
    :func:`~cmax_taichi.dense_flow` where a ray turns behind the camera) are drawn in
    :data:`NO_EVENT_COLOR` grey. :func:`flow_wheel` draws the matching legend.
    """
    from matplotlib.colors import hsv_to_rgb

    flow = np.asarray(flow, dtype=np.float64)
    if flow.shape[0] != 2:
        raise ValueError(f"flow must have shape (2, ...), got {flow.shape}")
    vx, vy = flow[0], flow[1]
    magnitude = np.hypot(vx, vy)
    undefined = np.isnan(magnitude)
    if max_magnitude is None:
        max_magnitude = float(np.max(magnitude[~undefined])) if np.any(~undefined) else 1.0
    max_magnitude = max_magnitude if max_magnitude > 0 else 1.0
    hue = np.mod(np.arctan2(vy, vx) / (2.0 * math.pi), 1.0)
    value = np.clip(magnitude / max_magnitude, 0.0, 1.0)
    hsv = np.stack([hue, np.ones_like(hue), value], axis=-1)
    rgb = hsv_to_rgb(np.nan_to_num(hsv))
    rgb[undefined] = float(NO_EVENT_COLOR)
    return rgb


def flow_wheel(size: int = 101) -> np.ndarray:
    """The legend of :func:`flow_to_rgb`: an RGBA disc (transparent outside), ``(size, size, 4)``.

    A pixel of the disc has the colour of a flow equal to its offset from the centre (y down), scaled
    so that the rim is the full magnitude.
    """
    r = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    flow = np.stack([(xx - r) / r, (yy - r) / r])
    rgba = np.ones((size, size, 4))
    rgba[..., :3] = flow_to_rgb(flow, max_magnitude=1.0)
    rgba[np.hypot(flow[0], flow[1]) > 1.0, 3] = 0.0  # transparent outside the disc
    return rgba


def show_flow(
    ax: Axes,
    flow: np.ndarray,
    *,
    max_magnitude: float | None = None,
    unit: str = "px/s",
    title: str = "Flow",
    wheel: bool = True,
) -> AxesImage:
    """Draw a flow field in colour with a colour-wheel legend in the lower-right corner.

    Parameters
    ----------
    flow : ndarray
        ``(2, H, W)`` flow (x, y components) in ``unit``.
    max_magnitude : float, optional
        Magnitude at full brightness (default the field's largest); shown on the legend. To update in
        place: ``artist.set_data(flow_to_rgb(new, m))`` and ``artist.wheel_axes.title.set_text(...)``.
    unit : str
        Unit of the flow, for the legend.
    title : str
        Axes title.
    wheel : bool
        Add the legend (an inset disc: direction = hue, magnitude = brightness, rim = ``max_magnitude``).

    Returns
    -------
    AxesImage
        The image artist; ``artist.wheel_axes`` is the legend's inset axes (or None).
    """
    flow = np.asarray(flow, dtype=np.float64)
    if max_magnitude is None:
        max_magnitude = float(np.nanmax(np.hypot(flow[0], flow[1])))
    artist = ax.imshow(flow_to_rgb(flow, max_magnitude), interpolation="nearest")
    _label_image_axes(ax, title)
    artist.wheel_axes = None
    artist.max_magnitude = max_magnitude
    if wheel:
        inset = ax.inset_axes([0.74, 0.02, 0.25, 0.25 * ax.bbox.width / max(ax.bbox.height, 1.0)])
        inset.imshow(flow_wheel(), interpolation="bilinear")
        inset.set_xticks([])
        inset.set_yticks([])
        for spine in inset.spines.values():
            spine.set_visible(False)
        inset.set_title(
            f"rim: {_fmt(max_magnitude)} {unit}" if max_magnitude > 0 else "no motion",
            fontsize=7,
            pad=2,
            bbox=dict(facecolor="w", alpha=0.8, lw=0, pad=1),
        )
        artist.wheel_axes = inset
    return artist


# --- regularizer maps ------------------------------------------------------------------------------------
def map_norm(
    values: np.ndarray,
    neutral: float,
    *,
    mask: np.ndarray | None = None,
    limit: float | None = None,
    log: bool = False,
    percentile: float = 99.0,
) -> Normalize:
    """A colour normalisation that puts ``neutral`` exactly at the middle of the colour map.

    Parameters
    ----------
    values : ndarray
        The map.
    neutral : float
        Value of an area-preserving warp (a regularizer's ``neutral``: 0 for divergence, 1 for
        deformation); it maps to 0.5.
    mask : ndarray of bool, optional
        Pixels that count when choosing the range (default all finite pixels).
    limit : float, optional
        Fixed half-range: ``neutral +- limit`` (linear), or the factor ``neutral * limit^(+-1)`` (log).
        Default: the ``percentile`` of the distance from ``neutral`` over the masked pixels.
    log : bool
        Symmetric in ``log(value / neutral)`` (for ratios such as the deformation; ``neutral > 0``).
    """
    from matplotlib.colors import LogNorm, Normalize

    v = np.asarray(values, dtype=np.float64)
    keep = np.isfinite(v) if mask is None else (np.asarray(mask, dtype=bool) & np.isfinite(v))
    if log:
        if not neutral > 0:
            raise ValueError(f"a log colour scale needs a positive neutral value, got {neutral}")
        if limit is None:
            ratios = np.abs(np.log(np.maximum(v[keep], 1e-12) / neutral))
            limit = float(np.exp(np.percentile(ratios, percentile))) if ratios.size else 2.0
        limit = max(float(limit), 1.0 + 1e-3)
        return LogNorm(vmin=neutral / limit, vmax=neutral * limit, clip=True)
    if limit is None:
        dist = np.abs(v[keep] - neutral)
        limit = float(np.percentile(dist, percentile)) if dist.size else 1.0
    limit = float(limit) if limit > 0 else max(abs(neutral), 1.0) * 1e-3
    return Normalize(vmin=neutral - limit, vmax=neutral + limit, clip=True)


def _masked_map(values: np.ndarray, count: np.ndarray | None) -> np.ma.MaskedArray:
    v = np.asarray(values, dtype=np.float64)
    mask = ~np.isfinite(v)
    if count is not None:
        mask |= ~(np.asarray(count) > 0)
    return np.ma.masked_array(v, mask=mask)


def show_map(
    ax: Axes,
    values: np.ndarray,
    *,
    neutral: float = 0.0,
    count: np.ndarray | None = None,
    unit: str = "",
    title: str = "",
    limit: float | None = None,
    log: bool = False,
    cmap: str = "RdBu_r",
    colorbar: bool = True,
) -> AxesImage:
    """Draw a map with a diverging colour map centred on ``neutral`` (white), grey where no event landed.

    Parameters
    ----------
    values : ndarray
        ``(H, W)`` map.
    neutral : float
        Value drawn white (the middle of ``cmap``).
    count : ndarray, optional
        Vote count per pixel; pixels with ``count <= 0`` are drawn grey (the map is undefined there).
        NaN pixels, the library's "no event here" (:meth:`ContrastMaximization.maps`), are drawn grey
        with or without ``count``.
    unit : str
        Unit of the map, for the colour bar ("" = dimensionless).
    title : str
        Axes title.
    limit, log
        Colour range, see :func:`map_norm`.
    cmap : str
        Diverging colour map (red above neutral, blue below by default).
    colorbar : bool
        Add a colour bar.

    Returns
    -------
    AxesImage
        The image artist (update with ``set_data(...)`` and ``set_norm(map_norm(...))``).
    """
    import matplotlib

    data = _masked_map(values, count)
    norm = map_norm(data.filled(np.nan), neutral, mask=~data.mask, limit=limit, log=log)
    colours = matplotlib.colormaps[cmap].with_extremes(bad=NO_EVENT_COLOR)
    artist = ax.imshow(data, cmap=colours, norm=norm, interpolation="nearest")
    _label_image_axes(ax, title)
    if colorbar:
        _colorbar(ax, artist, f"{unit or 'dimensionless'} (white = {neutral:g})")
    ax.text(
        0.01,
        0.01,
        "grey: no events",
        transform=ax.transAxes,
        fontsize=7,
        va="bottom",
        bbox=dict(facecolor="w", alpha=0.7, lw=0, pad=1),
    )
    return artist


def show_regularizer_map(
    ax: Axes,
    maps: Mapping[str, np.ndarray | float],
    name: str,
    *,
    limit: float | None = None,
    log: bool | None = None,
    title: str | None = None,
    colorbar: bool = True,
) -> AxesImage:
    """Draw one regularizer's map from :meth:`ContrastMaximization.maps`, centred on its neutral value.

    Parameters
    ----------
    maps : mapping
        The dict returned by ``prob.maps(theta)`` (needs ``maps[name]``, ``maps["count"]``).
    name : str
        Registered regularizer (``"divergence"``, ``"deformation"``, ...); its ``neutral`` value is white
        and its ``map_unit`` labels the colour bar.
    limit : float, optional
        Colour range, see :func:`map_norm`.
    log : bool, optional
        Log-symmetric colours; default True for ``"deformation"`` (a ratio of areas: 1/2 and 2 are equally
        far from 1), False otherwise.
    title : str, optional
        Default: the map's name and its penalty ``R`` when ``maps`` has it.
    colorbar : bool
        Add a colour bar.
    """
    reg = REGULARIZERS.get(name)
    if log is None:
        log = name == "deformation"
    if title is None:
        title = f"{name} map"
        if "R_" + name in maps:
            title += f" (R = {float(maps['R_' + name]):.3g})"
    return show_map(
        ax,
        np.asarray(maps[name]),
        neutral=reg.neutral,
        count=np.asarray(maps["count"]) if "count" in maps else None,
        unit=reg.map_unit,
        title=title,
        limit=limit,
        log=log,
        colorbar=colorbar,
    )


# --- objective landscapes --------------------------------------------------------------------------------
_SHORT = {"divergence": "Div.", "deformation": "Def."}


def regularizer_variants(
    events: Events,
    weight: float = 1.0,
    names: Sequence[str] = ("divergence", "deformation"),
    *,
    combined: bool = True,
    **problem_kwargs,
) -> dict[str, ContrastMaximization]:
    """The same problem without a regularizer, with each regularizer alone, and with all of them.

    Parameters
    ----------
    events : Events
        The window.
    weight : float
        ``lambda`` of every regularizer (dimensionless when the objective is normalised).
    names : sequence of str
        Registered regularizers to compare.
    combined : bool
        Also add the problem with all ``names`` at once ("Div. + Def." in the paper).
    **problem_kwargs
        Passed to :class:`ContrastMaximization` (``warp=``, ``camera=``, ``objective=``, ...).

    Returns
    -------
    dict
        Legend label -> problem, starting with ``"no regularizer"``.
    """
    from cmax_taichi.pipeline.problem import ContrastMaximization

    variants = {"no regularizer": ContrastMaximization(events, regularizers=None, **problem_kwargs)}
    for name in names:
        label = f"{_SHORT.get(name, name)} (λ={weight:g})"
        variants[label] = ContrastMaximization(events, regularizers={name: weight}, **problem_kwargs)
    if combined and len(names) > 1:
        label = " + ".join(_SHORT.get(n, n) for n in names) + f" (λ={weight:g})"
        variants[label] = ContrastMaximization(
            events, regularizers={n: weight for n in names}, **problem_kwargs
        )
    return variants


def _base_theta(prob: ContrastMaximization, theta) -> np.ndarray:
    if theta is None:
        return np.zeros(prob.model.n_params)
    return np.asarray(theta, dtype=np.float64).reshape(-1).copy()


def landscape_1d(
    problems: ContrastMaximization | Mapping[str, ContrastMaximization],
    index: int,
    values: Sequence[float] | np.ndarray,
    theta=None,
) -> dict[str, np.ndarray] | np.ndarray:
    """The objective ``J`` (``prob.value``) along one parameter, the others held at ``theta``.

    Parameters
    ----------
    problems : ContrastMaximization or mapping of label -> problem
        One problem, or several (e.g. :func:`regularizer_variants`).
    index : int
        Which parameter varies.
    values : array_like
        Its values, in the model's units.
    theta : array_like, optional
        The other parameters (default 0).

    Returns
    -------
    ndarray or dict
        ``J`` at each value (one problem), or label -> ``J`` (several).
    """
    values = np.asarray(values, dtype=np.float64)
    single = not isinstance(problems, Mapping)
    items = {"": problems} if single else problems
    curves = {}
    for label, prob in items.items():
        th = _base_theta(prob, theta)
        curve = np.empty(values.size)
        for k, v in enumerate(values):
            th[index] = v
            curve[k] = prob.value(th)
        curves[label] = curve
    return curves[""] if single else curves


def landscape_2d(
    prob: ContrastMaximization,
    indices: tuple[int, int],
    values_x: Sequence[float] | np.ndarray,
    values_y: Sequence[float] | np.ndarray,
    theta=None,
) -> np.ndarray:
    """The objective ``J`` (``prob.value``) over a grid of two parameters, the others held at ``theta``.

    Parameters
    ----------
    prob : ContrastMaximization
        The problem.
    indices : (int, int)
        The parameters on the x and y axes of the grid.
    values_x, values_y : array_like
        Their values (model units).
    theta : array_like, optional
        The other parameters (default 0).

    Returns
    -------
    ndarray
        ``J``, shape ``(len(values_y), len(values_x))`` (row = y value), ready for :func:`plot_landscape_2d`.
    """
    i, j = indices
    if i == j:
        raise ValueError("landscape_2d needs two different parameters")
    values_x = np.asarray(values_x, dtype=np.float64)
    values_y = np.asarray(values_y, dtype=np.float64)
    th = _base_theta(prob, theta)
    grid = np.empty((values_y.size, values_x.size))
    for r, vy in enumerate(values_y):
        th[j] = vy
        for c, vx in enumerate(values_x):
            th[i] = vx
            grid[r, c] = prob.value(th)
    return grid


def plot_landscape_1d(
    ax: Axes,
    values: Sequence[float] | np.ndarray,
    curves: Mapping[str, np.ndarray] | np.ndarray,
    *,
    xlabel: str,
    ylabel: str = "J (normalized: G / G(0) - Σ λR)",
    title: str = "Objective along one parameter",
    current: float | None = None,
    truth: float | None = None,
    mark_maxima: bool = True,
    legend_outside: bool = False,
) -> dict:
    """Draw objective curves over one parameter.

    Parameters
    ----------
    values : array_like
        Parameter values (x axis).
    curves : ndarray or mapping label -> ndarray
        ``J`` per value (one curve, or one per label, e.g. from :func:`landscape_1d`).
    xlabel, ylabel, title : str
        Labels (put the unit in ``xlabel``, e.g. :func:`param_label`).
    current : float, optional
        Draw a vertical line at the current value.
    truth : float, optional
        Draw a dashed vertical line at the ground truth.
    mark_maxima : bool
        Mark each curve's maximum with a dot of the curve's colour.
    legend_outside : bool
        Put the legend to the right of the axes (leave room for it) rather than over the curves.

    Returns
    -------
    dict
        ``"lines"`` (label -> Line2D), ``"current"`` (the vertical line or None), ``"maxima"``.
    """
    values = np.asarray(values, dtype=np.float64)
    if not isinstance(curves, Mapping):
        curves = {"J": np.asarray(curves)}
    lines, maxima = {}, {}
    finite = []
    for label, curve in curves.items():
        curve = np.asarray(curve, dtype=np.float64)
        (line,) = ax.plot(values, curve, lw=1.6, label=label)
        lines[label] = line
        if mark_maxima and np.any(np.isfinite(curve)):
            k = int(np.nanargmax(curve))
            (maxima[label],) = ax.plot(values[k], curve[k], "o", color=line.get_color(), ms=5)
        finite.append(curve[np.isfinite(curve)])
    # Regularized curves can plunge far below 0 near collapse; keep the interesting range visible.
    allv = np.concatenate(finite) if finite else np.array([0.0, 1.0])
    top = float(allv.max()) if allv.size else 1.0
    bottom = max(float(allv.min()), -0.5 * abs(top) - 1.0) if allv.size else 0.0
    pad = 0.05 * max(top - bottom, 1e-9)
    ax.set_ylim(bottom - pad, top + pad)
    handles = {"lines": lines, "maxima": maxima, "current": None}
    if truth is not None:
        ax.axvline(truth, color="k", ls="--", lw=1.0, label="ground truth")
    if current is not None:
        handles["current"] = ax.axvline(current, color="0.3", lw=1.2, label="current")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if legend_outside:
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    else:
        ax.legend(fontsize=7, loc="best")
    return handles


def plot_landscape_2d(
    ax: Axes,
    values_x: Sequence[float] | np.ndarray,
    values_y: Sequence[float] | np.ndarray,
    grid: np.ndarray,
    *,
    xlabel: str,
    ylabel: str,
    title: str = "Objective landscape",
    current: Sequence[float] | None = None,
    truth: Sequence[float] | None = None,
    path: np.ndarray | None = None,
    colorbar_label: str = "J (normalized)",
    cmap: str = "viridis",
    colorbar: bool = True,
) -> AxesImage:
    """Draw ``J`` over two parameters as a heat map (from :func:`landscape_2d`).

    Parameters
    ----------
    values_x, values_y : array_like
        Grid values (evenly spaced), model units.
    grid : ndarray
        ``(len(values_y), len(values_x))``.
    xlabel, ylabel, title : str
        Labels with units.
    current : (float, float), optional
        A point to mark (white cross).
    truth : (float, float), optional
        Ground truth (white star).
    path : ndarray, optional
        ``(n, 2)`` optimizer path in the same two parameters, drawn as a line with dots.
    colorbar_label, cmap, colorbar
        Colour bar options.
    """
    vx = np.asarray(values_x, dtype=np.float64)
    vy = np.asarray(values_y, dtype=np.float64)
    dx = (vx[-1] - vx[0]) / max(vx.size - 1, 1) / 2.0
    dy = (vy[-1] - vy[0]) / max(vy.size - 1, 1) / 2.0
    extent = (vx[0] - dx, vx[-1] + dx, vy[0] - dy, vy[-1] + dy)
    artist = ax.imshow(grid, origin="lower", extent=extent, aspect="auto", cmap=cmap, interpolation="nearest")
    if path is not None and len(path):
        path = np.asarray(path, dtype=np.float64)
        ax.plot(path[:, 0], path[:, 1], "-", color="w", lw=1.2, alpha=0.9)
        ax.plot(path[:, 0], path[:, 1], ".", color="tab:red", ms=4, label="optimizer path")
        ax.plot(path[-1, 0], path[-1, 1], "o", mfc="none", mec="tab:red", ms=9, mew=1.5, label="estimate")
    if truth is not None:
        ax.plot(truth[0], truth[1], "*", color="w", mec="k", ms=13, label="ground truth")
    if current is not None:
        ax.plot(current[0], current[1], "x", color="w", ms=9, mew=2, label="current")
    k = np.unravel_index(int(np.nanargmax(grid)), grid.shape)
    ax.plot(vx[k[1]], vy[k[0]], "+", color="tab:orange", ms=11, mew=2, label="grid maximum")
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=7, loc="upper right", framealpha=0.7)
    if colorbar:
        _colorbar(ax, artist, colorbar_label)
    return artist
