"""A simulated recording with its exact ground truth, and its MVSEC-like files (HDF5 events and labels
plus a ``*_gt_flow_dist.npz`` flow file) with the reader :func:`read_simulation`."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cmax_taichi.core.events import Camera, Events

if TYPE_CHECKING:
    from cmax_taichi.sim.scenes import Scene
    from cmax_taichi.sim.simulator import Simulator

__all__ = ["SimulatedRecording", "SimulationData", "read_simulation"]


@dataclass
class SimulatedRecording:
    """Simulated events with their exact ground truth.

    Attributes
    ----------
    x, y : numpy.ndarray
        Pixel coordinates (integers stored as float64), px.
    t : numpy.ndarray
        Timestamps, s (sorted).
    p : numpy.ndarray
        Polarities, int8 in {-1, +1}.
    labels : numpy.ndarray
        int16: the index of the layer that produced the event (0 background, k object k), -1 for noise
        and hot pixels.
    t_start, t_end : float
        Simulated interval, s.
    sensor_size : (int, int)
    camera : Camera
    simulator : Simulator
        The scene and its renderer (ground truth at any time).
    n_steps : int
        Number of renders.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    labels: np.ndarray
    t_start: float
    t_end: float
    sensor_size: tuple[int, int]
    camera: Camera
    simulator: Simulator = field(repr=False)
    n_steps: int = 0

    def __len__(self) -> int:
        return len(self.t)

    @property
    def scene(self) -> Scene:
        return self.simulator.scene

    def events(self, t0: float | None = None, t1: float | None = None) -> Events:
        """The events with ``t0 <= t < t1`` (default all) as :class:`cmax_taichi.Events`."""
        lo, hi = self._range(t0, t1)
        return Events(self.x[lo:hi], self.y[lo:hi], self.t[lo:hi], self.p[lo:hi], self.sensor_size)

    def label_slice(self, t0: float | None = None, t1: float | None = None) -> np.ndarray:
        """The labels of :meth:`events` with the same arguments."""
        lo, hi = self._range(t0, t1)
        return self.labels[lo:hi]

    def _range(self, t0, t1) -> tuple[int, int]:
        lo = 0 if t0 is None else int(np.searchsorted(self.t, t0, side="left"))
        hi = len(self.t) if t1 is None else int(np.searchsorted(self.t, t1, side="left"))
        return lo, hi

    def theta_at(self, t: float, layer: int = 0) -> np.ndarray:
        """Parameters of layer ``layer``'s warp for a window starting at ``t`` s (see
        :meth:`Motion.theta_at`)."""
        return self.scene.layers[layer].motion.theta_at(float(t))

    @property
    def warp(self) -> str:
        """Warp model of the camera (background) motion."""
        return self.scene.layers[0].motion.warp

    def displacement(self, t_a: float, t_b: float, x, y, layer: int = 0) -> np.ndarray:
        """Exact displacement (px) from ``t_a`` to ``t_b`` of the points of layer ``layer`` that are at
        ``(x, y)`` at ``t_a``; shape ``(2,) + x.shape``."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        m = self.scene.layers[layer].motion
        D = m.matrix(t_b, self.camera) @ np.linalg.inv(m.matrix(t_a, self.camera))
        q = np.tensordot(D, np.stack([x, y, np.ones_like(x)]), axes=1)
        return np.stack([q[0] / q[2] - x, q[1] / q[2] - y])

    def flow(self, t_a: float, t_b: float) -> np.ndarray:
        """Dense ground-truth flow (2, H, W), px: where the scene point seen at each pixel at ``t_a``
        is at ``t_b``, minus the pixel (MVSEC's ``*_flow_dist`` convention: indexed at the start
        positions). Each pixel follows the front-most layer covering it at ``t_a`` (for depth scenes
        the nearest surface); NaN where no layer covers it."""
        W, H = self.sensor_size
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
        label = self.label_map(t_a)
        out = np.full((2, H, W), np.nan)
        for k in range(len(self.scene.layers)):
            mask = label == k
            if np.any(mask):
                out[:, mask] = self.displacement(t_a, t_b, xx[mask], yy[mask], layer=k)
        return out

    def label_map(self, t: float) -> np.ndarray:
        """(H, W) int16: the layer seen at each pixel at time ``t`` s (coverage > 0.5; for depth scenes
        the nearest surface, -1 where none)."""
        return self.simulator.render(float(t))[1]

    def velocity(self, t: float) -> np.ndarray:
        """Dense instantaneous ground-truth flow (2, H, W), px/s, at time ``t`` s: the image velocity
        of the scene point seen at each pixel (the layer of :meth:`label_map`; NaN where none). Closed
        form for 3-D planes (:meth:`PlaneMotion.velocity`); for 2-D motions the central difference of
        the exact motion over +-1 us."""
        W, H = self.sensor_size
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
        label = self.label_map(t)
        out = np.full((2, H, W), np.nan)
        for k, layer in enumerate(self.scene.layers):
            mask = label == k
            if not np.any(mask):
                continue
            if hasattr(layer.motion, "velocity"):
                out[:, mask] = layer.motion.velocity(t, xx[mask], yy[mask], self.camera)
            else:
                h = 1e-6
                fwd = self.displacement(t, t + h, xx[mask], yy[mask], layer=k)
                back = self.displacement(t, t - h, xx[mask], yy[mask], layer=k)
                out[:, mask] = (fwd - back) / (2 * h)
        return out

    def depth(self, t: float) -> np.ndarray:
        """(H, W) depth (m, along the optical axis) of the surface seen at each pixel at time ``t`` s,
        for depth scenes (:attr:`Scene.has_depth`); NaN where no surface is seen."""
        if not self.scene.has_depth:
            raise ValueError("only a depth scene (3-D planes, cmax_taichi.sim.depth) has a depth")
        W, H = self.sensor_size
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
        label = self.label_map(t)
        out = np.full((H, W), np.nan)
        for k, layer in enumerate(self.scene.layers):
            mask = label == k
            if np.any(mask):
                out[mask] = layer.motion.depth(t, xx[mask], yy[mask], self.camera)
        return out

    def warp_events(self, t_ref: float, t0: float | None = None, t1: float | None = None):
        """Exact positions at ``t_ref`` s of the scene points that produced the events of
        ``[t0, t1)`` (:meth:`events`): ``(x, y)`` px, each event moved by the exact motion of its layer
        (its label) from its own time to ``t_ref``; NaN for noise and hot-pixel events (label -1).

        The image of warped events with these positions is the sharpest any warp can give (up to the
        pixel quantisation of the events): the reference of a dense-flow estimate's IWE."""
        lo, hi = self._range(t0, t1)
        x, y, t, lab = self.x[lo:hi], self.y[lo:hi], self.t[lo:hi], self.labels[lo:hi]
        xw = np.full(len(x), np.nan)
        yw = np.full(len(x), np.nan)
        cam = self.camera
        for k, layer in enumerate(self.scene.layers):
            sel = np.flatnonzero(lab == k)
            if not len(sel):
                continue
            m = layer.motion
            G_ref = m.matrix(float(t_ref), cam)
            if hasattr(m, "matrices"):
                G = m.matrices(t[sel], cam)
            else:
                G = np.stack([m.matrix(float(tk), cam) for tk in t[sel]])
            src = np.stack([x[sel], y[sel], np.ones(len(sel))], axis=1)
            at0 = np.linalg.solve(G, src[:, :, None])[:, :, 0]
            q = at0 @ G_ref.T
            xw[sel] = q[:, 0] / q[:, 2]
            yw[sel] = q[:, 1] / q[:, 2]
        return xw, yw

    def frame_times(self, frame_rate: float) -> np.ndarray:
        """Ground-truth frame timestamps ``t_start + k / frame_rate`` within the recording, s."""
        if not (math.isfinite(frame_rate) and frame_rate > 0):
            raise ValueError(f"frame_rate must be positive (Hz), got {frame_rate}")
        n = int(math.floor((self.t_end - self.t_start) * frame_rate + 1e-9)) + 1
        return self.t_start + np.arange(n) / frame_rate

    def write(self, out_dir, name: str, frame_rate: float = 32.0) -> tuple[Path, Path]:
        """Save in the MVSEC-like layout.

        Writes ``<out_dir>/<name>_data.hdf5``: ``davis/left/events`` (N, 4) float64 ``x, y, t [s], p``
        (p in {-1, +1}), ``davis/left/labels`` (N,) int16, attributes ``fx fy cx cy width height`` on
        ``davis/left``; ``ground_truth/t`` (M,) s and ``ground_truth/theta`` (M, P) of the camera
        (layer 0) motion with attribute ``warp``; ``ground_truth/layers/<k>/{t,theta}`` with attributes
        ``warp``, ``segment``, ``name`` for every layer (depth scenes: no ``theta``, and per layer the
        plane and its motions as the JSON attribute ``plane``, see :meth:`PlaneMotion.describe`);
        ``davis/left/image_raw_ts``, the frame times (MVSEC's grey-scale frame times, which set its
        evaluation windows); and the simulator settings as a JSON attribute.
        And ``<out_dir>/<name>_gt_flow_dist.npz``: ``timestamps`` (M,), ``x_flow_dist``, ``y_flow_dist``
        (M, H, W) float32, the flow in px from ``timestamps[i]`` to ``timestamps[i + 1]`` (the last one to
        ``timestamps[-1] + 1 / frame_rate``, within the recording when it is long enough, else
        extrapolated by the exact motion); 0 (MVSEC's mark) where a pixel has no ground truth.

        Returns
        -------
        (Path, Path)
            The HDF5 and the npz paths.
        """
        import h5py

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        h5_path = out / f"{name}_data.hdf5"
        npz_path = out / f"{name}_gt_flow_dist.npz"
        ts = self.frame_times(frame_rate)
        W, H = self.sensor_size
        with h5py.File(h5_path, "w") as f:
            left = f.create_group("davis/left")
            ev = np.stack([self.x, self.y, self.t, self.p.astype(np.float64)], axis=1)
            left.create_dataset("events", data=ev, compression="gzip", compression_opts=4)
            left.create_dataset("labels", data=self.labels, compression="gzip", compression_opts=4)
            cam = self.camera
            for key, value in (("fx", cam.fx), ("fy", cam.fy), ("cx", cam.cx), ("cy", cam.cy)):
                left.attrs[key] = float(value)
            left.attrs["width"] = W
            left.attrs["height"] = H
            left.attrs["dist"] = np.asarray(cam.dist, dtype=np.float64)
            # the layout the MVSEC reader (cmax_taichi.io) takes intrinsics from
            calib = [cam.fx, cam.fy, cam.cx, cam.cy, *cam.dist]
            left.create_dataset("calibration", data=np.asarray(calib, dtype=np.float64))
            # the ground-truth frame times, where MVSEC has its grey-scale frames (evaluation windows)
            left.create_dataset("image_raw_ts", data=ts)
            gt = f.create_group("ground_truth")
            gt.create_dataset("t", data=ts)
            depth = self.scene.has_depth
            if depth:  # 3-D planes: no warp parameters, the geometry and motions instead
                gt.attrs["warp"] = ""
            else:
                gt.create_dataset("theta", data=np.stack([self.theta_at(t) for t in ts]))
                gt.attrs["warp"] = self.warp
            layers = gt.create_group("layers")
            for k, layer in enumerate(self.scene.layers):
                g = layers.create_group(str(k))
                g.create_dataset("t", data=ts)
                if depth:
                    g.attrs["plane"] = json.dumps(layer.motion.describe())
                else:
                    g.create_dataset("theta", data=np.stack([layer.motion.theta_at(t) for t in ts]))
                    g.attrs["warp"] = layer.motion.warp
                    g.attrs["segment"] = float(layer.motion.segment or 0.0)
                g.attrs["name"] = layer.name
            f.attrs["simulator"] = json.dumps(
                {
                    "scene": self.scene.name,
                    "config": asdict(self.simulator.config),
                    "t_start": self.t_start,
                    "t_end": self.t_end,
                    "frame_rate": frame_rate,
                }
            )
        flows = np.stack([self.flow(t, t + 1.0 / frame_rate) for t in ts]).astype(np.float32)
        flows[~np.isfinite(flows)] = 0.0  # MVSEC's mark of a pixel without ground truth
        np.savez_compressed(npz_path, timestamps=ts, x_flow_dist=flows[:, 0], y_flow_dist=flows[:, 1])
        return h5_path, npz_path


@dataclass
class SimulationData:
    """A simulated recording read back from disk (see :meth:`SimulatedRecording.write`)."""

    events: Events
    labels: np.ndarray
    camera: Camera
    gt_t: np.ndarray
    gt_theta: np.ndarray
    warp: str
    flow_timestamps: np.ndarray
    flow: np.ndarray  # (M, 2, H, W) px between consecutive timestamps
    meta: dict


def read_simulation(h5_path) -> SimulationData:
    """Read ``<name>_data.hdf5`` and the ``<name>_gt_flow_dist.npz`` beside it."""
    import h5py

    h5_path = Path(h5_path)
    if not h5_path.name.endswith("_data.hdf5"):
        raise ValueError(f"expected a '<name>_data.hdf5' file, got {h5_path.name}")
    npz_path = h5_path.with_name(h5_path.name[: -len("_data.hdf5")] + "_gt_flow_dist.npz")
    with h5py.File(h5_path, "r") as f:
        left = f["davis/left"]
        ev = left["events"][()]
        labels = left["labels"][()]
        a = left.attrs
        camera = Camera(float(a["fx"]), float(a["fy"]), float(a["cx"]), float(a["cy"]))
        sensor = (int(a["width"]), int(a["height"]))
        gt_t = f["ground_truth/t"][()]
        # a depth scene has no warp parameters (an empty (M, 0) array)
        gt_theta = f["ground_truth/theta"][()] if "ground_truth/theta" in f else np.zeros((len(gt_t), 0))
        warp = str(f["ground_truth"].attrs["warp"])
        meta = json.loads(f.attrs["simulator"])
    d = np.load(npz_path)
    flow = np.stack([d["x_flow_dist"], d["y_flow_dist"]], axis=1).astype(np.float64)
    events = Events(ev[:, 0], ev[:, 1], ev[:, 2], ev[:, 3], sensor)
    return SimulationData(events, labels, camera, gt_t, gt_theta, warp, d["timestamps"], flow, meta)
