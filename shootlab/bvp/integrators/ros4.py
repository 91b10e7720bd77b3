"""Shampine's Rosenbrock method 4(3) (L.F. Shampine, ACM TOMS 8 (1982) 93-113) with the
coefficients of [NR] routine ``stiff`` ([NR] W.H. Press et al., Numerical Recipes in C, 2nd ed.,
1992, sec. 16.6; Rosenbrock methods: [HW2] sec. IV.7).  With ``W = I/(γh) − J``::

    W g_i = f(t + α_i h, y + Σ_{j<i} a_ij g_j) + c_ix h f_t + Σ_{j<i} c_ij g_j / h,
    y+ = y + Σ_i b_i g_i  (order 4),   error estimate Σ_i e_i g_i  (order 3),

A-stable, not L-stable: R(∞) = 1/3.  R(z) follows from the same recursion on y' = λ y.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from shootlab.bvp.tangents import jacobian_product, second_product, time_derivative
from .adaptive import AdaptiveIntegrator
from shootlab.bvp.tangents import _const, _value_and_jacobian
from .base import _lincomb, _matcomb


class Ros4(AdaptiveIntegrator):
    """Rosenbrock method 4(3) of Shampine, A-stable (L.F. Shampine, ACM TOMS 8
    (1982) 93-113), with the coefficients of [NR] routine ``stiff``.

    With ``W = I / (gamma h) - J``, ``J = df/dy(t, y)``, ``f_t = df/dt(t, y)``:

        W g1 = f(t, y)                             + c1x h f_t
        W g2 = f(t + a2x h, y + a21 g1)            + c2x h f_t + c21 g1 / h
        W g3 = f(t + a3x h, y + a31 g1 + a32 g2)   + c3x h f_t + (c31 g1 + c32 g2) / h
        W g4 = f(t + a3x h, y + a31 g1 + a32 g2)   + c4x h f_t + (c41 g1 + c42 g2 + c43 g3) / h
        y+   = y + sum_i b_i g_i,   error estimate sum_i e_i g_i (order 3).

    The 4th stage reuses the 3rd function value: 3 rhs calls per step, one of
    which also yields J and f_t by autograd; W is LU-factored once per step
    (batched).  A singular W counts as a non-finite attempt (step shrinks).

    The method is A-stable but not L-stable (``R(-inf) = 1/3``) and not
    stiffly accurate: on stiff problems driven by a time-dependent forcing
    (Prothero--Robinson type, ``y' = lam (y - g(t)) + g'(t)``) its error
    behaves like ``h^2``, so the controller takes many more steps there than
    on a linear stiff system or on chemical kinetics.
    """

    name = "ros4"
    order = 4
    stable = "A-stable, not L-stable (R(∞) = 1/3)"
    description = "Shampine's Rosenbrock 4(3), per-row adaptive steps"

    @classmethod
    def stability(cls, z):
        """The stage recursion on y' = λ y, y = 1, z = hλ (f_t = 0): with ``w = 1/γ − z``
        (h W), ``w g_i = z (1 + Σ_j a_ij g_j) + Σ_j c_ij g_j``, ``R = 1 + Σ_i b_i g_i``."""
        z = np.asarray(z, dtype=complex)
        w = 1.0 / cls.gam - z
        g1 = z / w
        g2 = (z * (1.0 + cls.a[0][0] * g1) + cls.c[1][0] * g1) / w
        f3 = z * (1.0 + cls.a[1][0] * g1 + cls.a[1][1] * g2)
        g3 = (f3 + cls.c[2][0] * g1 + cls.c[2][1] * g2) / w
        g4 = (f3 + cls.c[3][0] * g1 + cls.c[3][1] * g2 + cls.c[3][2] * g3) / w
        gs = (g1, g2, g3, g4)
        return 1.0 + sum(b * g for b, g in zip(cls.b, gs))
    error_order = 3
    gam = 1 / 2
    a = ((2.0,), (48 / 25, 6 / 25))  # a21; a31, a32 (stage 4 reuses stage 3)
    ax = (1.0, 3 / 5)  # a2x, a3x: stage times t + ax h
    c = ((), (-8.0,), (372 / 25, 12 / 5), (-112 / 125, -54 / 125, -2 / 5))  # c_ij, j < i
    cx = (1 / 2, -3 / 2, 121 / 50, 29 / 250)  # c1x..c4x
    b = (19 / 9, 1 / 2, 25 / 108, 125 / 108)
    e = (17 / 54, 7 / 36, 0.0, 125 / 108)

    def _attempt(self, rhs, t, y, h, f):
        n = y.shape[-1]
        f1, jac, dfdt = _value_and_jacobian(rhs, t, y, with_time=True)
        hc = h[:, None]
        eye = torch.eye(n, dtype=y.dtype, device=y.device)
        w = _const(eye / (self.gam * hc[..., None]), y) - jac
        lu, piv, info = torch.linalg.lu_factor_ex(w)

        def stage(i: int, f_i: Tensor, gs: list[Tensor]) -> Tensor:
            """g_i = W^-1 (f_i + c_ix h f_t + sum_j c_ij g_j / h)."""
            c_ij = hc.new_tensor(self.c[i]).expand(len(h), i)
            coefs = torch.cat([self.cx[i] * hc, c_ij / hc], -1)
            r = f_i + _lincomb(_const(coefs, y), [dfdt, *gs])
            return torch.linalg.lu_solve(lu, piv, r.unsqueeze(-1)).squeeze(-1)

        g1 = stage(0, f1, [])
        f2 = rhs(t + self.ax[0] * h, y + _lincomb(_const(self.a[0], y), [g1]))
        g2 = stage(1, f2, [g1])
        f3 = rhs(t + self.ax[1] * h, y + _lincomb(_const(self.a[1], y), [g1, g2]))
        g3 = stage(2, f3, [g1, g2])
        g4 = stage(3, f3, [g1, g2, g3])
        gs = [g1, g2, g3, g4]
        y_new = y + _lincomb(_const(self.b, y), gs)
        err = _lincomb(h.new_tensor(self.e), [g.detach() for g in gs])
        err = torch.where((info == 0)[:, None], err, torch.full_like(err, math.inf))
        return y_new, err, None, 3

    sensitivities = True

    def _attempt_sensitivity(self, rhs, t, y, S, h, f):
        """The stages of :meth:`_attempt` and their sensitivities ``G_i = ∂g_i/∂y0`` (h fixed).
        Differentiating ``W g_i = r_i``, ``W = I/(γh) − J(t, y)``::

            W G_i = F_i + Σ_j c_ij G_j / h + D_y[J g_i + c_ix h f_t] S,

        with ``F_i = J(t_i, Y_i) ∂Y_i/∂y0`` the sensitivity of the stage value f_i and the
        last term the second derivative of f (:func:`shootlab.bvp.tangents.second_product`,
        the derivative of W and f_t); ``S+ = S + Σ b_i G_i``."""
        n = y.shape[-1]
        f1, J = jacobian_product(rhs, t, y)
        dfdt = time_derivative(rhs, t, y)
        hc = h[:, None]
        eye = torch.eye(n, dtype=y.dtype, device=y.device)
        lu, piv, info = torch.linalg.lu_factor_ex(eye / (self.gam * hc[..., None]) - J)
        gs: list[Tensor] = []
        Gs: list[Tensor] = []

        def stage(i: int, f_i: Tensor, F_i: Tensor) -> None:
            c_ij = hc.new_tensor(self.c[i]).expand(len(h), i) / hc
            r = f_i + self.cx[i] * hc * dfdt + (_lincomb(c_ij, gs) if i else 0.0)
            g = torch.linalg.lu_solve(lu, piv, r.unsqueeze(-1)).squeeze(-1)
            R = F_i + second_product(rhs, t, y, g, self.cx[i] * h, S) + (_matcomb(c_ij, Gs) if i else 0.0)
            gs.append(g)
            Gs.append(torch.linalg.lu_solve(lu, piv, R))

        stage(0, f1, J @ S)
        a21 = hc.new_tensor(self.a[0]).expand(len(h), 1)
        f2, F2 = jacobian_product(rhs, t + self.ax[0] * h, y + _lincomb(a21, gs), S + _matcomb(a21, Gs))
        stage(1, f2, F2)
        a3 = hc.new_tensor(self.a[1]).expand(len(h), 2)
        f3, F3 = jacobian_product(rhs, t + self.ax[1] * h, y + _lincomb(a3, gs), S + _matcomb(a3, Gs))
        stage(2, f3, F3)
        stage(3, f3, F3)
        b = hc.new_tensor(self.b).expand(len(h), 4)
        err = _lincomb(h.new_tensor(self.e), gs)
        err = torch.where((info == 0)[:, None], err, torch.full_like(err, math.inf))
        return y + _lincomb(b, gs), S + _matcomb(b, Gs), err, None, 3

