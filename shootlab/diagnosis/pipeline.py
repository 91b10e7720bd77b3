"""The whole diagnosis (docs/design.md §4; ``docs/diagnosis.md``): :func:`diagnose` runs the steps in turn —
the nominal estimate, the noise floor (:mod:`.floor`), where (:mod:`.where`), which (:mod:`.which`)
and how far it shrinks (:mod:`.shrinkage`) — and settles the verdict.

Honest failure: an estimate that does not converge is retried on 2, 4 and 8 times the shooting
points (:func:`shootlab.diagnosis.estimators.estimate_retrying`); if it still fails the status is
``inconclusive`` and no shrink is reported.  With a validation record a selection counts only when
it makes the free-run misfit there shrink (:func:`settle`); otherwise the next-best models are
tried, and without one that shrinks it the status is ``not_confirmed``.  Between nested models the
simpler one is kept unless a likelihood-ratio test needs the richer one (:func:`prefer_nested`).
"""
from __future__ import annotations

import math
import time
from typing import Callable, Sequence

from shootlab.estimation.data import Measurements, with_filled_inputs
from shootlab.estimation.fit import EstimationResult
from shootlab.estimation.model import IdentificationModel
from .estimators import default_estimator, estimate_retrying, with_device, with_progress
from .effects import Library, unphysical
from .libraries import library_for
from .composition import extend
from .confirmation import confirm, reselect, validation_costs
from .floor import beyond_floor, left_by, noise_floor, validation_evidence
from .lookalikes import discriminate
from .lookalike_words import misfit_left, stand_in, stand_in_words
from .free_run_screen import rank_by_validation, screen
from .numerics import numerical_check
from .outcome import Diagnosis, Status, fmt
from .progress import brief, fit_line, progress_sink
from .shrinkage import validation_summary
from .verdicts import evidence_measure, evidence_words, measure_words, no_error_words, unexplained_words
from .where import locate, row_energy
from .selection import Candidate, ranking_nu
from .which import rank
from shootlab.estimation.weights import from_data

from .reestimation import (NESTED_ALPHA, from_nested, prefer_nested, reestimate, refitter, shrink_table,
                           undetermined)

__all__ = ["diagnose", "settle", "reestimate", "prefer_nested", "from_nested", "NESTED_ALPHA"]


def diagnose(model: IdentificationModel | str, data, library: Library | None = None, validation=None,
             nominal: EstimationResult | None = None, effects: Sequence[str] | None = None, seed: int = 0,
             alpha: float = 0.01, ratio_min: float = 1.5, share_min: float = 0.005, explained_min: float = 0.5,
             pairs: int = 3, alternatives: int = 2, numerics: bool = True,
             log: Callable[[str], None] | None = None, progress: bool = True, verbose: bool = False,
             device=None) -> Diagnosis:
    """Where / which / how far (module docstring) for ``model`` on ``data``.

    Parameters
    ----------
    model : IdentificationModel or str
        The nominal model, or an installed name (``"flexible"``).
    data : Measurements, str, path or dict of arrays
        The identification record.
    library : Library, optional
        The candidate effects and the family's estimation strategy; default
        :func:`library_for` (the model's own, its mechanics', the installed one, or offsets).
    validation : Measurements, str, path or dict of arrays, optional
        A record with another input: a selection counts only when it makes the free-run misfit
        there shrink; otherwise up to ``alternatives`` next-best models are tried.
    nominal : EstimationResult, optional
        An estimate of ``model`` on ``data`` to start from; else the library's estimator runs.
    effects : sequence of str, optional
        Only these candidates of the library.
    seed : int, optional
        Seed of the noise-floor surrogates' noise.
    alpha : float, optional
        Significance level of the rows' F tests and of the nested effects' likelihood-ratio
        tests (default 0.01).
    ratio_min, share_min : float, optional
        A row is significant only when its mean square is at least ``ratio_min`` times the
        floor's and its excess at least ``share_min`` of J (defaults 1.5 and 0.005).
    explained_min : float, optional
        Nothing is selected when the best candidate explains less than this share of the
        residual's excess over the floor (default 0.5).
    pairs : int, optional
        The best ``pairs`` singles are also scored two by two (default 3).
    alternatives : int, optional
        Next-best models tried when the selection does not shrink the validation misfit
        (default 2).
    numerics : bool, optional
        Numerical causes first (:mod:`.numerics`, default True): a significant residual that
        twice the shooting points or the model's declared refinement (``settings.refine``)
        brings to the floor, or by most of its excess, is answered ``numerical`` before any
        effect is tried.
    log : callable, optional
        Receives the progress lines (:mod:`.progress`: one per step and one per fit) instead of
        standard error.
    progress : bool, optional
        False: no progress lines.
    verbose : bool, optional
        Also a line per Newton iteration of every estimate.
    device : str or torch.device, optional
        Where the estimates' TPBVPs are solved (``"cpu"`` default, ``"cuda"``, ``"auto"``).

    Returns
    -------
    Diagnosis
        ``status`` (``confirmed``, ``selected``, ``no_structural_error``, ``unexplained``,
        ``numerical``, ``not_confirmed``, ``inconclusive``; :attr:`Diagnosis.status`),
        ``verdict`` in words, ``selected`` effects, the ``where`` table, the ranking, the
        extended estimate and the shrink of the misfit.  An estimate that does not converge is
        retried on 2, 4 and 8 times the shooting points; if it still fails the status is
        ``inconclusive`` and no shrink is reported.

    Raises
    ------
    ValueError
        Bad input: an unknown model or effect name, a record without the model's channels.
    """
    with progress_sink(log, progress, verbose) as sink:
        return _diagnose(model, data, library, validation, nominal, effects, seed, alpha, ratio_min, share_min,
                         explained_min, pairs, alternatives, numerics, sink, verbose, device)


def _diagnose(model, data, library, validation, nominal, effects, seed, alpha, ratio_min, share_min, explained_min,
              pairs, alternatives, numerics, log, verbose, device) -> Diagnosis:
    """:func:`diagnose` with its progress lines given to ``log`` (None: none)."""
    say = log or (lambda s: None)
    if isinstance(model, str):
        from shootlab.estimation.lookup import resolve_model
        model = resolve_model(model)
    data = with_filled_inputs(Measurements.coerce(data), model.given)
    data.require(model.measured, float(data.t[0]), float(data.t[-1]))
    model = from_data(model, data)          # default weights scaled once, by the identification record
    if validation is not None:
        validation = with_filled_inputs(Measurements.coerce(validation), model.given)
        validation.require(model.measured, float(validation.t[0]), float(validation.t[-1]))
    library = library or library_for(model, data)
    estimator = with_device(with_progress(library.estimator or default_estimator, verbose and log is not None), device)
    cands, skipped = library.applicable(model)
    if effects is not None:
        unknown = [e for e in effects if e not in library.names]
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; the library {library.name!r} has {library.names}")
        cands = [e for e in cands if e.name in effects]
    seconds = {}
    notes = []
    t0 = time.perf_counter()
    if nominal is None:
        say(f"estimating the nominal model {model.name} ...")
        nominal, tried = estimate_retrying(estimator, model, data, say)
        notes += tried
        say(fit_line(f"  {model.name}", nominal, time.perf_counter() - t0))
    seconds["nominal"] = time.perf_counter() - t0
    nm = nominal.problem.model
    if not nominal.success:         # the verdict says the message's first sentence, the notes all of it
        return Diagnosis(model=nm, library=library, data=data, validation=validation, nominal=nominal, floor=None,
                         noise={}, where=[], significant=False, which={}, selected=[],
                         verdict=f"inconclusive: the nominal model {model.name} could not be estimated "
                                 f"({brief(nominal.message)})", extended=None, shrink=None, skipped=skipped,
                         seconds=seconds, notes=notes + [f"the nominal estimate: {nominal.message}"],
                         status=Status.INCONCLUSIVE)
    say("  " + ", ".join(f"{k} = {v:.5g}" for k, v in nominal.parameters.items()))
    # noise floor
    t0 = time.perf_counter()
    sigma, floor, floor_notes = noise_floor(nominal, data, estimator, seed=seed, log=say,
                                              initial_state=library.initial_state)
    notes += floor_notes
    seconds["floor"] = time.perf_counter() - t0
    where = locate(nominal, floor, alpha=alpha, ratio_min=ratio_min, share_min=share_min)
    on_identification = any(w["significant"] for w in where)
    if floor is None:
        on_identification = True
        notes.append("without a noise floor every residual is treated as significant")
    say("where: " + ", ".join(f"{w['equation']} {100 * w['share']:.1f} %" + (" *" if w["significant"] else "")
                              for w in where if w["share"] >= 0.005))
    evidence = None
    if validation is not None:      # is the validation free run more than the noise explains?
        t0 = time.perf_counter()
        evidence = validation_evidence(nominal, floor, validation, library.initial_state, seed=seed, alpha=alpha)
        seconds["evidence"] = time.perf_counter() - t0
        say(f"validation: the nominal model's {evidence_measure(evidence)} {fmt(evidence['misfit'])} times the noise "
            f"({fmt(evidence['floor_misfit'])} on the noise floor; p = {fmt(evidence['p_value'], '.2g')})"
            + (" *" if evidence["significant"] else "") + f", {seconds['evidence']:.1f} s")
    on_validation = bool(evidence and evidence["significant"])
    significant = on_identification or on_validation
    numerical = None
    if on_identification and floor is not None and numerics:
        t0 = time.perf_counter()
        numerical, numerical_verdict = numerical_check(nominal, floor, data, estimator,
                                                       initial_state=library.initial_state, log=say)
        seconds["numerics"] = time.perf_counter() - t0
        if numerical_verdict is not None:
            say(numerical_verdict)
            return Diagnosis(model=nm, library=library, data=data, validation=validation, nominal=nominal,
                             floor=floor, noise=sigma, where=where, significant=significant, which={}, selected=[],
                             verdict=numerical_verdict, extended=None, shrink=unchanged(nominal, validation, library),
                             skipped=skipped, seconds=seconds, notes=notes, status=Status.NUMERICAL,
                             numerical=numerical, evidence=evidence)
    # which
    t0 = time.perf_counter()
    floor_sigma = {w["equation"]: w.get("floor_rms", 0.0) for w in where if w["kind"] != "dynamics"}
    if floor is None:
        floor_sigma = {w["equation"]: w["rms"] for w in where if w["kind"] != "dynamics"}
    n_eff = sum(w.get("n_eff", 0.0) for w in where if w["kind"] != "dynamics" and floor_sigma.get(w["equation"], 0) > 0)
    meas = [w for w in where if w["kind"] == "measurement" and w.get("channel") not in nm.given]
    nu = sum(w.get("n_eff", 0.0) for w in meas) if floor is not None else len(meas) * nominal.t.numel()
    # with the evidence on the validation record alone J is at its floor: the shares of J the
    # candidates explain are then of J itself, not of an excess over the floor
    J_floor = floor.J if floor is not None and (on_identification or not significant) else None
    say(f"which: {len(cands)} candidates, linearised re-estimation of each ...")
    which = rank(nominal, cands, data, floor_sigma=floor_sigma, n_eff=n_eff or nominal.t.numel(),
                 nu=nu or nominal.t.numel(), J_floor=J_floor, significant=significant,
                 explained_min=explained_min, pairs=pairs, log=say)
    seconds["rank"] = time.perf_counter() - t0
    skipped.update(which["not_identifiable"])
    selected, verdict = (which["selected"], which["verdict"]) if on_identification else ([], which["verdict"])
    say("which: " + ", ".join(f"{r['effect']} {100 * r['score']:.0f} % (confidence {r['confidence_nested']:.2f})"
                              for r in which["ranking"][:4]))
    if selected:            # (without a selection this is the final verdict, which the caller reports)
        say(verdict)
    extended_res, sh, free_run = None, None, None
    status = Status.NO_STRUCTURAL_ERROR if not significant else (Status.SELECTED if selected else Status.UNEXPLAINED)
    if not significant:
        verdict = no_error_words(nominal.J, floor, evidence)
    elif not on_identification:
        verdict = "the validation misfit is more than the noise explains but no candidate explains it"
    if selected:
        t0 = time.perf_counter()
        selected, status, verdict, extended_res, sh, settled = settle(
            nominal, library, estimator, which, data, validation, nu, explained_min, alternatives, log=say,
            evidence=evidence)
        notes += settled
        seconds["extended"] = time.perf_counter() - t0
    # the leading candidates re-estimated in full: before an answer without an explanation, and where
    # the validation record carries evidence the selection does not explain (the ranking on both records)
    unanswered = status in (Status.UNEXPLAINED, Status.INCONCLUSIVE)
    kept = selection_on_validation(nominal, library, selected, extended_res, validation, evidence, say) \
        if on_validation and status is Status.CONFIRMED and not library.free_run_screen else None
    weak = on_validation and (status is Status.NOT_CONFIRMED or (kept is not None and kept.why is not None))
    if significant and (unanswered or weak) and not library.free_run_screen:
        t0 = time.perf_counter()
        lead, got = confirmed_leaders(nominal, library, estimator, which, data, validation, evidence, nu, J_floor,
                                      on_identification and unanswered, explained_min, alternatives, say, notes,
                                      extra=[kept] if kept is not None else [])
        seconds["leaders"] = time.perf_counter() - t0
        if got is not None:
            if kept is not None and got[0] != kept.effects:
                notes.append(f"the TPBVP's selection {kept.label} was confirmed, but {kept.why}; the validation "
                             f"record decided between it and the leading candidates re-estimated in full")
            selected, status, verdict, extended_res, sh, free_run = got
        elif unanswered:
            verdict = unexplained_words(verdict, lead)
    if sh is None and status is not Status.INCONCLUSIVE:
        sh = unchanged(nominal, validation, library)
    after = None                # the answer's validation misfit by the evidence's measure
    if evidence is not None and status is Status.CONFIRMED and extended_res is not None and not library.free_run_screen:
        same = kept is not None and sorted(kept.effects) == sorted(selected) and kept.result is extended_res
        final = kept if same else selection_on_validation(nominal, library, selected, extended_res, validation,
                                                          evidence, say)
        after = final.validation_cost if final is not None else None
        if after is not None and after > evidence["cost"]:
            # confirmed by the free run from the record's start, while the measure that carries the
            # validation evidence says it predicts that record worse than the nominal model
            notes.append(f"{' + '.join(selected)} was confirmed by the free run from the record's start: {verdict}")
            later = verdict.partition("; ")[2]      # settle's clauses after its head (which has no "; ")
            verdict = (f"not confirmed: {' + '.join(selected)} explains the identification record but predicts the "
                       f"validation record worse than the nominal model by the {evidence_measure(evidence)}: "
                       f"{math.sqrt(after / evidence['samples']):.3g}× the noise against {evidence['misfit']:.3g}×"
                       + (f"; {later}" if later else ""))
            selected, status, after = [], Status.NOT_CONFIRMED, None
    left, leaves = None, False  # what the answer leaves there against its own noise floor; beyond it?
    if after is not None and evidence["samples"] and beyond_floor(after, evidence)[2]:
        t0 = time.perf_counter()
        on_validation = extend(nm, [library[e] for e in selected], data=validation)
        say(f"validation: {' + '.join(selected)} leaves more than the noise floor explains; its own floor ...")
        left = left_by(extended_res, data, validation, estimator, on_validation, library.initial_state, seed=seed,
                       alpha=alpha, log=lambda line: say(f"  {line}"), shapes=floor.shapes if floor else {})
        seconds["left"] = time.perf_counter() - t0
        if left is not None:
            say(f"validation: what {' + '.join(selected)} leaves there {fmt(left['misfit'])} times the noise "
                f"({fmt(left['floor_misfit'])} on its own noise floor; p = {fmt(left['p_value'], '.2g')})"
                + (" *" if left["significant"] else "") + f", {seconds['left']:.1f} s")
        leaves = left is None or left["significant"]        # without its own floor, the nominal one's
    if library.free_run_screen and validation is not None and status in (
            Status.NO_STRUCTURAL_ERROR, Status.UNEXPLAINED, Status.NOT_CONFIRMED):
        t0 = time.perf_counter()
        say(f"the TPBVP's verdict: {verdict or status}; the free run on the validation record decides")
        free_run = screen(model, library, cands, data, validation, initial=nominal.parameters, log=say)
        seconds["free_run"] = time.perf_counter() - t0
        notes.append(f"the TPBVP's verdict was: {verdict or status.value.replace('_', ' ')}")
        verdict = free_run["verdict"]
        if free_run["selected"]:
            selected, status, extended_res, sh = list(free_run["selected"]), Status.CONFIRMED, None, free_run["shrink"]
        elif free_run["refinements"] and free_run["model"] != nm.name:
            status = Status.NUMERICAL
        say(verdict)
    elif evidence is not None and significant and status is not Status.NUMERICAL:
        verdict += f" — {evidence_words(on_identification, nominal.J, floor, evidence, after, selected, left)}"
    # look-alikes of the settled selection: the validation record's evidence on them, and an experiment
    # that can tell them apart (lookalikes.discriminate); a look-alike without a converged re-estimate is
    # re-estimated for it, from the selection's solution where it nests a selected effect (from_nested)
    told = None
    if selected and which:
        t0 = time.perf_counter()
        told = discriminate(nominal, library, which, selected, data, validation, sigma, extended_res, free_run,
                            refitter(nominal, library, estimator, selected, extended_res, data, validation, say),
                            log=say, measured=evidence)
        if told is not None and leaves and not told["switch"]:
            ref = left or dict(evidence, misfit=math.sqrt(after / evidence["samples"]),
                               p_value=beyond_floor(after, evidence)[1])
            misfit_left(told, selected, f"a validation misfit {fmt(ref['misfit'])}× the noise ({fmt(ref['floor_misfit'])}× "
                                        f"on {'its own' if left else 'the'} noise floor; p = {ref['p_value']:.2g})")
        if told is not None and told["switch"] and told["switch"].get("free_run"):
            # the screen's answer, another one; or a richer form of the selection fitted by output error
            free_run = dict(free_run or dict(method="output-error", refinements=[]), **told["switch"]["free_run"])
            selected, sh, verdict = list(free_run["selected"]), free_run["shrink"], free_run["verdict"]
            extended_res = None
        elif told is not None and told["switch"]:
            selected, extended_res = list(told["switch"]["effects"]), told["switch"]["result"]
            sh = shrink_table(nominal, library, selected, extended_res, validation)
            val = sh.get("validation")
            excess = min(max(told["switch"]["explained_excess"], 0.0), 1.0)
            verdict = (f"structural error explained by {' + '.join(selected)} ({100 * excess:.0f} % of the residual's "
                       f"excess over the noise floor)" + (
                f", confirmed on the validation record: the {measure_words(val)} shrinks {val['before']:.3g} -> "
                f"{val['after']:.3g}" if val and (val.get("shrink") or 0.0) > 0 else ""))
        seconds["lookalikes"] = time.perf_counter() - t0
    # the answer's estimate outside its effects' physical ranges: a stand-in (Effect.physical)
    estimated = status is Status.CONFIRMED and selected and extended_res is not None and extended_res.success
    # (a richer form fitted by output error: its estimate is that fit)
    weighed = told is not None and bool((told["switch"] or {}).get("output_error")) and told["switch"].get("free_run")
    values = (extended_res.parameters if estimated else
              free_run["extended"]["parameters"] if weighed and status is Status.CONFIRMED else None)
    odd = unphysical([library[e] for e in selected], values) if values else []
    stand_in(told, selected, odd)
    if told is not None and told["words"]:
        verdict += told["words"]
    if after is not None and not (told and told["switch"]):     # what the answer leaves (Diagnosis.confidence)
        evidence["selection"] = dict(cost=after, left=leaves, own_floor={
            k: left[k] for k in ("measure", "misfit", "floor_misfit", "p_value")} if left else None)
    out = Diagnosis(model=nm, library=library, data=data, validation=validation, nominal=nominal, floor=floor,
                    noise=sigma, where=where, significant=significant, which=which, selected=selected,
                    verdict=verdict, extended=extended_res, shrink=sh, skipped=skipped, seconds=seconds, notes=notes,
                    status=status, numerical=numerical, free_run=free_run, evidence=evidence,
                    lookalikes=told["lookalikes"] if told else [], discrimination=told, unphysical=odd)
    if odd:
        say(f"not physical: {', '.join(odd)}")
    if odd and told is None:        # stand_in's words without the look-alikes' (Diagnosis.confidence caps)
        out.verdict += stand_in_words(odd, selected, out.confidence)
    return out


#: a confirmed selection that removes this share of the validation misfit's excess over the noise
#: floor leaves too little for another candidate to decide on (:func:`selection_on_validation`)
REMOVES = 0.9


def selection_on_validation(nominal: EstimationResult, library: Library, selected: Sequence[str],
                            extended: EstimationResult | None, validation: Measurements, evidence: dict,
                            say: Callable[[str], None]) -> Candidate | None:
    """A confirmed selection measured on the validation record (:func:`.confirmation.validation_costs`),
    as a candidate of the ranking on both records; its ``why`` says why the validation record is to
    decide — it removes less than :data:`REMOVES` of the validation misfit's excess over the noise
    floor and leaves a significant misfit (:func:`.floor.beyond_floor`) — else None.  None without
    an estimate."""
    if extended is None or not selected:
        return None
    c = Candidate(effects=list(selected), k=0, J=extended.J, parameters={}, result=extended, full=True)
    validation_costs(nominal, [c], library, validation, evidence, log=say)
    if c.validation_cost is None:
        return None
    ratio, p, still = beyond_floor(c.validation_cost, evidence)
    c.why = (f"it removes {100 * c.validation_explained:.0f} % of the validation misfit's excess over the noise "
             f"floor and leaves a misfit {math.sqrt(ratio):.3g} times the floor's (p = {p:.2g})"
             if still and c.validation_explained < REMOVES else None)
    return c


def confirmed_leaders(nominal: EstimationResult, library: Library, estimator: Callable[..., EstimationResult],
                      which: dict, data: Measurements, validation: Measurements | None, evidence: dict | None,
                      nu: float, J_floor: float | None, reselecting: bool, explained_min: float,
                      alternatives: int, say: Callable[[str], None], notes: list[str],
                      extra: Sequence[Candidate] = ()) -> tuple[list[Candidate], tuple | None]:
    """The leading candidates re-estimated in full (:func:`.confirmation.confirm`), then (in turn,
    until one holds):

    * with ``reselecting`` (the evidence on the identification record and nothing selected yet),
      the selection made again from the converged scores (:func:`.confirmation.reselect`) and
      :func:`settle`-d;
    * with the evidence on the validation record, the confirmed candidates — and ``extra``, a
      selection already confirmed and measured there — ranked by their validation cost
      (:func:`.free_run_screen.rank_by_validation`: those that remove at least ``explained_min`` of
      the nominal validation misfit's excess over the noise floor, the lowest cost first, the
      fewest effects first among look-alikes) and :func:`settle`-d in that order; the ranking is
      kept as the free-run screen's record (``method`` "re-estimates").

    Returns the leaders and (selected, status, verdict, extended estimate, shrink table, free-run
    record) of the first that holds, or None."""
    say("which: the leading candidates re-estimated in full ...")
    lead = confirm(nominal, which["models"], library, data, ranking_nu(which, nu), which["design"], log=say,
                   known=[x.result for x in extra if x.result is not None])
    reselect(which, library, nominal.J, J_floor, True, explained_min)
    if reselecting:
        if which["selected"]:
            say(which["verdict"])
            got = settle(nominal, library, estimator, which, data, validation, nu, explained_min, alternatives,
                         log=say)
            notes += got[-1]
            if got[1] in (Status.CONFIRMED, Status.SELECTED):
                return lead, (*got[:5], None)
    if not (evidence and evidence["significant"]):
        return lead, None
    measured = list(extra) + [c for c in lead if not any(sorted(c.effects) == sorted(x.effects) for x in extra)]
    validation_costs(nominal, measured[len(extra):], library, validation, evidence, log=say)
    record = rank_by_validation(nominal.problem.model.name, measured, evidence, explained_min)
    if not record["order"] or any(record["order"][0] is x for x in extra):
        return lead, None                   # none better than the selection already confirmed
    got = settle(nominal, library, estimator, which, data, validation, nu, explained_min,
                 alternatives=len(record["order"]) - 1, log=say, choices=record["order"], by="validation",
                 evidence=evidence)
    notes += got[-1]
    if got[1] is not Status.CONFIRMED:
        return lead, None
    label = " + ".join(got[0])
    if label in record["weights"]:      # (a nested form taken instead has no validation weight: the ranking's)
        record.update(selected=list(got[0]), confidence=record["weights"][label], verdict=got[2])
    return lead, (*got[:5], record)


def unchanged(nominal: EstimationResult, validation: Measurements | None, library: Library) -> dict:
    """The shrink table when nothing is added: the "extended" model is the nominal one and nothing
    shrinks (the validation misfit of the nominal model is still reported)."""
    nm = nominal.problem.model
    e0 = row_energy(nominal)
    sh = dict(identification=dict(before=nominal.J, after=nominal.J, shrink=0.0,
                                  per_channel={r: dict(before=v, after=v, shrink=0.0) for r, v in e0.items()}),
              validation=None)
    if validation is not None:
        sh["validation"] = validation_summary(nm, None, validation, nominal.parameters, None, library.initial_state)
    return sh


def settle(nominal: EstimationResult, library: Library, estimator: Callable[..., EstimationResult], which: dict,
           data: Measurements, validation: Measurements | None, nu: float, explained_min: float = 0.5,
           alternatives: int = 2, log: Callable[[str], None] | None = None,
           choices: Sequence[Candidate] | None = None, by: str = "identification", evidence: dict | None = None
           ) -> tuple[list[str], Status, str, EstimationResult | None, dict | None, list[str]]:
    """The selected model re-estimated in full (:func:`reestimate`; nested simpler models preferred,
    :func:`prefer_nested`) and, with a validation record, confirmed there — else up to
    ``alternatives`` next-best models tried (the models of ``which`` that explain at least
    ``explained_min`` of the excess over the floor, by the criterion).  A model that cannot be
    estimated gives way to the next one (its nested simpler form first, :func:`prefer_nested`),
    with or without a validation record, and the verdict says what failed; ``inconclusive`` only
    when none of them can be estimated.  ``choices``: the models to try in this order instead
    (the first counts as the selection, the next ones as alternatives); ``by``: the record whose
    misfit their share refers to (``"identification"``: of J's excess over the floor,
    ``Candidate.explained_excess``; ``"validation"``: of the validation cost's excess,
    ``Candidate.validation_explained``; with ``evidence``, the validation record's, the nested test
    asks that record too and the verdict names a richer model passed over, :func:`prefer_nested`).
    Returns (selected, status, verdict, extended estimate, shrink table, notes)."""
    say = log or (lambda s: None)
    nm = nominal.problem.model
    if choices is None:
        first_choice = which["best"]
        choices = [first_choice] + [m for m in which["models"] if m.effects and set(m.effects) != set(first_choice.effects)
                                    and m.explained_excess >= explained_min]
    notes: list[str] = []
    rejected, failed, seen = [], [], []
    first, first_failed, count = None, None, 0
    verdict = ""
    for model_k in choices:
        effs, ranked = list(model_k.effects), model_k
        passed = None               # a richer model this choice passed over for a nested one
        if count > alternatives or (count > 0 and validation is None and not failed):
            break                   # alternatives: to confirm on a validation record, or after a failure
        if sorted(effs) in seen:
            continue
        seen.append(sorted(effs))
        k, count = count, count + 1
        # a model that embeds a nested simpler one (Stribeck friction, Coulomb's) that does not converge
        # from its linearised solution starts from the nested model's solution (prefer_nested) before
        # more shooting points are tried: the quick withheld-effect benchmark's stribeck_m2 record
        # failed on 101, 202, 404 and 808 points (9 s) and then converged from Coulomb's solution
        # (an alternative is tried on the model's shooting points only: the retries on more points are
        # the selection's)
        nested_first = any(library[e].embed for e in effs)
        extended_res, sh, tried = reestimate(nominal, library, estimator, effs, model_k, data, validation, say,
                                             retry=k == 0 and not nested_first)
        notes += tried
        if k == 0 or not extended_res.success:
            # parsimony: a nested simpler model that does as well, or where this one fails
            rich, rich_failed = list(effs), None if extended_res.success else extended_res.message
            effs, extended_res, sh, model_k = prefer_nested(nominal, library, estimator, which, effs, extended_res,
                                                            sh, model_k, data, validation, nu, notes, say, evidence)
            if nested_first and k == 0 and not extended_res.success and effs == rich:     # no nested start either
                extended_res, sh, tried = reestimate(nominal, library, estimator, effs, model_k, data, validation,
                                                     say)
                notes += tried
                if extended_res.success:
                    effs, extended_res, sh, model_k = prefer_nested(nominal, library, estimator, which, effs,
                                                                    extended_res, sh, model_k, data, validation, nu,
                                                                    notes, say, evidence)
            if effs != rich:
                seen.append(sorted(effs))
                if rich_failed is not None:          # the verdict says what failed
                    failed.append(f"{nm.name}+{'+'.join(rich)} ({brief(rich_failed)})")
                elif evidence is not None and ranked.validation_explained is not None:
                    # what may explain the rest: the richer model the validation record ranked
                    passed = (f"{' + '.join(rich)} removes {100 * min(ranked.validation_explained, 1.0):.0f} % of the validation "
                              f"misfit's excess over the noise floor but is not established ({notes[-1]})")
        if not extended_res.success:        # the next model is tried; the verdict says what failed
            first_failed = first_failed or extended_res
            failed.append(f"{nm.name}+{'+'.join(effs)} ({brief(extended_res.message)})")
            notes.append(f"the extended model {nm.name}+{'+'.join(effs)} could not be estimated: "
                         f"{extended_res.message}")
            say(f"  {' + '.join(effs)} could not be estimated: the next model is tried")
            continue
        if first is None:
            first = (extended_res, sh)
        loose = undetermined(extended_res, [library[e] for e in effs])
        if loose:                          # an effect the data do not pin down is not an answer
            rejected.append(f"{' + '.join(effs)}: {loose}")
            say(f"  {' + '.join(effs)}: {loose}: not confirmed")
            continue
        val = sh.get("validation")
        say(f"  J {nominal.J:.4g} -> {extended_res.J:.4g}" + (
            f"; validation misfit {fmt(val['before'], '.4g')} -> {fmt(val['after'], '.4g')} ({val['measure']})"
            if val else ""))
        share = (f"{100 * min(max(model_k.explained_excess, 0.0), 1.0):.0f} % of the residual's excess over the "
                 f"noise floor" if by == "identification" else
                 f"{100 * min(max(model_k.validation_explained or 0.0, 0.0), 1.0):.0f} % of the validation "
                 f"misfit's excess over the noise floor")
        verdict = f"structural error explained by {' + '.join(effs)} ({share})"
        if val is None:
            selected, status = list(effs), Status.SELECTED
            verdict += "; not confirmed on validation data (none given)"
        elif val["shrink"] is not None and val["shrink"] > 0:
            selected, status = list(effs), Status.CONFIRMED
            verdict += (f", confirmed on the validation record: the {measure_words(val)} shrinks "
                        f"{val['before']:.3g} -> {val['after']:.3g}")
        else:
            rejected.append(f"{' + '.join(effs)} explains the identification record but not the validation "
                            f"record (the free-run misfit does not shrink)")
            say(f"  {' + '.join(effs)} does not shrink the validation misfit: not confirmed")
            continue
        if passed:
            verdict += f"; {passed}"
        if rejected:
            verdict += f"; passed over: {'; '.join(rejected)}"
        if failed:
            verdict += f"; could not be estimated: {'; '.join(failed)}"
        return selected, status, verdict, extended_res, sh, notes
    if first is None:                       # nothing could be estimated: honest failure
        verdict = f"inconclusive: the extended model {failed[0]} could not be estimated" if len(failed) == 1 else \
            f"inconclusive: no extended model could be estimated: {'; '.join(failed)}"
        return [], Status.INCONCLUSIVE, verdict, first_failed, None, notes
    extended_res, sh = first                # report the first converged choice's figures
    verdict = f"not confirmed: {'; '.join(rejected)}"
    if failed:
        verdict += f"; could not be estimated: {'; '.join(failed)}"
    return [], Status.NOT_CONFIRMED, verdict, extended_res, sh, notes


