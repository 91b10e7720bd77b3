"""Hairer's DOP853: the explicit Runge--Kutta pair of order 8 by Dormand and Prince with the
error estimator of [HNW1] sec. II.10 (coefficients of that section's code DOP853)::

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),  i = 1..12,     y+ = y + h Σ_i b_i k_i  (order 8),

12 stages, and f(t + h, y+) kept for the next step (first same as last), so 12 rhs calls per
step.  The error of the step is estimated from two embedded solutions, of orders 5 and 3::

    err = |h| ‖e₅‖² / √(‖e₅‖² + 0.01 ‖e₃‖²),    e_q = Σ_i E_q,i k_i / sc,

with ‖·‖ the root mean square and sc = atol + rtol max(|y|, |y+|): of order 8 in h for small
steps, and never much below the 5th-order estimate for large ones ([HNW1] p. 254).  Chosen over
``dopri5`` for tight tolerances ([HNW1] Fig. II.10.2), and ``auto``'s explicit pair: on the BVP
test set at rtol 1e-8 it took 0.65 of ``dopri5``'s time (geometric mean over 49 cases) with
errors up to 1e4x smaller (:class:`~shootlab.bvp.integrators.Auto`).
"""
from __future__ import annotations

import numpy as np
import torch

from .adaptive import AdaptiveIntegrator
from .base import _rms
from .explicit import _combine, _combine_sensitivity, _rk_stages, _rk_stages_sensitivity, _weighted, tableau_polynomial


class Dop853(AdaptiveIntegrator):
    """Hairer's DOP853 (module docstring): order 8, 12 stages + FSAL, per-row adaptive steps
    with the combined 5th/3rd-order error estimate."""

    name = "dop853"
    order = 8
    stable = "conditionally stable (step size control keeps hλ in the region)"
    description = "Dormand-Prince 8(5,3) (Hairer's DOP853), per-row adaptive steps"
    error_order = 7                 # the step size exponent −1/8 of DOP853
    fsal = True
    sensitivities = True

    @classmethod
    def stability(cls, z):
        """The tableau's polynomial of the 8th-order solution."""
        return np.polyval(tableau_polynomial(cls.a, cls.b)[::-1], z)

    c = (0.0, 0.05260015195876773, 0.0789002279381516, 0.1183503419072274, 0.2816496580927726,
         0.3333333333333333, 0.25, 0.3076923076923077, 0.6512820512820513, 0.6,
         0.8571428571428571, 1.0)
    a = (
         (0.05260015195876773,),
         (0.0197250569845379, 0.0591751709536137,),
         (0.02958758547680685, 0.0, 0.08876275643042054,),
         (0.2413651341592667, 0.0, -0.8845494793282861, 0.924834003261792,),
         (0.037037037037037035, 0.0, 0.0, 0.17082860872947386, 0.12546768756682242,),
         (0.037109375, 0.0, 0.0, 0.17025221101954405, 0.06021653898045596, -0.017578125,),
         (0.03709200011850479, 0.0, 0.0, 0.17038392571223998, 0.10726203044637328,
          -0.015319437748624402, 0.008273789163814023,),
         (0.6241109587160757, 0.0, 0.0, -3.3608926294469414, -0.868219346841726,
          27.59209969944671, 20.154067550477894, -43.48988418106996,),
         (0.47766253643826434, 0.0, 0.0, -2.4881146199716677, -0.590290826836843,
          21.230051448181193, 15.279233632882423, -33.28821096898486, -0.020331201708508627,),
         (-0.9371424300859873, 0.0, 0.0, 5.186372428844064, 1.0914373489967295,
          -8.149787010746927, -18.52006565999696, 22.739487099350505, 2.4936055526796523,
          -3.0467644718982196,),
         (2.273310147516538, 0.0, 0.0, -10.53449546673725, -2.0008720582248625,
          -17.9589318631188, 27.94888452941996, -2.8589982771350235, -8.87285693353063,
          12.360567175794303, 0.6433927460157636,),
    )
    b = (0.054293734116568765, 0.0, 0.0, 0.0, 0.0, 4.450312892752409, 1.8915178993145003,
         -5.801203960010585, 0.3111643669578199, -0.1521609496625161, 0.20136540080403034,
         0.04471061572777259)
    #: the two error estimators of [HNW1] sec. II.10 (13 entries: the 13th, FSAL, stage has weight 0)
    e3 = (-0.18980075407240762, 0.0, 0.0, 0.0, 0.0, 4.450312892752409, 1.8915178993145003,
          -5.801203960010585, -0.4226823213237919, -0.1521609496625161, 0.20136540080403034,
          0.02265179219836082, 0.0)
    e5 = (0.01312004499419488, 0.0, 0.0, 0.0, 0.0, -1.2251564463762044, -0.4957589496572502,
          1.6643771824549864, -0.35032884874997366, 0.3341791187130175, 0.08192320648511571,
          -0.022355307863886294, 0.0)

    def _error(self, y: torch.Tensor, y_new: torch.Tensor, h: torch.Tensor, ks: list[torch.Tensor]) -> torch.Tensor:
        """A vector whose scaled rms is the combined estimate of the module docstring (the step
        size control of :class:`AdaptiveIntegrator` takes the rms of error / sc)."""
        rtol, atol = self.tolerances()
        sc = atol + rtol * torch.maximum(y.detach().abs(), y_new.detach().abs())
        k = [x.detach() for x in ks]
        e5, e3 = _weighted(self.e5, k), _weighted(self.e3, k)
        r5, r3 = _rms(e5 / sc), _rms(e3 / sc)
        weight = torch.where(r5 > 0, r5 / torch.sqrt(r5 ** 2 + 0.01 * r3 ** 2), torch.zeros_like(r5))
        return (h * weight)[:, None] * e5

    def _attempt(self, rhs, t, y, h, f):
        ks = _rk_stages(rhs, t, y, h, self.c, self.a, k1=f)
        y_new = _combine(y, h, self.b, ks)
        ks.append(rhs(t + h, y_new))
        return y_new, self._error(y, y_new, h, ks), ks[-1], 12

    def _attempt_sensitivity(self, rhs, t, y, S, h, f):
        """Stages and their sensitivities (:func:`_rk_stages_sensitivity`), FSAL for both: the
        13th stage, (f, J S) at (t + h, y+), is the stage of coefficients b at c = 1."""
        ks, Ks = _rk_stages_sensitivity(rhs, t, y, S, h, self.c + (1.0,), self.a + (self.b,), k1=f)
        y_new, S_new = _combine(y, h, self.b, ks[:-1]), _combine_sensitivity(S, h, self.b, Ks[:-1])
        return y_new, S_new, self._error(y, y_new, h, ks), (ks[-1], Ks[-1]), 12
