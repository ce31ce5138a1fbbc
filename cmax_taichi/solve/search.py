"""The global initialisation of :func:`cmax_taichi.maximize`: grid (with a beam of zooming grids),
random and TPE searches over a box in the optimizer's internal units (px of displacement over the
window; see :mod:`cmax_taichi.solve.optimize`). Each returns every evaluated ``(value, u)``.
"""

from __future__ import annotations

import math

import numpy as np


def odd_points_per_dim(budget: int, n_dims: int) -> int:
    n = max(3, int(math.floor(budget ** (1.0 / n_dims) + 1e-9)))
    n = min(n, 101)
    return n if n % 2 else n - 1


def distinct_top(points: list[tuple[float, np.ndarray]], k: int, min_dist: np.ndarray) -> list:
    """The ``k`` best points, skipping any within ``min_dist`` (per dimension) of a better one."""
    out: list[tuple[float, np.ndarray]] = []
    for val, u in sorted(points, key=lambda p: -p[0]):
        if not math.isfinite(val):
            continue
        if all(np.any(np.abs(u - w) > min_dist) for _, w in out):
            out.append((val, u))
            if len(out) == k:
                break
    return out


def grid_search(obj, lo, hi, *, budget, beam, min_spacing, extra) -> list[tuple[float, np.ndarray]]:
    """Coarse grid over the box, then a beam of zooming 3^P grids (spacing halves) down to
    ``min_spacing`` px. Returns every evaluated (value, u)."""
    P = len(lo)
    n = odd_points_per_dim(budget, P)
    axes = [np.linspace(lo[i], hi[i], n) for i in range(P)]
    mesh = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, P)
    seen: dict[tuple, float] = {}

    def evaluate(u):
        key = tuple(np.round(u, 9))
        if key not in seen:
            seen[key] = obj.value(u)
        return seen[key]

    for u in list(mesh) + list(extra):
        evaluate(np.clip(u, lo, hi))
    spacing = (hi - lo) / (n - 1)
    offsets = np.stack(np.meshgrid(*([np.array([-1.0, 0.0, 1.0])] * P), indexing="ij"), -1).reshape(-1, P)
    while np.max(spacing) > min_spacing:
        spacing = spacing / 2.0
        points = [(v, np.array(k)) for k, v in seen.items()]
        for _, c in distinct_top(points, beam, spacing):
            for off in offsets:
                evaluate(np.clip(c + off * spacing, lo, hi))
    return [(v, np.array(k)) for k, v in seen.items()]


def random_search(obj, lo, hi, *, budget, rng, extra) -> list[tuple[float, np.ndarray]]:
    samples = rng.uniform(lo, hi, size=(max(1, budget), len(lo)))
    return [(obj.value(u), np.array(u)) for u in list(samples) + list(extra)]


def tpe_search(obj, lo, hi, *, budget, seed, extra) -> list[tuple[float, np.ndarray]]:
    try:
        import optuna
    except ImportError:
        raise ImportError(
            "init='tpe' needs optuna: pip install optuna (or 'cmax-taichi[tpe]'), or use init='grid'"
        ) from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=max(10, budget // 10))
    study = optuna.create_study(direction="maximize", sampler=sampler)
    names = [f"u{i}" for i in range(len(lo))]
    for u in extra:
        study.enqueue_trial({n: float(np.clip(x, a, b)) for n, x, a, b in zip(names, u, lo, hi, strict=True)})
    out: list[tuple[float, np.ndarray]] = []

    def objective(trial):
        u = np.array([trial.suggest_float(n, a, b) for n, a, b in zip(names, lo, hi, strict=True)])
        val = obj.value(u)
        out.append((val, u))
        return val if math.isfinite(val) else -1e30

    study.optimize(objective, n_trials=max(1, budget) + len(extra))
    return out
