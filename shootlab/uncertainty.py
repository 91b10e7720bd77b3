"""Standard errors and correlations of the estimated parameters (linearised covariance).

The estimate θ̂ is a function of the measured samples z (all channels, all sample times): the
converged shooting unknowns s* solve F(s*; z) = 0 (matching conditions of the TPBVP whose
right-hand side holds the data through the interpolating spline), and the reported parameter
is the time average of the parameter trajectories, θ̂ = L s* (trapezoid rule over the shooting
points, as in :func:`shootlab.estimation.estimate`).  Linearising at the optimum (implicit
function theorem; the delta method)::

    dθ̂ = G dz,        G = −L (∂F/∂s)⁻¹ ∂F/∂z                                     (1)

and, for white measurement noise of variance σ_c² on the samples of channel c (independent
between channels and samples)::

    Cov θ̂ = Σ_c σ̂_c² G_c G_cᵀ,     SE_j = √(Cov θ̂)_jj,     ρ_ij = Cov_ij / (SE_i SE_j)   (2)

This is the sandwich form H⁻¹ (Gᵀ Q Σ Q G) H⁻¹ of the covariance of a weighted least-squares
estimate, with H the curvature of the profile of J in θ (every state, input and costate
re-optimised) and Q the per-sample weights: since J = ½∫ξᵀVξ dt, a sample carries the weight
V·Δt (the integral, not the sum, over the samples).  When V·Δt is proportional to the inverse
noise variance on every channel, (2) reduces to the familiar σ̂² H⁻¹ with σ̂² = 2 J_ξ /(N − p)
in the units of V·Δt; (2) stays right when it is not — in particular for the equation rows
(zero pseudo-measurements, no noise), for a measured input shared between its own row and an
equation row (its residual ξ_c then holds only part of the noise), and for parameters allowed
to drift (θ' = ε_θ with finite W).

Cost: the Newton matrix ∂F/∂s at s* (one Jacobian evaluation, as one Newton iteration), a
transposed block solve (reverse mode through :meth:`BlockFactorization.solve`: Jᵀ y = Lᵀ), one
integration of the intervals recorded for autograd and p reverse sweeps to the spline
coefficients of the data (yᵀ ∂F/∂z), and the adjoint of the data spline (linear in the samples).

Noise variance per channel: σ̂_c = max(σ̂_c,res, σ̂_c,data) with
σ̂²_c,res = Σ_i ξ_c,i² / (N_c − p N_c / N) (the measurement residuals of the channel, with the
parameters' share of the degrees of freedom) and σ̂_c,data the model-free estimate from the
4th differences of the samples (:func:`shootlab.noise.noise_level`).  The residual estimate
is low when the fit shares a channel's noise with an equation row (a measured input), the
data estimate misses a misfit; the larger of the two is the honest one.  The covariance is
first order in the noise and assumes white noise: coloured residuals (a structural error)
make it optimistic.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from torch import Tensor

from .estimation import EstimationProblem


@dataclass
class Uncertainty:
    """Linearised covariance of θ̂ (module docstring, eq. 2) and the noise levels used."""

    parameters: list[str]
    covariance: np.ndarray                  # (p, p)
    noise: dict[str, float]                 # σ̂_c per measured channel, as used
    noise_residual: dict[str, float]        # σ̂_c,res from the residuals ξ_c
    noise_data: dict[str, float]            # σ̂_c,data from the 4th differences of the samples
    sensitivity: dict[str, np.ndarray]      # G_c (p, N_c): dθ̂ / d z_c,i per sample
    seconds: float = 0.0

    #: σ̂_c,res above this multiple of σ̂_c,data flags a misfit (coloured residuals)
    MISFIT_RATIO = 2.0

    @property
    def warnings(self) -> list[str]:
        """One line per channel whose residuals are well above the noise of its samples: a misfit
        (structural error), which the white-noise covariance does not describe."""
        out = []
        for c, res in self.noise_residual.items():
            data = self.noise_data.get(c, 0.0)
            if data > 0 and res > self.MISFIT_RATIO * data:
                out.append(f"channel {c}: residual σ {res:.3g} is {res / data:.1f}x the noise of the samples "
                           f"({data:.3g}): a misfit, not noise; the standard errors (white noise) are optimistic")
        return out

    @property
    def standard_errors(self) -> dict[str, float]:
        se = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return {p: float(v) for p, v in zip(self.parameters, se)}

    @property
    def correlation(self) -> np.ndarray:
        se = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.covariance / np.outer(se, se)


def spline_adjoint(t: np.ndarray, values: np.ndarray, grad: np.ndarray, reach: int = 60,
                   block: int = 8192) -> np.ndarray:
    """Mᵀ g for the linear map M: samples → Taylor coefficients of :class:`shootlab.data.Interpolant`
    (a cubic spline through the valid samples; ``values`` only give the NaN pattern).

    grad (q, K−1, 4): gradients with respect to the coefficients c_d (value, slope, curvature/2,
    third derivative/6 at the left end of each sample interval) of q quantities; returns (q, K)
    gradients with respect to the samples (zero at missing samples).

    The spline of a unit sample decays at least like 2⁻ʲ j knots away (the spline's tridiagonal
    system is diagonally dominant; 0.27ʲ on a uniform grid), so unit samples 2·reach + 1 apart
    do not see each other (2⁻⁶⁰ ≈ 1e−18): one spline per residue class ("comb") gives every
    column of M, each read within ``reach`` intervals of its sample.  O(K·reach) work."""
    ok = ~np.isnan(values)
    K, q = t.size, grad.shape[0]
    out = np.zeros((q, K))
    idx = np.flatnonzero(ok)
    nok = idx.size
    if nok < 2:
        return out
    period = min(2 * reach + 1, nok)
    unit = np.zeros((nok, period))
    unit[np.arange(nok), np.arange(nok) % period] = 1.0
    sp = CubicSpline(t[ok], unit, bc_type="not-a-knot" if nok > 3 else "natural")
    comb = np.arange(period)
    g_out = np.zeros((q, nok))
    for k0 in range(0, K - 1, block):
        k = np.arange(k0, min(k0 + block, K - 1))
        coef = np.stack([sp(t[k], d) / math.factorial(d) for d in range(4)], -1)     # (k, period, 4)
        contrib = np.einsum("qkd,kpd->qkp", grad[:, k], coef)
        # owner of (interval, comb): the comb's sample nearest the interval's left sample
        j0 = np.clip(np.searchsorted(idx, k, side="right") - 1, 0, nok - 1)[:, None]
        below = j0 - (j0 - comb[None, :]) % period
        above = below + period
        own = np.where((above < nok) & (above - j0 < j0 - below) | (below < 0), above, below)
        for r in range(q):
            g_out[r] += np.bincount(own.ravel(), weights=contrib[r].ravel(), minlength=nok)[:nok]
    out[:, idx] = g_out
    return out


def _pullback(out: Tensor, leaf: Tensor, cotangents: Tensor) -> Tensor:
    """(q, *leaf.shape): the vector–Jacobian products of ``out`` with each of the q cotangents,
    in one batched reverse sweep (vmap; one sweep each where vmap has no rule)."""
    zero = torch.zeros_like(leaf)
    if not out.requires_grad:                 # the data do not reach the matching conditions
        return zero.expand(cotangents.shape[0], *leaf.shape)
    try:
        g, = torch.autograd.grad(out, leaf, grad_outputs=cotangents, is_grads_batched=True,
                                 retain_graph=True, allow_unused=True)
        return zero.expand(cotangents.shape[0], *leaf.shape) if g is None else g
    except RuntimeError:
        rows = [torch.autograd.grad(out, leaf, grad_outputs=c, retain_graph=True, allow_unused=True)[0]
                for c in cotangents]
        return torch.stack([zero if r is None else r for r in rows])


def parameter_covariance(res) -> Uncertainty:
    """Linearised covariance of the parameters of an :class:`~shootlab.estimation.EstimationResult`
    (module docstring, eqs. 1–2).  Raises ``RuntimeError`` / ``SingularJacobianError`` when the
    Newton matrix at the solution cannot be formed."""
    import time

    from .noise import noise_level

    clock = time.perf_counter()
    prob, sh = res.problem, res.shooting
    model, system = prob.model, sh._system
    # every shooting point the solver used (``solve(refine=True)`` may have added some to t)
    s = (sh.x if sh._x_all is None else sh._x_all).detach()
    m, n = s.shape
    npar = len(model.parameters)
    # L: θ̂_j = trapezoid mean of the parameter j over the shooting points
    tk = system.t
    w = torch.zeros(m, dtype=s.dtype)
    h = tk[1:] - tk[:-1]
    w[:-1] += 0.5 * h
    w[1:] += 0.5 * h
    w = w / (tk[-1] - tk[0])
    cot = s.new_zeros(npar, m, n)
    for j in range(npar):
        cot[j, :, len(model.states) + j] = w
    # y_j = J⁻ᵀ L_jᵀ: reverse mode through the (linear) block solve
    fac = system.linearize(s)
    with torch.enable_grad():
        r_a = s.new_zeros(fac.p, requires_grad=True)
        r_match = s.new_zeros(m - 1, n, requires_grad=True)
        r_b = s.new_zeros(n - fac.p, requires_grad=True)
        delta = fac.solve(r_a, r_match, r_b)
        y = _pullback(delta, r_match, cot)                                                # (p, m−1, n)
    # yᵀ ∂F/∂z: F_match = y_k(t_{k+1}) − s_{k+1}; the data enter through the spline coefficients,
    # made a leaf of a fresh copy of the problem (nothing the solver kept about the data is reused)
    fresh = EstimationProblem(model, prob.data, dtype=prob.A.dtype, device=prob.A.device)
    interp = fresh.interp
    probe = copy.copy(system)
    probe.prob = fresh.bvp()
    with torch.enable_grad():
        leaf = interp.coef.detach().clone().requires_grad_(True)
        interp.coef = leaf
        ends = probe._integrate(s[:-1])
        gcoef = _pullback(ends, leaf, y)
    gcoef = torch.nan_to_num(gcoef).numpy()                                              # (p, K−1, cols, 4)
    data = prob.data
    t = np.asarray(data.t, dtype=np.float64)
    G: dict[str, np.ndarray] = {}
    for col, name in enumerate(interp.names):      # −: dθ̂ = −yᵀ ∂F/∂z dz; a channel in two rows adds up
        G[name] = G.get(name, 0.0) - spline_adjoint(t, np.asarray(data.channels[name], dtype=float),
                                                    gcoef[:, :, col, :])
    # noise level per channel: residuals with degrees of freedom, and the data alone
    inside = (t >= float(tk[0])) & (t <= float(tk[-1]))
    n_total = sum(int(np.sum(~np.isnan(np.asarray(data.channels[c])[inside]))) for c in G)
    sig_res, sig_data = {}, noise_level(data, list(G))
    for row, name in model.channels.items():
        xi = res.xi[row].detach().numpy()
        z = np.asarray(data.channels[name], dtype=float)[inside]
        xi = xi[~np.isnan(z)]
        dof = max(xi.size - npar * xi.size / max(n_total, 1), 1.0)
        sig_res[name] = max(sig_res.get(name, 0.0), float(np.sqrt(np.sum(xi ** 2) / dof)))
    sigma = {c: max(sig_res.get(c, 0.0), sig_data.get(c, 0.0)) for c in G}
    cov = np.zeros((npar, npar))
    for c, g in G.items():
        cov += sigma[c] ** 2 * (g @ g.T)
    return Uncertainty(list(model.parameters), cov, sigma, sig_res, dict(sig_data), G,
                       seconds=time.perf_counter() - clock)


def format_estimate(value: float, se: float | None, unit: str = "") -> str:
    """'1.0012 ± 0.0031 kg': the value to the standard error's second significant digit."""
    unit = f" {unit}" if unit else ""
    if se is None or not math.isfinite(se) or se <= 0 or not math.isfinite(value):
        return f"{value:.6g}{unit}"
    digits = max(0, 1 - int(math.floor(math.log10(se))))
    return f"{value:.{digits}f} ± {se:.{digits}f}{unit}"
