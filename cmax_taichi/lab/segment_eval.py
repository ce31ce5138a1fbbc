"""Evaluation of motion segmentation on labelled synthetic scenes.

* :func:`simulated_scene`: 2-4 textured objects moving independently over a static background,
  rendered by the event simulator (``cmax_taichi.sim``: photographic textures, threshold-crossing
  events, sensor noise), with the simulator's per-event labels and every event's true position at
  the reference time (from the exact motions). The comparison in docs/SEGMENTATION.md uses these.
* :func:`synthetic_scene`: a NumPy scene of 2-4 objects made of random edge segments moving
  independently (translation, optionally zoom and rotation about the object's centre), with the same
  ground truth. Fast, for unit tests.
* :func:`label_accuracy`: fraction of object events whose cluster is matched to their object, under the
  best one-to-one matching of clusters to objects (Hungarian algorithm with SciPy, else brute force).
* :func:`motion_errors`: per object, the mean endpoint error (px) between the matched cluster's warp
  of its events and their true positions at the reference time.
* :func:`spread_ratios`: per object, how much the matched cluster's warp shrinks the object's events
  (RMS spread of the warped events over that of their true positions; 1 = no contraction, 0 = the
  events collapsed to a point).
* ``python -m cmax_taichi.lab.segment_eval``: the with / without regularizer comparison of
  docs/SEGMENTATION.md.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from cmax_taichi.core.events import Events
from cmax_taichi.testing.reference import warp_events

__all__ = [
    "SyntheticScene",
    "simulated_scene",
    "spread_ratios",
    "synthetic_scene",
    "label_accuracy",
    "match_clusters",
    "motion_errors",
    "compare",
]


@dataclass
class SyntheticScene:
    """A labelled synthetic window.

    Attributes
    ----------
    events : Events
        Time-sorted events (px, s).
    labels : ndarray of int, shape (N,)
        Object of each event; -1 for noise events.
    x_ref, y_ref : ndarray, shape (N,)
        True position of each event's scene point at ``t = 0`` (the window start, ``t_ref="first"``), px;
        NaN for noise events.
    motions : list of dict
        Per object: ``centre`` (px), ``velocity`` (px/s), ``zoom`` (1/s), ``rotation`` (rad/s).
    """

    events: Events
    labels: np.ndarray
    x_ref: np.ndarray
    y_ref: np.ndarray
    motions: list


def _object_texture(rng: np.random.Generator, radius: float, n_segments: int) -> np.ndarray:
    """Random straight edge segments inside a disc of ``radius`` px: (n_segments, 2, 2) end points."""
    centres = rng.uniform(-0.7, 0.7, size=(n_segments, 2)) * radius
    angles = rng.uniform(0, np.pi, n_segments)
    half = rng.uniform(0.15, 0.45, n_segments) * radius
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1) * half[:, None]
    return np.stack([centres - d, centres + d], axis=1)


def synthetic_scene(
    n_objects: int = 2,
    n_events: int = 30000,
    sensor_size: tuple[int, int] = (240, 180),
    duration: float = 0.03,
    *,
    zoom: float = 0.0,
    rotation: float = 0.0,
    noise_fraction: float = 0.02,
    jitter: float = 0.3,
    seed: int = 0,
    speed: tuple[float, float] = (250.0, 600.0),
) -> SyntheticScene:
    """Objects of random edges moving independently over a static, event-free background.

    Parameters
    ----------
    n_objects : int
        2 to 4 (placed in the quadrants / halves of the sensor).
    n_events : int
        Events in all (objects share them equally; ``noise_fraction`` of them are uniform noise).
    sensor_size : (int, int)
        ``(W, H)``, px.
    duration : float
        Window length, s.
    zoom, rotation : float
        Largest magnitude of each object's expansion rate (1/s) and in-plane rotation (rad/s) about
        its own centre (0: pure translation).
    noise_fraction : float
        Fraction of uniformly distributed noise events (label -1).
    jitter : float
        Gaussian position noise of the object events, px.
    seed : int
        Random seed.
    speed : (float, float)
        Range of the objects' speeds, px/s; directions are spread around the circle so that the
        objects' velocities differ.
    """
    if not 1 <= int(n_objects) <= 4:
        raise ValueError(f"n_objects must be 1 to 4, got {n_objects}")
    rng = np.random.default_rng(seed)
    W, H = sensor_size
    K = int(n_objects)
    slots = {1: [(0.5, 0.5)], 2: [(0.28, 0.5), (0.72, 0.5)], 3: [(0.25, 0.3), (0.75, 0.3), (0.5, 0.72)]}
    slots[4] = [(0.27, 0.3), (0.73, 0.3), (0.27, 0.72), (0.73, 0.72)]
    radius = 0.2 * min(W, H) if K > 2 else 0.25 * min(W, H)
    phase = rng.uniform(0, 2 * np.pi)
    n_noise = int(round(noise_fraction * n_events))
    per_object = np.full(K, (n_events - n_noise) // K)
    per_object[: (n_events - n_noise) - per_object.sum()] += 1

    xs, ys, ts, xr, yr, labels, motions = [], [], [], [], [], [], []
    for k in range(K):
        centre = np.array([slots[K][k][0] * (W - 1), slots[K][k][1] * (H - 1)])
        ang = phase + 2 * np.pi * k / K + rng.uniform(-0.3, 0.3)
        v = rng.uniform(*speed) * np.array([np.cos(ang), np.sin(ang)])
        s = rng.uniform(-zoom, zoom) if zoom else 0.0
        w = rng.uniform(-rotation, rotation) if rotation else 0.0
        motions.append({"centre": centre, "velocity": v, "zoom": s, "rotation": w})
        segs = _object_texture(rng, radius, 14)
        lengths = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
        m = per_object[k]
        which = rng.choice(len(segs), size=m, p=lengths / lengths.sum())
        u = rng.uniform(0, 1, m)[:, None]
        q = segs[which, 0] + u * (segs[which, 1] - segs[which, 0])  # point in the object frame at t = 0
        t = rng.uniform(0, duration, m)
        a = (1.0 + s * t)[:, None]
        c, sn = np.cos(w * t), np.sin(w * t)
        rot = np.stack([c * q[:, 0] - sn * q[:, 1], sn * q[:, 0] + c * q[:, 1]], axis=1)
        pos = centre + v * t[:, None] + a * rot + rng.normal(0, jitter, size=(m, 2))
        xs.append(pos[:, 0])
        ys.append(pos[:, 1])
        ts.append(t)
        xr.append(centre[0] + q[:, 0])
        yr.append(centre[1] + q[:, 1])
        labels.append(np.full(m, k))
    xs.append(rng.uniform(0, W - 1, n_noise))
    ys.append(rng.uniform(0, H - 1, n_noise))
    ts.append(rng.uniform(0, duration, n_noise))
    xr.append(np.full(n_noise, np.nan))
    yr.append(np.full(n_noise, np.nan))
    labels.append(np.full(n_noise, -1))
    x, y, t = np.concatenate(xs), np.concatenate(ys), np.concatenate(ts)
    xr, yr, lab = np.concatenate(xr), np.concatenate(yr), np.concatenate(labels)
    inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    order = np.argsort(t[inside], kind="stable")
    x, y, t, xr, yr, lab = (a[inside][order] for a in (x, y, t, xr, yr, lab))
    t[0], t[-1] = 0.0, duration  # the window spans exactly [0, duration]
    p = rng.integers(0, 2, len(t))
    return SyntheticScene(Events(x, y, t, p, (W, H)), lab, xr, yr, motions)


def match_clusters(labels: np.ndarray, truth: np.ndarray, n_clusters: int) -> dict[int, int]:
    """Best one-to-one matching object -> cluster (maximum number of agreeing events).

    Uses ``scipy.optimize.linear_sum_assignment`` when SciPy is installed, else tries every assignment
    (fine for up to 6 clusters). Noise events (truth -1) are ignored. Objects left without a cluster
    (more objects than clusters) are missing from the result.
    """
    objects = np.unique(truth[truth >= 0])
    conf = np.zeros((len(objects), n_clusters))
    for a, o in enumerate(objects):
        conf[a] = np.bincount(labels[(truth == o) & (labels >= 0)], minlength=n_clusters)[:n_clusters]
    try:
        from scipy.optimize import linear_sum_assignment

        rows, cols = linear_sum_assignment(-conf)
        return {int(objects[r]): int(c) for r, c in zip(rows, cols, strict=True)}
    except ImportError:  # pragma: no cover - SciPy is a test dependency
        if n_clusters > 6 and len(objects) > 6:
            raise RuntimeError("brute-force matching is limited to 6 clusters: install scipy") from None
        best, best_map = -1.0, {}
        for perm in itertools.permutations(range(n_clusters), min(len(objects), n_clusters)):
            score = sum(conf[a, c] for a, c in enumerate(perm))
            if score > best:
                best, best_map = score, {int(objects[a]): c for a, c in enumerate(perm)}
        return best_map


def label_accuracy(labels: np.ndarray, truth: np.ndarray, n_clusters: int) -> float:
    """Fraction of object events (truth >= 0) whose cluster is the one matched to their object."""
    labels = np.asarray(labels)
    truth = np.asarray(truth)
    mapping = match_clusters(labels, truth, n_clusters)
    obj = truth >= 0
    hit = np.zeros(len(truth), dtype=bool)
    for o, c in mapping.items():
        hit |= (truth == o) & (labels == c)
    return float(hit[obj].mean()) if obj.any() else float("nan")


def motion_errors(result, scene: SyntheticScene) -> list[float]:
    """Per object, the mean distance (px) between its events warped by the matched cluster and their
    true positions at the reference time (the window's first event). NaN for an object without a
    cluster. The warps' centre is the image centre (segmentations without a camera)."""
    mapping = match_clusters(result.labels, scene.labels, result.n_clusters)
    errors = []
    for o in range(int(scene.labels.max()) + 1):
        if o not in mapping:
            errors.append(float("nan"))
            continue
        sel, xw, yw = _warp_object(result, scene, o, mapping)
        errors.append(float(np.nanmean(np.hypot(xw - scene.x_ref[sel], yw - scene.y_ref[sel]))))
    return errors


def _warp_object(result, scene: SyntheticScene, o: int, mapping: dict):
    ev = scene.events
    W, H = ev.sensor_size
    j = mapping[o]
    sel = scene.labels == o
    xw, yw, _, _ = warp_events(
        result.warps[j],
        ev.x[sel],
        ev.y[sel],
        ev.t[sel] - ev.t[0],
        list(result.thetas)[j],
        center=((W - 1) / 2.0, (H - 1) / 2.0),
        duration=ev.duration,
    )
    return sel, xw, yw


def spread_ratios(result, scene: SyntheticScene) -> list[float]:
    """Per object: RMS distance of its events warped by the matched cluster from their centroid,
    divided by the same of their true positions at the reference time. 1: the warp keeps the object's
    size; below 1: the warp contracts it (0: collapse to a point). NaN for an object without cluster."""
    mapping = match_clusters(result.labels, scene.labels, result.n_clusters)
    out = []
    for o in range(int(scene.labels.max()) + 1):
        if o not in mapping:
            out.append(float("nan"))
            continue
        sel, xw, yw = _warp_object(result, scene, o, mapping)
        ok = np.isfinite(xw) & np.isfinite(yw)
        spread = math.sqrt(np.var(xw[ok]) + np.var(yw[ok]))
        ref = math.sqrt(np.var(scene.x_ref[sel][ok]) + np.var(scene.y_ref[sel][ok]))
        out.append(spread / ref if ref > 0 else float("nan"))
    return out


def simulated_scene(
    n_objects: int = 2,
    n_events: int = 30000,
    sensor_size: tuple[int, int] = (240, 180),
    *,
    rotation: float = 1.5,
    zoom: float = 2.0,
    speed: tuple[float, float] = (250.0, 400.0),
    contrast_threshold: float = 0.5,
    skip: float = 0.01,
    seed: int = 0,
) -> SyntheticScene:
    """A window of ``n_events`` events of the event simulator: ``n_objects`` textured objects (disks and
    boxes of the simulator's ``multi_object_scene``) over a static background.

    The objects' motions alternate translation, planar rotation (se2) and similarity (sim2, rotation
    and scale) about the object's own centre; speeds are drawn from ``speed`` (px/s) in directions
    spread around the circle, angular rates from ``+-rotation`` (rad/s), scale rates from ``+-zoom``
    (1/s). The window starts ``skip`` seconds into the simulation (the sensor starts at rest).
    ``labels`` are the objects (0 .. n_objects - 1), -1 for the simulator's noise events and for the
    few events of the static background (none without noise); ``x_ref, y_ref`` are the exact positions
    of each event's scene point at the window's first event time.
    """
    from cmax_taichi.sim import Motion, multi_object_scene, simulate

    W, H = (int(v) for v in sensor_size)
    rng = np.random.default_rng(seed)
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    # the placement ring of multi_object_scene, to express each motion about the object's own centre
    phase = np.random.default_rng(seed).uniform(0, 2 * np.pi)
    motions, specs = [], []
    for k in range(int(n_objects)):
        ang = phase + 2 * np.pi * k / n_objects
        qx, qy = 0.28 * W * math.cos(ang), 0.25 * H * math.sin(ang)
        d = ang + np.pi / 2 + rng.uniform(-0.5, 0.5)
        v = rng.uniform(*speed) * np.array([math.cos(d), math.sin(d)])
        kind = ("translation2", "se2", "sim2")[k % 3]
        w = rng.uniform(-rotation, rotation) if kind != "translation2" else 0.0
        s = rng.uniform(-zoom, zoom) if kind == "sim2" else 0.0
        # velocity of the centre-relative model at the image centre: v_c = v - w Jr q - s q
        vx, vy = v[0] + w * qy - s * qx, v[1] - w * qx - s * qy
        theta = {"translation2": (v[0], v[1]), "se2": (vx, vy, w), "sim2": (vx, vy, w, s)}[kind]
        motions.append(Motion(kind, theta))
        specs.append({"centre": np.array([cx + qx, cy + qy]), "velocity": v, "zoom": s, "rotation": w})
    scene = multi_object_scene(
        (W, H),
        n_objects,
        background_motion=Motion("translation2", (0.0, 0.0)),
        object_motions=motions,
        seed=seed,
    )
    # duration: enough for n_events after the warm-up, from the scene's event rate (re-run if short)
    duration = skip + 0.04
    for _ in range(4):
        rec = simulate(scene, duration, contrast_threshold=contrast_threshold, seed=seed)
        i0 = int(np.searchsorted(rec.t, skip))
        if len(rec) - i0 >= n_events:
            break
        rate = max(len(rec) - i0, 1) / (duration - skip)
        duration = skip + 1.3 * n_events / rate
    else:
        raise RuntimeError(f"the simulation gave {len(rec) - i0} events, fewer than {n_events}")
    sl = slice(i0, i0 + n_events)
    x, y, t, p = rec.x[sl], rec.y[sl], rec.t[sl], rec.p[sl]
    layer = rec.labels[sl].astype(np.int64)
    labels = np.where(layer >= 1, layer - 1, -1)
    xr, yr = np.full(n_events, np.nan), np.full(n_events, np.nan)
    t_ref = float(t[0])
    for k in range(1, int(n_objects) + 1):
        m = scene.layers[k].motion
        Gref = m.matrix(t_ref, rec.camera)
        for i in np.flatnonzero(layer == k):
            q = Gref @ np.linalg.solve(m.matrix(float(t[i]), rec.camera), [x[i], y[i], 1.0])
            xr[i], yr[i] = q[0] / q[2], q[1] / q[2]
    return SyntheticScene(Events(x, y, t, p, (W, H)), labels, xr, yr, specs)


def compare(
    scenes: list[SyntheticScene],
    *,
    warps=("translation2", "mitrokhin4"),
    regularizer_sets=None,
    extra_clusters: int = 0,
    on_row=None,
    **segment_kwargs,
) -> list[dict]:
    """Segment every scene with every warp x regularizer setting, with K = objects + ``extra_clusters``
    clusters; one row of metrics per run."""
    from cmax_taichi.solve.segment import segment

    if regularizer_sets is None:
        regularizer_sets = {"none": {}, "div+def": {"divergence": 1.0, "deformation": 1.0}}
    rows = []
    for s_idx, scene in enumerate(scenes):
        n_obj = int(scene.labels.max()) + 1
        K = n_obj + int(extra_clusters)
        for warp in warps:
            for reg_name, regs in regularizer_sets.items():
                res = segment(scene.events, K, warp=warp, regularizers=regs, **segment_kwargs)
                err = motion_errors(res, scene)
                rows.append(
                    {
                        "scene": s_idx,
                        "objects": n_obj,
                        "K": K,
                        "warp": warp,
                        "regularizers": reg_name,
                        "accuracy": label_accuracy(res.labels, scene.labels, K),
                        "motion_error_px": float(np.nanmean(err)),
                        "worst_motion_error_px": float(np.nanmax(err)),
                        "min_spread_ratio": float(np.nanmin(spread_ratios(res, scene))),
                        "empty": int(res.empty.sum()),
                        "iterations": len(res.history),
                        "seconds": res.seconds,
                    }
                )
                if on_row is not None:
                    on_row(rows[-1])
    return rows


def _print_row(r: dict) -> None:
    print(
        f"scene {r['scene']} objects {r['objects']} K {r['K']} {r['warp']:12s} {r['regularizers']:14s} "
        f"acc {100 * r['accuracy']:5.1f}% err {r['motion_error_px']:6.2f} px "
        f"spread {r['min_spread_ratio']:.2f} empty {r['empty']} it {r['iterations']} {r['seconds']:.2f} s",
        file=sys.stderr,
        flush=True,
    )


def _table(rows: list[dict]) -> str:
    """Markdown table: mean over scenes per (objects, warp, regularizers)."""
    keys = []
    for r in rows:
        k = (r["objects"], r["K"], r["warp"], r["regularizers"])
        if k not in keys:
            keys.append(k)
    lines = [
        "| objects | K | warp | regularizers | label accuracy (%) | motion error (px) "
        "| smallest spread ratio | seconds |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k in keys:
        sel = [r for r in rows if (r["objects"], r["K"], r["warp"], r["regularizers"]) == k]
        acc = 100 * np.mean([r["accuracy"] for r in sel])
        acc_min = 100 * np.min([r["accuracy"] for r in sel])
        err = np.median([r["motion_error_px"] for r in sel])
        spread = np.min([r["min_spread_ratio"] for r in sel])
        sec = np.median([r["seconds"] for r in sel])
        lines.append(
            f"| {k[0]} | {k[1]} | {k[2]} | {k[3]} | {acc:.1f} (min {acc_min:.1f}) | {err:.2f} | "
            f"{spread:.2f} | {sec:.2f} |"
        )
    return "\n".join(lines)


def timing(
    n_events=(7500, 15000, 30000, 60000), n_clusters=(1, 2, 3, 4), repeats: int = 5, warp: str = "mitrokhin4"
) -> list[dict]:
    """Speed of segmentation with both regularizers on simulated windows of 3 objects, for every
    ``n_events`` at K = 3 and every ``n_clusters`` at 30,000 events (after a warm-up run that compiles).

    Per case: medians over ``repeats`` complete segmentations of wall-clock and process CPU seconds
    (CPU: all threads; on a machine shared with other jobs it is the steadier measure of the work), the
    iterations, and the wall / CPU milliseconds of one multi-cluster ``value_and_grad`` (median of 20).
    """
    from cmax_taichi.pipeline.clusters import MultiClusterCMax
    from cmax_taichi.solve.segment import segment

    regs = {"divergence": 1.0, "deformation": 1.0}
    big = simulated_scene(3, max(n_events), seed=7)
    rows = []
    cases = [(n, 3) for n in n_events] + [(30000, k) for k in n_clusters if k != 3]
    for n, k in cases:
        ev = big.events[:n]
        segment(ev, k, warp=warp, regularizers=regs)  # compile
        wall, cpu, its = [], [], []
        for _ in range(repeats):
            w0, c0 = time.perf_counter(), time.process_time()
            res = segment(ev, k, warp=warp, regularizers=regs)
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
            its.append(len(res.history))
        prob = MultiClusterCMax(ev, k, warp, regularizers=regs)
        prob.set_memberships(res.probabilities[res.kept])
        prob.value_and_grad(res.thetas)
        vg_wall, vg_cpu = [], []
        for _ in range(20):
            w0, c0 = time.perf_counter(), time.process_time()
            prob.value_and_grad(res.thetas)
            vg_wall.append(time.perf_counter() - w0)
            vg_cpu.append(time.process_time() - c0)
        rows.append(
            {
                "events": n,
                "K": k,
                "segment_wall_s": float(np.median(wall)),
                "segment_cpu_s": float(np.median(cpu)),
                "iterations": float(np.median(its)),
                "value_and_grad_wall_ms": 1e3 * float(np.median(vg_wall)),
                "value_and_grad_cpu_ms": 1e3 * float(np.median(vg_cpu)),
            }
        )
        print(rows[-1], file=sys.stderr, flush=True)
    return rows


def timing_table(rows: list[dict]) -> list[str]:
    """Markdown lines of :func:`timing` rows (the last column: CPU of one evaluation per event and
    cluster, fixed costs included)."""
    lines = [
        "| events | K | segmentation wall s | CPU s | iterations | value_and_grad wall ms | CPU ms "
        "| CPU us per event and cluster |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        per = 1e3 * r["value_and_grad_cpu_ms"] / (r["events"] * r["K"])
        lines.append(
            f"| {r['events']} | {r['K']} | {r['segment_wall_s']:.2f} | {r['segment_cpu_s']:.2f} | "
            f"{r['iterations']:.0f} | {r['value_and_grad_wall_ms']:.1f} | {r['value_and_grad_cpu_ms']:.1f} | "
            f"{per:.3f} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m cmax_taichi.lab.segment_eval",
        description="Motion segmentation with and without collapse regularizers on synthetic scenes.",
    )
    parser.add_argument(
        "--source",
        choices=["simulator", "numpy"],
        default="simulator",
        help="scenes from the event simulator (default) or the fast NumPy edge scenes",
    )
    parser.add_argument("--objects", type=int, nargs="+", default=[2, 3, 4], help="objects per scene")
    parser.add_argument("--scenes", type=int, default=3, help="scenes (seeds) per object count")
    parser.add_argument("--events", type=int, default=30000, help="events per scene")
    parser.add_argument("--lam", type=float, default=1.0, help="weight of each regularizer")
    parser.add_argument(
        "--extra-clusters", type=int, nargs="+", default=[0, 1], help="K - objects (several: one run each)"
    )
    parser.add_argument("--timing", action="store_true", help="measure the speed instead (see timing())")
    args = parser.parse_args(argv)
    if args.timing:
        print("\n".join(timing_table(timing())))
        return 0
    regs = {"none": {}, f"div+def ({args.lam:g})": {"divergence": args.lam, "deformation": args.lam}}
    make = simulated_scene if args.source == "simulator" else synthetic_scene
    scenes = [make(k, args.events, seed=100 * k + s) for k in args.objects for s in range(args.scenes)]
    t0 = time.perf_counter()
    rows = []
    for extra in args.extra_clusters:
        rows += compare(scenes, regularizer_sets=regs, extra_clusters=extra, on_row=_print_row)
    print(_table(rows))
    print(f"\n({len(rows)} segmentations in {time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
