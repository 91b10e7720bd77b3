"""Implicit fixed-step schemes: the stage equations ``G(z) = 0`` of one step solved by simplified
Newton ([HW2] sec. IV.8) on detached values, and derivatives by the implicit function theorem at
the converged stages, ``∂z/∂y = −G_z⁻¹ G_y`` (not through the Newton iterations).
"""
from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from shootlab.bvp.tangents import rhs_jacobian
from .base import FixedStepIntegrator, _rms
from shootlab.bvp.tangents import _const, _is_dual


def _simplified_newton(G: Callable[[Tensor, Tensor], Tensor], matrix: Callable[[Tensor, Tensor], Tensor],
                       z: Tensor, scale: Tensor, maxiter: int, theta_max: float = 0.25,
                       held: "HeldNewton | None" = None) -> tuple[Tensor, Tensor, int]:
    """Row-wise simplified Newton iteration for ``G(z) = 0`` on detached values ([HW2] sec. IV.8).

    ``matrix(rows, z_rows)`` gives the Newton matrix ``M ≈ G'(z)`` (r, N, N) of the rows ``rows``
    (indices into the batch); it is formed and LU-factored at the starting iterate and kept for
    ``z ← z − M⁻¹ G(z)`` (``G(rows, z_rows)`` (r, N)) while the iteration contracts fast,
    ``θ_k = ‖Δz_k‖ / ‖Δz_{k−1}‖ < theta_max``; a row that contracts more slowly (or grows) gets a
    fresh matrix at its new iterate — at worst full Newton.  Converged: ``rms(Δz / scale) ≤ 1``
    within ``maxiter`` iterations; a row with a non-finite correction or a singular matrix fails.

    ``held`` (:class:`HeldNewton`, the steps of one interval): the factorised matrices of its last
    step are kept (the step size is the same) and every one formed here is kept for the next, and
    the test is on the contraction ([HW2] sec. IV.8): the error left after a correction is about
    η_k ‖Δz_k‖, η_k = θ_k / (1 − θ_k), so a row is converged when ``η_k rms(Δz_k / scale) ≤ 1`` —
    at the first correction with η_0 = max(η, 1e-16)^0.8 of the step before; every row's last η
    is kept.  Where the iteration contracts fast (a linear system: η ≈ 0) one correction a step.

    Returns ``(z, converged, nfev)``; nfev counts the G calls and the matrix builds.
    """
    m = z.shape[0]
    z = z.detach().clone()
    converged = torch.zeros(m, dtype=torch.bool, device=z.device)
    rows = torch.arange(m, device=z.device)
    stale = torch.ones(m, dtype=torch.bool, device=z.device)
    prev = torch.full((m,), math.inf, dtype=z.dtype, device=z.device)
    lu = piv = None
    nfev = 0
    if held is not None:
        last = held.eta.clamp_min(1e-16) ** 0.8          # η_0 (per row of ``rows``)
        if held.factors is not None:
            (lu, piv), stale = held.factors, torch.zeros_like(stale)
    for k in range(maxiter):
        if not rows.numel():
            break
        if stale.any():
            lu_s, piv_s, info = torch.linalg.lu_factor_ex(matrix(rows[stale], z[rows[stale]]))
            nfev += 1
            if held is not None:
                held.keep(rows[stale], lu_s, piv_s)
            if lu is None:
                lu, piv = lu_s, piv_s
            else:
                lu, piv = lu.clone(), piv.clone()
                lu[stale], piv[stale] = lu_s, piv_s
            usable = torch.ones_like(stale)
            usable[stale] = info == 0
            rows, lu, piv, prev = rows[usable], lu[usable], piv[usable], prev[usable]
            if held is not None:
                last = last[usable]
            if not rows.numel():
                break
        dz = torch.linalg.lu_solve(lu, piv, G(rows, z[rows]).unsqueeze(-1)).squeeze(-1)
        nfev += 1
        err = _rms(dz / scale[rows])
        finite = torch.isfinite(err)
        z[rows[finite]] -= dz[finite]
        if held is None:
            done = finite & (err <= 1.0)
        else:
            if k > 0:                       # θ_k = ‖Δz_k‖ / ‖Δz_{k−1}‖
                theta = err / prev
                last = torch.where(theta < 1.0, theta / (1.0 - theta), math.inf)
            held.eta[rows] = last
            done = finite & (last * err <= 1.0)
        converged[rows[done]] = True
        go = finite & ~done
        stale = (err / prev >= theta_max)[go]
        rows, lu, piv, prev = rows[go], lu[go], piv[go], err[go]
        if held is not None:
            last = last[go]
    return z, converged, nfev


class HeldNewton:
    """What the steps of an integration share where the Newton matrices are formed from one given
    Jacobian per row (``Integrator.integrate``'s ``jacobian``): that Jacobian J (r, n, n), each
    row's contraction estimate η of its last iteration and the factorised Newton matrices of its
    last step (:func:`_simplified_newton`; the steps of an interval have one step size).  Indexing
    by a row mask or indices gives those rows'."""

    def __init__(self, J: Tensor, eta: Tensor | None = None,
                 factors: tuple[Tensor, Tensor] | None = None):
        self.J = J
        self.eta = torch.ones(J.shape[0], dtype=J.dtype, device=J.device) if eta is None else eta
        self.factors = factors

    def __getitem__(self, rows) -> "HeldNewton":
        return HeldNewton(self.J[rows], self.eta[rows],
                          None if self.factors is None else (self.factors[0][rows], self.factors[1][rows]))

    def keep(self, rows: Tensor, lu: Tensor, pivots: Tensor) -> None:
        """Keep the factorisation (``torch.linalg.lu_factor``'s) of the rows ``rows``' new matrices."""
        if self.factors is None:
            m = self.J.shape[0]
            self.factors = (lu.new_zeros(m, *lu.shape[1:]), pivots.new_ones(m, *pivots.shape[1:]))
        self.factors[0][rows], self.factors[1][rows] = lu, pivots


class _ImplicitFixedStep(FixedStepIntegrator):
    """Fixed-step implicit scheme.  The stage equations are solved by simplified Newton
    (:func:`_simplified_newton`: the Newton matrix from the rhs Jacobian at the start of the
    step, built once per step and refreshed only where the iteration stalls; the Jacobians by
    forward mode, :func:`shootlab.bvp.tangents.rhs_jacobian`).  Derivatives are not taken through
    the iteration but by the implicit function theorem at the converged stages: ``G(z, y) = 0``
    gives ``∂z/∂y = −G_z⁻¹ G_y`` with ``G_z`` the *exact* Newton matrix there — as forward
    sensitivities (``_step_sensitivity``), or, when ``y`` carries a graph or forward tangents
    (the reverse-sweep path), as one differentiable Newton correction
    ``z* − G_z⁻¹ G(z*, y)`` whose derivative in ``y`` is exactly that.

    ``rtol``/``atol`` (defaults 1e-10/1e-12) set the Newton stopping test
    ``rms(dz / (atol + rtol |y|)) <= 1``; at most ``newton_maxiter`` iterations; the Newton
    matrix is rebuilt where the contraction factor reaches ``newton_theta`` (0: full Newton).
    """

    kind = "implicit"
    sensitivities = True
    holds_jacobian = True

    def __init__(self, steps: int = 1, rtol: float | None = None, atol: float | None = None,
                 newton_maxiter: int = 20, newton_theta: float = 0.25):
        super().__init__(steps, rtol, atol)
        self.newton_maxiter, self.newton_theta = int(newton_maxiter), float(newton_theta)

    def _newton_scale(self, y: Tensor) -> Tensor:
        rtol = 1e-10 if self.rtol is None else self.rtol
        atol = 1e-12 if self.atol is None else self.atol
        return atol + rtol * y.detach().abs()

    def _solve(self, G, matrix, z0: Tensor, scale: Tensor, held: HeldNewton | None = None
               ) -> tuple[Tensor, Tensor, int]:
        return _simplified_newton(G, matrix, z0, scale, self.newton_maxiter, self.newton_theta, held)

    def _held_state(self, J: Tensor) -> HeldNewton:
        return HeldNewton(J)

    @staticmethod
    def _held(held: HeldNewton | None, fresh: Callable[[Tensor, Tensor], Tensor]) -> Callable[[Tensor, Tensor], Tensor]:
        """The Jacobian of a Newton matrix for the rows ``rows`` at their iterates z: the held
        Jacobian's rows (:class:`HeldNewton`) at a row's first matrix of the interval,
        ``fresh(rows, z)`` for a row whose iteration asks again (it contracted slowly), and without
        one."""
        if held is None:
            return fresh
        first = torch.full((held.J.shape[0],), held.factors is None, dtype=torch.bool, device=held.J.device)

        def jacobian(rows: Tensor, z: Tensor) -> Tensor:
            use = first[rows]
            first[rows] = False
            if bool(use.all()):
                return held.J[rows]
            out = held.J[rows].clone()
            out[~use] = fresh(rows[~use], z[~use])
            return out
        return jacobian


def _differentiable(y: Tensor) -> bool:
    return y.requires_grad or _is_dual(y)


def _lu_solve(M: Tensor, B: Tensor) -> Tensor:
    """``M⁻¹ B`` for batched matrices M (r, N, N) and B (r, N) or (r, N, k)."""
    lu, piv, _ = torch.linalg.lu_factor_ex(M)     # singular: non-finite values, reported as such
    return torch.linalg.lu_solve(lu, piv, B.unsqueeze(-1)).squeeze(-1) if B.dim() == 2 else \
        torch.linalg.lu_solve(lu, piv, B)



class _OneStageImplicit(_ImplicitFixedStep):
    """The one-stage θ-methods ``y+ = y + h f(t + θh, Y)``, ``Y = (1 − θ) y + θ y+``
    (θ = 1: backward Euler, θ = 1/2: implicit midpoint; :meth:`_point` gives Y).

    Simplified Newton on ``G(z) = z − y − h f(t + θh, Y(y, z))`` from ``z = y`` with
    ``M = I − θh J(t + θh, Y)``.  Sensitivity (implicit function theorem, J* at the converged
    Y): ``(I − θh J*) S+ = (I + (1 − θ)h J*) S``, i.e. ``S+ = (I − θh J*)⁻¹ S / θ − (1/θ − 1) S``.
    """

    theta: float

    def _point(self, y: Tensor, z: Tensor) -> Tensor:
        """The stage value Y at which f is evaluated."""
        raise NotImplementedError

    @classmethod
    def stability_matrix(cls, Z: Tensor) -> Tensor:
        """R(Z) = (I − θZ)⁻¹ (I + (1 − θ)Z)."""
        eye = torch.eye(Z.shape[-1], dtype=Z.dtype, device=Z.device)
        return torch.linalg.solve(eye - cls.theta * Z, eye + (1.0 - cls.theta) * Z)

    def _stages(self, rhs, t, y, h, held=None):
        n = y.shape[-1]
        tm, hc, yd = t + self.theta * h, h[:, None], y.detach()
        eye = torch.eye(n, dtype=y.dtype, device=y.device)
        jacobian = self._held(held, lambda rows, z: rhs_jacobian(rhs, tm[rows], self._point(yd[rows], z))[1])
        z, ok, nfev = self._solve(
            lambda rows, z: z - yd[rows] - hc[rows] * rhs(tm[rows], self._point(yd[rows], z)),
            lambda rows, z: eye - self.theta * hc[rows, :, None] * jacobian(rows, z),
            yd, self._newton_scale(y), held)
        return z, ok, nfev, tm, hc, eye

    def _step(self, rhs, t, y, h, held=None):
        z, ok, nfev, tm, hc, eye = self._stages(rhs, t, y, h, held)
        if not _differentiable(y):
            return z, ok, nfev
        M = eye - self.theta * hc[..., None] * rhs_jacobian(rhs, tm, self._point(y.detach(), z))[1]
        zc = _const(z, y)
        g = zc - y - _const(hc, y) * rhs(tm, self._point(y, zc))
        return zc - _lu_solve(M, g), ok, nfev + 2

    def _step_sensitivity(self, rhs, t, y, S, h):
        z, ok, nfev, tm, hc, eye = self._stages(rhs, t, y, h)
        _, J = rhs_jacobian(rhs, tm, self._point(y, z))
        if S is None:                                   # an interval's first step: S = I
            S = eye.expand_as(J)
        X = _lu_solve(eye - self.theta * hc[..., None] * J, S)
        return z, (X if self.theta == 1.0 else X / self.theta - (1.0 / self.theta - 1.0) * S), ok, nfev + 1
