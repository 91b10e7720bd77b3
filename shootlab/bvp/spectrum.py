"""Bounds on and values of the local Jacobians' spectra, batched: max|λ| and max Re λ of many small
matrices (report eq. 5.6), exactly by eigenvalues on the CPU or bounded by batched matrix products
elsewhere (no per-matrix kernels on a GPU)."""
from __future__ import annotations

import math

import torch
from torch import Tensor

from .device import accelerator_paths



#: the values of ``method`` (``spectral=`` of :func:`shootlab.solve`)
SPECTRAL_METHODS = ("auto", "exact", "bound")


def spectral_method(method: str, J: Tensor) -> str:
    """``"exact"`` or ``"bound"`` for ``method`` on the device of J: ``"auto"`` is the exact
    eigenvalues on the CPU (LAPACK, one batched call) and the bounds from matrix products on an
    accelerator, where batched eigenvalues run as a host loop over the matrices
    (:func:`shootlab.bvp.device.accelerator_paths`)."""
    if method not in SPECTRAL_METHODS:
        raise ValueError(f"spectral method must be one of {', '.join(SPECTRAL_METHODS)}, got {method!r}")
    if method == "auto":
        return "bound" if accelerator_paths(J) else "exact"
    return method


def spectral_bounds(J: Tensor, method: str = "auto") -> tuple[Tensor, Tensor]:
    """(max|λ|, max Re λ) of each matrix of J (k, n, n).

    ``"exact"``: from the eigenvalues (:func:`batched_eigvals`); where LAPACK gives none, the
    bounds ‖J‖∞ ≥ |λ| and Gershgorin's max_i (J_ii + Σ_{j≠i} |J_ij|) ≥ Re λ stand in.
    ``"bound"``: upper bounds from batched matrix products alone (:func:`spectral_radius_bound`,
    :func:`abscissa_bound`), within a relative 1e-4 of the exact values (and, for max Re λ, an
    absolute 1e-9·max|λ|): every decision taken on them (``solve``'s ``refine`` and
    ``max_growth``, the ``auto`` integrator's stiff rows) errs on the safe side — a finer grid,
    a refused interval, the A-stable scheme.  ``"auto"``: :func:`spectral_method`."""
    if spectral_method(method, J) == "bound":
        rho = spectral_radius_bound(J)
        return rho, abscissa_bound(J, rho)
    lam = batched_eigvals(J)
    rho, kappa = lam.abs().amax(-1), lam.real.amax(-1)
    failed = torch.isnan(lam.real).any(-1)
    if not bool(failed.any()):
        return rho, kappa
    diag = J.diagonal(dim1=-2, dim2=-1)
    rho = torch.where(failed, J.abs().sum(-1).amax(-1), rho)
    kappa = torch.where(failed, (diag + J.abs().sum(-1) - diag.abs()).amax(-1), kappa)
    return rho, kappa


#: squarings of :func:`_power_bound`: the bound after j of them is ‖M^(2^j)‖^(1/2^j) ≥ ρ(M)
SQUARINGS = 48


def _power_bound(M: Tensor) -> Tensor:
    """log ρ(M) ≤ min_j 2^(−j) log ‖M^(2^j)‖∞ for each matrix of M (k, n, n), j = 0 … SQUARINGS
    (Gelfand: the bound tends to log ρ; its excess is about log(κ(V))/2^j for a diagonalisable M
    with eigenvectors V, and log(2^j)·d/2^j for a Jordan block of size d + 1).  The powers are
    normalised at every squaring, M^(2^j) = e^(L_j) N_j with ‖N_j‖∞ = 1, so nothing overflows;
    a nilpotent M gives −inf."""
    norm = M.abs().sum(-1).amax(-1)
    log_scale = torch.log(norm)
    best = log_scale.clone()
    N = M / norm.clamp_min(torch.finfo(M.dtype).tiny)[..., None, None]
    for j in range(1, SQUARINGS + 1):
        N = N @ N
        log_scale = 2.0 * log_scale
        nu = N.abs().sum(-1).amax(-1)
        log_scale = log_scale + torch.log(nu)
        best = torch.minimum(best, log_scale / 2.0 ** j)
        N = N / nu.clamp_min(torch.finfo(M.dtype).tiny)[..., None, None]
    return best


def spectral_radius_bound(J: Tensor) -> Tensor:
    """An upper bound on max|λ| of each matrix of J (k, n, n) from batched matrix products:
    min_j ‖J^(2^j)‖∞^(1/2^j) (:func:`_power_bound`) — at most ‖J‖∞, within a relative
    log(κ(V))/2^48 of ρ(J) for a diagonalisable J."""
    return torch.exp(_power_bound(J))


def abscissa_bound(J: Tensor, rho: Tensor | None = None) -> Tensor:
    """An upper bound on max Re λ of each matrix of J (k, n, n) from batched matrix products.

    With τ = 1/c, c ≥ ρ(J) (:func:`spectral_radius_bound`, at least 1e-3·‖J‖∞), the eigenvalues
    of E = e^{τJ} are e^{τλ}, so max Re λ = log ρ(E)/τ exactly, and :func:`_power_bound` bounds
    log ρ(E) from above.  |τλ| ≤ 1 keeps E well scaled (|e^{τλ}| ∈ [e^{−1}, e]); the excess of the
    bound is about c·log(κ(V))/2^48.  ``torch.linalg.matrix_exp`` is a Taylor polynomial with
    scaling and squaring: matrix products only.  ``rho``: :func:`spectral_radius_bound`'s, if known."""
    norm = J.abs().sum(-1).amax(-1)
    c = torch.maximum(spectral_radius_bound(J) if rho is None else rho, 1e-3 * norm)
    zero = c <= 0                                           # J = 0: max Re λ = 0
    c = torch.where(zero, torch.ones_like(c), c)
    E = torch.linalg.matrix_exp(J / c[..., None, None])
    kappa = _power_bound(E) * c
    return torch.where(zero, torch.zeros_like(kappa), kappa)


def batched_eigvals(J: Tensor) -> Tensor:
    """Eigenvalues of each matrix of J (k, n, n) as a complex (k, n) tensor.  LAPACK's QR
    iteration can fail on badly scaled, nearly defective matrices and then fails the whole
    batch: the matrices are retried one by one, and those that still fail get NaN."""
    try:
        return torch.linalg.eigvals(J)
    except torch.linalg.LinAlgError:
        cdtype = torch.complex128 if J.dtype == torch.float64 else torch.complex64
        out = torch.full(J.shape[:-1], complex(math.nan, math.nan), dtype=cdtype, device=J.device)
        for k in range(J.shape[0]):          # rare fallback path, not the hot loop
            try:
                out[k] = torch.linalg.eigvals(J[k])
            except torch.linalg.LinAlgError:
                pass
        return out
