"""Output-error estimation: the parameters θ that make the model's free run fit the record,

    min_θ  ½ Σ_c Σ_i ((y_c(t_i; θ) − z_c,i) / σ_c)²,

y_c the measured channel c predicted by the free run x' = A x + B ζ(x, t), ε = 0, driven by the
``given`` channels (:func:`shootlab.estimation.free_run.simulate`, or the model's own exact simulator,
``settings.simulate``), σ_c the channel's noise level from the record
(:func:`shootlab.estimation.data.noise_level`).  It is what CasADi + IPOPT direct multiple shooting solves in
the peers' benchmarks, and the companion of the report's optimal estimation (eq. 2.6), which also
admits model errors ε.  Where the TPBVP cannot be solved — the 50-element confined model, whose
fastest modes the implicit midpoint rule can no longer separate on 201 points — this is
the estimate; elsewhere it is a start for the TPBVP or a second opinion.

Gauss–Newton with a trust region (``scipy.optimize.least_squares``, method ``trf``) in log θ for
a parameter bounded to (0, ∞) (scale-free steps from a start off by a factor of ten), in θ
otherwise, inside the model's declared bounds; the Jacobian by forward differences
(:data:`DIFF_STEP`), its columns' free runs as one batch where the simulator can
(:func:`shootlab.estimation.free_run.simulate_many`).  The covariance is the linearised σ̂² (JᵀJ)⁻¹ with
σ̂² = 2 cost / (ν − p) — near 1 when the residuals are white noise at the record's level, so
``misfit_ratio`` = √σ̂² is also a first misfit measure.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from .data import Measurements, with_filled_inputs
from .model import IdentificationModel
from shootlab.bvp.newton import Status

__all__ = ["OutputErrorResult", "estimate_output_error", "Simulator", "DIFF_STEP", "termination"]

#: the forward-difference step, relative to each unknown: a free run is exact only to its
#: integrator's or matrix exponential's rounding (~1e-10 relative on the stiff confined model), so a
#: step near √ε leaves a Jacobian too poor to converge (on a noise-free 20-element record a step of
#: 1e-7 stopped short of the solution, 1e-5 reached it)
DIFF_STEP = 1e-5

#: what a failed free run raises (a trial point where the model cannot be integrated)
FAILED = (RuntimeError, ValueError, FloatingPointError, np.linalg.LinAlgError)

#: ``(model, data, parameters, initial_state or None) -> {channel: predicted samples at data.t}``;
#: one with a method ``many(model, data, [parameters], [initial_state or None])`` (a list of those
#: dicts, :class:`shootlab.estimation.free_run.FreeRun`) has the Jacobian's columns run as one batch
Simulator = Callable[[IdentificationModel, Measurements, Mapping[str, float], "np.ndarray | None"],
                     Mapping[str, np.ndarray]]


@dataclass
class OutputErrorResult:
    """The output-error estimate (module docstring).  ``status`` is a
    :class:`shootlab.bvp.newton.Status`, the shooting runs' own: CONVERGED when the trust-region
    iteration met a tolerance (:func:`termination`), MAX_ITER when it ran out of free runs,
    INTEGRATION_FAILED when the free run fails at the final parameters; ``success`` is
    ``status == CONVERGED``."""

    model: IdentificationModel
    parameters: dict[str, float]
    success: bool
    status: Status
    message: str
    cost: float                                   # ½ Σ (residual / σ)²
    samples: int                                  # ν: residuals in the cost
    evaluations: int                              # free runs, Jacobian columns included
    standard_errors: dict[str, float] = field(default_factory=dict)
    correlation: np.ndarray | None = None
    noise: dict[str, float] = field(default_factory=dict)       # σ_c used
    rms: dict[str, float] = field(default_factory=dict)         # RMS misfit / σ_c per channel
    predicted: dict[str, np.ndarray] = field(default_factory=dict)
    initial_state: np.ndarray | None = None                     # the fitted states at t₀ (fit_initial_state)
    seconds: float = 0.0

    @property
    def misfit_ratio(self) -> float:
        """√(2 cost / (ν − p)): about 1 for white residuals at the record's noise level."""
        dof = max(self.samples - len(self.parameters) - (0 if self.initial_state is None else self.initial_state.size), 1)
        return math.sqrt(2.0 * self.cost / dof)


def _default_simulator(model: IdentificationModel, device=None) -> Simulator:
    from .free_run import FreeRun
    return model.settings.simulate or FreeRun(device=device)


def estimate_output_error(model: IdentificationModel, data, initial: Mapping[str, float] | None = None,
                          simulator: Simulator | None = None, noise: Mapping[str, float] | None = None,
                          fit_initial_state: bool | None = None, tol: float = 1e-8, max_evaluations: int = 400,
                          log: Callable[[str], None] | None = None, device=None,
                          bounds: Mapping[str, tuple[float, float]] | None = None,
                          max_seconds: float | None = None, max_runs: int | None = None) -> OutputErrorResult:
    """The parameters θ whose free run fits the record: output error (module docstring).

    Parameters
    ----------
    model : IdentificationModel
        The model; its free run x' = A x + B ζ(x, t), ε = 0 is driven by its ``given`` channels.
    data : Measurements, str, path or dict of arrays
        The record (:meth:`Measurements.coerce`).
    initial : mapping of str to float, optional
        Initial parameter values; default the model's ``prior``.
    simulator : Simulator, optional
        The free run; default ``model.settings.simulate``, else
        :class:`~shootlab.estimation.free_run.FreeRun`.
    noise : mapping of str to float, optional
        σ_c per channel; default the record's noise level
        (:func:`shootlab.estimation.data.noise_level`).
    fit_initial_state : bool, optional
        Make the states at t₀ unknowns too (``initial_state`` of the result), started from the
        model's initial approximation; otherwise the free run starts there, which for a state
        read off the record by differentiation (a velocity) carries the differentiation's edge
        error into every sample.  Default: fitted unless the model brings its own simulator,
        which fixes its start.
    tol : float, optional
        Relative tolerance on the cost and on θ (default 1e−8).
    max_evaluations : int, optional
        Evaluations of the residual (``scipy.optimize.least_squares``' ``max_nfev``; the free runs
        of the batched Jacobian's columns are not counted), default 400.
    log : callable, optional
        Receives one line per iteration.
    device : str or torch.device, optional
        Where the default free run is integrated (``"cpu"`` default, ``"cuda"``, ``"auto"``); a
        simulator of the model's own or one passed in runs where it runs.
    bounds : mapping of str to (float, float), optional
        A box (low, high) for some parameters, beside (and before) the model's own ``bounds``: the
        fit is constrained to it, and may end on its edge.
    max_seconds : float, optional
        A time budget: the fit stops, not converged, after the first iteration that ends past it.
    max_runs : int, optional
        A budget of free runs (the Jacobian's columns counted): the fit stops, not converged, after
        the first iteration that ends past it — unlike ``max_seconds``, the same on every machine.

    Returns
    -------
    OutputErrorResult
        ``parameters``, ``success`` and ``status`` (:class:`~shootlab.bvp.newton.Status`),
        ``standard_errors`` and ``correlation`` (σ̂² (JᵀJ)⁻¹), ``rms`` misfit per channel over its
        noise level, the ``predicted`` channels.

    Raises
    ------
    ValueError
        Bad input, a parameter without an initial value, or a free run that fails at the start
        (naming the parameter values).  A free run that fails at a later trial point counts as a
        very poor fit there (the trust region shrinks).
    """
    from scipy.optimize import least_squares

    from .data import noise_level

    clock = time.perf_counter()
    data = with_filled_inputs(Measurements.coerce(data), model.given)
    data.require(model.measured, float(data.t[0]), float(data.t[-1]))
    if fit_initial_state is None:
        fit_initial_state = simulator is None and model.settings.simulate is None
    from shootlab.bvp.device import resolve_device

    simulator = simulator or _default_simulator(model, resolve_device(device))
    names = list(model.parameters)
    start = dict(model.prior, **(initial or {}))
    missing = [p for p in names if p not in start]
    if missing:
        raise ValueError(f"no initial value for {missing}: give them (initial=) or as the model's prior")
    outputs = [c for c in model.measured if c not in model.given]
    keep = {c: np.isfinite(data.channels[c]) for c in outputs}
    sigma = dict(noise) if noise is not None else noise_level(data, outputs)
    for c in outputs:
        if not sigma.get(c, 0.0) > 0:
            sigma[c] = max(float(np.std(data.channels[c][keep[c]])), 1e-12)
    # the unknowns q: log θ for a parameter bounded to (0, ∞), θ itself otherwise
    box = dict(model.bounds, **(bounds or {}))
    bounds = {p: tuple(float(v) for v in box.get(p, (-math.inf, math.inf))) for p in names}
    logged = [bounds[p] == (0.0, math.inf) for p in names]
    for p, lg in zip(names, logged):
        lo, hi = bounds[p]
        v = float(start[p])
        if not (math.isfinite(v) and lo < v < hi):
            raise ValueError(f"initial {p} = {v!r} is not inside its bounds ({lo:g}, {hi:g})")

    def theta(q: np.ndarray) -> dict[str, float]:
        return {p: float(np.exp(v) if lg else v) for p, v, lg in zip(names, q, logged)}

    np_ = len(names)
    q0 = np.array([math.log(float(start[p])) if lg else float(start[p]) for p, lg in zip(names, logged)])
    lo = np.array([-np.inf if lg else bounds[p][0] for p, lg in zip(names, logged)])
    hi = np.array([np.inf if lg else bounds[p][1] for p, lg in zip(names, logged)])
    if fit_initial_state:
        import torch
        from .model import measured_states
        t0 = torch.as_tensor(data.t[:1], dtype=torch.float64)
        s0 = (model.initial_states(data, t0) if model.initial_states else measured_states(model, data, t0))[0]
        q0 = np.concatenate([q0, s0.detach().cpu().numpy()])
        lo, hi = np.concatenate([lo, np.full(s0.numel(), -np.inf)]), np.concatenate([hi, np.full(s0.numel(), np.inf)])
    count = [0]
    nres = sum(int(k.sum()) for k in keep.values())

    def predicted(q: np.ndarray) -> dict[str, np.ndarray]:
        count[0] += 1
        return simulator(model, data, theta(q), q[np_:] if fit_initial_state else None)

    def misfit(y: Mapping[str, np.ndarray]) -> np.ndarray:
        r = np.concatenate([((np.asarray(y[c]) - data.channels[c]) / sigma[c])[keep[c]] for c in outputs])
        return r if np.isfinite(r).all() else np.full(nres, 1e10)

    def residual(q: np.ndarray) -> np.ndarray:
        try:
            return misfit(predicted(q))
        except FAILED:
            return np.full(nres, 1e10)

    many = getattr(simulator, "many", None)

    def jacobian(q: np.ndarray) -> np.ndarray:
        """Forward differences (step :data:`DIFF_STEP` relative, turned back inside the bounds), the
        base point and every column in one batched free run (``simulator.many``)."""
        h = DIFF_STEP * np.where(q >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(q))
        h = (q + h) - q
        out = (q + h > hi) | (q + h < lo)
        h[out] = -h[out]
        qs = [q, *(q + np.diag(h))]
        count[0] += len(qs)
        try:
            runs = many(model, data, [theta(x) for x in qs], [x[np_:] if fit_initial_state else None for x in qs])
            rs = [misfit(y) for y in runs]
        except FAILED:
            rs = [residual(x) for x in qs]
        return np.stack([(r - rs[0]) / hj for r, hj in zip(rs[1:], h)], 1)

    r0 = residual(q0)
    if not (r0 < 1e10).all():
        raise ValueError(f"the free run fails at the initial parameters {theta(q0)}: choose another start")
    iterations, stopped = [0], [""]

    def progress(intermediate_result):
        iterations[0] += 1
        if log is not None:
            values = ", ".join(f"{p} = {v:.6g}" for p, v in theta(intermediate_result.x).items())
            log(f"output error {iterations[0]:3d}: {values}, cost {intermediate_result.cost:.6g}, "
                f"{time.perf_counter() - clock:.1f} s")
        if max_seconds is not None and time.perf_counter() - clock > max_seconds:
            stopped[0] = f"its time budget of {max_seconds:.3g} s"
        if max_runs is not None and count[0] > max_runs:
            stopped[0] = f"its budget of {max_runs} free runs"
        if stopped[0]:
            raise StopIteration
    fit = least_squares(residual, q0, jac=jacobian if many is not None else "2-point", bounds=(lo, hi),
                        method="trf", x_scale="jac", diff_step=DIFF_STEP, ftol=tol, xtol=tol, gtol=tol,
                        max_nfev=max_evaluations, callback=progress)
    params = theta(fit.x)
    s0_hat = fit.x[np_:].copy() if fit_initial_state else None
    status, message = termination(fit.status, bool((fit.fun < 1e10).all()), tol, iterations[0], count[0],
                                  max_evaluations, stopped[0])
    success = status == Status.CONVERGED
    if not success:
        message += f" (at {', '.join(f'{p} = {v:.6g}' for p, v in params.items())})"
    se, corr = _standard_errors(fit, nres, params, logged)
    if not se:
        message += "; the parameters are not separately identifiable from this record (JᵀJ is singular)"
    y = simulator(model, data, params, s0_hat) if success else {}
    rms = {c: float(np.sqrt(np.mean(((np.asarray(y[c]) - data.channels[c]) / sigma[c])[keep[c]] ** 2)))
           for c in outputs} if y else {}
    return OutputErrorResult(model=model, parameters=params, success=success, status=status,
                             message=message, cost=float(fit.cost), samples=nres, evaluations=count[0],
                             standard_errors=se, correlation=corr, noise=sigma, rms=rms, initial_state=s0_hat,
                             predicted={c: np.asarray(y[c]) for c in outputs} if y else {},
                             seconds=time.perf_counter() - clock)


#: what each of ``scipy.optimize.least_squares``' successful statuses says (relative tolerance ``tol``)
_MET = {1: "the gradient's max-norm below {tol:g}", 2: "the relative change of the cost below {tol:g}",
        3: "the relative step below {tol:g}", 4: "the relative change of the cost and the step below {tol:g}"}


def termination(scipy_status: int, finite: bool, tol: float, iterations: int, evaluations: int,
                max_evaluations: int, budget: str = "its budget") -> tuple[Status, str]:
    """The :class:`~shootlab.bvp.newton.Status` and one-line message of an output-error fit from
    ``scipy.optimize.least_squares``' status (1–4: a tolerance met, 0: ``max_nfev`` reached, −2:
    stopped at the ``budget`` it names: time or free runs) and
    whether the free run at its last point is ``finite``: ``converged: … after k iterations (n free
    runs)`` as the shooting runs say it."""
    runs = f"after {iterations} iterations ({evaluations} free runs)"
    if not finite:
        return Status.INTEGRATION_FAILED, f"not converged: the free run fails or overflows at the last point, {runs}"
    if scipy_status in _MET:
        return Status.CONVERGED, f"converged: {_MET[scipy_status].format(tol=tol)} {runs}"
    if scipy_status == 0:
        return Status.MAX_ITER, f"not converged: {max_evaluations} evaluations (max_evaluations) reached, {runs}"
    if scipy_status == -2:
        return Status.MAX_ITER, f"not converged: stopped at {budget}, {runs}"
    raise ValueError(f"scipy.optimize.least_squares returned status {scipy_status}")


def _standard_errors(fit, samples: int, params: dict[str, float], logged: list[bool]
                     ) -> tuple[dict[str, float], np.ndarray | None]:
    """Standard errors and correlation of θ from the linearised covariance σ̂² (JᵀJ)⁻¹ of the
    unknowns q (σ̂² = 2 cost / (ν − dim q)), mapped to θ (dθ = θ dq for a logged parameter); empty
    when JᵀJ is singular."""
    n, p = fit.x.size, len(params)
    JtJ = fit.jac.T @ fit.jac
    if np.linalg.matrix_rank(JtJ) < n:
        return {}, None
    s2 = 2.0 * fit.cost / max(samples - n, 1)
    d = np.array([v if lg else 1.0 for v, lg in zip(params.values(), logged)])
    cov = (s2 * np.linalg.inv(JtJ))[:p, :p] * np.outer(d, d)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        return {k: float(v) for k, v in zip(params, sd)}, cov / np.outer(sd, sd)
