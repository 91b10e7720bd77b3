"""The leading candidates confirmed by converged re-estimation (``docs/diagnosis.md``, "Leading
candidates re-estimated in full").

The ranking (:func:`.which.rank`) scores most candidates by one undamped Newton step of the extended
estimation problem from the nominal solution: exact for a term linear in everything, a misjudgement
where the extended model's response is far from linear in a parameter — a cubic stiffness k3·Δ³
stiffens the very motion that makes Δ, and one step from k3 = 0, where ∂(k3 Δ³)/∂Δ = 0, sees none
of it.  Before the diagnosis answers "no candidate explains it" or "inconclusive", and whenever
the validation record alone carries the evidence of a structural error, :func:`confirm`
re-estimates in full

* the :data:`LEADERS` leading models by the ranking's criterion (singles and pairs), and
* every single whose one-step score is unreliable (:func:`unreliable`): a parameter declared
  nonlinear (:attr:`.effects.Effect.nonlinear`), or a step that diverged and was not replaced by a
  converged re-estimate,

each by the damped Newton of :func:`.which.fully_estimated` from the data's states, started from
its one-step parameters and — for a declared nonlinear parameter — from a log-spaced scan of its
magnitude (:func:`scan_starts`: one undamped step with the parameter pinned at each value, the steps
taken together, the :data:`SCAN_FULL` best values then re-estimated in full).  A converged
re-estimate replaces the candidate's score (``Candidate.full``; the step's J stays in
``Candidate.linearised``); a candidate none of whose starts converges is not scored (J = ∞,
``Candidate.failed`` says why): a score from a failed re-estimate is never a result.
:func:`reselect` then weighs and selects again (:func:`.selection.weigh`, :func:`.selection.select`), and
:func:`validation_costs` measures each confirmed candidate on the validation record (its cost
C_v, the shrink 1 − C_v/C_v,nominal and the share of the nominal misfit's excess over the noise
floor it removes).
"""
from __future__ import annotations

import math
import time
from typing import Callable, Mapping, Sequence

import numpy as np

from .composition import extend
from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from .effects import Effect, Library
from .estimators import one_steps
from .progress import brief
from .shrinkage import misfit
from .selection import Candidate, ranking_table, select, weigh
from .which import fully_estimated

__all__ = ["confirm", "leaders", "unreliable", "scan_starts", "reselect", "validation_costs", "failures", "LEADERS",
           "SCAN_FULL", "SCAN_PER_DECADE"]

#: the leading models (by the ranking's criterion) re-estimated in full before a verdict
LEADERS = 3
#: scan values of a declared nonlinear parameter per decade of its magnitude
SCAN_PER_DECADE = 2
#: the best scan values (by the pinned step's J) from which a full re-estimate starts
SCAN_FULL = 2


def _nonlinear(effect: Effect, v) -> dict[str, tuple[float, float]]:
    """The effect's declared nonlinear parameters and their ranges (evaluated on ``v`` if a function)."""
    decl = effect.nonlinear(v) if callable(effect.nonlinear) else effect.nonlinear
    return {p: (float(lo), float(hi)) for p, (lo, hi) in (decl or {}).items()}


def unreliable(candidate: Candidate, library: Library) -> str | None:
    """Why a single's one-step score cannot be trusted, or None: a parameter its effect declares
    nonlinear, or a step that diverged (or left the effect's bounds) and was not re-estimated in
    full (where the residual is not significant the ranking does not, :func:`.which.score`; where
    it is, a diverged step was re-estimated from every start of :func:`.which.fully_estimated`
    already, and J = ∞ says that none converged)."""
    if len(candidate.effects) != 1 or candidate.unidentifiable:
        return None
    effect = library[candidate.effects[0]]
    if effect.nonlinear:
        return "declared nonlinear in " + (", ".join(effect.nonlinear) if not callable(effect.nonlinear)
                                           else "its parameters")
    if not math.isfinite(candidate.J) and (candidate.why or "").startswith("not evaluated"):
        return "its step diverged"
    return None


def leaders(models: Sequence[Candidate], library: Library, n: int = LEADERS) -> list[Candidate]:
    """The ``n`` leading models with effects by the criterion (finite), then every single whose score
    is :func:`unreliable`, each once."""
    ranked = sorted((m for m in models if m.effects and math.isfinite(m.criterion)), key=lambda m: m.criterion)
    out = ranked[:max(n, 0)]
    out += [m for m in models if unreliable(m, library) and not any(m is o for o in out)]
    return out


def scan_starts(effect: Effect, v, values: Mapping[str, float], per_decade: int = SCAN_PER_DECADE) -> list[dict]:
    """Starting values of the effect's parameters for a scan of its declared nonlinear ones
    (:attr:`.effects.Effect.nonlinear`): each magnitude from ``low`` to ``high``, ``per_decade``
    values per decade (log-spaced, both ends included), with each sign its bounds allow; the other
    parameters at ``values``.  Several nonlinear parameters are scanned one at a time."""
    out = []
    for p, (lo, hi) in _nonlinear(effect, v).items():
        lo, hi = abs(lo), abs(hi)
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > 0):
            continue
        lo = min(max(lo, 1e-300), hi)
        count = max(int(math.ceil(per_decade * math.log10(hi / lo))) + 1, 1)
        b_lo, b_hi = effect.bounds.get(p, (-math.inf, math.inf))
        for mag in np.geomspace(lo, hi, count):
            for val in (float(mag), -float(mag)):
                if b_lo <= val <= b_hi:
                    out.append(dict(values, **{p: val}))
    return out


def _scanned(nominal: EstimationResult, effect: Effect, data: Measurements, candidate: Candidate, design,
             say: Callable[[str], None]) -> list[tuple[float, dict]]:
    """The :data:`SCAN_FULL` best scan values of the candidate's declared nonlinear parameters by the
    J of one undamped step with them pinned (:func:`scan_starts`; the steps taken together), with
    that J."""
    v = design.vars([effect], candidate.parameters)
    starts = scan_starts(effect, v, candidate.parameters)
    if not starts:
        return []
    pinned = list(_nonlinear(effect, v)) + [p for p in candidate.shape if p not in _nonlinear(effect, v)]
    try:
        steps = one_steps(nominal, [effect], data, starts, pinned=pinned)
    except Exception as exc:  # noqa: BLE001 - the scan is reported and skipped
        say(f"  {effect.name}: scan not taken ({type(exc).__name__}: {brief(str(exc))})")
        return []
    scored = sorted(((r.J, s) for r, s in zip(steps, starts) if math.isfinite(r.J)), key=lambda js: js[0])
    if scored:
        say(f"  {effect.name}: scan of {', '.join(_nonlinear(effect, v))} over {len(starts)} values, best "
            + ", ".join(f"{p} = {s[p]:.3g} (J {J:.4g})" for J, s in scored[:SCAN_FULL] for p in _nonlinear(effect, v)))
    return scored[:SCAN_FULL]


def confirm(nominal: EstimationResult, models: Sequence[Candidate], library: Library, data: Measurements,
            nu: float, design, n: int = LEADERS, log: Callable[[str], None] | None = None,
            known: Sequence[EstimationResult] = ()) -> list[Candidate]:
    """Re-estimate the :func:`leaders` of ``models`` in full (module docstring), in place: a converged
    re-estimate becomes the candidate's score (``full``, ``linearised`` the step's J), a failure
    takes the candidate out of the comparison (J = ∞, ``failed``).  A candidate that already holds
    a converged full re-estimate (a diverged step replaced by :func:`.which.fully_estimated`) is
    kept as it is, unless its effect declares a nonlinear parameter, which is scanned as well;
    so is one whose model ``known`` holds a converged estimate of (the verdict's, by the library's
    estimator).  ``design``: the ranking's regression design (the estimated variables the
    declared ranges are computed from).  Returns the leaders."""
    say = log or (lambda s: None)
    lead = leaders(models, library, n)
    for c in lead:
        done = next((r for r in known if r.success and sorted(r.problem.model.settings.effects)
                     == sorted(c.effects)), None)
        if done is not None and not c.full:
            c.linearised = c.J
            c.update(done, nu)
            c.full, c.failed, c.why = True, None, None
        effects = [library[e] for e in c.effects]
        single = effects[0] if len(effects) == 1 else None
        declared = single is not None and bool(single.nonlinear)
        if c.full and c.result is not None and not declared:
            continue
        clock = time.perf_counter()
        best: tuple[float, dict, EstimationResult] | None = None
        why = []

        def full_from(start: Mapping[str, float]) -> None:
            nonlocal best
            bounds = {p: e.bounds.get(p, (-math.inf, math.inf)) for e in effects for p in e.parameters}
            start = {p: min(max(v, bounds[p][0]), bounds[p][1]) for p, v in start.items() if p in bounds}
            J, par, res = fully_estimated(nominal, effects, data, start, [], why.append,
                                          context="re-estimated in full as a leading candidate")
            if res is not None and (best is None or J < best[0]):
                best = (J, par, res)
        if c.full and c.result is not None:
            best = (c.J, dict(c.parameters), c.result)
        elif not c.unidentifiable:          # from the step's parameters (the screened ones where it diverged)
            full_from(c.parameters)
        if declared:        # a scan value whose pinned step already beats the best full re-estimate
            for J_step, start in _scanned(nominal, single, data, c, design, say):
                if best is None or J_step < best[0]:
                    full_from(start)
        if c.full and c.result is not None and best[2] is c.result:
            say(f"  {c.label}: its full re-estimate holds (J {c.J:.5g}), {time.perf_counter() - clock:.1f} s")
            continue
        c.linearised = c.linearised if c.linearised is not None else c.J
        if best is None:
            c.failed = why[-1] if why else "no start to re-estimate it from"
            c.J, c.result, c.criterion, c.full = math.inf, None, math.inf, False
            say(f"  {c.label}: not confirmed by a full re-estimate ({brief(c.failed)}), "
                f"{time.perf_counter() - clock:.1f} s")
            continue
        J, par, res = best
        c.update(res, nu)
        c.full, c.failed, c.why = True, None, None
        say(f"  {c.label}: J {c.linearised:.5g} (one step) -> {J:.5g} re-estimated in full in {res.iterations} "
            f"iterations ({', '.join(f'{p} = {v:.4g}' for p, v in par.items())}), {time.perf_counter() - clock:.1f} s")
    return lead


def reselect(which: dict, library: Library, J0: float, J_floor: float | None, significant: bool,
             explained_min: float) -> None:
    """The weights, the ranking and the selection of ``which`` (:func:`.which.rank`'s dict) computed
    again from its candidates' scores, in place (after :func:`confirm`)."""
    models = which["models"]
    weigh(models, J0, J_floor)
    none = next(m for m in models if not m.effects)
    singles = {m.effects[0]: m for m in models if len(m.effects) == 1}
    effects = [library[n] for n in singles]
    ranking = ranking_table(effects, singles, models, none)
    for r in ranking:
        c = singles[r["effect"]]
        r.update(full=c.full, linearised=c.linearised, failed=c.failed, validation_shrink=c.validation_shrink)
    best, selected, verdict = select(models, singles, ranking, J_floor, significant, explained_min)
    models.sort(key=lambda m: m.criterion)
    which.update(ranking=ranking, best=best, selected=selected, verdict=verdict,
                 selected_parameters=dict(best.parameters) if selected else {},
                 explained_excess=best.explained_excess if selected else None)


def validation_costs(nominal: EstimationResult, candidates: Sequence[Candidate], library: Library,
                     validation: Measurements, evidence: dict, log: Callable[[str], None] | None = None) -> None:
    """Each candidate holding a converged full re-estimate measured on the validation record, in place:
    ``validation_cost`` C_v of the extended model with its estimate, by the measure of ``evidence``
    (:func:`.floor.validation_evidence`: the free run or restarted windows, σ the record's noise),
    ``validation_shrink`` 1 − C_v / C_v,nominal and ``validation_explained`` (C_v,nominal − C_v) /
    (C_v,nominal − C_v,floor): the share of the nominal misfit's excess over what the noise floor
    explains that it removes."""
    say = log or (lambda s: None)
    nm = nominal.problem.model
    C0 = evidence["cost"]
    C_floor = evidence["floor_misfit"] ** 2 * evidence["samples"]
    for c in candidates:
        if not (c.full and c.result is not None and c.result.success):
            continue
        clock = time.perf_counter()
        try:
            ext = extend(nm, [library[e] for e in c.effects], data=validation)
            m = misfit(ext, validation, c.result.parameters, evidence["measure"], library.initial_state,
                       sigma=evidence["noise"])
            C = m["cost"]
        except Exception as exc:  # noqa: BLE001 - a model that cannot be run has no validation cost
            say(f"  {c.label}: no validation free run ({type(exc).__name__}: {brief(str(exc))})")
            continue
        c.validation_cost = C
        c.validation_effective_samples = m.get("effective_samples")
        c.validation_shrink = 1.0 - C / C0 if C0 > 0 and math.isfinite(C) else -math.inf
        excess = C0 - C_floor
        c.validation_explained = (C0 - C) / excess if excess > 0 and math.isfinite(C) else 0.0
        say(f"  {c.label}: validation cost {C:.5g} (shrink {c.validation_shrink:+.3f}, "
            f"{100 * c.validation_explained:.0f} % of the excess over the floor), {time.perf_counter() - clock:.1f} s")


def failures(candidates: Sequence[Candidate]) -> list[str]:
    """``label (why)`` for each candidate whose full re-estimate failed."""
    return [f"{c.label} ({brief(c.failed)})" for c in candidates if c.failed]
