"""Physics core (numpy + numba, no ROS): parameters, force models, integrators, analysis.

The names below are imported on first use (PEP 562), so ``from afm_ros.core.physics.parameters
import ParamSpec`` (the z controller, the ROS parameter glue) does not pull in numba and the
kernels.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "PeriodAnalysis": "analysis",
    "SteadyStateResult": "analysis",
    "analyze": "analysis",
    "cleveland_sin_phase": "analysis",
    "steady_state": "analysis",
    "free_solution": "analytic",
    "steady_amplitude_phase": "analytic",
    "DMTForce": "forces",
    "NoForce": "forces",
    "make_force_model": "forces",
    "tip_sample_force": "forces",
    "METHODS": "integrators",
    "ALL_PHYSICS_SPECS": "parameters",
    "CANTILEVER_SPECS": "parameters",
    "DMT_SPECS": "parameters",
    "Cantilever": "parameters",
    "DMTSample": "parameters",
    "Drive": "parameters",
    "ParamSpec": "parameters",
    "Samples": "simulation",
    "Simulation": "simulation",
    "seed_simulation": "simulation",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
