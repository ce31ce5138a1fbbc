"""Shared plumbing of the demos: matplotlib backend choice, inputs (real recordings or synthetic
scenes) and the optimizer call. Uses the public API of cmax_taichi only.

The real recordings live in ``../shared/data`` beside the checkout (``CMAX_SHARED_DATA`` overrides the
folder); every demo falls back to a synthetic scene generated here with NumPy when they are absent.
"""

from __future__ import annotations

import os
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import cmax_taichi as cm
from cmax_taichi.io import open_recording

REPO = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("CMAX_SHARED_DATA", REPO.parent / "shared" / "data"))
ECD_SEQUENCES = ("boxes_rotation", "dynamic_rotation", "poster_rotation", "shapes_rotation")


def setup_matplotlib(save: str | None) -> bool:
    """Pick the backend before pyplot is imported; return True for an interactive window.

    ``--save`` always renders headless (Agg). Without it the window opens when a display exists
    (``DISPLAY`` / ``WAYLAND_DISPLAY`` on Linux; macOS and Windows always have one).
    """
    import matplotlib

    has_display = bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    has_display |= sys.platform in ("darwin", "win32")
    if save is not None or not has_display:
        matplotlib.use("Agg", force=True)
        return False
    return True


def no_display_exit(name: str) -> int:
    print(
        f"{name}: no display found; run with --save out.png to render the figure to a file", file=sys.stderr
    )
    return 2


def save_figure(fig, path: str, dpi: int, compact: bool = False) -> None:
    """Save ``fig``; ``compact``: a 256-colour palette PNG (about 2x smaller, for docs/images)."""
    if not compact:
        fig.savefig(path, dpi=dpi)
    else:
        import io

        from PIL import Image  # matplotlib depends on Pillow

        buffer = io.BytesIO()
        fig.savefig(buffer, dpi=dpi, format="png")
        buffer.seek(0)
        Image.open(buffer).convert("RGB").quantize(256).save(path, optimize=True)
    print(f"saved {path}")


def start(parser, argv, name: str):
    """Parse ``argv`` and pick the matplotlib backend (:func:`setup_matplotlib`).

    Returns ``(args, interactive)``; ``(None, False)`` when there is neither a display nor ``--save``
    (the demo then returns 2; the message is printed here).
    """
    args = parser.parse_args(argv)
    interactive = setup_matplotlib(args.save)
    if not interactive and args.save is None:
        no_display_exit(name)
        return None, False
    return args, interactive


def show_or_save(fig, args) -> int:
    """Save the figure when ``--save`` was given, else show it in a window; the demo's exit code."""
    if args.save:
        save_figure(fig, args.save, args.dpi, args.compact)
        return 0
    import matplotlib.pyplot as plt

    plt.show()
    return 0


def add_save_arguments(parser) -> None:
    """``--max-events``, ``--save``, ``--dpi``, ``--compact`` (shared by every demo)."""
    parser.add_argument(
        "--max-events", type=int, help="use every k-th event so that at most this many remain"
    )
    parser.add_argument("--save", metavar="PNG", help="render headless into this file instead of a window")
    parser.add_argument("--dpi", type=int, default=80, help="resolution of --save (default 80)")
    parser.add_argument("--compact", action="store_true", help="--save a 256-colour PNG (smaller file)")


def subsample(events: cm.Events, max_events: int | None) -> cm.Events:
    """Every k-th event so that at most ``max_events`` remain: the same window, fewer events."""
    if max_events is None or len(events) <= max_events:
        return events
    step = int(np.ceil(len(events) / max_events))
    return events[::step]


@dataclass
class Scene:
    """Events for a demo, with what is known about them."""

    events: cm.Events
    camera: cm.Camera | None
    name: str
    truth: np.ndarray | None = None  # ground-truth parameters (model units), when known
    truth_label: str = "ground truth"
    extra: dict = field(default_factory=dict)


def subsample_scene(scene: Scene, max_events: int | None, note: bool = True) -> None:
    """:func:`subsample` the scene's events in place, and its per-event ``extra["labels"]`` with them;
    ``note``: say so in the scene's name (whenever ``max_events`` is given)."""
    n = len(scene.events)
    scene.events = subsample(scene.events, max_events)
    labels = scene.extra.get("labels")
    if labels is not None and max_events and n > max_events:
        scene.extra["labels"] = labels[:: int(np.ceil(n / max_events))]
    if note and max_events:
        scene.name = f"{scene.name.split(',')[0]}, {len(scene.events)} events (subsampled)"


# --- MVSEC indoor_flying1 (collapse explorer) ---------------------------------------------------------------
def load_mvsec(n_events: int = 30000) -> Scene | None:
    """The first ``n_events`` of the MVSEC indoor_flying1 cut (undistorted), or None when absent.

    ``n_events`` = 30000 is the window size of the paper's MVSEC experiments.
    """
    folder = DATA_DIR / "mvsec_indoor_flying1"
    if not (folder / "events.txt").exists():
        return None
    with warnings.catch_warnings():
        # Undistorted float coordinates fall a little outside the sensor; the reader drops those.
        warnings.filterwarnings("ignore", message=".*outside the .* sensor", category=RuntimeWarning)
        with open_recording(folder) as rec:
            events = rec.read(0, n_events)
            camera = rec.camera
    return Scene(
        events, camera, f"MVSEC indoor_flying1, {len(events)} events, {events.duration * 1e3:.0f} ms"
    )


def _segment_points(rng: np.random.Generator, n: int, n_segments: int, half_extent: np.ndarray) -> np.ndarray:
    """``n`` points on random straight segments and corners in ``[-half, half]^2`` (a textured scene)."""
    a = rng.uniform(-half_extent, half_extent, size=(n_segments, 2))
    angle = rng.uniform(0, np.pi, n_segments)
    length = rng.uniform(10, 40, n_segments)
    which = rng.integers(0, n_segments, n)
    s = rng.uniform(-0.5, 0.5, n) * length[which]
    pts = a[which] + s[:, None] * np.stack([np.cos(angle[which]), np.sin(angle[which])], axis=1)
    return pts + rng.normal(0, 0.35, size=pts.shape)


def synthetic_zoom(n_events: int = 20000, h_z: float = 2.0, duration: float = 0.15, seed: int = 0) -> Scene:
    """Textured edges under forward camera motion: an expanding scene with exact zoom ``h_z`` [1/s].

    A point at reference offset ``x0`` (from the image centre, at the first event's time) is seen at
    ``x0 / (1 - h_z t)``: the ``zoom1`` warp ``c + (1 - t h_z)(x - c)`` maps it back exactly, so the true
    parameter is ``h_z`` (and ``(0, 0, h_z, 0)`` for ``mitrokhin4``).
    """
    rng = np.random.default_rng(seed)
    width, height = 240, 180
    c = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    n_total = int(n_events * 1.6)  # some leave the sensor while it expands
    pts = _segment_points(rng, n_total, 60, c * 0.95)
    t = np.sort(rng.uniform(0.0, duration, n_total))
    xy = c + pts / (1.0 - h_z * t)[:, None]
    noise = rng.random(n_total) < 0.05
    xy[noise] = rng.uniform([0, 0], [width - 1, height - 1], size=(int(noise.sum()), 2))
    inside = (xy[:, 0] >= 0) & (xy[:, 0] <= width - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= height - 1)
    idx = np.flatnonzero(inside)[:n_events]
    p = rng.integers(0, 2, idx.size)
    events = cm.Events(xy[idx, 0], xy[idx, 1], t[idx], p, (width, height))
    return Scene(
        events,
        None,
        f"synthetic forward motion (true h_z = {h_z:g} 1/s), {len(events)} events",
        truth=np.array([h_z]),
    )


def synthetic_two_objects(n_events: int = 12000, duration: float = 0.05, seed: int = 2) -> Scene:
    """A textured background and a textured square moving with different translations (px/s).

    ``Scene.extra["labels"]``: the true object of each event (0 background, 1 square); ``Scene.truth``:
    the two velocities, shape (2, 2).
    """
    rng = np.random.default_rng(seed)
    width, height = 240, 180
    velocity = np.array([[-80.0, 20.0], [150.0, -60.0]])
    n_square = n_events // 3
    half = np.array([width / 2.0, height / 2.0])
    background = _segment_points(rng, n_events - n_square, 80, half) + half
    square = _segment_points(rng, n_square, 25, np.array([30.0, 30.0])) + [90.0, 90.0]
    pts = np.vstack([background, square])
    label = np.r_[np.zeros(len(background), int), np.ones(len(square), int)]
    t = rng.uniform(0.0, duration, len(pts))
    xy = pts + t[:, None] * velocity[label]
    inside = (xy[:, 0] >= 0) & (xy[:, 0] <= width - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= height - 1)
    order = np.argsort(t[inside], kind="stable")
    xy, t, label = xy[inside][order], t[inside][order], label[inside][order]
    events = cm.Events(xy[:, 0], xy[:, 1], t, rng.integers(0, 2, len(t)), (width, height))
    name = f"two objects (background {velocity[0].tolist()}, square {velocity[1].tolist()} px/s)"
    return Scene(events, None, name, truth=velocity, extra={"labels": label})


# --- ECD rotation (rotation demo) -------------------------------------------------------------------------
def load_ecd(sequence: str) -> Scene | None:
    """A raw ECD rotation window with its calibration and the gyro ground truth, or None when absent."""
    if sequence not in ECD_SEQUENCES:
        raise ValueError(f"unknown sequence {sequence!r}; valid: {', '.join(ECD_SEQUENCES)}")
    folder = DATA_DIR / "ecd_rotation" / sequence
    if not (folder / "events.txt").exists():
        return None
    with open_recording(folder) as rec:
        events = rec.read()  # raw distorted pixels: the problem undistorts them with rec.camera
        camera = rec.camera
        gyro = rec.angular_velocity(0.5 * (events.t[0] + events.t[-1]))
    name = f"ECD {sequence}, {len(events)} events, {events.duration * 1e3:.1f} ms"
    return Scene(events, camera, name, truth=np.asarray(gyro, dtype=np.float64), truth_label="IMU gyro")


def _rodrigues(w: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Rotation matrices ``exp(dt [w]_x)``, shape (n, 3, 3)."""
    angle = np.linalg.norm(w) * dt
    axis = w / max(np.linalg.norm(w), 1e-12)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def synthetic_rotation(
    n_events: int = 20000,
    w: tuple[float, float, float] = (0.4, -1.0, 0.6),
    duration: float = 0.08,
    seed: int = 1,
) -> Scene:
    """Textured edges seen by a rotating camera (no distortion), exact angular velocity ``w`` [rad/s].

    Uses the convention of the data README: a bearing at time t maps to the reference (first event)
    time by ``bearing_ref = exp(hat(w) (t - t_ref)) bearing_t``,
    so ``bearing_t = exp(-hat(w) dt) bearing_ref``.
    """
    rng = np.random.default_rng(seed)
    width, height = 240, 180
    camera = cm.Camera(200.0, 200.0, 119.5, 89.5)
    w = np.asarray(w, dtype=np.float64)
    n_total = int(n_events * 1.5)
    pts = _segment_points(rng, n_total, 70, np.array([150.0, 115.0])) + [camera.cx, camera.cy]
    t = np.sort(rng.uniform(0.0, duration, n_total))
    rays = np.stack(
        [(pts[:, 0] - camera.cx) / camera.fx, (pts[:, 1] - camera.cy) / camera.fy, np.ones(n_total)], 1
    )
    rotated = np.einsum("nij,nj->ni", _rodrigues(-w, t), rays)
    x = camera.cx + camera.fx * rotated[:, 0] / rotated[:, 2]
    y = camera.cy + camera.fy * rotated[:, 1] / rotated[:, 2]
    noise = rng.random(n_total) < 0.05
    x[noise] = rng.uniform(0, width - 1, int(noise.sum()))
    y[noise] = rng.uniform(0, height - 1, int(noise.sum()))
    inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    idx = np.flatnonzero(inside)[:n_events]
    events = cm.Events(x[idx], y[idx], t[idx], rng.integers(0, 2, idx.size), (width, height))
    name = f"synthetic rotation, {len(events)} events, {duration * 1e3:.0f} ms"
    return Scene(events, camera, name, truth=w, truth_label="true w")


# --- optimizer ----------------------------------------------------------------------------------------------
def run_optimizer(prob: cm.ContrastMaximization, theta0=None, method: str = "adam", init: str = "none"):
    """:func:`cmax_taichi.maximize` from ``theta0`` (default 0).

    ``init="none"`` is a local ascent from ``theta0`` only (what the demos animate: where gradient
    ascent goes from the point you chose); ``"auto"`` adds the global search first.
    """
    if theta0 is None and init == "none":
        theta0 = np.zeros(prob.model.n_params)
    return cm.maximize(prob, theta0=theta0, method=method, init=init)


def optimizer_path(result) -> tuple[np.ndarray, np.ndarray]:
    """``(theta (K, P), J (K,))`` of the iterates of the optimizer's winning local run."""
    return np.asarray(result.history.theta, dtype=np.float64), np.asarray(
        result.history.value, dtype=np.float64
    )
