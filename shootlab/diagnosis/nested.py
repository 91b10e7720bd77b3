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
from shootlab.estimation.free_run import counted
from shootlab.estimation.model import IdentificationModel
from .composition import extend
from .design import cost_difference, free_run_cost, free_run_residuals, pointwise_cost
from .effects import Library
from .free_run_screen import output_error_fit, selection
from .selection import LOOK_ALIKE_Z

__all__ = ["nested_fits", "weigh_fits", "by_output_error", "decided", "as_answer", "nested_in", "RICHER_Z", "WEIGH_RUNS",
           "WEIGH_CALLS"]


#: a richer form fitted by output error is the answer over the simpler one it contains where it
#: predicts the records better by this many standard errors of the costs' difference (the nested
#: test's: the normal quantile 1 − :data:`.reestimation.NESTED_ALPHA`)
RICHER_Z = 2.3263

#: free runs the output-error fits of one weighing may take together (the Jacobian's columns
#: counted; a Stribeck fit on a 1001-sample record of the two-mass rig took 1,555): a budget in runs,
#: not seconds, so that a weighing ends at the same point, with the same answer, on any machine and
#: under any load.  Past it the fit is not converged and the weighing says nothing
#: (docs/diagnosis.md, "Nested look-alikes weighed by output error")
WEIGH_RUNS = 5000

#: the weighing is skipped, saying so, where the simpler model's fit shows a pace at which the
#: budget's runs would take more than this many right-hand-side calls (:class:`~shootlab.estimation.
#: free_run.Work`: the same count on any machine and under any load; at the 1.3–1.6 ms a call
#: measured on one core for the pendulum's and the rig's free runs, about an hour): where a free run
#: takes thousands of calls (a long record run sample by sample) a Stribeck fit would take hours
WEIGH_CALLS = 2.5e6


def nested_fits(model: IdentificationModel, library: Library, simple: Sequence[str],
                simple_parameters: Mapping[str, float], rich: Sequence[str],
                rich_parameters: Mapping[str, float] | None, data: Measurements,
                say: Callable[[str], None]) -> dict | None:
    """The output-error fits of two nested models on the identification record: ``simple`` and
    ``rich``, the same effects but one replaced by an effect that nests it, or ``simple`` and one
    effect more (None where they are neither).

    The simpler model's fit starts from ``simple_parameters`` (its TPBVP estimate); the richer
    one's from ``rich_parameters`` where there is one, then from each of its effect's embeddings of
    the simpler fit (:attr:`.effects.Effect.embed`; an added effect: its own initial values beside
    the simpler fit), in turn, until one converges at or below the simpler fit's cost — the richer
    model contains the simpler one, so a fit above it has not reached its minimum and says nothing
    about the richer form.  Each fit is constrained to the effects' bounds (it may end on one); all
    together are given :data:`WEIGH_RUNS` free runs (the simpler one a tenth of them), and the richer
    one none where the simpler fit's pace would take them past :data:`WEIGH_CALLS`.  Returns a
    dict: ``simple`` and ``rich`` (:class:`~shootlab.estimation.output_error.OutputErrorResult`;
    ``rich`` None where no start served or none was tried, ``simple`` unconverged where its fit
    failed), ``tries`` (per richer start: its values, ``success``, ``cost``, ``on_bound``,
    ``evaluations``, ``seconds``, ``message``) and, where the richer fit was not tried for the
    simpler one's pace, ``not_tried`` (why, in words)."""
    how = library.initial_state
    swaps = [(e, n) for e in rich if e not in simple for n in library[e].nests if n in simple]
    added = [e for e in rich if e not in simple]
    if len(swaps) == 1:
        richer, simpler = swaps[0]
    elif len(added) == 1 and set(simple) < set(rich):
        richer, simpler = added[0], None
    else:
        return None
    clock = time.perf_counter()
    mine, theirs = [library[e] for e in simple], [library[e] for e in rich]
    box_a, box_b = _box(mine), _box(theirs)
    ext = extend(model, mine, data=data)
    with counted() as work:
        fit_a = output_error_fit(ext, data, _into(dict(ext.prior, **simple_parameters), box_a), how, bounds=box_a,
                                 max_runs=WEIGH_RUNS // 10)     # from its TPBVP estimate: a few iterations
    say(f"  {' + '.join(simple)} by output error: " + (f"cost {fit_a.cost:.5g}" if fit_a.success else fit_a.message)
        + f", {fit_a.evaluations} free runs, {time.perf_counter() - clock:.1f} s")
    out = dict(simple=fit_a, rich=None, tries=[])
    if not fit_a.success:
        return out
    pace = work.calls / max(fit_a.evaluations, 1)
    if pace * WEIGH_RUNS > WEIGH_CALLS:
        out["not_tried"] = (f"at {pace:.3g} right-hand-side calls a free run its {WEIGH_RUNS} runs could take "
                            f"{pace * WEIGH_RUNS:.3g} (more than {WEIGH_CALLS:.3g}; here "
                            f"{fit_a.seconds / max(fit_a.evaluations, 1):.2g} s a run)")
        say(f"  {' + '.join(rich)} by output error: not tried — {out['not_tried']}")
        return out
    used = fit_a.evaluations
    ext = extend(model, theirs, data=data)
    embedded = ([dict(library[richer].parameters)] if simpler is None else
                library[richer].embed(simpler, fit_a.parameters) if library[richer].embed else [])
    starts = ([dict(rich_parameters)] if rich_parameters else []) + [dict(fit_a.parameters, **e) for e in embedded]
    for start in starts:
        tick = time.perf_counter()
        if used >= WEIGH_RUNS:
            say(f"  {' + '.join(rich)} by output error: its budget of {WEIGH_RUNS} free runs is spent")
            break
        fit = output_error_fit(ext, data, _into(dict(ext.prior, **start), box_b), how, bounds=box_b,
                               max_runs=WEIGH_RUNS - used)
        used += fit.evaluations
        above = fit.success and fit.cost > fit_a.cost * (1.0 + 1e-9)       # not at the richer model's minimum
        values = {p: float(start[p]) for p in library[richer].parameters if p in start}
        edge = _on_edge(theirs, fit.parameters) if fit.success else []
        out["tries"].append(dict(start=values, success=bool(fit.success), cost=float(fit.cost), above=above,
                                 on_bound=edge, evaluations=fit.evaluations, seconds=time.perf_counter() - tick,
                                 message=fit.message, parameters=dict(fit.parameters)))
        said = ", ".join(f"{p} = {v:.3g}" for p, v in values.items())
        say(f"  {' + '.join(rich)} by output error from {said}: "
            + (fit.message if not fit.success else
               f"cost {fit.cost:.5g}, above the simpler model's" if above else f"cost {fit.cost:.5g}")
            + (f" (on its bound: {', '.join(edge)})" if edge else "")
            + f", {fit.evaluations} free runs, {time.perf_counter() - tick:.1f} s")
        if fit.success and not above:
            out["rich"] = fit
            break
    return out


def by_output_error(model: IdentificationModel, library: Library, simple: Sequence[str],
                    simple_parameters: Mapping[str, float], rich: Sequence[str],
                    rich_parameters: Mapping[str, float] | None, data: Measurements, validation: Measurements,
                    sigma: Mapping[str, float], sigma_v: Mapping[str, float] | None,
                    say: Callable[[str], None], not_weighed: dict | None = None) -> dict | None:
    """Two nested models fitted by output error (:func:`nested_fits`) and weighed on both records
    (:func:`.lookalikes.discriminate`, step 5).

    Both fits are run freely from the library's start on both records, and z = (ΔC − Δk) / se: ΔC
    the simpler model's cost Σ((y − z)/σ)² minus the richer one's, summed over the records, Δk the
    richer one's extra parameters (what they lower the identification record's cost by on average
    where they are not needed), se the standard error of ΔC (:func:`.design.cost_difference`, the
    residuals' autocorrelation counted): positive where the richer form predicts better.  Returns
    None where a fit or a free run fails, else a dict: ``effects`` (the richer form), ``simple``,
    the fits' ``parameters`` and ``parameters_simple``, ``on_bound`` (the richer fit's parameters
    that end on their bounds: :func:`decided`), the validation costs ``cost_richer`` and
    ``cost_simple``, the identification ones ``identification_cost_richer`` and
    ``identification_cost_simple``, and ``z`` and its parts.  ``not_weighed``: a dict to which a
    sentence is added, under the richer form's effects (a frozenset), where the richer fit was not
    tried for the simpler one's pace (the verdict's words: the look-alike stands without a
    weighing)."""
    clock = time.perf_counter()
    fits = nested_fits(model, library, simple, simple_parameters, rich, rich_parameters, data, say)
    if fits is not None and fits.get("not_tried") and not_weighed is not None:
        not_weighed[frozenset(rich)] = (f"{' + '.join(rich)} was not weighed against {' + '.join(simple)} by output "
                                        f"error: {fits['not_tried']}")
    weighed = weigh_fits(model, library, simple, rich, fits, data, validation, sigma, sigma_v, say)
    return None if weighed is None else dict(weighed, seconds=time.perf_counter() - clock)


def _start(fit, how):
    """Where a fit's free run on its own record starts: the state the fit estimated with its
    parameters (the start ``"fitted"``), else the library's rule ``how``."""
    s0 = getattr(fit, "initial_state", None)
    return how if s0 is None else (lambda model, data: [float(v) for v in s0])


def weigh_fits(model: IdentificationModel, library: Library, simple: Sequence[str], rich: Sequence[str],
               fits: dict | None, data: Measurements, validation: Measurements, sigma: Mapping[str, float],
               sigma_v: Mapping[str, float] | None, say: Callable[[str], None]) -> dict | None:
    """:func:`by_output_error`'s weighing of :func:`nested_fits`' ``fits``: None where there is no
    richer fit or a free run fails."""
    if fits is None or fits["rich"] is None:
        return None
    how = library.initial_state
    mine, theirs = [library[e] for e in simple], [library[e] for e in rich]
    records = ((data, sigma), (validation, sigma_v))
    runs = [[free_run_residuals(model, e, rec, f.parameters, _start(f, how) if rec is data else how, sg)
             for rec, sg in records] for e, f in ((mine, fits["simple"]), (theirs, fits["rich"]))]
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
    return dict(effects=list(rich), simple=list(simple), parameters=dict(fits["rich"].parameters),
                on_bound=_on_edge(theirs, fits["rich"].parameters),
                parameters_simple=dict(fits["simple"].parameters), cost_richer=costs[1][1], cost_simple=costs[0][1],
                identification_cost_richer=costs[1][0], identification_cost_simple=costs[0][0],
                cost_difference=dC, extra_parameters=dk, standard_error=se, z=z,
                tries=[{k: v for k, v in t.items() if k != "parameters"} for t in fits["tries"]])


def decided(weighed: dict) -> bool:
    """Whether the weighing ``weighed`` (:func:`by_output_error`) tells the nested pair apart: the
    richer form where z ≥ :data:`RICHER_Z`; the simpler one where z ≤ −:data:`.selection.LOOK_ALIKE_Z`
    and the richer fit is at its own minimum — one that ends on a bound has been held from where it
    would go, and can show the richer form is needed, never that it is not."""
    z = weighed["z"]
    return z >= RICHER_Z or (z <= -LOOK_ALIKE_Z and not weighed.get("on_bound"))


def _box(effects) -> dict[str, tuple[float, float]]:
    """The effects' declared bounds: the box of their output-error fits."""
    return {p: lohi for e in effects for p, lohi in e.bounds.items()}


def _into(values: Mapping[str, float], box: Mapping[str, tuple[float, float]]) -> dict[str, float]:
    """``values`` with each one on or beyond its bound in ``box`` moved 0.1 % of the box's width (of
    the values' size for a half-open box) inside it: a bounded fit starts strictly inside."""
    out = dict(values)
    for p, (lo, hi) in box.items():
        if p in out and not lo < out[p] < hi:
            size = hi - lo if math.isfinite(hi - lo) else max(abs(b) for b in (lo, hi, out[p]) if math.isfinite(b))
            step = 1e-3 * (size or 1.0)
            out[p] = lo + step if out[p] <= lo else hi - step
    return out


def _on_edge(effects, values: Mapping[str, float]) -> list[str]:
    """``p = v`` for each of the effects' bounded parameters that ends on its bound (within 0.1 % of
    the bound, or of the box's width for a bound at 0 — 0 itself in a half-open box: the bounded
    fit's iterates stay strictly inside)."""
    out = []
    for p, (lo, hi) in _box(effects).items():
        width = hi - lo if math.isfinite(hi - lo) else 0.0      # a bound at 0 of a half-open box: only 0 itself
        size = {b: abs(b) or width for b in (lo, hi) if math.isfinite(b)}
        if p in values and any(abs(values[p] - b) <= 1e-3 * d for b, d in size.items()):
            out.append(f"{p} = {values[p]:.3g}")
    return out


def as_answer(model: IdentificationModel, library: Library, weighed: dict, nominal: Mapping[str, float],
              data: Measurements, validation: Measurements, sigma: Mapping[str, float],
              sigma_v: Mapping[str, float] | None, confidence: float,
              why: str = "its TPBVP estimate did not converge") -> dict:
    """The richer form of :func:`by_output_error`'s result ``weighed`` as a free-run answer
    (:func:`.free_run_screen.selection`) with ``confidence``: its shrink from the nominal estimate
    (``nominal``, its parameters) on both records, and the two fits as the report's rows; ``why``
    it is estimated by output error, in words."""
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
    answer["verdict"] = (f"structural error explained by {label}, estimated by output error ({why}): the "
                         f"validation free-run cost shrinks "
                         f"{100 * row['validation_shrink']:.0f} %")
    return answer


def nested_in(library: Library, simple: Sequence[str], rich: Sequence[str]) -> bool:
    """Whether the model ``simple`` is ``rich`` with one effect replaced by one that effect nests."""
    extra, missing = set(rich) - set(simple), set(simple) - set(rich)
    return (len(extra) == 1 and len(missing) == 1 and len(simple) == len(rich)
            and next(iter(missing)) in library[next(iter(extra))].nests)
