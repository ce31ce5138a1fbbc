"""Dense optical flow by contrast maximization, protected from event collapse.

The flow lives on a grid of nodes over the sensor (:class:`FlowGrid`), bilinearly interpolated to each
event; :class:`DenseFlowProblem` gives J and its exact gradient in the node values (the fused kernel of
``kernels/dense_flow.py``), with the paper's divergence and deformation regularizers computed per event
in closed form from the interpolant, smoothness terms on the grid (:data:`SMOOTHNESS`) and the
multi-reference objective. docs/flow.md explains the model and the solver.
"""

from cmax_taichi.flow.grid import FlowGrid, grid_for_cell_size
from cmax_taichi.flow.problem import MULTI_REFERENCE, DenseEvaluation, DenseFlowProblem, resolve_references
from cmax_taichi.flow.smoothness import SMOOTHNESS, Smoothness, register_smoothness, smoothness_names

__all__ = [
    "DenseEvaluation",
    "DenseFlowProblem",
    "FlowGrid",
    "MULTI_REFERENCE",
    "SMOOTHNESS",
    "Smoothness",
    "grid_for_cell_size",
    "register_smoothness",
    "resolve_references",
    "smoothness_names",
]
