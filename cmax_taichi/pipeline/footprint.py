"""The footprint the one-pass kernels share: the fused pipeline (kernels/fused.py) and the dense flow
(kernels/dense_flow.py) size their fields and compile their kernels by the same image, objective and
accumulation choices; they are declared here once, for both, and passed as keywords.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import taichi as ti

from cmax_taichi.core import backend


def n_slices() -> int:
    """Accumulation slices of the splat: one per CPU thread; 1 (atomics) on a GPU."""
    if backend.info().arch != "cpu":
        return 1
    return max(1, int(ti.lang.impl.current_cfg().cpu_max_num_threads))


@dataclass(frozen=True)
class KernelFootprint:
    """The image and objective a one-pass kernel set is built for (hashable: a part of workspace keys).

    Attributes
    ----------
    width, height : int
        The kernels' image, px (the sensor plus any padding).
    n_channels : int
        Images per reference (2 for split polarity).
    radius : int
        Gaussian blur radius, px (0 = no blur).
    n_slices : int
        Accumulation slices of the splat (:func:`n_slices`; 1 with atomics).
    shared_count : bool
        The regularizers' count image is the IWE itself (unweighted, unsplit votes).
    objective_slots : int
        Per-pixel partial sums the objective declares per channel.
    sobel : bool
        The objective reads the Sobel gradient of the IWE.
    """

    width: int
    height: int
    n_channels: int
    radius: int
    n_slices: int
    shared_count: bool
    objective_slots: int
    sobel: bool

    def fields_options(self) -> dict:
        """The keywords of the fields' constructors (``FusedFields``, ``DenseFlowFields``)."""
        return asdict(self)

    def kernel_options(self, objective, *, atomic: bool, weighted: bool, split: bool, real) -> dict:
        """The keywords of the kernel factories (``make_fused_kernels``, ``make_dense_flow_kernels``).

        Parameters
        ----------
        objective : FusedObjective
            The objective's fused declaration (``pixel``, ``finalize``, ``adjoint``).
        atomic : bool
            Atomic scatter (a GPU arch) instead of per-slice accumulation.
        weighted, split : bool
            Per-event vote weights; split polarity.
        real
            The Taichi float type.
        """
        return dict(
            pixel_fn=objective.pixel,
            finalize_fn=objective.finalize,
            adjoint_fn=objective.adjoint,
            atomic_scatter=atomic,
            weighted=weighted,
            split_polarity=split,
            real=real,
            **asdict(self),
        )


def kernels_key(objective_name: str, objective, regularizers, *flags) -> tuple:
    """The key of a compiled kernel set within a workspace: the objective (its name and fused
    declaration), the regularizers (names and instances) and the caller's compile-time ``flags``."""
    return (objective_name, id(objective), tuple((r.name, id(r)) for r in regularizers), *flags)
