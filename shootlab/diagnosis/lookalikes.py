"""Look-alike candidates (``docs/diagnosis.md``, "Confidence and look-alikes"): :func:`discriminate`
compares a settled selection with its heaviest rivals on both records and names those the records
cannot tell from it, with the confidence they leave, and weighs by output error a richer form of
it the TPBVP cannot settle (:mod:`.nested`).  What the verdict says of them, and the caps an answer
that may stand in for an effect outside the library gets, are :mod:`.lookalike_words`'; the
experiment that would tell them apart is :func:`.design.propose`.
"""
from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy.special import ndtr

from shootlab.estimation.data import Measurements, noise_level
from shootlab.estimation.model import IdentificationModel
from .effects import Library, unphysical
from .libraries import library_for
from .free_run_screen import selection
from .nested import RICHER_Z, as_answer, by_output_error, decided, nested_in
from .selection import LOOK_ALIKE, LOOK_ALIKE_Z, PAIR_GAIN, Candidate, criterion, heaviest, rivals, weigh
from .design import (cost_difference, free_run_cost, free_run_residuals, pointwise_cost, propose,
                     separation_power, separation_z, validation_cost)
from .lookalike_words import UNRESOLVED, words

__all__ = ["discriminate", "RIVALS", "SCOPE"]


# -- look-alikes in a verdict --------------------------------------------------------------------------------------
#: the heaviest effects outside the selection whose free runs are compared with the selection's
RIVALS = 2


#: effects outside the selection whose models weigh less than this share of the selection's are not
#: compared (their weight leaves no doubt)
SCOPE = 1e-6


def discriminate(nominal, library: Library, which: dict, selected: Sequence[str], data: Measurements,
                 validation: Measurements | None, sigma: Mapping[str, float], chosen=None,
                 free_run: dict | None = None, refit: Callable[[list[str], object], object] | None = None,
                 design: bool = True, log: Callable[[str], None] | None = None,
                 measured: dict | None = None) -> dict | None:
    """Look-alikes of a settled selection, the validation record's evidence on them, the confidence
    they leave and an experiment that would tell them apart (module docstring).

    ``nominal``: the nominal estimate; ``which``: :func:`.which.rank`'s result (its models weighed);
    ``chosen``: the converged re-estimate of the selection; ``free_run``: the free-run screen's
    result, when its verdict stands (its candidates are then weighed on their output-error costs:
    the identification record's and the validation record's, :func:`_screened`); ``refit(effects,
    candidate)``: a converged re-estimate of a rival that has none (or None), for its free runs;
    ``design``: propose an experiment (:func:`propose`) while look-alikes remain.

    1. With a validation record the selection's and the :data:`RIVALS` heaviest rivals' free-run
       costs there (:func:`free_run_cost`) enter the weights (:func:`.selection.weigh`); a rival that
       then outweighs the selection becomes the selection (``switch``: its effects and estimate) —
       not a richer form of it (the nested likelihood-ratio test found its parameters not needed).
       Where the free-run screen decided (by the validation record alone), a candidate that
       outweighs its selection on both records becomes the selection (``switch["free_run"]``: the
       screen's answer for it, :func:`.free_run_screen.selection`).
    2. The selection and each of those rivals (weighing at least :data:`SCOPE` of it) are run freely
       on both records; ΔC, the sum over the records of the rival's cost minus the selection's,
       against its standard error (:func:`cost_difference`) gives z, and Φ(z) the probability that
       the selection's costs stay the lower over records like these — whichever model is right.
       S = Σ((y_A − y_B)/σ)², the separation of their free runs on the records, bounds what the
       records can tell: were one of the two exact, ΔC would be ±S with spread s = max(2√S, se)
       (2√S on white noise, se where the residuals are correlated), and the right one would have
       the lower cost with probability Φ(S/s) — where ΔC is far larger, what decides is a misfit
       both leave, not the difference between them.
    3. A rival is a look-alike when its models weigh at least :data:`.selection.LOOK_ALIKE` of the
       selection's (:func:`.selection.rivals`) or min(z, S/s) < :data:`LOOK_ALIKE_Z` (:func:`_told`);
       the confidence is the weight of the selection's models (with look-alikes: of the models
       that name it), at most Φ(min(z, S/s)) of every rival compared — below 0.9 beside a
       look-alike.
    4. A richer form of the selection that no start brought to a converged estimate at or below the
       selection's J (Stribeck friction beside a Coulomb verdict, :func:`_richer_at_their_minimum`)
       is named as a look-alike, and the confidence is at most :data:`.lookalike_words.UNRESOLVED`: the records have
       not weighed it; where step 5 leaves it undecided, the experiment is between the two
       output-error fits.  So is a richer selection given up for the simpler form it contains in
       step 1 (the identification record's likelihood ratio took the richer, the validation record
       the simpler: the records disagree).
    5. A richer form of the selection, or a simpler one, that is left a look-alike by step 3 or 4
       is fitted by output error with the selection (:func:`.nested.by_output_error`): the TPBVP's model
       errors can absorb what a richer friction law adds, brief forces at each reversal of the
       motion, and its Newton iteration there meets a stiff, near-singular problem.  Where the
       richer of the two fits predicts both records better by :data:`.nested.RICHER_Z` standard errors it
       is the answer (a switch to the richer form: ``switch["output_error"]``, its estimate the
       output-error fit), where the simpler predicts as well (z at most −:data:`LOOK_ALIKE_Z`, the
       richer fit not held on a bound: :func:`.nested.decided`) the simpler form is, and otherwise
       the look-alike stays; the confidence is at most Φ(z) where the answer is the richer form,
       Φ(−z) where it is the simpler.  So is the heaviest model where it is the selection and one
       effect more, a pair :func:`.selection.select` set aside because its second effect lowers J by
       less than :data:`.selection.PAIR_GAIN` of what the selection leaves (:func:`_complemented`):
       the TPBVP's model errors can absorb that effect too.
    6. A selection whose estimate is not physical and takes the shape of another effect's law
       (:attr:`.effects.Effect.imitates`: Stribeck friction whose level rises with speed, viscous
       friction's shape) gives way to that effect's model where it was compared in step 2, its
       own estimate is physical and the selection predicts the records better by less than
       :data:`.nested.RICHER_Z` standard errors (``switch["imitated"]``: the ways it is not) — also
       where the weights of step 1 took the imitation for that model; the confidence is at most
       :data:`.lookalike_words.UNRESOLVED`: what the imitation fits better may be an effect outside the library.

    Returns None without a selection (or one the ranking did not weigh), else a dict:
    ``lookalikes`` (effect names), ``rivals`` (each: effect, its model's effects, weight, ratio to the
    selection's weight, whether nested, validation cost, and ΔC, its standard error, z, S and
    Φ(S/s) where compared), ``confidence``, ``evidence`` (the effective sizes), ``switch``, ``experiment`` (or None),
    ``not_weighed`` (the step-5 weighings not tried, in words) and ``words`` (what the verdict adds)."""
    say = log or (lambda s: None)
    if not selected or not which:
        return None
    nests = {e.name: tuple(e.nests) for e in library.effects}
    model = nominal.problem.model
    how = library.initial_state
    chans = [c for c in model.measured if c not in model.given]
    sigma = {c: sigma[c] for c in chans if c in sigma} if sigma else noise_level(data, chans)
    sigma_v = None if validation is None else (dict(measured["noise"]) if measured is not None
                                               else noise_level(validation, chans))
    switch = None
    effect = library.__getitem__
    screened = bool(free_run and free_run.get("selected") and free_run.get("method") == "output-error")
    if screened:
        model, effect, models, params = _screened(model, library, free_run, data)
        lead = params.get(frozenset(selected))
        if lead is None:
            return None
        nu = free_run_cost(model, [effect(n) for n in selected], data, lead, how, sigma)[1]
        for m in models:
            m.criterion = _criterion(m.J, m.k, nu)
        evidence = dict(weigh(models, models[0].J, None), nu=nu, nu_residual=nu)
    else:
        models, params = list(which.get("models", [])), {}
        for m in models:
            if m.full and m.result is not None and m.result.success:
                params[frozenset(m.effects)] = dict(m.result.parameters)
        if chosen is not None and getattr(chosen, "success", False):
            params[frozenset(selected)] = dict(chosen.parameters)
        evidence = dict(which.get("evidence") or {})
    mine = next((m for m in models if set(m.effects) == set(selected)), None)
    if mine is None:            # a selection made up after the ranking (a nested model): its weight is not known
        return None

    def fitted(m, again: bool = False) -> dict | None:
        """The model's converged parameters, re-estimated (``refit``) where it has none (or
        ``again``); a re-estimate with a lower J than the model's score replaces it."""
        key = frozenset(m.effects)
        if (again or key not in params) and refit is not None and not screened:
            res = refit(list(m.effects), m)
            if res is not None and res.success and (key not in params or res.J < m.J):
                params[key], m.refit = dict(res.parameters), res
        return params.get(key)

    unresolved = [] if screened else _richer_at_their_minimum(models, mine, selected, library, fitted, evidence,
                                                               nominal.J, which, say)
    own, near = rivals(models, selected, nests, ratio=SCOPE)
    if screened and validation is not None:
        # the screen ranked by the validation record alone; weighed on both records a rival may lead
        best = max((r["model"] for r in near if not r["nested"]), key=lambda m: m.weight, default=None)
        row = None if best is None else next((r for r in free_run.get("candidates", [])
                                              if [r["effect"]] == best.effects), None)
        if row is not None and best.weight > mine.weight:
            old, mine, selected = mine, best, list(best.effects)
            own, near = _rivals_beside(models, selected, nests, old)
            switch = dict(effects=list(selected), result=None, replaced=list(old.effects), weight=best.weight,
                          replaced_weight=old.weight, explained_excess=None, simpler=False,
                          free_run=selection(model, effect(selected[0]), validation, free_run, row, best.weight,
                                             library.initial_state))
            say(f"  weighed on both records {mine.label} leads {old.label} ({best.weight:.3g} against "
                f"{old.weight:.3g}): it is the selection")
    if near and validation is not None and not screened:
        for m in [mine] + [r["model"] for r in near[:RIVALS]]:
            if fitted(m) is not None and getattr(m, "validation_cost", None) is None:
                m.validation_cost, m.validation_effective_samples = validation_cost(
                    model, [effect(n) for n in m.effects], validation, params[frozenset(m.effects)], how, sigma_v,
                    measured)
                say(f"  {m.label}: validation free-run cost {m.validation_cost:.5g} "
                    f"({m.validation_effective_samples:.0f} effective samples)")
        evidence.update({k: v for k, v in weigh(models, nominal.J, which.get("J_floor"),
                                                reference=getattr(mine, "validation_cost", None)).items()
                         if k == "nu_validation"})
        own, near = rivals(models, selected, nests, ratio=SCOPE)
        # a richer nested rival is not switched to by the weights: the likelihood-ratio test found its
        # extra parameters not needed (reestimation.prefer_nested), and a richer form left unresolved caps
        # the confidence; a simpler one is, where the validation record outweighs that test
        simpler = {e for s in selected for e in nests.get(s, ())}
        best = max((r["model"] for r in near if frozenset(r["model"].effects) in params
                    and (not r["nested"] or r["effect"] in simpler)), key=lambda m: m.weight, default=None)
        if best is not None and best.weight > mine.weight:
            old = mine
            mine, selected = best, list(best.effects)
            own, near = _rivals_beside(models, selected, nests, old)
            switch = _switch_to(best, old, simpler=any(e in simpler for e in best.effects))
    # the free runs of the selection and its heaviest rivals on both records, pointwise
    records = [(data, sigma)] + ([(validation, sigma_v)] if validation is not None else [])
    runs: dict = {}

    def residuals(m) -> list[dict] | None:
        key = frozenset(m.effects)
        if key not in runs:
            p = fitted(m)
            res = [None if p is None else free_run_residuals(model, [effect(n) for n in m.effects], rec, p, how, sg,
                                                     measured if rec is validation else None)
                   for rec, sg in records]
            runs[key] = None if any(r is None for r in res) else res
        return runs[key]
    for r in near[:RIVALS]:
        a, b = residuals(mine), residuals(r["model"])
        if a is None or b is None:
            continue
        parts = [cost_difference(pointwise_cost(x), pointwise_cost(y)) for x, y in zip(a, b)]
        dC, se = sum(p[0] for p in parts), math.sqrt(sum(p[1] ** 2 for p in parts))
        # their free runs' separation on the records given, Σ((y_A − y_B)/σ)² = Σ(r_A − r_B)²
        S = sum(float(np.nansum((x[c] - y[c]) ** 2)) for x, y in zip(a, b) for c in x)
        r.update(cost_difference=dC, standard_error=se, z=dC / se if se > 0 else math.copysign(math.inf, dC),
                 separation=S)
        r["power"] = separation_power(S, se)
        say(f"  {mine.label} against {r['model'].label}: free-run costs {dC:+.4g} ± {se:.3g} (z = {r['z']:.3g}), "
            f"separation of their free runs {S:.4g} noise units")
    alike = [r for r in near if r["ratio"] >= LOOK_ALIKE or _told(r) < LOOK_ALIKE_Z]
    weighed = None      # a simpler or richer form of the selection among the look-alikes, weighed by output error
    not_weighed: dict[frozenset, str] = {}      # the weighings not tried, by the richer form's effects
    nested = None if switch or screened or validation is None else next(
        (r for r in alike if nested_in(library, r["model"].effects, selected)
         or nested_in(library, selected, r["model"].effects)), None)
    if nested is not None and fitted(nested["model"]) is not None and frozenset(selected) in params:
        other = (list(nested["model"].effects), fitted(nested["model"]))
        pair = ((other, (selected, params[frozenset(selected)])) if nested_in(library, other[0], selected)
                else ((selected, params[frozenset(selected)]), other))        # (simpler, richer)
        weighed = by_output_error(model, library, *pair[0], *pair[1], data, validation, sigma, sigma_v, say,
                                  not_weighed)
    if weighed is not None:
        z, rival = weighed["z"], nested["model"]
        if decided(weighed):     # the records tell them apart
            alike, near = [r for r in alike if r is not nested], [r for r in near if r is not nested]
            if sorted(rival.effects) == sorted(weighed["effects"] if z >= RICHER_Z else weighed["simple"]):
                switch = _weighed_switch(rival.effects, selected, weighed, getattr(rival, "refit", None) or rival.result,
                                         rival.explained_excess)
                selected = list(rival.effects)
                alike = [r for r in alike if r["effect"] not in selected]
    held = sum(m.weight for m in models if all(any(e == s or s in nests.get(e, ()) for e in m.effects)
                                                   for s in selected))
    confidence = own if alike else held
    zs = [_told(r) for r in near if "z" in r]
    if zs:
        confidence = min(confidence, _phi(min(zs)))
    if weighed is not None:     # the chance that the selection predicts better than its nested look-alike
        confidence = min(confidence, _phi(_from_selection(weighed, selected)))
    unresolved = [] if switch else unresolved
    # a richer form of the selection the TPBVP could not estimate, or the selection and the effect the gain
    # rule set aside beside it, weighed by output error
    complement = None if unresolved or switch or screened else _complemented(models, mine)
    richer = None
    if (unresolved or complement) and validation is not None and not screened and frozenset(selected) in params:
        rich, why = ((unresolved[0].effects, "its TPBVP estimate did not converge") if unresolved else
                     (complement.effects, f"its second effect lowers the TPBVP's J by less than {PAIR_GAIN:.0%} "
                                          f"of what {' + '.join(selected)} leaves"))
        richer = by_output_error(model, library, selected, params[frozenset(selected)], rich, None, data,
                                 validation, sigma, sigma_v, say, not_weighed)
    if richer is not None:
        not_weighed.pop(frozenset(richer["effects"]), None)     # weighed after all (a faster simpler fit)
        weighed, z = richer, richer["z"]
        if decided(richer):     # the records decide between the two
            unresolved = [m for m in unresolved if sorted(m.effects) != sorted(richer["effects"])]
        if z >= RICHER_Z:
            replaced, selected = list(selected), list(richer["effects"])
            confidence = min(confidence, _phi(z))
            alike = [r for r in alike if r["effect"] not in selected + replaced]
            switch = _weighed_switch(selected, replaced, richer, free_run=as_answer(
                model, library, richer, nominal.parameters, data, validation, sigma, sigma_v, confidence, why))
            design = False          # the experiment's models would be the replaced selection's
        else:
            confidence = min(confidence, _phi(-z))
    # (also after a switch by the weights alone: the validation record may take the imitation for its own law)
    weighed_out = switch is not None and bool(switch.get("output_error") or switch.get("free_run"))
    imitated = None if screened or weighed_out else _imitated(library, selected, params, near)
    if imitated is not None:        # step 6: the effect whose law the selection's estimate takes the shape of
        r, why = imitated
        switch = _switch_to(r["model"], mine, replaced=list(selected), imitated=why, z=r["z"])
        selected = list(r["model"].effects)
        near, alike = [], []        # the records' comparisons were the replaced selection's
        confidence = min(confidence, UNRESOLVED)
    undecided = [e for m in unresolved for e in m.effects if e not in selected]
    if switch and switch["simpler"]:    # the records disagree: the identification record took the richer form
        undecided += [e for e in switch["replaced"] if e not in selected]
    if undecided:           # a richer form no start could estimate, or one the records disagree on
        confidence = min(confidence, UNRESOLVED)
    out = dict(lookalikes=list(dict.fromkeys([r["effect"] for r in alike] + undecided)),
               confidence=confidence if (alike or zs or screened or undecided or weighed is not None) else None,
               evidence=evidence, switch=switch, experiment=None, threshold=LOOK_ALIKE, threshold_z=LOOK_ALIKE_Z,
               unresolved=[m.label for m in unresolved], unexplained=None, unphysical=[],
               output_error=weighed, not_weighed=list(not_weighed.values()),
               rivals=[dict(effect=r["effect"], effects=list(r["model"].effects), weight=r["weight"], ratio=r["ratio"],
                            nested=r["nested"], validation_cost=getattr(r["model"], "validation_cost", None),
                            **{k: r[k] for k in ("cost_difference", "standard_error", "z", "separation", "power")
                               if k in r},
                            lookalike=any(r is x for x in alike))
                       for r in near[:RIVALS] + [x for x in alike[RIVALS:] if not any(x is y for y in near[:RIVALS])]])
    def experiment(rival) -> dict | None:
        pa, pb = params.get(frozenset(selected)), fitted(rival)
        if pb is None and rival.result is not None:          # its linearised re-estimate
            pb = dict(rival.result.parameters)
        if pa is None or pb is None:
            return None
        return pair_experiment((list(selected), pa), (list(rival.effects), pb))

    def pair_experiment(a, b) -> dict | None:       # each (its effects, its parameters)
        return propose(model, library, [a, b], data, sigma, validation, effects_of=effect, log=say,
                       nominal=None if screened else nominal.parameters)
    undecided_pair = _undecided_fits(weighed, selected, undecided)
    if alike and design:
        out["experiment"] = experiment(alike[0]["model"])
    elif undecided_pair and design:     # the look-alike is a richer form only output error estimated
        out["experiment"] = pair_experiment(*undecided_pair)
    elif near:              # on request (``--design``): against the heaviest rival, look-alike or not
        out["propose"] = lambda: experiment(near[0]["model"])
    out["words"] = words(out, selected)
    return out


def _undecided_fits(weighed: dict | None, selected: Sequence[str], undecided: Sequence[str]) -> tuple | None:
    """The selection and the undecided richer form of it as the output-error weighing fitted them —
    ((effects, parameters), (effects, parameters)) — where that weighing is of the two and left
    them undecided (step 4: a richer form without a converged TPBVP estimate); else None."""
    extra = set() if weighed is None else set(weighed["effects"]) - set(selected)
    if not extra or not extra <= set(undecided) or sorted(weighed["simple"]) != sorted(selected):
        return None
    return ((list(weighed["simple"]), weighed["parameters_simple"]),
            (list(weighed["effects"]), weighed["parameters"]))


def _richer_at_their_minimum(models: list, mine, selected: Sequence[str], library: Library, fitted, evidence: dict,
                             J0: float, which: dict, say: Callable[[str], None]) -> list:
    """The selection with one effect replaced by a richer one that nests it (Stribeck friction for
    Coulomb friction) has its minimum at or below the selection's J.  Where that model was not
    scored (a pair the ranking did not form: it is added to ``models``), or its score lies above
    the selection's (its own start found another minimum) or is no converged re-estimate, it is
    re-estimated (``fitted(m, again=True)``: also from the selection's solution) and, with a lower
    J, takes that estimate's score; the weights are then made again (:func:`.selection.weigh`, on the
    effective size already used).  Returns those richer models that no start brought to a converged
    estimate at or below the selection's J (*unresolved*: the records' verdict on them is not known)."""
    nu = evidence.get("nu") or 2.0
    changed, unresolved = False, []
    for s in selected:
        for rich in (e for e in library.effects if s in e.nests and e.name not in selected):
            effs = [rich.name if e == s else e for e in selected]
            m = next((x for x in models if sorted(x.effects) == sorted(effs)), None)
            if m is None:
                k = sum(len(library[e].parameters) for e in effs)
                m = Candidate(effects=effs, k=k, J=math.inf, parameters={p: v for e in effs for p, v in
                                                                         library[e].parameters.items()},
                              result=None, criterion=math.inf)
                models.append(m)
            elif m.full and m.result is not None and m.result.success and m.J <= mine.J:
                continue
            say(f"  {m.label} contains {mine.label} but scored J {m.J:.5g} against its {mine.J:.5g}: re-estimated")
            if fitted(m, again=True) is not None and getattr(m, "refit", None) is not None and m.refit.J < m.J:
                m.update(m.refit, nu)
                m.full, changed = True, True
                say(f"  {m.label}: J {m.J:.5g}")
            if not (m.full and m.result is not None and m.result.success and m.J <= mine.J * (1.0 + 1e-9)):
                unresolved.append(m)
    if changed:
        weigh(models, J0, which.get("J_floor"), reference=getattr(mine, "validation_cost", None))
    return unresolved


def _rivals_beside(models: list, selected: Sequence[str], nests: Mapping, old) -> tuple[float, list[dict]]:
    """:func:`.selection.rivals` of a selection that replaced ``old``: the effects weighing at least
    :data:`SCOPE` of it, and ``old``'s effects whatever their weight — the records are asked how far
    they tell the new selection from the one it replaced."""
    own, near = rivals(models, selected, nests, ratio=0.0)
    return own, [r for r in near if r["ratio"] >= SCOPE or r["effect"] in old.effects]


def _complemented(models: Sequence, mine) -> object | None:
    """The heaviest model where it is the selection ``mine`` and one effect more — a pair that
    :func:`.selection.select` set aside for its second effect's gain on J — else None."""
    top, chosen = heaviest(models), set(mine.effects)
    return top if chosen and chosen < set(top.effects) and len(top.effects) == len(chosen) + 1 else None


def _imitated(library: Library, selected: Sequence[str], params: Mapping, near: Sequence[dict]) -> tuple | None:
    """The compared rival whose law the selection's estimate takes the shape of (:attr:`.effects.Effect.imitates`)
    where that estimate is not physical, the rival's own estimate is, and the records do not prefer the
    selection by :data:`.nested.RICHER_Z` standard errors: (the rival, the ways the estimate is not
    physical); else None."""
    values = params.get(frozenset(selected))
    if values is None:
        return None
    for name in selected:
        e = library[name]
        why = unphysical([e], values)
        other = e.imitates({p: values[p] for p in e.parameters}) if e.imitates is not None and why else None
        if other is None or other not in library.names:
            continue
        want = frozenset(other if s == name else s for s in selected)
        theirs = params.get(want)
        if theirs is None or unphysical([library[n] for n in want], theirs):
            continue
        r = next((r for r in near if frozenset(r["model"].effects) == want), None)
        if r is not None and r.get("z", math.inf) < RICHER_Z:
            return r, why
    return None


def _switch_to(model, old, simpler: bool = False, **more) -> dict:
    """The switch of the selection ``old`` (its :class:`.selection.Candidate`) to ``model``, estimated by
    the TPBVP (its re-estimate where it has one); ``more``: the step's own entries."""
    return dict(dict(effects=list(model.effects), result=getattr(model, "refit", None) or model.result,
                     replaced=list(old.effects), weight=model.weight, replaced_weight=old.weight,
                     explained_excess=model.explained_excess, simpler=simpler), **more)


def _weighed_switch(effects: Sequence[str], replaced: Sequence[str], weighed: dict, result=None,
                    explained_excess: float | None = None, free_run: dict | None = None) -> dict:
    """The switch of the selection ``replaced`` to ``effects`` that the weighing ``weighed`` decided:
    the answer's weight Φ(|z|); ``result``, its TPBVP estimate, or ``free_run``, its answer by output
    error (:func:`.nested.as_answer`)."""
    w = _phi(abs(weighed["z"]))
    out = dict(effects=list(effects), result=result, replaced=list(replaced), weight=w, replaced_weight=1.0 - w,
               explained_excess=explained_excess, simpler=False, output_error=weighed)
    return out if free_run is None else dict(out, free_run=free_run)


def _from_selection(weighed: dict, selected: Sequence[str]) -> float:
    """The z of the weighing ``weighed`` (:func:`.nested.by_output_error`) from the side of the
    selection: z where it is the richer form, −z where it is the simpler (z > 0: the richer predicts
    the records better)."""
    return -weighed["z"] if sorted(selected) == sorted(weighed["simple"]) else weighed["z"]


def _told(rival: dict) -> float:
    """How far the records tell a compared rival from the selection, in standard deviations: the
    smaller of z (the costs' difference over its spread) and :func:`.design.separation_z` of their free
    runs' separation; inf where not compared."""
    if "z" not in rival:
        return math.inf
    return min(rival["z"], separation_z(rival["separation"], rival.get("standard_error") or 0.0))


def _phi(z: float) -> float:
    """The standard normal distribution function."""
    return float(ndtr(z))


def _criterion(J: float, k: int, nu: float) -> float:
    return criterion(J, k, max(nu, 2.0))


def _screened(model: IdentificationModel, library: Library, free_run: dict, data: Measurements):
    """The free-run screen's candidates as weighed models: the model it added them to (the nominal
    model's declared refinements walked to its name), an effect by name for that model (from its
    own library where it has one, :func:`.libraries.library_for`: an effect's terms name the rows of
    the model it was built for), a :class:`.selection.Candidate` per converged candidate and one without
    an effect — ``J`` twice the output-error cost on the identification record (Σ ((y − z)/σ)²),
    ``validation_cost`` the free-run cost on the validation record (:mod:`.free_run_screen`) — and
    the fitted parameters by effects."""
    base = model
    for _ in range(4):
        if model.name == free_run.get("model"):
            break
        refine = model.settings.refine
        finer = refine() if callable(refine) else None
        if finer is None:
            break
        model = finer
    fine = library_for(model, data) if model is not base else library

    def effect(name: str):
        return fine[name] if name in fine.names else library[name]

    nominal = free_run.get("nominal") or {}
    none = Candidate(effects=[], k=0, J=2.0 * float(nominal.get("cost", math.inf)), parameters={}, result=None)
    none.validation_cost = free_run.get("nominal_validation_cost")
    models, params = [none], {}
    for r in free_run.get("candidates", []):
        if not (r.get("success") and math.isfinite(r.get("validation_cost", math.inf))):
            continue
        m = Candidate(effects=[r["effect"]], k=len(effect(r["effect"]).parameters),
                      J=2.0 * float(r["identification_cost"]), parameters=dict(r["parameters"]), result=None)
        m.validation_cost, m.validation_effective_samples = r["validation_cost"], r.get("validation_effective_samples")
        models.append(m)
        params[frozenset([r["effect"]])] = dict(r["parameters"])
    return model, effect, models, params


