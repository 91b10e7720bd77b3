"""Optimal estimation: a model in augmented state form → the TPBVP of its optimality conditions.

Identification model (report eqs. 2.4–2.5), x = states and constant parameters, ζ = input
estimates, ε and ξ residuals::

    x' = A x + B ζ + ε
    E z_m(t) = f(x, t) + F(x, t) ζ + ξ          (model equations as zero pseudo-measurements
                                                 and the real measurement equations)

    J = ½ (x(a) − q_a)ᵀ W_a (x(a) − q_a) + ½ ∫ₐᵇ (εᵀ W ε + ξᵀ V ξ) dt                (eq. 2.6)

Stationarity of J gives the TPBVP of eq. 2.7 in (x, λ), 2·dim(x) equations, built by
:class:`shootlab.estimation.optimality.EstimationProblem` (its right-hand side, Jacobian and boundary
conditions); this module holds the model, the initial approximation, :func:`estimate` (multiple
shooting on that TPBVP, weight continuation) and the free-run :func:`simulate`.
"""
from __future__ import annotations

import contextlib
import inspect
import math
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .data import Measurements, with_filled_inputs
from .model import IdentificationModel, measured_states
from .optimality import EstimationProblem
from shootlab.bvp.problem import as_tensor
from shootlab.bvp.newton import NEWTON, Status
from shootlab.bvp.shooting import local_spectrum
from . import weights
from shootlab.bvp.solver import ShootingResult, solve


# -- estimation ----------------------------------------------------------------------------
@dataclass
class EstimationResult:
    """Outcome of :func:`estimate`."""

    success: bool
    message: str
    parameters: dict[str, float]
    J: float
    t: Tensor                       # data sample times inside [a, b]
    x: dict[str, Tensor]            # smoothed states and parameter trajectories at t
    zeta: dict[str, Tensor]
    eps: dict[str, Tensor]          # ε per state/parameter
    xi: dict[str, Tensor]           # ξ per equation row
    shooting: ShootingResult
    problem: EstimationProblem
    seconds: float
    points: int
    #: the Newton strategies tried, in order, each from the same start (:func:`solve_falling_back`):
    #: newton, success, status, message, iterations, jacobian_evaluations, residual_norm, seconds
    attempts: list[dict] = field(default_factory=list)
    _uncertainty: object = field(default=None, repr=False)
    #: where the progress line of the covariance goes (:func:`phase`; None: nowhere)
    log: Callable[[str], None] | None = field(default=None, repr=False)

    @property
    def iterations(self) -> int:
        return self.shooting.iterations

    @property
    def uncertainty(self):
        """Linearised covariance of the parameters (:func:`shootlab.estimation.uncertainty.parameter_covariance`:
        Cov θ̂ = Σ_c σ̂_c² G_c G_cᵀ, G_c = dθ̂/dz_c), computed on first use; ``None`` for a
        failed estimate or when the Newton matrix at the solution is singular."""
        if self._uncertainty is None and self.success:
            from shootlab.bvp.linalg import SingularJacobianError
            from .uncertainty import parameter_covariance
            try:
                with phase(f"covariance of the parameters from {self.t.numel()} samples", self.log):
                    self._uncertainty = parameter_covariance(self)
            except (SingularJacobianError, RuntimeError):
                self._uncertainty = False
        return self._uncertainty or None

    @property
    def standard_errors(self) -> dict[str, float]:
        """Standard error of every parameter (NaN when not available, see :attr:`uncertainty`)."""
        u = self.uncertainty
        return u.standard_errors if u is not None else {p: float("nan") for p in self.parameters}

    @property
    def covariance(self) -> np.ndarray:
        """(p, p) covariance of the parameters, order ``problem.model.parameters`` (NaN when not available)."""
        u = self.uncertainty
        return u.covariance if u is not None else np.full((len(self.parameters),) * 2, np.nan)

    @property
    def correlation(self) -> np.ndarray:
        """(p, p) correlation matrix of the parameters (NaN when not available)."""
        u = self.uncertainty
        return u.correlation if u is not None else np.full((len(self.parameters),) * 2, np.nan)

    def simulate(self, data=None, parameters: Mapping[str, float] | None = None,
                 initial_state: Sequence[float] | None = None) -> dict[str, np.ndarray]:
        """Free-run prediction of the measured channels with θ̂ (or ``parameters``).

        ``data``: measurements holding at least the model's ``given`` channels (default: the
        identification data, starting from the estimated state x̂(a)).  On other data the
        states start from ``initial_state`` if given (e.g. at rest), else from the model's
        initial approximation; ζ follows from the model equations and the given channels.
        """
        from .free_run import simulate
        if data is None and initial_state is None:
            initial_state = [float(self.x[name][0]) for name in self.problem.model.states]
        return simulate(self.problem.model, data if data is not None else self.problem.data,
                        dict(self.parameters, **(parameters or {})), initial_state)


def initial_approximation(model: IdentificationModel, data: Measurements, t: Tensor,
                          initial: Mapping[str, float] | None = None,
                          log: Callable[[str], None] | None = None) -> Tensor:
    """(m, 2 nx): states from the data (model.initial_states), parameters from the prior
    overridden by ``initial``, costates λ = 0 (the report's choice).  ``log`` (progress lines)
    goes to the model's ``initial_parameters`` hook if it takes a ``log`` argument."""
    params = dict(model.prior)
    for k, v in (initial or {}).items():
        if k not in model.parameters:
            raise ValueError(f"unknown parameter {k!r} for model {model.name!r}; it has {model.parameters}")
        params[k] = float(v)
    missing = [p for p in model.parameters if p not in params]
    if missing:
        raise ValueError(f"no initial value for parameter(s) {missing}")
    prepare = model.settings.prefit
    if prepare is not None:     # the model's own check (ValueError) or refinement of the values
        extra = {"log": log} if log is not None and "log" in inspect.signature(prepare).parameters else {}
        params = dict(prepare(data, dict(params), t, **extra) or params)
    states = model.initial_states(data, t) if model.initial_states else measured_states(model, data, t)
    states = as_tensor(states, name="initial states").to(dtype=t.dtype, device=t.device)
    theta = torch.tensor([params[p] for p in model.parameters], dtype=t.dtype, device=t.device)
    X = torch.cat([states, theta.expand(t.numel(), -1), t.new_zeros(t.numel(), model.nx)], -1)
    return X


def warm_start(model: IdentificationModel, previous: EstimationResult, t: Tensor, X0: Tensor) -> Tensor:
    """Initial approximation from a previous estimate (another model, weights or grid): every
    state, parameter and costate that the two models share by name is taken from ``previous``
    at t; the rest stays as in ``X0``.  This is the report's remedy for weights that are hard to
    start from: solve with easier ones, then restart from that solution (§4.2)."""
    old, shot = previous.problem.model, previous.shooting
    tq = t.clamp(shot.t[0], shot.t[-1])
    # on the same grid its shooting points themselves (the last one too: sol would integrate the
    # last interval to it — 40 stage evaluations of one row, a tenth of a diagnosis's one-step)
    tq = tq.to(shot.t)
    Xp = shot.x if tq.shape == shot.t.shape and torch.equal(tq, shot.t) else shot.sol(tq)
    Xp = Xp.to(X0)
    X0 = X0.clone()
    for j, name in enumerate(model.names):
        if name in old.names:
            i = old.names.index(name)
            X0[:, j], X0[:, model.nx + j] = Xp[:, i], Xp[:, old.nx + i]
    return X0


def estimate(model: IdentificationModel | str, data, n_points: int | None = None, initial: Mapping[str, float] | None = None,
             interval: tuple[float, float] | None = None, start: EstimationResult | None = None,
             device: str | torch.device | None = None, dtype: torch.dtype | None = None,
             fallback: bool | None = None, **solve_options) -> EstimationResult:
    """Estimate the states, inputs and parameters of ``model`` from ``data`` (optimal estimation).

    Minimises J = ½ (x(a) − q_a)ᵀ W_a (x(a) − q_a) + ½ ∫ₐᵇ (εᵀWε + ξᵀVξ) dt (report eq. 2.6) for
    the model x' = A x + B ζ + ε, E z_m = f(x, t) + F(x, t) ζ + ξ by solving the TPBVP of its
    optimality conditions (eq. 2.7) with :func:`shootlab.solve`; the parameters are states with
    θ' = ε_θ.

    Parameters
    ----------
    model : IdentificationModel or str
        The model, or an installed name (e.g. ``"msd"``; :func:`~.lookup.resolve_model`).
    data : Measurements, str, path or dict of arrays
        The record: ``t`` and the model's measured channels (:meth:`Measurements.coerce`).  Gaps in
        a given (driving) channel are filled where the fill's error allows.
    n_points : int, optional
        Equidistant shooting points on ``interval``; default :func:`default_points` (the model's
        ``settings.points``, more on a record longer than the one they were chosen for).
    initial : mapping of str to float, optional
        Initial parameter values, over the model's prior (and over ``start``'s).
    interval : (float, float), optional
        The time range [a, b] to estimate on; default the record's.
    start : EstimationResult, optional
        Warm start from a previous estimate (:func:`warm_start`).
    device : str or torch.device, optional
        Where the TPBVP is solved: ``"cpu"`` (default), ``"cuda"`` or ``"auto"``
        (:func:`shootlab.bvp.device.resolve_device`); the record is moved there once and the
        result's series come back to the CPU.
    dtype : torch.dtype, optional
        Default float64.
    fallback : bool, optional
        Where the Newton iteration stalls, try the strategies of :data:`FALLBACK` in turn from the
        same start (:func:`solve_falling_back`, recorded in ``attempts``), also when ``newton`` is
        given; in a weight continuation every stage falls back alike.  Default
        ``model.settings.fallback`` (True).
    **solve_options
        Options of :func:`shootlab.solve` (``integrator``, ``steps``, ``newton``, ``tol``,
        ``max_iter``, ``verbose``, …), over the model's ``settings.solver``.  With ``verbose``,
        phases longer than :data:`PHASE_SECONDS` report on stderr (:func:`phase`).

    Returns
    -------
    EstimationResult
        ``success``, ``message``, ``parameters``, ``J``; the smoothed states ``x``, inputs
        ``zeta`` and residuals ``eps``, ``xi`` at the samples; ``standard_errors``,
        ``covariance``, ``correlation`` (linearised, on first use); ``simulate(data)``; the
        ``shooting`` result and the ``attempts``.  A failed solve is returned with
        ``success=False``; where the intervals are long for the local Jacobian's time scales its
        message names a number of shooting points to try.

    Raises
    ------
    ValueError
        Bad input: an unknown model name, a record without the model's channels, too few
        samples, an unknown option.
    """
    from shootlab.bvp.device import resolve_device

    dev = resolve_device(device)
    if isinstance(model, str):
        from .lookup import resolve_model
        model = resolve_model(model)
    solve_options = _solver_options(model, solve_options)
    data = with_filled_inputs(Measurements.coerce(data), model.given, cover=interval)
    model = weights.from_data(model, data)
    if n_points is None:
        n_points = default_points(model, data, interval, initial)
    stages = weight_stages(model, model.settings.weight_continuation)
    if fallback is None:
        fallback = bool(model.settings.fallback)
    if stages and start is None:        # continuation in the weights (report §4.2), each stage warm
        start = continue_in_weights(stages, data, n_points, initial, interval,
                                    dict(solve_options, device=dev, dtype=dtype, fallback=fallback), final=False)
        if not start.success:
            return start
        initial = None
    verbose = solve_options.get("verbose", False)
    prob, t, X0, (a, b) = posed(model, data, n_points, initial, interval, start, verbose, device=dev, dtype=dtype)
    clock = time.perf_counter()
    res, attempts = solve_falling_back(prob.bvp(), t, X0, solve_options, fallback)
    seconds = time.perf_counter() - clock
    if not res.success:
        res.message += _more_points_hint(res, prob, t, X0)
    out = summarise(prob, res, a, b, seconds, log=progress_line if verbose else None)
    out.attempts = attempts
    return out


#: |λ|max·h of a shooting interval that :func:`default_points` keeps on a record longer than the
#: one the model's points were chosen for (unless the model's own grid is coarser).  On the
#: mass–spring–damper a twice longer interval stops at the damping floor, from m = b = k = 10 on a
#: 200 s record and from m = b = k = 50 on 10 s.
INTERVAL_GROWTH = 0.5


def default_points(model: IdentificationModel, data, interval: tuple[float, float] | None = None,
                   initial: Mapping[str, float] | None = None) -> int:
    """The number of shooting points of an estimate when none is given: the model's declared
    ``points`` P (``settings.points``), or more on a record longer than the one
    they were chosen for.

    The rule: the record's length T = b − a against the model's time scales, the eigenvalues λ
    of the local Jacobian ∂f/∂x of the TPBVP (eq. 2.7) at the initial approximation on the
    P-point grid (states from the data, parameters from the prior and ``initial``, costates 0;
    the model's ``prefit`` stage is not run for this probe).  A model that declares
    the record length its P points were chosen for (``settings.span``) keeps, on a longer
    record, intervals with |λ|max·h ≤ C, where

        C = max(INTERVAL_GROWTH, |λ|max·span/(P − 1))                     (:func:`_growth_bound`)

    is the |λ|max·h of the grid the model was tuned on, but no finer than
    :data:`INTERVAL_GROWTH` = 0.5 (a mode changes by at most e^0.5 over an interval, and
    Newton's linearisation of an interval holds from far parameter values):

        m = max(P, 1 + ⌈|λ|max·T / C⌉).

    The mass–spring–damper (P = 101 for 10 s, |λ|max ≈ 1, C = 0.5): 101 points on 10 s, 409 on
    200 s, 4073 on 2000 s.  Without ``span``, or on a record no longer than it, P stands: its
    count is the model's choice for its own time scales (the rig: |λ|max·h = 3.2 on its 1 s
    record, the confined compression with its tolerance continuation: 12).  Raises ValueError
    for data that lack the model's channels on the interval (as :func:`estimate`)."""
    data = Measurements.coerce(data)
    model = weights.from_data(model, data)
    P = model.settings.points
    a, b = interval if interval is not None else (float(data.t[0]), float(data.t[-1]))
    span = model.settings.span
    if span is None or not b - a > float(span) or P < 2:
        return P
    data.require(model.measured, a, b)
    data.require_samples(model, a, b)
    lam = _probe_eigenvalues(model, data, P, (a, b), initial)
    rho = float(lam.abs().max()) if lam.numel() else 0.0
    if not rho > 0:
        return P
    return max(P, 1 + math.ceil(rho * (b - a) / _growth_bound(model, rho, b - a)))


def _growth_bound(model: IdentificationModel, rho: float, T: float) -> float:
    """C of :func:`default_points`: the |λ|max·h of the model's own grid — its ``points`` on its
    ``span`` (on the record's length T where it declares none or T is shorter) — but at least
    :data:`INTERVAL_GROWTH`; ``rho`` = |λ|max."""
    P = model.settings.points
    span = model.settings.span
    tuned = float(span) if span is not None and T > float(span) else T
    return max(INTERVAL_GROWTH, rho * tuned / max(P - 1, 1))


def _probe_eigenvalues(model: IdentificationModel, data: Measurements, points: int, interval: tuple[float, float],
                       initial: Mapping[str, float] | None) -> Tensor:
    """The eigenvalues (complex, flat) of ∂f/∂x at the initial approximation on ``points``
    equidistant points of ``interval``, those of the points where they are finite: the probe of
    :func:`default_points` (the model's ``prefit`` stage is not run for it)."""
    from shootlab.bvp.suggest import local_eigenvalues

    probe = replace(model, settings=model.settings.replace(prefit=None))
    t = torch.linspace(interval[0], interval[1], int(points), dtype=torch.float64)
    X = initial_approximation(probe, data, t, initial)
    lam = local_eigenvalues(EstimationProblem(probe, data).bvp().rhs, t, X)
    return lam[torch.isfinite(lam).all(-1)].reshape(-1)


def _more_points_hint(res: ShootingResult, prob: EstimationProblem, t: Tensor, X0: Tensor) -> str:
    """For a solve that stopped on a singular Newton matrix, at the damping floor or on intervals
    too long for the growth at the guess, on intervals long for the local Jacobian's time scales
    at the initial approximation — |λ|max·h above the bound C of :func:`default_points` (the
    model's own grid, at least :data:`INTERVAL_GROWTH`): the advice to use more points, the count
    that keeps |λ|max·h ≤ C (at least twice the intervals); '' otherwise."""
    if res.status not in (Status.SINGULAR, Status.STEP_TOO_SMALL, Status.INTERVALS_TOO_LONG):
        return ""
    with torch.no_grad():
        rho = local_spectrum(prob.bvp(), t, X0)[0]
    rho = float(rho[torch.isfinite(rho)].max()) if bool(torch.isfinite(rho).any()) else 0.0
    T, m = float(t[-1] - t[0]), t.numel()
    bound = _growth_bound(prob.model, rho, T)
    if not rho * T / (m - 1) > bound:
        return ""
    more = max(2 * (m - 1) + 1, 1 + math.ceil(rho * T / bound))
    return (f"; the {m - 1} intervals are long for the problem's time scales (|λ|max·h = {rho * T / (m - 1):.3g} "
            f"at the initial approximation): try more shooting points, e.g. --points {more} (n_points={more})")


#: a phase of an estimate that runs longer than this reports on the progress log (:func:`phase`)
PHASE_SECONDS = 2.0


def progress_line(line: str) -> None:
    """A progress line on stderr (the log of :func:`phase` in a verbose estimate)."""
    print(line, file=sys.stderr, flush=True)


@contextlib.contextmanager
def phase(what: str, log: Callable[[str], None] | None, after: float | None = None):
    """Progress of a phase of an estimate (the summary, the covariance, writing the results):
    ``-- what ...`` on ``log`` once it has run ``after`` seconds (:data:`PHASE_SECONDS`), and
    ``-- what: N.N s`` when it ends — both only for a phase that long; nothing without ``log``."""
    if log is None:
        yield
        return
    after = PHASE_SECONDS if after is None else after
    clock = time.perf_counter()
    timer = threading.Timer(after, log, args=(f"-- {what} ...",))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        took = time.perf_counter() - clock
        if took > after:
            log(f"-- {what}: {took:.1f} s")


#: the Newton strategies :func:`solve_falling_back` tries, in this order, after the first stalls
FALLBACK = ("armijo", "trust_region")


def solve_falling_back(bvp, t: Tensor, X0: Tensor, options: Mapping, fallback: bool = True
                       ) -> tuple[ShootingResult, list[dict]]:
    """``solve(bvp, t, X0, **options)``; where its Newton strategy stalls — damping or step below
    its floor, no progress (status STEP_TOO_SMALL), or a singular Newton matrix at an iterate it
    stepped to (SINGULAR after an accepted step) — and ``fallback``, the strategies of
    :data:`FALLBACK` other than that one in turn, each from X0, until one converges.  A maximum
    of iterations, an integration failure, a singular matrix at the start itself and the fixed
    steps of ``undamped`` are answered as they are.  Each switch is a progress line where
    ``options["verbose"]``.  Returns the converged result (its message naming the strategy), or
    the first strategy's with the others' failures appended, and one record per attempt."""
    res = solve(bvp, t, X0, **options)
    first = _newton_name(options.get("newton", "deuflhard"))
    attempts = [_attempt(first, res)]
    stalled = res.status == Status.STEP_TOO_SMALL or (res.status == Status.SINGULAR and len(res.history) > 1)
    if res.success or not fallback or not stalled or first == "undamped":
        return res, attempts
    failed, verbose = [(first, res)], options.get("verbose", False)
    for name in (n for n in FALLBACK if NEWTON[n].name != first):
        if verbose:
            print(f"{failed[-1][0]} stopped: {_why(failed[-1][1])}; trying newton={name} from the same start ...",
                  flush=True)
        alt = solve(bvp, t, X0, **_with_newton(options, name))
        attempts.append(_attempt(name, alt))
        if alt.success:
            alt.message += f" (newton={name}; " + ", ".join(n for n, _ in failed) + " stopped)"
            return alt, attempts
        failed.append((name, alt))
    res.message += "; the fallbacks stopped too: " + "; ".join(f"{n}: {_why(r)}" for n, r in failed[1:])
    return res, attempts


def _newton_name(newton) -> str:
    """The canonical name of a strategy given by name or as an object."""
    return NEWTON[newton].name if isinstance(newton, str) and newton in NEWTON else getattr(newton, "name", str(newton))


def _why(res: ShootingResult) -> str:
    """A failed solve's message without its advice (the part from "; try")."""
    return res.message.split("; try")[0]


def _with_newton(options: Mapping, name: str) -> dict:
    """``options`` with the Newton strategy ``name`` and its default options, in every continuation
    stage too."""
    out = dict(options, newton=name, newton_options={})
    if options.get("continuation"):
        out["continuation"] = [{k: v for k, v in stage.items() if k not in ("newton", "newton_options")}
                               for stage in options["continuation"]]
    return out


def _attempt(name: str, res: ShootingResult) -> dict:
    return dict(newton=name, success=res.success, status=int(res.status), message=res.message,
                iterations=res.iterations, jacobian_evaluations=res.jacobian_evaluations,
                residual_norm=res.residual_norm, seconds=res.seconds)

def posed(model: IdentificationModel, data: Measurements, n_points: int, initial: Mapping[str, float] | None,
          interval: tuple[float, float] | None, start: EstimationResult | None, verbose: bool = False,
          device: torch.device | None = None, dtype: torch.dtype | None = None
          ) -> tuple[EstimationProblem, Tensor, Tensor, tuple[float, float]]:
    """The TPBVP of an estimate (:func:`estimate`, without its weight continuation): the problem,
    the grid of ``n_points`` shooting points on ``interval``, the initial approximation there (warm
    from ``start`` when given, ``initial`` over its parameters) and the interval — each checked."""
    a, b = interval if interval is not None else (float(data.t[0]), float(data.t[-1]))
    if not b > a:
        raise ValueError(f"empty interval [{a}, {b}]")
    data.require(model.measured, a, b)
    if int(n_points) < 2:
        raise ValueError(f"n_points must be at least 2, got {n_points}")
    data.require_samples(model, a, b)
    dtype = dtype or torch.float64
    prob = EstimationProblem(model, data, dtype=dtype, device=device)
    t = torch.linspace(a, b, int(n_points), dtype=dtype, device=device)
    X0 = initial_approximation(model, data, t, initial, log=print if verbose else None)
    if verbose and model.settings.prefit is not None and start is None:
        given = dict(model.prior, **{k: float(v) for k, v in (initial or {}).items()})
        used = {p: float(X0[0, model.names.index(p)]) for p in model.parameters}
        if used != given:
            print("initial parameters refined by the model: "
                  + ", ".join(f"{p} {given[p]:.6g} -> {used[p]:.6g}" for p in used), flush=True)
    if start is not None:
        X0 = warm_start(model, start, t, X0)
        for k, v in (initial or {}).items():
            X0[:, model.names.index(k)] = float(v)
    prob.check_regular(t, X0)
    return prob, t, X0, (a, b)


def _solver_options(model: IdentificationModel, options: Mapping) -> dict:
    """The options of :func:`shootlab.solve` for an estimate of ``model``: its ``settings.solver``,
    the given ``options`` over them."""
    return {**model.settings.solver, **options}


def weight_stages(model: IdentificationModel, levels: Sequence[float] | None,
                  rows: Sequence[int] | None = None) -> list[IdentificationModel]:
    """The easier models of a continuation in the weights (report §4.2): ``model`` with the entries
    ``rows`` (indices of its equations; default all) of its constant diagonal V capped at each of
    ``levels`` below their largest, in increasing order — none where V is not a constant vector.
    The stages do not continue in the weights again (``settings.weight_continuation`` None); they
    are estimated in turn by :func:`continue_in_weights`."""
    if not levels or callable(model.V) or as_tensor(model.V, name="V").ndim != 1:
        return []
    V = as_tensor(model.V, name="V").tolist()
    capped = set(range(len(V)) if rows is None else rows)
    top = max((V[i] for i in capped), default=-math.inf)
    settings = model.settings.replace(weight_continuation=None)
    return [replace(model, V=[min(v, float(lv)) if i in capped else v for i, v in enumerate(V)], settings=settings)
            for lv in sorted(levels) if float(lv) < top]


#: the Newton tolerance of a weight continuation's stages before the last (:func:`continue_in_weights`)
STAGE_TOL = 1e-6


def continue_in_weights(stages: Sequence[IdentificationModel], data, n_points: int | None,
                        initial: Mapping[str, float] | None, interval, solve_options: dict,
                        final: bool = True) -> EstimationResult:
    """Estimate the easier models ``stages`` in turn, each from the previous solution: the report's
    remedy for weights that are hard to start from (§4.2; the diagnosis's weight-continuation
    estimator runs its stages here too).  A stage that only starts the next one stops at the Newton
    tolerance :data:`STAGE_TOL` (or the given one, if looser); the last, where ``final``, at the
    given one.  The last stage's result; a failed stage is returned at once, its message naming
    the stage."""
    prev = None
    for i, stage in enumerate(stages):
        opts = solve_options
        if not (final and i == len(stages) - 1):
            given = _solver_options(stage, solve_options).get("tol")
            opts = dict(solve_options, tol=max(STAGE_TOL, given or 0.0))
        res = estimate(stage, data, n_points, initial=initial if prev is None else None, interval=interval,
                       start=prev, **opts)
        if solve_options.get("verbose"):
            print(f"-- weight continuation stage {i + 1}/{len(stages)}: {res.message}", flush=True)
        if not res.success:
            res.message = f"weight continuation stage {i + 1}/{len(stages)}: {res.message}"
            return res
        prev = res
    return prev


def sample_times(prob: EstimationProblem, a: float, b: float) -> Tensor:
    """The record's sample times in [a, b]."""
    ts = torch.as_tensor(prob.data.t, dtype=torch.float64)
    return ts[(ts >= a) & (ts <= b)]


#: samples per batch of the summary's evaluation of ζ, ε, ξ (:func:`summarise`): bounds its memory
SUMMARY_ROWS = 1 << 14


def summarise(prob: EstimationProblem, res: ShootingResult, a: float, b: float, seconds: float,
              X: Tensor | None = None, log: Callable[[str], None] | None = None) -> EstimationResult:
    """The estimate of the solved TPBVP ``prob`` on [a, b]: states, inputs, errors and J at the
    record's samples (:func:`sample_times`), where the solution is ``X`` if given, else from one
    pass over all shooting intervals (:meth:`~shootlab.bvp.solver.ShootingResult.swept`: a fixed-step
    scheme's own step values where the samples are its step grid).  ζ, ε, ξ come in batches of
    :data:`SUMMARY_ROWS` samples, so that the memory stays linear in the samples with a small
    constant; ``log``: the progress line of a long summary (:func:`phase`)."""
    m = prob.model
    ts = sample_times(prob, a, b).to(res.t)
    with phase(f"summary: states and residuals at {ts.numel()} samples", log):
        if X is None:
            X = res.swept(ts)
        x = X[:, :m.nx]
        zeta, eps, xi, integrand = [], [], [], []
        with torch.no_grad():
            for rows in torch.arange(ts.numel(), device=ts.device).split(SUMMARY_ROWS):
                p = prob.parts(ts[rows], X[rows])
                zeta.append(p["zeta"])
                eps.append(p["eps"])
                xi.append(p["xi"])
                integrand.append((p["eps"] * (p["W"] @ p["eps"].unsqueeze(-1)).squeeze(-1)).sum(-1)
                                 + (p["xi"] * (p["V"] @ p["xi"].unsqueeze(-1)).squeeze(-1)).sum(-1))
        zeta, eps, xi, integrand = (torch.cat(v) for v in (zeta, eps, xi, integrand))
    # parameters from the shooting-point values (finite even when a failed run's re-integration is not)
    theta, tk = res.x[:, len(m.states):m.nx], res.t
    params = {name: float(torch.trapezoid(theta[:, j], tk) / (tk[-1] - tk[0])) for j, name in enumerate(m.parameters)}
    d0 = X[0, :m.nx] - prob.q_a
    J = 0.5 * float(d0 @ prob.W_a @ d0) + 0.5 * float(torch.trapezoid(integrand, ts))
    message = res.message
    if res.status == Status.INTERVALS_TOO_LONG:
        message += ("; in an estimation the fast modes also come from the weights: a parameter with a small W "
                    "drifts to follow the data (a larger W on the parameters, e.g. W={'k': 1e10}, holds it "
                    "constant), and a large V on a row speeds up its costate")
    cpu = lambda v: v.cpu()        # noqa: E731  (the series on the CPU, wherever the solve ran)
    return EstimationResult(
        success=res.success, message=message, parameters=params, J=J, t=cpu(ts),
        x={n: cpu(x[:, j]) for j, n in enumerate(m.names)},
        zeta={n: cpu(zeta[:, j]) for j, n in enumerate(m.inputs)},
        eps={n: cpu(eps[:, j]) for j, n in enumerate(m.names)},
        xi={n: cpu(xi[:, j]) for j, n in enumerate(m.equations)},
        shooting=res, problem=prob, seconds=seconds, points=res.t.numel(), log=log)
