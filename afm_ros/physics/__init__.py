"""Physics core (numpy + numba, no ROS): parameters, force models, integrators, analysis."""
from .analysis import PeriodAnalysis, SteadyStateResult, analyze, cleveland_sin_phase, steady_state
from .analytic import free_solution, steady_amplitude_phase
from .forces import DMTForce, NoForce, make_force_model, tip_sample_force
from .integrators import METHODS
from .parameters import (ALL_PHYSICS_SPECS, CANTILEVER_SPECS, DMT_SPECS, Cantilever, DMTSample, Drive,
                         ParamSpec)
from .simulation import Samples, Simulation, seed_simulation

__all__ = [
    "PeriodAnalysis", "SteadyStateResult", "analyze", "cleveland_sin_phase", "steady_state",
    "free_solution", "steady_amplitude_phase", "DMTForce", "NoForce", "make_force_model",
    "tip_sample_force", "METHODS", "ALL_PHYSICS_SPECS", "CANTILEVER_SPECS", "DMT_SPECS",
    "Cantilever", "DMTSample", "Drive", "ParamSpec", "Samples", "Simulation", "seed_simulation",
]
