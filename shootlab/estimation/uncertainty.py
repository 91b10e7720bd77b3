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
coefficients of the data (yᵀ ∂F/∂z), and the adjoint of the data spline
(:func:`spline_adjoint`: one banded solve per parameter).  Work and memory are linear in the
samples: the only per-sample arrays are the p gradients G_c and the coefficients' gradients.

Noise variance per channel: σ̂_c = max(σ̂_c,res, σ̂_c,data) with
σ̂²_c,res = Σ_i ξ_c,i² / (N_c − p N_c / N) (the measurement residuals of the channel, with the
parameters' share of the degrees of freedom) and σ̂_c,data the model-free estimate from the
4th differences of the samples (:func:`shootlab.estimation.data.noise_level`).  The residual estimate
is low when the fit shares a channel's noise with an equation row (a measured input), the
data estimate misses a misfit; the larger of the two is the honest one.  The covariance is
first order in the noise and assumes white noise: coloured residuals (a structural error)
make it optimistic.  A channel is flagged as a misfit (:attr:`Uncertainty.warnings`) when its
residual σ̂_c,res exceeds :data:`Uncertainty.MISFIT_RATIO` times the larger of σ̂_c,data and
:data:`Uncertainty.FIT_FLOOR` times the spread of its samples: on a noise-free record σ̂_c,data
is only its floor of 1e-6 of the spread, and a fit exact to the accuracy of the integrator and
of the spline through the samples leaves residuals of about 1e-5 of it (the confined
compression's noise-free record: 1.4e-5 to 6.4e-5), which are not a misfit.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from torch import Tensor

from .optimality import EstimationProblem


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
    spread: dict[str, float] = field(default_factory=dict)    # standard deviation of the channel's samples

    #: σ̂_c,res above this multiple of σ̂_c,data flags a misfit (coloured residuals)
    MISFIT_RATIO = 2.0
    #: ... and above this fraction of the spread of the channel's samples (module docstring)
    FIT_FLOOR = 1e-4

    @property
    def warnings(self) -> list[str]:
        """One line per channel whose residuals are well above the noise of its samples — and
        above the accuracy of the fit, :data:`FIT_FLOOR` of the samples' spread: a misfit
        (structural error), which the white-noise covariance does not describe."""
        out = []
        for c, res in self.noise_residual.items():
            data = self.noise_data.get(c, 0.0)
            floor = self.FIT_FLOOR * self.spread.get(c, 0.0)
            if data > 0 and res > self.MISFIT_RATIO * max(data, floor):
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


def spline_adjoint(t: np.ndarray, values: np.ndarray, grad: np.ndarray) -> np.ndarray:
    """Mᵀ g for the linear map M: samples → Taylor coefficients of :class:`shootlab.estimation.data.Interpolant`
    (a cubic spline through the valid samples; ``values`` only give the NaN pattern).

    grad (q, K−1, 4): gradients with respect to the coefficients c_d (value, slope, curvature/2,
    third derivative/6 at the left end of each sample interval) of q quantities; returns (q, K)
    gradients with respect to the samples (zero at missing samples).

    M is a chain of linear maps, each transposed here in O(K) work and memory (no matrix of M
    is formed).  With x_j, y_j the n valid samples, h_j = x_{j+1} − x_j and the divided
    differences m_j = (y_{j+1} − y_j)/h_j, the spline's slopes s solve the tridiagonal
    not-a-knot system A s = B m (scipy's ``CubicSpline``); its piece j has the coefficients

        c0 = y_j,  c1 = s_j,  c2 = (m_j − s_j)/h_j − τ_j,  c3 = τ_j/h_j,   τ_j = (s_j + s_{j+1} − 2 m_j)/h_j

    and sample interval k takes the piece j(k) that holds its left end t_k (as ``PPoly`` finds
    it), re-expanded about t_k:  c'(δ) = T(δ) c with δ = t_k − x_j.  The adjoint runs the chain
    backwards: Tᵀ per sample interval, summed per piece; the coefficients' transpose; one banded
    solve with Aᵀ for the slopes (``scipy.linalg.solve_banded``); Bᵀ and the differences'
    transpose.  Fewer than 4 valid samples (a natural spline, or a constant): from the spline
    of each unit sample."""
    from scipy.linalg import solve_banded

    ok = ~np.isnan(values)
    K, q = t.size, grad.shape[0]
    out = np.zeros((q, K))
    idx = np.flatnonzero(ok)
    n = idx.size
    if n == 0:
        return out
    if n <= 3:                                       # Interpolant's natural spline or constant
        if n == 1:
            out[:, idx[0]] = grad[:, :, 0].sum(1)
            return out
        sp = CubicSpline(t[idx], np.eye(n), bc_type="natural")
        M = np.stack([sp(t[:-1], d) / math.factorial(d) for d in range(4)], -1)      # (K−1, n, 4)
        out[:, idx] = np.einsum("qkd,knd->qn", grad, M)
        return out
    x = t[idx]
    h = np.diff(x)
    # Tᵀ: the sample intervals' coefficient gradients moved to the left ends of their pieces
    piece = np.clip(np.searchsorted(x, t[:-1], side="right") - 1, 0, n - 2)
    d = (t[:-1] - x[piece])[None, :]
    g0, g1, g2, g3 = (grad[..., i] for i in range(4))
    moved = (g0, g0 * d + g1, (g0 * d + 2 * g1) * d + g2, ((g0 * d + 3 * g1) * d + 3 * g2) * d + g3)
    gc = np.zeros((4, q, n - 1))
    for i, g in enumerate(moved):
        for r in range(q):
            gc[i, r] = np.bincount(piece, weights=g[r], minlength=n - 1)
    # the coefficients' transpose: to y, s and m
    g_tau = -gc[2] + gc[3] / h
    g_y = np.zeros((q, n))
    g_s = np.zeros((q, n))
    g_m = gc[2] / h - 2 * g_tau / h
    g_y[:, :-1] += gc[0]
    g_s[:, :-1] += gc[1] - gc[2] / h + g_tau / h
    g_s[:, 1:] += g_tau / h
    # s = A⁻¹ B m: the band of A (scipy's layout, not-a-knot ends) and the solve with Aᵀ
    ab = np.zeros((3, n))
    ab[1, 1:-1] = 2 * (h[:-1] + h[1:])
    ab[0, 2:] = h[:-1]
    ab[2, :-2] = h[1:]
    d0, d1 = x[2] - x[0], x[-1] - x[-3]
    ab[1, 0], ab[0, 1] = h[1], d0
    ab[1, -1], ab[2, -2] = h[-2], d1
    abT = np.zeros_like(ab)
    abT[0, 1:], abT[1], abT[2, :-1] = ab[2, :-1], ab[1], ab[0, 1:]
    g_b = solve_banded((1, 1), abT, g_s.T, check_finite=False).T                     # (q, n)
    # Bᵀ: b_0 and b_{n−1} from the not-a-knot ends, b_i = 3 (h_i m_{i−1} + h_{i−1} m_i) inside
    g_m[:, :-1] += 3 * h[1:] * g_b[:, 1:-1]
    g_m[:, 1:] += 3 * h[:-1] * g_b[:, 1:-1]
    g_m[:, 0] += (h[0] + 2 * d0) * h[1] / d0 * g_b[:, 0]
    g_m[:, 1] += h[0] ** 2 / d0 * g_b[:, 0]
    g_m[:, -2] += h[-1] ** 2 / d1 * g_b[:, -1]
    g_m[:, -1] += (2 * d1 + h[-1]) * h[-2] / d1 * g_b[:, -1]
    # m_j = (y_{j+1} − y_j)/h_j
    g_y[:, :-1] -= g_m / h
    g_y[:, 1:] += g_m / h
    out[:, idx] = g_y
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

    from .data import noise_level

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
    spread = {c: float(np.nanstd(np.asarray(data.channels[c], dtype=float)[inside])) for c in G}
    return Uncertainty(list(model.parameters), cov, sigma, sig_res, dict(sig_data), G,
                       seconds=time.perf_counter() - clock, spread=spread)


def format_estimate(value: float, se: float | None, unit: str = "") -> str:
    """'1.0012 ± 0.0031 kg': the value to the standard error's second significant digit."""
    unit = f" {unit}" if unit else ""
    if se is None or not math.isfinite(se) or se <= 0 or not math.isfinite(value):
        return f"{value:.6g}{unit}"
    digits = max(0, 1 - int(math.floor(math.log10(se))))
    return f"{value:.{digits}f} ± {se:.{digits}f}{unit}"
