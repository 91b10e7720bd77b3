"""Trust-region globalisation of the shooting Newton: Powell's dogleg on the equilibrated least
squares (``newton="trust_region"``, :class:`TrustRegionNewton`).

The merit function is the weighted sum of squares of the shooting residual F(s) (report §3.2)

    f(s) = ½ ‖D F(s)‖²,

D = diag(D_a, D_1 … D_{m−1}, D_b) the row equilibration of the structured factorisation
(:func:`shootlab.bvp.linalg.factorize`): each matching row of [Y_k, −I] and each boundary row of
B_a, B_b divided by its largest entry.  f therefore does not depend on the units in which the
equations are written (a row multiplied by c has its D divided by c), as the default Newton's
tests do not.  At an iterate s_k with the Jacobian J (the block-bidiagonal matrix of eq. 3.11a:
B_a, then Y_k and −I, then B_b) the model of f is the Gauss–Newton quadratic

    q(δ) = ½ ‖D (F + J δ)‖²,      ∇q(0) = g = Jᵀ D² F,

trusted in the ball ‖S δ‖₂ ≤ Δ, S = diag(column norms of D J) kept non-decreasing over the
iterations (Moré, "The Levenberg–Marquardt algorithm", 1978; MINPACK's ``diag``, mode 1): a
column that stays small (an unknown the equations barely see) is allowed a long step.

The step is Powell's dogleg (Nocedal & Wright, *Numerical Optimization*, 2nd ed., §4.1, in the
variables z = S δ):

    δ_N = −J⁻¹ F                           the Newton step (the structured solve; q(δ_N) = 0)
    δ_g = −S⁻² g,  t* = ‖S⁻¹g‖² / ‖D J δ_g‖²,  δ_C = t* δ_g     the Cauchy point (minimiser of q
                                                                  along the scaled steepest descent)
    δ(Δ) = δ_N                              if ‖S δ_N‖ ≤ Δ
         = (Δ / ‖S δ_g‖) δ_g                if ‖S δ_C‖ ≥ Δ
         = δ_C + β (δ_N − δ_C)              otherwise, β ∈ [0, 1] with ‖S δ(Δ)‖ = Δ,

shortened to stay inside the problem's bounds (:func:`shootlab.bvp.step_length.step_to_boundary`).
Where the Newton matrix is singular (a fold of the problem, a parameter at a degenerate value)
the Cauchy step alone is taken: the iteration goes on where the other strategies stop.  Products
J δ and Jᵀ v are formed from the blocks (:class:`ShootingJacobian`, O(m n²), no dense matrix).

Acceptance and radius (N&W Algorithm 4.1 with the rules of MINPACK's ``hybrd``, Moré, Garbow and
Hillstrom 1980): with the same D in both,

    ρ = (f(s) − f(s + δ)) / (q(0) − q(δ)),

the step is taken when ρ > η (1e−4); Δ ← ½ min(Δ, ‖S δ‖) when ρ < 0.1 (or the trial point cannot
be integrated), else Δ ← max(Δ, 2 ‖S δ‖) when ρ ≥ ½ or after two successes in a row, and
Δ ← 2 ‖S δ‖ when |ρ − 1| ≤ 0.1.  The first radius is the Newton step's length, so near a regular
root the iteration is Newton's, quadratically convergent.  D is taken afresh at every Jacobian:
kept from the first (a fixed merit function), the rows of Troesch's problem that grow with the
solution stay weighted as at the flat start, and from y = 0 at μ = 12–20 the iteration does not
converge where the fresh D does.

Giving up: Δ below ``min_radius``·‖S s‖ (status STEP_TOO_SMALL), or ``slow`` successive
accepted steps each lowering ‖D F‖ by less than 0.1 % (MINPACK ``hybrd``'s "not making good
progress": a local minimum of f that is not a root), or the gradient g = 0 at a singular matrix
(SINGULAR).  One Jacobian per accepted step; a rejected trial costs one residual.

The strategy enters :data:`shootlab.bvp.newton.NEWTON` when this module is imported (``import
shootlab`` does).  :func:`shootlab.estimation.estimate` falls back to it where the default Newton
and ``armijo`` stall.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .linalg import SingularJacobianError, _row_scale, factorize
from .newton import CONVERGED, NEWTON, NewtonStrategy
from .shooting import IntegrationFailure
from .step_length import step_to_boundary

__all__ = ["ShootingJacobian", "TrustRegionNewton"]


@dataclass
class ShootingJacobian:
    """The multiple-shooting Jacobian (report eq. 3.11a) as its blocks: rows [B_a; matching;
    B_b], the matching block row k holding Y_k at unknown k and −I at unknown k + 1.

    Y (m−1, n, n), B_a (p, n), B_b (n−p, n).  Unknowns δ have shape (m, n); residual-sized
    vectors are flat (p + (m−1) n + n − p,), in the order of ``ShootingSystem.residual``'s F."""

    Y: Tensor
    B_a: Tensor
    B_b: Tensor

    @classmethod
    def at(cls, system, s: Tensor) -> "ShootingJacobian":
        """The blocks of ``system`` (a :class:`~shootlab.bvp.shooting.ShootingSystem`) at s."""
        B_a, B_b = system.bc_jacobians(s)
        return cls(system.interval_jacobians(s).detach(), B_a.detach(), B_b.detach())

    def _split(self, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        p, (L, n, _) = self.B_a.shape[0], self.Y.shape
        return v[:p], v[p:p + L * n].reshape(L, n), v[p + L * n:]

    def matvec(self, d: Tensor) -> Tensor:
        """J δ for δ (m, n): [B_a δ_1; Y_k δ_k − δ_{k+1}; B_b δ_m]."""
        match = (self.Y @ d[:-1].unsqueeze(-1)).squeeze(-1) - d[1:]
        return torch.cat([self.B_a @ d[0], match.reshape(-1), self.B_b @ d[-1]])

    def rmatvec(self, v: Tensor) -> Tensor:
        """Jᵀ v, shape (m, n): unknown k collects Y_kᵀ v_k − v_{k−1}, the first B_aᵀ v_a, the last
        B_bᵀ v_b."""
        v_a, v_match, v_b = self._split(v)
        out = torch.zeros(v_match.shape[0] + 1, v_match.shape[1], dtype=v.dtype, device=v.device)
        out[:-1] += (self.Y.transpose(-1, -2) @ v_match.unsqueeze(-1)).squeeze(-1)
        out[1:] -= v_match
        out[0] += self.B_a.T @ v_a
        out[-1] += self.B_b.T @ v_b
        return out

    def row_scale(self) -> Tensor:
        """D (flat): 1 / the largest entry of each row, the equilibration of
        :func:`~shootlab.bvp.linalg.factorize` (a matching row's −I counts: its D is at most 1); 1 for
        a boundary row that is zero at this point."""
        def boundary(B: Tensor) -> Tensor:
            return torch.where(B.abs().amax(-1) > 0, _row_scale(B), torch.ones(B.shape[0], dtype=B.dtype))
        return torch.cat([boundary(self.B_a), _row_scale(self.Y, floor=1.0).reshape(-1), boundary(self.B_b)])

    def column_norms(self, D: Tensor) -> Tensor:
        """‖column‖₂ of D J for every unknown, shape (m, n)."""
        D_a, D_match, D_b = self._split(D)
        sq = torch.zeros(D_match.shape[0] + 1, D_match.shape[1], dtype=D.dtype, device=D.device)
        sq[:-1] += (D_match.unsqueeze(-1) * self.Y).square().sum(-2)        # Y_k's column j, its rows scaled
        sq[1:] += D_match.square()                                          # the −I of the row before
        sq[0] += (D_a.unsqueeze(-1) * self.B_a).square().sum(0)
        sq[-1] += (D_b.unsqueeze(-1) * self.B_b).square().sum(0)
        return sq.sqrt()


class _Dogleg:
    """The dogleg path at one iterate (module docstring): its step for any radius."""

    def __init__(self, jac: ShootingJacobian, D: Tensor, S: Tensor, F: Tensor, newton: Tensor | None):
        self.jac, self.D, self.S, self.DF = jac, D, S, D * F
        self.f = 0.5 * float(self.DF @ self.DF)
        grad = jac.rmatvec(D * self.DF)                     # g = Jᵀ D² F
        self.gnorm = float((grad / S).norm())               # ‖S⁻¹ g‖
        self.descent = -grad / S.square()                   # δ_g, with ‖S δ_g‖ = ‖S⁻¹ g‖
        curvature = float((D * jac.matvec(self.descent)).square().sum())
        self.cauchy_t = self.gnorm ** 2 / curvature if curvature > 0 else math.inf
        self.newton = newton
        self.newton_norm = float((S * newton).norm()) if newton is not None else math.nan

    def step(self, radius: float) -> Tensor:
        """δ(Δ) on the dogleg path."""
        if self.newton is not None and self.newton_norm <= radius:
            return self.newton
        cauchy_len = self.cauchy_t * self.gnorm
        if self.newton is None or cauchy_len >= radius:
            return min(self.cauchy_t, radius / self.gnorm) * self.descent
        dc = self.cauchy_t * self.descent
        zc, zd = self.S * dc, self.S * (self.newton - dc)
        a, b, c = float(zd.square().sum()), float((zc * zd).sum()), float(zc.square().sum()) - radius ** 2
        root = math.sqrt(max(b * b - a * c, 0.0))
        beta = (-b + root) / a if b <= 0 else -c / (b + root)       # the root in [0, 1], stably
        return dc + min(max(beta, 0.0), 1.0) * (self.newton - dc)

    def predicted(self, step: Tensor) -> float:
        """q(0) − q(δ), the reduction of f the linear model predicts."""
        r = self.DF + self.D * self.jac.matvec(step)
        return self.f - 0.5 * float(r @ r)


class TrustRegionNewton(NewtonStrategy):
    """Powell's dogleg trust region on ½‖D F‖² (module docstring).

    eta         least ratio ρ of actual to predicted reduction at which a step is taken (1e−4)
    min_radius  give up when the radius falls below this times ‖S s‖ (1e−12)
    slow        give up after this many successive steps that each lower ‖D F‖ by less than 0.1 %
                (10, MINPACK's ``hybrd``); None: never
    """

    name = "trust_region"

    def __init__(self, eta: float = 1e-4, min_radius: float = 1e-12, slow: int | None = 10, **kw):
        super().__init__(**kw)
        if not 0.0 <= eta < 0.25:
            raise ValueError(f"eta must lie in [0, 0.25), got {eta}")
        if not 0.0 < min_radius < 1.0:
            raise ValueError(f"min_radius must lie in (0, 1), got {min_radius}")
        if slow is not None and int(slow) < 1:
            raise ValueError(f"slow must be a positive number of iterations or None, got {slow}")
        self.eta, self.min_radius = eta, min_radius
        self.slow = None if slow is None else int(slow)

    def _iterate(self, system, s, out):
        F = self._first_residual(system, s)[0]
        self._record(out, float(F.abs().max()), 0.0, True)
        prob = getattr(system, "prob", None)
        radius, S, slow, successes = None, None, 0, 0
        while not self.converged(F, s):
            if out.iterations >= self.max_iter:
                return self._out_of_iterations(out, s)
            out.iterations += 1
            jac = ShootingJacobian.at(system, s)
            out.jacobian_evaluations += 1
            D = jac.row_scale()
            cols = jac.column_norms(D)
            cols = torch.where(cols > 0, cols, torch.ones_like(cols))
            S = cols if S is None else torch.maximum(S, cols)
            newton, singular = None, None
            try:
                newton = system.newton_step(factorize(jac.Y, jac.B_a, jac.B_b), F)
                if not bool(torch.isfinite(newton).all()):
                    newton = None
            except SingularJacobianError as exc:
                singular = exc
            path = _Dogleg(jac, D, S, F, newton)
            if newton is None and not path.gnorm > 0:
                raise singular or SingularJacobianError("singular Newton matrix and a zero gradient of |DF|^2")
            if radius is None:
                radius = path.newton_norm if newton is not None else path.cauchy_t * path.gnorm
            floor = self.min_radius * max(float((S * s).norm()), 1.0)
            while True:
                step = path.step(radius)
                step = step * step_to_boundary(prob, s, step)
                length = float((S * step).norm())
                predicted = path.predicted(step)
                try:
                    F_new = system.residual(s + step).F
                    DF_new = D * F_new
                    actual = path.f - 0.5 * float(DF_new @ DF_new)
                except IntegrationFailure:
                    F_new, actual = None, -math.inf
                ratio = actual / predicted if predicted > 0 and math.isfinite(actual) else -math.inf
                if ratio < 0.1:                   # MINPACK hybrd's radius update
                    radius, successes = 0.5 * min(radius, length), 0
                else:
                    successes += 1
                    if ratio >= 0.5 or successes > 1:
                        radius = max(radius, 2.0 * length)
                    if abs(ratio - 1.0) <= 0.1:
                        radius = 2.0 * length
                if ratio > self.eta:
                    break
                if radius < floor:
                    return self._stalled(out, s, f"trust radius below {self.min_radius:g} |Ss|",
                                         "no step along the dogleg lowers |DF|^2 as its linear model predicts")
            slow = slow + 1 if actual < 2e-3 * path.f else 0     # ‖DF‖ lowered by < 0.1 %
            s, F = s + step, F_new
            out.s = s
            self._record(out, float(F.abs().max()), length / path.newton_norm if newton is not None else math.nan,
                         True)
            if self.slow is not None and slow >= self.slow and not self.converged(F, s):
                return self._stalled(out, s, f"|DF| lowered by less than 0.1 % in {self.slow} iterations",
                                     "the iteration is stuck near a local minimum of |DF|^2 that is not a root")
        out.s, out.status = s, CONVERGED
        out.message = f"converged: |F|_inf = {out.residual_norm:.3e} after {out.iterations} iterations"


NEWTON[TrustRegionNewton.name] = TrustRegionNewton       # newton="trust_region" (shootlab imports this module)
