"""Collapse explorer: drag the warp parameters and watch event collapse happen, and the regularizers stop it.

Shows, live, the image of warped events (IWE), the flow the warp implies, the divergence and deformation
maps, and the objective J along one parameter without a regularizer, with each regularizer and with both
(the current value marked). "Optimize" runs the optimizer from the current point on the chosen objective
and animates its path.

    python demos/collapse_explorer.py                      # 1-DOF zoom, interactive window
    python demos/collapse_explorer.py --warp mitrokhin4    # 4-DOF model
    python demos/collapse_explorer.py --save out.png       # headless picture

Data: the MVSEC indoor_flying1 cut in ../shared/data when present, else a synthetic forward motion.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np

if __package__ in (None, ""):  # run as a script: make the sibling _common importable
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))

import _common

import cmax_taichi as cm
from cmax_taichi import viz

WARPS = ("zoom1", "mitrokhin4")


def parameter_ranges(warp: str, duration: float, width: int) -> np.ndarray:
    """Slider ranges ``(n, 2)`` scaled by the window duration T: collapse of zoom sits at h_z ~ 1/T."""
    if warp == "zoom1":
        return np.array([[-1.5 / duration, 2.5 / duration]])
    translation = 0.25 * width / duration  # a quarter of the sensor over the window, px/s
    return np.array(
        [
            [-translation, translation],
            [-translation, translation],
            [-1.5 / duration, 2.5 / duration],
            [-1.0 / duration, 1.0 / duration],
        ]
    )


class Explorer:
    """The figure, its artists and the callbacks that keep them in sync with ``theta``."""

    def __init__(self, scene: _common.Scene, warp: str, lam: float, samples: int, interactive: bool):
        import matplotlib.pyplot as plt

        self.scene = scene
        self.interactive = interactive
        self.samples = samples
        kwargs = dict(warp=warp, camera=scene.camera)
        self.problems = viz.regularizer_variants(scene.events, weight=lam, **kwargs)
        self.labels = list(self.problems)
        self.base = self.problems["no regularizer"]
        self.model = self.base.model
        self.n = self.model.n_params
        self.ranges = parameter_ranges(warp, self.base.duration, self.base.width)
        self.truth = scene.truth
        if scene.truth is not None and warp == "mitrokhin4" and scene.truth.size == 1:
            self.truth = np.array([0.0, 0.0, scene.truth[0], 0.0])
        self.theta = np.zeros(self.n)
        self.curve_index = 2 if warp == "mitrokhin4" else 0  # h_z: the collapsing parameter
        self.curve_stale = True
        self.path_artists: list = []
        self._animation = None
        self._batch = False
        self._color_limits()

        self.fig = plt.figure(figsize=(15, 9.2 if self.n > 1 or interactive else 8.4))
        bottom = 0.11 + 0.035 * self.n
        if interactive:  # room for the radio buttons under the plots
            bottom = max(bottom, 0.27)
        grid = self.fig.add_gridspec(
            2, 3, left=0.05, right=0.95, top=0.91, bottom=bottom, hspace=0.38, wspace=0.42
        )
        self.ax_iwe = self.fig.add_subplot(grid[0, 0])
        self.ax_div = self.fig.add_subplot(grid[0, 1])
        self.ax_def = self.fig.add_subplot(grid[0, 2])
        self.ax_flow = self.fig.add_subplot(grid[1, 0])
        self.ax_curve = self.fig.add_subplot(grid[1, 1:])
        box = self.ax_curve.get_position()  # room on the right for the legend
        self.ax_curve.set_position([box.x0, box.y0, box.width - 0.14, box.height])
        self._build_images()
        self._build_widgets(bottom)

    # --- set-up ---------------------------------------------------------------------------------------------
    def _color_limits(self) -> None:
        """Fixed colour ranges over the whole slider box, so that colours compare across positions."""
        div, dfm = 1e-9, 1.0 + 1e-3
        for i in range(self.n):
            for end in self.ranges[i]:
                th = np.zeros(self.n)
                th[i] = end
                maps = self.base.maps(th)
                hit = maps["count"] > 0
                div = max(div, float(np.percentile(np.abs(maps["divergence"][hit]), 99)))
                ratio = np.abs(np.log(np.maximum(maps["deformation"][hit], 1e-3)))
                dfm = max(dfm, float(np.exp(np.percentile(ratio, 99))))
        self.div_limit, self.def_limit = div, min(dfm, 10.0)  # beyond 10x the colours saturate

    def _build_images(self) -> None:
        th = self.theta
        maps = self.base.maps(th)
        self.im_iwe = viz.show_iwe(self.ax_iwe, self.base.iwe(th))
        self.im_div = viz.show_regularizer_map(self.ax_div, maps, "divergence", limit=self.div_limit)
        self.im_def = viz.show_regularizer_map(self.ax_def, maps, "deformation", limit=self.def_limit)
        self.im_flow = viz.show_flow(
            self.ax_flow, self.base.dense_flow(th), title="Flow of the warp (black: 0)"
        )

    def _build_widgets(self, bottom: float) -> None:
        from matplotlib.widgets import Button, RadioButtons, Slider

        self.sliders = []
        for i in range(self.n):
            ax = self.fig.add_axes([0.12, bottom - 0.085 - 0.035 * i, 0.45, 0.022])
            lo, hi = self.ranges[i]
            slider = Slider(ax, viz.param_label(self.model, i), lo, hi, valinit=0.0)
            slider.on_changed(self._on_slider)
            self.sliders.append(slider)
        if not self.interactive:
            return
        ax_radio = self.fig.add_axes([0.63, 0.01, 0.17, bottom - 0.12])
        ax_radio.set_title("optimize", fontsize=8)
        self.radio = RadioButtons(ax_radio, self.labels, active=len(self.labels) - 1)
        for text in self.radio.labels:
            text.set_fontsize(8)
        self.button = Button(self.fig.add_axes([0.82, bottom - 0.1, 0.07, 0.04]), "Optimize")
        self.button.on_clicked(lambda _event: self.optimize(self.radio.value_selected))
        self.reset = Button(self.fig.add_axes([0.9, bottom - 0.1, 0.06, 0.04]), "Reset")
        self.reset.on_clicked(lambda _event: self.set_theta(np.zeros(self.n)))
        if self.n > 1:
            ax_pick = self.fig.add_axes([0.82, 0.01, 0.14, bottom - 0.14])
            ax_pick.set_title("curve over", fontsize=8)
            self.pick = RadioButtons(ax_pick, list(self.model.params), active=self.curve_index)
            self.pick.on_clicked(self._on_pick)
        # Curves through the current point are recomputed when the mouse is released, not while dragging.
        self.fig.canvas.mpl_connect("button_release_event", lambda _event: self.refresh_curve())

    # --- callbacks ------------------------------------------------------------------------------------------
    def _on_slider(self, _value) -> None:
        if self._batch:
            return
        new = np.array([s.val for s in self.sliders])
        others = np.arange(self.n) != self.curve_index
        if np.any(new[others] != self.theta[others]):
            self.curve_stale = True
        self.theta = new
        self.update_images()
        if not self.curve_stale:
            self.update_marks()
        self.fig.canvas.draw_idle()

    def _on_pick(self, label: str) -> None:
        self.curve_index = list(self.model.params).index(label)
        self.curve_stale = True
        self.refresh_curve()

    def set_theta(self, theta: np.ndarray) -> None:
        """Move the sliders (which redraws) to ``theta``, clipped to the slider ranges."""
        theta = np.clip(theta, self.ranges[:, 0], self.ranges[:, 1])
        self._batch = True  # one update and one redraw for all sliders, not one per slider
        try:
            for s, v in zip(self.sliders, theta, strict=True):
                s.drawon = False
                s.set_val(float(v))
        finally:
            self._batch = False
            for s in self.sliders:
                s.drawon = True
        self._on_slider(None)

    # --- drawing --------------------------------------------------------------------------------------------
    def update_images(self) -> None:
        th = self.theta
        image = self.base.iwe(th)
        self.im_iwe.set_data(image)
        self.im_iwe.set_clim(*viz.iwe_limits(image))
        g = self.base.value(th)  # the problem without regularizer: J = G / G(0)
        self.ax_iwe.set_title(f"IWE (G / G(0) = {g:.3g})")
        maps = self.base.maps(th)
        for name, artist, ax in (
            ("divergence", self.im_div, self.ax_div),
            ("deformation", self.im_def, self.ax_def),
        ):
            artist.set_data(np.ma.masked_array(maps[name], mask=~(maps["count"] > 0)))
            ax.set_title(f"{name} map (R = {maps['R_' + name]:.3g})")
        # Flow brightness is scaled per frame (the legend's rim says to what): a fixed scale over the
        # slider box would leave every moderate flow black.
        flow = self.base.dense_flow(th)
        rim = float(np.hypot(flow[0], flow[1]).max())
        self.im_flow.set_data(viz.flow_to_rgb(flow, rim))
        label = f"rim: {rim:.3g} px/s" if rim < 100 else f"rim: {rim:.0f} px/s"
        self.im_flow.wheel_axes.title.set_text(label if rim > 1e-9 else "no motion")

    def refresh_curve(self) -> None:
        if not self.curve_stale:
            return
        i = self.curve_index
        self.values = np.linspace(*self.ranges[i], self.samples)
        curves = viz.landscape_1d(self.problems, i, self.values, self.theta)
        self.ax_curve.clear()
        truth = None if self.truth is None else float(self.truth[i])
        self.curve_handles = viz.plot_landscape_1d(
            self.ax_curve,
            self.values,
            curves,
            xlabel=viz.param_label(self.model, i),
            title=self._curve_title(),
            current=float(self.theta[i]),
            truth=truth,
            legend_outside=True,
        )
        self.current_marks = {
            label: self.ax_curve.plot([], [], "s", mfc="w", mec=line.get_color(), ms=7, mew=1.5)[0]
            for label, line in self.curve_handles["lines"].items()
        }
        self.path_artists = []
        self.curve_stale = False
        self.update_marks()
        self.fig.canvas.draw_idle()

    def _curve_title(self) -> str:
        name = self.model.params[self.curve_index]
        if self.n == 1:
            return f"Objective J along {name} (dots: maxima, squares: current)"
        return f"Objective J along {name}, other parameters at their slider values (dots: maxima)"

    def update_marks(self) -> None:
        """Move the 'current' line and the per-curve squares to the current parameter."""
        i = self.curve_index
        self.curve_handles["current"].set_xdata([self.theta[i], self.theta[i]])
        for label, prob in self.problems.items():
            self.current_marks[label].set_data([self.theta[i]], [prob.value(self.theta)])

    def optimize(self, label: str):
        """Run the optimizer on objective ``label`` from the current point; draw (and animate) its path."""
        result = _common.run_optimizer(self.problems[label], self.theta.copy())
        path, values = _common.optimizer_path(result)
        summary = ", ".join(f"{p} = {v:.3g}" for p, v in zip(self.model.params, result.theta, strict=True))
        self.fig.suptitle(
            f"{self._suptitle()}\noptimizer on '{label}' ({len(path) - 1} iterations): {summary}", fontsize=10
        )
        if self.interactive:
            self._animate(path, lambda: self._draw_path(label, path, values))
        else:
            self.set_theta(result.theta)
            self.refresh_curve()
            self._draw_path(label, path, values)
        return result

    def _draw_path(self, label: str, path: np.ndarray, values: np.ndarray) -> None:
        """The optimizer's path projected on the curve's parameter (J of the optimized objective)."""
        for artist in self.path_artists:
            artist.remove()
        color = self.curve_handles["lines"][label].get_color()
        i = self.curve_index
        self.path_artists = self.ax_curve.plot(
            path[:, i], values, ".-", color=color, lw=0.8, ms=4, alpha=0.8, label=f"optimizer path ({label})"
        )
        self.path_artists += self.ax_curve.plot(
            path[0, i], values[0], "o", mfc="none", mec=color, ms=10, label="start"
        )
        self.path_artists += self.ax_curve.plot(
            path[-1, i], values[-1], "*", color=color, mec="k", ms=14, label="estimate"
        )
        self.ax_curve.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
        self.fig.canvas.draw_idle()

    def _animate(self, path: np.ndarray, done) -> None:
        """Step the sliders along the optimizer's path (about 20 frames), then call ``done``."""
        frames = np.vstack([path[:: int(np.ceil(len(path) / 20))], path[-1:]])  # ~20 redraws
        timer = self.fig.canvas.new_timer(interval=50)
        state = {"k": 0}

        def step():
            if state["k"] >= len(frames):
                timer.stop()
                self.refresh_curve()
                done()
                return
            self.set_theta(frames[state["k"]])
            state["k"] += 1

        timer.add_callback(step)
        timer.start()
        self._animation = timer  # keep a reference, or the timer is garbage-collected

    def _suptitle(self) -> str:
        return f"Event collapse explorer: {self.scene.name}, warp {self.model.name}"

    def draw(self, theta: np.ndarray) -> None:
        self.fig.suptitle(self._suptitle(), fontsize=11)
        self.set_theta(theta)
        self.curve_stale = True
        self.refresh_curve()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--warp", choices=WARPS, default="zoom1", help="motion model (default zoom1)")
    parser.add_argument("--theta", type=float, nargs="+", help="initial parameters (model units), default 0")
    parser.add_argument("--lam", type=float, default=5.0, help="weight λ of each regularizer (default 5)")
    parser.add_argument("--samples", type=int, default=0, help="points per objective curve (default 81 / 41)")
    parser.add_argument(
        "--synthetic", action="store_true", help="use the synthetic scene even if MVSEC is present"
    )
    parser.add_argument(
        "--optimize",
        metavar="OBJECTIVE",
        choices=("none", "divergence", "deformation", "both"),
        help="run the optimizer from --theta on this objective and draw its path (headless too)",
    )
    _common.add_save_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args, interactive = _common.start(build_parser(), argv, "collapse_explorer")
    if args is None:
        return 2
    scene = None if args.synthetic else _common.load_mvsec()
    if scene is None:
        scene = _common.synthetic_zoom()
    _common.subsample_scene(scene, args.max_events)
    n_params = cm.get_warp(args.warp).n_params
    theta = np.zeros(n_params) if args.theta is None else np.asarray(args.theta, dtype=np.float64)
    if theta.size != n_params:
        raise SystemExit(f"--theta needs {n_params} value(s) for {args.warp}, got {theta.size}")
    samples = args.samples or (81 if n_params == 1 else 41)

    explorer = Explorer(scene, args.warp, args.lam, samples, interactive)
    explorer.draw(theta)
    if args.optimize:
        label = {"none": 0, "divergence": 1, "deformation": 2, "both": 3}[args.optimize]
        explorer.optimize(explorer.labels[label])
    return _common.show_or_save(explorer.fig, args)


if __name__ == "__main__":
    sys.exit(main())
