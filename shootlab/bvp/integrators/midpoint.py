"""The implicit midpoint rule ([HNW1] sec. II.7, [HW2] sec. IV.3)::

    y+ = y + h f(t + h/2, (y + y+)/2),        R(z) = (1 + z/2) / (1 − z/2),

order 2, A-stable and symmetric (R(−z) = 1/R(z): |R(z)| < 1 exactly when Re z < 0, and
|R| → 1 at infinity), the scheme for stiff boundary value problems with growing and decaying
fast modes.
"""
from __future__ import annotations

from .implicit import _OneStageImplicit


class ImplicitMidpoint(_OneStageImplicit):
    """Implicit midpoint rule ``y+ = y + h f(t + h/2, (y + y+)/2)`` (order 2, A-stable,
    symmetric: ``R(−z) = 1/R(z)``, ``|R(z)| ≶ 1`` exactly when ``Re z ≶ 0``).

    The scheme for stiff *boundary value* problems with growing and decaying fast modes (a
    Hamiltonian TPBVP has both): it neither amplifies the growing modes beyond |R| → 1 (no
    overflow on long shooting intervals) nor turns them into decaying ones as L-stable schemes
    (radau3, implicit Euler) do — that would leave the conditions at b nothing to act on.
    Simplified Newton on ``G(z) = z − y − h f(t + h/2, (y + z)/2)`` from ``z = y`` with
    ``M = I − (h/2) J(t + h/2, y)``.  Sensitivity (implicit function theorem, J* at the
    converged midpoint): ``(I − h/2 J*) S+ = (I + h/2 J*) S``, i.e. ``S+ = 2 (I − h/2 J*)⁻¹ S − S``.
    """

    name = "midpoint"
    order = 2
    stable = "A-stable, symmetric (|R| = 1 on the imaginary axis and at infinity)"
    description = "implicit midpoint rule + simplified Newton, steps equal steps"

    @classmethod
    def stability(cls, z):
        """R(z) = (1 + z/2) / (1 − z/2)."""
        return (1.0 + 0.5 * z) / (1.0 - 0.5 * z)

    theta = 0.5

    def _point(self, y, z):
        return 0.5 * (y + z)
