"""How far along a Newton direction: the step-length rules of the strategies in
:mod:`shootlab.bvp.newton`, each a choice of λ in s + λδ.

* :func:`armijo_search` — the line search of the report §3.3 (Press et al., *Numerical Recipes*
  2nd ed. §9.7, ``lnsrch``) on f = ½ FᵀF along the Newton direction δ = −J⁻¹F, whose slope is
  ∇f·δ = −FᵀF: λ = 1 first, accepted by the Armijo test (eq. 3.17)::

      f(s + λδ) ≤ f(s) + α λ ∇f·δ,    α = 1e−4

  otherwise the minimiser of the quadratic model of f(s + λδ) (eq. 3.19), later of the cubic
  through the last two trials (eqs. 3.20–3.21), kept within [0.1 λ, 0.5 λ], down to a floor
  λ_min; a trial point that cannot be integrated (overflow) shortens λ by 10.  ``armijo``.
* :func:`step_to_boundary` — the fraction-to-the-boundary rule of interior-point methods (IPOPT's
  τ = :data:`TO_BOUNDARY`): the largest λ ≤ 1 that keeps s + λδ inside the problem's bounds
  (``BVP.lower``, ``upper``) by a margin.  ``deuflhard``.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from .shooting import IntegrationFailure, ShootingSystem

__all__ = ["armijo_search", "step_to_boundary", "TO_BOUNDARY"]


def armijo_search(system: ShootingSystem, s: Tensor, F: Tensor, delta: Tensor, alpha: float = 1e-4,
                  min_step: float = 1e-8, full_only: bool = False):
    """Backtracking along the Newton direction delta until the Armijo test on f = ½FᵀF holds
    (report eqs. 3.17–3.21, NR lnsrch; module docstring): the accepted (s, F, f, λ, the last
    integration failure or None), or None when λ falls below ``min_step`` (with ``full_only``:
    when the full step fails)."""
    f = 0.5 * float(F @ F)
    slope = -2.0 * f                        # ∇f·δ = Fᵀ J δ = −FᵀF for δ = −J⁻¹F
    lam, lam2, f2, failure = 1.0, None, None, None
    floor = 1.0 if full_only else min_step
    while lam >= floor:
        s_new = s + lam * delta
        try:
            F_new = system.residual(s_new).F
        except IntegrationFailure as exc:      # overflow at the trial point: shorten the step
            lam, lam2, f2, failure = 0.1 * lam, None, None, exc
            continue
        f_new = 0.5 * float(F_new @ F_new)
        if math.isfinite(f_new) and f_new <= f + alpha * lam * slope:      # eq. 3.17
            return s_new, F_new, f_new, lam, failure
        if not math.isfinite(f_new):
            lam, lam2, f2 = 0.1 * lam, None, None
            continue
        if lam2 is None:     # quadratic model, eq. 3.19 (written for any λ: after an overflow λ < 1)
            tmp = -slope * lam ** 2 / (2.0 * (f_new - f - slope * lam))
        else:                                                  # cubic model, eqs. 3.20–3.21
            r1 = f_new - f - lam * slope
            r2 = f2 - f - lam2 * slope
            a = (r1 / lam ** 2 - r2 / lam2 ** 2) / (lam - lam2)
            b = (-lam2 * r1 / lam ** 2 + lam * r2 / lam2 ** 2) / (lam - lam2)
            if a == 0.0:
                tmp = -slope / (2.0 * b)
            else:
                disc = b * b - 3.0 * a * slope
                if disc < 0.0:
                    tmp = 0.5 * lam
                elif b <= 0.0:
                    tmp = (-b + math.sqrt(disc)) / (3.0 * a)
                else:
                    tmp = -slope / (b + math.sqrt(disc))
        tmp = min(tmp, 0.5 * lam)                              # never back up: λ falls monotonically
        lam2, f2 = lam, f_new
        lam = max(tmp, 0.1 * lam)
    return None


#: fraction of the distance to a bound that one step may cover (IPOPT's τ)
TO_BOUNDARY = 0.99


def step_to_boundary(prob, s: Tensor, dx: Tensor) -> float:
    """The largest λ ≤ 1 with s + λΔx at most ``TO_BOUNDARY`` of the way to the problem's bounds
    (``BVP.lower``/``upper``): the fraction-to-the-boundary rule of interior-point methods."""
    lam = 1.0
    for bound, sign in ((getattr(prob, "lower", None), -1.0), (getattr(prob, "upper", None), 1.0)):
        if bound is None:
            continue
        gap = sign * (torch.as_tensor(bound, dtype=s.dtype, device=s.device) - s)     # > 0 inside
        toward = sign * dx > 0
        if toward.any():
            lam = min(lam, float((TO_BOUNDARY * gap[toward] / (sign * dx[toward])).min()))
    return lam
