"""Friction laws for the manipulator models and the virtual rig.

Every law is written once, as a formula over an *array namespace* that is either
``torch`` or ``numpy``: if any argument is a ``torch.Tensor`` the torch functions are
used (autograd works, shapes broadcast over any leading batch dimensions), otherwise
numpy is used (plain floats / ``np.ndarray``, e.g. inside ``scipy.integrate.solve_ivp``).
This module does not import torch itself (numpy-only use stays light).

All laws return the friction torque **opposing** the motion convention used in
:mod:`manipulators.rig`: the law gives ``f(v)`` with the sign of ``v``; the equation
of motion subtracts it (``m v' = ... - f(v)``).

Laws (each with its analytic derivative ``d f / d v``):

* smooth Coulomb (DESIGN §3, report §4.3, "sinusoidal acceleration" transition)::

      f(v) = f_c * (v/v_s + sin(pi v / v_s) / pi)   for |v| <  v_s
      f(v) = f_c * sign(v)                          for |v| >= v_s
      f'(v) = (f_c / v_s) * (1 + cos(pi v / v_s))   for |v| <  v_s, 0 outside

  At ``v = ±v_s`` value (±f_c) and slope (0) match from both sides, and even the second
  derivative (``-pi f_c sin(pi v/v_s)/v_s**2`` → 0) matches, so the law is C².
  The slope at ``v = 0`` is ``2 f_c / v_s``.

* viscous: ``f(v) = b_v v``, ``f'(v) = b_v``.

* Stribeck (C¹): ``f(v) = (f_c + (f_s - f_c) exp(-(v/v_st)^2)) * σ(v) + b_v v`` where
  ``σ(v)`` is the smooth sign above (``smooth_coulomb`` with ``f_c = 1``). A product of
  C¹ (in fact C²) functions, hence C¹.

Parameters may be floats or tensors (e.g. ``f_c`` taken from an augmented state vector,
shape ``(batch,)``); they broadcast against ``v``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

import sys

__all__ = [
    "smooth_sign",
    "smooth_sign_dv",
    "smooth_coulomb",
    "smooth_coulomb_dv",
    "viscous",
    "viscous_dv",
    "stribeck",
    "stribeck_dv",
    "FrictionLaw",
    "SmoothCoulomb",
    "Viscous",
    "Stribeck",
    "CombinedFriction",
]

_PI = math.pi


def _xp(*args: Any):
    """Return ``torch`` if any argument is a tensor, else ``numpy``.

    torch is looked up in ``sys.modules`` instead of being imported: if it has not been
    imported, no argument can be a tensor, so numpy-only users (the rig simulator) never pay
    for importing torch.
    """
    torch = sys.modules.get("torch")
    if torch is not None:
        for a in args:
            if isinstance(a, torch.Tensor):
                return torch
    return np


def _as_array(xp, v):
    if xp is np:
        return np.asarray(v, dtype=float)
    return v if isinstance(v, xp.Tensor) else xp.as_tensor(v, dtype=xp.get_default_dtype())


def _scalars(*args: Any) -> bool:
    """True when every argument is a plain number (a Python or numpy float, an int): the laws then
    take :mod:`math`'s scalar functions — a simulator's right-hand side calls them once per
    evaluation, where numpy's array machinery costs ten times the arithmetic."""
    return all(type(a) in (float, int, np.float64) for a in args)


def _sign(x: float) -> float:
    """``np.sign`` of a float (NaN stays NaN)."""
    return 1.0 if x > 0 else -1.0 if x < 0 else x


def _finish(xp, out, *args):
    """Return a numpy scalar as a Python float when all inputs were scalars."""
    if xp is np and all(np.ndim(a) == 0 for a in args):
        return float(out)
    return out


# ----------------------------------------------------------------------------- smooth sign
def smooth_sign(v, v_s):
    """C¹ (indeed C²) sign with a sinusoidal-acceleration transition of half-width ``v_s``.

    ``σ(v) = x + sin(pi x)/pi`` with ``x = v / v_s`` for ``|x| < 1``, ``sign(v)`` outside.
    """
    if _scalars(v, v_s) and v_s != 0:
        x = v / v_s
        return float(x + math.sin(_PI * x) / _PI) if abs(x) < 1.0 else _sign(float(x))
    xp = _xp(v, v_s)
    vv = _as_array(xp, v)
    x = vv / v_s
    xc = xp.clip(x, -1.0, 1.0)
    inner = xc + xp.sin(_PI * xc) / _PI
    out = xp.where(xp.abs(x) < 1.0, inner, xp.sign(x))
    return _finish(xp, out, v, v_s)


def smooth_sign_dv(v, v_s):
    """``d σ / d v = (1 + cos(pi v/v_s)) / v_s`` inside the transition, 0 outside."""
    xp = _xp(v, v_s)
    vv = _as_array(xp, v)
    x = vv / v_s
    xc = xp.clip(x, -1.0, 1.0)
    inner = (1.0 + xp.cos(_PI * xc)) / v_s
    out = xp.where(xp.abs(x) < 1.0, inner, xp.zeros_like(inner))
    return _finish(xp, out, v, v_s)


# ----------------------------------------------------------------------------- laws
def smooth_coulomb(v, f_c, v_s):
    """Smooth Coulomb friction ``f_c σ(v)`` (DESIGN §3)."""
    out = f_c * smooth_sign(v, v_s)
    return out


def smooth_coulomb_dv(v, f_c, v_s):
    """``d/dv`` of :func:`smooth_coulomb`."""
    return f_c * smooth_sign_dv(v, v_s)


def viscous(v, b_v):
    """Viscous friction ``b_v v``."""
    return b_v * v


def viscous_dv(v, b_v):
    """``d/dv`` of :func:`viscous` (``b_v``, broadcast to the shape of ``v``)."""
    xp = _xp(v, b_v)
    vv = _as_array(xp, v)
    out = b_v * xp.ones_like(vv)
    return _finish(xp, out, v, b_v)


def _stribeck_level(xp, vv, f_c, f_s, v_st):
    e = xp.exp(-((vv / v_st) ** 2))
    return f_c + (f_s - f_c) * e, e


def stribeck(v, f_c, f_s, v_st, v_s, b_v=0.0):
    """C¹ Stribeck friction.

    ``f(v) = (f_c + (f_s - f_c) exp(-(v/v_st)^2)) σ(v) + b_v v`` with ``σ`` the smooth sign of
    half-width ``v_s``. ``f_s`` is the static (break-away) level, ``f_c`` the Coulomb level,
    ``v_st`` the Stribeck velocity.
    """
    if _scalars(v, f_c, f_s, v_st, v_s, b_v) and v_st != 0:
        r = v / v_st
        return float((f_c + (f_s - f_c) * math.exp(-(r * r))) * smooth_sign(v, v_s) + b_v * v)
    xp = _xp(v, f_c, f_s, v_st, v_s, b_v)
    vv = _as_array(xp, v)
    level, _ = _stribeck_level(xp, vv, f_c, f_s, v_st)
    out = level * smooth_sign(vv, v_s) + b_v * vv
    return _finish(xp, out, v, f_c, f_s, v_st, v_s, b_v)


def stribeck_dv(v, f_c, f_s, v_st, v_s, b_v=0.0):
    """``d/dv`` of :func:`stribeck`."""
    xp = _xp(v, f_c, f_s, v_st, v_s, b_v)
    vv = _as_array(xp, v)
    level, e = _stribeck_level(xp, vv, f_c, f_s, v_st)
    dlevel = (f_s - f_c) * e * (-2.0 * vv / v_st**2)
    out = dlevel * smooth_sign(vv, v_s) + level * smooth_sign_dv(vv, v_s) + b_v
    return _finish(xp, out, v, f_c, f_s, v_st, v_s, b_v)


# ----------------------------------------------------------------------------- classes
class FrictionLaw:
    """Base class: ``law(v)`` gives the friction torque, ``law.dv(v)`` its derivative."""

    def __call__(self, v):  # pragma: no cover - abstract
        raise NotImplementedError

    def dv(self, v):  # pragma: no cover - abstract
        raise NotImplementedError

    # alias, for readability at call sites
    def derivative(self, v):
        return self.dv(v)

    def __add__(self, other: "FrictionLaw") -> "CombinedFriction":
        return CombinedFriction((self, other))


@dataclass(frozen=True)
class SmoothCoulomb(FrictionLaw):
    """Smooth Coulomb friction of level ``f_c`` and transition half-width ``v_s``."""

    f_c: Any
    v_s: Any

    def __call__(self, v):
        return smooth_coulomb(v, self.f_c, self.v_s)

    def dv(self, v):
        return smooth_coulomb_dv(v, self.f_c, self.v_s)


@dataclass(frozen=True)
class Viscous(FrictionLaw):
    """Viscous friction ``b_v v``."""

    b_v: Any

    def __call__(self, v):
        return viscous(v, self.b_v)

    def dv(self, v):
        return viscous_dv(v, self.b_v)


@dataclass(frozen=True)
class Stribeck(FrictionLaw):
    """C¹ Stribeck friction (see :func:`stribeck`)."""

    f_c: Any
    f_s: Any
    v_st: Any
    v_s: Any
    b_v: Any = 0.0

    def __call__(self, v):
        return stribeck(v, self.f_c, self.f_s, self.v_st, self.v_s, self.b_v)

    def dv(self, v):
        return stribeck_dv(v, self.f_c, self.f_s, self.v_st, self.v_s, self.b_v)


@dataclass(frozen=True)
class CombinedFriction(FrictionLaw):
    """Sum of several friction laws."""

    laws: tuple

    def __call__(self, v):
        out = 0.0
        for law in self.laws:
            out = out + law(v)
        return out

    def dv(self, v):
        out = 0.0
        for law in self.laws:
            out = out + law.dv(v)
        return out

    def __add__(self, other: FrictionLaw) -> "CombinedFriction":
        return CombinedFriction(self.laws + (other,))
