"""The report's chapter 4 as a workflow users can run on their own data.

The flexible rotation manipulator (:mod:`manipulators.flexible`) is identified in the order of
the report:

1. :func:`identify_plain` — the plain two-inertia model (§4.2) with the report's weights, reached
   by *weight continuation* (the report: the weights were found by trial and error, and "a
   solution of the TPBVP with (slightly) varied weighting factors is obtained efficiently when
   using the former solution as an initial approximation").  From the prior, the report's
   V = (1, 1, 1e4, 1e9, 1e9) makes the Newton iteration crawl (damping 0.1 at every step), so
   the measurement weights are raised stage by stage along :data:`PLAIN_SCHEDULE`, each stage
   warm-started from the previous one (states, parameters and costates by name).
2. The structural error: :func:`plot_equation_residuals` (fig. 4.5) and
   :func:`residual_velocity_correlation` / :func:`plot_residual_vs_velocity` (fig. 4.6) — the
   residual on the equation of motion of mass 2 against its estimated velocity.
3. :func:`identify_extended` — the model with smooth Coulomb friction (§4.3–4.4), W = V = I,
   warm-started from the plain estimate's parameters or cold from the report's initial values;
   fig. 4.10
   (:func:`plot_extended`).
4. :func:`validate` — free-run simulation of the estimated models on other data (the report's
   figs. 4.11, 4.12) and the RMS errors of s1, s2.

:func:`run_workflow` chains all of it and writes the figures and a JSON summary into a folder.
Data are anything :meth:`shootlab.estimation.data.Measurements.coerce` reads (a CSV with columns
``t,u,s1,s2``, a mapping of arrays, Measurements) or a :class:`manipulators.rig.RigData`.

Units (everything per unit motor constant c): time [s], angles [rad], velocities [rad/s],
motor command u and the residuals on the equations of motion [-] (torque/c), m/c [s²/rad],
k/c [1/rad], b/c [s/rad], f/c [-].
"""
from __future__ import annotations

import json
import math
import time
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

from shootlab.estimation.data import Measurements
from shootlab.estimation import EstimationResult, estimate
from shootlab.outputs import json_ready

from .flexible import REPORT_PRIOR, STATES, WEIGHT_LEVELS, friction_model, plain_model
from .flexible import UNITS as FLEXIBLE_UNITS
from .friction import smooth_sign

# the measurement weights V_s of the continuation stages (see plain_weights); the last stage
# is the report's V = (1, 1, 1e4, 1e9, 1e9)
PLAIN_SCHEDULE: tuple[float, ...] = WEIGHT_LEVELS
U_WEIGHT_CAP = 1e4          # the report's weight on the motor-command row
REPORT_INITIAL_EXTENDED = dict(REPORT_PRIOR, f1=0.0, f2=0.0)
# the report's extended-model estimates (§4.4) and its computing time for them
REPORT_EXTENDED = dict(m1=5.40, m2=0.47, k=1000.0, b=2.3, f1=1.26, f2=39.9)
REPORT_EXTENDED_MINUTES = 7.5
REPORT_PLAIN_MINUTES = 2.5

UNITS = {p: FLEXIBLE_UNITS[p] for p in ("m1", "m2", "k", "b", "f1", "f2")}


# -- data and options ---------------------------------------------------------------------------
def as_measurements(data) -> Measurements:
    """Measurements from a CSV path, a mapping, Measurements or rig data (its measured columns)."""
    if hasattr(data, "measured") and callable(data.measured) and not isinstance(data, Measurements):
        data = data.measured()
    return Measurements.coerce(data)


def plain_weights(level: float, u_cap: float = U_WEIGHT_CAP) -> tuple[float, ...]:
    """diag(V) of a continuation stage: (1, 1, min(level, u_cap), level, level) for the rows
    (mass1, mass2, u, s1, s2) — the equations of motion stay at 1, the measurement rows rise."""
    level = float(level)
    return (1.0, 1.0, min(level, float(u_cap)), level, level)


def _solve_options(model, points: int | None, solve: Mapping | None) -> tuple[int, dict]:
    opts = dict(model.settings.solver)
    opts.update(solve or {})
    return int(points or model.settings.points), opts


def _rms(a) -> float:
    a = np.asarray(a, dtype=float)
    return float(np.sqrt(np.mean(a * a)))


def _np(v) -> np.ndarray:
    return v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else np.asarray(v, dtype=float)


def _result(r) -> EstimationResult:
    return r.result if isinstance(r, PlainIdentification) else r


def _run_info(res: EstimationResult, wall: float) -> dict:
    sh = res.shooting
    return dict(success=bool(res.success), message=res.message, iterations=int(sh.iterations),
                jacobian_evaluations=int(sh.jacobian_evaluations), residual_norm=float(sh.residual_norm),
                points=int(res.points), solve_seconds=float(res.seconds), seconds=float(wall),
                J=float(res.J), parameters=dict(res.parameters))


# -- 1. the plain model with weight continuation --------------------------------------------------
@dataclass
class PlainIdentification:
    """Outcome of :func:`identify_plain`: the last stage's estimate and a record per stage."""

    result: EstimationResult                 # the last stage run (the report's weights if all converged)
    stages: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def success(self) -> bool:
        return bool(self.stages) and all(s["success"] for s in self.stages)

    @property
    def iterations(self) -> int:
        return sum(s["iterations"] for s in self.stages)

    @property
    def parameters(self) -> dict[str, float]:
        return self.result.parameters

    def summary(self) -> dict:
        return dict(success=self.success, iterations=self.iterations, seconds=self.seconds,
                    points=int(self.result.points), parameters=dict(self.parameters), stages=self.stages)


def identify_plain(data, *, points: int | None = None, schedule: Sequence = PLAIN_SCHEDULE, W=1e4,
                   prior: Mapping[str, float] | None = None, initial: Mapping[str, float] | None = None,
                   prior_weight: float = 0.0, solve: Mapping | None = None, out: str | Path | None = None,
                   tag: str = "", verbose: bool = False) -> PlainIdentification:
    """Estimate the plain model (report §4.2) by weight continuation.

    ``schedule``: one entry per stage, a level V_s (→ :func:`plain_weights`) or a full diag(V)
    of 5 entries; default :data:`PLAIN_SCHEDULE`, ending at the report's weights.  Stage 1 starts
    from the prior (``prior``, ``initial``) with the states from the data and λ = 0; every later
    stage from the previous stage's solution.  The continuation stops at the first stage that
    does not converge (``success`` is then False and ``result`` is that stage's outcome).
    Fig. 4.3 is the free-run simulation with the initial parameter values, starting at rest.
    ``points`` (default 101) and ``solve`` (default: RK4, 10 steps per interval) as for
    :func:`shootlab.estimate`.  ``prior_weight``: hold the parameters at ``prior`` (see
    :func:`manipulators.flexible.plain_model`; 0, the report's reading, leaves them free).  With
    ``out``: figs. 4.3, 4.5, 4.6 and the standard estimation files of the last stage in
    ``out/plain``; a ``tag`` is appended to those names (``fig4_6_…{tag}.png``, ``plain{tag}``).
    """
    data = as_measurements(data)
    if not len(schedule):
        raise ValueError("the weight schedule is empty")
    prev, stages = None, []
    t_start = time.perf_counter()
    for i, level in enumerate(schedule):
        V = plain_weights(level) if np.ndim(level) == 0 else tuple(float(v) for v in level)
        model = plain_model(W=W, V=V, prior=prior, prior_weight=prior_weight, continuation=False)
        n, opts = _solve_options(model, points, solve)
        t0 = time.perf_counter()
        res = estimate(model, data, n_points=n, initial=initial if prev is None else None, start=prev, **opts)
        info = dict(stage=i + 1, V=list(V), **_run_info(res, time.perf_counter() - t0))
        stages.append(info)
        if verbose:
            print(f"  plain stage {i + 1}/{len(schedule)} V = {V}: {'ok' if res.success else 'FAILED'}, "
                  f"{info['iterations']} iterations, {info['seconds']:.1f} s, "
                  + ", ".join(f"{k} {v:.4g}" for k, v in res.parameters.items()), flush=True)
        prev = res
        if not res.success:
            break
    out_obj = PlainIdentification(result=prev, stages=stages, seconds=time.perf_counter() - t_start)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        m0, p0 = plain_model(prior=prior), dict(REPORT_PRIOR, **(prior or {}), **(initial or {}))
        prior_pred = simulate_model(m0, data, p0, initial_state(m0, data, p0))      # from rest
        plot_measured_vs_model(data, {"model, initial parameter values": prior_pred},
                               out / "fig4_3_measured_vs_model.png",
                               "fig. 4.3: measured vs model (plain model, initial parameter values)")
        plot_equation_residuals(prev, out / f"fig4_5_equation_residuals{tag}.png")
        plot_residual_vs_velocity(prev, out / f"fig4_6_residual_vs_velocity{tag}.png")
        from shootlab.outputs import write_estimation
        write_estimation(prev, out / f"plain{tag}")
    return out_obj


# -- 2. the structural error ------------------------------------------------------------------------
def residual_velocity_correlation(result, equation: str = "mass2", velocity: str = "v2",
                                  v_s: float | None = None) -> dict:
    """How the residual ξ on an equation of motion depends on the estimated velocity (fig. 4.6).

    Returned (all over the data samples of the estimate):

    ``pearson_velocity``     r(ξ, v̂) — the linear correlation with the velocity
    ``pearson_sign``         r(ξ, sign v̂) — with the Coulomb-friction signature (report eq. 4.2)
    ``pearson_smooth_sign``  r(ξ, σ(v̂; v_s)) — with the smoothed signature of the extended model
                             (v_s: the model's v_s2 setting, 1.0 rad/s by default)
    ``partial_sign``         the partial correlation of ξ and sign v̂ given v̂ (both with their
                             linear regression on [1, v̂] removed)
    ``multiple_r``           R of the least-squares fit ξ ≈ c0 + c_v v̂ + c_sign sign v̂, with the
                             coefficients ``fit`` (c_sign estimates a missing Coulomb level)
    ``coulomb_bound``        r(sign v̂, v̂): the Pearson r(ξ, v̂) of a residual that is exactly a
                             missing Coulomb friction f·sign v̂ and nothing else — what
                             ``pearson_velocity`` can reach for that error on this record
                             (2√2/π ≈ 0.90 for a sinusoid of constant amplitude, less when the
                             amplitude varies, as in a sweep through a resonance)

    Why several numbers: a model that estimates a viscous coefficient b leaves, at the optimum,
    a residual nearly orthogonal to the relative velocity (the stationarity condition for b),
    so r(ξ, v̂) is small *by construction* even when a velocity-dependent force is missing —
    the linear part of that force is absorbed into b̂.  What the plain model cannot absorb is
    the part that is not linear in v̂: the step of Coulomb friction, measured by
    ``partial_sign``.
    """
    res = _result(result)
    xi = _np(res.xi[equation])
    v = _np(res.x[velocity])
    if v_s is None:
        v_s = float(res.problem.model.settings.extra.get("v_s2" if velocity == "v2" else "v_s1", 1.0))
    sgn = np.sign(v)
    sig = np.asarray(smooth_sign(v, float(v_s)), dtype=float)

    def r(a, b):
        a, b = a - a.mean(), b - b.mean()
        d = math.sqrt(float(a @ a) * float(b @ b))
        return float(a @ b) / d if d > 0 else math.nan

    X1 = np.column_stack([np.ones_like(v), v])
    res_xi = xi - X1 @ np.linalg.lstsq(X1, xi, rcond=None)[0]
    res_sg = sgn - X1 @ np.linalg.lstsq(X1, sgn, rcond=None)[0]
    X = np.column_stack([np.ones_like(v), v, sgn])
    c, *_ = np.linalg.lstsq(X, xi, rcond=None)
    fitted = X @ c
    ss_res, ss_tot = float(np.sum((xi - fitted) ** 2)), float(np.sum((xi - xi.mean()) ** 2))
    return dict(equation=equation, velocity=velocity, samples=int(v.size), v_s=float(v_s),
                pearson_velocity=r(xi, v), pearson_sign=r(xi, sgn), pearson_smooth_sign=r(xi, sig),
                partial_sign=r(res_xi, res_sg), coulomb_bound=r(sgn, v),
                multiple_r=math.sqrt(max(0.0, 1.0 - ss_res / ss_tot)) if ss_tot > 0 else math.nan,
                fit=dict(c0=float(c[0]), c_v=float(c[1]), c_sign=float(c[2])),
                rms_residual=_rms(xi), rms_velocity=_rms(v))


# -- 3. the extended model --------------------------------------------------------------------------
def _states_only(previous: EstimationResult):
    """``previous`` as a warm start with its costates set to zero (see identify_extended)."""
    nx, sh = previous.problem.model.nx, previous.shooting

    def sol(t):
        X = sh.sol(t).clone()
        X[:, nx:] = 0.0
        return X

    x = sh.x.clone()
    x[:, nx:] = 0.0
    return types.SimpleNamespace(problem=previous.problem, shooting=types.SimpleNamespace(t=sh.t, x=x, sol=sol))


def identify_extended(data, start=None, *, warm: str = "parameters", points: int | None = None, W=1.0,
                      V=(1.0,) * 5, v_s1: float = 0.1, v_s2: float = 1.0,
                      prior: Mapping[str, float] | None = None, initial: Mapping[str, float] | None = None,
                      solve: Mapping | None = None, out: str | Path | None = None,
                      verbose: bool = False) -> EstimationResult:
    """Estimate the extended model (report §4.3–4.4: W = V = I, v_s1 = 0.1, v_s2 = 1.0).

    ``start``: a previous estimate (e.g. :func:`identify_plain`'s) to warm-start from, matched by
    name; ``warm`` says what is taken from it:

    ``"parameters"`` (default)  its parameters; states from the data (report §4.2), λ = 0
    ``"states"``                its smoothed states and parameters, λ = 0
    ``"all"``                   states, parameters and costates (shootlab's ``start=``)

    Measured on the virtual rig (friction-only and full effects, 1 s sweep, 101 points): from the
    converged plain estimate "parameters" and "states" converge in 7–8 iterations (cold: 7–11);
    "all" breaks down (a singular Newton matrix, resp. no convergence in 60 iterations) — λ scales
    with the weights (λ' = −Aᵀλ − CᵀVξ) and the plain model's V = 1e9 on the encoder rows makes
    its costates meaningless for V = I.  On 0.3 s of data from a poor plain estimate (one stage
    V = I), "states" crawled (no convergence in 25 iterations) while "parameters" converged in 8:
    the plain model's smoothed states are shaped by the wrong (frictionless) dynamics, the data's
    are not.  Without ``start`` the iteration starts cold from the report's initial values
    (4.7, 0.39, 978, 2.7, 0, 0), or ``prior`` / ``initial``; ``initial`` always has the last word.
    With ``out``: fig. 4.10 and the standard estimation files in ``out/extended``.
    """
    data = as_measurements(data)
    model = friction_model(W=W, V=V, v_s1=v_s1, v_s2=v_s2, prior=prior)
    n, opts = _solve_options(model, points, solve)
    init, begin = dict(initial or {}), None
    if start is not None:
        prev = _result(start)
        if warm == "states":
            begin = _states_only(prev)
        elif warm == "all":
            begin = prev
        elif warm == "parameters":
            init = {k: v for k, v in prev.parameters.items() if k in model.parameters} | init
        else:
            raise ValueError(f"warm must be 'states', 'parameters' or 'all', got {warm!r}")
    res = estimate(model, data, n_points=n, initial=init or None, start=begin, verbose=verbose, **opts)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        plot_extended(res, out / "fig4_10_extended_estimates.png")
        from shootlab.outputs import write_estimation
        write_estimation(res, out / "extended")
    return res


# -- 4. validation -----------------------------------------------------------------------------------
def simulate_model(model, data, parameters: Mapping[str, float], initial_state=None) -> dict[str, np.ndarray]:
    """Free-run simulation of ``model`` with ``parameters`` on the command u of ``data``."""
    from shootlab.estimation.free_run import simulate
    return simulate(model, as_measurements(data), dict(parameters), initial_state)


INITIAL_STATE_WINDOW = 0.05     # s: the stretch of data the free-run initial state is fitted to


def initial_state(model, data, parameters: Mapping[str, float], how="rest",
                  window: float = INITIAL_STATE_WINDOW) -> np.ndarray | None:
    """The state [s1, s2, v1, v2] a free-run simulation starts from.

    ``"rest"`` (default) s1, s2 the first samples, v1 = v2 = 0: an experiment that starts at
                         standstill, as identification and validation experiments usually do
    ``"fit"``            least squares: the free-run response of ``model`` with ``parameters`` fits
                         the measured s1, s2 over the first ``window`` seconds (starting from
                         ``"rest"``); the same procedure for every model compared, but it lets a
                         model hide its own errors in the first ``window`` in the initial velocity
    ``"data"``           the model's own initial approximation: s from the encoders, v by
                         central differences (report §4.2) — on quantised encoder data a poor
                         velocity (one count in 1 ms is 0.8 rad/s), which then drifts the whole run
    a sequence           used as given
    Returns None for ``"data"`` (shootlab's default).
    """
    data = as_measurements(data)
    if not isinstance(how, str):
        return np.asarray(how, dtype=float)
    if how == "data":
        return None
    rest = np.array([data.channels["s1"][0], data.channels["s2"][0], 0.0, 0.0])
    if how == "rest":
        return rest
    if how != "fit":
        raise ValueError(f"initial must be 'fit', 'rest', 'data' or a state vector, got {how!r}")
    from scipy.optimize import least_squares
    n = max(int(np.searchsorted(data.t, data.t[0] + window, side="right")), 4)
    sub = Measurements(data.t[:n], {k: v[:n] for k, v in data.channels.items()})
    meas = np.concatenate([sub.channels["s1"], sub.channels["s2"]])

    def resid(x):
        pred = simulate_model(model, sub, parameters, x)
        return np.concatenate([pred["s1"], pred["s2"]]) - meas

    fit = least_squares(resid, rest, x_scale=[1e-3, 1e-3, 0.1, 0.1], diff_step=1e-4)
    return fit.x


def validate(results: Mapping[str, object], data, *, initial="rest", window: float = INITIAL_STATE_WINDOW,
             out: str | Path | None = None, figure: str = "fig4_12_validation.png",
             title: str | None = None) -> dict:
    """Free-run simulation of every estimated model on the command u of ``data`` (ε = 0) compared
    with the measured s1, s2.  ``initial``: how the simulation's initial state is found — see
    :func:`initial_state` (default: at rest; ``window`` is for ``"fit"``).

    ``results``: label → estimate (:class:`EstimationResult` or :class:`PlainIdentification`).
    Returns label → dict(rms_s1, rms_s2, rms (both channels), max_abs_s1, max_abs_s2,
    initial_state, parameters, prediction arrays); with ``out`` a figure in the style of
    figs. 4.11/4.12.
    """
    data = as_measurements(data)
    report, preds = {}, {}
    for label, r in results.items():
        res = _result(r)
        model = res.problem.model
        x0 = initial_state(model, data, res.parameters, initial, window)
        pred = simulate_model(model, data, res.parameters, x0)
        preds[label] = pred
        n = pred["t"].size
        e1 = pred["s1"] - data.channels["s1"][:n]
        e2 = pred["s2"] - data.channels["s2"][:n]
        report[label] = dict(rms_s1=_rms(e1), rms_s2=_rms(e2), rms=math.sqrt(0.5 * (_rms(e1) ** 2 + _rms(e2) ** 2)),
                             max_abs_s1=float(np.abs(e1).max()), max_abs_s2=float(np.abs(e2).max()),
                             samples=int(n), complete=bool(n == data.t.size),
                             initial=initial if isinstance(initial, str) else "given",
                             initial_state=[float(v) for v in (x0 if x0 is not None else
                                            [pred["state:" + s][0] for s in model.states])],
                             parameters=dict(res.parameters), prediction=pred)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        plot_measured_vs_model(data, preds, out / figure, title or "measured vs free-run simulation")
    return report


def rms_ratios(validation: Mapping[str, dict], worse: str = "plain", better: str = "extended") -> dict:
    """RMS error of ``worse`` over that of ``better`` per channel (s1, s2, both)."""
    a, b = validation[worse], validation[better]
    return {k: a[k] / b[k] if b[k] > 0 else math.inf for k in ("rms_s1", "rms_s2", "rms")}


# -- figures ----------------------------------------------------------------------------------------
def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


_COLORS = ["tab:red", "tab:blue", "tab:green", "tab:purple"]


def plot_measured_vs_model(data, predictions: Mapping[str, dict], path, title: str = "") -> Path:
    """Figs. 4.3 / 4.11 / 4.12: motor command, s1 and s2 measured vs model (free-run)."""
    plt = _plt()
    data = as_measurements(data)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    t = data.t
    axes[0].plot(t, data.channels["u"], color="0.3", lw=0.8, label="u (command)")
    axes[0].set_ylabel("motor command u [-]")
    for ax, ch, name in ((axes[1], "s1", "mass 1 (end-effector)"), (axes[2], "s2", "mass 2 (rotor)")):
        ax.plot(t, data.channels[ch], color="k", lw=1.6, label=f"{ch} measured")
        for (label, pred), c in zip(predictions.items(), _COLORS):
            ax.plot(pred["t"], pred[ch], color=c, lw=1.0, ls="--" if c != _COLORS[0] else "-",
                    label=f"{ch}, {label}")
        ax.set_ylabel(f"rotation {name}, {ch} [rad]")
    for ax in axes:
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_equation_residuals(result, path) -> Path:
    """Fig. 4.5: residuals ξ on the two equations of motion, with the command u for scale."""
    plt = _plt()
    res = _result(result)
    t = _np(res.t)
    u = _np(res.zeta["u"])
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for ax, eq, name in ((axes[0], "mass1", "mass 1 (end-effector)"), (axes[1], "mass2", "mass 2 (rotor)")):
        ax.plot(t, u, color="0.75", lw=0.8, label="estimated command u (scale)")
        ax.plot(t, _np(res.xi[eq]), color="tab:red", lw=1.0, label=f"ξ {eq}: residual on the equation of motion")
        ax.axhline(0.0, color="0.5", lw=0.5)
        ax.set_ylabel(f"ξ, {name} [-]")
        ax.legend(fontsize=7, loc="upper right")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"fig. 4.5: residuals on the equations of motion ({res.problem.model.name} model)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_residual_vs_velocity(result, path, correlation: dict | None = None) -> Path:
    """Fig. 4.6: residual on the equation of motion of mass 2 and the estimated velocity of
    mass 2 in time, and the residual against that velocity with the Coulomb + viscous fit."""
    plt = _plt()
    res = _result(result)
    corr = correlation or residual_velocity_correlation(res)
    t, xi, v = _np(res.t), _np(res.xi["mass2"]), _np(res.x["v2"])
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(13, 4), gridspec_kw=dict(width_ratios=[1.6, 1]))
    l1 = a0.plot(t, xi, color="tab:red", lw=1.0, label="ξ mass2 (residual on the equation of motion)")
    a0.set_ylabel("residual ξ mass 2 [-]", color="tab:red")
    a0.set_xlabel("time [s]")
    a0.axhline(0.0, color="0.6", lw=0.5)
    b0 = a0.twinx()
    l2 = b0.plot(t, v, color="tab:blue", lw=1.0, label="estimated velocity of mass 2, v2")
    b0.set_ylabel("estimated velocity of mass 2 [rad/s]", color="tab:blue")
    a0.set_ylim(-1.15 * abs(xi).max(), 1.15 * abs(xi).max())         # zeros of both curves aligned
    b0.set_ylim(-1.15 * abs(v).max(), 1.15 * abs(v).max())
    a0.legend(l1 + l2, [l.get_label() for l in l1 + l2], fontsize=7, loc="upper right")
    a0.grid(alpha=0.3)
    a1.plot(v, xi, ".", ms=2.5, color="tab:red", alpha=0.6, label="samples")
    vv = np.linspace(v.min(), v.max(), 801)
    c = corr["fit"]
    a1.plot(vv, c["c0"] + c["c_v"] * vv + c["c_sign"] * np.sign(vv), color="k", lw=1.2,
            label=f"fit {c['c0']:.2g} {c['c_v']:+.3g}·v {c['c_sign']:+.3g}·sign v")
    a1.axhline(0.0, color="0.6", lw=0.5)
    a1.axvline(0.0, color="0.6", lw=0.5)
    a1.set_xlabel("estimated velocity of mass 2, v2 [rad/s]")
    a1.set_ylabel("residual ξ mass 2 [-]")
    a1.set_title(f"r(ξ, v) = {corr['pearson_velocity']:.2f} (Coulomb alone: {corr['coulomb_bound']:.2f}),  "
                 f"r(ξ, sign v) = {corr['pearson_sign']:.2f},\n"
                 f"partial r(ξ, sign v | v) = {corr['partial_sign']:.2f},  R(ξ; v, sign v) = {corr['multiple_r']:.2f}",
                 fontsize=8)
    a1.legend(fontsize=7, loc="best")
    a1.grid(alpha=0.3)
    held = bool((torch.diagonal(res.problem.W_a)[len(STATES):] > 0).any())     # W_a on the parameters
    fig.suptitle("fig. 4.6: tracking the structural error — residual of mass 2 vs its estimated velocity "
                 f"({res.problem.model.name} model, parameters {'held at the prior' if held else 'free'})",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def plot_extended(result, path) -> Path:
    """Fig. 4.10: estimated quantities of the extended model and their residuals — s2 measured
    vs estimated and ξ_s2, the parameter trajectories k̂(t), f̂2(t) and their ε, and the
    residuals on the equations of motion."""
    plt = _plt()
    res = _result(result)
    data = res.problem.data
    t = _np(res.t)
    s2m = np.interp(t, data.t, data.channels["s2"])
    fig, ax = plt.subplots(4, 2, figsize=(12, 10), sharex=True)
    ax[0, 0].plot(t, s2m, color="k", lw=1.6, label="s2 measured")
    ax[0, 0].plot(t, _np(res.x["s2"]), color="tab:red", lw=1.0, ls="--", label="s2 estimated")
    ax[0, 0].set_ylabel("rotation mass 2 [rad]")
    ax[0, 1].plot(t, _np(res.xi["s2"]), color="tab:red", lw=0.8, label="ξ s2 = measured − estimated s2")
    ax[0, 1].set_ylabel("residual s2 [rad]")
    for row, p in ((1, "k"), (2, "f2")):
        est = _np(res.x[p])
        ax[row, 0].plot(t, est, color="tab:blue", lw=1.2, label=f"estimated {p}(t), mean {res.parameters[p]:.6g}")
        ax[row, 0].set_ylabel(f"{p}/c [{UNITS[p]}]")
        pad = max(1e-3 * abs(res.parameters[p]), 1e-9)
        lo, hi = est.min(), est.max()
        if hi - lo < 2 * pad:
            ax[row, 0].set_ylim(res.parameters[p] - 10 * pad, res.parameters[p] + 10 * pad)
        ax[row, 1].plot(t, _np(res.eps[p]), color="tab:blue", lw=0.8, label=f"ε {p} (residual on the parameter equation)")
        ax[row, 1].set_ylabel(f"ε {p} [{UNITS[p]}/s]")
    for eq, c in (("mass1", "tab:green"), ("mass2", "tab:red")):
        ax[3, 0].plot(t, _np(res.xi[eq]), color=c, lw=0.8, label=f"ξ {eq}")
    ax[3, 0].set_ylabel("residual, equations of motion [-]")
    ax[3, 1].plot(t, _np(res.xi["u"]), color="0.3", lw=0.8, label="ξ u = command − estimated u")
    ax[3, 1].set_ylabel("residual, motor command [-]")
    for a in ax.flat:
        a.grid(alpha=0.3)
        a.legend(fontsize=7, loc="upper right")
    for a in ax[-1]:
        a.set_xlabel("time [s]")
    fig.suptitle(f"fig. 4.10: estimated quantities and residuals ({res.problem.model.name} model)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


# -- the whole chapter ---------------------------------------------------------------------------------
def run_workflow(identification, validation, *, out: str | Path | None = None, points: int | None = None,
                 solve: Mapping | None = None, schedule: Sequence = PLAIN_SCHEDULE, warm: str = "parameters",
                 v_s1: float = 0.1, v_s2: float = 1.0, initial="rest", held_prior_weight: float | None = None,
                 verbose: bool = False) -> dict:
    """Chapter 4 on one identification record and one validation record (module docstring).

    The extended model is warm-started from the plain one (``warm``, see :func:`identify_extended`)
    when the continuation converged, else cold from the report's initial values.  ``initial``:
    the free-run simulations' initial state (:func:`initial_state`, default at rest).
    ``held_prior_weight``: also identify the plain model with its parameters held at the prior
    (:func:`identify_plain` with that ``prior_weight``) and report its fig. 4.6 and correlation
    (``correlation_held``; figures tagged ``_held``): with free parameters the plain model
    absorbs the linear part of a missing friction into b̂, with held ones the residual keeps it.
    Returns a dict with the plain identification, the extended estimate, the correlation of
    fig. 4.6, the validation on both records and the RMS ratios (plain / extended); with
    ``out`` every figure and ``summary.json`` are written there.
    """
    ident, valid = as_measurements(identification), as_measurements(validation)
    out = Path(out) if out is not None else None
    plain = identify_plain(ident, points=points, schedule=schedule, solve=solve, out=out, verbose=verbose)
    corr = residual_velocity_correlation(plain)
    held = held_corr = None
    if held_prior_weight is not None:
        held = identify_plain(ident, points=points, schedule=schedule, solve=solve, out=out, verbose=verbose,
                              prior_weight=held_prior_weight, tag="_held")
        held_corr = residual_velocity_correlation(held)
    if not plain.success:       # a failed stage is no place to start from: the report's cold start
        warm = "none (plain model did not converge)"
        if verbose:
            print("  the plain model did not converge; the extended model starts cold", flush=True)
    t0 = time.perf_counter()
    ext = identify_extended(ident, start=plain if plain.success else None,
                            warm=warm if plain.success else "parameters", points=points, solve=solve,
                            v_s1=v_s1, v_s2=v_s2, out=out)
    ext_info = _run_info(ext, time.perf_counter() - t0)
    if verbose:
        print(f"  extended (warm start: {warm}): {'ok' if ext.success else 'FAILED'}, {ext_info['iterations']} "
              f"iterations, {ext_info['seconds']:.1f} s", flush=True)
    models = {"plain": plain, "extended": ext}
    fit = validate(models, ident, initial=initial, out=out, figure="fig4_11_identification_input.png",
                   title="fig. 4.11: identification input, free-run simulation with the estimated parameters")
    val = validate(models, valid, initial=initial, out=out, figure="fig4_12_validation_input.png",
                   title="fig. 4.12: validation input, free-run simulation with the estimated parameters")
    summary = dict(plain=plain.summary(), residual_correlation=corr, extended=ext_info,
                   **({} if held is None else dict(plain_held=dict(held.summary(), prior_weight=held_prior_weight),
                                                   residual_correlation_held=held_corr)),
                   extended_warm_start=warm, validation_initial_state=initial if isinstance(initial, str) else "given",
                   identification_fit={k: _strip(v) for k, v in fit.items()},
                   validation={k: _strip(v) for k, v in val.items()},
                   validation_ratio=rms_ratios(val), identification_ratio=rms_ratios(fit))
    if out is not None:
        write_json(out / "summary.json", summary)
    return dict(plain=plain, extended=ext, correlation=corr, plain_held=held, correlation_held=held_corr,
                identification_fit=fit, validation=val, summary=summary)


def _strip(v: dict) -> dict:
    return {k: x for k, x in v.items() if k != "prediction"}


def write_json(path, obj) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(json_ready(obj), indent=2))
    return path
