"""The real-data claims of docs/results-real.md, one test per claim, on the shared
recordings (skipped with a message when ../shared/data is absent). The full table comes from
``python -m cmax_taichi.lab.experiments_real``; these tests use the same pipeline with smaller global
searches where noted, to stay within the test-time budget."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import shared_data_dir

import cmax_taichi as cm
from cmax_taichi import io
from cmax_taichi.lab.experiments_real import ROTATION_CUTS
from cmax_taichi.metrics import angular_velocity_error, covered_area_ratio, covered_share, fwl_problem

pytestmark = pytest.mark.usefixtures("f64")

#: smaller global search than the experiments' default (1000 grid points, 3 starts)
QUICK = {"n_init": 216, "n_starts": 1}


def _rotation_cut(name):
    with io.open_recording(shared_data_dir("ecd_rotation", name)) as rec:
        w_gt = rec.angular_velocity(0.5 * (rec.t_start + rec.t_end))
        return rec.read(), rec.camera, np.asarray(w_gt)


def test_ecd_rotation_estimates_are_sharper_than_the_gyro_and_close_to_it():
    """Every window: FWL(estimate) >= FWL(gyro), and |w_est - w_gt| < 25% of |w_gt|; the divergence and
    the deformation regularizers change the estimate by less than 5% (checked on one window here, on
    all four by the experiments script)."""
    for name in ROTATION_CUTS:
        events, camera, w_gt = _rotation_cut(name)
        prob = cm.ContrastMaximization(events, warp="rotation3", camera=camera)
        res = cm.maximize(prob, **QUICK)
        fprob = fwl_problem(prob.events, "rotation3", camera=camera)
        assert fprob.value(res.theta) >= fprob.value(w_gt), name
        rel = angular_velocity_error(res.theta, w_gt)["relative"][0]
        assert rel < 0.25, (name, res.theta, w_gt, rel)
        if name == "dynamic_rotation":
            for reg in ("divergence", "deformation"):
                rprob = cm.ContrastMaximization(
                    events, warp="rotation3", camera=camera, regularizers={reg: 1.0}
                )
                rres = cm.maximize(rprob, theta0=res.theta)
                change = np.linalg.norm(rres.theta - res.theta) / np.linalg.norm(res.theta)
                assert change < 0.05, (name, reg, rres.theta, res.theta)


def test_slider_depth_translation_is_about_minus_110_px_per_s():
    with io.open_recording(shared_data_dir("ecd_slider_depth")) as rec:
        events, camera = rec.read(), rec.camera
    prob = cm.ContrastMaximization(events, warp="translation2", camera=camera)
    res = cm.maximize(prob)
    assert np.hypot(res.theta[0] + 110.0, res.theta[1]) < 11.0, res


def test_mvsec_zoom_collapses_without_a_regularizer_and_not_with_both():
    """zoom1, variance, first 30,000 events of indoor_flying1: no regularizer and the whitening
    baseline collapse (FWL far above 1; two thirds of the pixels the unwarped events cover are left
    empty as the events are drawn into the centre); divergence + deformation (lambda = 1 each) does
    not."""
    with io.open_recording(shared_data_dir("mvsec_indoor_flying1")) as rec, warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # 121 events fall outside the sensor
        events, camera = rec.read(0, 30000), rec.camera
    fprob = fwl_problem(events, "zoom1", camera=camera)
    outcome = {}
    for label, kwargs in (
        ("none", {}),
        ("whitening", {"whitening": True}),
        ("div + def", {"regularizers": {"divergence": 1.0, "deformation": 1.0}}),
    ):
        prob = cm.ContrastMaximization(events, warp="zoom1", camera=camera, **kwargs)
        res = cm.maximize(prob, n_starts=1)
        theta = res.theta
        outcome[label] = (fprob.value(theta), covered_share(fprob, theta), covered_area_ratio(fprob, theta))
    for label in ("none", "whitening"):
        fwl, share, area = outcome[label]
        assert fwl > 3.0 and share < 0.5 and area < 1.0, (label, outcome[label])
    fwl, share, area = outcome["div + def"]
    assert fwl < 1.2 and area > 0.9, outcome


def test_mvsec_mitrokhin4_divergence_alone_needs_the_recommended_lambda():
    """The hardest configuration of the lambda sweep (mitrokhin4, gradient magnitude, divergence
    alone): it collapses at lambda = 1 and not at RECOMMENDED_LAMBDA, the weight that
    ``experiments_real`` selects. The sweep searches globally with the thorough grid
    (``init="grid"``, as ``lab.experiments`` does): maximize's default coarse-to-fine search stays
    near the motion here and does not reach the collapse at lambda = 1 either (FWL 1.26 on this
    window), which says nothing about the weight."""
    from cmax_taichi.models.regularizers import RECOMMENDED_LAMBDA

    with io.open_recording(shared_data_dir("mvsec_indoor_flying1")) as rec, warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        events, camera = rec.read(0, 30000), rec.camera
    fprob = fwl_problem(events, "mitrokhin4", camera=camera)
    outcome = {}
    for lam in (1.0, RECOMMENDED_LAMBDA):
        prob = cm.ContrastMaximization(
            events,
            warp="mitrokhin4",
            objective="gradient_magnitude",
            camera=camera,
            regularizers={"divergence": lam},
        )
        theta = cm.maximize(prob, init="grid").theta
        outcome[lam] = (fprob.value(theta), covered_share(fprob, theta))
    fwl, share = outcome[1.0]
    assert fwl > 3.0 and share < 0.5, outcome
    fwl, share = outcome[RECOMMENDED_LAMBDA]
    assert fwl < 1.5 and share >= 0.5, outcome
