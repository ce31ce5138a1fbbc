"""PyTorch twin of the CMax pipeline, written the way PyTorch CMax code computes it (benchmark only).

Warp the events with tensor operations, vote them into the image with ``scatter_add_`` (bilinear
weights, out-of-image corners masked), blur with two 1-D ``conv2d`` (zero padding), take the
variance, vote the regularizer maps the same way, and let autograd produce dJ/dtheta. It follows
docs/FORMULAS.md for the configuration the benchmark sweeps: warps ``translation2``, ``rotation3``,
``mitrokhin4`` (and ``zoom1``), objective ``variance`` normalised by ``G(0)``, polarity ignored, no
per-event weights, divergence and deformation regularizers.

PyTorch is an optional benchmark extra (``pip install "cmax-taichi[bench]"``); nothing else in the
package imports this module. Units as in the rest of the library: px, s, px/s, 1/s, rad/s.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812 - the PyTorch convention

__all__ = ["TorchCMax", "TWIN_WARPS"]

TWIN_WARPS = ("zoom1", "translation2", "rotation3", "mitrokhin4")
KAPPA = 0.05  # soft support m = C / (C + kappa), as kernels/maps.py
DEF_FLOOR = 1e-3  # deformation guard, as kernels/maps.py
MIN_RAY_Z = 1e-6  # rotation3: rays at or behind this depth are dropped
ROT_SERIES_PHI = 1e-4  # rotation3: Rodrigues series below this angle (rad)


class TorchCMax:
    """The augmented objective ``J = G / G0 - lambda_div R_div - lambda_def R_def`` in PyTorch.

    Parameters
    ----------
    x, y, t : array_like, shape (N,)
        Event positions (px) and times (s), sorted by time.
    warp : str
        One of :data:`TWIN_WARPS`.
    sensor_size : (int, int)
        ``(W, H)`` (px).
    center : (float, float)
        Centre ``(c_x, c_y)`` of the zoom / rotation models (px).
    focal : (float, float), optional
        ``(f_x, f_y)`` (px), needed by ``rotation3``.
    t_ref : float, optional
        Reference time (s); default the first event's time.
    blur_sigma : float
        Gaussian blur (px); 0 = none.
    lambda_div, lambda_def : float
        Regularizer weights (a zero weight skips that map entirely, as PyTorch code would).
    dtype : torch.dtype
        ``torch.float64`` (default) or ``torch.float32``.
    device : str
        ``"cpu"`` or ``"cuda"``.
    """

    def __init__(
        self,
        x,
        y,
        t,
        *,
        warp: str,
        sensor_size: tuple[int, int],
        center: tuple[float, float],
        focal: tuple[float, float] | None = None,
        t_ref: float | None = None,
        blur_sigma: float = 1.0,
        lambda_div: float = 0.0,
        lambda_def: float = 0.0,
        dtype: torch.dtype = torch.float64,
        device: str = "cpu",
    ) -> None:
        if warp not in TWIN_WARPS:
            raise ValueError(f"the PyTorch twin implements {TWIN_WARPS}, not {warp!r}")
        if warp == "rotation3" and focal is None:
            raise ValueError("rotation3 needs focal=(fx, fy)")
        self.warp = warp
        self.W, self.H = (int(v) for v in sensor_size)
        self.dtype, self.device = dtype, torch.device(device)
        t = np.asarray(t, dtype=np.float64)
        self.T = float(t.max() - t.min())
        t0 = float(t.min()) if t_ref is None else float(t_ref)
        # orientation of R_div: +1 when t_ref is before the mean event time (docs/FORMULAS.md)
        self.s_t = 1.0 if t0 <= float(t.mean()) else -1.0

        def as_tensor(a):
            return torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=dtype, device=self.device)

        self.x, self.y, self.dt = as_tensor(x), as_tensor(y), as_tensor(t - t0)
        self.cx, self.cy = (float(v) for v in center)
        self.fx, self.fy = (float(v) for v in (focal or (1.0, 1.0)))
        self.lambda_div, self.lambda_def = float(lambda_div), float(lambda_def)
        self.n_params = {"zoom1": 1, "translation2": 2, "rotation3": 3, "mitrokhin4": 4}[warp]
        self.taps = None
        if blur_sigma > 0:
            r = int(math.ceil(3 * blur_sigma))
            g = torch.exp(
                -(torch.arange(-r, r + 1, dtype=dtype, device=self.device) ** 2) / (2 * blur_sigma**2)
            )
            self.taps = g / g.sum()
        with torch.no_grad():
            self.G0 = float(self._objective(torch.zeros(self.n_params, dtype=dtype, device=self.device)))

    # --- pipeline -------------------------------------------------------------------------------
    def _warp(self, th: torch.Tensor):
        """Warped positions (px), |det dx'/dx| and div v (1/s) per event; ``ok`` masks dropped events."""
        x, y, dt = self.x, self.y, self.dt
        xt, yt = x - self.cx, y - self.cy
        ok = None
        if self.warp == "translation2":
            xw, yw = x - dt * th[0], y - dt * th[1]
            det = torch.ones_like(x)
            div = torch.zeros_like(x)
        elif self.warp == "zoom1":
            s = 1.0 - dt * th[0]
            xw, yw = self.cx + s * xt, self.cy + s * yt
            det = s * s
            div = (2.0 * th[0]).expand_as(x)
        elif self.warp == "mitrokhin4":
            T = self.T
            sig = dt / T
            amp = th[2] * T + 1.0
            a11, a21 = amp * torch.cos(th[3] * T), amp * torch.sin(th[3] * T)
            xw = x - dt * th[0] - sig * ((a11 - 1.0) * xt - a21 * yt)
            yw = y - dt * th[1] - sig * (a21 * xt + (a11 - 1.0) * yt)
            det = (1.0 + sig - sig * a11) ** 2 + (sig * a21) ** 2
            div = (2.0 * (a11 - 1.0) / T).expand_as(x)
        else:  # rotation3: Rodrigues rotation of the calibrated ray, X' = X + a (k x X) + b k x (k x X)
            X = torch.stack([xt / self.fx, yt / self.fy, torch.ones_like(x)], dim=-1)
            k = dt[:, None] * th[None, :]
            phi2 = (k * k).sum(-1)
            small = phi2 < ROT_SERIES_PHI**2
            phi = torch.sqrt(torch.where(small, torch.ones_like(phi2), phi2))
            a = torch.where(small, 1.0 - phi2 / 6.0, torch.sin(phi) / phi)
            b = torch.where(small, 0.5 - phi2 / 24.0, (1.0 - torch.cos(phi)) / (phi * phi))
            kx = torch.linalg.cross(k, X, dim=-1)
            Xr = X + a[:, None] * kx + b[:, None] * torch.linalg.cross(k, kx, dim=-1)
            z = Xr[:, 2]
            ok = z > MIN_RAY_Z
            zs = torch.where(ok, z, torch.ones_like(z))
            xw = self.cx + self.fx * Xr[:, 0] / zs
            yw = self.cy + self.fy * Xr[:, 1] / zs
            det = 1.0 / zs**3
            div = -3.0 * (th[1] * X[:, 0] - th[0] * X[:, 1])
        return xw, yw, det.abs(), div, ok

    def _votes(self, xw, yw, ok, per_event: list[torch.Tensor]) -> torch.Tensor:
        """Bilinear ``scatter_add`` of each per-event value into its own image: (K, H, W)."""
        W, H = self.W, self.H
        inside = (xw > -1.0) & (xw < W) & (yw > -1.0) & (yw < H)
        if ok is not None:
            inside = inside & ok
        x0, y0 = torch.floor(xw), torch.floor(yw)
        ax, ay = xw - x0, yw - y0
        x0, y0 = x0.long(), y0.long()
        K = len(per_event)
        flat = torch.zeros(K * H * W, dtype=self.dtype, device=self.device)
        vals = torch.stack(per_event)  # (K, N)
        for dx, dy, wgt in (
            (0, 0, (1 - ax) * (1 - ay)),
            (1, 0, ax * (1 - ay)),
            (0, 1, (1 - ax) * ay),
            (1, 1, ax * ay),
        ):
            col, row = x0 + dx, y0 + dy
            keep = inside & (col >= 0) & (col < W) & (row >= 0) & (row < H)
            idx = torch.where(keep, row * W + col, torch.zeros_like(col))
            w = torch.where(keep, wgt, torch.zeros_like(wgt))
            offsets = (torch.arange(K, device=self.device) * (H * W))[:, None]
            flat = flat.scatter_add(0, (idx[None, :] + offsets).reshape(-1), (vals * w[None, :]).reshape(-1))
        return flat.view(K, H, W)

    def _blur(self, img: torch.Tensor) -> torch.Tensor:
        if self.taps is None:
            return img
        r = (self.taps.numel() - 1) // 2
        out = F.conv2d(img[None, None], self.taps.view(1, 1, 1, -1), padding=(0, r))
        return F.conv2d(out, self.taps.view(1, 1, -1, 1), padding=(r, 0))[0, 0]

    def _objective(self, th: torch.Tensor, parts: dict | None = None) -> torch.Tensor:
        xw, yw, det, div, ok = self._warp(th)
        ones = torch.ones_like(xw)
        use_maps = self.lambda_div != 0.0 or self.lambda_def != 0.0
        per_event = [ones]
        if use_maps:
            per_event += [ones, div, det]  # count, numerators of the divergence and deformation maps
        votes = self._votes(xw, yw, ok, per_event)
        iwe = self._blur(votes[0])
        g_raw = (iwe * iwe).mean() - iwe.mean() ** 2
        J = g_raw / (self.G0 if hasattr(self, "G0") else 1.0)
        if parts is not None:
            parts["G_raw"] = g_raw
        if use_maps:
            count = votes[1]
            has = count > 0
            safe = torch.where(has, count, torch.ones_like(count))
            m = count / (count + KAPPA)
            msum = m.sum()
            div_map = torch.where(has, votes[2] / safe, torch.zeros_like(count))
            d = torch.clamp_min(torch.where(has, votes[3] / safe, torch.ones_like(count)), DEF_FLOOR)
            alpha = torch.where(has, torch.maximum(d, 1.0 / d) - 1.0, torch.zeros_like(count))
            # one-sided: net contraction is penalised, expansion is not rewarded (docs/FORMULAS.md)
            r_div = torch.clamp_min((m * self.s_t * self.T * div_map).sum() / msum, 0.0)
            r_def = (m * alpha).sum() / msum
            J = J - self.lambda_div * r_div - self.lambda_def * r_def
        return J

    # --- public ---------------------------------------------------------------------------------
    def value(self, theta) -> float:
        """J at ``theta`` (no autograd graph)."""
        with torch.no_grad():
            th = torch.as_tensor(np.asarray(theta, dtype=np.float64), dtype=self.dtype, device=self.device)
            return float(self._objective(th))

    def value_and_grad(self, theta) -> tuple[float, np.ndarray]:
        """``(J, dJ/dtheta)`` by autograd."""
        th = torch.tensor(np.asarray(theta, dtype=np.float64), dtype=self.dtype, device=self.device)
        th.requires_grad_(True)
        J = self._objective(th)
        J.backward()
        return float(J.detach()), th.grad.detach().cpu().numpy().astype(np.float64)
