"""The model extended with chosen effects, re-estimated in full (``docs/diagnosis.md``, "Nested effects"):
:func:`reestimate` from a candidate's linearised solution, retried on more shooting points;
:func:`prefer_nested` the simpler of two nested models unless a likelihood-ratio test needs the richer;
:func:`from_nested` a richer model from the converged solution of the one it nests; :func:`refitter`
both in turn, for the look-alikes' comparison.  An estimate that does not converge, or leaves an
effect's bounds, is reported as failed, never as a result.
"""
from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Callable, Sequence

from .composition import extend
from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from .estimators import estimate_retrying, giving_up
from .effects import Library
from .progress import brief, fit_line
from .shrinkage import shrink
from .selection import Candidate, ranking_nu, weigh
from .which import outside_bounds

__all__ = ["reestimate", "prefer_nested", "validation_z", "nested_models", "from_nested", "refitter", "shrink_table",
           "undetermined", "NESTED_ALPHA", "OUTSIDE", "LOOSE"]


#: significance of the likelihood-ratio test between nested models (:func:`prefer_nested`)
NESTED_ALPHA = 0.01


#: an effect parameter whose standard error at the extended estimate exceeds this multiple of its
#: value's size is not determined by the data (e.g. an overflow level above every level reached)
LOOSE = 1.0


def undetermined(res: EstimationResult, effects: Sequence) -> str | None:
    """Why the effects' parameters are not determined at the extended estimate ``res`` (a standard
    error above :data:`LOOSE` times the value's size, or none: a singular Newton matrix at the
    solution), or None when they are.  An effect whose term is inactive at its estimate — an
    overflow level beyond the record — fits nothing and is not an answer."""
    se = res.standard_errors
    loose = []
    for e in effects:
        for p in e.parameters:
            v, s = res.parameters[p], se.get(p, math.nan)
            size = max(abs(v), float(e.scale.get(p, 0.0)) * 1e-3)
            if not (math.isfinite(s) and s <= LOOSE * size):
                loose.append(f"{p} = {v:.4g} ± {s:.2g}" if math.isfinite(s) else f"{p} = {v:.4g} (no standard error)")
    return f"not determined by the data: {', '.join(loose)}" if loose else None


#: the message of a re-estimate that converged outside an effect's declared bounds
OUTSIDE = "the estimate leaves the effects' bounds"


def prefer_nested(nominal: EstimationResult, library: Library, estimator: Callable[..., EstimationResult],
                  which: dict, effs: list[str], res: EstimationResult, sh: dict | None, cand: Candidate,
                  data: Measurements, validation: Measurements | None, nu: float, notes: list[str],
                  say: Callable[[str], None], evidence: dict | None = None
                  ) -> tuple[list[str], EstimationResult, dict | None, Candidate]:
    """Between nested models the simpler one unless the data need the richer one's extra
    parameters: each model nested in ``effs`` (:func:`nested_models`, closest first) is
    re-estimated in full, and the richer is kept only if the likelihood ratio ν log(J_simple/J_rich)
    exceeds the χ² quantile (1 − ``NESTED_ALPHA``) with the difference in parameters as degrees of
    freedom (ν: the effective number of measured samples) — or, with ``evidence`` (the validation
    record's, :func:`.floor.validation_evidence`, where that record decides), when the richer model
    predicts the validation record better by more than chance allows (:func:`validation_z` at least
    the normal quantile 1 − ``NESTED_ALPHA``): parameters fitted on the identification record alone
    do not help out of sample by chance.  A richer model that passes the likelihood ratio but
    predicts the validation record worse by as much (z at most minus that quantile) is not kept:
    its extra parameters fitted something of the identification record that the validation record
    does not have (the independent rig's Coulomb record, seed 2: Stribeck friction lowered J by
    0.8 %, LR 15.8 against 9.21, and its validation free-run cost was 11116 against Coulomb's 6239).
    The models estimated here take their full estimates among the weighed ones (:func:`rescore`).
    Where the richer model's estimate left an effect's bounds (its best fit lies outside its
    domain, :data:`OUTSIDE`) or did not converge, it is re-estimated from the first converged
    nested model's solution where its effect declares how it embeds the simpler one
    (:func:`from_nested`); failing that, the nested model is taken (the notes say why).  Where no
    nested model converges either, the richer model's failure is returned (:func:`settle` then
    tries the next model).  Returns the chosen (effects, result, shrink, candidate)."""
    from scipy.stats import chi2, norm

    outside = not res.success and res.message.startswith(OUTSIDE)
    if not res.success and not outside and not any(library[e].embed for e in effs):
        return effs, res, sh, cand
    if res.success:
        rescore(which, cand, res, nu, nominal.J)
    k_rich = sum(len(library[e].parameters) for e in effs)
    for s_effs, s_cand in nested_models(which["models"], library, effs):
        s_res, s_sh, tried = reestimate(nominal, library, estimator, s_effs, s_cand, data, validation, say)
        notes += tried
        if not s_res.success:
            continue
        if not res.success:                 # the richer model from the simpler one's solution
            r = from_nested(nominal, library, estimator, effs, s_effs, s_res, data, validation, say)
            if r is not None:
                notes.append(f"{' + '.join(effs)} estimated from the solution of {' + '.join(s_effs)}, which it "
                             f"contains ({res.message})")
                (res, sh), cand = r, replace(cand)
                cand.update(res, ranking_nu(which, nu))
                weigh([cand], nominal.J, which.get("J_floor"))
                outside = False
                rescore(which, cand, res, nu, nominal.J)
        s_cand = rescore(which, s_cand, s_res, nu, nominal.J)
        if not res.success:                 # it left its bounds, or cannot be estimated even from here
            why = ("has no estimate in its domain" if outside else
                   "could not be estimated, from its own start nor from this one's solution")
            notes.append(f"{' + '.join(s_effs)} taken for {' + '.join(effs)}, which contains it and {why} "
                         f"({res.message})")
            say(f"  {brief(notes[-1])}")
            return list(s_effs), s_res, s_sh, s_cand
        if not (s_res.J > 0 and res.J > 0):
            continue
        dk = k_rich - sum(len(library[e].parameters) for e in s_effs)
        lr, limit = nu * math.log(s_res.J / res.J), float(chi2.ppf(1.0 - NESTED_ALPHA, max(dk, 1)))
        z = validation_z(nominal, library, effs, res, s_effs, s_res, validation, evidence) \
            if evidence is not None and validation is not None else None
        z_limit = float(norm.ppf(1.0 - NESTED_ALPHA))
        say(f"  nested test {' + '.join(s_effs)} within {' + '.join(effs)}: LR {lr:.3g} vs χ²({max(dk, 1)}) {limit:.3g}"
            + (f"; on the validation record z = {z:.3g} vs ±{z_limit:.3g}" if z is not None else ""))
        if lr >= limit and z is not None and z <= -z_limit:
            # the extra parameters fit the identification record and predict the validation record worse
            notes.append(f"{' + '.join(s_effs)} preferred to {' + '.join(effs)}, which contains it: the likelihood "
                         f"ratio on the identification record ({lr:.3g} ≥ {limit:.3g}) takes {' + '.join(effs)}, but it "
                         f"predicts the validation record worse by z = {-z:.3g} ≥ {z_limit:.3g} standard errors "
                         f"(α = {NESTED_ALPHA})")
            return list(s_effs), s_res, s_sh, s_cand
        if lr < limit and not (z is not None and z >= z_limit):
            notes.append(f"{' + '.join(s_effs)} preferred to {' + '.join(effs)}, which contains it: likelihood "
                         f"ratio {lr:.3g} < {limit:.3g} (χ², {max(dk, 1)} degrees of freedom, α = {NESTED_ALPHA})"
                         + (f"; on the validation record {' + '.join(effs)} predicts better by z = {z:.3g} < "
                            f"{z_limit:.3g} standard errors" if z is not None else ""))
            return list(s_effs), s_res, s_sh, s_cand
        if lr < limit:
            notes.append(f"{' + '.join(effs)} kept, although the identification record alone would take "
                         f"{' + '.join(s_effs)} (likelihood ratio {lr:.3g} < {limit:.3g}): on the validation record "
                         f"it predicts better by z = {z:.3g} ≥ {z_limit:.3g} standard errors (α = {NESTED_ALPHA})")
    return effs, res, sh, cand


def rescore(which: dict, cand: Candidate, res: EstimationResult, nu: float, J0: float) -> Candidate:
    """A model re-estimated in full beside the ranking: ``res`` becomes its score among the weighed
    models (``which["models"]``) where it lowers J below the score there, and a model the ranking
    did not form (a Coulomb + delay pair made up from its singles) joins them; the weights are then
    made again.  Without it the weights compare a one-step score with a full estimate: a Coulomb +
    delay pair the nested test estimated at J 1.1745 kept a weight of 1e-88 beside the Stribeck +
    delay pair's 1.1651, two parameters apart (the independent rig's Coulomb record, seed 2), and
    the verdict said Stribeck with confidence 1.00.  Returns the weighed model of ``cand``'s effects."""
    models = which.setdefault("models", [])
    held = next((m for m in models if sorted(m.effects) == sorted(cand.effects)), None)
    if held is None:
        if not res.success:
            return cand
        held = cand
        models.append(held)
    if res.success and (held.result is None or res.J < held.J):
        held.update(res, ranking_nu(which, nu))
        held.full = True
        weigh(models, J0, which.get("J_floor"))
    return held


def validation_z(nominal: EstimationResult, library: Library, effs: Sequence[str], res: EstimationResult,
                 s_effs: Sequence[str], s_res: EstimationResult, validation: Measurements, evidence: dict
                 ) -> float | None:
    """How many standard errors the richer model ``effs`` (estimate ``res``) predicts the validation
    record better than the simpler ``s_effs`` (``s_res``): the difference C_simple − C_rich of their
    costs there by the evidence's measure (:func:`.design.free_run_residuals`) over its standard
    error, the residuals' autocorrelation counted (:func:`.design.cost_difference`); None where
    either free run fails."""
    from .design import cost_difference, free_run_residuals, pointwise_cost

    nm, how = nominal.problem.model, library.initial_state
    runs = [free_run_residuals(nm, [library[e] for e in e_], validation, r.parameters, how, evidence["noise"],
                               evidence) for e_, r in ((effs, res), (s_effs, s_res))]
    if any(r is None for r in runs):
        return None
    dC, se = cost_difference(pointwise_cost(runs[0]), pointwise_cost(runs[1]))
    return dC / se if se > 0 else None


def nested_models(models: Sequence[Candidate], library: Library, effs: list[str]) -> list[tuple[list[str], Candidate]]:
    """The models nested in ``effs`` with their candidates, closest first: each effect replaced by
    one it nests (a Stribeck + delay pair → Coulomb + delay), then, for a pair, its members by
    their J.  A replacement that was not scored as a candidate is made up from its members'
    single candidates (their parameters as the start), when they were."""
    def found(s: list[str]) -> Candidate | None:
        hit = next((m for m in models if sorted(m.effects) == sorted(s)), None)
        if hit is not None or len(s) == 1:
            return hit
        singles = [next((m for m in models if m.effects == [e]), None) for e in s]
        if any(m is None for m in singles):
            return None
        return Candidate(effects=list(s), k=sum(m.k for m in singles), J=math.inf,
                         parameters={p: v for m in singles for p, v in m.parameters.items()}, result=None)
    replaced = [effs[:i] + [n] + effs[i + 1:] for i, e in enumerate(effs) for n in library[e].nests]
    members = [[e] for e in effs] if len(effs) > 1 else []
    out = [(s, found(s)) for s in replaced]
    out += sorted(((s, found(s)) for s in members), key=lambda c: c[1].J if c[1] is not None else math.inf)
    return [(s, c) for s, c in out if c is not None]


def from_nested(nominal: EstimationResult, library: Library, estimator: Callable[..., EstimationResult],
                effs: list[str], s_effs: list[str], s_res: EstimationResult, data: Measurements,
                validation: Measurements | None, say: Callable[[str], None]
                ) -> tuple[EstimationResult, dict | None] | None:
    """The richer model ``effs`` re-estimated from the converged estimate ``s_res`` of the model
    ``s_effs`` nested in it: the effect that replaces a simpler one starts from each of its
    declared embeddings of the simpler one's estimate (:attr:`.effects.Effect.embed`), the other
    effects from their estimates.  The converged estimate in the effects' bounds with the least J
    and its shrink table, or None."""
    swaps = [(e, n) for e in effs if e not in s_effs for n in library[e].nests if n in s_effs]
    if len(swaps) != 1 or library[swaps[0][0]].embed is None:
        return None
    rich, simple = swaps[0]
    if any(e not in s_effs for e in effs if e != rich):     # another effect besides: no estimate to start it from
        return None
    kept = {p: s_res.parameters[p] for e in effs if e != rich for p in library[e].parameters}
    best = None
    for start in library[rich].embed(simple, s_res.parameters):
        cand = Candidate(effects=list(effs), k=sum(len(library[e].parameters) for e in effs), J=math.inf,
                         parameters={**kept, **start}, result=s_res)
        how = (f"from the solution of {' + '.join(s_effs)} with "
               + ", ".join(f"{p} = {v:.3g}" for p, v in start.items()))
        res, _, _ = reestimate(nominal, library, estimator, effs, cand, data, validation, say, retry=False,
                               measure=False, how=how)
        if res.success and (best is None or res.J < best.J):
            best = res
    return None if best is None else (best, shrink_table(nominal, library, effs, best, validation))


def reestimate(nominal: EstimationResult, library: Library, estimator: Callable[..., EstimationResult],
               effects: Sequence[str], candidate: Candidate, data: Measurements, validation: Measurements | None,
               say: Callable[[str], None], retry: bool = True, measure: bool = True,
               how: str = "from its linearised solution"
               ) -> tuple[EstimationResult, dict | None, list[str]]:
    """The model extended with ``effects`` re-estimated from the candidate's linearised solution
    (parameters clipped to the effects' bounds); where that does not converge, from the data's
    states with the same parameters (the model's at the warm estimate's); then on more shooting
    points (``retry``); and how far the misfit shrinks (:func:`shrink_table`; None when it did not
    converge or ``measure`` is False).  One progress line: the model, ``how`` it was started, the
    result and the time."""
    nm = nominal.problem.model
    sel = [library[n] for n in effects]
    ext = extend(nm, sel, data=data)
    init = dict(candidate.parameters)
    for e in sel:
        for p, (lo, hi) in e.bounds.items():
            if p in init:
                init[p] = min(max(init[p], lo), hi)
    clock = time.perf_counter()
    warm = candidate.result or nominal
    attempt = dict(initial=init, **giving_up(ext, estimator))      # a failure is reported, a simpler model tried
    res, tried = estimator(ext, data, start=warm, **attempt), []
    if not res.success:
        # the warm start's smoothed states can carry the misfit the effects are to explain
        # (:func:`.estimators.damped`): from the data's states before more shooting points
        tried.append(f"{ext.name} {how} did not converge: {res.message}")
        say(f"  {brief(tried[-1])}; from the data's states ...")
        values = {p: v for p, v in warm.parameters.items() if p in ext.parameters}
        cold = estimator(ext, data, **dict(attempt, initial={**values, **init}))
        if cold.success:
            res, how = cold, "from the data's states"
        else:
            tried.append(f"{ext.name} from the data's states did not converge: {cold.message}")
    if retry and not res.success:
        res, more = estimate_retrying(estimator, ext, data, say, first=res, start=warm, **attempt)
        tried += more
    outside = outside_bounds(sel, res.parameters, ".3g") if res.success else []
    what = f"re-estimated {ext.name} {how}"
    if outside:         # an estimate outside an effect's domain (a Stribeck velocity below 0) is none
        say(f"{what}: J = {res.J:.5g} but {OUTSIDE}: {', '.join(outside)}, {time.perf_counter() - clock:.1f} s")
        res = replace(res, success=False, message=f"{OUTSIDE}: {', '.join(outside)}")
    else:
        say(fit_line(what, res, time.perf_counter() - clock))
    if not res.success or not measure:
        return res, None, tried
    return res, shrink_table(nominal, library, effects, res, validation), tried


def shrink_table(nominal: EstimationResult, library: Library, effects: Sequence[str], res: EstimationResult,
                 validation: Measurements | None) -> dict:
    """How far the misfit shrinks from ``nominal`` to the extended estimate ``res``
    (:func:`.shrinkage.shrink`; ``validation`` None without a validation record)."""
    nm = nominal.problem.model
    sh = shrink(nominal, res, validation, library.initial_state, nm, [library[n] for n in effects])
    sh.setdefault("validation", None)
    return sh


def refitter(nominal: EstimationResult, library: Library, estimator: Callable[..., EstimationResult],
             selected: Sequence[str], extended: EstimationResult | None, data: Measurements,
             validation: Measurements | None, say: Callable[[str], None]
             ) -> Callable[[list[str], Candidate], EstimationResult | None]:
    """A re-estimation for a look-alike of the selection ``selected`` (its converged estimate
    ``extended``): from the look-alike's linearised solution (:func:`reestimate`, no retries) and,
    where the look-alike nests a selected effect, also from the selection's solution
    (:func:`from_nested`) — the lower converged J of the two: a richer model's minimum lies at or
    below the one it nests, and its own start can miss it.  The function returns the converged
    estimate or None."""
    def refit(effs: list[str], cand: Candidate) -> EstimationResult | None:
        res, _, _ = reestimate(nominal, library, estimator, effs, cand, data, validation, say, retry=False,
                               measure=False)
        if extended is not None and extended.success:
            nested = from_nested(nominal, library, estimator, effs, list(selected), extended, data, validation, say)
            if nested is not None and nested[0].success and (not res.success or nested[0].J < res.J):
                res = nested[0]
        return res if res.success else None
    return refit
