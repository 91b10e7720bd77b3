"""Explicit Euler ([HNW1] sec. I.7)::

    y+ = y + h f(t, y),        R(z) = 1 + z,

order 1, stable for |1 + hλ| ≤ 1 (real limit hλ ≥ −2).
"""
from __future__ import annotations

from .explicit import ExplicitRK


class Euler(ExplicitRK):
    """Explicit Euler, ``y+ = y + h f(t, y)`` (order 1).  ``steps=1`` is a single
    Euler step over the whole interval."""

    name = "euler"
    order = 1
    description = "explicit Euler, steps equal steps"
    c = (0.0,)
    a = ()
    b = (1.0,)

