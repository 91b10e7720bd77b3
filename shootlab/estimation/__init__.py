"""Optimal estimation: a model in augmented state form, the TPBVP of its optimality conditions."""
from .data import Measurements
from .fit import EstimationResult, estimate
from .model import IdentificationModel, smoothed

__all__ = ["IdentificationModel", "EstimationResult", "estimate", "Measurements", "smoothed"]
