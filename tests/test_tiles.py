"""Image work that follows the events (kernels/tiles.py): the passes run over the segments the warped
events touch, dilated by each pass's footprint, and the untouched pixels enter in closed form.

* The regions of the tile masks against NumPy dilations of the touched pixels.
* Windows whose events touch a corner, the far corner (the partial last segment of a row whose width is
  not a multiple of the segment), a band, one segment, the image border, a few crowded pixels, or are
  spread over the image, with blur off and on, Sobel objectives, weights, polarity channels and both
  regularizers: the fused path and the generic chain against the float64 reference (value) and its
  central differences (gradient), on several warps.
* A window warped out of the image (no pixel touched), K clusters, ``maps()`` and ``iwe()``.
* The same J and dJ/dtheta to the last bit whatever was evaluated before (the passes clear what the
  previous call left over the previous regions) and in another problem on the same events.
"""

from __future__ import annotations

import numpy as np
import pytest
import taichi as ti
from cmax_taichi.kernels import tiles as ktiles
from scipy import ndimage

import cmax_taichi as cm
from cmax_taichi.pipeline.clusters import MultiClusterCMax
from cmax_taichi.pipeline.fused import FusedPipeline
from cmax_taichi.testing import reference

pytestmark = pytest.mark.usefixtures("f64")

SENSOR = (150, 110)  # 150 = 37 segments and 2 px: every row ends in a partial segment
CAMERA = cm.Camera(fx=120.0, fy=118.0, cx=74.6, cy=54.8)
DURATION = 0.05
TOL = dict(value=1e-10, grad=2e-6)
BOTH = {"divergence": 0.7, "deformation": 1.3}
THETAS = {
    "translation2": [60.0, -35.0],
    "mitrokhin4": [50.0, -30.0, 3.0, 2.0],
    "rotation3": [0.6, -0.9, 1.5],
}


def window(kind: str, n: int = 300, seed: int = 0):
    """Events (x, y, t, p) of one kind of sparse window on :data:`SENSOR`."""
    rng = np.random.default_rng(seed)
    W, H = SENSOR
    if kind == "corner":  # the top-left corner, on the image border
        x, y = rng.uniform(0, 10, n), rng.uniform(0, 8, n)
    elif kind == "far_corner":  # the bottom-right corner: the partial last segments, the last row
        x, y = rng.uniform(W - 9, W - 1, n), rng.uniform(H - 7, H - 1, n)
    elif kind == "band":
        x, y = rng.uniform(0, W - 1, n), rng.uniform(50, 54, n)
    elif kind == "one_segment":  # one segment of one row (columns 80-83 of row 40)
        x, y = rng.uniform(80, 82.99, n), rng.uniform(40, 40.99, n)
    elif kind == "border":  # on the four borders
        side = rng.integers(0, 4, n)
        s = rng.uniform(0, 1, n)
        x = np.select([side == 0, side == 1], [0.0 * s, (W - 1) + 0.0 * s], (W - 1) * s)
        y = np.select([side == 2, side == 3], [0.0 * s, (H - 1) + 0.0 * s], (H - 1) * s)
    elif kind == "crowded":  # three pixels, many events each
        centres = np.array([[30.3, 20.6], [31.1, 20.2], [100.7, 70.4]])
        which = rng.integers(0, 3, n)
        x, y = centres[which, 0] + rng.normal(0, 0.05, n), centres[which, 1] + rng.normal(0, 0.05, n)
    elif kind == "spread":
        x, y = rng.uniform(0, W - 1, n), rng.uniform(0, H - 1, n)
    else:
        raise ValueError(kind)
    x, y = np.clip(x, 0, W - 1), np.clip(y, 0, H - 1)
    t = np.sort(rng.uniform(0, DURATION, n))
    t[0], t[-1] = 0.0, DURATION
    return x, y, t, rng.integers(0, 2, n)


def _ref_kwargs(warp, options):
    regs = options.get("regularizers", {})
    return dict(
        warp=warp,
        sensor_size=SENSOR,
        center=(CAMERA.cx, CAMERA.cy),
        focal=(CAMERA.fx, CAMERA.fy),
        t_ref=options.get("t_ref", "first"),
        objective=options.get("objective", "variance"),
        blur_sigma=options.get("blur_sigma", 1.0),
        polarity=options.get("polarity", "ignore"),
        weights=options.get("weights"),
        lambda_div=regs.get("divergence", 0.0),
        lambda_def=regs.get("deformation", 0.0),
    )


def _problem(raw, warp, options, *, fused=True):
    saved = FusedPipeline.enabled
    FusedPipeline.enabled = fused
    try:
        prob = cm.ContrastMaximization(cm.Events(*raw, SENSOR), warp=warp, camera=CAMERA, **options)
    finally:
        FusedPipeline.enabled = saved
    assert (prob._fused is not None) == fused
    return prob


def _check(prob, raw, warp, options, theta):
    theta = np.asarray(theta, dtype=np.float64)
    value, grad = prob.value_and_grad(theta)
    kwargs = _ref_kwargs(warp, options)
    ref = reference.evaluate(*raw, theta, **kwargs)
    assert value == pytest.approx(ref["J"], rel=TOL["value"], abs=TOL["value"])
    fd = reference.central_difference_grad(*raw, theta, rel_step=1e-6, **kwargs)
    err = np.max(np.abs(grad - fd)) / max(np.max(np.abs(fd)), 1e-12)
    assert err < TOL["grad"], f"gradient {grad} vs finite differences {fd} (rel err {err:.2e})"
    if prob._fused is not None and prob._fused.stores_event_terms:
        # its value-only launch leaves the stored Jacobians out, and fast math then compiles the
        # warped positions' arithmetic differently: the same sums to a few ulps (kernels/fused.py)
        assert prob.value(theta) == pytest.approx(value, rel=1e-14, abs=1e-15)
    else:
        assert prob.value(theta) == value  # the value-only launch sums in the same order
    return value, grad


# --- the regions ----------------------------------------------------------------------------------
def _segment_mask(pixels: np.ndarray) -> np.ndarray:
    H, W = pixels.shape
    ns = -(-W // ktiles.SEG)
    padded = np.zeros((H, ns * ktiles.SEG), bool)
    padded[:, :W] = pixels
    return padded.reshape(H, ns, ktiles.SEG).any(axis=2)


def _words_to_segments(words: np.ndarray, ns: int) -> np.ndarray:
    bits = (words[:, :, None] >> np.arange(32, dtype=np.uint32)) & 1
    return bits.reshape(words.shape[0], -1)[:, :ns].astype(bool)


@pytest.mark.parametrize("width", [150, 128, 37])
def test_regions_are_the_dilated_touched_segments(width):
    """F0 holds exactly the segments of the touched pixels (two rows and two columns per footprint),
    region (kx, ry) its dilation by kx segments and ry rows; the lists are the regions' segments in
    row-major order, the pixel counts their in-image pixels; the marks are cleared."""
    H = 40
    regions = [(0, 0), (1, 0), (1, 3), (2, 4), (3, 0)]
    tf = ktiles.TileFields(width, H, regions, lists=True)
    ops = ktiles.ops_for(tf)
    rng = np.random.default_rng(width)
    pos = np.concatenate(
        [rng.uniform(-0.99, width - 0.01, (60, 2)) * [1, H / width], [[-0.5, -0.5], [width - 0.5, H - 0.5]]]
    )
    n = len(pos)
    px = ti.field(ti.f64, shape=n)
    py = ti.field(ti.f64, shape=n)
    px.from_numpy(pos[:, 0].copy())
    py.from_numpy(pos[:, 1].copy())
    mark = ktiles.mark_position

    @ti.kernel
    def mark_all():
        for i in range(n):
            mark(tf, ti.Vector([px[i], py[i]]))

    for _ in range(2):  # twice: the second build starts from the marks the first one cleared
        mark_all()
        ops.compact(tf)
    touched = np.zeros((H, width), bool)
    for x, y in pos:
        ix, iy = int(np.floor(x)), int(np.floor(y))
        touched[max(iy, 0) : iy + 2, max(ix, 0) : ix + 2] = True
    f0 = _segment_mask(touched)
    ns = tf.n_segments
    masks = tf.masks()
    lists, counts, pixels = tf.lists.to_numpy(), tf.count.to_numpy(), tf.pixels.to_numpy()
    for ri, (kx, ry) in enumerate(regions):
        want = ndimage.binary_dilation(f0, np.ones((2 * ry + 1, 2 * kx + 1), bool)) if ri else f0
        got = _words_to_segments(masks[ri], ns)
        np.testing.assert_array_equal(got, want, err_msg=f"region {(kx, ry)}")
        rows, segs = np.nonzero(want)
        np.testing.assert_array_equal(lists[ri, : counts[ri]], rows * ns + segs)
        cols = np.repeat(want, ktiles.SEG, axis=1)[:, :width]
        assert pixels[ri] == cols.sum()
    assert not tf.words.to_numpy()[: (H + 1) * tf.n_words].any()  # the marks
    assert ktiles.reach(3) == 1 and ktiles.reach(4) == 1 and ktiles.reach(5) == 2 and ktiles.reach(0) == 0


# --- sparse windows against the reference ------------------------------------------------------------
CASES = [
    ("corner", "translation2", dict(regularizers=BOTH)),
    ("far_corner", "mitrokhin4", dict(objective="gradient_magnitude", regularizers={"deformation": 1.0})),
    ("band", "rotation3", dict(blur_sigma=2.0)),
    ("one_segment", "mitrokhin4", dict(blur_sigma=0.0, regularizers=BOTH)),
    (
        "border",
        "mitrokhin4",
        dict(objective="mean_square", polarity="split", regularizers={"divergence": 2.0}),
    ),
    ("crowded", "translation2", dict(weights=np.linspace(0.2, 1.5, 300), regularizers=BOTH)),
    (
        "spread",
        "mitrokhin4",
        dict(objective="gradient_magnitude", polarity="signed", blur_sigma=1.5, regularizers=BOTH),
    ),
    ("border", "rotation3", dict(objective="gradient_magnitude", blur_sigma=0.0)),
]


@pytest.mark.parametrize("case", range(len(CASES)), ids=[f"{k}-{w}" for k, w, _ in CASES])
def test_sparse_windows_fused_against_reference(case):
    kind, warp, options = CASES[case]
    raw = window(kind)
    prob = _problem(raw, warp, options)
    for scale in (1.0, 0.4):
        _check(prob, raw, warp, options, np.asarray(THETAS[warp]) * scale)


CHAIN_CASES = [0, 1, 4, 6]  # the generic chain compiles slowly: one case per objective and option


@pytest.mark.parametrize("case", CHAIN_CASES, ids=[f"{CASES[c][0]}-{CASES[c][1]}" for c in CHAIN_CASES])
def test_sparse_windows_chain_against_reference_and_fused(case):
    kind, warp, options = CASES[case]
    raw = window(kind)
    chain = _problem(raw, warp, options, fused=False)
    fused = _problem(raw, warp, options)
    theta = np.asarray(THETAS[warp])
    v1, g1 = _check(chain, raw, warp, options, theta)
    v2, g2 = fused.value_and_grad(theta)
    assert v1 == pytest.approx(v2, rel=1e-11, abs=1e-12)
    np.testing.assert_allclose(g1, g2, rtol=1e-8, atol=1e-10 * max(1.0, np.max(np.abs(g2))))
    np.testing.assert_allclose(chain.iwe(theta), fused.iwe(theta), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "chain"])
def test_window_warped_out_of_the_image(fused):
    """Events inside at the identity, all warped out of the image at theta: no pixel touched, J = 0
    (a flat image, no map support) and a zero gradient; the identity again as before."""
    x, y, t, p = window("corner")
    t = 0.04 + 0.01 * (t / DURATION)  # every event at least 9 ms from t_ref (within a duration of it)
    raw = (x, y, t, p)
    options = dict(regularizers=BOTH, t_ref=0.031)
    prob = _problem(raw, "translation2", options, fused=fused)
    identity = prob.value_and_grad(np.zeros(2))
    theta = np.array([-40000.0, -30000.0])  # 360 px left and 270 px up, at least
    value, grad = prob.value_and_grad(theta)
    ref = reference.evaluate(*raw, theta, **_ref_kwargs("translation2", options))
    assert value == 0.0 == ref["J"]
    np.testing.assert_array_equal(grad, 0.0)
    assert not prob.iwe(theta).any()
    again = prob.value_and_grad(np.zeros(2))
    assert again[0] == identity[0]
    np.testing.assert_array_equal(again[1], identity[1])


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "chain"])
def test_same_bits_whatever_came_before(fused):
    """J and dJ/dtheta to the last bit: the first call, after calls that touched other regions (larger,
    smaller, none), after another problem on the same pooled fields, and in a second problem on the same
    events; the value-only launch gives the same J."""
    warp, options = "mitrokhin4", dict(regularizers=BOTH)
    raw_a, raw_b = window("band", seed=3), window("spread", seed=4)
    a = _problem(raw_a, warp, options, fused=fused)
    b = _problem(raw_b, warp, options, fused=fused)
    theta = np.asarray(THETAS[warp])
    v0, g0 = a.value_and_grad(theta)
    for other in (theta * 3.0, theta * 0.0, theta + [5000.0, 4000.0, 0.0, 0.0], theta * -2.0):
        a.value_and_grad(other)
        a.value(other)
        b.value_and_grad(other)
        v, g = a.value_and_grad(theta)
        assert v == v0
        np.testing.assert_array_equal(g, g0)
    assert a.value(theta) == v0
    twin = _problem(raw_a, warp, options, fused=fused)
    v, g = twin.value_and_grad(theta)
    assert v == v0
    np.testing.assert_array_equal(g, g0)


def test_iwe_and_maps_on_a_sparse_window():
    """iwe() and maps() after calls on other regions: the whole image against the reference (zero / NaN
    where no event landed)."""
    warp, options = "mitrokhin4", dict(regularizers=BOTH)
    raw = window("corner", seed=5)
    prob = _problem(raw, warp, options)
    kwargs = _ref_kwargs(warp, options)
    for theta in (np.asarray(THETAS[warp]), np.asarray(THETAS[warp]) * -1.5, np.zeros(4)):
        prob.value_and_grad(theta * 2.0)
        prob.maps(theta * 3.0)
        ref = reference.evaluate(*raw, theta, **kwargs)
        np.testing.assert_allclose(prob.iwe(theta), ref["iwe"][0], rtol=1e-12, atol=1e-13)
        maps = prob.maps(theta)
        np.testing.assert_allclose(maps["count"], ref["count"], rtol=1e-12, atol=1e-13)
        hit = ref["count"] > 0
        np.testing.assert_array_equal(np.isnan(maps["divergence"]), ~hit)
        np.testing.assert_allclose(maps["divergence"][hit], ref["div_map"][hit], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(maps["deformation"][hit], ref["def_map"][hit], rtol=1e-10, atol=1e-12)
        assert maps["R_deformation"] == pytest.approx(ref["R_def"], rel=1e-9, abs=1e-12)


def test_clusters_on_a_sparse_window():
    """K = 2 clusters on a band window (each cluster's own touched pixels) against the reference sum,
    gradient against its central differences; the same bits after other calls."""
    raw = window("band", seed=6)
    n = len(raw[0])
    warps = ["translation2", "mitrokhin4"]
    rng = np.random.default_rng(7)
    P = rng.dirichlet(np.ones(2), size=n)
    P[P < 0.15] = 0.0
    prob = MultiClusterCMax(cm.Events(*raw, SENSOR), 2, warps, regularizers=BOTH, camera=CAMERA)
    prob.set_memberships(P)
    thetas = [np.asarray(THETAS["translation2"]), np.asarray(THETAS["mitrokhin4"]) * 0.7]
    kwargs = _ref_kwargs("translation2", dict(regularizers=BOTH))
    kwargs.pop("warp")
    kwargs.pop("weights")

    def ref_sum(parts):
        return sum(
            reference.evaluate(*raw, parts[j], warp=warps[j], weights=P[:, j], **kwargs)["J"]
            for j in range(2)
        )

    value, grad = prob.value_and_grad(thetas)
    assert value == pytest.approx(ref_sum(thetas), rel=TOL["value"], abs=TOL["value"])
    flat = prob.flatten(thetas)
    fd = reference.central_differences(lambda f: ref_sum(prob.unpack(f)), flat, rel_step=1e-6)
    err = np.max(np.abs(grad - fd)) / max(np.max(np.abs(fd)), 1e-12)
    assert err < TOL["grad"], f"gradient {grad} vs finite differences {fd} (rel err {err:.2e})"
    prob.value_and_grad([t * 3.0 for t in thetas])
    again = prob.value_and_grad(thetas)
    assert again[0] == value
    np.testing.assert_array_equal(again[1], grad)
    images = prob.iwes(thetas)
    for j in range(2):
        r = reference.evaluate(*raw, thetas[j], warp=warps[j], weights=P[:, j], **kwargs)
        np.testing.assert_allclose(images[j], r["iwe"][0], rtol=1e-12, atol=1e-13)
