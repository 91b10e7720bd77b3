"""Mechanical systems of shootlab: friction laws, the flexible rotation manipulator's
virtual rig and the mass–spring–damper data generator.

Names are imported lazily (PEP 562), so ``import manipulators`` does not import torch or
scipy; ``from manipulators import simulate_rig`` loads :mod:`manipulators.rig` on demand.
"""
from __future__ import annotations

import importlib

# public name -> submodule that defines it
_EXPORTS = {
    # manipulators.friction
    "smooth_sign": "friction",
    "smooth_sign_dv": "friction",
    "smooth_coulomb": "friction",
    "smooth_coulomb_dv": "friction",
    "viscous": "friction",
    "viscous_dv": "friction",
    "stribeck": "friction",
    "stribeck_dv": "friction",
    "FrictionLaw": "friction",
    "SmoothCoulomb": "friction",
    "Viscous": "friction",
    "Stribeck": "friction",
    "CombinedFriction": "friction",
    # manipulators.rig
    "RigSettings": "rig",
    "RigData": "rig",
    "PDController": "rig",
    "TwoInertia": "rig",
    "eigenfrequency_hz": "rig",
    "linear_system_matrices": "rig",
    "sine_sweep": "rig",
    "smoothed_steps": "rig",
    "pd_validation_input": "rig",
    "simulate_rig": "rig",
    "msd_input": "rig",
    "msd_data": "rig",
    "save_csv": "rig",
    "load_csv": "rig",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    mod = _EXPORTS.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{mod}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
