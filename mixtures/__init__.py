"""Confined compression of a biphasic mixture (report ch. 5): FE model and analytic checks."""
from .confined import (
    DEFAULT_EXPERIMENT,
    MEASUREMENT_COLUMNS,
    CallableHistory,
    ConfinedCompression,
    ConstantPermeability,
    ExponentialPermeability,
    ExponentialSolid,
    LinearSolid,
    Matrices,
    Measurements,
    RampHoldLoad,
    SampledHistory,
    Simulation,
    StepLoad,
    as_history,
    creep,
    read_measurements_csv,
    simulate,
    simulated_measurements,
    stress_relaxation,
    write_measurements_csv,
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
    "Matrices", "Measurements", "RampHoldLoad", "SampledHistory", "Simulation", "StepLoad",
    "as_history", "creep", "read_measurements_csv", "simulate", "simulated_measurements",
    "stress_relaxation", "write_measurements_csv", "consolidation_coefficient",
    "degree_of_consolidation", "ramp_hold_pressure", "ramp_hold_settlement", "terzaghi_pressure",
    "terzaghi_settlement", "time_factor",
]
