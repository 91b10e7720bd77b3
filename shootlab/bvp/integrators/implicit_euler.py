"""Backward (implicit) Euler ([HW2] sec. IV.3)::

    y+ = y + h f(t + h, y+),        R(z) = 1 / (1 − z),

order 1, L-stable: R(z) → 0 for z → ∞ in any direction, so it damps growing modes too (a
TPBVP's growing partner becomes a decaying one once |hλ| > 2).
"""
from __future__ import annotations

from .implicit import _OneStageImplicit


class ImplicitEuler(_OneStageImplicit):
    """Backward Euler, ``y+ = y + h f(t + h, y+)`` (order 1, L-stable).

    Simplified Newton on ``G(z) = z - y - h f(t+h, z)`` from ``z = y`` with
    ``M = I - h J(t+h, y)``.  Sensitivity (implicit function theorem):
    ``(I − h J(t+h, y+)) S+ = S``.
    """

    name = "implicit_euler"
    order = 1
    stable = "L-stable"
    description = "backward Euler + simplified Newton, steps equal steps"

    @classmethod
    def stability(cls, z):
        """R(z) = 1 / (1 − z)."""
        return 1.0 / (1.0 - z)

    theta = 1.0

    def _point(self, y, z):
        return z
