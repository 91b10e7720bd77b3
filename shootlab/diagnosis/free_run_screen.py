"""Which effect, judged by the free run on the validation record (``docs/diagnosis.md``).

On a stiff model the TPBVP's J is not a misfit measure: on the confined-compression model an
unmodelled effect moves J of the estimate by 0.08–5.7× that of the clean record, down as often as
up, because the model errors ε absorb it (``benchmarks/mixture_misfit.py``).  What a user sees —
the free run against the record — does separate them.  A library that declares
``free_run_screen=True`` gets this second test when the TPBVP's verdict is not a confirmed one:

1. **the model's own resolution first**: the nominal model and its declared refinement
   (``settings.refine``, e.g. twice the elements) are fitted by output error
   (:mod:`shootlab.estimation.output_error`) to the identification record; while the refinement lowers the
   validation record's free-run cost by at least :data:`SHRINK_MIN`, it replaces the model
   (at most :data:`MAX_REFINEMENTS` times) — the misfit was partly the discretisation;
2. **every candidate** (taken by name from the refined model's library when the model was
   refined: the terms name its rows) is added to that model and fitted by output error, started from the
   nominal fit (a failed fit is recorded against the candidate, the screen goes on);
3. **the validation record decides**: the cost C_v = Σ ((y − z)/σ)² of the free run there, with
   σ the validation record's noise level; a candidate counts when its fit converged and
   C_v shrinks by at least :data:`SHRINK_MIN` (on clean independent records every candidate's
   shrink was ≤ 0.01, with effects 0.15–0.57 for the right one);
4. the verdict is the candidate with the largest shrink; its confidence the Akaike-type weight
   exp(−ΔC_v / 2s²) / Σ over the counting candidates, s² = C_v/ν_eff of the best (its cost per
   effective sample of its residual, :func:`.where.effective_samples`), so that two candidates
   that explain the record alike
   (*look-alikes*, e.g. a filter resistance and a machine compliance at moderate size) share it
   and both are named.

Free runs of the nominal and the extended models by the same general integrator
(:func:`shootlab.estimation.free_run.simulate`), from the library's start (``initial_state``) on both records,
so that the comparison is like for like.

Steps 3–4 serve every model family (:func:`rank_by_validation`): where the validation record
carries the evidence of a structural error (:func:`shootlab.diagnosis.floor.validation_evidence`),
the leading candidates' converged TPBVP re-estimates (:mod:`shootlab.diagnosis.confirmation`) are
judged by their validation cost in the same way — one free run each instead of an output-error
fit, and a candidate counts only when it removes at least half of the nominal misfit's excess
over the noise floor.  The output-error fits remain for the libraries that declare
``free_run_screen=True``, whose TPBVP J is not a misfit measure.
"""
from __future__ import annotations

import math
import time
from typing import Callable, Mapping, Sequence

import numpy as np

from .composition import extend
from shootlab.estimation.data import Measurements
from shootlab.estimation.model import IdentificationModel
from shootlab.estimation.free_run import FreeRun
from shootlab.estimation.data import noise_level
from shootlab.estimation.output_error import OutputErrorResult, estimate_output_error
from .effects import Effect, Library
from .progress import brief
from .shrinkage import free_run_start, validation_summary
from .where import effective_samples

__all__ = ["screen", "rank_by_validation", "validation_weights", "output_error_fit", "selection", "SHRINK_MIN",
           "MAX_REFINEMENTS", "LOOK_ALIKE"]

#: the least relative shrink of the validation free-run cost that counts (a refinement or an effect)
SHRINK_MIN = 0.05
#: refinements of the model's resolution tried in turn
MAX_REFINEMENTS = 2
#: candidates whose Akaike-type weight is at least this are named beside the best (look-alikes)
LOOK_ALIKE = 0.2


def _general(how) -> FreeRun:
    """The output-error simulator: the general free run from the library's start."""
    return FreeRun(start=lambda model, data, params: free_run_start(model, data, how, params))


def _cost(model: IdentificationModel, data: Measurements, params: Mapping[str, float], how,
          sigma: Mapping[str, float]) -> tuple[float, float]:
    """Σ ((free run − z)/σ)² over the measured (non-given) channels of ``data`` (inf if the free run
    fails), and the residuals' effective number of samples (:func:`.where.effective_samples`)."""
    try:
        y = _general(how)(model, data, params)
    except Exception:  # noqa: BLE001 - a diverging model is a result
        return math.inf, 0.0
    cost, n_eff = 0.0, 0.0
    for c in (c for c in model.measured if c not in model.given):
        r = (np.asarray(y[c]) - data.channels[c]) / sigma[c]
        r = r[np.isfinite(data.channels[c])]
        cost += float(np.sum(r * r))
        n_eff += effective_samples(r - r.mean()) if r.size > 2 else float(r.size)
    return (cost, n_eff) if math.isfinite(cost) else (math.inf, 0.0)


def output_error_fit(model: IdentificationModel, data: Measurements, initial: Mapping[str, float], how,
                     exact_first: bool = False, bounds: Mapping[str, tuple[float, float]] | None = None,
                     max_runs: int | None = None) -> OutputErrorResult:
    """Output error with the general free run; ``exact_first``: from the model's own simulator's fit;
    ``bounds``, ``max_runs``: :func:`~shootlab.estimation.output_error.estimate_output_error`'s.
    With the start ``how`` = ``"fitted"`` the states at the record's first sample are estimated with
    the parameters."""
    if exact_first and model.settings.simulate is not None:
        quick = estimate_output_error(model, data, initial=initial, fit_initial_state=False, bounds=bounds)
        if quick.success:
            initial = quick.parameters
    return estimate_output_error(model, data, initial=initial, simulator=_general(how),
                                 fit_initial_state=how == "fitted", tol=1e-6, bounds=bounds, max_runs=max_runs)


def screen(model: IdentificationModel, library: Library, candidates: Sequence[Effect], data: Measurements,
           validation: Measurements, initial: Mapping[str, float] | None = None,
           log: Callable[[str], None] | None = None) -> dict:
    """The free-run screen (module docstring).  Returns a dict: ``model`` (the model the candidates
    were added to), ``refinements`` (each tried: model name, validation cost, shrink), ``nominal``
    (its output-error fit), ``candidates`` (per effect: success, parameters, identification and
    validation cost and shrink, weight, or the error), ``selected`` ([] or one effect), ``look_alikes``,
    ``confidence``, ``verdict`` and ``shrink`` (the validation table of
    :func:`shootlab.diagnosis.shrinkage.validation_summary`, nominal → extended output-error fits)."""
    say = log or (lambda s: None)
    clock = time.perf_counter()
    how = library.initial_state
    chans = [c for c in model.measured if c not in model.given]
    sigma_v = noise_level(validation, chans)
    start = dict(model.prior, **(initial or {}))
    nominal = output_error_fit(model, data, start, how, exact_first=True)
    if not nominal.success:
        return dict(model=model.name, refinements=[], nominal=_summary(nominal), candidates=[], selected=[],
                    look_alikes=[], confidence=None, shrink=None, seconds=time.perf_counter() - clock,
                    verdict=f"the free-run screen could not fit the nominal model {model.name}: {nominal.message}")
    Cv, _ = _cost(model, validation, nominal.parameters, how, sigma_v)
    say(f"free run: {model.name} by output error, validation cost {Cv:.4g}, {time.perf_counter() - clock:.1f} s")
    refinements = []
    for _ in range(MAX_REFINEMENTS):
        refine = model.settings.refine
        finer = refine() if callable(refine) else None
        if finer is None:
            break
        tick = time.perf_counter()
        fit = output_error_fit(finer, data, nominal.parameters, how, exact_first=True)
        Cf = _cost(finer, validation, fit.parameters, how, sigma_v)[0] if fit.success else math.inf
        gain = 1.0 - Cf / Cv
        refinements.append(dict(model=finer.name, resolution=finer.settings.resolution, success=fit.success,
                                validation_cost=Cf, shrink=gain))
        say(f"free run: {finer.name}, " + (f"validation cost {Cf:.4g} (shrink {gain:+.2f})" if fit.success else
                                           f"not converged: {brief(fit.message)}")
            + f", {time.perf_counter() - tick:.1f} s")
        if not (fit.success and gain >= SHRINK_MIN):
            break
        model, nominal, Cv = finer, fit, Cf
    if any(r["model"] == model.name for r in refinements):
        candidates = _for_refined(model, candidates, data)
    rows = []
    for effect in candidates:
        row: dict = dict(effect=effect.name)
        tick = time.perf_counter()
        try:
            ext = extend(model, [effect], data=data)
            fit = output_error_fit(ext, data, dict(ext.prior, **nominal.parameters), how)
            row.update(success=fit.success, message=fit.message, parameters=fit.parameters,
                       identification_cost=fit.cost, identification_shrink=1.0 - fit.cost / nominal.cost)
            if fit.success:
                cv, n_eff = _cost(extend(model, [effect], data=validation), validation, fit.parameters, how, sigma_v)
                row.update(validation_cost=cv, validation_shrink=1.0 - cv / Cv, validation_effective_samples=n_eff)
        except Exception as exc:  # noqa: BLE001 - one candidate's failure is recorded, the screen goes on
            row.update(success=False, message=f"{type(exc).__name__}: {exc}")
        say(f"free run: + {effect.name}: " + (f"validation shrink {row['validation_shrink']:+.3f}"
                                              if "validation_shrink" in row else f"not converged: {brief(row['message'])}")
            + f", {time.perf_counter() - tick:.1f} s")
        rows.append(row)
    counting = [r for r in rows if r.get("success") and r.get("validation_shrink", -math.inf) >= SHRINK_MIN]
    out = dict(model=model.name, method="output-error", refinements=refinements, nominal=_summary(nominal), nominal_validation_cost=Cv,
               candidates=rows, selected=[], look_alikes=[], confidence=None, shrink=None)
    refined, why = model.settings.resolution or model.name, _refined_why(refinements)
    if not counting:
        out["verdict"] = (f"numerical: use {refined} ({why}); no effect beyond it" if why else
                          f"no candidate makes the validation free run shrink by {100 * SHRINK_MIN:.0f} %")
        out["seconds"] = time.perf_counter() - clock
        return out
    best, alikes = validation_weights(counting)
    out.update(selection(model, next(e for e in candidates if e.name == best["effect"]), validation, out, best,
                         best["weight"], how, alikes))
    out["seconds"] = time.perf_counter() - clock
    return out


def _refined_why(refinements: list[dict]) -> str:
    """Why the screen refined the model, in words ("" where it did not)."""
    return (f"the coarser model's own discretisation explained {100 * refinements[0]['shrink']:.0f} % of the "
            f"validation misfit" if refinements and refinements[0]["shrink"] >= SHRINK_MIN else "")


def selection(model: IdentificationModel, effect: Effect | Sequence[Effect], validation: Measurements, screened: dict,
              row: dict, confidence: float, how, alikes: Sequence[str] = ()) -> dict:
    """The screen's answer for one candidate (an effect, or several taken together: ``row["effects"]``
    names them): ``selected``, ``look_alikes``, ``confidence``, ``extended`` (its output-error fit),
    ``shrink`` (identification and validation, nominal → extended) and ``verdict``.  ``model``: the
    model the candidates were added to; ``screened``: the screen's result (its nominal fit and
    refinements); ``row``: the candidate's row there."""
    nominal, why = screened["nominal"], _refined_why(screened.get("refinements") or [])
    effects = [effect] if isinstance(effect, Effect) else list(effect)
    names = list(row.get("effects") or [row["effect"]])
    ext = extend(model, effects, data=validation)
    shrink = dict(identification=dict(before=nominal["cost"], after=row["identification_cost"],
                                      shrink=row["identification_shrink"], per_channel={}),
                  validation=validation_summary(model, ext, validation, nominal["parameters"], row["parameters"],
                                                how))
    verdict = (f"structural error in the free run: {row['effect']}"
               + (f" (or {', '.join(alikes)}: alike on these records)" if alikes else "")
               + (f" with {model.settings.resolution or model.name} ({why})" if why else "")
               + f"; the validation free-run cost shrinks {100 * row['validation_shrink']:.0f} % "
                 f"(confidence {confidence:.2f})")
    return dict(selected=names, look_alikes=list(alikes), confidence=confidence,
                extended=dict(model="+".join([model.name] + names), method="output-error", success=True,
                              parameters=row["parameters"], cost=row["identification_cost"], effects=names),
                shrink=shrink, verdict=verdict)


def validation_weights(counting: list[dict]) -> tuple[dict, list[str]]:
    """The Akaike-type weights exp(−ΔC_v / 2s²) of the rows that count (in place, ``weight``; s² =
    C_v/ν_eff of the best: its cost per effective sample of its residual, a validation residual
    that is mostly misfit being strongly correlated, so that a small cost difference says little),
    the best row and the look-alikes (weight at least :data:`LOOK_ALIKE`)."""
    best = min(counting, key=lambda r: r["validation_cost"])
    s2 = best["validation_cost"] / max(best.get("validation_effective_samples") or 1.0, 1.0)
    for r in counting:
        r["weight"] = math.exp(-(r["validation_cost"] - best["validation_cost"]) / (2.0 * s2))
    total = sum(r["weight"] for r in counting)
    for r in counting:
        r["weight"] /= total
    return best, [r["effect"] for r in counting if r is not best and r["weight"] >= LOOK_ALIKE]


def rank_by_validation(model: str, candidates: Sequence, evidence: dict, explained_min: float = 0.5) -> dict:
    """The free-run screen's judgement (module docstring, steps 3–4) on the candidates' converged
    TPBVP re-estimates instead of output-error fits: every model family, where the validation
    record carries the evidence of a structural error
    (:func:`shootlab.diagnosis.confirmation.validation_costs` measured each candidate there).  A
    candidate counts when its re-estimate converged, its validation cost shrinks by at least
    :data:`SHRINK_MIN` and it removes at least ``explained_min`` of the nominal model's misfit
    beyond the noise floor's (``Candidate.validation_explained``).  Returns the record kept as
    :attr:`shootlab.diagnosis.Diagnosis.free_run`: ``method`` "re-estimates", ``candidates`` (a
    row per candidate measured), ``order`` (the counting candidates, the lowest cost first),
    ``weights`` (label → Akaike-type weight, :func:`validation_weights`), ``look_alikes``."""
    rows, by_label = [], {}
    for c in candidates:
        if c.validation_cost is None:
            continue
        rows.append(dict(effect=c.label, effects=list(c.effects), success=True, parameters=dict(c.parameters),
                         identification_J=c.J, validation_cost=c.validation_cost,
                         validation_shrink=c.validation_shrink, validation_explained=c.validation_explained,
                         validation_effective_samples=c.validation_effective_samples))
        by_label[c.label] = c
    counting = [r for r in rows if r["validation_shrink"] >= SHRINK_MIN
                and (r["validation_explained"] or 0.0) >= explained_min]
    out = dict(model=model, method="re-estimates", refinements=[], nominal_validation_cost=evidence["cost"],
               candidates=rows, order=[], weights={}, selected=[], look_alikes=[], confidence=None, shrink=None)
    if not counting:
        return out
    _, alikes = validation_weights(counting)
    top = max(r["weight"] for r in counting)       # parsimony among look-alikes: the fewest effects first
    counting.sort(key=lambda r: (r["weight"] < LOOK_ALIKE * top, len(r["effects"]), r["validation_cost"]))
    out.update(order=[by_label[r["effect"]] for r in counting], weights={r["effect"]: r["weight"] for r in counting},
               look_alikes=alikes)
    return out


def _for_refined(model: IdentificationModel, candidates: Sequence[Effect],
                 data: Measurements) -> list[Effect]:
    """The candidates for a refined model: an effect's terms name the rows and variables of the
    model it was built for (the mixture's element rows, the element length), so they are taken by
    name from the refined model's own library (:func:`.effects.library_for`); an effect that library
    lacks keeps its original terms."""
    from .libraries import library_for
    fine = library_for(model, data)
    return [fine[e.name] if e.name in fine.names else e for e in candidates]


def _summary(r: OutputErrorResult) -> dict:
    return dict(model=r.model.name, success=r.success, message=r.message, parameters=dict(r.parameters),
                cost=r.cost, misfit_ratio=r.misfit_ratio, rms_over_noise=r.rms)
