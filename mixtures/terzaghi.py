"""Terzaghi's one-dimensional consolidation: the analytic reference for the linear mixture model.

Set-up of :mod:`mixtures.confined`: a layer ``0 ≤ z ≤ L`` on an impermeable bottom (``z = 0``),
drained at the top (``z = L``, ``p = 0``), linear solid with aggregate modulus ``H``, constant
permeability ``K``, intrinsically incompressible constituents, compressive load ``P(t)`` on top.

Derivation (standard; e.g. Terzaghi 1923, Mow et al. 1980 for the biphasic form).  Momentum:
``H ∂s/∂z − p = −P(t)``.  Mass + Darcy with the impermeable bottom: ``∂s/∂t = K ∂p/∂z``.
Eliminating ``s``::

    ∂p/∂t = c ∂²p/∂z² + dP/dt,     c = H·K,     ∂p/∂z(0) = 0,  p(L) = 0.

Dimensionless: ``ζ = z/L``, time factor ``T = c t / L²``.  For a **step** ``P`` at ``t = 0`` the
undrained initial state is ``p(z, 0+) = P`` and, with ``λ_m = (2m+1)π/2``::

    p(z,t) = P Σ_m 2(−1)^m/λ_m · cos(λ_m ζ) · exp(−λ_m² T)
    w(t)   = (P L / H) [1 − Σ_m (2/λ_m²) exp(−λ_m² T)]          (settlement = compression)

For small ``T`` the image (error-function) form converges much faster::

    p(z,t) = P [1 − Σ_{n≥0} (−1)^n (erfc(((2n+1)L − z)/(2√(ct))) + erfc(((2n+1)L + z)/(2√(ct))))]
    w(t)   = (2P√(ct)/H) [1/√π + 2 Σ_{n≥1} (−1)^n ierfc(n L/√(ct))],
    ierfc(x) = e^{−x²}/√π − x erfc(x)

(the layer is half of the symmetric slab −L ≤ z ≤ L with both faces drained; Carslaw & Jaeger,
*Conduction of Heat in Solids*, ch. III, series and error-function forms).  Here the series is
used for ``T ≥ 0.1`` and the image form below; each to double precision.

A **ramp-and-hold** load (``P`` reached at ``t_r``, then held) follows by Duhamel's principle
from the unit ramp response ``R(t) = (1/t_r)∫₀ᵗ step(τ) dτ``: ``ramp_hold(t) = R(t) − R(t − t_r)``.
The ramp series have 1/λ³ (pressure) and 1/λ⁴ (settlement) terms and are summed with many terms.

All functions are vectorised numpy (``z`` and ``t`` broadcast against each other).
"""
from __future__ import annotations

import numpy as np
from scipy.special import erfc

__all__ = [
    "consolidation_coefficient",
    "time_factor",
    "terzaghi_pressure",
    "terzaghi_settlement",
    "degree_of_consolidation",
    "ramp_hold_pressure",
    "ramp_hold_settlement",
]

_T_SWITCH = 0.1          # series for T ≥ 0.1, image form below
_SERIES_TERMS = 60       # exp(−λ² T) < 1e-300 long before m = 60 when T ≥ 0.1
_IMAGE_TERMS = 12        # erfc(n/√T)-type terms, T < 0.1: negligible after a few
_RAMP_TERMS = 4000       # slowly convergent (1/λ³) ramp series


def _check(H, K, L):
    for name, v in (("H", H), ("K", K), ("L", L)):
        a = np.asarray(v, dtype=float)
        if not np.all(np.isfinite(a)) or not np.all(a > 0):
            raise ValueError(f"{name} must be finite and > 0, got {v!r}")


def consolidation_coefficient(H, K):
    """``c = H·K`` (dimensionless units of the mixture model)."""
    return np.asarray(H, dtype=float) * np.asarray(K, dtype=float)


def time_factor(t, H=2.0, K=1.0, L=1.0):
    """Terzaghi's time factor ``T = c t / L²``."""
    return consolidation_coefficient(H, K) * np.asarray(t, dtype=float) / np.asarray(L) ** 2


def _lam(n):
    return (2 * np.arange(n) + 1) * np.pi / 2


def _ierfc(x):
    return np.exp(-x * x) / np.sqrt(np.pi) - x * erfc(x)


def _step_pressure_unit(zeta, T):
    """``p/P`` for a unit step, ``ζ ∈ [0,1]``, ``T > 0`` (arrays broadcast)."""
    zeta, T = np.broadcast_arrays(np.asarray(zeta, float), np.asarray(T, float))
    out = np.empty(zeta.shape)
    big = T >= _T_SWITCH
    if np.any(big):
        lam = _lam(_SERIES_TERMS)
        z, TT = zeta[big][..., None], T[big][..., None]
        sgn = (-1.0) ** np.arange(_SERIES_TERMS)
        out[big] = np.sum(2 * sgn / lam * np.cos(lam * z) * np.exp(-lam ** 2 * TT), axis=-1)
    small = ~big
    if np.any(small):
        z, TT = zeta[small][..., None], T[small][..., None]
        n = np.arange(_IMAGE_TERMS)
        sgn = (-1.0) ** n
        d = 2 * np.sqrt(TT)
        dissipated = np.sum(sgn * (erfc(((2 * n + 1) - z) / d) + erfc(((2 * n + 1) + z) / d)),
                            axis=-1)
        out[small] = 1.0 - dissipated
    return out


def _step_settlement_unit(T):
    """``w H / (P L)`` for a unit step (degree of consolidation ``U(T)``), ``T > 0``."""
    T = np.asarray(T, float)
    out = np.empty(T.shape)
    big = T >= _T_SWITCH
    if np.any(big):
        lam = _lam(_SERIES_TERMS)
        out[big] = 1.0 - np.sum(2 / lam ** 2 * np.exp(-lam ** 2 * T[big][..., None]), axis=-1)
    small = ~big
    if np.any(small):
        TT = T[small][..., None]
        n = np.arange(1, _IMAGE_TERMS + 1)
        sq = np.sqrt(TT[..., 0])
        out[small] = 2 * sq * (1 / np.sqrt(np.pi)
                               + 2 * np.sum((-1.0) ** n * _ierfc(n / np.sqrt(TT)), axis=-1))
    return out


def degree_of_consolidation(T):
    """Average degree of consolidation ``U(T) = w(t)/w(∞)`` for a step load (``T ≥ 0``)."""
    T = np.asarray(T, float)
    if np.any(T < 0) or not np.all(np.isfinite(T)):
        raise ValueError("T must be finite and ≥ 0")
    Tp = np.where(T > 0, T, 1.0)
    return np.where(T > 0, _step_settlement_unit(Tp), 0.0)


def terzaghi_pressure(z, t, P=1.0, H=2.0, K=1.0, L=1.0):
    """Pore pressure ``p(z, t)`` after a step load ``P`` applied at ``t = 0``.

    ``t = 0`` is read as ``0+`` (undrained: ``p = P`` inside, 0 at the filter ``z = L``);
    ``t < 0`` gives 0 (no load yet).  ``z`` from the bottom, ``0 ≤ z ≤ L``.
    """
    _check(H, K, L)
    z = np.asarray(z, float)
    t = np.asarray(t, float)
    if np.any(z < -1e-12 * L) or np.any(z > L * (1 + 1e-12)):
        raise ValueError("z must lie in [0, L]")
    zeta = np.clip(z / L, 0.0, 1.0)
    T = time_factor(t, H, K, L)
    zeta, T = np.broadcast_arrays(zeta, T)
    pos = T > 0
    Tp = np.where(pos, T, 1.0)
    p = _step_pressure_unit(zeta, Tp)
    p = np.where(pos, p, np.where(T == 0, 1.0, 0.0))
    return P * np.where(zeta < 1, p, 0.0)  # drained filter: exactly 0 at z = L


def terzaghi_settlement(t, P=1.0, H=2.0, K=1.0, L=1.0):
    """Settlement (compression of the sample, positive) after a step load ``P`` at ``t = 0``;
    tends to ``P·L/H``; ≈ ``2P√(ct/π)/H`` at early time; 0 for ``t ≤ 0``."""
    _check(H, K, L)
    T = time_factor(t, H, K, L)
    Tp = np.where(T > 0, T, 1.0)
    return np.where(T > 0, P * L / H * _step_settlement_unit(Tp), 0.0)


def _ramp_unit(zeta, T, which):
    """Response to ``P(t) = t`` in units where ``c = L = 1`` and ``H = 1``, i.e. ``∫₀ᵀ step``.

    ``which='p'``: pressure at ``ζ``; ``which='w'``: settlement.  0 for ``T ≤ 0``.
    """
    T = np.asarray(T, float)
    Tc = np.maximum(T, 0.0)[..., None]
    lam = _lam(_RAMP_TERMS)
    decay = -np.expm1(-lam ** 2 * Tc)  # 1 − exp(−λ²T), accurate for small T
    if which == "p":
        sgn = (-1.0) ** np.arange(_RAMP_TERMS)
        z = np.asarray(zeta, float)[..., None]
        return np.sum(2 * sgn / lam ** 3 * np.cos(lam * z) * decay, axis=-1)
    # ∫₀ᵀ U(τ) dτ = T − Σ 2/λ⁴ (1 − e^{−λ²T}); the tail beyond the last term is ≤ 2/(3λ_M³)·…
    return Tc[..., 0] - np.sum(2 / lam ** 4 * decay, axis=-1)


def ramp_hold_pressure(z, t, P=1.0, t_ramp=0.1, H=2.0, K=1.0, L=1.0):
    """Pore pressure for a load ramped linearly from 0 (``t = 0``) to ``P`` (``t = t_ramp``) and
    then held (``t_ramp > 0``)."""
    _check(H, K, L)
    if not t_ramp > 0:
        raise ValueError("t_ramp must be > 0 (use terzaghi_pressure for a step)")
    z = np.asarray(z, float)
    zeta = np.clip(z / L, 0.0, 1.0)
    T = time_factor(t, H, K, L)
    Tr = float(time_factor(t_ramp, H, K, L))
    zeta, T = np.broadcast_arrays(zeta, T)
    return P / Tr * (_ramp_unit(zeta, T, "p") - _ramp_unit(zeta, T - Tr, "p"))


def ramp_hold_settlement(t, P=1.0, t_ramp=0.1, H=2.0, K=1.0, L=1.0):
    """Settlement (compression) for the ramp-and-hold load of :func:`ramp_hold_pressure`."""
    _check(H, K, L)
    if not t_ramp > 0:
        raise ValueError("t_ramp must be > 0 (use terzaghi_settlement for a step)")
    T = time_factor(t, H, K, L)
    Tr = float(time_factor(t_ramp, H, K, L))
    return P * L / H / Tr * (_ramp_unit(None, T, "w") - _ramp_unit(None, T - Tr, "w"))
