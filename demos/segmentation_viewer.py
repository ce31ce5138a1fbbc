"""Segmentation viewer: motion segmentation by multi-cluster CMax (``cmax_taichi.segment``).

Shows the events coloured by cluster, the image of the unwarped events, each cluster's sharpened
IWE (its events warped by its own motion), a colour composite of the clusters, and how the cluster
memberships evolved over the iterations.

    python demos/segmentation_viewer.py                     # two objects, interactive window
    python demos/segmentation_viewer.py --save out.png      # headless picture

Data: a synthetic scene generated here with NumPy (a textured background and a textured square moving
differently, labels known, so the picture reports the agreement with the truth).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from itertools import permutations

import numpy as np

if __package__ in (None, ""):  # run as a script: make the sibling _common importable
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))

import _common

import cmax_taichi as cm
from cmax_taichi import viz
from cmax_taichi.solve.segment import segment

COLOURS = np.array(
    [[0.12, 0.47, 0.71], [0.84, 0.15, 0.16], [0.17, 0.63, 0.17], [0.58, 0.40, 0.74], [1.0, 0.50, 0.05]]
)


def agreement(labels: np.ndarray, truth: np.ndarray, k: int) -> float:
    """Share of events whose cluster matches the truth under the best relabelling (K <= 5)."""
    kept = labels >= 0
    best = 0.0
    for perm in permutations(range(k)):
        mapped = np.asarray(perm)[labels[kept]]
        best = max(best, float(np.mean(mapped == truth[kept])))
    return best


def build_figure(scene: _common.Scene, result, truth: np.ndarray | None):
    import matplotlib.pyplot as plt

    k = result.n_clusters
    events = result.events
    labels = result.labels[result.kept] if result.kept is not None else result.labels
    W, H = events.sensor_size
    fig = plt.figure(figsize=(15, 9))
    gs = fig.add_gridspec(2, max(3, k), left=0.05, right=0.96, top=0.9, bottom=0.07, hspace=0.35, wspace=0.4)
    it = len(result.history)
    title = f"Motion segmentation by multi-cluster CMax: {scene.name}, K = {k}, {it} iterations"
    title += f", {result.seconds:.1f} s"
    if truth is not None:
        title += f"\nagreement with the true labels: {100 * agreement(result.labels, truth, k):.1f}%"
    fig.suptitle(title, fontsize=11)

    # Events coloured by cluster (at their recorded positions), the latest drawn last.
    ax = fig.add_subplot(gs[0, 0])
    step = max(1, len(events) // 15000)  # scatter of at most ~15k points
    ax.scatter(events.x[::step], events.y[::step], s=0.6, c=COLOURS[labels[::step] % len(COLOURS)], lw=0)
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title("Events coloured by cluster")
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")
    for j in range(k):
        ax.plot(
            [], [], "s", color=COLOURS[j % len(COLOURS)], label=f"cluster {j + 1}: {result.sizes[j]} events"
        )
    ax.legend(fontsize=7, loc="upper right", markerscale=1.2)

    # The unwarped events, and a colour composite of the sharpened cluster IWEs.
    identity = cm.ContrastMaximization(events, warp="translation2").iwe([0.0, 0.0])
    viz.show_iwe(fig.add_subplot(gs[0, 1]), identity, title="Unwarped events (identity warp)")
    ax = fig.add_subplot(gs[0, 2])
    composite = np.ones((H, W, 3))
    for j in range(k):
        lo, hi = viz.iwe_limits(result.iwes[j])
        strength = np.clip(result.iwes[j] / hi, 0.0, 1.0)[..., None]
        composite *= 1.0 - strength * (1.0 - COLOURS[j % len(COLOURS)])  # multiply: overlaps darken
    ax.imshow(composite, interpolation="nearest")
    ax.set_title("Sharpened clusters (colour composite)")
    ax.set_xlabel("x [px]")
    ax.set_ylabel("y [px]")

    # Each cluster's own IWE (its events, membership-weighted, warped by its motion).
    model = cm.get_warp(result.warps[0])
    for j in range(min(k, 3)):
        ax = fig.add_subplot(gs[1, j])
        theta = np.asarray(result.thetas[j])
        parts = [f"{p} = {v:.3g} {u}" for p, v, u in zip(model.params, theta, model.units, strict=False)]
        lines = ", ".join(parts[:2]) + ("\n" + ", ".join(parts[2:]) if len(parts) > 2 else "")
        viz.show_iwe(ax, result.iwes[j], title=f"Cluster {j + 1} IWE: {lines}")
        ax.title.set_fontsize(9)

    # Memberships over the iterations: each cluster's membership mass, and the share of changed labels.
    if k <= 2:
        ax = fig.add_subplot(gs[1, 2])
        iters = np.arange(1, it + 1)
        mass = np.array([h["mass"] for h in result.history], dtype=np.float64)
        total = np.array([h.get("events", mass[i].sum()) for i, h in enumerate(result.history)], dtype=float)
        for j in range(k):
            ax.plot(iters, mass[:, j] / total, "o-", color=COLOURS[j], label=f"cluster {j + 1} share")
        ax.set_ylim(0, 1)
        ax.set_xlabel("iteration")
        ax.set_ylabel("membership share (sum of memberships / events)")
        ax.set_title("Memberships over iterations")
        ax.grid(alpha=0.3)
        twin = ax.twinx()
        changed = [100 * h["changed"] for h in result.history]
        twin.plot(iters, changed, "k--", lw=1, label="labels changed")
        twin.set_ylabel("labels changed in the iteration [%]")
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = twin.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="center right")
    return fig


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--clusters", type=int, default=2, help="number of clusters K (default 2)")
    parser.add_argument("--warp", default="translation2", help="motion model of every cluster")
    parser.add_argument("--lam", type=float, default=0.0, help="λ of both collapse regularizers (default 0)")
    parser.add_argument("--iterations", type=int, default=12, help="most alternations (default 12)")
    _common.add_save_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args, _ = _common.start(build_parser(), argv, "segmentation_viewer")
    if args is None:
        return 2
    scene = _common.synthetic_two_objects()
    _common.subsample_scene(scene, args.max_events, note=False)
    truth = scene.extra["labels"]
    regs = {"divergence": args.lam, "deformation": args.lam} if args.lam > 0 else None
    result = segment(
        scene.events, args.clusters, warp=args.warp, regularizers=regs, max_iterations=args.iterations
    )
    print(result)
    if truth is not None:
        print(f"agreement with the true labels: {100 * agreement(result.labels, truth, args.clusters):.1f}%")
    fig = build_figure(scene, result, truth)
    return _common.show_or_save(fig, args)


if __name__ == "__main__":
    sys.exit(main())
