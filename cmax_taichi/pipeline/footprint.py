"""What the one-launch pipelines' callers share: the fused pipeline (``pipeline/fused.py``) and the dense
flow (``flow/problem.py``) size their fields and compile their kernels by the same image, objective and
accumulation choices. The shape itself is one declaration, ``kernels/fused_common.py``'s
:class:`~cmax_taichi.kernels.fused_common.ImageLayout` (the fields and the kernels read it); here is how a
caller fills it (:func:`image_layout`), how many thread slices the CPU gets (:func:`n_slices`) and the
key of a compiled kernel set (:func:`kernels_key`).
"""

from __future__ import annotations

import taichi as ti

from cmax_taichi.core import backend
from cmax_taichi.kernels.fused_common import ImageLayout


def n_slices() -> int:
    """Accumulation slices of the splat: one per CPU thread; 1 (atomics) on a GPU."""
    if backend.info().arch != "cpu":
        return 1
    return max(1, int(ti.lang.impl.current_cfg().cpu_max_num_threads))


def image_layout(
    *,
    n_channels: int,
    radius: int,
    shared_count: bool,
    objective_slots: int,
    sobel: bool,
    atomic: bool,
) -> ImageLayout:
    """The :class:`ImageLayout` of a problem's kernels (hashable: a part of the kernels' and workspaces'
    keys) in the backend's float type, with one slice per CPU thread, or one slice when the event passes
    add atomically (``atomic``: a GPU arch, or a forced atomic path). The sensor is not in it: the
    kernels take their image's width and height as arguments.

    Parameters
    ----------
    n_channels : int
        Images per reference (2 for split polarity).
    radius : int
        Gaussian blur radius, px (0 = no blur).
    shared_count : bool
        The regularizers' count image is the IWE itself (unweighted, unsplit votes).
    objective_slots : int
        Per-pixel partial sums the objective declares per channel.
    sobel : bool
        The objective reads the Sobel gradient of the IWE.
    atomic : bool
        Atomic scatter into one slice instead of per-thread slices.
    """
    return ImageLayout(
        real=backend.real(),
        n_channels=n_channels,
        radius=radius,
        n_slices=1 if atomic else n_slices(),
        shared_count=shared_count,
        objective_slots=objective_slots,
        sobel=sobel,
    )


def kernels_key(objective_name: str, objective, regularizers, *flags) -> tuple:
    """The key of a compiled kernel set within a workspace: the objective (its name and fused
    declaration), the regularizers (names and instances) and the caller's compile-time ``flags``."""
    return (objective_name, id(objective), tuple((r.name, id(r)) for r in regularizers), *flags)
