"""Motion segmentation by multi-model Contrast Maximization (Stoffregen et al., ICCV 2019), protected
from event collapse by the regularizers of Shiba et al. (Sensors 2022).

:func:`segment` alternates

(a) gradient ascent (Adam) on every cluster's parameters with the memberships fixed, on the augmented
    multi-cluster objective of :class:`~cmax_taichi.pipeline.clusters.MultiClusterCMax`
    ``J = sum_j [G_j / G0_j - sum_r lambda_r R_jr]``;
(b) the membership update of Stoffregen et al.: ``P[i, j]`` proportional to ``I_j(x'_ij)``, cluster j's
    blurred, membership-weighted IWE at event i's position warped by cluster j (sharpened by a
    temperature, or hard),

until the memberships stop changing. The clusters start from the translational motions that image
patches vote for (each patch's sharpest candidate of a coarse, then a fine grid, scored by CMax on a
subsample of the events; no ground truth needed).
Algorithm and formulas: docs/SEGMENTATION.md.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TextIO

import numpy as np

from cmax_taichi.core import backend
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.models.warps import WarpModel
from cmax_taichi.pipeline.clusters import MultiClusterCMax
from cmax_taichi.solve.optimize import AdamStepper

__all__ = ["SegmentationResult", "segment"]


@dataclass
class SegmentationResult:
    """What :func:`segment` found.

    Attributes
    ----------
    labels : ndarray of int, shape (N,)
        Cluster of each input event (argmax of ``probabilities``); -1 for events dropped by the
        camera's undistortion (outside the sensor).
    probabilities : ndarray, shape (N, K)
        Memberships (rows sum to 1 over the non-empty clusters; 0 rows for dropped events).
    thetas : ndarray, shape (K, P), or list of K arrays
        Each cluster's parameters in the model's physical units (px/s, 1/s, rad/s); a list when the
        clusters use models with different parameter counts.
    warps : tuple of str
        Each cluster's warp model.
    iwes : ndarray, shape (K, H, W)
        Each cluster's sharpened (blurred, membership-weighted) IWE at ``thetas``, in votes.
    empty : ndarray of bool, shape (K,)
        Clusters that lost their events (their column of ``probabilities`` is 0).
    history : list of dict
        One entry per iteration: ``J`` (objective after the parameter step), ``sizes`` (events per
        cluster, argmax), ``mass`` (sum of memberships per cluster), ``changed`` (fraction of labels
        that changed), ``dP`` (mean absolute membership change), ``seconds`` (since the start).
    seconds : float
        Wall-clock time of the whole segmentation, s (including kernel compilation, if any).
    converged : bool
        The memberships stopped changing before ``max_iterations``.
    value : float
        Final multi-cluster objective J.
    events : Events
        The events that were segmented (after undistortion when a camera with distortion was given).
    kept : ndarray of bool, shape (N,)
        Which input events are in ``events``.
    """

    labels: np.ndarray
    probabilities: np.ndarray
    thetas: np.ndarray | list
    warps: tuple
    iwes: np.ndarray
    empty: np.ndarray
    history: list = field(default_factory=list)
    seconds: float = 0.0
    converged: bool = False
    value: float = float("nan")
    events: Events | None = None
    kept: np.ndarray | None = None

    @property
    def n_clusters(self) -> int:
        return int(self.probabilities.shape[1])

    @property
    def sizes(self) -> np.ndarray:
        """Events per cluster (by label)."""
        return np.bincount(self.labels[self.labels >= 0], minlength=self.n_clusters)

    def __repr__(self) -> str:
        return (
            f"SegmentationResult(K={self.n_clusters}, warps={','.join(self.warps)}, "
            f"sizes={self.sizes.tolist()}, "
            f"empty={np.flatnonzero(self.empty).tolist()}, iterations={len(self.history)}, "
            f"converged={self.converged}, seconds={self.seconds:.2f})"
        )


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------
def _check_int(name: str, value, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if int(value) < low:
        raise ValueError(f"{name} must be at least {low}, got {value}")
    return int(value)


def _check_positive(name: str, value) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number, got {value}")
    return value


def _position_jacobian(prob: MultiClusterCMax) -> np.ndarray:
    """``d x'_ij / d theta`` at theta = 0 by central differences, shape (N, n_total, 2): row a holds
    the derivative of the positions warped by the cluster that owns flat parameter a.

    The clusters are independent, so parameter number k of every cluster is perturbed at once. Two
    passes: a unit step measures how far each parameter moves the events, then a step that moves them
    about 0.5 px gives the derivative (exact for parameters that enter linearly, accurate in f32).
    """
    n, P = prob.n_events, prob.n_total
    owner = np.repeat(np.arange(prob.n_clusters), prob.n_params)
    rank = np.concatenate([np.arange(k) for k in prob.n_params])  # index of each parameter in its cluster
    jac = np.zeros((n, P, 2))
    steps = np.ones(P)
    for _pass in range(2):
        for k in range(max(prob.n_params)):
            sel = rank == k
            tp = np.where(sel, steps, 0.0)
            diff = prob.warped_positions(tp) - prob.warped_positions(-tp)  # (N, K, 2)
            for a in np.flatnonzero(sel):
                jac[:, a] = diff[:, owner[a]] / (2 * steps[a])
        moved = np.sqrt(np.mean(np.sum(jac**2, axis=2), axis=0)) * steps  # rms px per step
        if np.all((moved > 0.05) & (moved < 5.0)) or _pass == 1:
            break
        steps = np.where(moved > 0, 0.5 * steps / np.maximum(moved, 1e-300), 1.0)
    return jac


def _translation_to_params(jac: np.ndarray, prob: MultiClusterCMax, j: int, v: np.ndarray) -> np.ndarray:
    """Cluster j's parameters whose warp best reproduces the constant flow ``v`` (px/s) at theta = 0:
    least squares of ``J_j theta ~ -dt v`` over the events (linearised)."""
    o, k = prob.offsets[j], prob.n_params[j]
    dt = prob.events.t - prob.t_ref
    A = jac[:, o : o + k, :].transpose(0, 2, 1).reshape(-1, k)  # (2N, k)
    b = (-dt[:, None] * v[None, :]).reshape(-1)
    theta, *_ = np.linalg.lstsq(A, b, rcond=None)
    return theta


def _memberships(values: np.ndarray, active: np.ndarray, temperature: float, hard: bool) -> np.ndarray:
    """Stoffregen's update: ``P[i, j] ~ I_j(x'_ij)^(1/temperature)`` over the active clusters (uniform
    where no active cluster sees the event); ``hard``: one-hot argmax."""
    n, K = values.shape
    v = np.where(active[None, :], np.maximum(values, 0.0), 0.0)
    if hard:
        P = np.zeros_like(v)
        P[np.arange(n), np.argmax(np.where(active[None, :], v, -1.0), axis=1)] = 1.0
        return P
    scale = float(v.max()) if v.size and v.max() > 0 else 1.0
    v = v / scale
    if temperature != 1.0:
        v = v ** (1.0 / temperature)
    total = v.sum(axis=1, keepdims=True)
    uniform = np.where(active, 1.0 / max(int(active.sum()), 1), 0.0)[None, :]
    with np.errstate(invalid="ignore", divide="ignore"):
        P = np.where(total > 0, v / np.where(total > 0, total, 1.0), uniform)
    return P


def _renormalise(P: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Rows of P restricted to the active clusters, summing to 1 (uniform where a row is all 0)."""
    P = np.where(active[None, :], P, 0.0)
    total = P.sum(axis=1, keepdims=True)
    uniform = np.where(active, 1.0 / max(int(active.sum()), 1), 0.0)[None, :]
    return np.where(total > 0, P / np.where(total > 0, total, 1.0), uniform)


def _sparsify(P: np.ndarray, floor: float) -> np.ndarray:
    """Memberships below ``floor`` set to 0 (their votes are then skipped by the kernels)."""
    return np.where(floor > P, 0.0, P)


def _duplicates(P: np.ndarray, positions: np.ndarray, active: np.ndarray, distance: float) -> list:
    """Pairs ``(keep, drop)`` of active clusters that move the events alike: the membership-weighted
    mean distance between the two clusters' warped positions of the events either holds is below
    ``distance`` px. The cluster with the smaller membership mass is dropped (once per cluster)."""
    mass = P.sum(axis=0)
    out: list[tuple[int, int]] = []
    gone: set[int] = set()
    idx = [j for j in np.argsort(-mass) if active[j]]
    for a, j in enumerate(idx):
        for k in idx[a + 1 :]:
            if j in gone or k in gone:
                continue
            w = P[:, j] + P[:, k]
            d = np.linalg.norm(positions[:, j] - positions[:, k], axis=1)
            ok = np.isfinite(d)
            if w[ok].sum() > 0 and float(np.sum(w[ok] * d[ok]) / w[ok].sum()) < distance:
                out.append((int(j), int(k)))
                gone.add(k)
    return out


def _labels(P: np.ndarray, active: np.ndarray) -> np.ndarray:
    return np.argmax(np.where(active[None, :], P, -1.0), axis=1)


def _candidate_scores(
    sub: Events, disp: np.ndarray, cell: float, T: float, t_ref: float, batch: int
) -> np.ndarray:
    """Per-event CMax score of translational candidates: ``s[i, c]`` = the IWE of all subsampled events
    warped by candidate c (displacement ``disp[c]`` px over the window), binned ``cell`` px per pixel and
    blurred by one bin, at event i's warped position (how many events candidate c aligns with event i).
    """
    W, H = sub.sensor_size
    Wc, Hc = int(math.ceil((W - 1) / cell)) + 1, int(math.ceil((H - 1) / cell)) + 1
    binned = Events(sub.x / cell, sub.y / cell, sub.t, sub.p, (Wc, Hc), undistorted=True, _validated=True)
    flows = disp / (cell * T)  # binned px/s
    # the candidates are scored ``batch`` at a time as the clusters of one problem, which takes at
    # least as many events as clusters: on a tiny window, fewer at a time
    batch = max(1, min(batch, len(sub)))
    prob = MultiClusterCMax(binned, batch, "translation2", blur_sigma=1.0, normalize=False, t_ref=t_ref)
    prob.set_memberships(np.ones((len(sub), batch)), identity=False)
    scores = np.zeros((len(sub), len(disp)))
    for start in range(0, len(disp), batch):
        chunk = flows[start : start + batch]
        thetas = np.zeros((batch, 2))
        thetas[: len(chunk)] = chunk
        values, _ = prob.lookup(thetas, positions=False, images_only=True)
        scores[:, start : start + len(chunk)] = values[:, : len(chunk)]
    return scores


def _patch_votes(scores: np.ndarray, sub: Events, patch: float) -> np.ndarray:
    """Local CMax votes: the events are grouped in square patches of ``patch`` px (by their unwarped
    position); each patch's total score per candidate is a local contrast measure, and the patch votes
    for its best candidate with weight ``S_best - S_mean`` (how many more aligned events that candidate
    gives the patch than an average one: patches without a clear motion, or with a few noise events
    only, weigh little)."""
    W, H = sub.sensor_size
    nx = int(math.ceil(W / patch))
    pid = (np.floor(sub.y / patch) * nx + np.floor(sub.x / patch)).astype(np.int64)
    uniq, inv = np.unique(pid, return_inverse=True)
    S = np.zeros((len(uniq), scores.shape[1]))
    np.add.at(S, inv, scores)
    best = np.argmax(S, axis=1)
    gain = S[np.arange(len(uniq)), best] - S.mean(axis=1)
    return np.bincount(best, weights=gain, minlength=scores.shape[1])


def _pick_by_votes(votes: np.ndarray, disp: np.ndarray, k: int, *, min_separation: float) -> list[int]:
    """Non-maximum suppression: up to k candidates in decreasing order of votes, each at least
    ``min_separation`` px (Chebyshev, displacement over the window) from those chosen before."""
    allowed = np.ones(len(disp), dtype=bool)
    chosen: list[int] = []
    for _ in range(k):
        if not allowed.any():
            break
        c = int(np.argmax(np.where(allowed, votes, -np.inf)))
        chosen.append(c)
        allowed &= np.max(np.abs(disp - disp[c]), axis=1) >= min_separation
    return chosen


def _grid_init(
    events: Events,
    n_clusters: int,
    *,
    max_displacement: float,
    n_sample: int,
    rng: np.random.Generator,
    t_ref: float,
    batch: int = 8,
) -> np.ndarray:
    """Pick K translational flows (px/s) by local CMax votes on a subsample of the events.

    Coarse stage: every candidate of a square grid of displacements over the window (step 4 px, up to
    ``max_displacement``) scores every event (:func:`_candidate_scores`, events binned 4 px); patches of
    an eighth of the sensor vote for their best candidate (:func:`_patch_votes`), and the ``K + 1``
    most voted candidates at least 8 px apart are kept. Fine stage at full resolution (blur 1 px): a
    7 x 7 grid of step 1 px around each of them votes again, and the K most voted candidates at least
    3 px apart are the result. Patches are
    local, so a motion that half-sharpens two objects (which a global score may prefer) gets no votes.
    Returns (K, 2) flows in px/s.
    """
    n = len(events)
    idx = np.sort(rng.choice(n, size=min(n, n_sample), replace=False))
    sub = events[idx]
    T = events.duration
    patch = max(events.sensor_size) / 8.0
    r = max(1, int(round(max_displacement / 4.0)))
    steps = np.arange(-r, r + 1, dtype=np.float64) * 4.0
    coarse = np.array([(dx, dy) for dy in steps for dx in steps])
    votes = _patch_votes(_candidate_scores(sub, coarse, 4.0, T, t_ref, batch), sub, patch)
    picks = _pick_by_votes(votes, coarse, n_clusters + 1, min_separation=8.0)
    offsets = np.arange(-3, 4, dtype=np.float64)
    fine = np.unique(
        np.array([coarse[c] + (dx, dy) for c in picks for dy in offsets for dx in offsets]).round(6), axis=0
    )
    votes = _patch_votes(_candidate_scores(sub, fine, 1.0, T, t_ref, batch), sub, patch)
    chosen = _pick_by_votes(votes, fine, n_clusters, min_separation=3.0)
    while len(chosen) < n_clusters:  # fewer distinct candidates than clusters: repeat the best
        chosen.append(chosen[0])
    return fine[chosen] / T


# --------------------------------------------------------------------------------------------------
# the driver
# --------------------------------------------------------------------------------------------------
def segment(
    events: Events,
    n_clusters: int = 2,
    warp: str | WarpModel | Sequence = "mitrokhin4",
    objective: str = "variance",
    regularizers: Mapping[str, float] | None = None,
    camera: Camera | None = None,
    *,
    t_ref: str | float = "first",
    blur_sigma: float = 1.0,
    temperature: float = 1.0,
    hard: bool = False,
    max_iterations: int = 12,
    steps: int = 8,
    learning_rate: float = 0.5,
    tol: float = 2e-3,
    init_thetas: np.ndarray | Sequence[np.ndarray] | None = None,
    max_displacement: float | None = None,
    init_events: int = 4000,
    min_cluster_fraction: float = 0.01,
    min_membership: float = 0.02,
    merge_distance: float = 1.0,
    seed: int = 0,
    progress: bool | TextIO = False,
) -> SegmentationResult:
    """Segment a window of events into K independently moving clusters.

    Parameters
    ----------
    events : Events
        The window.
    n_clusters : int
        K, 1 <= K <= number of events. Surplus clusters (K larger than the number of motions) may
        empty out; they are reported in ``result.empty``.
    warp : str, WarpModel or sequence of K of them
        Motion model of every cluster, or one per cluster (e.g. ``["translation2", "mitrokhin4"]``).
    objective : str
        Focus measure of each cluster's IWE (see :func:`cmax_taichi.objective_names`).
    regularizers : mapping of str to float, optional
        Collapse regularizers and weights, the same in every cluster, e.g.
        ``{"divergence": 1.0, "deformation": 1.0}``.
    camera : Camera, optional
        Intrinsics: centre of the zoom/rotation models (``rotation3`` needs them); distorted events
        are undistorted with it.
    t_ref : {"first", "middle", "last"} or float
        Reference time of the warps (a float: seconds on the events' clock, within the window's span
        give or take its duration).
    blur_sigma : float
        Gaussian blur of the IWEs, px.
    temperature : float
        Membership update ``P ~ I^(1/temperature)``: 1 is Stoffregen et al.'s rule, smaller is
        sharper, larger is softer.
    hard : bool
        Hard assignments (each event to the cluster whose IWE is largest at its warped position).
    max_iterations : int
        Alternations of (a) the parameter step and (b) the membership update.
    steps : int
        Adam iterations of the first parameter step (3/8 as many, at least 1, in the later ones, which
        start close to their optimum).
    learning_rate : float
        Adam step, in pixels of displacement over the window: each parameter is scaled by how far it
        moves the events (at theta = 0), so one learning rate serves px/s, 1/s and rad/s alike. It
        halves every iteration down to a tenth.
    tol : float
        Stop when the fraction of events that change cluster falls below ``tol`` and the mean
        absolute membership change below ``10 tol``.
    init_thetas : (K, P) array or list of K arrays, optional
        Starting parameters (physical units); default: the grid initialisation.
    max_displacement : float, optional
        Largest displacement over the window (px) the grid initialisation considers; default 15% of
        the larger sensor side.
    init_events : int
        Events subsampled for the grid initialisation.
    min_cluster_fraction : float
        A cluster whose membership mass falls below this fraction of the events (or below 3 events)
        is declared empty and leaves the objective.
    min_membership : float
        Memberships below this are set to 0 in the cluster images (speed: their votes are skipped).
    merge_distance : float
        Two clusters whose warps move the events they hold to within this many px of each other on
        average (membership-weighted) describe one motion: the smaller one is merged into the larger
        and reported empty. 0 disables merging.
    seed : int
        Seed of the subsampling.
    progress : bool or stream
        Show progress on stderr (or on the given stream): the set-up (the first use of a configuration
        compiles its kernels), then each iteration with its J and the share of events that changed
        cluster (:class:`~cmax_taichi.solve.sequence.ProgressBar`).

    Returns
    -------
    SegmentationResult

    Raises
    ------
    ValueError
        For an empty window, K < 1, K larger than the number of events, or bad options.
    """
    start = time.perf_counter()
    if not isinstance(events, Events):
        raise TypeError(f"events must be cmax_taichi.Events, got {type(events).__name__}")
    if len(events) == 0:
        raise ValueError("the window is empty: no events to segment")
    K = _check_int("n_clusters", n_clusters, 1)
    if len(events) < K:
        raise ValueError(f"n_clusters = {K} is more than the {len(events)} events of the window")
    temperature = _check_positive("temperature", temperature)
    max_iterations = _check_int("max_iterations", max_iterations, 1)
    steps = _check_int("steps", steps, 0)
    learning_rate = _check_positive("learning_rate", learning_rate)
    tol = _check_positive("tol", tol)
    init_events = _check_int("init_events", init_events, 2)
    seed = _check_int("seed", seed, 0)
    if max_displacement is not None:
        max_displacement = _check_positive("max_displacement", max_displacement)
    if not 0 <= float(min_cluster_fraction) < 1:
        raise ValueError(f"min_cluster_fraction must be in [0, 1), got {min_cluster_fraction}")
    if not 0 <= float(min_membership) < 1:
        raise ValueError(f"min_membership must be in [0, 1), got {min_membership}")
    merge_distance = float(merge_distance)
    if not (math.isfinite(merge_distance) and merge_distance >= 0):
        raise ValueError(f"merge_distance must be a finite number of px >= 0, got {merge_distance}")
    backend.ensure_initialized()
    rng = np.random.default_rng(seed)
    bar = None
    if progress:
        from cmax_taichi.solve.sequence import ProgressBar

        stream = progress if not isinstance(progress, bool) else None
        bar = ProgressBar(max_iterations + 1, label="segment", stream=stream, unit="step")
    try:
        prob = MultiClusterCMax(
            events,
            K,
            warp,
            objective=objective,
            regularizers=regularizers,
            camera=camera,
            t_ref=t_ref,
            blur_sigma=blur_sigma,
        )
        ev = prob.events
        W, H = ev.sensor_size
        warps = tuple(m.name for m in prob.models)

        jac = _position_jacobian(prob)
        rms = np.sqrt(np.mean(np.sum(jac**2, axis=2), axis=0))  # px of displacement per unit parameter
        scale = np.where(rms > 0, 1.0 / np.maximum(rms, 1e-300), 1.0)  # parameter units per px

        # --- initialisation --------------------------------------------------------------------------
        if init_thetas is not None:
            theta = prob.flatten(init_thetas)
        else:
            dmax = 0.15 * max(W, H) if max_displacement is None else max_displacement
            flows = _grid_init(ev, K, max_displacement=dmax, n_sample=init_events, rng=rng, t_ref=prob.t_ref)
            theta = np.concatenate([_translation_to_params(jac, prob, j, flows[j]) for j in range(K)])
        active = np.ones(K, dtype=bool)
        prob.set_memberships(np.ones((prob.n_events, K)))
        values, _ = prob.lookup(theta, positions=False)
        P = _memberships(values, active, temperature, hard)
        if bar is not None:
            bar.update("initialised")

        history: list[dict] = []
        converged = False
        value = float("nan")
        for it in range(max_iterations):
            min_mass = max(3.0, float(min_cluster_fraction) * prob.n_events)
            emptied = active & (P.sum(axis=0) < min_mass)
            if emptied.any():
                active &= ~emptied
                P = _renormalise(P, active)
            prob.set_memberships(_sparsify(P, min_membership), active)
            active = prob.active

            # (a) parameters: Adam ascent in pixel-scaled coordinates, keeping the best point seen
            lr = learning_rate * max(0.5**it, 0.1)
            n_steps = steps if it == 0 else max(1, (3 * steps) // 8)
            adam = AdamStepper(theta.size)
            best_value, best_theta = -np.inf, theta.copy()
            for s in range(n_steps + 1):
                value, grad = prob.value_and_grad(theta)
                if value > best_value:
                    best_value, best_theta = value, theta.copy()
                if s == n_steps:
                    break
                theta = theta + lr * scale * adam.direction(grad * scale)
            theta = best_theta
            value = best_value

            # (b) memberships from every cluster's IWE at the events' warped positions
            values, positions = prob.lookup(theta, positions=merge_distance > 0)
            P_new = _memberships(values, active, temperature, hard)
            merged = _duplicates(P_new, positions, active, merge_distance) if merge_distance > 0 else []
            for keep, drop in merged:
                P_new[:, keep] += P_new[:, drop]
                P_new[:, drop] = 0.0
                active[drop] = False
            changed = float(np.mean(_labels(P_new, active) != _labels(P, active)))
            dP = float(np.mean(np.abs(P_new - P)))
            P = P_new
            labels = _labels(P, active)
            done = changed < tol and dP < 10 * tol and not merged
            history.append(
                {
                    "J": value,
                    "sizes": np.bincount(labels, minlength=K).tolist(),
                    "mass": P.sum(axis=0).round(1).tolist(),
                    "changed": changed,
                    "dP": dP,
                    "active": active.tolist(),
                    "merged": merged,
                    "seconds": time.perf_counter() - start,
                }
            )
            if bar is not None:
                bar.update(f"J={value:.3f}, {100 * changed:.1f}% changed")
            if done:
                converged = True
                break

        # final images with the final memberships
        prob.set_memberships(_sparsify(P, min_membership), active)
        active = prob.active
        P = np.where(active[None, :], P, 0.0)
        value, iwes = prob.value_and_images(theta)
        labels_kept = _labels(P, active)

        n_in = len(events)
        labels = np.full(n_in, -1, dtype=np.int64)
        labels[prob.kept] = labels_kept
        probabilities = np.zeros((n_in, K))
        probabilities[prob.kept] = P
        parts = prob.unpack(theta)
        thetas = np.stack(parts) if len(set(prob.n_params)) == 1 else parts
        return SegmentationResult(
            labels=labels,
            probabilities=probabilities,
            thetas=thetas,
            warps=warps,
            iwes=iwes,
            empty=~active,
            history=history,
            seconds=time.perf_counter() - start,
            converged=converged,
            value=value,
            events=ev,
            kept=prob.kept.copy(),
        )
    finally:
        if bar is not None:
            bar.close()
