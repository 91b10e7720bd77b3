"""The multiple-shooting engine for two-point boundary value problems (report ch. 3)."""
from .batch import ParametricBVP, solve_batch
from .integrators import INTEGRATORS, get_integrator
from .linalg import SingularJacobianError
from .newton import NEWTON, Status, get_newton
from . import trust_region as _trust_region    # noqa: F401  (adds newton="trust_region" to NEWTON)
from .problem import BVP
from .solver import ShootingResult, solve, solve_together
from .suggest import suggest_shooting_points

__all__ = ["BVP", "solve", "solve_together", "solve_batch", "ParametricBVP", "ShootingResult", "Status", "INTEGRATORS", "get_integrator",
           "NEWTON", "get_newton", "SingularJacobianError", "suggest_shooting_points"]
