"""Dense flow collapse and its prevention: one window of events, the dense flow estimated without any
regularizer, with total variation alone, with the divergence penalty alone, with the paper's divergence
and deformation penalties, and with the library's defaults; the image of warped events (IWE) and the flow
of each, with its FWL, the share of events whose neighbourhood the warp shrinks to less than half its area,
and what the optimizer did on each level (every row of the figure comes from levels that moved).

    python demos/dense_flow_collapse.py                    # the MVSEC indoor_flying1 cut, a window
    python demos/dense_flow_collapse.py --save out.png     # headless picture
    python demos/dense_flow_collapse.py --synthetic        # a simulated box room instead
    python demos/dense_flow_collapse.py --ecd boxes_rotation --save out.png   # an ECD rotation cut, whose
                                                           # gyro gives the FWL of the true motion

Without a regularizer the dense flow gathers the events onto points and short lines (FWL far above any
true flow's); total variation alone and the divergence alone do not stop it; the divergence and
deformation penalties together do, and so do the defaults (docs/flow.md, "What each regularizer does").
Data: the MVSEC cut in ../shared/data when present, else the simulated scene.
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
from cmax_taichi.flow import DEFAULT_REGULARIZERS, DenseFlowEstimator, DenseFlowProblem
from cmax_taichi.metrics import fwl

#: the variants shown, left to right: (label, references, regularizers)
VARIANTS = (
    ("no regularizer", "first", {}),
    ("total variation alone (1.0)", "first", {"total_variation": 1.0}),
    ("divergence alone (10)", "first", {"divergence": 10.0}),
    ("divergence + deformation (10)", "first", {"divergence": 10.0, "deformation": 10.0}),
    ("defaults (middle t_ref)", "middle", dict(DEFAULT_REGULARIZERS)),
)


def synthetic_scene(max_events: int | None) -> _common.Scene:
    from cmax_taichi.testing.flow_scenes import depth_scene

    scene = depth_scene(
        (240, 180), duration=0.05, displacement=(5.0, 2.0), n_events=max_events or 20000, seed=0
    )
    return _common.Scene(scene.events, None, f"simulated box room, {len(scene.events)} events")


def undistorted(scene: _common.Scene) -> cm.Events:
    """The scene's events, undistorted with its camera where that has distortion."""
    camera = scene.camera
    return scene.events.undistort(camera) if camera is not None and camera.has_distortion else scene.events


def estimate_all(events: cm.Events, grid: tuple[int, int], levels: int) -> list[dict]:
    """Each variant's flow, FWL (variance of its IWE over that of the unwarped events) and the share of
    events whose neighbourhood the warp shrinks below half its area."""
    out = []
    for label, refs, regs in VARIANTS:
        est = DenseFlowEstimator(grid, levels=levels, references=refs, regularizers=regs)
        res = est.estimate(events)
        fwl_problem = DenseFlowProblem(events, res.grid, objective="variance", references="first")
        q = fwl_problem.event_quantities(res.nodes)
        out.append(
            {
                "label": label,
                "result": res,
                "iwe": fwl_problem.iwe(res.nodes),
                "fwl": fwl_problem.value(res.nodes),
                "shrunk": float(np.mean(np.abs(q["det"]) < 0.5)),
            }
        )
        moves = ", ".join(f"{lv.status} {lv.iterations} it" for lv in res.levels)
        print(
            f"{label:32s} FWL {out[-1]['fwl']:7.3f}   events shrunk below half their area: "
            f"{100 * out[-1]['shrunk']:5.1f}%   J {res.value:8.3f}   {res.seconds:.2f} s   levels: {moves}"
        )
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--synthetic", action="store_true", help="a simulated scene instead of the MVSEC cut")
    parser.add_argument(
        "--ecd",
        metavar="SEQUENCE",
        choices=_common.ECD_SEQUENCES,
        help="an ECD rotation cut instead (its gyro's rotation gives the true motion's FWL)",
    )
    parser.add_argument("--grid", type=int, nargs=2, default=[16, 16], metavar=("NX", "NY"))
    parser.add_argument("--levels", type=int, default=4)
    _common.add_save_arguments(parser)
    args, _ = _common.start(parser, argv, "dense_flow_collapse")
    if args is None:
        return 2
    import matplotlib.pyplot as plt

    if args.ecd is not None:
        scene = _common.load_ecd(args.ecd)
        if scene is None:
            print(f"no ECD cut {args.ecd!r} in {_common.DATA_DIR / 'ecd_rotation'}")
            return 1
    else:
        scene = None if args.synthetic else _common.load_mvsec(30000)
    if scene is None:
        scene = synthetic_scene(args.max_events)
    else:
        _common.subsample_scene(scene, args.max_events)
    print(scene.name)
    events = undistorted(scene)
    if scene.truth is not None:  # the gyro's rotation: the FWL of the true motion, for scale
        true_fwl = fwl(scene.events, "rotation3", scene.truth, camera=scene.camera)
        print(f"{'true motion (' + scene.truth_label + ')':32s} FWL {true_fwl:7.3f}")
        scene.name += f"; FWL of the true motion ({scene.truth_label}): {true_fwl:.2f}"
    rows = estimate_all(events, tuple(args.grid), args.levels)
    fig, axes = plt.subplots(2, len(rows) + 1, figsize=(3.8 * (len(rows) + 1), 6.6), constrained_layout=True)
    grid = rows[0]["result"].grid
    zero = DenseFlowProblem(events, grid, objective="variance")
    viz.show_iwe(axes[0, 0], zero.iwe(np.zeros(grid.shape)), title="IWE, no motion", colorbar=False)
    axes[1, 0].axis("off")
    axes[1, 0].text(0.02, 0.5, scene.name, wrap=True, fontsize=9, va="center")
    peak = max(float(np.nanmax(np.hypot(*r["result"].displacement()))) for r in rows[3:]) or 1.0
    for k, r in enumerate(rows, start=1):
        res = r["result"]
        viz.show_iwe(axes[0, k], r["iwe"], title=f"{r['label']}\nFWL {r['fwl']:.2f}", colorbar=False)
        viz.show_flow(
            axes[1, k],
            res.displacement(),
            max_magnitude=peak,
            unit="px",
            title=f"flow; {100 * r['shrunk']:.0f}% of events shrunk",
        )
    fig.suptitle("Dense flow by contrast maximization: collapse without regularizers, and its prevention")
    return _common.show_or_save(fig, args)


if __name__ == "__main__":
    sys.exit(main())
