"""Explicit Runge--Kutta methods given by their Butcher tableau ([HNW1] sec. II.1)::

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),      y+ = y + h Σ_i b_i k_i,

with the forward sensitivities ``K_i = ∂k_i/∂y0`` of the stages (internal numerical
differentiation) and the stability function of the tableau, the polynomial
``R(z) = 1 + Σ_{k≥1} bᵀ A^{k−1} 1 z^k`` ([HNW1] sec. IV.2, A nilpotent).
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np
import torch
from torch import Tensor

from shootlab.bvp.tangents import batched_stages, jacobian_product
from .base import RHS, FixedStepIntegrator
from shootlab.bvp.tangents import _const, _is_dual


def _weighted(coefs: tuple[float, ...], xs: list[Tensor]) -> Tensor:
    """``Σ_j coefs[j] xs[j]`` with the tableau's numbers as Python floats, zero terms skipped: one
    scaled add per term on contiguous tensors.  (Stacking the terms along a new last axis for one
    product with the row costs a strided copy of them all, more than the whole sum.)"""
    acc = None
    for c, x in zip(coefs, xs):
        if c != 0.0:
            acc = x * c if acc is None else acc.add(x, alpha=c)
    return torch.zeros_like(xs[0]) if acc is None else acc


def _combine(y: Tensor, h: Tensor, coefs: tuple[float, ...], ks: list[Tensor]) -> Tensor:
    """``y + h Σ_j coefs[j] ks[j]`` with ``h`` of shape (m,).  Every stage point and every y+ of
    the explicit schemes is formed here, so the residual's and the Jacobian's integrations visit
    the same points bit for bit."""
    hc = h[:, None]
    if _is_dual(y):
        hc = _const(hc, y)
    return y.addcmul(hc, _weighted(coefs, ks))


def _combine_sensitivity(S: Tensor | None, h: Tensor, coefs: tuple[float, ...], Ks: list[Tensor]) -> Tensor:
    """``S + h Σ_j coefs[j] Ks[j]``: :func:`_combine` for the sensitivities (matrices); S None
    for the identity."""
    if S is not None:
        return S.addcmul(h[:, None, None], _weighted(coefs, Ks))
    out = _weighted(coefs, Ks) * h[:, None, None]
    out.diagonal(dim1=-2, dim2=-1).add_(1.0)
    return out


def _rk_stages(rhs: RHS, t: Tensor, y: Tensor, h: Tensor, c: tuple[float, ...],
               a: tuple[tuple[float, ...], ...], k1: Tensor | None = None,
               points: list[Tensor] | None = None) -> list[Tensor]:
    """Stage derivatives ``k_i = rhs(t + c_i h, y + h sum_j a_ij k_j)`` of an
    explicit Runge--Kutta method (``a`` strictly lower triangular, one row per
    stage after the first).  ``k1`` may be supplied (FSAL); ``points`` collects the stage
    points ``Y_i`` after the first."""
    ks = [rhs(t, y) if k1 is None else k1]
    for ci, ai in zip(c[1:], a):
        Y = _combine(y, h, ai, ks)
        if points is not None:
            points.append(Y)
        ks.append(rhs(t + ci * h, Y))
    return ks


def _rk_stages_sensitivity(rhs: RHS, t: Tensor, y: Tensor, S: Tensor | None, h: Tensor, c: tuple[float, ...],
                           a: tuple[tuple[float, ...], ...], k1: tuple[Tensor, Tensor] | None = None
                           ) -> tuple[list[Tensor], list[Tensor]]:
    """Stages ``k_i`` of :func:`_rk_stages` and their sensitivities ``K_i = ∂k_i/∂y0``::

        Y_i = y + h Σ_j a_ij k_j,      ∂Y_i/∂y0 = S + h Σ_j a_ij K_j,
        k_i = f(t + c_i h, Y_i),       K_i = J(t + c_i h, Y_i) ∂Y_i/∂y0.

    The stage points do not depend on the sensitivities, so on few equations
    (:func:`~shootlab.bvp.tangents.batched_stages`) the stages are computed first and J at all their
    points comes from one batched call — a reverse sweep, or the rhs's own Jacobian — instead of
    one per stage (the rows are independent; on bvpT1, 214k → 73k Python calls per solve);
    otherwise each ``(k_i, K_i)`` is one forward-mode call
    (:func:`~shootlab.bvp.tangents.jacobian_product`: J·(∂Y_i/∂y0) without forming J).
    ``k1 = (k_1, K_1)`` may be supplied (FSAL); S None for the identity (an interval's first
    step: K_1 = J, one n × n product per row fewer — at n = 100, 200 rows, 14 ms)."""
    if batched_stages(y.shape[-1]):
        points: list[Tensor] = []
        ks = _rk_stages(rhs, t, y, h, c, a, k1=None if k1 is None else k1[0], points=points)
        times = [t + ci * h for ci in c[1:]]
        if k1 is None:
            points, times = [y] + points, [t] + times
        m = y.shape[0]
        _, J = jacobian_product(rhs, torch.cat(times), torch.cat(points))
        Js = list(J.split(m))
        Ks = [Js.pop(0) if S is None else Js.pop(0) @ S] if k1 is None else [k1[1]]
        for ai, Ji in zip(a, Js):
            Ks.append(Ji @ _combine_sensitivity(S, h, ai, Ks))
        return ks, Ks
    ks, Ks = ([k1[0]], [k1[1]]) if k1 is not None else ([], [])
    if not ks:
        k, K = jacobian_product(rhs, t, y, S)
        ks.append(k)
        Ks.append(K)
    for ci, ai in zip(c[1:], a):
        k, K = jacobian_product(rhs, t + ci * h, _combine(y, h, ai, ks), _combine_sensitivity(S, h, ai, Ks))
        ks.append(k)
        Ks.append(K)
    return ks, Ks


def tableau_polynomial(a: tuple[tuple[float, ...], ...], b: tuple[float, ...]) -> np.ndarray:
    """Coefficients ``[1, c_1, ..., c_s]`` (ascending powers) of the stability polynomial of an
    explicit tableau: ``c_k = bᵀ A^{k−1} 1`` (A strictly lower triangular, hence nilpotent)."""
    s = len(b)
    A = np.zeros((s, s))
    for i, row in enumerate(a, start=1):
        A[i, :len(row)] = row
    coef, v = [1.0], np.ones(s)
    for _ in range(s):
        coef.append(float(np.asarray(b, dtype=float) @ v))
        v = A @ v
    return np.asarray(coef)


class ExplicitRK(FixedStepIntegrator):
    """Explicit Runge--Kutta method with Butcher tableau ``(c, a, b)``,
    ``steps`` equal steps; ``rtol``/``atol`` are accepted and unused."""

    c: ClassVar[tuple[float, ...]]
    a: ClassVar[tuple[tuple[float, ...], ...]]
    b: ClassVar[tuple[float, ...]]

    kind = "explicit"
    stable = "conditionally stable (a bounded region)"
    sensitivities = True

    @classmethod
    def stability(cls, z):
        """The tableau's polynomial (:func:`tableau_polynomial`)."""
        return np.polyval(tableau_polynomial(cls.a, cls.b)[::-1], z)

    @classmethod
    def stability_matrix(cls, Z: Tensor) -> Tensor:
        """The tableau's polynomial at matrices Z (…, n, n), by Horner's rule."""
        coef = tableau_polynomial(cls.a, cls.b)
        eye = torch.eye(Z.shape[-1], dtype=Z.dtype, device=Z.device)
        R = float(coef[-1]) * eye
        for c in coef[-2::-1]:
            R = Z @ R + float(c) * eye
        return R

    def _step(self, rhs, t, y, h):
        ks = _rk_stages(rhs, t, y, h, self.c, self.a)
        ok = torch.ones(y.shape[0], dtype=torch.bool, device=y.device)
        return _combine(y, h, self.b, ks), ok, len(ks)

    def _step_sensitivity(self, rhs, t, y, S, h):
        """``y+ = y + h Σ b_i k_i``,  ``S+ = S + h Σ b_i K_i`` (:func:`_rk_stages_sensitivity`)."""
        ks, Ks = _rk_stages_sensitivity(rhs, t, y, S, h, self.c, self.a)
        ok = torch.ones(y.shape[0], dtype=torch.bool, device=y.device)
        return _combine(y, h, self.b, ks), _combine_sensitivity(S, h, self.b, Ks), ok, len(ks)

