"""The grid of a dense flow: nodes over the sensor, bilinear interpolation, coarse-to-fine refinement.

A :class:`FlowGrid` of ``nx x ny`` cells spans the sensor: node ``(i, j)`` sits at
``(i sx, j sy)`` px with ``sx = (W - 1) / nx``, ``sy = (H - 1) / ny``, so the corner nodes are the corner
pixel centres. The flow between nodes is the bilinear interpolant of the four nodes of a cell
(docs/FORMULAS.md, "Dense flow model"). Node values are arrays of shape ``(ny + 1, nx + 1, 2)`` (row
``j``, column ``i``, x then y component), in px/s.

Refining a grid halves its cells (``2 nx x 2 ny``); the refined grid holds the same interpolant
exactly (:meth:`FlowGrid.prolong`), so a coarse-to-fine run starts each level where the last ended.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["FlowBeyondSensorError", "FlowGrid", "auto_padding", "check_padded_sensor", "grid_for_cell_size"]


class FlowBeyondSensorError(ValueError):
    """A displacement asked over an interval that carries the flow beyond the sensor."""


def _halvings(n: int) -> int:
    """How many times ``n`` halves into whole numbers (its factors of 2)."""
    return (int(n) & -int(n)).bit_length() - 1


@dataclass(frozen=True)
class FlowGrid:
    """Nodes of a dense flow over a ``width x height`` sensor.

    Parameters
    ----------
    width, height : int
        Sensor size, px (at least 2 each).
    nx, ny : int
        Cells along x and y (at least 1 each); the grid has ``(nx + 1) (ny + 1)`` nodes.
    """

    width: int
    height: int
    nx: int
    ny: int

    def __post_init__(self) -> None:
        for name in ("width", "height", "nx", "ny"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"FlowGrid {name} must be an integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        if self.width < 2 or self.height < 2:
            raise ValueError(f"a flow grid needs a sensor of at least 2x2 px, got {self.width}x{self.height}")
        if self.nx < 1 or self.ny < 1:
            raise ValueError(f"a flow grid needs at least 1x1 cells, got {self.nx}x{self.ny}")
        if self.nx > self.width - 1 or self.ny > self.height - 1:
            raise ValueError(
                f"{self.nx}x{self.ny} cells are finer than the pixels of a {self.width}x{self.height} "
                f"sensor (at most {self.width - 1}x{self.height - 1})"
            )

    # --- shape ---------------------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        """Shape of a node array: ``(ny + 1, nx + 1, 2)``."""
        return (self.ny + 1, self.nx + 1, 2)

    @property
    def n_nodes(self) -> int:
        return (self.nx + 1) * (self.ny + 1)

    @property
    def n_params(self) -> int:
        """Parameters of a flow on this grid (two per node)."""
        return 2 * self.n_nodes

    @property
    def spacing(self) -> tuple[float, float]:
        """``(sx, sy)``: node spacing, px."""
        return ((self.width - 1) / self.nx, (self.height - 1) / self.ny)

    def node_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """``(X, Y)``, each ``(ny + 1, nx + 1)``: node positions, px."""
        sx, sy = self.spacing
        return np.meshgrid(np.arange(self.nx + 1) * sx, np.arange(self.ny + 1) * sy)

    def check_nodes(self, nodes, name: str = "nodes") -> np.ndarray:
        """``nodes`` as a float64 array of :attr:`shape` (a flat array of :attr:`n_params` values is
        reshaped); ValueError naming ``name`` for another size or non-finite values."""
        try:
            arr = np.asarray(nodes, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"{name} must be an array of numbers of shape {self.shape}") from None
        if arr.size != self.n_params:
            raise ValueError(
                f"{name} has {arr.size} values ({arr.shape}); a {self.nx}x{self.ny}-cell grid takes "
                f"{self.n_params} (shape {self.shape})"
            )
        arr = arr.reshape(self.shape)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} has non-finite values")
        return arr

    # --- coarse to fine -------------------------------------------------------------------------------
    def refined(self) -> FlowGrid:
        """The grid with every cell split in four (``2 nx x 2 ny`` cells)."""
        return FlowGrid(self.width, self.height, 2 * self.nx, 2 * self.ny)

    def prolong(self, nodes) -> np.ndarray:
        """The node values on :meth:`refined` that give exactly the same interpolant."""
        U = self.check_nodes(nodes)
        out = np.zeros((2 * self.ny + 1, 2 * self.nx + 1, 2))
        out[::2, ::2] = U
        out[::2, 1::2] = 0.5 * (U[:, :-1] + U[:, 1:])
        out[1::2, ::2] = 0.5 * (U[:-1] + U[1:])
        out[1::2, 1::2] = 0.25 * (U[:-1, :-1] + U[:-1, 1:] + U[1:, :-1] + U[1:, 1:])
        return out

    def pyramid(self, levels: int) -> list[FlowGrid]:
        """The ``levels`` grids of a coarse-to-fine run ending at this one (coarsest first); ValueError
        when the cells do not halve that often."""
        if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or levels < 1:
            raise ValueError(f"levels must be an integer >= 1, got {levels!r}")
        most = 1 + min(_halvings(self.nx), _halvings(self.ny))
        if levels > most:  # 2^(levels - 1) is not computed: levels may be huge
            multiple = f"{2 ** (levels - 1)}" if levels <= 21 else f"2^{levels - 1}"
            raise ValueError(
                f"{levels} levels halve the cells {levels - 1} times: the finest grid's {self.nx}x{self.ny} "
                f"cells allow at most {most} level(s); use fewer levels, or cells that are multiples of "
                f"{multiple}"
            )
        return [
            FlowGrid(self.width, self.height, self.nx // 2**k, self.ny // 2**k)
            for k in range(levels - 1, -1, -1)
        ]

    # --- interpolation --------------------------------------------------------------------------------
    def _cells(self, x, y):
        sx, sy = self.spacing
        fx = np.asarray(x, dtype=np.float64) / sx
        fy = np.asarray(y, dtype=np.float64) / sy
        i = np.clip(np.floor(fx), 0, self.nx - 1).astype(np.int64)
        j = np.clip(np.floor(fy), 0, self.ny - 1).astype(np.int64)
        return i, j, fx - i, fy - j

    def interpolate(self, nodes, x, y) -> np.ndarray:
        """The flow at positions ``(x, y)`` (px), ``(2,) + x.shape``, in the units of ``nodes``."""
        U = self.check_nodes(nodes)
        i, j, a, b = self._cells(x, y)
        return np.moveaxis(
            (1 - a)[..., None] * (1 - b)[..., None] * U[j, i]
            + a[..., None] * (1 - b)[..., None] * U[j, i + 1]
            + (1 - a)[..., None] * b[..., None] * U[j + 1, i]
            + a[..., None] * b[..., None] * U[j + 1, i + 1],
            -1,
            0,
        )

    def derivatives(self, nodes, x, y) -> tuple[np.ndarray, np.ndarray]:
        """``(du/dx, du/dy)`` of the interpolant at ``(x, y)``, each ``(2,) + x.shape`` (units of
        ``nodes`` per px)."""
        U = self.check_nodes(nodes)
        i, j, a, b = self._cells(x, y)
        sx, sy = self.spacing
        a, b = a[..., None], b[..., None]
        du_dx = ((1 - b) * (U[j, i + 1] - U[j, i]) + b * (U[j + 1, i + 1] - U[j + 1, i])) / sx
        du_dy = ((1 - a) * (U[j + 1, i] - U[j, i]) + a * (U[j + 1, i + 1] - U[j, i + 1])) / sy
        return np.moveaxis(du_dx, -1, 0), np.moveaxis(du_dy, -1, 0)

    def dense(self, nodes) -> np.ndarray:
        """The interpolant on every pixel centre: ``(2, H, W)``, units of ``nodes``."""
        yy, xx = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return self.interpolate(nodes, xx, yy)

    def trajectories(self, nodes, dt: float, max_step_px: float = 8.0) -> np.ndarray:
        """The displacement over ``dt`` (s) of the point at every pixel centre that moves with the flow
        (px/s), ``(2, H, W)`` px: ``dx/dt = u(x)`` integrated along its path (RK4, steps of at most
        ``max_step_px`` of motion), the field held fixed over ``dt``; where a path leaves the sensor it
        takes the velocity of the nearest point of the sensor.

        ``dt u(x)`` (the straight line at the start's velocity) differs from it by about
        ``dt^2 / 2 (Du) u`` wherever the flow varies: 0.2 px on the simulator's ``room`` window,
        whose ground truth (MVSEC's convention too) is the displacement of the scene point seen at
        each pixel at the start.

        FlowBeyondSensorError (a ValueError), before any step, when the flow over ``dt`` would carry
        points farther than the sensor's diagonal: the integration's cost grows with that distance,
        and past it every path has left the sensor (e.g. the flow of a window of a microsecond
        extrapolated over 50 ms)."""
        U = self.check_nodes(nodes)
        dt = float(dt)
        speed = float(np.abs(U).max(initial=0.0))
        peak = speed * abs(dt)
        reach = math.hypot(self.width, self.height)
        if not peak <= reach:  # the work grows with the reach: bounded by the sensor's diagonal
            raise FlowBeyondSensorError(
                f"the flow over dt = {dt:g} s moves points by up to {peak:.3g} px (peak {speed:.3g} px/s), "
                f"beyond the {self.width}x{self.height} sensor (diagonal {reach:.0f} px): the displacement "
                "is not defined that far (every path leaves the sensor); choose a shorter dt"
            )
        steps = max(1, math.ceil(peak / max_step_px))
        h = dt / steps
        yy, xx = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        x, y = xx.copy(), yy.copy()
        ux, uy = U[..., 0].ravel(), U[..., 1].ravel()
        row = self.nx + 1

        def velocity(px, py):  # interpolate() on flat node indices: a window's flow in ~10 ms
            i, j, a, b = self._cells(np.clip(px, 0, self.width - 1), np.clip(py, 0, self.height - 1))
            k = j * row + i
            w00, w10, w01, w11 = (1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b
            return tuple(
                w00 * c.take(k) + w10 * c.take(k + 1) + w01 * c.take(k + row) + w11 * c.take(k + row + 1)
                for c in (ux, uy)
            )

        for _ in range(steps):
            k1 = velocity(x, y)
            k2 = velocity(x + h / 2 * k1[0], y + h / 2 * k1[1])
            k3 = velocity(x + h / 2 * k2[0], y + h / 2 * k2[1])
            k4 = velocity(x + h * k3[0], y + h * k3[1])
            x = x + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            y = y + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        return np.stack([x - xx, y - yy])

    def fit(self, flow) -> np.ndarray:
        """Node values whose interpolant is closest (least squares over the finite pixels) to a dense
        ``(2, H, W)`` flow of this sensor: e.g. a previous window's flow on another grid."""
        flow = np.asarray(flow, dtype=np.float64)
        if flow.shape != (2, self.height, self.width):
            raise ValueError(f"flow must have shape (2, {self.height}, {self.width}), got {flow.shape}")
        from scipy.sparse import coo_matrix
        from scipy.sparse.linalg import lsqr

        yy, xx = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        ok = np.all(np.isfinite(flow), axis=0)
        i, j, a, b = self._cells(xx[ok], yy[ok])
        n = np.count_nonzero(ok)
        stride = self.nx + 1
        cols = np.concatenate(
            [j * stride + i, j * stride + i + 1, (j + 1) * stride + i, (j + 1) * stride + i + 1]
        )
        vals = np.concatenate([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b])
        rows = np.tile(np.arange(n), 4)
        A = coo_matrix((vals, (rows, cols)), shape=(n, self.n_nodes)).tocsr()
        out = np.zeros((self.n_nodes, 2))
        for c in range(2):
            if n:
                # damp: nodes without a finite pixel nearby stay near 0 instead of being undetermined
                out[:, c] = lsqr(A, flow[c][ok], damp=1e-6, atol=1e-12, btol=1e-12)[0]
        return out.reshape(self.shape)


def grid_for_cell_size(sensor_size: tuple[int, int], cell_px: float, levels: int = 1) -> FlowGrid:
    """The grid whose cells are closest to ``cell_px`` px wide and high, with cell counts that halve
    ``levels - 1`` times (multiples of ``2 ** (levels - 1)``)."""
    W, H = (int(v) for v in sensor_size)
    if not (isinstance(cell_px, (int, float)) and math.isfinite(cell_px) and cell_px > 0):
        raise ValueError(f"cell size must be a positive number of px, got {cell_px!r}")
    step = 2 ** (int(levels) - 1)
    nx = max(step, step * round((W - 1) / cell_px / step))
    ny = max(step, step * round((H - 1) / cell_px / step))
    return FlowGrid(W, H, nx, ny)


def auto_padding(sensor_size: tuple[int, int], share: float) -> int:
    """The automatic margin of a dense flow's IWE, px: ``share`` of the larger sensor side, less where
    the padded image would exceed ``max_sensor_pixels`` (:func:`cmax_taichi.get_limits`), so that every
    sensor within the limit (4096 x 4096 by default) can be estimated without choosing a padding."""
    from cmax_taichi.core.limits import get_limits

    W, H = (int(v) for v in sensor_size)
    pad = round(share * max(W, H))
    limit = get_limits().max_sensor_pixels
    if (W + 2 * pad) * (H + 2 * pad) > limit:  # the largest p with (W + 2p)(H + 2p) <= limit
        pad = max(0, math.floor((-(W + H) + math.sqrt((W - H) ** 2 + 4 * limit)) / 4))
        while pad > 0 and (W + 2 * pad) * (H + 2 * pad) > limit:  # rounding of the square root
            pad -= 1
    return pad


def check_padded_sensor(sensor_size: tuple[int, int], padding: int, option: str = "padding") -> None:
    """ValueError, naming the sensor and the margin, when the IWE of a dense flow (the sensor with
    ``padding`` px on every side) exceeds ``max_sensor_pixels``: checked before any work."""
    from cmax_taichi.core.limits import ENV_VARS, get_limits

    width, height = (int(v) for v in sensor_size)
    limit = get_limits().max_sensor_pixels
    how = "raise the limit with cmax_taichi.set_limits(max_sensor_pixels=...) or "
    how += ENV_VARS["max_sensor_pixels"]
    if width * height > limit:
        raise ValueError(
            f"the {width}x{height} sensor ({width * height:,} px) exceeds max_sensor_pixels = {limit:,}: "
            + how
        )
    padded_w, padded_h = width + 2 * padding, height + 2 * padding
    if padded_w * padded_h > limit:
        raise ValueError(
            f"the {width}x{height} sensor with a margin of {padding} px on every side ({option}) makes an "
            f"image of {padded_w}x{padded_h} = {padded_w * padded_h:,} pixels, above max_sensor_pixels = "
            f"{limit:,}: choose a {option} of at most {auto_padding((width, height), 1.0)} px, or {how}"
        )
