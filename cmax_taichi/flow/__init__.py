"""Dense optical flow by contrast maximization, protected from event collapse.

The flow lives on a grid of nodes over the sensor (:class:`FlowGrid`), bilinearly interpolated to each
event; :class:`DenseFlowProblem` gives J and its exact gradient in the node values (the fused kernel of
``kernels/dense_flow.py``), with the paper's divergence and deformation regularizers computed per event
in closed form from the interpolant, smoothness terms on the grid (:data:`SMOOTHNESS`) and the
multi-reference objective. docs/flow.md explains the model and the solver.
"""

from cmax_taichi.flow.grid import FlowGrid, grid_for_cell_size
from cmax_taichi.flow.problem import MULTI_REFERENCE, DenseEvaluation, DenseFlowProblem, resolve_references
from cmax_taichi.flow.sequence import FlowWindow, iter_flow
from cmax_taichi.flow.smoothness import SMOOTHNESS, Smoothness, register_smoothness, smoothness_names
from cmax_taichi.flow.solver import (
    DEFAULT_OPTIONS,
    DEFAULT_REGULARIZERS,
    KINK_WIDTH,
    LEVEL_STATUSES,
    DenseFlowEstimator,
    FlowResult,
    LevelReport,
    estimate_flow,
)

__all__ = [
    "DEFAULT_OPTIONS",
    "DEFAULT_REGULARIZERS",
    "DenseEvaluation",
    "DenseFlowEstimator",
    "DenseFlowProblem",
    "FlowGrid",
    "FlowResult",
    "FlowWindow",
    "KINK_WIDTH",
    "LEVEL_STATUSES",
    "LevelReport",
    "MULTI_REFERENCE",
    "SMOOTHNESS",
    "Smoothness",
    "estimate_flow",
    "grid_for_cell_size",
    "iter_flow",
    "register_smoothness",
    "resolve_references",
    "smoothness_names",
]
