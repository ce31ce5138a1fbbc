"""cmax-taichi: Contrast Maximization for event cameras with the event-collapse regularizers of
Shiba, Aoki and Gallego (Sensors 2022), as Taichi kernels that run on the CPU and the GPU.

Public names only; see README.md for a worked example and docs/FORMULAS.md for every formula. The
simulator, the batch runner and segmentation are imported when first used (:data:`_LAZY`), so that
``import cmax_taichi`` (and the command line) does not pay for what a run does not use.
"""

import importlib
import os

# Taichi prints a "[Taichi] version ..." banner to stdout when it is imported: noise in every command's
# output (--help included) and in a program's own; cmax_taichi.backend_info() and 'cmax-taichi info'
# say what runs. ENABLE_TAICHI_HEADER_PRINT=1 in the environment brings it back.
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")

from cmax_taichi.core.backend import BackendInfo, init  # noqa: E402 - after the banner setting
from cmax_taichi.core.backend import info as backend_info
from cmax_taichi.core.events import Camera, Events
from cmax_taichi.core.limits import Limits, get_limits, set_limits
from cmax_taichi.models.objectives import (
    OBJECTIVES,
    FusedObjective,
    Objective,
    objective_names,
    register_objective,
    unregister_objective,
)
from cmax_taichi.models.regularizers import (
    RECOMMENDED_LAMBDA,
    REGULARIZERS,
    Regularizer,
    register_regularizer,
    regularizer_names,
    unregister_regularizer,
)
from cmax_taichi.models.warps import (
    WARPS,
    WarpModel,
    get_warp,
    register_warp,
    unregister_warp,
    warp_names,
)
from cmax_taichi.pipeline.flow_field import dense_flow
from cmax_taichi.pipeline.fused import ChainPathWarning
from cmax_taichi.pipeline.jacobians import event_jacobians
from cmax_taichi.pipeline.parameters import NonFiniteResultError
from cmax_taichi.pipeline.problem import POLARITY_MODES, ContrastMaximization, Evaluation
from cmax_taichi.pipeline.tiers import warmup
from cmax_taichi.solve.optimize import OptimizeResult, maximize

__version__ = "0.1.0"

#: public names imported on first use: name -> (module, attribute)
_LAZY = {
    "SimulatedRecording": ("cmax_taichi.sim", "SimulatedRecording"),
    "Simulator": ("cmax_taichi.sim", "Simulator"),
    "SimulatorConfig": ("cmax_taichi.sim", "SimulatorConfig"),
    "read_simulation": ("cmax_taichi.sim", "read_simulation"),
    "simulate_preset": ("cmax_taichi.sim", "simulate_preset"),
    "batch_run": ("cmax_taichi.solve.batch", "run"),
    "SegmentationResult": ("cmax_taichi.solve.segment", "SegmentationResult"),
    "segment": ("cmax_taichi.solve.segment", "segment"),
    "CheckReport": ("cmax_taichi.testing.checks", "CheckReport"),
    "check_model": ("cmax_taichi.testing.checks", "check_model"),
    "check_objective": ("cmax_taichi.testing.checks", "check_objective"),
    "check_regularizer": ("cmax_taichi.testing.checks", "check_regularizer"),
}


def __getattr__(name: str):
    if name in _LAZY:
        module, attribute = _LAZY[name]
        value = getattr(importlib.import_module(module), attribute)
        globals()[name] = value  # later lookups find it directly
        return value
    raise AttributeError(f"module 'cmax_taichi' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "BackendInfo",
    "Camera",
    "ChainPathWarning",
    "CheckReport",
    "ContrastMaximization",
    "Evaluation",
    "Events",
    "OBJECTIVES",
    "FusedObjective",
    "Limits",
    "NonFiniteResultError",
    "Objective",
    "OptimizeResult",
    "POLARITY_MODES",
    "RECOMMENDED_LAMBDA",
    "REGULARIZERS",
    "Regularizer",
    "SegmentationResult",
    "SimulatedRecording",
    "Simulator",
    "SimulatorConfig",
    "WARPS",
    "WarpModel",
    "backend_info",
    "batch_run",
    "check_model",
    "check_objective",
    "check_regularizer",
    "dense_flow",
    "event_jacobians",
    "get_limits",
    "get_warp",
    "init",
    "maximize",
    "objective_names",
    "read_simulation",
    "register_objective",
    "register_regularizer",
    "register_warp",
    "regularizer_names",
    "segment",
    "set_limits",
    "simulate_preset",
    "unregister_objective",
    "unregister_regularizer",
    "unregister_warp",
    "warmup",
    "warp_names",
]
