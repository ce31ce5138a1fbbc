"""Accuracy of the dense flow (cmax_taichi.flow) against the exact flow of simulated depth scenes, beside
the best global warp on the same window (the dense flow's accuracy target).

    python benchmarks/dense_flow_accuracy.py [--scenes boxroom planes room object] [--out DIR]

Scenes (346x260, one window each, all its events):

* ``boxroom``: :func:`cmax_taichi.testing.flow_scenes.depth_scene`, a camera moving sideways in a box room
  (flow proportional to the inverse depth: 5.4-11.6 px over the 0.05 s window, a factor 2.15 across the
  image, smooth), rendered from a texture under the exact flow;
* ``planes``, ``room``, ``object``: the simulator's depth presets (:func:`cmax_taichi.sim.depth_example`:
  textured 3-D planes rendered by the ESIM-like simulator, with occlusions and flow discontinuities);
* ``corridor``: the simulator's preset of a camera translating sideways along a corridor (5-14 px over
  the window, smooth, nothing occluded): the 3-D counterpart of ``boxroom``.

Each scene is scored as the benchmarks count it (:func:`cmax_taichi.metrics.flow_error`): the displacement
over the window against the exact one on the pixels with events, AEE px, 3PE %. Methods: our dense flow
with its defaults (16 x 16 cells, 4 levels), our dense flow on a 32 x 32 grid (5 levels), the least-squares
fit of the 16 x 16 grid to the exact flow (the best the grid can represent, for scale), and the global warp
``mitrokhin4`` with divergence and deformation at 10 (``cm.maximize`` with its default search). Writes
``OUT/dense_flow_accuracy.json``, ``OUT/dense_flow_accuracy.md`` and ``OUT/dense_flow_accuracy.png``
(truth, dense and global flows, dense error, per scene).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

SCENES = ("boxroom", "planes", "room", "object", "corridor")


def scene_window(name: str) -> dict:
    """``events``, ``truth`` ((2, H, W) px over the window, NaN where unknown), ``duration`` (s)."""
    if name == "boxroom":
        from cmax_taichi.testing.flow_scenes import depth_scene

        scene = depth_scene((346, 260), duration=0.05, displacement=(5.0, 2.0), n_events=60000, seed=0)
        return {"events": scene.events, "truth": scene.displacement(), "duration": scene.duration}
    from cmax_taichi.sim import depth_example

    ex = depth_example(name)
    return {"events": ex.events, "truth": ex.flow, "duration": ex.t1 - ex.t0}


def _score(pred: np.ndarray, window: dict) -> dict:
    from cmax_taichi.metrics import event_mask, flow_error

    m = flow_error(pred, window["truth"], event_mask(window["events"]), (3.0,))
    return {"AEE": m["AEE"], "3PE": m["3PE"], "n_pixels": m["n_pixels"]}


def run_scene(name: str) -> dict:
    import cmax_taichi as cm
    from cmax_taichi.flow import DenseFlowEstimator

    window = scene_window(name)
    events, truth, T = window["events"], window["truth"], window["duration"]
    mag = np.hypot(*truth)[np.isfinite(truth).all(0)]
    row = {
        "scene": name,
        "events": len(events),
        "truth_px_p5_p50_p95": [float(v) for v in np.percentile(mag, [5, 50, 95])],
        "flows": {},
        "methods": {},
    }
    for label, grid, levels in (("dense 16x16", (16, 16), 4), ("dense 32x32", (32, 32), 5)):
        t0 = time.perf_counter()
        res = DenseFlowEstimator(grid, levels=levels).estimate(events)
        pred = res.flow(T)
        row["methods"][label] = {**_score(pred, window), "wall_s": time.perf_counter() - t0}
        row["flows"][label] = pred
        if label == "dense 16x16":
            fit = res.grid.dense(res.grid.fit(np.nan_to_num(truth)))
            row["methods"]["16x16 grid fitted to the truth"] = _score(fit, window)
    t0 = time.perf_counter()
    prob = cm.ContrastMaximization(
        events, warp="mitrokhin4", regularizers={"divergence": 10.0, "deformation": 10.0}
    )
    result = cm.maximize(prob)
    pred = prob.dense_flow(result.theta, dt=T)
    row["methods"]["global mitrokhin4 + div 10 + def 10"] = {
        **_score(pred, window),
        "wall_s": time.perf_counter() - t0,
    }
    row["flows"]["global"] = pred
    row["flows"]["truth"] = truth
    return row


def _table(rows: list[dict]) -> str:
    lines = [
        "| scene | events | truth px (p5 / p50 / p95) | method | AEE px | 3PE % | wall s |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p = r["truth_px_p5_p50_p95"]
        for k, (label, m) in enumerate(r["methods"].items()):
            head = (
                f"| {r['scene']} | {r['events']} | {p[0]:.1f} / {p[1]:.1f} / {p[2]:.1f} "
                if k == 0
                else "| | | "
            )
            wall = f"{m['wall_s']:.1f}" if "wall_s" in m else ""
            lines.append(f"{head}| {label} | {m['AEE']:.3f} | {m['3PE']:.2f} | {wall} |")
    return "\n".join(lines)


def _figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cmax_taichi import viz

    fig, axes = plt.subplots(
        len(rows), 4, figsize=(16, 3.4 * len(rows)), squeeze=False, constrained_layout=True
    )
    for ax, r in zip(axes, rows, strict=True):
        f = r["flows"]
        truth = np.nan_to_num(f["truth"])
        peak = float(np.abs(truth).max()) or 1.0
        dense, glob = r["methods"]["dense 16x16"], r["methods"]["global mitrokhin4 + div 10 + def 10"]
        viz.show_flow(ax[0], truth, max_magnitude=peak, unit="px", title=f"{r['scene']}: truth")
        viz.show_flow(
            ax[1],
            f["dense 16x16"],
            max_magnitude=peak,
            unit="px",
            title=f"dense 16x16: AEE {dense['AEE']:.2f} px",
        )
        viz.show_flow(
            ax[2], f["global"], max_magnitude=peak, unit="px", title=f"global: AEE {glob['AEE']:.2f} px"
        )
        err = np.hypot(*(f["dense 16x16"] - f["truth"]))
        im = ax[3].imshow(err, cmap="magma", vmin=0, vmax=3)
        ax[3].set_title("dense 16x16: end-point error, px")
        ax[3].axis("off")
        fig.colorbar(im, ax=ax[3], shrink=0.8)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--out", type=Path, default=Path("bench-dense-flow"))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}; {os.cpu_count()} CPUs", flush=True)
    rows = []
    for name in args.scenes:
        rows.append(run_scene(name))
        print(_table(rows[-1:]), flush=True)
    table = _table(rows)
    (args.out / "dense_flow_accuracy.md").write_text(table + "\n")
    public = [{k: v for k, v in r.items() if k != "flows"} for r in rows]
    (args.out / "dense_flow_accuracy.json").write_text(json.dumps(public, indent=1))
    _figure(rows, args.out / "dense_flow_accuracy.png")
    print(table)
    print(f"wrote {args.out / 'dense_flow_accuracy.md'}, .json, .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
