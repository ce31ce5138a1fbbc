"""Multi-cluster Contrast Maximization: K motion models competing for the events of one window.

:class:`MultiClusterCMax` is the value-and-gradient engine of motion segmentation
(:func:`cmax_taichi.segment`). Given memberships ``P`` (events x clusters, fixed), cluster j's image
is the IWE of all events warped by cluster j's parameters, each voting with weight ``P[i, j]``; the
augmented objective is the sum over clusters

    J = sum_j [ G_j(theta_j) / G0_j - lambda_div R_Div,j(theta_j) - lambda_def R_Def,j(theta_j) ]

where ``G0_j`` is cluster j's objective at the identity warp with the same memberships (so each
cluster's contrast is scale-free and lambda means the same in every cluster), and the maps of R are
built with ``|P[i, j]|`` as the event weights. Each term is exactly
``reference.evaluate(..., weights=P[:, j], normalize=..., lambda_div=..., lambda_def=...)["J"]``
(docs/SEGMENTATION.md). Gradients for every cluster's parameters come from one
reverse pass of the kernels of ``kernels/clusters.py``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import taichi as ti

from cmax_taichi.core import backend, workspace
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.kernels import clusters as kcl
from cmax_taichi.kernels import events as kevents
from cmax_taichi.models.regularizers import REGULARIZERS, Regularizer
from cmax_taichi.models.warps import WarpModel, get_warp
from cmax_taichi.pipeline import setup as psetup

__all__ = ["MultiClusterCMax"]


def _resolve_warps(warp, n_clusters: int) -> list[WarpModel]:
    if isinstance(warp, (str, WarpModel)):
        return [get_warp(warp)] * n_clusters
    try:
        warps = list(warp)
    except TypeError:
        raise TypeError(f"warp must be a name, a WarpModel or a list of {n_clusters} of them") from None
    if len(warps) != n_clusters:
        raise ValueError(
            f"got {len(warps)} warps for {n_clusters} clusters: give one warp or one per cluster"
        )
    return [get_warp(w) for w in warps]


def _warp_inputs(ws) -> kevents.WarpInputs:
    """The events, parameters and context of a cluster workspace, as the per-event kernels read them."""
    return kevents.WarpInputs(ws.ex, ws.ey, ws.edt, ws.th, ws.ctx)


class MultiClusterCMax(psetup.SetupView):
    """K clusters' augmented CMax objective on one window, for fixed memberships.

    Parameters
    ----------
    events : Events
        The window (at least 2 events spanning a positive time).
    n_clusters : int
        K >= 1.
    warp : str, WarpModel or sequence of K of them
        Motion model of every cluster, or one per cluster.
    objective : str
        Focus measure (see :func:`cmax_taichi.objective_names`).
    regularizers : mapping of str to float, optional
        Weights ``lambda`` of the regularizers, the same for every cluster.
    camera : Camera, optional
        Intrinsics (centre of the zoom/rotation models; needed by ``rotation3``). Distorted events are
        undistorted with it; ``kept`` says which input events remain.
    t_ref : {"first", "middle", "last"} or float
        Reference time (a float is seconds on the events' clock, within the window's span give or
        take its duration: :func:`~cmax_taichi.pipeline.setup.resolve_t_ref`).
    blur_sigma : float
        Gaussian blur of the IWEs, px (0 = none).
    normalize : bool
        Divide each cluster's objective by its identity-warp value ``G0_j`` (default).
    capacity : int
        Size the event fields for at least this many events (windows of different sizes then share
        one set of fields and compiled kernels).

    Notes
    -----
    Polarity is ignored (each event votes ``P[i, j]``). Parameters are passed as a (K, P) array, a
    list of K arrays (clusters with different models), or the flat concatenation; gradients come back
    flat (see :meth:`unpack`). Call :meth:`set_memberships` before evaluating.
    """

    def __init__(
        self,
        events: Events,
        n_clusters: int,
        warp: str | WarpModel | Sequence = "mitrokhin4",
        objective: str = "variance",
        regularizers: Mapping[str, float] | None = None,
        camera: Camera | None = None,
        t_ref: str | float = "first",
        blur_sigma: float = 1.0,
        normalize: bool = True,
        capacity: int = 0,
    ) -> None:
        self._backend = backend.ensure_initialized()
        if not isinstance(events, Events):
            raise TypeError(f"events must be cmax_taichi.Events, got {type(events).__name__}")
        if isinstance(n_clusters, bool) or not isinstance(n_clusters, (int, np.integer)):
            raise TypeError(f"n_clusters must be an integer, got {n_clusters!r}")
        K = int(n_clusters)
        if K < 1:
            raise ValueError(f"n_clusters must be at least 1, got {K}")
        self.n_clusters = K
        self.models = _resolve_warps(warp, K)
        setup = psetup.ProblemSetup.build(
            events, self.models, objective, regularizers, camera, t_ref, blur_sigma, normalize
        )
        if setup.n_events < K:
            raise ValueError(f"n_clusters = {K} is more than the {setup.n_events} events of the window")
        psetup.check_limits(setup, f"this {K}-cluster problem", n_clusters=K)
        self.setup = setup  # events, camera, objective, t_ref, ... (SetupView)
        self.capacity = workspace.capacity_for(max(self.n_events, int(capacity)))
        self.n_params = tuple(m.n_params for m in self.models)
        self.offsets = tuple(int(v) for v in np.concatenate([[0], np.cumsum(self.n_params)[:-1]]))
        self.n_total = int(sum(self.n_params))
        self._memberships: np.ndarray | None = None
        self._active = np.ones(K, dtype=bool)
        self.G0 = np.ones(K)
        self._allocate()
        self._build_kernels()

    # --- parameters ------------------------------------------------------------------------------
    def flatten(self, thetas) -> np.ndarray:
        """Flat float64 vector of all clusters' parameters from a (K, P) array, a list of K arrays or
        a flat vector."""
        if thetas is None or isinstance(thetas, (str, bytes)):
            raise TypeError(
                f"thetas must be a (K, P) array, a list of K arrays or a flat vector, got {thetas!r}"
            )
        try:
            arr = np.asarray(thetas, dtype=np.float64)
        except OverflowError:  # an int such as 10**400
            raise ValueError("thetas has a value beyond the largest float64 (1.8e+308)") from None
        except (TypeError, ValueError):  # ragged: one array per cluster
            arr = None
        if arr is not None and arr.ndim == 1:
            flat = arr
        else:
            try:
                parts = [np.asarray(t, dtype=np.float64).reshape(-1) for t in thetas]
            except OverflowError:
                raise ValueError("thetas has a value beyond the largest float64 (1.8e+308)") from None
            except (TypeError, ValueError):
                raise TypeError(
                    "thetas must be a (K, P) array, a list of K arrays or a flat vector"
                ) from None
            if len(parts) != self.n_clusters:
                raise ValueError(f"got parameters for {len(parts)} clusters, expected {self.n_clusters}")
            for j, (part, n) in enumerate(zip(parts, self.n_params, strict=True)):
                if part.size != n:
                    raise ValueError(
                        f"cluster {j} ({self.models[j].name}) takes {n} parameter(s), got {part.size}"
                    )
            flat = np.concatenate(parts)
        if flat.size != self.n_total:
            raise ValueError(f"expected {self.n_total} parameters in all, got {flat.size}")
        if not np.all(np.isfinite(flat)):  # None converts to NaN
            i = int(np.flatnonzero(~np.isfinite(flat))[0])
            j = int(np.searchsorted(self.offsets, i, side="right")) - 1
            raise ValueError(
                f"thetas: parameter {i - self.offsets[j]} of cluster {j} ({self.models[j].name}) is "
                f"non-finite (NaN, an infinity or None): {flat}"
            )
        return flat

    def unpack(self, flat) -> list[np.ndarray]:
        """Split a flat parameter (or gradient) vector into the K clusters' vectors."""
        flat = np.asarray(flat, dtype=np.float64).reshape(-1)
        return [flat[o : o + n].copy() for o, n in zip(self.offsets, self.n_params, strict=True)]

    # --- fields and kernels ----------------------------------------------------------------------
    def _allocate(self) -> None:
        K, W, H = self.n_clusters, self.width, self.height
        self._reg_names = list(self.regularizer_weights)
        key = (
            "clusters",
            self._backend.generation,
            self.capacity,
            W,
            H,
            K,
            self.n_total,
            len(self._reg_names),
            self.setup.radius,
            self.objective.slots_per_channel,
            psetup.images_key(self.setup, K),
        )
        self._ws = workspace.acquire(key, self._build_fields, f"a {K}-cluster problem on a {W}x{H} sensor")
        ev = self.events
        # Events are uploaded in pixel (row-major) order: neighbouring threads then vote into nearby
        # pixels, which makes the atomic adds of the splat and its adjoint ~1.5x cheaper than time order.
        self._order = np.argsort(np.floor(ev.y) * W + np.floor(ev.x), kind="stable")
        self._per_event = {
            "ex": ev.x[self._order],
            "ey": ev.y[self._order],
            "edt": (ev.t - self.t_ref)[self._order],
        }

    def _build_fields(self, ws) -> None:
        """Allocate a workspace's fields (once per shape)."""
        real = backend.real()
        cap = self.capacity
        K, W, H, n_r = self.n_clusters, self.width, self.height, len(self.regularizer_weights)
        ws.ex = ti.field(real, shape=cap)
        ws.ey = ti.field(real, shape=cap)
        ws.edt = ti.field(real, shape=cap)
        ws.pw = ti.field(real, shape=(cap, K))
        ws.th = ti.Vector.field(self.n_total, real, shape=(), needs_grad=True)
        ws.ctx = ti.Vector.field(5, real, shape=())
        psetup.allocate_images(ws, self.setup, K)
        # memberships are >= 0, so the map count C_j = sum |P_ij| beta is the unblurred vote image itself
        ws.count = ws.vote
        if n_r:
            ws.numer = ti.field(real, shape=(K * n_r, H, W), needs_grad=True)
        else:
            ws.numer = workspace.dummy(real, (1, 1, 1))
        ws.macc = ti.Vector.field(K * (1 + n_r), real, shape=(), needs_grad=True)
        ws.lam = ti.Vector.field(max(2 * n_r, 1), real, shape=())
        ws.g0 = ti.Vector.field(K, real, shape=())
        ws.cw = ti.Vector.field(K, real, shape=())
        ws.acc = ti.Vector.field(self.objective.slots_per_channel * K, real, shape=(), needs_grad=True)
        ws.loss = ti.field(real, shape=(), needs_grad=True)
        ws.diag = ti.Vector.field(K * (1 + n_r), real, shape=())
        ws.look = ti.field(real, shape=(cap, K))
        ws.pos = ti.field(real, shape=(cap, K, 2))
        S = 1 + n_r
        ws.mpart = (
            ti.field(real, shape=(H * ws.tiles.n_segments, K * S), needs_grad=True)
            if n_r
            else workspace.dummy(real, (1, 1))
        )
        images = [ws.vote, ws.vote.grad] + (
            [ws.tmp, ws.tmp.grad, ws.img, ws.img.grad] if self.setup.radius else []
        )
        if n_r:
            images += [ws.numer, ws.numer.grad]
        rows = ((ws.mpart, 0), (ws.mpart.grad, 0)) if n_r else ()
        scalars = (ws.acc, ws.macc, ws.loss, ws.acc.grad, ws.macc.grad, ws.loss.grad, ws.th.grad)
        ws.clear = psetup.make_clear(ws, tuple(images), rows, scalars)

    def _load(self) -> None:
        """Upload this problem's events, constants and memberships into the shared workspace if
        another problem used it since."""
        ws = self._ws
        if ws.owned_by(self):
            return
        psetup.upload(ws, self.setup, self._per_event)
        ws.take(self)
        if self._memberships is not None:
            self._upload_memberships()

    def _upload_memberships(self) -> None:
        ws = self._ws
        buf = np.zeros(ws.pw.shape, dtype=backend.numpy_real())
        buf[: self.n_events] = self._memberships[self._order]
        ws.pw.from_numpy(buf)
        ws.g0[None] = [float(g) if g > 0 else 1.0 for g in self.G0]
        ws.cw[None] = [1.0 if a else 0.0 for a in self._active]

    def _build_kernels(self) -> None:
        models, W, H, K = self.models, self.width, self.height, self.n_clusters
        regs: list[Regularizer] = [REGULARIZERS.get(n) for n in self._reg_names]
        warp_fns = tuple(m.warp for m in models)
        quantities = tuple(tuple(r.quantity_fn(m) for r in regs) for m in models)
        penalties = tuple(r.penalty for r in regs)
        reg_key = tuple((r.name, id(r)) for r in regs)
        model_key = tuple((m.name, id(m)) for m in models)
        self._k_splat = psetup.cached_kernel(
            ("cl_splat", model_key, reg_key, W, H),
            lambda: kcl.make_cluster_splat_kernel(
                warp_fns, quantities, self.offsets, self.n_params, width=W, height=H
            ),
        )
        self._k_mark = psetup.cached_kernel(
            ("cl_mark", model_key, W, H),
            lambda: kcl.make_cluster_mark_kernel(warp_fns, self.offsets, self.n_params, width=W, height=H),
        )
        self._k_lookup = psetup.cached_kernel(
            ("cl_lookup", model_key, W, H),
            lambda: kcl.make_cluster_lookup_kernel(warp_fns, self.offsets, self.n_params, width=W, height=H),
        )
        self._kimg = psetup.image_kernels(self.setup, K, self._ws)
        obj = self.objective
        if regs:
            self._k_maps = psetup.cached_kernel(
                ("cl_maps", reg_key, K, W, H), lambda: kcl.make_cluster_maps_reduce(penalties, K, W, H)
            )
        one_sided = self.setup.one_sided()
        self._k_loss = psetup.cached_kernel(
            ("cl_loss", obj.name, id(obj), K, W * H, one_sided),
            lambda: kcl.make_cluster_loss_kernel(obj.finalize, K, W * H, one_sided),
        )

    # --- memberships -------------------------------------------------------------------------------
    def set_memberships(self, memberships, active=None, identity: bool = True) -> np.ndarray:
        """Fix the memberships and compute each cluster's identity-warp objective ``G0_j``.

        Parameters
        ----------
        memberships : array_like, shape (N, K)
            ``P[i, j] >= 0``: event i's vote weight in cluster j (rows need not sum to 1). N counts the
            events after undistortion (``len(self.events)``).
        active : array_like of bool, shape (K,), optional
            Clusters that count in J (default all). A cluster whose identity image is flat
            (``G0_j <= 0``, e.g. no weight at all) is left out of J as well.
        identity : bool
            Compute ``G0_j`` (one forward pass). False: skip it (``G0_j = 1``, e.g. when only the
            images and lookups are needed).

        Returns
        -------
        ndarray, shape (K,)
            ``G0_j`` (raw objective of cluster j at the identity warp; units of I^2; NaN when
            ``identity=False``).
        """
        P = np.asarray(memberships, dtype=np.float64)
        if P.shape != (self.n_events, self.n_clusters):
            raise ValueError(
                f"memberships must have shape ({self.n_events}, {self.n_clusters}), got {P.shape}"
            )
        if not np.all(np.isfinite(P)) or np.any(P < 0):
            raise ValueError("memberships must be finite and >= 0")
        act = np.ones(self.n_clusters, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        if act.shape != (self.n_clusters,):
            raise ValueError(f"active must have {self.n_clusters} entries")
        self._check_alive()
        self._memberships = P
        self.G0 = np.ones(self.n_clusters)
        self._active = act.copy()
        self._load()
        self._upload_memberships()
        if not identity:
            self.identity_objective = np.full(self.n_clusters, np.nan)
            return self.identity_objective.copy()
        self._forward(np.zeros(self.n_total))  # every model's identity is theta = 0
        g_raw = self._diag_vector()[:, 0]
        self.identity_objective = g_raw.copy()
        self._active = act & (g_raw > 0) & np.isfinite(g_raw)
        self.G0 = np.where(self._active, g_raw, 1.0) if self.normalize else np.ones(self.n_clusters)
        self._upload_memberships()
        return g_raw

    @property
    def active(self) -> np.ndarray:
        """Which clusters count in J (bool, (K,))."""
        return self._active.copy()

    # --- evaluation ------------------------------------------------------------------------------
    def _check_alive(self) -> None:
        if backend.info().generation != self._backend.generation:
            raise RuntimeError(
                "this problem was built before the Taichi backend was reset (by cmax_taichi.init() or "
                "after a failed allocation); build it again"
            )

    def _require_memberships(self) -> None:
        if self._memberships is None:
            raise RuntimeError("call set_memberships(P) before evaluating")

    def _kernel_chain(self):
        ws = self._ws
        chain = [
            (self._k_splat, (self.n_events, _warp_inputs(ws), ws.pw, ws.vote, ws.numer)),
            # forward only: the touched segments and the regions of the passes
            (self._k_mark, (self.n_events, _warp_inputs(ws), ws.pw, ws.tiles)),
            (self._kimg.compact, (ws.tiles,)),
        ]
        if self.blur_sigma > 0:
            chain.append((self._kimg.blur_x, (ws.vote, ws.tmp, ws.taps, ws.tiles, psetup.RX)))
            chain.append((self._kimg.blur_y, (ws.tmp, ws.img, ws.taps, ws.tiles, psetup.RXY)))
        chain.append((self._kimg.reduce, self._kimg.reduce_args(ws, ws.img, ws.acc)))
        if self._reg_names:
            chain.append((self._k_maps, (ws.count, ws.numer, ws.macc, ws.tiles, ws.mpart)))
        chain.append((self._k_loss, (ws.acc, ws.macc, ws.lam, ws.g0, ws.cw, ws.loss, ws.diag)))
        return chain

    def _forward(self, flat: np.ndarray, images_only: bool = False) -> float:
        self._load()
        self._ws.th[None] = flat.tolist()
        self._ws.clear()  # what the last evaluation wrote (images, gradients, sums), over its regions
        chain = self._kernel_chain()
        if images_only:  # the splat and the blur: the cluster images, no objective
            chain = chain[: 5 if self.blur_sigma > 0 else 3]
        psetup.run_chain(chain)
        return float("nan") if images_only else float(self._ws.loss[None])

    def _backward(self) -> np.ndarray:
        ws = self._ws
        # the gradients were cleared with the forward pass's fields; an objective's own reduce kernel
        # (no declared pixel terms) writes its image gradient everywhere
        if not self._kimg.tiled:
            ws.img.grad.fill(0)
        ws.loss.grad[None] = 1.0
        psetup.run_chain_backward(
            self._kernel_chain(), self._kimg.blur_adjoints(), (self._k_mark, self._kimg.compact)
        )
        return ws.th.grad.to_numpy().astype(np.float64).reshape(-1)

    def _diag_vector(self) -> np.ndarray:
        S = 1 + len(self._reg_names)
        return self._ws.diag.to_numpy().astype(np.float64).reshape(self.n_clusters, S)

    def value(self, thetas) -> float:
        """Augmented multi-cluster objective J (sum over the active clusters)."""
        self._check_alive()
        self._require_memberships()
        return self._forward(self.flatten(thetas))

    def value_and_grad(self, thetas) -> tuple[float, np.ndarray]:
        """``(J, dJ/dtheta)``; the gradient is flat (see :meth:`unpack`), physical units."""
        self._check_alive()
        self._require_memberships()
        value = self._forward(self.flatten(thetas))
        return value, self._backward()

    def evaluate(self, thetas) -> dict:
        """Per-cluster terms at ``thetas``.

        Returns
        -------
        dict
            ``"J"`` (float), ``"J_k"`` (K,) each cluster's term (0 for inactive clusters),
            ``"G_raw"`` (K,), ``"G"`` (K,) (``G_raw / G0``), ``"G0"`` (K,) and ``"R"``: a dict
            regularizer name -> (K,) penalties of the regularizers weighted in J.
        """
        self._check_alive()
        self._require_memberships()
        value = self._forward(self.flatten(thetas))
        d = self._diag_vector()
        lam = np.asarray(self.setup.lam[: len(self._reg_names)])
        G = d[:, 0] / self.G0
        Jk = G - (d[:, 1:] @ lam if self._reg_names else 0.0)  # diag holds R with scale and hinge
        return {
            "J": value,
            "J_k": np.where(self._active, Jk, 0.0),
            "G_raw": d[:, 0].copy(),
            "G": G,
            "G0": self.identity_objective.copy(),
            "R": {name: d[:, 1 + r].copy() for r, name in enumerate(self._reg_names)},
        }

    def lookup(
        self, thetas, positions: bool = True, images_only: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Every cluster's blurred IWE at every event's position warped by that cluster.

        Parameters
        ----------
        thetas : (K, P) array, list of K arrays or flat vector
            Parameters (physical units).
        positions : bool
            Also return the warped positions.
        images_only : bool
            Build the images only (no objective, maps or loss: faster, and those kernels are not
            compiled).

        Returns
        -------
        values : ndarray, shape (N, K)
            ``I_j(x'_ij)`` (bilinear interpolation; 0 outside the image), in votes.
        positions : ndarray, shape (N, K, 2), or None
            Warped positions ``x'_ij`` (px); None when ``positions=False`` (saves the transfer).
        """
        self._check_alive()
        self._require_memberships()
        self._forward(self.flatten(thetas), images_only=images_only)
        ws = self._ws
        self._k_lookup(self.n_events, _warp_inputs(ws), ws.img, ws.look, ws.pos)
        values = self._unsort(ws.look.to_numpy())
        return values, (self._unsort(ws.pos.to_numpy()) if positions else None)

    def _unsort(self, a: np.ndarray) -> np.ndarray:
        """Rows of a per-event field (pixel order, padded to capacity) back in the events' order."""
        out = np.empty((self.n_events,) + a.shape[1:], dtype=np.float64)
        out[self._order] = a[: self.n_events]
        return out

    def warped_positions(self, thetas) -> np.ndarray:
        """Every event warped by every cluster's parameters, shape (N, K, 2), px (no image work)."""
        self._check_alive()
        self._load()
        ws = self._ws
        ws.th[None] = self.flatten(thetas).tolist()
        self._k_lookup(self.n_events, _warp_inputs(ws), ws.img, ws.look, ws.pos)
        return self._unsort(ws.pos.to_numpy())

    def value_and_images(self, thetas) -> tuple[float, np.ndarray]:
        """``J`` and the K blurred, membership-weighted IWEs (K, H, W) from one forward pass."""
        self._check_alive()
        self._require_memberships()
        value = self._forward(self.flatten(thetas))
        return value, self._ws.img.to_numpy().astype(np.float64)

    def iwes(self, thetas) -> np.ndarray:
        """The K blurred, membership-weighted IWEs at ``thetas``, shape (K, H, W)."""
        self._check_alive()
        self._require_memberships()
        self._forward(self.flatten(thetas))
        return self._ws.img.to_numpy().astype(np.float64)

    def __repr__(self) -> str:
        regs = ", ".join(f"{k}={v:g}" for k, v in self.regularizer_weights.items()) or "none"
        warps = ",".join(m.name for m in self.models)
        return (
            f"MultiClusterCMax(K={self.n_clusters}, warps={warps}, objective={self.objective.name}, "
            f"regularizers={regs}, events={self.n_events}, sensor={self.width}x{self.height})"
        )
