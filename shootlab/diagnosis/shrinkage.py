"""How far the misfit shrinks (docs/design.md §4, step 3; ``docs/diagnosis.md``, "How far it shrinks").

The model extended with the selected effects (:func:`shootlab.diagnosis.composition.extend`) is re-estimated
warm-started from the nominal estimate, and the weighted residual J, the per-row residual energies
and — on validation data with another input — the free-run simulation error of the measured
channels (:func:`free_run_error`) are reported before and after, with ``shrink = 1 − after/before``.
"""
from __future__ import annotations

import inspect
import math
from typing import Callable, Mapping, Sequence

import numpy as np
import torch

from .composition import Term, extend
from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from shootlab.estimation.model import IdentificationModel
from shootlab.estimation.free_run import simulate
from shootlab.estimation.data import noise_level
from .where import effective_samples, row_energy

__all__ = ["shrink", "free_run_error", "windowed_error", "free_run_start", "fit_start", "made_start", "shrink_ratio",
           "validation_summary", "standardised_cost", "misfit", "measure_of", "restart_windows", "DRIFT_LIMIT",
           "WINDOWS", "FITTED_RUNS"]

#: a nominal free run off by more than this many channel standard deviations (relative RMS) is
#: judged drift-dominated, and the validation measure becomes :func:`windowed_error`
DRIFT_LIMIT = 1.0
#: the number of restart windows of :func:`windowed_error`
WINDOWS = 10


def free_run_start(model: IdentificationModel, data: Measurements, how,
                   parameters: Mapping[str, float] | None = None) -> list[float] | None:
    """The initial state of a free run on ``data`` (:attr:`shootlab.diagnosis.Library.initial_state`):
    ``"rest"`` measured states from the first samples, others zero; ``"fitted"`` that start refined
    by least squares of the whole record's measured channels over the initial state, with the
    run's ``parameters`` (:func:`fit_start`); ``"data"`` None (the model's own initial
    approximation); or ``how(model, data)`` — ``how(model, data, parameters)`` if it takes a third
    argument (the parameters of the run: a start that depends on an estimated offset)."""
    if callable(how):
        takes = len(inspect.signature(how).parameters) >= 3
        return [float(v) for v in (how(model, data, dict(parameters or {})) if takes else how(model, data))]
    if how == "data":
        return None
    if how not in ("rest", "fitted"):
        raise ValueError(f"initial_state must be 'rest', 'fitted', 'data' or a function, got {how!r}")
    if how == "fitted" and parameters is None:
        raise ValueError("the start 'fitted' is the state that fits the record with the run's parameters: "
                         "give them (parameters=)")
    out = []
    for s in model.states:
        if s in data.channels:
            v = data.channels[s][:5]
            v = v[~np.isnan(v)]
            out.append(float(np.mean(v)) if v.size else 0.0)
        else:
            out.append(0.0)
    if how == "fitted":
        chans = [c for c in model.measured if c not in model.given]
        typical = None                  # each state's size over the record, as the data suggest it
        if model.initial_states is not None:
            x = model.initial_states(data, torch.as_tensor(data.t, dtype=torch.float64)).numpy()
            typical = np.maximum(np.nan_to_num(np.abs(x)).max(0), 1e-6)
        # the whole record: LM to convergence, not the few steps a window's burn-in takes (with
        # friction the start's reach is non-linear: measured, 11 runs left the rig's Stribeck fit
        # 260 above the cost its own fitted start reached)
        out = [float(v) for v in fit_start(model, data, dict(parameters), np.asarray(out),
                                           noise_level(data, chans), typical, FITTED_RUNS * (len(out) + 1))]
    return out


#: free runs per state (and one) that a ``"fitted"`` start's least squares may take
FITTED_RUNS = 10


def made_start(how):
    """Where the free run on a record made rather than measured starts — a noise-floor surrogate, a
    proposed experiment: at rest for the start ``"fitted"`` (there is no measured start to fit, and
    one fitted with a model's parameters to a record they do not explain would carry that model's
    error into the made record), else ``how``."""
    return "rest" if how == "fitted" else how


def fit_start(model: IdentificationModel, data: Measurements, parameters: Mapping[str, float], guess: np.ndarray,
              sigma: Mapping[str, float] | None = None, scale: np.ndarray | None = None,
              evaluations: int | None = None) -> np.ndarray:
    """The state at ``data``'s first sample whose free run, with ``parameters``, fits the measured
    channels of ``data`` best: least squares (Levenberg–Marquardt in the state over ``scale``,
    default max(|guess|, 1e-6), from ``guess``, at most ``evaluations`` free runs, default
    2(n + 1) + 1 for n states) of the residuals in units of ``sigma`` (the channels' noise levels;
    1 without).  A start whose run fails counts as a bad one."""
    from scipy.optimize import least_squares

    chans = [c for c in model.measured if c not in model.given]
    unit = {c: float((sigma or {}).get(c, 1.0)) or 1.0 for c in chans}      # residuals in units of the noise
    y = np.concatenate([data.channels[c] / unit[c] for c in chans])
    guess = np.asarray(guess, dtype=float)
    scale = np.maximum(np.abs(guess), 1e-6) if scale is None else scale

    def residual(z: np.ndarray) -> np.ndarray:
        try:
            p = simulate(model, data, parameters, list(z * scale))
            r = np.concatenate([p[c] / unit[c] for c in chans]) - y
        except Exception:  # noqa: BLE001 - a start that diverges is a bad start
            return np.full(y.size, 1e6)
        r = np.where(np.isfinite(r), r, 1e6)
        return np.where(np.isnan(y), 0.0, r)
    return least_squares(residual, guess / scale, method="lm",
                         max_nfev=evaluations or 2 * (guess.size + 1) + 1).x * scale


def free_run_error(model: IdentificationModel, data: Measurements, parameters: Mapping[str, float],
                   initial_state="rest", sigma: Mapping[str, float] | None = None) -> dict:
    """Free-run simulation of the measured (non-given) channels on ``data``: RMS error per channel,
    relative to the channel's standard deviation, and overall (quadratic mean of the relative
    errors); infinite when the simulation does not reach the end of the record.  With ``sigma``
    (the channels' noise levels) also the error *above the noise*, √max(MSE − σ², 0): what the
    model gets wrong, without the measurement noise no model can predict."""
    x0 = free_run_start(model, data, initial_state, parameters)
    try:
        pred = simulate(model, data, parameters, x0)
        ok = pred["t"].size == data.t.size
    except Exception as exc:  # noqa: BLE001 - a diverging model is a result, not a crash
        pred, ok = {"t": data.t[:0], "error": f"{type(exc).__name__}: {exc}"}, False
    return _misfit(model, data, pred if ok else None, sigma)


def restart_windows(data: Measurements, windows: int = WINDOWS, burn_in: float = 0.25
                    ) -> list[tuple[int, int, int, Measurements]]:
    """``windows`` equal windows of ``data``: each one's first and last sample (i0, i1), the samples
    of its burn-in (``burn_in`` of it, at least 2) and the record on it."""
    t = data.t
    edges = np.linspace(0, t.size - 1, windows + 1).astype(int)
    return [(int(i0), int(i1), max(int(burn_in * (i1 - i0)), 2),
             Measurements(t[i0:i1 + 1], {c: v[i0:i1 + 1] for c, v in data.channels.items()}))
            for i0, i1 in zip(edges[:-1], edges[1:])]


def windowed_error(model: IdentificationModel, data: Measurements, parameters: Mapping[str, float],
                   windows: int = WINDOWS, sigma: Mapping[str, float] | None = None, burn_in: float = 0.25) -> dict:
    """The misfit of :func:`free_run_error` for simulations restarted in each of ``windows`` equal
    windows, so that a drifting integrator (a position driven by a force) is judged on its
    dynamics, not on its accumulated drift.  Each window's initial state is estimated from its
    first ``burn_in`` share (least squares of the measured channels over the start state, from
    the model's initial approximation of the data's state) with the model's own parameters, and
    the misfit is measured on the rest of the window."""
    chans = [c for c in model.measured if c not in model.given]
    t = data.t
    parts = restart_windows(data, windows, burn_in)
    guess = model.initial_states(data, torch.as_tensor(t[[w[0] for w in parts]], dtype=torch.float64)).numpy()
    scale = np.maximum(np.abs(guess).max(0), 1e-6)      # every window's start on one scale
    kept = {c: np.full(t.size, np.nan) for c in chans}
    for k, (i0, i1, cut, piece) in enumerate(parts):
        start = Measurements(t[i0:i0 + cut], {c: v[i0:i0 + cut] for c, v in data.channels.items()})
        try:
            x0 = fit_start(model, start, parameters, guess[k], sigma, scale)
            pred = simulate(model, piece, parameters, list(x0))
        except Exception:  # noqa: BLE001 - a diverging model is a result
            return _misfit(model, data, None, sigma)
        if pred["t"].size != piece.t.size:
            return _misfit(model, data, None, sigma)
        for c in chans:
            kept[c][i0 + cut:i1 + 1] = pred[c][cut:]
    m = np.isfinite(kept[chans[0]])
    part = Measurements(t[m], {c: v[m] for c, v in data.channels.items()})
    out = _misfit(model, part, dict({c: v[m] for c, v in kept.items()}, t=t[m]), sigma)
    out["window"] = float(t[-1] - t[0]) / windows
    return out


def _misfit(model: IdentificationModel, data: Measurements, pred: dict | None,
            sigma: Mapping[str, float] | None) -> dict:
    """The errors of :func:`free_run_error` for a prediction ``pred`` (None: did not reach the end)."""
    chans = [c for c in model.measured if c not in model.given]
    ok = pred is not None
    per, rel, rel_n = {}, [], []
    for ch in chans:
        y = data.channels[ch]
        if ok and np.all(np.isfinite(pred[ch])):
            m = ~np.isnan(y)
            e = pred[ch][m] - y[m]
            mse = float(np.mean(e * e))
        else:
            mse = math.inf
        sd = float(np.nanstd(y)) or 1.0
        rms = math.sqrt(mse)
        per[ch] = dict(rms=rms, relative=rms / sd)
        rel.append(rms / sd)
        if sigma is not None:
            above = math.sqrt(max(mse - float(sigma.get(ch, 0.0)) ** 2, 0.0)) if math.isfinite(mse) else math.inf
            per[ch]["above_noise"] = above
            rel_n.append(above / sd)
    overall = float(np.sqrt(np.mean(np.square(rel)))) if rel else math.nan
    out = dict(per_channel=per, overall=overall, prediction=pred, complete=ok)
    if sigma is not None:
        out["overall_above_noise"] = float(np.sqrt(np.mean(np.square(rel_n)))) if rel_n else math.nan
        out["cost"], out["samples"], out["effective_samples"] = standardised_cost(model, data, pred, sigma)
    return out


def standardised_cost(model: IdentificationModel, data: Measurements, pred: Mapping[str, np.ndarray] | None,
                      sigma: Mapping[str, float]) -> tuple[float, int, float]:
    """The cost C = Σ_c Σ_i ((z_c,i − y_c,i)/σ_c)² of a prediction ``pred`` of the measured (non-given)
    channels of ``data`` over their recorded samples (σ_c: the channel's noise level), the number
    of those samples n and the residuals' effective number of samples (:func:`.where.effective_samples`
    of each channel's standardised residual, summed).  Under noise alone, white at level σ, C is
    χ²_n: C/n is the mean square in units of the noise variance.  (inf, n, 0) without a complete
    prediction.  A channel recorded without noise (σ = 0) is measured in units of 1e-12 of its std."""
    chans = [c for c in model.measured if c not in model.given]
    cost, n, n_eff = 0.0, 0, 0.0
    for c in chans:
        y = np.asarray(data.channels[c], dtype=float)
        m = ~np.isnan(y)
        n += int(m.sum())
        if pred is None or not np.all(np.isfinite(pred[c][m])):
            cost = math.inf
            continue
        unit = float(sigma.get(c, 0.0)) or 1e-12 * (float(np.nanstd(y)) or 1.0)
        r = (np.asarray(pred[c], dtype=float)[m] - y[m]) / unit
        cost += float(r @ r)
        n_eff += effective_samples(r) if r.size > 2 else float(r.size)
    return (cost, n, n_eff) if math.isfinite(cost) else (math.inf, n, 0.0)


def misfit(model: IdentificationModel, data: Measurements, parameters: Mapping[str, float], measure: str,
           initial_state="rest", sigma: Mapping[str, float] | None = None) -> dict:
    """The validation misfit by ``measure``: ``"free_run"`` (:func:`free_run_error`, from
    ``initial_state``), ``"windows"`` (:func:`windowed_error`) or ``"fitted_start"`` (one free run
    from the initial state fitted to the whole record, :func:`free_run_start` ``"fitted"``: a
    start fitted to a short burn-in leaves a velocity loosely fixed, and with friction the run
    drifts — on the independent rig's motor-side Coulomb record the Coulomb model then missed its
    validation record by 5.0 times the noise against 1.1 from the whole record's start)."""
    if measure == "windows":
        return windowed_error(model, data, parameters, sigma=sigma)
    if measure == "fitted_start":
        return free_run_error(model, data, parameters, "fitted", sigma=sigma)
    if measure != "free_run":
        raise ValueError(f"measure must be 'free_run', 'windows' or 'fitted_start', got {measure!r}")
    return free_run_error(model, data, parameters, initial_state, sigma=sigma)


def shrink_ratio(before: float, after: float) -> float | None:
    """1 − after/before (None without a finite ``before``; −inf when ``after`` is not finite)."""
    if before is None or after is None or not math.isfinite(before):
        return None
    if before <= 0:
        return 0.0
    return 1.0 - after / before if math.isfinite(after) else -math.inf


def shrink(nominal: EstimationResult, extended: EstimationResult, validation=None, initial_state="rest",
           nominal_model: IdentificationModel | None = None, effects: Sequence[Term] = ()) -> dict:
    """How far it shrinks (module docstring): J and the rows' residual energies before/after on the
    identification record, and the free-run misfit before/after on ``validation`` (if given)."""
    nm = nominal_model or nominal.problem.model
    e0, e1 = row_energy(nominal), row_energy(extended)
    ident = dict(before=nominal.J, after=extended.J, shrink=shrink_ratio(nominal.J, extended.J),
                 per_channel={r: dict(before=e0[r], after=e1.get(r), shrink=shrink_ratio(e0[r], e1.get(r))) for r in e0})
    out = dict(identification=ident)
    if validation is not None:
        val = Measurements.coerce(validation)
        ext_model = extend(nm, effects, data=val) if effects else nm
        out["validation"] = validation_summary(nm, ext_model, val, nominal.parameters, extended.parameters,
                                                initial_state)
    return out


def validation_summary(before_model: IdentificationModel, after_model: IdentificationModel | None,
                       val: Measurements, before_params: Mapping[str, float],
                       after_params: Mapping[str, float] | None, initial_state) -> dict:
    """The misfit on the validation record before/after (``after_model`` None: the nominal model
    alone), per channel and overall, also above the record's noise.  The measure is the free run
    from the record's start — unless the nominal model's free run is off by more than
    :data:`DRIFT_LIMIT` channel standard deviations (an integrating plant whose drift swamps the
    dynamics), then simulations restarted on windows (:func:`windowed_error`); ``measure`` says
    which, both are kept (``free_run``, ``windows``)."""
    chans = [c for c in before_model.measured if c not in before_model.given]
    sigma = noise_level(val, chans)

    def pair(error: Callable[..., dict], *args) -> list[dict]:
        b = error(before_model, val, before_params, *args, sigma=sigma)
        return [b, error(after_model, val, after_params, *args, sigma=sigma) if after_model is not None else b]
    measures = {"free_run": pair(free_run_error, initial_state)}
    use = measure_of(before_model, measures["free_run"][0])
    if use == "windows":
        measures["windows"] = pair(windowed_error)
    summary = {name: _before_after(*ba) for name, ba in measures.items()}
    b, a = measures[use]
    out = dict(summary[use], **summary, noise=sigma, measure=use,
               definition="RMS error per channel; overall: quadratic mean over the channels of RMS error / channel "
                          "std; *_above_noise: sqrt(max(MSE - noise^2, 0)), the noise estimated from the validation "
                          "record; free_run: one simulation from the record's start; windows: simulations restarted "
                          "from the data's state at the start of each window",
               predictions=dict(before=b["prediction"], after=a["prediction"] if after_model is not None else None))
    if use == "windows":
        out["window"] = b["window"]
    return out


def measure_of(model: IdentificationModel, free_run: dict) -> str:
    """The validation measure for ``model`` given its nominal free-run error ``free_run``
    (:func:`free_run_error`): ``"windows"`` when that free run is off by more than
    :data:`DRIFT_LIMIT` channel standard deviations and the model has an initial approximation
    of the states to restart from, else ``"free_run"``."""
    drifts = not free_run["overall"] <= DRIFT_LIMIT
    return "windows" if drifts and model.initial_states is not None else "free_run"


def _before_after(b: dict, a: dict) -> dict:
    per = {}
    for ch in b["per_channel"]:
        B, A = b["per_channel"][ch], a["per_channel"][ch]
        per[ch] = dict(before=B["rms"], after=A["rms"], shrink=shrink_ratio(B["rms"], A["rms"]),
                       before_above_noise=B["above_noise"], after_above_noise=A["above_noise"],
                       shrink_above_noise=shrink_ratio(B["above_noise"], A["above_noise"]))
    return dict(before=b["overall"], after=a["overall"], shrink=shrink_ratio(b["overall"], a["overall"]),
                before_above_noise=b["overall_above_noise"], after_above_noise=a["overall_above_noise"],
                shrink_above_noise=shrink_ratio(b["overall_above_noise"], a["overall_above_noise"]),
                per_channel=per)
