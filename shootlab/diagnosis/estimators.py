"""Estimation strategies the diagnosis runs (docs/design.md §4; ``docs/diagnosis.md``): an estimator is
``estimator(model, data, initial=None, start=None, **options) -> EstimationResult``.

* :func:`default_estimator` — :func:`shootlab.estimation.estimate` with the model's settings;
* :func:`weight_continuation_estimator` — the report's remedy for large measurement weights
  (§4.2): the weights are reached by continuation, the stages those of a model's own
  ``weight_continuation`` setting (:func:`shootlab.estimation.fit.weight_stages`, estimated in turn by
  :func:`shootlab.estimation.fit.continue_in_weights`) on the measurement rows;
* :func:`estimate_retrying` — an estimator run again on 2, 4 and 8 times the shooting points
  when it does not converge (intervals too long for the problem's growth, report §3.2);
* :func:`one_step` — the linearised re-estimation of a model extended with added terms
  (:func:`shootlab.diagnosis.composition.extend`): one step of the named Newton strategy ``undamped``
  (:class:`shootlab.bvp.newton.UndampedNewton`, ``max_iter=1``) from a converged solution.
"""
from __future__ import annotations

import inspect
import time
from dataclasses import replace
from typing import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .composition import Term, extend, extend_weight
from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import (EstimationResult, _solver_options, continue_in_weights, estimate, posed, sample_times,
                                     summarise, weight_stages)
from shootlab.estimation.model import IdentificationModel
from shootlab.bvp.solver import solve_together
from shootlab.estimation import weights
from shootlab.estimation.data import noise_level

__all__ = ["default_estimator", "weight_continuation_estimator", "one_step", "damped", "giving_up", "GIVE_UP",
           "one_steps", "final_stage_options", "estimate_retrying", "RETRY_POINTS", "with_progress"]


def default_estimator(model: IdentificationModel, data, initial=None, start=None, **options) -> EstimationResult:
    """:func:`shootlab.estimation.estimate` with the model's settings."""
    return estimate(model, data, initial=initial, start=start, **options)


def weight_continuation_estimator(factor: float = 100.0, noise_weights: bool = False, reference: float = 1.0,
                                  cap: Mapping[str, float] | None = None) -> Callable[..., EstimationResult]:
    """An estimator that reaches the model's measurement weights by continuation (the report's
    remedy for the flexible manipulator, §4.2): the measurement rows' diagonal V starts at the
    level of the model-equation rows and is raised by ``factor`` per stage
    (:func:`shootlab.estimation.fit.weight_stages` with those levels on the measurement rows), each
    stage warm-started from the previous one (:func:`~shootlab.estimation.fit.continue_in_weights`).
    With ``start`` (a warm start) it goes straight to the final weights, and falls back to the
    continuation if that fails (the result's message then begins with why the warm start stopped).

    ``noise_weights``: cap each non-given measurement row's weight at ``reference / σ̂²`` (σ̂ the
    channel's noise level, :func:`noise_level`): weights that trust the encoders far beyond their
    noise make the smoother chase it and the Newton iteration crawl.  ``cap``: fixed caps per row.
    Only for models whose V is a constant vector."""
    def estimator(model: IdentificationModel, data, initial=None, start=None, **options) -> EstimationResult:
        data = Measurements.coerce(data)
        V = model.V
        if callable(V) or torch.as_tensor(np.asarray(V, dtype=np.float64) if not isinstance(V, Tensor) else V).ndim != 1:
            return estimate(model, data, initial=initial, start=start, **options)
        V = torch.as_tensor(np.asarray(V, dtype=np.float64) if not isinstance(V, Tensor) else V, dtype=torch.float64).clone()
        meas = [i for i, r in enumerate(model.equations) if r in model.channels]
        eqs = [i for i in range(len(model.equations)) if i not in meas]
        if noise_weights:
            sig = noise_level(data, [model.channels[model.equations[i]] for i in meas])
            for i in meas:
                ch = model.channels[model.equations[i]]
                if ch not in model.given and sig[ch] > 0:
                    V[i] = min(float(V[i]), reference / sig[ch] ** 2)
        for row, c in (cap or {}).items():
            if row in model.equations:
                i = model.equations.index(row)
                V[i] = min(float(V[i]), float(c))
        target = replace(model, V=V)
        warm = None
        if start is not None:
            warm = estimate(target, data, initial=initial, start=start, **options)
            if warm.success:
                return warm
            if options.get("verbose"):
                print(f"-- the warm start at the final weights: {warm.message}", flush=True)
        base = float(V[eqs].min()) if eqs else 1.0
        top = float(V[meas].max()) if meas else base
        levels, lv = [], base
        while lv < top:
            levels.append(lv)
            lv *= factor
        stages = weight_stages(target, levels, meas)
        opts = dict(options)
        n_points, interval = opts.pop("n_points", None), opts.pop("interval", None)
        res = continue_in_weights(stages + [target], data, n_points, initial, interval, opts)
        if warm is not None and res.success:        # said first: the line of a fit shows its first sentence
            res.message = (f"the warm start at the final weights stopped ({warm.message}); by weight "
                           f"continuation from the data's states: {res.message}")
        return res
    return estimator


def final_stage_options(model: IdentificationModel) -> dict:
    """The model's solver settings with a continuation schedule reduced to its last stage."""
    opts = dict(model.settings.solver)
    cont = opts.pop("continuation", None)
    if cont:
        opts.update(cont[-1])
    return opts



def one_step(nominal: EstimationResult, effects: Sequence[Term], data, values: Mapping[str, float],
             pinned: Sequence[str] = (), start: EstimationResult | None = None) -> EstimationResult:
    """The linearised re-estimation of the model extended with ``effects``: one undamped Newton
    step of the extended TPBVP from the nominal solution (new parameters at ``values``; those in
    ``pinned`` held there by a strong prior).  For a term linear in its free parameters this step
    *is* the re-estimation, up to the curvature of the rest of the model: it accounts for how the
    states, inputs and nominal parameters re-adjust (what a regression on the residual alone
    misses when the weights let the smoother absorb part of a structural error).  ``start``: warm
    start from another (extended) estimate instead of the nominal one, for a second step."""
    ext = _pinned(extend(nominal.problem.model, effects, data=data, initial=values), effects, values, pinned)
    return estimate(ext, data, n_points=nominal.points, initial=dict(values), start=start or nominal,
                    **_one_step_options(nominal.problem.model))


def one_steps(nominal: EstimationResult, effects: Sequence[Term], data, starts: Sequence[Mapping[str, float]],
              pinned: Sequence[str] = (), warm: Sequence[EstimationResult | None] | None = None
              ) -> list[EstimationResult]:
    """:func:`one_step` from each of ``starts`` (with ``warm[i]`` for ``start``), the steps taken
    together: the extended models differ only in their boundary conditions (the pinned values), so
    every integration runs all their intervals as one batch (:class:`shootlab.bvp.shooting.ShootingBatch`).
    The same results as one by one to rounding; where the steps cannot be taken together (an
    adaptive integrator) they are taken one by one, and so is a step that could not be
    integrated or met a singular Newton matrix (:func:`one_step` shortens or reports it)."""
    data = Measurements.coerce(data)
    warm = list(warm) if warm is not None else [None] * len(starts)
    if len(starts) < 2:
        return [one_step(nominal, effects, data, v, pinned, w) for v, w in zip(starts, warm)]
    clock = time.perf_counter()
    nm = nominal.problem.model
    opts = _one_step_options(nm)
    models = [weights.from_data(_pinned(extend(nm, effects, data=data, initial=v), effects, v, pinned), data)
              for v in starts]          # as estimate() has them
    tpbvps = [posed(m, data, nominal.points, dict(v), None, w or nominal) for m, v, w in zip(models, starts, warm)]
    probs = [p for p, _, _, _ in tpbvps]
    first = probs[0].bvp()               # one vector field: only the boundary conditions differ
    bvps = [first] + [replace(p.bvp(), rhs=first.rhs, jac=first.jac) for p in probs[1:]]
    t, (a, b) = tpbvps[0][1], tpbvps[0][3]
    together = solve_together(bvps, t, [X0 for _, _, X0, _ in tpbvps],
                              **_solver_options(models[0], opts))
    if together is None:
        return [one_step(nominal, effects, data, v, pinned, w) for v, w in zip(starts, warm)]
    results, values = together
    seconds = (time.perf_counter() - clock) / len(starts)
    return [summarise(p, r, a, b, seconds, X=X) if r is not None else one_step(nominal, effects, data, v, pinned, w)
            for p, r, X, v, w in zip(probs, results, values(sample_times(probs[0], a, b)), starts, warm)]


def _pinned(ext: IdentificationModel, effects: Sequence[Term], values: Mapping[str, float],
            pinned: Sequence[str]) -> IdentificationModel:
    """``ext`` with the parameters ``pinned`` held at ``values`` by a strong prior (W_a = 1e8/scale²)."""
    if not pinned or callable(ext.W_a):
        return ext
    Wa = torch.as_tensor(extend_weight(ext.W_a, ext.nx, 0, 0.0)).clone()
    Wa = torch.diag(Wa) if Wa.ndim == 1 else Wa
    for p in pinned:
        j = ext.names.index(p)
        sc = float(next(e.scale.get(p, abs(values[p]) or 1.0) for e in effects if p in e.parameters)) or 1.0
        Wa[j, j] = 1e8 / sc ** 2
    return replace(ext, W_a=Wa)


def _one_step_options(model: IdentificationModel) -> dict:
    """The solver options of a one-step re-estimate: the model's last stage, one undamped step."""
    opts = final_stage_options(model)
    opts.update(max_iter=1, newton="undamped", newton_options={}, max_growth=None, continuation=None)
    return opts


#: how the diagnosis's re-estimates of candidate models give up (:func:`damped`; the library's
#: estimator in ``shootlab.diagnosis.reestimation.reestimate``): a damping factor below Deuflhard's floor
#: for highly nonlinear problems, or max|F| not halved in 10 iterations
#: (:class:`shootlab.bvp.newton.DeuflhardNewton`) — a candidate that fails is reported and the next
#: start, or the simpler model, is tried.  On the diagnosis benchmark no run that converged came
#: near either limit, while the runs that failed spent most of their time before failing.  Such a run is not
#: tried again with the other Newton strategies (``fallback=False``, :func:`shootlab.estimation.estimate`).
GIVE_UP = dict(min_damping=1e-4, stall=10)


def giving_up(model: IdentificationModel, estimator: Callable | None = None) -> dict:
    """The options that make an estimate of ``model`` give up as :data:`GIVE_UP` says
    (``newton_options``, the model's own over them, and ``fallback=False`` where the estimator
    takes it) where its Newton is the default ``deuflhard`` and ``estimator``, if given, takes
    options; else {}."""
    solve = model.settings.solver
    takes = estimator is None or _takes(estimator, "newton_options")
    if solve.get("newton", "deuflhard") != "deuflhard" or not takes:
        return {}
    out = dict(newton_options={**GIVE_UP, **(solve.get("newton_options") or {})})
    if estimator is None or _takes(estimator, "fallback"):
        out["fallback"] = False
    return out


def damped(nominal: EstimationResult, effects: Sequence[Term], data, values: Mapping[str, float],
           max_iter: int = 50, warm: bool = False) -> EstimationResult:
    """The full re-estimation of the model extended with ``effects`` with the model's own globalised
    Newton, the model's parameters from the nominal estimate and the new ones from ``values``: what
    replaces the one undamped step of :func:`one_step` where that step diverges or leaves the
    effect's bounds.  The states start from the model's initial approximation of the data (cold),
    or with ``warm`` from the nominal solution — which can mislead: its smoothed states carry the
    misfit the effect is to explain (on a one-axis drive with Stribeck friction, Coulomb friction
    from the nominal solution converges to f = −1.2 with J twice the nominal one, from the data's
    states to f = 1.39 with J 1 % of it)."""
    ext = extend(nominal.problem.model, effects, data=data, initial=values)
    opts = final_stage_options(nominal.problem.model)
    opts.update(max_iter=max_iter, continuation=None, **giving_up(ext))
    return estimate(ext, data, n_points=nominal.points, initial=dict(nominal.parameters, **values),
                    start=nominal if warm else None, **opts)


#: shooting-point multiples tried when an estimate of the diagnosis does not converge
RETRY_POINTS = (2, 4, 8)


def estimate_retrying(estimator: Callable[..., EstimationResult], model: IdentificationModel, data,
                      say: Callable[[str], None], first: EstimationResult | None = None,
                      **kw) -> tuple[EstimationResult, list[str]]:
    """``estimator(model, data, **kw)`` (or ``first``, a failed result of it the caller has
    reported); when it does not converge, again on 2, 4 and 8 times as many shooting points
    (intervals too long for the problem's growth, or a Newton iteration that a finer grid makes
    more linear).  The last result and a note per failed attempt."""
    from .progress import brief

    res = first if first is not None else estimator(model, data, **kw)
    notes = []
    base = res.points
    for factor in RETRY_POINTS:
        if res.success:
            break
        if res is first:
            say(f"  {model.name}: retrying on {factor * base} points ...")
        else:
            notes.append(f"{model.name} on {res.points} shooting points did not converge: {res.message}")
            say(f"  {model.name} on {res.points} shooting points did not converge: {brief(res.message)}; "
                f"retrying on {factor * base} points ...")
        res = estimator(model, data, n_points=factor * base, **kw)
    return res, notes


def with_progress(estimator: Callable, on: bool) -> Callable:
    """``estimator`` with ``verbose=True`` (a progress line per Newton iteration) when ``on`` and it
    takes that option (the built-in ones pass ``**options`` to :func:`estimate`)."""
    if not on or not _takes(estimator, "verbose"):
        return estimator
    return lambda *args, **kw: estimator(*args, verbose=True, **kw)


def with_device(estimator: Callable, device) -> Callable:
    """``estimator`` solving on ``device`` (``estimate``'s ``device=``) when that is not the CPU
    and it takes that option; else ``estimator`` itself."""
    from shootlab.bvp.device import resolve_device

    dev = resolve_device(device)
    if dev.type == "cpu" or not _takes(estimator, "device"):
        return estimator
    return lambda *args, **kw: estimator(*args, **dict(kw, device=dev))


def _takes(estimator: Callable, option: str) -> bool:
    """Whether ``estimator`` takes the keyword ``option`` (by name or ``**options``)."""
    params = inspect.signature(estimator).parameters.values()
    return any(p.kind is inspect.Parameter.VAR_KEYWORD or p.name == option for p in params)
