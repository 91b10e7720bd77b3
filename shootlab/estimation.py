"""Optimal estimation: a model in augmented state form → the TPBVP of its optimality conditions.

Identification model (report eqs. 2.4–2.5), x = states and constant parameters, ζ = input
estimates, ε and ξ residuals::

    x' = A x + B ζ + ε
    E z_m(t) = f(x, t) + F(x, t) ζ + ξ          (model equations as zero pseudo-measurements
                                                 and the real measurement equations)

    J = ½ (x(a) − q_a)ᵀ W_a (x(a) − q_a) + ½ ∫ₐᵇ (εᵀ W ε + ξᵀ V ξ) dt                (eq. 2.6)

Stationarity of J gives the TPBVP of eq. 2.7 in (x, λ), 2·dim(x) equations, built by
:class:`shootlab.optimality.EstimationProblem` (its right-hand side, Jacobian and boundary
conditions); this module holds the model, the initial approximation, :func:`estimate` (multiple
shooting on that TPBVP, weight continuation) and the free-run :func:`simulate`.
"""
from __future__ import annotations

import inspect
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .data import Interpolant, Measurements, linear_fill, with_filled_inputs
from .optimality import EstimationProblem, _check_weight
from .problem import as_tensor
from .newton import NEWTON, Status
from . import weights
from .solver import ShootingResult, solve


@dataclass
class IdentificationModel:
    """A model in augmented state form (module docstring).

    states, parameters  names; x = states + parameters (parameters have θ' = ε_θ)
    inputs              names of ζ
    equations           names of the rows of f and F
    channels            row name → data channel for the measurement rows; the other rows are
                        model equations (zero pseudo-measurements)
    A, B                constant (nx, nx), (nx, nζ); parameter rows are zero
    f(x, t), F(x, t)    batched torch functions: x (..., nx), t (...) → (..., r), (..., r, nζ)
    W, V, W_a           weights: a vector (diagonal), a matrix, or a function of t returning either
    q_a                 prior on x(a) (zeros by default; only components with W_a > 0 matter)
    prior               default initial parameter values
    given               the channels known when the model is *simulated* (its inputs, e.g. the
                        motor command); with the model-equation rows they determine ζ
    initial_states      (data, t) → (m, n_states) initial approximation of the states at t
    settings            defaults for estimate and the CLI: "points", "solve" (options of
                        shootlab.solve), optionally "weight_continuation": levels at which the
                        diagonal V is capped in stages estimated first, each warm-starting the
                        next (report §4.2), and
                        "initial_parameters": (data, params, t) →
                        params or None, called with the initial parameter values before the
                        initial approximation is built (raise ValueError for bad values, or
                        return refined ones)
    units               optional unit per name — "t", states, parameters, inputs, channels and
                        equation rows (the unit of the row's residual ξ) — for labels and
                        summaries, e.g. {"t": "s", "s": "m", "u": "N", "m": "kg"}; "-" for a
                        dimensionless quantity, no entry for an unknown unit
    bounds              optional (low, high) per state or parameter name that the Newton
                        iterates keep strictly inside, e.g. {"m": (0, inf)} for a positive mass
                        (IPOPT users give the same bounds)
    """

    name: str
    states: list[str]
    parameters: list[str]
    inputs: list[str]
    equations: list[str]
    channels: dict[str, str]
    A: Tensor
    B: Tensor
    f: Callable[[Tensor, Tensor], Tensor]
    F: Callable[[Tensor, Tensor], Tensor]
    W: object
    V: object
    W_a: object = None
    q_a: object = None
    prior: dict[str, float] = field(default_factory=dict)
    given: list[str] = field(default_factory=list)
    initial_states: Callable[[Measurements, Tensor], Tensor] | None = None
    settings: dict = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)

    def f_and_F(self, x: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """f(x, t) and F(x, t); from one evaluation where f and F are methods of one object that
        has ``f_and_F`` (a declared model's rows, :meth:`shootlab.rows.Rows.f_and_F`; an extended
        model, :func:`shootlab.composition.extend`)."""
        owner = getattr(self.f, "__self__", None)
        if owner is not None and getattr(self.F, "__self__", None) is owner and hasattr(owner, "f_and_F"):
            return owner.f_and_F(x, t)
        return self.f(x, t), self.F(x, t)

    def __post_init__(self):
        self.A = as_tensor(self.A, name="A")
        self.B = as_tensor(self.B, name="B")
        nx, nz, r = self.nx, len(self.inputs), len(self.equations)
        if tuple(self.A.shape) != (nx, nx):
            raise ValueError(f"A must be ({nx}, {nx}) for {nx} states + parameters, got {tuple(self.A.shape)}")
        if tuple(self.B.shape) != (nx, nz):
            raise ValueError(f"B must be ({nx}, {nz}), got {tuple(self.B.shape)}")
        unknown = set(self.channels) - set(self.equations)
        if unknown:
            raise ValueError(f"channels name rows {sorted(unknown)} that are not among the equations {self.equations}")
        bad_given = set(self.given) - set(self.channels.values())
        if bad_given:
            raise ValueError(f"given channels {sorted(bad_given)} are not measured channels")
        self.W_a = torch.zeros(nx, dtype=torch.float64) if self.W_a is None else self.W_a
        self.q_a = torch.zeros(nx, dtype=torch.float64) if self.q_a is None else as_tensor(self.q_a, name="q_a")
        for name, lohi in self.bounds.items():
            if name not in self.names:
                raise ValueError(f"bounds for {name!r}, which is not a state or parameter of {self.names}")
            if len(lohi) != 2 or not float(lohi[0]) < float(lohi[1]):
                raise ValueError(f"bounds for {name!r} must be (low, high) with low < high, got {lohi!r}")
        _check_weight(self.W, nx, "W", positive=True)
        _check_weight(self.V, r, "V", positive=False)
        _check_weight(self.W_a, nx, "W_a", positive=False)

    @property
    def names(self) -> list[str]:
        return list(self.states) + list(self.parameters)

    @property
    def nx(self) -> int:
        return len(self.states) + len(self.parameters)

    @property
    def measured(self) -> list[str]:
        return list(dict.fromkeys(self.channels.values()))

    def label(self, name: str) -> str:
        """'name [unit]' from :attr:`units` ('name' when the unit is not declared)."""
        unit = self.units.get(name)
        return f"{name} [{unit}]" if unit else name


# -- initial approximation helpers ---------------------------------------------------------
def central_difference(values: Tensor, t: Tensor) -> Tensor:
    """Derivative of samples (K, …) on a grid t (K,) by central differences (one-sided at the ends)."""
    return torch.gradient(values, spacing=(t,), dim=0, edge_order=2)[0]


def smoothed(values: Tensor, t: Tensor, deriv: int = 1, window: int = 11, order: int = 3) -> Tensor:
    """Noisy samples (K, …) smoothed (deriv=0) or differentiated (deriv=1) by a Savitzky–Golay
    filter (scipy.signal) on a uniform grid; plain values / central differences where the grid
    is irregular or shorter than the window.  Missing samples (NaN) are filled by linear
    interpolation first.  For initial approximations (report §3.4: derivatives from data)."""
    from scipy.signal import savgol_filter

    v = values.detach().cpu().numpy().reshape(values.shape[0], -1).copy()
    tn = t.detach().cpu().numpy()
    for j in range(v.shape[1]):
        v[:, j] = linear_fill(tn, v[:, j])
    dt = np.diff(tn)
    if tn.size < window or np.abs(dt - dt.mean()).max() > 1e-6 * abs(dt.mean()):
        d = np.gradient(v, tn, axis=0, edge_order=2) if deriv else v
    else:
        d = savgol_filter(v, window, order, deriv=deriv, delta=float(dt.mean()), axis=0)
    return torch.as_tensor(d.reshape(values.shape), dtype=values.dtype, device=values.device)


def measured_states(model: IdentificationModel, data: Measurements, t: Tensor) -> Tensor:
    """States that are measured channels taken from the data at t (across a missing sample by
    linear interpolation, :func:`~shootlab.data.linear_fill`), the rest zero."""
    names = [s for s in model.states if s in data.channels]
    if any(np.isnan(data.channels[s]).any() for s in names):
        data = Measurements(data.t, {s: linear_fill(data.t, data.channels[s]) for s in names})
    ip = Interpolant(data, names, t.dtype, t.device)
    out = t.new_zeros(t.numel(), len(model.states))
    vals = ip.values(t) if ip.names else None
    for j, name in enumerate(ip.names):
        out[:, model.states.index(name)] = vals[:, j]
    return out


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

    @property
    def iterations(self) -> int:
        return self.shooting.iterations

    @property
    def uncertainty(self):
        """Linearised covariance of the parameters (:func:`shootlab.uncertainty.parameter_covariance`:
        Cov θ̂ = Σ_c σ̂_c² G_c G_cᵀ, G_c = dθ̂/dz_c), computed on first use; ``None`` for a
        failed estimate or when the Newton matrix at the solution is singular."""
        if self._uncertainty is None and self.success:
            from .linalg import SingularJacobianError
            from .uncertainty import parameter_covariance
            try:
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
    prepare = model.settings.get("initial_parameters")
    if prepare is not None:     # the model's own check (ValueError) or refinement of the values
        extra = {"log": log} if log is not None and "log" in inspect.signature(prepare).parameters else {}
        params = dict(prepare(data, dict(params), t, **extra) or params)
    states = model.initial_states(data, t) if model.initial_states else measured_states(model, data, t)
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
    Xp = shot.x if tq.shape == shot.t.shape and torch.equal(tq, shot.t) else shot.sol(tq)
    X0 = X0.clone()
    for j, name in enumerate(model.names):
        if name in old.names:
            i = old.names.index(name)
            X0[:, j], X0[:, model.nx + j] = Xp[:, i], Xp[:, old.nx + i]
    return X0


def estimate(model: IdentificationModel | str, data, n_points: int | None = None, initial: Mapping[str, float] | None = None,
             interval: tuple[float, float] | None = None, start: EstimationResult | None = None,
             fallback: bool | None = None, **solve_options) -> EstimationResult:
    """Estimate states, inputs and parameters of ``model`` (or a built-in name, e.g. ``"msd"``) from
    ``data`` by multiple shooting on the TPBVP of eq. 2.7, with ``n_points`` equidistant shooting
    points on ``interval`` (default: the data's time range).  ``start``: warm start from a previous estimate (:func:`warm_start`);
    ``initial`` then overrides the parameters it names.  ``solve_options`` go to
    :func:`shootlab.solve`, over the model's defaults ``model.settings["solve"]``; ``n_points``
    defaults to ``model.settings["points"]`` (else 101).

    ``fallback``: where the Newton iteration stalls, the strategies of :data:`FALLBACK` are tried
    in turn from the same start (:func:`solve_falling_back`; recorded in ``attempts``) — also when
    ``newton`` is given.  Default ``model.settings["fallback"]``, else True; False: the first
    strategy's result as it is.  In a weight continuation every stage falls back alike."""
    if isinstance(model, str):
        from .models import resolve_model
        model = resolve_model(model)
    solve_options = _solver_options(model, solve_options)
    n_points = n_points if n_points is not None else model.settings.get("points", 101)
    data = with_filled_inputs(Measurements.coerce(data), model.given, cover=interval)
    model = weights.from_data(model, data)
    stages = _weight_stages(model)
    if fallback is None:
        fallback = bool(model.settings.get("fallback", True))
    if stages and start is None:        # continuation in the weights (report §4.2), each stage warm
        start = continue_in_weights(stages, data, n_points, initial, interval, dict(solve_options, fallback=fallback),
                                    final=False)
        if not start.success:
            return start
        initial = None
    prob, t, X0, (a, b) = posed(model, data, n_points, initial, interval, start, solve_options.get("verbose", False))
    clock = time.perf_counter()
    res, attempts = solve_falling_back(prob.bvp(), t, X0, solve_options, fallback)
    out = summarise(prob, res, a, b, time.perf_counter() - clock)
    out.attempts = attempts
    return out


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
    """The canonical name of a strategy given by name (an alias such as ``press`` too) or as an object."""
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
          interval: tuple[float, float] | None, start: EstimationResult | None, verbose: bool = False
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
    prob = EstimationProblem(model, data)
    t = torch.linspace(a, b, int(n_points), dtype=torch.float64)
    X0 = initial_approximation(model, data, t, initial, log=print if verbose else None)
    if verbose and model.settings.get("initial_parameters") is not None and start is None:
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
    """The options of :func:`shootlab.solve` for an estimate of ``model``: its ``settings["solve"]``,
    the given ``options`` over them."""
    return {**model.settings.get("solve", {}), **options}


def _weight_stages(model: IdentificationModel) -> list[IdentificationModel]:
    """The easier models of ``settings["weight_continuation"]`` (levels L₁ < L₂ < …): the model with
    every entry of its constant diagonal V capped at each level below its largest entry."""
    levels = model.settings.get("weight_continuation")
    if not levels or callable(model.V) or as_tensor(model.V, name="V").ndim != 1:
        return []
    V = as_tensor(model.V, name="V").tolist()
    settings = {k: v for k, v in model.settings.items() if k != "weight_continuation"}
    return [replace(model, V=[min(v, float(lv)) for v in V], settings=settings)
            for lv in sorted(levels) if float(lv) < max(V)]


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


def summarise(prob: EstimationProblem, res: ShootingResult, a: float, b: float, seconds: float,
              X: Tensor | None = None) -> EstimationResult:
    """The estimate of the solved TPBVP ``prob`` on [a, b]: states, inputs, errors and J at the
    record's samples (:func:`sample_times`), where the solution is ``X`` if given."""
    m = prob.model
    ts = sample_times(prob, a, b)
    X = res.sol(ts, grid=True) if X is None else X       # the samples are (usually) on the integration's steps
    with torch.no_grad():
        p = prob.parts(ts, X)
    x = X[:, :m.nx]
    # parameters from the shooting-point values (finite even when a failed run's re-integration is not)
    theta, tk = res.x[:, len(m.states):m.nx], res.t
    params = {name: float(torch.trapezoid(theta[:, j], tk) / (tk[-1] - tk[0])) for j, name in enumerate(m.parameters)}
    integrand = (p["eps"] * (p["W"] @ p["eps"].unsqueeze(-1)).squeeze(-1)).sum(-1) \
        + (p["xi"] * (p["V"] @ p["xi"].unsqueeze(-1)).squeeze(-1)).sum(-1)
    d0 = X[0, :m.nx] - prob.q_a
    J = 0.5 * float(d0 @ prob.W_a @ d0) + 0.5 * float(torch.trapezoid(integrand, ts))
    message = res.message
    if res.status == Status.INTERVALS_TOO_LONG:
        message += ("; in an estimation the fast modes also come from the weights: a parameter with a small W "
                    "drifts to follow the data (a larger W on the parameters, e.g. W={'k': 1e10}, holds it "
                    "constant), and a large V on a row speeds up its costate")
    return EstimationResult(
        success=res.success, message=message, parameters=params, J=J, t=ts,
        x={n: x[:, j] for j, n in enumerate(m.names)},
        zeta={n: p["zeta"][:, j] for j, n in enumerate(m.inputs)},
        eps={n: p["eps"][:, j] for j, n in enumerate(m.names)},
        xi={n: p["xi"][:, j] for j, n in enumerate(m.equations)},
        shooting=res, problem=prob, seconds=seconds, points=res.t.numel())
