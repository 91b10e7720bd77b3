"""The classical 4-stage Runge--Kutta method ([HNW1] sec. II.1)::

    k1 = f(t, y),                 k2 = f(t + h/2, y + h k1/2),
    k3 = f(t + h/2, y + h k2/2),  k4 = f(t + h, y + h k3),
    y+ = y + h (k1 + 2 k2 + 2 k3 + k4) / 6,

order 4; R(z) = 1 + z + z²/2 + z³/6 + z⁴/24 (real stability limit hλ ≥ −2.785).
"""
from __future__ import annotations

from .explicit import ExplicitRK


class RK4(ExplicitRK):
    """Classical 4-stage Runge--Kutta method of order 4 ([HNW1] sec. II.1)."""

    name = "rk4"
    order = 4
    description = "classical 4-stage Runge-Kutta, steps equal steps"
    c = (0.0, 0.5, 0.5, 1.0)
    a = ((0.5,), (0.0, 0.5), (0.0, 0.0, 1.0))
    b = (1 / 6, 1 / 3, 1 / 3, 1 / 6)

