"""Runge--Kutta--Fehlberg 4(5) without step control (E. Fehlberg, NASA TR R-315, 1969; [HNW1]
sec. II.5), advancing with the 4th-order solution::

    y+ = y + h (25/216 k1 + 1408/2565 k3 + 2197/4104 k4 − 1/5 k5),

the stages k1..k5 of Fehlberg's tableau; R(z) = 1 + z + z²/2 + z³/6 + z⁴/24 + z⁵/104.
"""
from __future__ import annotations

from .explicit import ExplicitRK


class RKF45(ExplicitRK):
    """Runge--Kutta--Fehlberg 4(5) without step control, advancing with the
    4th-order solution as the MUSN code did (E. Fehlberg, NASA TR R-315, 1969;
    [HNW1] sec. II.5).  The 4th-order weights do not use the 6th stage, which
    is therefore not evaluated: 5 rhs calls per step, order 4."""

    name = "rkf45"
    order = 4
    description = "Fehlberg 4(5) advancing with the 4th-order solution, steps equal steps"
    c = (0.0, 1 / 4, 3 / 8, 12 / 13, 1.0)
    a = ((1 / 4,),
         (3 / 32, 9 / 32),
         (1932 / 2197, -7200 / 2197, 7296 / 2197),
         (439 / 216, -8.0, 3680 / 513, -845 / 4104))
    b = (25 / 216, 0.0, 1408 / 2565, 2197 / 4104, -1 / 5)

