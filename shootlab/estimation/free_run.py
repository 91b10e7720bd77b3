"""The free run of an identification model: x' = A x + B ζ(x, t), ε = 0, driven by the recorded
``given`` channels (report eqs. 2.4–2.5 with the model errors set to zero) — the simulation the
diagnosis compares with a record (its noise floor's surrogates, the validation misfit) and that
users run to see a model's response.

Between samples the given channels are linear, so every step runs from one sample to the next
(no step straddles a kink).  Non-stiff on the sample grid: classical RK4, one step per sample
interval.  Stiff: the two-stage Radau IIA method (order 3, L-stable; Hairer & Wanner, *Solving
ODEs II*, §IV.5) with :data:`RADAU_SUBSTEPS` steps per sample interval, its stage equations solved
by simplified Newton with the Jacobian of the right-hand side taken once per sample interval by
central differences, stopped on the contraction's error estimate (§IV.8) — every evaluation
batched (the Jacobian's columns in one call, both stages in one call).  LSODA over the whole
record, which restarts at every sample's kink, is the fallback when the Newton iteration does not
converge.

Both schemes first run every sample interval at once (:func:`_shoot_samples`): the free run as a
multiple-shooting problem on the sample grid, its matching conditions solved by Newton sweeps
over all intervals as one batch — a few calls of the right-hand side on T rows instead of 4–10
calls on one row per sample, an order of magnitude faster, the same states to 1e-11 of their
range.  A run
whose sweeps do not converge goes sample by sample.  The Jacobian of the right-hand side comes
from the least squares that determines ζ (:class:`~shootlab.bvp.tangents.VectorField`), not from a
least-squares solve per central-difference probe.

:func:`simulate_many` runs several parameter sets (and starts) as rows of one batch: on models whose
right-hand side costs mostly per-call overhead, P runs cost about one — the columns of the
output-error Jacobian (:class:`FreeRun`, :mod:`shootlab.estimation.output_error`).
"""
from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .data import Interpolant, Measurements, with_filled_inputs
from .model import IdentificationModel, measured_states
from shootlab.bvp.linalg import apply_qt, householder_qr
from shootlab.bvp.spectrum import spectral_bounds
from shootlab.bvp.tangents import VectorField

__all__ = ["simulate", "simulate_many", "FreeRun", "RK4_REACH", "RADAU_SUBSTEPS"]


#: the free run's fixed RK4 step on the sample grid is taken only where ρ(∂s'/∂s)·h stays below
#: this (local error of the fastest mode ≲ 1e-4 per step; RK4 is stable to 2.78)
RK4_REACH = 0.5


def _rows(rhs: Callable[[Tensor, Tensor], Tensor], tt: Tensor, S: Tensor) -> Tensor:
    """``rhs`` on every row of ``S`` (…, n), the times ``tt`` broadcast to its leading shape: one call."""
    lead = S.shape[:-1]
    return rhs(torch.broadcast_to(tt, lead).reshape(-1), S.reshape(-1, S.shape[-1])).reshape(S.shape)


#: a row's F_s counts as of full column rank for the fast solves of :func:`_least_squares_solution`
#: when the smallest |diagonal entry| of its triangular factor is above this multiple of the largest
FULL_RANK = 1e-10


def _least_squares_solution(Fs: Tensor, rs: Tensor) -> Tensor:
    """ζ minimising ‖F_s ζ − r_s‖ on every row (…, rows, nζ), (…, rows): by LU with partial pivoting
    where F_s is square, by Householder QR where it is tall — when every row's triangular factor
    is of full rank (:data:`FULL_RANK`) — else by the rank-revealing least squares of
    ``torch.linalg.lstsq`` (the minimum-norm solution), several times slower than LU on small
    square blocks."""
    b = rs.unsqueeze(-1)
    if Fs.shape[-2] == Fs.shape[-1]:
        LU, pivots, info = torch.linalg.lu_factor_ex(Fs)
        if _full_rank(LU) and not bool(info.any()):
            return torch.linalg.lu_solve(LU, pivots, b).squeeze(-1)
    elif Fs.shape[-2] > Fs.shape[-1]:
        reflectors, tau, R = householder_qr(Fs)
        if _full_rank(R):
            k = R.shape[-1]
            return torch.linalg.solve_triangular(R, apply_qt(reflectors, tau, b)[..., :k, :], upper=True).squeeze(-1)
    return torch.linalg.lstsq(Fs, b).solution.squeeze(-1)


def _full_rank(R: Tensor) -> bool:
    """Whether every triangular factor R (…, k, k) has all |R_ii| > :data:`FULL_RANK` · max |R_ii|
    (a non-finite entry fails)."""
    d = R.diagonal(dim1=-2, dim2=-1).abs()
    return bool((d > FULL_RANK * d.amax(-1, keepdim=True)).all())


def _jacobian(rhs: Callable[[Tensor, Tensor], Tensor], tt: Tensor, s: Tensor) -> Tensor:
    """∂rhs/∂s (R, n, n) at the rows ``s`` (R, n), times ``tt`` (R,): the right-hand side's own
    (a :class:`~shootlab.bvp.tangents.VectorField`), else central differences with the step
    1e-6 (1 + |s_j|), every column of every row in one call."""
    if isinstance(rhs, VectorField):
        return rhs.jacobian(tt, s)[1]
    n = s.shape[-1]
    d = 1e-6 * (1.0 + s.abs())
    eye = torch.eye(n, dtype=s.dtype, device=s.device)
    probe = torch.cat([s[:, None, :] + d[:, :, None] * eye, s[:, None, :] - d[:, :, None] * eye], 1)
    vals = _rows(rhs, tt[:, None], probe)                           # vals[p, j] = rhs(s_p ± d_pj e_j)
    return ((vals[:, :n] - vals[:, n:]) / (2 * d[:, :, None])).transpose(-1, -2)


def _too_stiff(rhs: Callable[[Tensor, Tensor], Tensor], t: Tensor, s: Tensor, hmax: float) -> bool:
    """Whether RK4 with steps up to ``hmax`` is not accurate at the rows ``s`` (P, n) at time ``t``:
    the spectral radius of ∂rhs/∂s times hmax above :data:`RK4_REACH` for any row (on an
    accelerator an upper bound on it: :func:`~shootlab.bvp.shooting.spectral_bounds`)."""
    J = _jacobian(rhs, t.expand(s.shape[0]), s)
    return float(spectral_bounds(J)[0].max()) * hmax > RK4_REACH


def _rk4_step(rhs: Callable[[Tensor, Tensor], Tensor], t: Tensor, dt: Tensor, y: Tensor) -> Tensor:
    """One classical RK4 step of every row of ``y`` (R, n) from ``t`` by ``dt`` (R,)."""
    dc = dt[:, None]
    k1 = rhs(t, y)
    k2 = rhs(t + dt / 2, y + dc / 2 * k1)
    k3 = rhs(t + dt / 2, y + dc / 2 * k2)
    k4 = rhs(t + dt, y + dc * k3)
    return y + dc / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def _rk4_on_samples(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor) -> Tensor | None:
    """The free runs of P systems (``s0`` (P, n); ``rhs(t (R,), S (R, n))`` on rows) by classical
    RK4 with one step per sample interval (between samples the given channels are linear, so the
    step sees no kink) — (T, P, n) — or None where that is not accurate (:func:`_too_stiff` at the
    start, middle and end of the record, on the way) or a state turns non-finite.
    Four right-hand sides per sample against ~26 for LSODA, which restarts at every sample's kink."""
    h = ts[1:] - ts[:-1]
    hmax = float(h.max()) if h.numel() else 0.0
    out = [s0]
    s = s0
    for k in range(ts.numel() - 1):
        if k in (0, ts.numel() // 2) and _too_stiff(rhs, ts[k], s, hmax):
            return None
        s = _rk4_step(rhs, ts[k].expand(s.shape[0]), h[k].expand(s.shape[0]), s)
        if not bool(torch.isfinite(s).all()):
            return None
        out.append(s)
    if ts.numel() > 1 and _too_stiff(rhs, ts[-1], s, hmax):
        return None
    return torch.stack(out)


#: Newton sweeps of a free run with all sample intervals at once (:func:`_shoot_samples`) before
#: it hands over to the run sample by sample, or this many in a row without a new least defect
#: (from a constant start the defects of a non-linear run first wander: the rig with backlash
#: took 10 sweeps, 0.38 → 5.1 → 0.25 → 1.3 → 0.18 → 3.8e-3 → … → 3.3e-10; a forced Duffing
#: oscillator over 10 periods' worth of samples 13)
MAX_SWEEPS, STALLED_SWEEPS = 25, 5


def _rk4_in_parallel(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor,
                     sweeps: int = MAX_SWEEPS) -> tuple[Tensor | None, bool]:
    """The free run of :func:`_rk4_on_samples` with all sample intervals at once
    (:func:`_shoot_samples`; Y_k = R(h_k J_k), RK4's stability polynomial at the Jacobian of
    the interval's start), with the same test for stiffness at the start, middle and end of
    the record: (the run, False), or (None, whether it was found too stiff for RK4) where the
    test fails, a state turns non-finite or the sweeps run out."""
    s = s0.reshape(1, -1) if s0.dim() == 1 else s0
    T = ts.numel()
    if T < 2:
        return None, False
    hmax = float((ts[1:] - ts[:-1]).max())
    if _too_stiff(rhs, ts[0], s, hmax):
        return None, True
    eye = torch.eye(s.shape[-1], dtype=s.dtype, device=s.device)

    def step(t: Tensor, dt: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        end = _rk4_step(rhs, t, dt, y)
        hJ = dt[:, None, None] * _jacobian(rhs, t, y)
        Y = eye + hJ @ (eye + hJ / 2 @ (eye + hJ / 3 @ (eye + hJ / 4)))    # 1 + z + z²/2 + z³/6 + z⁴/24
        return end, torch.isfinite(end).all(-1), Y
    S = _shoot_samples(step, s0, ts, sweeps=sweeps)
    if S is None:
        return None, False
    runs = S if s0.dim() > 1 else S[:, None]
    if any(_too_stiff(rhs, ts[k], runs[k], hmax) for k in sorted({T // 2, T - 1})):
        return None, True
    return S, False


#: Radau IIA steps per sample interval in a stiff free run: the fastest modes are damped (L-stable),
#: the slow ones resolved to a local error of order (h/4)⁴ — on the 6-element confined model with
#: 401 samples the free run agrees with LSODA (rtol 1e-8) to 8e-6 of the channels' range (3e-5 with
#: 3 elements, 2e-6 with 12: a hundredth of a 1 % noise), in a fraction of LSODA's time
RADAU_SUBSTEPS = 4

#: the two-stage Radau IIA tableau (c, A; b is A's last row: stiffly accurate)
_RADAU_C = (1.0 / 3.0, 1.0)
_RADAU_A = ((5.0 / 12.0, -1.0 / 12.0), (3.0 / 4.0, 1.0 / 4.0))


def _radau_steps(rhs: Callable[[Tensor, Tensor], Tensor], t0: Tensor, H: Tensor, s: Tensor, eta: Tensor,
                 substeps: int, tol: float, max_newton: int, sensitivity: bool = False):
    """``substeps`` equal steps of the two-stage Radau IIA method over [t0, t0 + H] from ``s``, for
    independent rows: ``s`` (R, n), ``t0``, ``H``, ``eta`` (R,) — R = P r, rows p r … p r + r − 1 of
    system p, as ``rhs`` takes them.  Stage increments Z = h (A ⊗ I) f(t + c h, s + Z) by simplified
    Newton with the matrix I − h A ⊗ J, J = ∂f/∂s at (t0, s) (:func:`_jacobian`; each row its own,
    factorised as a batch); a row's iteration stops where the error left, estimated from the
    contraction rate θ as η ‖ΔZ‖ with η = θ/(1 − θ), is below ``tol`` (relative) — the first
    iteration with η of the step before ([HW2] §IV.8).  Returns (the end states, η, whether each
    row converged within ``max_newton`` iterations, and with ``sensitivity`` the step map's
    derivative with J held: Y = (I + [0 I] (I − h A ⊗ J)⁻¹ h (c ⊗ J))^substeps, (R, n, n))."""
    R, n = s.shape
    A = torch.tensor(_RADAU_A, dtype=s.dtype, device=s.device)
    c = torch.tensor(_RADAU_C, dtype=s.dtype, device=s.device)
    eye = torch.eye(2 * n, dtype=s.dtype, device=s.device)
    dt = (H / substeps).expand(R)
    J = _jacobian(rhs, t0.expand(R), s)
    M = eye - dt[:, None, None] * (A[:, None, :, None] * J[:, None, :, None, :]).reshape(R, 2 * n, 2 * n)
    lu = torch.linalg.lu_factor(M)                                                    # I − h A ⊗ J
    ok = torch.ones(R, dtype=torch.bool, device=s.device)
    for j in range(substeps):
        tt = t0.expand(R)[:, None] + (j + c) * dt[:, None]
        Z = s.new_zeros(R, 2, n)
        going = torch.ones(R, dtype=torch.bool, device=s.device)
        bound = tol * (1.0 + s.abs().amax(-1))
        eta = eta.clamp(min=1e-16) ** 0.8
        last = s.new_ones(R)
        for i in range(max_newton):
            G = dt[:, None, None] * (A @ _rows(rhs, tt, s[:, None, :] + Z)) - Z
            dZ = torch.linalg.lu_solve(*lu, G.reshape(R, 2 * n, 1)).reshape(R, 2, n)
            dZ = torch.where(going[:, None, None], dZ, 0.0)          # a converged row keeps its Z
            Z = Z + dZ
            size = dZ.abs().amax((1, 2))
            if i > 0:           # θ = ‖ΔZ_i‖/‖ΔZ_{i−1}‖; the error left ≈ η ‖ΔZ_i‖
                theta = size / last
                eta = torch.where(going, torch.where(theta < 1, theta / (1 - theta), math.inf), eta)
            going = going & ~(eta * size <= bound)
            if not bool(going.any()):
                break
            last = size
        ok = ok & ~going
        s = s + Z[:, 1]
    Y = None
    if sensitivity:             # (I − h A ⊗ J) ∂Z/∂s = h (A 1 ⊗ J), A 1 = c;  ∂s₊/∂s = I + ∂Z₂/∂s
        dZ = torch.linalg.lu_solve(*lu, dt[:, None, None] * torch.cat([c[0] * J, c[1] * J], -2))
        Y = torch.linalg.matrix_power(torch.eye(n, dtype=s.dtype, device=s.device) + dZ[:, n:], substeps)
    return s, eta, ok, Y


def _radau_on_samples(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor,
                      substeps: int = RADAU_SUBSTEPS, tol: float = 1e-10, max_newton: int = 10) -> Tensor | None:
    """The free run by the two-stage Radau IIA method (module docstring), one sample interval after
    the other (:func:`_radau_steps`, η carried from step to step); ``rhs(t (R,), S (R, n))`` on
    rows; ``s0`` (n,) → (T, n), or P systems at once: (P, n) → (T, P, n).  None when an iteration
    does not converge in ``max_newton`` steps or a state turns non-finite."""
    single = s0.dim() == 1
    s = s0.reshape(1, -1) if single else s0
    eta = s.new_ones(s.shape[0])
    out = [s]
    for k in range(ts.numel() - 1):
        s, eta, ok, _ = _radau_steps(rhs, ts[k], ts[k + 1] - ts[k], s, eta, substeps, tol, max_newton)
        if not bool(ok.all() and torch.isfinite(s).all()):
            return None
        out.append(s)
    S = torch.stack(out)
    return S[:, 0] if single else S


def _radau_in_parallel(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor,
                       substeps: int = RADAU_SUBSTEPS, tol: float = 1e-10, max_newton: int = 10,
                       sweeps: int = MAX_SWEEPS) -> Tensor | None:
    """The free run of :func:`_radau_on_samples` with all sample intervals at once
    (:func:`_shoot_samples`; Y_k the step map's derivative with the Jacobian held over the
    interval, :func:`_radau_steps`, η carried from sweep to sweep); None where a stage
    iteration fails, a state turns non-finite or the sweeps run out."""
    eta = None

    def step(t0: Tensor, H: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        nonlocal eta
        eta = y.new_ones(y.shape[0]) if eta is None else eta
        end, eta, ok, Y = _radau_steps(rhs, t0, H, y, eta, substeps, tol, max_newton, sensitivity=True)
        return end, ok, Y
    return _shoot_samples(step, s0, ts, tol, sweeps)


def _shoot_samples(step: Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]], s0: Tensor, ts: Tensor,
                   tol: float = 1e-10, sweeps: int = MAX_SWEEPS) -> Tensor | None:
    """A free run with all sample intervals at once: multiple shooting of the initial-value
    problem on the sample grid (report eq. 3.2, the boundary conditions s_0 given).  The unknowns
    are the states S_k at the samples; every sweep integrates every interval from its S_k as rows
    of one batch, ``step(t_k (R,), h_k (R,), S_k (R, n)) → (φ_k(S_k), converged (R,), Y_k (R, n, n))``
    with Y_k ≈ ∂φ_k/∂S_k; the defects d_k = φ_k(S_k) − S_{k+1} of the matching conditions
    (eq. 3.3) follow, and Newton's correction δ_0 = 0, δ_{k+1} = Y_k δ_k + d_k (forward
    substitution, the free run's own direction) is summed for all k at once by
    :func:`_affine_scan`.  With Y_k exact (a model linear in its states) one sweep solves and a
    second confirms; otherwise it is a quasi-Newton.  The same discrete scheme as the run sample
    by sample, so the same states to its tolerance: stops when every |d_k| ≤ 10 tol (1 + |φ_k|),
    after that sweep's correction (the states then depend smoothly on the parameters, as a
    forward-difference Jacobian of the runs needs).  ``s0`` (n,) → (T, n), or (P, n) → (T, P, n);
    None when a step fails, a state turns non-finite, the sweeps run out or stall
    (:data:`MAX_SWEEPS`; the caller then goes sample by sample)."""
    single = s0.dim() == 1
    s = s0.reshape(1, -1) if single else s0
    P, n = s.shape
    K = ts.numel() - 1
    if K < 1:
        return None
    t0, H = ts[:-1].repeat(P), (ts[1:] - ts[:-1]).repeat(P)       # row p K + k: interval k of system p
    S = s[:, None, :].expand(P, K + 1, n).clone()
    least, stalled = math.inf, 0
    for _ in range(sweeps):
        end, ok, Y = step(t0, H, S[:, :-1].reshape(P * K, n))
        end = end.reshape(P, K, n)
        if not bool(ok.all() and torch.isfinite(end).all()):
            return None
        d = end - S[:, 1:]
        done = bool((d.abs() <= 10 * tol * (1.0 + end.abs().amax(-1, keepdim=True))).all())
        size = float(d.abs().max())
        least, stalled = (size, 0) if size < least else (least, stalled + 1)
        if stalled >= STALLED_SWEEPS:
            return None
        S[:, 1:] += _affine_scan(Y.reshape(P, K, n, n), d)
        if not bool(torch.isfinite(S).all()):
            return None
        if done:                # with the last correction: its error is second order in d
            return S[0] if single else S.transpose(0, 1)
    return None


def _affine_scan(Y: Tensor, d: Tensor) -> Tensor:
    """x_1 … x_K of the recursion x_0 = 0, x_{k+1} = Y_k x_k + d_k for ``Y`` (…, K, n, n) and ``d``
    (…, K, n), as an inclusive scan of the affine maps x ↦ Y_k x + d_k (Hillis–Steele: log₂ K
    batched compositions (Y', d') ∘ (Y, d) = (Y' Y, Y' d + d') instead of K sequential steps)."""
    Y, d = Y.clone(), d.clone()
    K, shift = d.shape[-2], 1
    while shift < K:
        d[..., shift:, :] = d[..., shift:, :] + (Y[..., shift:, :, :] @ d[..., :-shift, :, None]).squeeze(-1)
        Y[..., shift:, :, :] = Y[..., shift:, :, :] @ Y[..., :-shift, :, :]
        shift *= 2
    return d


def simulate(model: IdentificationModel, data, parameters: Mapping[str, float],
             initial_state: Sequence[float] | None = None, t=None, device=None) -> dict[str, np.ndarray]:
    """Free-run simulation x' = A x + B ζ(x, t), ε = 0, ζ from the model-equation rows and the
    rows of the ``given`` channels (least squares if over-determined); returns the predicted
    measured channels (the measurement rows f + F ζ) and the states at the sample times
    (``state:<name>``), at ``t`` if given (default the record's times); ``device``: where the run is
    integrated (:func:`shootlab.bvp.device.resolve_device`; default the CPU)."""
    return simulate_many(model, data, [parameters], [initial_state], t, device)[0]


def simulate_many(model: IdentificationModel, data, parameter_sets: Sequence[Mapping[str, float]],
                  initial_states: Sequence[Sequence[float] | None] | None = None, t=None,
                  device=None) -> list[dict[str, np.ndarray]]:
    """The free runs of :func:`simulate` for several parameter sets (and initial states; None: the
    model's initial approximation) at once: the systems are rows of one batch, so P runs cost
    about one in a model whose right-hand side is dominated by per-call overhead — the columns of
    a forward-difference Jacobian (:func:`shootlab.estimation.output_error.estimate_output_error`).  When one
    system is too stiff for RK4 on the samples, all take Radau IIA; when that fails, every
    system is run alone (its own fallbacks).  ``device``: :func:`simulate`'s."""
    from shootlab.bvp.device import resolve_device

    dev = resolve_device(device)
    data = Measurements.coerce(data)
    data.require(model.given, float(data.t[0]), float(data.t[-1]))
    data = with_filled_inputs(data, model.given, ends="error")      # the run starts at the first sample
    P = len(parameter_sets)
    starts = list(initial_states) if initial_states is not None else [None] * P
    if len(starts) != P:
        raise ValueError(f"{P} parameter sets but {len(starts)} initial states")
    rows = model.equations
    sim_rows = [i for i, r in enumerate(rows) if r not in model.channels or model.channels[r] in model.given]
    out_rows = [i for i, r in enumerate(rows) if r in model.channels and model.channels[r] not in model.given]
    given_rows = [i for i in sim_rows if rows[i] in model.channels]
    interp = Interpolant(data, [model.channels[rows[i]] for i in given_rows], device=dev)
    theta = torch.tensor([[float(ps[p]) for p in model.parameters] for ps in parameter_sets],
                         dtype=torch.float64, device=dev).reshape(P, len(model.parameters))
    ts = torch.as_tensor(data.t if t is None else np.asarray(t, dtype=np.float64), dtype=torch.float64, device=dev)
    if any(x is None for x in starts):
        guess = (model.initial_states(data, ts[:1]) if model.initial_states else measured_states(model, data, ts[:1]))[0]
        guess = torch.as_tensor(guess).to(ts)
    s0 = torch.stack([guess if x is None else torch.as_tensor(np.asarray(x, dtype=np.float64), device=dev)
                      for x in starts])
    A, B = model.A.to(torch.float64).to(dev), model.B.to(torch.float64).to(dev)

    def least_squares(x: Tensor, tt: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """f, F and the least squares F_s ζ ≈ r_s = z − f_s of the simulated rows (the model
        equations, whose pseudo-measurements are zero, and the given channels)."""
        f, F = model.f_and_F(x, tt)
        z = torch.zeros_like(f)
        if given_rows:
            z[..., given_rows] = interp.values(tt)
        return f, F, F[..., sim_rows, :], (z - f)[..., sim_rows]

    def zeta_of(x: Tensor, tt: Tensor):
        f, F, Fs, rs = least_squares(x, tt)
        return _least_squares_solution(Fs, rs), f, F

    ns = len(model.states)

    rows_theta: dict[int, Tensor] = {}         # θ for R rows, made once per R

    def with_theta(s: Tensor) -> Tensor:
        """x = [s, θ] for the rows s (R, ns); R = P r, row p r + i belongs to system p."""
        R = s.shape[0]
        if R not in rows_theta:
            rows_theta[R] = theta.repeat_interleave(R // P, 0)
        return torch.cat([s, rows_theta[R]], -1)

    def rhs(tt: Tensor, s: Tensor) -> Tensor:
        """s' for the rows s (R, ns) at times tt (R,)."""
        x = with_theta(s)
        zeta, _, _ = zeta_of(x, tt)
        return (x @ A.T + zeta @ B.T)[:, :ns]

    def jacobian(tt: Tensor, s: Tensor) -> tuple[Tensor, Tensor]:
        """(s', ∂s'/∂s) at the rows s (R, ns): f and F by central differences (the step of
        :func:`_jacobian`), and ζ's derivative from the least squares' own QR factor instead of a
        least-squares solve per probe — at full column rank of F_s, ζ = (F_sᵀF_s)⁻¹F_sᵀ r_s with
        r_s = z − f_s, so

            ∂ζ = (F_sᵀF_s)⁻¹ [F_sᵀ (−∂f_s − ∂F_s ζ) + ∂F_sᵀ (r_s − F_s ζ)].

        F is differenced along every state only where it moves along one random direction (on a
        model linear in its states it depends on the parameters alone), instead of one
        least-squares solve per probe of every state.
        A rank-deficient or under-determined F_s: central differences of the whole rhs."""
        x = with_theta(s)
        R = s.shape[0]
        d = 1e-6 * (1.0 + s.abs())
        step = d[:, :, None] * torch.eye(ns, dtype=s.dtype, device=s.device)        # (R, ns, ns)

        def at(ds: Tensor) -> tuple[Tensor, Tensor]:        # x + [ds, 0] for ds (R, k, ns), times per row
            k = ds.shape[1]
            xp = (x[:, None, :] + torch.cat([ds, ds.new_zeros(R, k, x.shape[-1] - ns)], -1)).reshape(R * k, -1)
            return xp, tt[:, None].expand(R, k).reshape(-1)

        _, F0, Fs, r0 = least_squares(x, tt)
        if Fs.shape[-2] < Fs.shape[-1]:                 # under-determined: the minimum-norm ζ
            return rhs(tt, s), _jacobian(rhs, tt, s)
        reflectors, tau, Rf = householder_qr(Fs)
        if not _full_rank(Rf):
            return rhs(tt, s), _jacobian(rhs, tt, s)
        qtr = apply_qt(reflectors, tau, r0[..., None])[..., :Rf.shape[-1], :]
        zeta = torch.linalg.solve_triangular(Rf, qtr, upper=True).squeeze(-1)
        two_d = 2 * d[:, :, None]
        fp = model.f(*at(torch.cat([step, -step], 1))).reshape(R, 2 * ns, -1)[..., sim_rows]
        w = torch.einsum("rsz,rjs->rzj", Fs, -(fp[:, :ns] - fp[:, ns:]) / two_d)     # Fₛᵀ(−∂fₛ), (R, nζ, ns)
        v = d * torch.randn(ns, generator=torch.Generator().manual_seed(0), dtype=s.dtype).to(s.device)
        Fv = model.F(*at(torch.stack([v, -v], 1))).reshape(R, 2, *F0.shape[1:])
        if not torch.equal(Fv[:, 0], Fv[:, 1]):          # F moves with the states
            Fp = model.F(*at(torch.cat([step, -step], 1))).reshape(R, 2 * ns, *F0.shape[1:])[..., sim_rows, :]
            dF = (Fp[:, :ns] - Fp[:, ns:]) / two_d[..., None]                       # (R, ns, rows, nζ)
            res = r0 - (Fs @ zeta[..., None]).squeeze(-1)
            w = w - torch.einsum("rsz,rjs->rzj", Fs, (dF @ zeta[:, None, :, None]).squeeze(-1)) \
                + torch.einsum("rjsz,rs->rzj", dF, res)
        y = torch.linalg.solve_triangular(Rf.transpose(-1, -2), w, upper=False)
        dzeta = torch.linalg.solve_triangular(Rf, y, upper=True)                    # (R, nζ, ns)
        return (x @ A.T + zeta @ B.T)[:, :ns], A[:ns, :ns] + B[:ns] @ dzeta

    field = VectorField(rhs, jacobian)

    S, stiff = _rk4_in_parallel(field, s0, ts)      # all sample intervals at once, else one by one
    if S is None and not stiff:
        S = _rk4_on_samples(field, s0, ts)
    if S is None:                   # stiff on the sample grid
        S = _radau_in_parallel(field, s0, ts)
        if S is None:
            S = _radau_on_samples(field, s0, ts)
    if S is None and P > 1:         # its Newton iteration failed for some system: each alone
        return [simulate_many(model, data, [ps], [x], t, dev)[0] for ps, x in zip(parameter_sets, starts)]
    if S is None:                   # an adaptive stiff solver
        from scipy.integrate import solve_ivp

        def fun(tt, s):
            return rhs(torch.tensor([tt], dtype=torch.float64, device=dev),
                       torch.as_tensor(s, device=dev)[None])[0].cpu().numpy()
        sol = solve_ivp(fun, (float(ts[0]), float(ts[-1])), s0[0].cpu().numpy(), method="LSODA",
                        t_eval=ts.cpu().numpy(), rtol=1e-8, atol=1e-10)
        if not sol.success:
            raise RuntimeError(f"free-run simulation failed: {sol.message}")
        S = torch.as_tensor(sol.y.T, device=dev)[:, None]
    T = S.shape[0]
    X = torch.cat([S, theta.expand(T, -1, -1)], -1).reshape(T * P, -1)
    zeta, f, F = zeta_of(X, ts[:T].repeat_interleave(P))
    pred = (f + (F @ zeta.unsqueeze(-1)).squeeze(-1)).reshape(T, P, -1)
    runs = []
    ts, pred, S = ts.cpu(), pred.cpu(), S.cpu()
    for p in range(P):
        out = {"t": ts.numpy()[:T]}
        for i in out_rows:
            out[model.channels[rows[i]]] = pred[:, p, i].numpy()
        for j, name in enumerate(model.states):
            out[f"state:{name}"] = S[:, p, j].numpy()
        runs.append(out)
    return runs


class FreeRun:
    """The general free run as an output-error simulator (:data:`shootlab.estimation.output_error.Simulator`),
    ``start(model, data, parameters)`` the initial state where none is passed (None: the model's
    initial approximation); :meth:`many` runs several parameter sets as one batch
    (:func:`simulate_many`)."""

    def __init__(self, start: Callable[[IdentificationModel, Measurements, Mapping[str, float]],
                                       Sequence[float] | None] | None = None, device=None):
        self.start, self.device = start, device

    def __call__(self, model: IdentificationModel, data: Measurements, parameters: Mapping[str, float],
                 s0=None) -> dict[str, np.ndarray]:
        return self.many(model, data, [parameters], [s0])[0]

    def many(self, model: IdentificationModel, data: Measurements, parameter_sets: Sequence[Mapping[str, float]],
             states: Sequence | None = None) -> list[dict[str, np.ndarray]]:
        states = list(states) if states is not None else [None] * len(parameter_sets)
        if self.start is not None:
            states = [self.start(model, data, ps) if x is None else x for ps, x in zip(parameter_sets, states)]
        return simulate_many(model, data, parameter_sets, states, device=self.device)
