"""The whitening baseline where ``rotation3`` sends events behind the camera, and the whitening's own
collapse of ``rotation3`` on the real poster_rotation cut (docs/results-real.md, "Whitening and
rotation3")."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import CAMERA, edge_events, shared_data_dir
from test_pipeline_gradients import REGS, check_against_reference

import cmax_taichi as cm
from cmax_taichi import io
from cmax_taichi.core.checks import EventsDroppedWarning
from cmax_taichi.lab.experiments_real import WHITENING_RAY
from cmax_taichi.testing import reference

#: rotations (rad/s) that send 106 and 48 of the 400 test events (64 x 48 px, 50 ms) behind the camera
BEHIND = {"pitch": [0.0, 40.0, 0.0], "oblique": [25.0, -25.0, 10.0]}


def _n_behind(theta) -> int:
    x, y, t, _ = edge_events(n=400, seed=0)
    geometry = dict(**reference.camera_geometry(CAMERA), duration=t.max() - t.min())
    xw, _, _, _ = reference.warp_events("rotation3", x, y, t - t.min(), np.asarray(theta), **geometry)
    return int(np.sum(~np.isfinite(xw)))


@pytest.mark.parametrize("regs", ["none", "both"])
@pytest.mark.parametrize("name", list(BEHIND))
def test_whitening_leaves_events_behind_the_camera_out(name, regs):
    """An event that rotation3 rotates behind the camera is dropped by the whitened IWE as by the plain
    one: out of the moments and voted nowhere, as in the float64 reference. (The kernels used to keep it
    in the moments at the sentinel position, -1e7 px, and whiten it too: J 1354 instead of 858 at
    (78, -78, 130) rad/s on poster_rotation.) Value and gradient against the reference."""
    assert _n_behind(BEHIND[name]) >= 40
    options = dict(warp="rotation3", regularizers=REGS[regs], camera=CAMERA, whitening=True)
    check_against_reference("f64", {**options, "theta": BEHIND[name]}, fused=False)


def test_whitening_collapse_of_rotation3_on_poster_rotation(f64):
    """The whitening's own collapse, not a defect and not a matter of the search: along ever larger
    rotations the whitened J climbs from about 1 to hundreds (kernels = float64 reference), far above
    its value at the gyro, while the same warps blur the unwhitened IWE (J well below 1). A rotation of
    1.6-4 rad over the window sends a few events near the horizon, thousands of px away: their
    covariance is what whitening divides by, so it shrinks every other event into a few pixels."""
    with io.open_recording(shared_data_dir("ecd_rotation", "poster_rotation")) as rec:
        events = rec.read()
        camera = rec.camera
        w_gt = np.asarray(rec.angular_velocity(0.5 * (rec.t_start + rec.t_end)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EventsDroppedWarning)  # undistortion leaves the sensor
        white = cm.ContrastMaximization(events, warp="rotation3", camera=camera, whitening=True)
        plain = cm.ContrastMaximization(events, warp="rotation3", camera=camera)
    ev = white.events
    j_gyro = white.value(w_gt)
    assert j_gyro == pytest.approx(plain.value(w_gt), rel=0.01)  # near the truth whitening is harmless
    for s, factor in ((0.4, 40.0), (0.5, 300.0), (1.0, 500.0)):
        theta = s * np.asarray(WHITENING_RAY)
        ref = reference.evaluate_window(ev, theta, warp="rotation3", camera=camera, whitening=True)
        j = white.value(theta)
        assert j == pytest.approx(ref["J"], rel=1e-9)
        assert j > factor * j_gyro, (s, j, j_gyro)
        assert plain.value(theta) < 0.25
