"""The free run of an identification model: x' = A x + B ζ(x, t), ε = 0, driven by the recorded
``given`` channels (report eqs. 2.4–2.5 with the model errors set to zero) — the simulation the
diagnosis compares with a record (its noise floor's surrogates, the validation misfit) and that
users run to see a model's response.

Between samples the given channels are linear, so every step runs from one sample to the next
(no step straddles a kink).  The schemes are the engine's (:mod:`shootlab.bvp.integrators`).
Non-stiff on the sample grid: classical RK4, one step per sample interval.  Stiff: the two-stage
Radau IIA method (order 3, L-stable; Hairer & Wanner, *Solving ODEs II*, §IV.5) with
:data:`RADAU_SUBSTEPS` steps per sample interval, its stage equations solved by simplified Newton
with the Jacobian of the right-hand side taken once per sample interval and held over its steps,
stopped on the contraction's error estimate (§IV.8; ``Integrator.integrate``'s ``jacobian``).
LSODA over the whole record, which restarts at every sample's kink, is the fallback when the
Newton iteration does not converge.

Both schemes first run every sample interval at once (:func:`_shoot_samples`): the free run as
the engine's multiple-shooting problem with the samples as shooting points and the initial state
as its boundary condition (:func:`shootlab.bvp.solver.solve_together`), its matching conditions
solved by full Newton steps with the structured solve — a few calls of the right-hand side on T
rows instead of 4–10 calls on one row per sample, an order of magnitude faster.  The interval
Jacobians are the linearisation at each sample (the engine's ``jacobian="frozen"``: R(hJ)^steps,
R the scheme's stability function): one Jacobian of the right-hand side per sample and sweep,
exact for a model linear in its states (one step solves it), a quasi-Newton otherwise.  A run
whose sweeps do not converge over the whole record (a stiff one also with exact interval
Jacobians) is run in windows that shorten where they fail (:func:`_in_windows`), and only a
window of :data:`MIN_WINDOW` intervals that fails goes sample by sample.  The Jacobian of the
right-hand side comes from the least squares that determines ζ
(:class:`~shootlab.bvp.tangents.VectorField`), not from a least-squares solve per
central-difference probe.

:func:`simulate_many` runs several parameter sets (and starts) as rows of one batch: on models whose
right-hand side costs mostly per-call overhead, P runs cost about one — the columns of the
output-error Jacobian (:class:`FreeRun`, :mod:`shootlab.estimation.output_error`).
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from typing import Callable, Iterator, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .data import Interpolant, Measurements, with_filled_inputs
from .model import IdentificationModel, measured_states
from shootlab.bvp.integrators import Integrator, get_integrator
from shootlab.bvp.linalg import apply_qt, householder_qr
from shootlab.bvp.problem import BVP
from shootlab.bvp.solver import solve_together
from shootlab.bvp.spectrum import spectral_bounds
from shootlab.bvp.tangents import VectorField, rhs_jacobian

__all__ = ["simulate", "simulate_many", "FreeRun", "Work", "counted", "RK4_REACH", "RADAU_SUBSTEPS", "ROWS_PER_CALL"]


#: the free run's fixed RK4 step on the sample grid is taken only where ρ(∂s'/∂s)·h stays below
#: this (local error of the fastest mode ≲ 1e-4 per step; RK4 is stable to 2.78)
RK4_REACH = 0.5

#: Radau IIA steps per sample interval in a stiff free run: the fastest modes are damped (L-stable),
#: the slow ones resolved to a local error of order (h/4)⁴ — on the 6-element confined model with
#: 401 samples the free run agrees with LSODA (rtol 1e-8) to 8e-6 of the channels' range (3e-5 with
#: 3 elements, 2e-6 with 12: a hundredth of a 1 % noise), in a fraction of LSODA's time
RADAU_SUBSTEPS = 4


#: a call of a free run's right-hand side or of its Jacobian on R rows counts as 1 + R / ROWS_PER_CALL
#: calls (:class:`Work`): on the rig's and the pendulum's models a call on 1000 rows costs about
#: twice a call on one (1.6–1.7 times for the right-hand side, 2.2–2.6 for its Jacobian): the
#: per-call overhead against the work per row
ROWS_PER_CALL = 1000


class Work:
    """The work of the free runs made inside :func:`counted`, in right-hand-side calls
    (:data:`ROWS_PER_CALL`): the same count on any machine and under any load, where seconds are
    not — the pace by which :func:`shootlab.diagnosis.nested.nested_fits` decides whether a fit is
    worth trying."""

    def __init__(self) -> None:
        self.calls = 0.0

    def add(self, rows: int) -> None:
        self.calls += 1.0 + rows / ROWS_PER_CALL


_counting: list[Work] = []


@contextmanager
def counted() -> Iterator[Work]:
    """``with counted() as work:`` — ``work.calls`` is then the work of the free runs made inside."""
    work = Work()
    _counting.append(work)
    try:
        yield work
    finally:
        _counting.remove(work)


def _count(rows: int) -> None:
    for work in _counting:
        work.add(rows)


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
    square blocks.  A row with a non-finite entry (a run that has blown up) gets NaN, and LAPACK
    never sees it."""
    b = rs.unsqueeze(-1)
    bad = ~(torch.isfinite(Fs).flatten(-2).all(-1) & torch.isfinite(rs).all(-1))
    if bool(bad.any()):
        eye = torch.eye(Fs.shape[-2], Fs.shape[-1], dtype=Fs.dtype, device=Fs.device)
        ok = _least_squares_solution(torch.where(bad[..., None, None], eye, Fs), torch.where(bad[..., None], 0.0, rs))
        return torch.where(bad[..., None], math.nan, ok)
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


def _rk4() -> Integrator:
    """Classical RK4, one step per sample interval (the engine's :class:`~shootlab.bvp.integrators.RK4`)."""
    return get_integrator("rk4", steps=1)


def _radau(substeps: int = RADAU_SUBSTEPS, tol: float = 1e-10, max_newton: int = 20) -> Integrator:
    """The two-stage Radau IIA method with ``substeps`` steps per sample interval (the engine's
    :class:`~shootlab.bvp.integrators.Radau3`), its stage equations solved to the relative and
    absolute tolerance ``tol`` in at most ``max_newton`` simplified-Newton iterations."""
    return get_integrator("radau3", steps=substeps, rtol=tol, atol=tol, newton_maxiter=max_newton)


def _on_samples(integ: Integrator, rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor,
                check: Callable[[int, Tensor], bool] | None = None) -> Tensor | None:
    """The free run one sample interval after the other: ``integ`` from every sample to the next,
    all systems as rows of one batch; ``rhs(t (R,), S (R, n))`` on rows; ``s0`` (n,) → (T, n), or
    P systems at once: (P, n) → (T, P, n).  None where an integration fails (stage equations not
    converged, a non-finite state) or ``check(k, S_k)`` is False at a sample k."""
    single = s0.dim() == 1
    s = s0.reshape(1, -1) if single else s0
    out = [s]
    for k in range(ts.numel() - 1):
        if check is not None and not check(k, s):
            return None
        held = rhs_jacobian(rhs, ts[k].expand(s.shape[0]), s)[1] if integ.holds_jacobian else None
        res = integ.integrate(rhs, ts[k], ts[k + 1], s, jacobian=held)
        if bool(res.failed.any()) or not bool(torch.isfinite(res.y).all()):
            return None
        s = res.y
        out.append(s)
    if check is not None and not check(ts.numel() - 1, s):
        return None
    S = torch.stack(out)
    return S[:, 0] if single else S


def _rk4_on_samples(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor) -> Tensor | None:
    """The free runs of P systems (``s0`` (P, n); ``rhs(t (R,), S (R, n))`` on rows) by classical
    RK4 with one step per sample interval (between samples the given channels are linear, so the
    step sees no kink) — (T, P, n) — or None where that is not accurate (:func:`_too_stiff` at the
    start, middle and end of the record, on the way) or a state turns non-finite.
    Four right-hand sides per sample against ~26 for LSODA, which restarts at every sample's kink."""
    h = ts[1:] - ts[:-1]
    hmax = float(h.max()) if h.numel() else 0.0
    T = ts.numel()

    def accurate(k: int, s: Tensor) -> bool:
        return k not in (0, T // 2, T - 1) or T < 2 or not _too_stiff(rhs, ts[k], s, hmax)
    return _on_samples(_rk4(), rhs, s0, ts, accurate)


#: full Newton steps of a free run with all sample intervals at once (:func:`_shoot_samples`) before
#: it hands over to the run sample by sample, or this many without halving the least defect
#: (:func:`shootlab.bvp.newton.stalled`): from a constant start the defects of a non-linear run
#: first wander, rising again for a few steps before they fall (a forced Duffing oscillator over
#: ten periods: 7 steps before the least defect halves, 12 in all)
MAX_SWEEPS, STALLED_SWEEPS = 25, 8


def _shoot_samples(integ: Integrator, rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor,
                   tol: float = 1e-9, sweeps: int = MAX_SWEEPS, jacobian: str = "frozen") -> Tensor | None:
    """A free run with all sample intervals at once: multiple shooting of the initial-value problem
    on the sample grid (report eq. 3.2; the samples are the shooting points, the boundary
    conditions S_0 = s_0 and none at the end), by the engine's full Newton steps on the matching
    conditions (eq. 3.3) with the structured solve (:func:`shootlab.bvp.solver.solve_together`:
    the P systems' intervals as rows of one batch).  The interval Jacobians are the linearisation
    at each sample, Y_k = R(h_k J_k) for ``integ``'s stability function R (``jacobian="frozen"``:
    one Jacobian of ``rhs`` per sample and sweep, the same J_k held for an implicit scheme's Newton
    matrices) — or, with ``jacobian="autograd"``, the exact ∂y_k(t_{k+1})/∂s_k from the forward
    sensitivities of the same pass (about twice a frozen sweep's cost; Newton then converges
    quadratically where the frozen steps contract slowly).  From the constant start S_k = s_0 each
    sweep integrates every interval once; a model linear in its states is solved by the first step
    and confirmed by the next residual.
    A system stops when its defects pass the test max|d| ≤ tol (1 + max|S|), after one more
    correction from that sweep's Jacobian (the states then depend smoothly on the parameters, as a
    forward-difference Jacobian of the runs needs).  The same discrete scheme as the run sample by
    sample (:func:`_on_samples`), so the same states to the tolerance.  ``s0`` (n,) → (T, n), or
    (P, n) → (T, P, n); None when an integration fails, a Newton matrix is singular, the sweeps run
    out or stall (:data:`MAX_SWEEPS`; the caller then goes sample by sample)."""
    single = s0.dim() == 1
    s = s0.reshape(1, -1) if single else s0
    T = ts.numel()
    if T < 2:
        return None
    probs = [BVP(rhs, _starting_at(row), _no_condition, name="free run") for row in s]
    together = solve_together(probs, ts, [row.expand(T, -1) for row in s], integrator=integ.name,
                              steps=integ.steps, rtol=integ.rtol, atol=integ.atol, newton="undamped",
                              jacobian=jacobian, max_iter=sweeps, tol=tol, final_step=True, stall=STALLED_SWEEPS)
    if together is None or any(r is None or not r.success for r in together[0]):
        return None
    S = torch.stack([r.x for r in together[0]], 1)
    if not bool(torch.isfinite(S).all()):
        return None
    return S[:, 0] if single else S


def _starting_at(s0: Tensor) -> Callable[[Tensor], Tensor]:
    """The initial-value condition x(a) − s_0 = 0 of a free run."""
    return lambda x: x - s0


def _no_condition(x: Tensor) -> Tensor:
    """No condition at the end of a free run."""
    return x[:0]


def _rk4_in_parallel(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor,
                     sweeps: int = MAX_SWEEPS) -> tuple[Tensor | None, bool]:
    """The free run of :func:`_rk4_on_samples` with all sample intervals at once
    (:func:`_shoot_samples` with RK4), with the same test for stiffness at the start, middle and
    end of the record: (the run, False), or (None, whether it was found too stiff for RK4) where
    the test fails, a state turns non-finite or the sweeps run out."""
    s = s0.reshape(1, -1) if s0.dim() == 1 else s0
    if ts.numel() < 2:
        return None, False
    hmax = float((ts[1:] - ts[:-1]).max())
    if _too_stiff(rhs, ts[0], s, hmax):
        return None, True
    S = _shoot_samples(_rk4(), rhs, s0, ts, sweeps=sweeps)
    if S is None:
        return None, False
    return (None, True) if _stiff_on_the_way(rhs, S, ts, hmax) else (S, False)


def _stiff_on_the_way(rhs: Callable[[Tensor, Tensor], Tensor], S: Tensor, ts: Tensor, hmax: float) -> bool:
    """:func:`_too_stiff` at the middle and end of the run ``S`` (T, n) or (T, P, n)."""
    T = ts.numel()
    runs = S if S.dim() > 2 else S[:, None]
    return any(_too_stiff(rhs, ts[k], runs[k], hmax) for k in sorted({T // 2, T - 1}))


def _rk4_in_windows(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor) -> Tensor | None:
    """The RK4 free run in windows (:func:`_in_windows`; the shortest sample by sample), None where
    it fails or is too stiff for RK4 at the middle or end of the record."""
    S = _in_windows(lambda s, t: _shoot_samples(_rk4(), rhs, s, t), s0, ts,
                    lambda s, t: _rk4_on_samples(rhs, s, t))
    hmax = float((ts[1:] - ts[:-1]).max())
    return None if S is None or _stiff_on_the_way(rhs, S, ts, hmax) else S


#: the shortest window of sample intervals a free run in windows shoots at once (:func:`_in_windows`);
#: one this short that fails is run sample by sample
MIN_WINDOW = 8


def _in_windows(shoot: Callable[[Tensor, Tensor], Tensor | None], s0: Tensor, ts: Tensor,
                fallback: Callable[[Tensor, Tensor], Tensor | None]) -> Tensor | None:
    """A free run over consecutive windows of the record, each shot with all its sample intervals
    at once (``shoot(s, ts_window)``: (P, n) → (W + 1, P, n), None where it fails) from the state
    the one before ends in.  Where the sweeps over the whole record fail because the linearisation
    about the constant start carries its corrections too far — a run that is unstable or strongly
    non-linear: a pendulum whose friction, at a non-physical value an output-error fit tries,
    pumps energy in has defects of 1e143 after its first sweep — shorter stretches converge.  The
    first window is a quarter of the record; one that fails is cut to a quarter and tried again,
    one that converges lets the next be twice as long; one of :data:`MIN_WINDOW` intervals that
    fails is run by ``fallback`` (sample by sample).  ``s0`` (n,) → (T, n) or (P, n) → (T, P, n);
    None where the fallback fails."""
    single = s0.dim() == 1
    s = s0.reshape(1, -1) if single else s0
    parts, k, last = [s[None]], 0, ts.numel() - 1
    width = max(last // 4, MIN_WINDOW)
    while k < last:
        end = min(k + width, last)
        S = shoot(s, ts[k:end + 1])
        if S is None and width > MIN_WINDOW:
            width = max(width // 4, MIN_WINDOW)
            continue
        S = S if S is not None else fallback(s, ts[k:end + 1])
        if S is None:
            return None
        parts.append(S[1:])
        s, k, width = S[-1], end, 2 * width
    S = torch.cat(parts)
    return S[:, 0] if single else S


def _radau_on_samples(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor,
                      substeps: int = RADAU_SUBSTEPS, tol: float = 1e-10, max_newton: int = 20) -> Tensor | None:
    """The free run by the two-stage Radau IIA method (:func:`_radau`), one sample interval after
    the other (:func:`_on_samples`); ``s0`` (n,) → (T, n), or (P, n) → (T, P, n).  None when a
    stage iteration does not converge in ``max_newton`` steps or a state turns non-finite."""
    return _on_samples(_radau(substeps, tol, max_newton), rhs, s0, ts)


def _radau_in_parallel(rhs: Callable[[Tensor, Tensor], Tensor], s0: Tensor, ts: Tensor,
                       substeps: int = RADAU_SUBSTEPS, tol: float = 1e-10,
                       sweeps: int = MAX_SWEEPS) -> Tensor | None:
    """The free run of :func:`_radau_on_samples` with all sample intervals at once
    (:func:`_shoot_samples` with Radau IIA): by frozen interval Jacobians, and where their sweeps do
    not converge by exact ones (a stiff switching law, such as a Stribeck hump narrower than the
    motion: the frozen sweeps of the rig's Stribeck model with v_st = 0.2 do not converge in 25, while exact
    ones converge in 7, 15 times faster than the run sample by sample); None where a stage
    iteration fails, a state turns non-finite or both run out."""
    integ = _radau(substeps, tol)
    S = _shoot_samples(integ, rhs, s0, ts, sweeps=sweeps)
    return S if S is not None else _shoot_samples(integ, rhs, s0, ts, sweeps=sweeps, jacobian="autograd")


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

    ns, nx = len(model.states), model.nx
    # the integrated state y: the states s, θ held in the right-hand side — or, for several systems
    # in one batch, y = [s, p] with p the system's index (p' = 0), by which each row finds its θ:
    # the integrators' rows are independent (they drop finished rows and stack stage points), so a
    # row must carry what tells it apart.  y' and ∂y'/∂y are zero in p's row and column (θ is
    # constant in p between the integers, which p never leaves)
    k = ns if P == 1 else ns + 1

    def full(y: Tensor) -> Tensor:
        """x = [s, θ] for the rows y (R, k)."""
        if k == ns:
            return torch.cat([y, theta.expand(y.shape[0], -1)], -1)
        return torch.cat([y[:, :ns], theta[y[:, ns].round().long().clamp(0, P - 1)]], -1)

    Ay = torch.cat([A[:ns], A.new_zeros(k - ns, nx)])          # y' = Ay x + By ζ (p' = 0)
    By = torch.cat([B[:ns], B.new_zeros(k - ns, B.shape[1])])

    def rhs(tt: Tensor, y: Tensor) -> Tensor:
        """y' for the rows y (R, k) at times tt (R,)."""
        _count(y.shape[0])
        x = full(y)
        zeta, _, _ = zeta_of(x, tt)
        return x @ Ay.T + zeta @ By.T

    def jacobian(tt: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        """(y', ∂y'/∂y) at the rows y (R, k): f and F by central differences (the step of
        :func:`_jacobian`), and ζ's derivative from the least squares' own QR factor instead of a
        least-squares solve per probe — at full column rank of F_s, ζ = (F_sᵀF_s)⁻¹F_sᵀ r_s with
        r_s = z − f_s, so

            ∂ζ = (F_sᵀF_s)⁻¹ [F_sᵀ (−∂f_s − ∂F_s ζ) + ∂F_sᵀ (r_s − F_s ζ)].

        F is differenced along every state only where it moves along one random direction (on a
        model linear in its states it depends on the parameters alone), instead of one
        least-squares solve per probe of every state.
        A rank-deficient or under-determined F_s: central differences of the whole rhs."""
        _count(y.shape[0])
        x, s = full(y), y[:, :ns]
        R = y.shape[0]
        d = 1e-6 * (1.0 + s.abs())
        step = d[:, :, None] * torch.eye(ns, dtype=s.dtype, device=s.device)        # (R, ns, ns)

        def at(ds: Tensor) -> tuple[Tensor, Tensor]:        # x + [ds, 0] for ds (R, j, ns), times per row
            j = ds.shape[1]
            xp = (x[:, None, :] + torch.cat([ds, ds.new_zeros(R, j, nx - ns)], -1)).reshape(R * j, -1)
            return xp, tt[:, None].expand(R, j).reshape(-1)

        _, F0, Fs, r0 = least_squares(x, tt)
        regular = Fs.shape[-2] >= Fs.shape[-1]
        if regular:
            reflectors, tau, Rf = householder_qr(Fs)
            regular = _full_rank(Rf)
        if not regular:         # under-determined (the minimum-norm ζ) or rank-deficient: differences of the whole rhs
            J = _jacobian(rhs, tt, y)
            J[..., ns:] = 0.0
            return rhs(tt, y), J
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
        u = torch.linalg.solve_triangular(Rf.transpose(-1, -2), w, upper=False)
        dzeta = torch.linalg.solve_triangular(Rf, u, upper=True)                    # (R, nζ, ns)
        J = y.new_zeros(R, k, k)
        J[:, :ns, :ns] = A[:ns, :ns] + B[:ns] @ dzeta
        return x @ Ay.T + zeta @ By.T, J

    field = VectorField(rhs, jacobian)
    y0 = s0 if k == ns else torch.cat([s0, torch.arange(P, dtype=s0.dtype, device=dev)[:, None]], -1)

    S, stiff = _rk4_in_parallel(field, y0, ts)      # all sample intervals at once, else in windows
    if S is None and not stiff:
        S = _rk4_in_windows(field, y0, ts)
    if S is None:                   # stiff on the sample grid
        S = _radau_in_parallel(field, y0, ts)
        if S is None:
            integ = _radau()
            S = _in_windows(lambda s, t: _shoot_samples(integ, field, s, t), y0, ts,
                            lambda s, t: _radau_on_samples(field, s, t))
    if S is None and P > 1:         # an integration failed for some system: each alone
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
    S = S[..., :ns]
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
