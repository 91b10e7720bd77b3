"""Nested models weighed by output error (``docs/diagnosis.md``, "Nested look-alikes weighed by output
error"): :func:`by_output_error` fits a model and a richer form of it (one effect replaced by one
that nests it: Stribeck friction for Coulomb friction) by output error and weighs them on both
records, where the TPBVP cannot — its model errors absorb what the richer law adds, and its Newton
iteration there meets a stiff, near-singular problem; :func:`as_answer` makes the richer form an
answer.  :func:`.lookalikes.discriminate` decides with them.
"""
from __future__ import annotations

import math
import time
from typing import Callable, Mapping, Sequence

from shootlab.estimation.data import Measurements
from shootlab.estimation.model import IdentificationModel
from .composition import extend
from .design import cost_difference, free_run_cost, free_run_residuals, pointwise_cost
from .effects import Library
from .free_run_screen import output_error_fit, selection
from .which import outside_bounds

__all__ = ["by_output_error", "as_answer", "nested_in", "RICHER_Z"]


#: a richer form fitted by output error is the answer over the simpler one it contains where it
#: predicts the records better by this many standard errors of the costs' difference (the nested
#: test's: the normal quantile 1 − :data:`.reestimation.NESTED_ALPHA`)
RICHER_Z = 2.3263


def by_output_error(model: IdentificationModel, library: Library, simple: Sequence[str],
                    simple_parameters: Mapping[str, float], rich: Sequence[str],
                    rich_parameters: Mapping[str, float] | None, data: Measurements, validation: Measurements,
                    sigma: Mapping[str, float], sigma_v: Mapping[str, float] | None,
                    say: Callable[[str], None]) -> dict | None:
    """Two nested models fitted by output error and weighed on both records
    (:func:`.lookalikes.discriminate`, step 5): ``simple`` and ``rich``, the same effects but one
    replaced by an effect that nests it.

    The simpler model's fit starts from its TPBVP estimate ``simple_parameters``; the richer one's
    from its TPBVP estimate ``rich_parameters`` where there is one, then from each of its effect's
    embeddings of the simpler fit (:attr:`.effects.Effect.embed`), in turn, until one converges
    inside the effects' bounds at or below the simpler fit's cost on the identification record —
    the richer model contains the simpler one, so a fit above it has not reached its minimum and
    says nothing about the richer form.  Both are run freely from the library's start on both records, and
    z = (ΔC − Δk) / se: ΔC the simpler model's cost Σ((y − z)/σ)² minus the richer one's, summed
    over the records, Δk the richer one's extra parameters (what they lower the identification
    record's cost by on average where they are not needed), se the standard error of ΔC
    (:func:`.design.cost_difference`, the residuals' autocorrelation counted): positive where the
    richer form predicts better.  Returns None where a fit or a free run fails, else a dict:
    ``effects`` (the richer form), ``simple``, the fits' ``parameters`` and ``parameters_simple``,
    the validation costs ``cost_richer`` and ``cost_simple``, the identification one
    ``identification_cost_richer``, and ``z`` and its parts."""
    how = library.initial_state
    swaps = [(e, n) for e in rich if e not in simple for n in library[e].nests if n in simple]
    if len(swaps) != 1:
        return None
    richer, simpler = swaps[0]
    clock = time.perf_counter()
    mine, theirs = [library[e] for e in simple], [library[e] for e in rich]
    ext = extend(model, mine, data=data)
    fit_a = output_error_fit(ext, data, dict(ext.prior, **simple_parameters), how)
    say(f"  {' + '.join(simple)} by output error: " + (f"cost {fit_a.cost:.5g}" if fit_a.success else
                                                       f"not converged ({fit_a.message})")
        + f", {time.perf_counter() - clock:.1f} s")
    if not fit_a.success:
        return None
    ext = extend(model, theirs, data=data)
    embedded = library[richer].embed(simpler, fit_a.parameters) if library[richer].embed else []
    starts = ([dict(rich_parameters)] if rich_parameters else []) + [dict(fit_a.parameters, **e) for e in embedded]
    fit_b = None
    for start in starts:
        tick = time.perf_counter()
        fit = output_error_fit(ext, data, dict(ext.prior, **start), how)
        out = outside_bounds(theirs, fit.parameters, ".3g") if fit.success else []
        above = fit.success and fit.cost > fit_a.cost * (1.0 + 1e-9)       # not at the richer model's minimum
        said = ", ".join(f"{p} = {start[p]:.3g}" for p in library[richer].parameters if p in start)
        say(f"  {' + '.join(rich)} by output error from {said}: "
            + (f"not converged ({fit.message})" if not fit.success else
               f"cost {fit.cost:.5g} but outside its bounds: {', '.join(out)}" if out else
               f"cost {fit.cost:.5g}, above the simpler model's" if above else f"cost {fit.cost:.5g}")
            + f", {time.perf_counter() - tick:.1f} s")
        if fit.success and not out and not above:
            fit_b = fit
            break
    if fit_b is None:
        return None
    records = ((data, sigma), (validation, sigma_v))
    runs = [[free_run_residuals(model, e, rec, f.parameters, how, sg) for rec, sg in records]
            for e, f in ((mine, fit_a), (theirs, fit_b))]
    if any(r is None for rr in runs for r in rr):
        return None
    parts = [cost_difference(pointwise_cost(b), pointwise_cost(a)) for a, b in zip(*runs)]     # C_simple − C_rich
    dk = sum(len(e.parameters) for e in theirs) - sum(len(e.parameters) for e in mine)
    dC, se = sum(p[0] for p in parts), math.sqrt(sum(p[1] ** 2 for p in parts))
    z = (dC - dk) / se if se > 0 else math.copysign(math.inf, dC - dk)
    costs = [[float(pointwise_cost(r).sum()) for r in rr] for rr in runs]
    say(f"  by output error, {' + '.join(rich)} against {' + '.join(simple)}: free-run costs {costs[1][0]:.5g} / "
        f"{costs[1][1]:.5g} against {costs[0][0]:.5g} / {costs[0][1]:.5g} (identification / validation), "
        f"z = {z:.3g}")
    return dict(effects=list(rich), simple=list(simple), parameters=dict(fit_b.parameters),
                parameters_simple=dict(fit_a.parameters), cost_richer=costs[1][1], cost_simple=costs[0][1],
                identification_cost_richer=costs[1][0], cost_difference=dC, extra_parameters=dk, standard_error=se,
                z=z, seconds=time.perf_counter() - clock)


def as_answer(model: IdentificationModel, library: Library, weighed: dict, nominal: Mapping[str, float],
              data: Measurements, validation: Measurements, sigma: Mapping[str, float],
              sigma_v: Mapping[str, float] | None, confidence: float) -> dict:
    """The richer form of :func:`by_output_error`'s result ``weighed`` as a free-run answer
    (:func:`.free_run_screen.selection`) with ``confidence``: its shrink from the nominal estimate
    (``nominal``, its parameters) on both records, and the two fits as the report's rows."""
    how = library.initial_state
    before = [free_run_cost(model, [], rec, nominal, how, sg)[0] for rec, sg in ((data, sigma), (validation, sigma_v))]
    rich, label = weighed["effects"], " + ".join(weighed["effects"])
    row = dict(effect=label, effects=list(rich), parameters=dict(weighed["parameters"]),
               identification_cost=weighed["identification_cost_richer"],
               identification_shrink=1.0 - weighed["identification_cost_richer"] / before[0],
               validation_cost=weighed["cost_richer"], validation_shrink=1.0 - weighed["cost_richer"] / before[1])
    answer = selection(model, [library[e] for e in rich], validation,
                       dict(nominal=dict(cost=before[0], parameters=dict(nominal)), refinements=[]), row, confidence,
                       how)
    answer.update(model=model.name, candidates=[         # the report's table of the two fits
        dict(effect=" + ".join(e), success=True, validation_shrink=1.0 - c / before[1])
        for e, c in ((weighed["simple"], weighed["cost_simple"]), (rich, weighed["cost_richer"]))])
    answer["verdict"] = (f"structural error explained by {label}, estimated by output error (its TPBVP estimate "
                         f"did not converge): the validation free-run cost shrinks "
                         f"{100 * row['validation_shrink']:.0f} %")
    return answer


def nested_in(library: Library, simple: Sequence[str], rich: Sequence[str]) -> bool:
    """Whether the model ``simple`` is ``rich`` with one effect replaced by one that effect nests."""
    extra, missing = set(rich) - set(simple), set(simple) - set(rich)
    return (len(extra) == 1 and len(missing) == 1 and len(simple) == len(rich)
            and next(iter(missing)) in library[next(iter(extra))].nests)
