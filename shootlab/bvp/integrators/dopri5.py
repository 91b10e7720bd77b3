"""The Dormand--Prince 5(4) pair (J.R. Dormand, P.J. Prince, J. Comput. Appl. Math. 6 (1980)
19-26; coefficients from [HNW1] Table II.5.2)::

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),  i = 1..7,
    y+ = y + h Σ_i b_i k_i  (order 5),   error estimate h Σ_i (b_i − b̂_i) k_i  (order 4),

7 stages, first-same-as-last (k7 = f(t + h, y+)), so 6 rhs calls per step.  One step's
stability function is the 6th-degree polynomial of the tableau, R(z) = Σ_{k≤5} z^k/k! + z⁶/600
(real stability limit hλ ≥ −3.3); the step size control keeps hλ inside that region.
"""
from __future__ import annotations

import numpy as np

from .adaptive import AdaptiveIntegrator
from .explicit import _combine, _combine_sensitivity, _rk_stages, _rk_stages_sensitivity, _weighted, tableau_polynomial


class Dopri5(AdaptiveIntegrator):
    """Dormand--Prince 5(4) (J.R. Dormand, P.J. Prince, J. Comput. Appl. Math.
    6 (1980) 19-26; coefficients from [HNW1] Table II.5.2).  Advances with the
    5th-order solution; 7 stages, first-same-as-last, so 6 rhs calls per
    step.  Error estimate ``h sum_i (b_i - bhat_i) k_i`` is of order 4.
    """

    name = "dopri5"
    order = 5
    stable = "conditionally stable (step size control keeps hλ in the region)"
    description = "Dormand-Prince 5(4), per-row adaptive steps"

    @classmethod
    def stability(cls, z):
        """The tableau's polynomial of the 5th-order solution (degree 6)."""
        return np.polyval(tableau_polynomial(cls.a, cls.b)[::-1], z)
    error_order = 4
    fsal = True
    c = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0)
    a = ((1 / 5,),
         (3 / 40, 9 / 40),
         (44 / 45, -56 / 15, 32 / 9),
         (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
         (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656))
    b = (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84)
    bhat = (5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40)
    e = tuple(bi - bh for bi, bh in zip(b + (0.0,), bhat))  # b_7 = 0 (FSAL stage)

    sensitivities = True

    def _attempt(self, rhs, t, y, h, f):
        ks = _rk_stages(rhs, t, y, h, self.c, self.a, k1=f)
        y_new = _combine(y, h, self.b, ks)
        ks.append(rhs(t + h, y_new))
        return y_new, self._error(h, ks), ks[-1], 6

    def _attempt_sensitivity(self, rhs, t, y, S, h, f):
        """Stages and their sensitivities (:func:`_rk_stages_sensitivity`), FSAL for both: the
        7th stage, (f, J S) at (t + h, y+), is the stage of coefficients b at c = 1."""
        ks, Ks = _rk_stages_sensitivity(rhs, t, y, S, h, self.c + (1.0,), self.a + (self.b,), k1=f)
        y_new, S_new = _combine(y, h, self.b, ks[:-1]), _combine_sensitivity(S, h, self.b, Ks[:-1])
        return y_new, S_new, self._error(h, ks), (ks[-1], Ks[-1]), 6

    def _error(self, h, ks):
        """h Σ_i (b_i − b̂_i) k_i, on detached values."""
        return h[:, None] * _weighted(self.e, [k.detach() for k in ks])
