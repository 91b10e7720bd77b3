"""Confined compression of a biphasic mixture (report ch. 5): FE model and analytic checks.

Modules: :mod:`~mixtures.laws` (material laws), :mod:`~mixtures.confined` (the finite-element
model), :mod:`~mixtures.loads` (prescribed histories), :mod:`~mixtures.simulation` (forward
simulation, simulated records), :mod:`~mixtures.terzaghi` (analytic solution),
:mod:`~mixtures.identification` (the estimation model), :mod:`~mixtures.prefit` (output-error
prefit), :mod:`~mixtures.effects` (the diagnosis library).  Records are
:class:`shootlab.estimation.data.Measurements`.
"""
from .confined import ConfinedCompression, Matrices
from .laws import ConstantPermeability, ExponentialPermeability, ExponentialSolid, LinearSolid
from .loads import DEFAULT_EXPERIMENT, CallableHistory, RampHoldLoad, SampledHistory, StepLoad, as_history
from .simulation import (
    MEASUREMENT_COLUMNS,
    Simulation,
    creep,
    simulate,
    simulated_measurements,
    stress_relaxation,
)
from .terzaghi import (
    consolidation_coefficient,
    degree_of_consolidation,
    ramp_hold_pressure,
    ramp_hold_settlement,
    terzaghi_pressure,
    terzaghi_settlement,
    time_factor,
)

__all__ = [
    "DEFAULT_EXPERIMENT", "MEASUREMENT_COLUMNS", "CallableHistory", "ConfinedCompression",
    "ConstantPermeability", "ExponentialPermeability", "ExponentialSolid", "LinearSolid",
    "Matrices", "RampHoldLoad", "SampledHistory", "Simulation", "StepLoad",
    "as_history", "creep", "simulate", "simulated_measurements",
    "stress_relaxation", "consolidation_coefficient",
    "degree_of_consolidation", "ramp_hold_pressure", "ramp_hold_settlement", "terzaghi_pressure",
    "terzaghi_settlement", "time_factor",
]
