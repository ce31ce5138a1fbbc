"""Float64 NumPy reference of the dense flow model (docs/FORMULAS.md, "Dense flow model"), written
independently of ``kernels/dense_flow.py`` and ``cmax_taichi/flow/`` to check them.

Every quantity is built from its definition: the bilinear interpolant of the node flow at each event
(weights of the four nodes of its cell), its Jacobian from the derivatives of those weights, the warp
``x'_r = x - (t - t_r) u(x)`` to each reference time, ``det`` by ``numpy.linalg.det`` of
``I - dt_r Du``, ``div`` as the trace of ``Du``; the IWE, blur and objectives of :mod:`reference`; the
maps and penalties of the divergence and deformation regularizers at every reference; the weighted
harmonic mean of the normalised objectives; the smoothness terms by explicit loops over the grid's
edges. :func:`central_difference_grad` gives dJ/dU by central differences.

Units: positions px, times s, node flow px/s, divergence 1/s.
"""

from __future__ import annotations

import numpy as np

from cmax_taichi.testing.reference import (
    DEF_FLOOR,
    KAPPA,
    bilinear_votes,
    objective_value,
    polarity_iwe,
)

#: Charbonnier constant of ``total_variation`` (strain units)
TV_EPS = 1e-3
_REF_FRACTIONS = {"first": 0.0, "middle": 0.5, "last": 1.0}


def node_weights(x, y, grid: tuple[int, int], sensor_size: tuple[int, int]):
    """For each position: the flat indices of the 4 nodes of its cell ``(N, 4)``, their bilinear weights
    ``(N, 4)`` and the weights' x and y derivatives ``(N, 4)`` (1/px). Nodes are numbered row by row,
    ``(nx + 1)`` per row; positions outside the grid use the nearest border cell."""
    nx, ny = grid
    W, H = sensor_size
    sx, sy = (W - 1) / nx, (H - 1) / ny
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    i = np.minimum(np.maximum(np.floor(x / sx), 0), nx - 1).astype(np.int64)
    j = np.minimum(np.maximum(np.floor(y / sy), 0), ny - 1).astype(np.int64)
    a = x / sx - i
    b = y / sy - j
    idx = np.stack(
        [j * (nx + 1) + i, j * (nx + 1) + i + 1, (j + 1) * (nx + 1) + i, (j + 1) * (nx + 1) + i + 1], 1
    )
    w = np.stack([(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b], 1)
    wx = np.stack([-(1 - b), 1 - b, -b, b], 1) / sx
    wy = np.stack([-(1 - a), -a, 1 - a, a], 1) / sy
    return idx, w, wx, wy


def dense_warp(x, y, t, nodes, *, grid, sensor_size, t_ref: float):
    """Warp events with the node flow ``nodes`` (``(ny + 1, nx + 1, 2)`` px/s) to ``t_ref`` (s).

    Returns
    -------
    dict
        ``xw``, ``yw`` (px), ``u`` (N, 2) px/s, ``Du`` (N, 2, 2) 1/s (``Du[k, c, d] = du_c/dx_d``),
        ``det`` (``det(I - dt Du)``), ``div`` (1/s).
    """
    U = np.asarray(nodes, dtype=np.float64).reshape(-1, 2)
    idx, w, wx, wy = node_weights(x, y, grid, sensor_size)
    u = np.einsum("nk,nkc->nc", w, U[idx])
    du_dx = np.einsum("nk,nkc->nc", wx, U[idx])
    du_dy = np.einsum("nk,nkc->nc", wy, U[idx])
    Du = np.stack([du_dx, du_dy], axis=2)  # [n, component, derivative]
    dt = np.asarray(t, dtype=np.float64) - float(t_ref)
    xw = np.asarray(x, dtype=np.float64) - dt * u[:, 0]
    yw = np.asarray(y, dtype=np.float64) - dt * u[:, 1]
    jac = np.eye(2)[None] - dt[:, None, None] * Du
    return {
        "xw": xw,
        "yw": yw,
        "u": u,
        "Du": Du,
        "det": np.linalg.det(jac),
        "div": np.trace(Du, axis1=1, axis2=2),
    }


def smoothness_value(name: str, nodes, *, grid, sensor_size, duration: float) -> float:
    """``total_variation``, ``quadratic`` or ``curvature`` of the node displacements over the window
    (loops; docs/FORMULAS.md, "Smoothness terms")."""
    nx, ny = grid
    W, H = sensor_size
    sx, sy = (W - 1) / nx, (H - 1) / ny
    D = np.asarray(nodes, dtype=np.float64).reshape(ny + 1, nx + 1, 2) * duration
    if name == "curvature":
        return _curvature(D, nx, ny, sx, sy, float(max(W, H)))
    terms = []
    for j in range(ny + 1):
        for i in range(nx + 1):
            for c in range(2):
                if i < nx:
                    terms.append((D[j, i + 1, c] - D[j, i, c]) / sx)
                if j < ny:
                    terms.append((D[j + 1, i, c] - D[j, i, c]) / sy)
    e = np.array(terms)
    if name == "total_variation":
        return float(np.mean(np.sqrt(e * e + TV_EPS**2) - TV_EPS))
    if name == "quadratic":
        return float(np.mean(e * e))
    raise ValueError(f"unknown smoothness {name!r}")


def _curvature(D, nx: int, ny: int, sx: float, sy: float, side: float) -> float:
    """``L^2 [mean(D_xx^2) + mean(D_yy^2) + 2 mean(D_xy^2)]`` over both components; a mean is absent
    where the grid has fewer than 2 cells along its axis."""
    xx, yy, xy = [], [], []
    for j in range(ny + 1):
        for i in range(nx + 1):
            for c in range(2):
                if 0 < i < nx:
                    xx.append((D[j, i + 1, c] - 2.0 * D[j, i, c] + D[j, i - 1, c]) / (sx * sx))
                if 0 < j < ny:
                    yy.append((D[j + 1, i, c] - 2.0 * D[j, i, c] + D[j - 1, i, c]) / (sy * sy))
                if i < nx and j < ny:
                    xy.append((D[j + 1, i + 1, c] - D[j + 1, i, c] - D[j, i + 1, c] + D[j, i, c]) / (sx * sy))
    total = 2.0 * float(np.mean(np.square(xy)))
    for terms in (xx, yy):
        if terms:
            total += float(np.mean(np.square(terms)))
    return side * side * total


def dense_evaluate(
    x,
    y,
    t,
    p,
    nodes,
    *,
    grid: tuple[int, int],
    sensor_size: tuple[int, int],
    references=("first",),
    reference_weights=None,
    objective: str = "variance",
    normalize: bool = True,
    blur_sigma: float = 1.0,
    polarity: str = "ignore",
    weights=None,
    lambda_div: float = 0.0,
    lambda_def: float = 0.0,
    smoothness: dict | None = None,
    kink_width: float = 0.0,
) -> dict:
    """J of a dense flow (docs/FORMULAS.md, "Dense flow model").

    ``references``: names ("first", "middle", "last") or fractions of the window; ``reference_weights``
    (default equal) are normalised to sum 1. Returns ``J``, ``H`` (the weighted harmonic mean of
    ``G_r / G0``), ``G`` (per reference, raw), ``G0``, ``R_div``, ``R_def`` (weighted over the
    references), per-reference lists ``R_div_r``, ``R_def_r``, ``iwe`` (list of (C, H, W)) and
    ``smoothness`` values. ``kink_width`` > 0 rounds the kinks of the divergence's hinge and of the
    deformation's ``max(D, 1/D)`` (docs/FORMULAS.md, "Rounded kinks").
    """
    W, H = (int(v) for v in sensor_size)
    x, y, t, p = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (x, y, t, p))
    n = x.size
    pol = np.where(p > 0, 1.0, -1.0)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    fr = [(_REF_FRACTIONS[r] if isinstance(r, str) else float(r)) for r in references]
    om = np.ones(len(fr)) if reference_weights is None else np.asarray(reference_weights, dtype=np.float64)
    om = om / om.sum()
    T = float(t.max() - t.min())
    t0 = float(t.min())
    mean_t = float(np.mean(t))

    def iwe_of(xw, yw):
        return polarity_iwe(xw, yw, w, pol, polarity, W, H, blur_sigma)

    g0 = objective_value(objective, iwe_of(x, y)) if normalize else 1.0
    G, iwes, r_div, r_def = [], [], [], []
    aw = np.abs(w)
    for f in fr:
        t_r = t0 + f * T
        q = dense_warp(x, y, t, nodes, grid=grid, sensor_size=(W, H), t_ref=t_r)
        img = iwe_of(q["xw"], q["yw"])
        iwes.append(img)
        G.append(objective_value(objective, img))
        count = bilinear_votes(q["xw"], q["yw"], aw, W, H)
        ndiv = bilinear_votes(q["xw"], q["yw"], aw * q["div"], W, H)
        ndef = bilinear_votes(q["xw"], q["yw"], aw * np.abs(q["det"]), W, H)
        support = count > 0
        safe = np.where(support, count, 1.0)
        m = count / (count + KAPPA)
        msum = float(np.sum(m))
        div_map = np.where(support, ndiv / safe, 0.0)
        d = np.maximum(np.where(support, ndef / safe, 1.0), DEF_FLOOR)
        alpha = np.where(support, _round_max(d, 1.0 / d, kink_width) - 1.0, 0.0)
        s_t = 1.0 if t_r <= mean_t else -1.0
        r_div.append(
            float(_round_max(s_t * T * float(np.sum(m * div_map)) / msum, 0.0, kink_width))
            if msum > 0
            else 0.0
        )
        r_def.append(float(np.sum(m * alpha)) / msum if msum > 0 else 0.0)
    G = np.array(G)
    if np.all(G > 0):
        hval = 1.0 / float(np.sum(om * g0 / G))
    else:
        hval = 0.0
    R_div = float(np.sum(om * np.array(r_div)))
    R_def = float(np.sum(om * np.array(r_def)))
    smooth = {
        name: smoothness_value(name, nodes, grid=grid, sensor_size=(W, H), duration=T)
        for name in (smoothness or {})
    }
    J = (
        hval
        - lambda_div * R_div
        - lambda_def * R_def
        - sum((smoothness or {})[k] * v for k, v in smooth.items())
    )
    return {
        "J": float(J),
        "H": hval,
        "G": G.tolist(),
        "G0": float(g0),
        "R_div": R_div,
        "R_def": R_def,
        "R_div_r": r_div,
        "R_def_r": r_def,
        "iwe": iwes,
        "smoothness": smooth,
    }


def _round_max(a, b, width: float):
    """``max(a, b) = (a + b + |a - b|) / 2`` with ``|z|`` rounded to ``z^2 / (2 width) + width / 2`` where
    ``|z| < width`` (``width`` 0: exact)."""
    z = np.asarray(a, dtype=np.float64) - b
    absz = np.abs(z)
    if width > 0:
        absz = np.where(absz < width, z * z / (2 * width) + width / 2, absz)
    return 0.5 * (a + b + absz)


def central_difference_grad(x, y, t, p, nodes, *, step: float, **kwargs) -> np.ndarray:
    """dJ/dU (shape of ``nodes``, 1/(px/s)) by central differences of :func:`dense_evaluate` with a
    step of ``step`` px/s per node value."""
    U = np.asarray(nodes, dtype=np.float64)
    grad = np.zeros(U.size)
    flat = U.reshape(-1)
    for k in range(flat.size):
        up, um = flat.copy(), flat.copy()
        up[k] += step
        um[k] -= step
        jp = dense_evaluate(x, y, t, p, up.reshape(U.shape), **kwargs)["J"]
        jm = dense_evaluate(x, y, t, p, um.reshape(U.shape), **kwargs)["J"]
        grad[k] = (jp - jm) / (2 * step)
    return grad.reshape(U.shape)
