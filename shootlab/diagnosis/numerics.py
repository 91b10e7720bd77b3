"""Numerical causes before physical ones (``docs/diagnosis.md``, "Numerical causes first").

A residual above the noise floor may be the model's own numerics, not a missing effect: a
discretisation too coarse for the record (the 3-element confined-compression model on a record of
a continuum), or shooting intervals too long for the integrator.  Before the effect library is
consulted, two checks:

* **more shooting points** (:func:`points_check`): the nominal model re-estimated on twice the
  shooting points, warm-started, with the last stage of its solver settings (a fixed-step scheme
  then also takes half the step).  J of a converged, resolved estimate does not move; if it drops
  by most of its excess over the floor J_floor the misfit is the grid's.
* **a finer model** (:func:`refinement_check`): a model may declare its refinement,
  ``settings.refine``: a callable returning the same model on a finer discretisation (or None
  when there is none), with ``settings.resolution`` naming the discretisation in words
  ("3 elements").  The refined model is estimated (warm-started where it shares the nominal's
  variables; otherwise from the nominal parameters, with its own initial approximation) and both
  are compared by their free-run misfit on the identification record above the noise
  (:func:`free_run_misfit`, in units of the noise), all driven by the nominal estimate's smoothed
  inputs (:func:`smoothed_record`), so that the input noise a free run propagates does not count.
  J itself is not comparable between discretisations: their equation rows and integrators differ
  (on a 200-element record with 1 % noise on every channel, the 6-element confined model on the
  midpoint rule, 201 points, leaves J = 0.027 where the 3-element one on RK4 leaves 2.7e-5, and
  each is significantly above its own floor).  The refinement is the answer when it brings
  the free-run misfit within the noise (:data:`AT_NOISE`) or removes most of it; it is refined
  again, up to ``refinements`` times, while the misfit keeps falling, so that the verdict names
  a resolution at the noise where one is reached.

"Most" is :data:`NUMERICAL_MIN` (half of the excess, the rule the effect selection uses).
"""
from __future__ import annotations

import math
import time
from typing import Callable, Mapping

import numpy as np

from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from shootlab.estimation.model import IdentificationModel
from .estimators import estimate_retrying, final_stage_options
from shootlab.estimation.data import noise_level
from .floor import NoiseFloor
from .progress import brief, fit_line
from .shrinkage import free_run_error

__all__ = ["numerical_check", "points_check", "refinement_check", "free_run_misfit", "smoothed_record",
           "NUMERICAL_MIN", "AT_NOISE"]

#: the share of the residual's excess over the floor (J) or of the free-run misfit above the noise a
#: numerical change must remove to be the answer
NUMERICAL_MIN = 0.5

#: a free-run misfit at most this many times the noise is within the noise (it adds a quarter of
#: the noise variance; the noise level itself is known to a few per cent)
AT_NOISE = 0.5


def _summary(res: EstimationResult) -> dict:
    m = res.problem.model
    return dict(model=m.name, resolution=m.settings.resolution, points=int(res.points), J=res.J,
                parameters=dict(res.parameters), success=bool(res.success), message=res.message)


def points_check(nominal: EstimationResult, floor: NoiseFloor | None, data: Measurements,
                 estimator: Callable[..., EstimationResult], factor: int = 2,
                 log: Callable[[str], None] | None = None) -> dict:
    """The nominal model on ``factor`` times the shooting intervals (module docstring).  ``numerical``
    when J drops by more than :data:`NUMERICAL_MIN` of its excess over the floor."""
    say = log or (lambda s: None)
    nm = nominal.problem.model
    points = factor * (nominal.points - 1) + 1
    opts = dict(final_stage_options(nm), continuation=None)
    clock = time.perf_counter()
    what = f"numerics: {nm.name} on {points} shooting points"
    try:
        res = estimator(nm, data, n_points=points, start=nominal, **opts)
    except Exception as exc:  # noqa: BLE001 - a check that cannot run is reported, not fatal
        say(f"{what}: not run: {type(exc).__name__}: {brief(str(exc))}")
        return dict(check="points", numerical=False, note=f"not run: {type(exc).__name__}: {exc}")
    out = dict(check="points", before=_summary(nominal), after=_summary(res), numerical=False)
    if not res.success:
        say(fit_line(what, res, time.perf_counter() - clock))
        out["note"] = f"the estimate on {points} points did not converge: {res.message}"
        return out
    excess = nominal.J - (floor.J if floor is not None else 0.0)
    out["change"] = (nominal.J - res.J) / excess if excess > 0 else 0.0
    out["numerical"] = bool(excess > 0 and out["change"] > NUMERICAL_MIN)
    say(f"{what}: J {nominal.J:.5g} -> {res.J:.5g}"
        + (f" ({100 * out['change']:.0f} % of the excess over the floor)" if excess > 0 else "")
        + f", {res.iterations} iterations, {time.perf_counter() - clock:.1f} s")
    return out


def smoothed_record(res: EstimationResult, data: Measurements) -> Measurements:
    """``data`` with each given (input) channel replaced by the estimate's own value of it, the model
    side of its row (measured − ξ, eq. 2.5): the input a free run is driven with, without the
    measurement noise that a free run would otherwise carry into every output."""
    m = res.problem.model
    t = res.t.numpy()
    chans = {k: v.copy() for k, v in data.channels.items()}
    for row, ch in m.channels.items():
        if ch in m.given and ch in chans:
            fitted = np.interp(data.t, t, chans[ch][np.searchsorted(data.t, t)] - res.xi[row].numpy())
            inside = (data.t >= t[0]) & (data.t <= t[-1]) & ~np.isnan(chans[ch])
            chans[ch][inside] = fitted[inside]
    return Measurements(data.t.copy(), chans)


def free_run_misfit(res: EstimationResult, driven: Measurements, sigma: Mapping[str, float],
                    initial_state="rest") -> dict:
    """The free-run misfit of the estimated model on the record ``driven`` above the noise, in units of
    the noise: per measured channel √max(MSE − σ², 0) / σ (:func:`.shrinkage.free_run_error`);
    ``overall`` the quadratic mean over the channels.  Unlike J it means the same for any
    discretisation of the model (its equation rows and integrator do not enter)."""
    fr = free_run_error(res.problem.model, driven, res.parameters, initial_state, sigma)
    per = {ch: (d["above_noise"] / sigma[ch] if sigma.get(ch, 0.0) > 0 else math.inf)
           for ch, d in fr["per_channel"].items()}
    overall = float(np.sqrt(np.mean(np.square(list(per.values()))))) if per else math.nan
    return dict(per_channel=per, overall=overall, complete=fr["complete"])


def refinement_check(nominal: EstimationResult, data: Measurements, estimator: Callable[..., EstimationResult],
                     refinements: int = 2, initial_state="rest",
                     log: Callable[[str], None] | None = None) -> dict | None:
    """The model's declared refinements estimated in turn (module docstring); None when the model
    declares none.  ``numerical`` with the refined model (``use``) when one brings the free-run misfit
    to the noise (:data:`AT_NOISE`) or removes most (:data:`NUMERICAL_MIN`) of the nominal's."""
    say = log or (lambda s: None)
    nm = nominal.problem.model
    if nm.settings.refine is None:
        return None
    sigma = noise_level(data, [c for c in nm.measured if c not in nm.given])
    driven = smoothed_record(nominal, data)          # one input for every model compared
    m0 = free_run_misfit(nominal, driven, sigma, initial_state)
    before = dict(_summary(nominal), misfit=m0)
    say(f"numerics: free-run misfit of {nm.name} above the noise {m0['overall']:.3g} σ")
    out = dict(check="refinement", before=before, steps=[], numerical=False, use=None, refined_model=None)
    if not math.isfinite(m0["overall"]):
        out["note"] = "the nominal model's free run does not reach the end of the record: a refinement cannot be judged"
        return out
    if not m0["overall"] > AT_NOISE:
        out["note"] = "the nominal model's free run is within the noise: no refinement can remove a misfit"
        return out
    current, last = nm, m0["overall"]
    for _ in range(max(refinements, 0)):
        refine = current.settings.refine
        finer = refine() if callable(refine) else None
        if finer is None:
            break
        if not isinstance(finer, IdentificationModel):
            raise ValueError(f"model {current.name}: settings.refine() returned {type(finer).__name__}, "
                             f"not an IdentificationModel")
        clock = time.perf_counter()
        what = f"numerics: the refined model {finer.name} ({finer.settings.resolution or 'finer'})"
        initial = {p: v for p, v in nominal.parameters.items() if p in finer.parameters}
        warm = dict(start=nominal) if finer.names == nm.names else {}
        res, notes = estimate_retrying(estimator, finer, data, say, initial=initial, **warm)
        step = dict(_summary(res), notes=notes)
        out["steps"].append(step)
        if not res.success:
            say(fit_line(what, res, time.perf_counter() - clock))
            step["note"] = f"the refined model could not be estimated: {res.message}"
            break
        mis = free_run_misfit(res, driven, sigma, initial_state)
        step.update(misfit=mis, removed=1.0 - mis["overall"] / m0["overall"])
        say(f"{what}: free-run misfit above the noise {mis['overall']:.3g} σ (nominal {m0['overall']:.3g} σ), "
            f"{res.iterations} iterations, {time.perf_counter() - clock:.1f} s")
        if mis["overall"] <= AT_NOISE or step["removed"] > NUMERICAL_MIN:
            out.update(numerical=True, use=step, refined_model=finer)
        if mis["overall"] <= AT_NOISE or not mis["overall"] < 0.9 * last:    # at the noise, or no longer falling
            break
        current, last = finer, mis["overall"]
    return out


def numerical_check(nominal: EstimationResult, floor: NoiseFloor | None, data: Measurements,
                    estimator: Callable[..., EstimationResult], refinements: int = 2, initial_state="rest",
                    log: Callable[[str], None] | None = None) -> tuple[dict, str | None]:
    """Both checks (more shooting points first, then the declared refinement).  Returns the record
    of the checks (``diagnosis.json``: ``numerical``) and the verdict when the misfit is numerical
    (else None)."""
    out = dict(points=points_check(nominal, floor, data, estimator, log=log))
    nm = nominal.problem.model
    pc = out["points"]
    if pc["numerical"]:
        after = pc["after"]
        return out, (f"the misfit is numerical: use {after['points']} shooting points or more (J {nominal.J:.4g} -> "
                     f"{after['J']:.4g}, {100 * pc['change']:.0f} % of the excess over the noise floor)")
    rc = refinement_check(nominal, data, estimator, refinements, initial_state, log=log)
    if rc is None:
        return out, None
    finer = rc.pop("refined_model")
    out["refinement"] = rc
    if not rc["numerical"]:
        return out, None
    step = rc["use"]
    what = finer.settings.resolution or finer.name
    now = nm.settings.resolution or nm.name
    m0, m1 = rc["before"]["misfit"]["overall"], step["misfit"]["overall"]
    return out, (f"the misfit is numerical: use {what} (the model has {now}): the free-run misfit above the noise "
                 f"falls from {m0:.2g} to {m1:.2g} times the noise"
                 + (", within the noise" if m1 <= AT_NOISE else f" ({100 * step['removed']:.0f} % of it removed)")
                 + f" (J {nominal.J:.4g} -> {step['J']:.4g}, not comparable between discretisations; "
                 f"{step['points']} shooting points; estimated "
                 + ", ".join(f"{k} = {v:.5g}" for k, v in step["parameters"].items()) + ")")
