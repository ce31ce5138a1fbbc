"""Event simulator kernels: per-pixel rendering of the log intensity and threshold-crossing events.

ESIM-like (Rebecq et al. 2018): the driver (``cmax_taichi/simulate.py``) renders the scene at an
adaptive rate; between two renders each pixel's log intensity is taken as linear in time, and the
pixel emits one event each time it crosses a level ``ref +- C`` of its reference (the level of its
last event), with the timestamp linearly interpolated between the two renders. A change spanning
several thresholds gives several events in one render interval.

Kernels are built by factories closed over the static sizes (number of layers, sensor size) and take
every field as a template argument. No autodiff is needed here, so the emitter uses a dynamic loop
per pixel. Events are written into preallocated buffers through an atomic counter (a 0-D field);
their order in the buffer is arbitrary and the driver sorts them.

Times inside the kernels are seconds relative to the start of the simulation; the emitter records,
per event, the render step index and the fraction of the step, from which the driver rebuilds the
exact float64 timestamp.
"""

import taichi as ti


@ti.func
def _mirror(u, n):
    """Mirror-repeat coordinate ``u`` (texels) into ``[0, n - 1]``."""
    period = 2.0 * (n - 1)
    v = u - period * ti.floor(u / period)
    if v > n - 1:
        v = period - v
    return v


@ti.func
def _sample(tex, layer, u, v, nx, ny):
    """Bilinear sample of ``tex[layer]`` at texel ``(u, v)`` (column, row), inside ``[0, n-1]``."""
    i0 = ti.min(ti.cast(ti.floor(u), ti.i32), nx - 2)
    j0 = ti.min(ti.cast(ti.floor(v), ti.i32), ny - 2)
    i0 = ti.max(i0, 0)
    j0 = ti.max(j0, 0)
    a = u - i0
    b = v - j0
    return (
        (1.0 - a) * (1.0 - b) * tex[layer, j0, i0]
        + a * (1.0 - b) * tex[layer, j0, i0 + 1]
        + (1.0 - a) * b * tex[layer, j0 + 1, i0]
        + a * b * tex[layer, j0 + 1, i0 + 1]
    )


def make_render_kernel(mirror: tuple, opaque: tuple, width: int, height: int, depth_test: bool = False):
    """Build the renderer of a layered scene.

    Parameters
    ----------
    mirror : tuple of bool
        Per layer, drawn back (0) to front: True for an infinite plane tiled by the mirrored texture
        (backgrounds), False for a texture that is transparent outside its bounds (objects).
    opaque : tuple of bool
        Per layer: True when its coverage is 1 everywhere inside (its alpha is then not sampled).
    width, height : int
        Sensor size, px.
    depth_test : bool
        False: the layers are composited in their order (painter's algorithm). True: every ``hinv[k]``
        is scaled so that the third texel coordinate is the inverse depth ``1 / Z`` of the layer at the
        pixel (3-D planes, ``sim/rigid.py``), and each pixel composites the layers nearest first
        ("over": ``sum_k a_k c_k prod_{j nearer} (1 - a_j)``); the label is the nearest layer with
        coverage > ``label_cover``, -1 where no layer covers the pixel.

    Returns
    -------
    kernel
        ``render(tex, alpha, tex_shape, hinv, log_eps, label_cover, out_log, out_label)``: ``tex`` and
        ``alpha`` are
        ``(n_layers, Ht, Wt)`` linear intensity in [0, 1] and coverage in [0, 1]; ``tex_shape[k]`` is
        ``(Wt_k, Ht_k)``; ``hinv[k]`` maps homogeneous image coordinates (px) to texel coordinates of
        layer k at the render time. Writes ``log(I + log_eps)`` into ``out_log`` (H, W) and the index
        of the front-most layer covering each pixel (coverage > 0.5; with ``depth_test`` coverage >
        ``label_cover``) into ``out_label``.
    """
    n_layers = len(mirror)

    @ti.kernel
    def render(
        tex: ti.template(),
        alpha: ti.template(),
        tex_shape: ti.template(),
        hinv: ti.template(),
        log_eps: float,
        label_cover: float,
        out_log: ti.template(),
        out_label: ti.template(),
    ):
        for j, i in ti.ndrange(height, width):
            value = 0.0
            label = 0
            covers = ti.Vector([0.0] * n_layers)
            colors = ti.Vector([0.0] * n_layers)
            inv_depth = ti.Vector([0.0] * n_layers)
            for k in ti.static(range(n_layers)):
                h = hinv[k]
                X = h @ ti.Vector([float(i), float(j), 1.0])
                nx = tex_shape[k][0]
                ny = tex_shape[k][1]
                cover = 0.0
                color = 0.0
                if X[2] > 1e-9:
                    u = X[0] / X[2]
                    v = X[1] / X[2]
                    inside = True
                    if ti.static(mirror[k]):
                        u = _mirror(u, nx)
                        v = _mirror(v, ny)
                    else:
                        inside = u >= 0.0 and v >= 0.0 and u <= nx - 1.0 and v <= ny - 1.0
                    if inside:
                        color = _sample(tex, k, u, v, nx, ny)
                        if ti.static(opaque[k]):
                            cover = 1.0
                        else:
                            cover = _sample(alpha, k, u, v, nx, ny)
                if ti.static(depth_test):
                    covers[k] = cover
                    colors[k] = color
                    inv_depth[k] = X[2]
                else:
                    value = cover * color + (1.0 - cover) * value
                    if cover > 0.5:
                        label = k
            if ti.static(depth_test):
                label = -1
                nearest = 0.0
                for k in ti.static(range(n_layers)):
                    through = 1.0  # the light of layer k that the layers in front of it let through
                    for m in ti.static(range(n_layers)):
                        if ti.static(m != k):  # noqa: SIM102 - a compile-time branch
                            if inv_depth[m] > inv_depth[k] or (inv_depth[m] == inv_depth[k] and m > k):
                                through *= 1.0 - covers[m]
                    value += covers[k] * colors[k] * through
                    if covers[k] > label_cover and inv_depth[k] > nearest:
                        nearest = inv_depth[k]
                        label = k
            out_log[j, i] = ti.log(value + log_eps)
            out_label[j, i] = label

    return render


@ti.kernel
def count_crossings(
    log_now: ti.template(),
    ref: ti.template(),
    prev: ti.template(),
    c_pos: ti.template(),
    c_neg: ti.template(),
    total: ti.template(),
    max_change: ti.template(),
    label_now: ti.template(),
    label_prev: ti.template(),
    skip_label_change: ti.i32,
):
    """Upper bound of the events the next ``emit`` will write (refractory ignored) into ``total``,
    and the largest ``|log_now - prev|`` of any pixel into ``max_change``. Changes no state.

    With ``skip_label_change`` (depth scenes) a pixel whose label changed between the two renders does
    not count in ``max_change``: where two surfaces meet without an anti-aliased edge (the corner of
    two walls, a surface passing behind another) its intensity jumps however short the step, so
    shortening the step cannot bound it; the step is still bounded by the largest image motion."""
    for j, i in log_now:
        L1 = log_now[j, i]
        r = ref[j, i]
        n = 0
        if L1 - r >= c_pos[j, i]:
            n = ti.cast(ti.floor((L1 - r) / c_pos[j, i]), ti.i32)
        elif r - L1 >= c_neg[j, i]:
            n = ti.cast(ti.floor((r - L1) / c_neg[j, i]), ti.i32)
        if n > 0:
            ti.atomic_add(total[None], n)
        if skip_label_change == 0 or label_now[j, i] == label_prev[j, i]:
            ti.atomic_max(max_change[None], ti.abs(L1 - prev[j, i]))


@ti.kernel
def emit(
    log_now: ti.template(),
    label_now: ti.template(),
    prev: ti.template(),
    label_prev: ti.template(),
    ref: ti.template(),
    c_pos: ti.template(),
    c_neg: ti.template(),
    last_t: ti.template(),
    t0: float,
    t1: float,
    refractory: float,
    step: ti.i32,
    ev_pix: ti.template(),
    ev_frac: ti.template(),
    ev_pol: ti.template(),
    ev_label: ti.template(),
    ev_step: ti.template(),
    counter: ti.template(),
    capacity: ti.i32,
):
    """Threshold crossings of every pixel between the render at ``t0`` (``prev``) and the render at
    ``t1`` (``log_now``), seconds; then ``prev <- log_now``.

    Each crossing of ``ref + C+`` (``ref - C-``) moves the reference by one threshold and, unless it
    falls within ``refractory`` seconds of the pixel's last event, writes one event: pixel index
    ``y * W + x``, the fraction of the step at which the linear interpolation crosses the level,
    polarity +1 / -1, the label of the front-most layer at the pixel in either render, and ``step``.
    Crossings inside the refractory period are not reported but still move the reference (the pixel
    resets without reporting). Events beyond ``capacity`` are counted but not written.
    """
    width = log_now.shape[1]
    for j, i in log_now:
        L0 = prev[j, i]
        L1 = log_now[j, i]
        r = ref[j, i]
        change = L1 - L0
        if ti.abs(change) < 1e-12:
            change = 1e-12  # unreachable by the invariant; keeps the division finite
        label = ti.max(label_now[j, i], label_prev[j, i])
        polarity = 0
        c = 0.0
        if L1 - r >= c_pos[j, i]:
            polarity = 1
            c = c_pos[j, i]
        elif r - L1 >= c_neg[j, i]:
            polarity = -1
            c = -c_neg[j, i]
        if polarity != 0:
            # the invariant r - C- < L0 < r + C+ puts every crossing strictly after t0
            while (L1 - (r + c)) * polarity >= 0.0:
                r += c
                frac = ti.min(ti.max((r - L0) / change, 0.0), 1.0)
                t = t0 + frac * (t1 - t0)
                if t - last_t[j, i] >= refractory:
                    last_t[j, i] = t
                    idx = ti.atomic_add(counter[None], 1)
                    if idx < capacity:
                        ev_pix[idx] = j * width + i
                        ev_frac[idx] = frac
                        ev_pol[idx] = ti.cast(polarity, ti.i8)
                        ev_label[idx] = ti.cast(label, ti.i8)
                        ev_step[idx] = step
        ref[j, i] = r
        prev[j, i] = L1
        label_prev[j, i] = label_now[j, i]


@ti.kernel
def reset_state(
    log_now: ti.template(),
    label_now: ti.template(),
    prev: ti.template(),
    label_prev: ti.template(),
    ref: ti.template(),
    last_t: ti.template(),
    never: float,
):
    """Start of a simulation: the reference and the previous render are the first render."""
    for j, i in log_now:
        prev[j, i] = log_now[j, i]
        ref[j, i] = log_now[j, i]
        label_prev[j, i] = label_now[j, i]
        last_t[j, i] = never
