"""Rotation estimation: 3-DOF angular velocity of an event camera by CMax, against the IMU gyro.

Shows the image of warped events (IWE) before (identity warp) and after (the estimate), and at the gyro
value; the estimate against the gyro per axis; the optimizer's trajectory over its iterations; and the
objective landscape over the two axes of largest rotation with the optimizer's path.

    python demos/rotation_estimation.py                                  # boxes_rotation, window
    python demos/rotation_estimation.py --sequence dynamic_rotation
    python demos/rotation_estimation.py --save out.png                   # headless picture

Data: the raw ECD windows in ../shared/data/ecd_rotation (distorted pixels, undistorted by the problem
with the calibration) when present, else a simulated rotation with an exactly known angular velocity.
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

REGULARIZERS = {
    "none": None,
    "divergence": ("divergence",),
    "deformation": ("deformation",),
    "both": ("divergence", "deformation"),
}


def landscape_axes(truth: np.ndarray | None, estimate: np.ndarray) -> tuple[int, int]:
    """The two parameters with the largest rotation (ground truth if known, else the estimate)."""
    ref = np.abs(truth if truth is not None else estimate)
    i, j = np.sort(np.argsort(ref)[::-1][:2])
    return int(i), int(j)


def landscape_values(k: int, points: list[np.ndarray], n: int) -> np.ndarray:
    """Grid values of parameter ``k`` covering 0 and ``points`` with a margin (rad/s)."""
    vals = [0.0] + [float(p[k]) for p in points if p is not None]
    lo, hi = min(vals), max(vals)
    margin = max(0.15 * (hi - lo), 0.2)
    return np.linspace(lo - margin, hi + margin, n)


def build_figure(
    scene: _common.Scene, prob: cm.ContrastMaximization, result, objective_label: str, grid: int, init: str
):
    import matplotlib.pyplot as plt

    model = prob.model
    estimate = np.asarray(result.theta)
    truth = scene.truth
    path, values = _common.optimizer_path(result)

    start = "local ascent from 0" if init == "none" else f"{init} search, then local ascent"
    fig = plt.figure(figsize=(15, 9))
    gs = fig.add_gridspec(2, 3, left=0.05, right=0.96, top=0.9, bottom=0.07, hspace=0.35, wspace=0.38)
    fig.suptitle(
        f"Rotation estimation by CMax: {scene.name}\nobjective: {objective_label}; "
        f"optimizer: {result.method}, {start} ({len(path) - 1} iterations, {result.seconds:.2f} s)",
        fontsize=11,
    )

    zero = np.zeros(model.n_params)
    images = [("Before: identity warp", zero), ("After: CMax estimate", estimate)]
    if truth is not None:
        images.append((f"At the {scene.truth_label} value", truth))
    for col, (title, theta) in enumerate(images):
        ax = fig.add_subplot(gs[0, col])
        value = prob.value(theta)
        viz.show_iwe(ax, prob.iwe(theta), title=f"{title} (J = {value:.3g})")

    # Estimate against the ground truth, per axis.
    ax = fig.add_subplot(gs[1, 0])
    x = np.arange(model.n_params)
    width = 0.38
    ax.bar(x - width / 2, estimate, width, label="CMax estimate", color="tab:blue")
    if truth is not None:
        ax.bar(x + width / 2, truth, width, label=scene.truth_label, color="0.55")
        err = np.degrees(estimate - truth)
        ax.set_title("Angular velocity; error [deg/s]: " + ", ".join(f"{e:+.1f}" for e in err), fontsize=10)
    else:
        ax.set_title("Angular velocity (no ground truth)")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xticks(x, [viz.param_label(model, k) for k in x])
    ax.set_ylabel("angular velocity [rad/s]")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)

    # Trajectory: parameters over iterations, with the ground truth dashed; J on a twin axis.
    ax = fig.add_subplot(gs[1, 1])
    it = np.arange(len(path))
    for k in range(model.n_params):
        (line,) = ax.plot(it, path[:, k], lw=1.5, label=model.params[k])
        if truth is not None:
            ax.axhline(truth[k], color=line.get_color(), ls="--", lw=1.0)
    ax.set_xlabel("iteration (local ascent)")
    ax.set_ylabel("angular velocity [rad/s] (dashed: ground truth)")
    ax.set_title("Optimizer trajectory")
    ax.grid(alpha=0.3)
    twin = ax.twinx()
    twin.plot(it, values, color="k", lw=1.0, alpha=0.6, label="J")
    twin.set_ylabel("J (normalized)")
    lines = ax.get_legend_handles_labels()
    more = twin.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], fontsize=8, loc="lower right")

    # Landscape over the two largest axes, the third at the estimate, with the path.
    ax = fig.add_subplot(gs[1, 2])
    i, j = landscape_axes(truth, estimate)
    points = [truth, estimate, *path]  # the whole path stays on the map
    vx = landscape_values(i, points, grid)
    vy = landscape_values(j, points, grid)
    surface = viz.landscape_2d(prob, (i, j), vx, vy, theta=estimate)
    viz.plot_landscape_2d(
        ax,
        vx,
        vy,
        surface,
        xlabel=viz.param_label(model, i),
        ylabel=viz.param_label(model, j),
        title=f"J over ({model.params[i]}, {model.params[j]}), {model.params[3 - i - j]} at the estimate",
        truth=None if truth is None else truth[[i, j]],
        path=path[:, [i, j]],
    )
    return fig


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--sequence", choices=_common.ECD_SEQUENCES, default="boxes_rotation")
    parser.add_argument("--synthetic", action="store_true", help="simulated rotation even if ECD is present")
    parser.add_argument(
        "--regularizer",
        choices=tuple(REGULARIZERS),
        default="none",
        help="regularizers in the objective (rotation is well posed: none needed; default none)",
    )
    parser.add_argument("--lam", type=float, default=1.0, help="weight λ of each regularizer (default 1)")
    parser.add_argument("--method", choices=("adam", "armijo", "lbfgs"), default="adam", help="local ascent")
    parser.add_argument(
        "--init",
        choices=("none", "auto", "grid", "random"),
        default="none",
        help="none: local ascent from 0 (default); auto/grid/random: global search first",
    )
    parser.add_argument("--grid", type=int, default=25, help="landscape grid points per axis (default 25)")
    _common.add_save_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args, _ = _common.start(build_parser(), argv, "rotation_estimation")
    if args is None:
        return 2
    scene = None if args.synthetic else _common.load_ecd(args.sequence)
    if scene is None:
        scene = _common.synthetic_rotation()
    _common.subsample_scene(scene, args.max_events)

    names = REGULARIZERS[args.regularizer]
    weights = None if names is None else {n: args.lam for n in names}
    prob = cm.ContrastMaximization(scene.events, warp="rotation3", camera=scene.camera, regularizers=weights)
    result = _common.run_optimizer(prob, None, method=args.method, init=args.init)
    label = "IWE variance" + (
        "" if names is None else " - " + " - ".join(f"{args.lam:g} R_{n}" for n in names)
    )
    summary = ", ".join(f"{p} = {v:+.3f}" for p, v in zip(prob.model.params, result.theta, strict=True))
    print(f"{scene.name}: estimate {summary} rad/s")
    if scene.truth is not None:
        print(f"{scene.truth_label}: " + ", ".join(f"{v:+.3f}" for v in scene.truth) + " rad/s")

    fig = build_figure(scene, prob, result, label, args.grid, args.init)
    return _common.show_or_save(fig, args)


if __name__ == "__main__":
    sys.exit(main())
