"""Which effect explains the residual (docs/design.md §4, step 2; ``docs/diagnosis.md``, "Which effect").

A candidate :class:`~shootlab.diagnosis.effects.Effect` adds a term to some rows of the model
(``f + term``); its *signature* is that term evaluated on the estimated states, inputs and data.

* :func:`~.screening.screen` (:mod:`.screening`) — the term fitted to the residual, rows
  standardised by the floor, the nominal parameters' sensitivities ∂(f + Fζ)/∂θ as free nuisance
  columns (what re-estimating them could absorb; :class:`~.screening.Design`), the effect's
  parameters by bounded non-linear least squares from a few starts: it picks the parameters the
  term is not linear in.
* :func:`score` — the linearised re-estimation (:func:`shootlab.diagnosis.estimators.one_step`: one
  undamped Newton step of the extended TPBVP from the nominal solution); :func:`score_pairs` —
  the best compatible singles in pairs; :func:`polish_leaders` — further steps for the leaders;
  :func:`fully_estimated` — the damped re-estimation that replaces a step that cannot be trusted.
* :func:`.selection.weigh` and :func:`.selection.select` (:mod:`.selection`) — the posterior
  weight of every model from the evidence of both records, the selection and its look-alikes.

Every model of the comparison is a :class:`~.selection.Candidate`; :func:`rank` runs the steps in turn.
"""
from __future__ import annotations

import itertools
import math
import time
from typing import Callable, Mapping, Sequence

from .composition import channel_reader
from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from .estimators import damped, one_step, one_steps
from .effects import Effect
from .progress import brief
from .screening import Design, collinearity, regression_design, screen
from .selection import PAIR_GAIN, Candidate, criterion, ranking_table, select, weigh

__all__ = ["score", "score_pairs", "polish_leaders", "fully_estimated", "rank", "outside_bounds"]


#: a candidate with less than this share of its term outside the nominal parameters'
#: sensitivities is not identifiable next to them (:func:`~.screening.collinearity`): re-estimating
#: the model's own parameters reproduces it (an input offset next to a constant force, an actuator
#: gain next to a free mass, damping and stiffness)
COLLINEAR_SHARE = 0.05

#: a linearised step that leaves J above this multiple of the nominal J has diverged (an effect
#: that does not help leaves J where it was); :func:`score` re-estimates that candidate in full
DIVERGED = 1.01

#: a pair's step that ends above its better member is re-estimated in full where the weaker
#: member alone lowers the nominal J by at least this share of the J the better one leaves: the
#: pair nests both, so its minimum lies below the better member's, by up to the weaker one's gain
#: where the two act apart; a smaller gain cannot move the ranking much, and that step stands
PAIR_REFIT = 0.1


# -- scoring, pairs, polish ------------------------------------------------------------------------
def score(nominal: EstimationResult, effect: Effect, design: Design, data: Measurements, nu: float,
          shape_trials: int = 4, refine: int = 2, log: Callable[[str], None] | None = None,
          in_full: bool = True) -> Candidate:
    """A single effect's linearised re-estimation (:func:`shootlab.diagnosis.estimators.one_step`), shape
    parameters held at the screened values — J after the step is what re-estimating with that
    effect leaves.  Other starting shapes are tried too (the screening sees the residual after the
    smoother has absorbed part of the error, its shape can be off), and a second step with every
    parameter free refines the shape from the ``refine`` best.  A step that diverges is replaced
    by a full re-estimation (:func:`fully_estimated`) when ``in_full``; otherwise (the residual is
    not significant, so no score can change the verdict) the candidate is not evaluated (J = ∞)."""
    say = log or (lambda s: None)
    clock = time.perf_counter()
    starts, screened, linear = screen(design, effect)
    share, along, absorbers = collinearity(design, effect, screened, linear)
    k = len(effect.parameters)
    if share < COLLINEAR_SHARE:
        why = (f"not identifiable: {100 * (1 - share):.4g} % of its term ({along}) is what re-estimating "
               f"{', '.join(absorbers)} already produces")
        say(f"  {effect.name:<22} {why}")
        return Candidate(effects=[effect.name], k=k, J=math.inf, parameters=dict(screened), result=None,
                         screened=screened, unidentifiable=why)
    shape = [p for p in effect.parameters if p not in linear]
    trials = [{p: (0.0 if p in linear else screened[p]) for p in effect.parameters}]
    for st in starts:
        cand = {p: (0.0 if p in linear else float(st[p])) for p in effect.parameters}
        if shape and all(cand != tr for tr in trials):
            trials.append(cand)
    trials = trials[:shape_trials] if shape else trials[:1]
    done = sorted(_stepped(nominal, effect, data, trials, shape if linear else (), [None] * len(trials), say),
                  key=lambda d: d[0])
    J, par, res = done[0]
    if shape:
        # a second undamped step with every parameter free refines the shape, from the two best
        # starts (a step from a start far from the optimum overshoots where the term is steep)
        firsts = [(par1, res1) for J1, par1, res1 in done[:refine] if res1 is not None and math.isfinite(J1)]
        for J2, par2, res2 in _stepped(nominal, effect, data, [p for p, _ in firsts], (), [r for _, r in firsts]):
            if res2 is not None and J2 < J and _inside([effect], par2):
                J, par, res = J2, par2, res2
    J0 = nominal.J
    diverged, full = not (J <= DIVERGED * J0 and _inside([effect], par)), False
    why = []
    if diverged and in_full:
        J, par, res = fully_estimated(nominal, [effect], data, screened, linear, why.append)
        full = res is not None
    elif diverged:
        why.append("not evaluated: the linearised step diverged, and the residual is not significant (no full "
                   "re-estimation)")
        J, par, res = math.inf, dict(screened), None
    say(f"  {effect.name:<22} {_outcome(J, J0, why)}" + (f" [{len(trials)} starts]" if len(trials) > 1 else "")
        + f", {time.perf_counter() - clock:.1f} s")
    return Candidate(effects=[effect.name], k=k, J=J, parameters=par, result=res, criterion=criterion(J, k, nu),
                     screened=screened, shape=shape if linear else [], full=full,
                     why=None if math.isfinite(J) else (why[-1] if why else "no re-estimate"))


def _stepped(nominal: EstimationResult, effect: Effect, data: Measurements, starts: Sequence[Mapping[str, float]],
             pinned: Sequence[str], warm: Sequence[EstimationResult | None],
             say: Callable[[str], None] | None = None) -> list[tuple[float, dict[str, float], EstimationResult | None]]:
    """(J, the effect's parameters, the re-estimate) of one undamped step from each start (warm
    from ``warm``'s estimate where given), the steps taken together
    (:func:`shootlab.diagnosis.estimators.one_steps`; one by one where they cannot be); a start that cannot be
    evaluated gives (inf, the start, None) and is reported through ``say``."""
    together = None
    if len(starts) > 1:
        try:
            together = one_steps(nominal, [effect], data, starts, pinned=pinned, warm=warm)
        except Exception:  # noqa: BLE001 - each start again alone, its failure reported
            pass
    out = []
    for i, (start, w) in enumerate(zip(starts, warm)):
        try:
            res = together[i] if together is not None else one_step(nominal, [effect], data, start, pinned, w)
            out.append((res.J if math.isfinite(res.J) else math.inf, {p: res.parameters[p] for p in effect.parameters},
                        res))
        except Exception as exc:  # noqa: BLE001 - a candidate that cannot be evaluated is reported
            out.append((math.inf, dict(start), None))
            if say is not None:
                say(f"  {effect.name}: start {_values(start)} not evaluated ({type(exc).__name__}: {brief(str(exc))})")
    return out


def _values(values: Mapping[str, float]) -> str:
    """``p = v, …`` with 4 significant digits."""
    return ", ".join(f"{p} = {v:.4g}" for p, v in values.items())


def _outcome(J: float, J0: float, why: Sequence[str]) -> str:
    """A candidate's score in words: J and how much less than the nominal ``J0`` it is (with how it
    was reached, ``why``'s last entry, where a full re-estimation replaced the step), or ``not
    converged: <why's first sentence>`` where no J was reached."""
    if not math.isfinite(J):            # the first sentence of why: a solver's message adds its advice
        text = brief(why[-1]) if why else "no re-estimate"
        return text if text.startswith("not ") else f"not converged: {text}"
    less = 100 * (J0 - J) / J0
    return (f"J {J:.5g} ({abs(less):.1f} % {'less' if less >= 0 else 'more'}" + (f"; {why[-1]}" if why else "")
            + ")")


def fully_estimated(nominal: EstimationResult, effects: Sequence[Effect], data: Measurements,
                    values: Mapping[str, float], linear: Sequence[str], say: Callable[[str], None],
                    context: str = "the linearised step diverged"
                    ) -> tuple[float, dict[str, float], EstimationResult | None]:
    """What replaces a diverged linearised step: the damped, full re-estimation
    (:func:`shootlab.diagnosis.estimators.damped`) of the model with ``effects`` from the data's states —
    with the nominal parameters and ``values``, then with the ``linear`` parameters at 0, then
    with the model's own initial parameter values (the nominal ones can be far from those of the
    extended model: the cascaded tanks' overflow needs a 36 % larger pump gain) — and last from
    the nominal solution; the first that converges inside the bounds to a J below the nominal
    one, else (inf, ``values``, None).  A start that converges below the nominal J outside the
    bounds ends the tries: the data put the effect's minimum there (on the quick withheld-effect
    benchmark every later start reached the same minimum, J to 1e-7: input_delay on three rig
    records, filter_permeability on three mixture records — 30 s of re-estimates).  ``context``
    opens the line said (why the candidate is re-estimated in full)."""
    names = [p for e in effects for p in e.parameters]
    zero = {p: (0.0 if p in linear else values[p]) for p in names}
    prior = dict(nominal.problem.model.prior)
    tries = [(dict(values), False), (zero, False), (dict(prior, **values), False), (zero, True)]
    seen, why = [], "no start converged"
    for start, warm in tries:
        if (start, warm) in seen:
            continue
        seen.append((start, warm))
        try:
            full = damped(nominal, list(effects), data, start, warm=warm)
        except Exception as exc:  # noqa: BLE001 - reported, the next start is tried
            why = f"{type(exc).__name__}: {exc}"
            continue
        par = {p: full.parameters[p] for p in names}
        if full.success and full.J < nominal.J and _inside(effects, par):
            say(f"{context}; damped re-estimation from "
                f"{'the nominal solution' if warm else 'the data'} in {full.iterations} iterations")
            return full.J, par, full
        why = (full.message if not full.success else ", ".join(outside_bounds(effects, par)) if full.J < nominal.J
               else f"J {full.J:.4g} not below the nominal {nominal.J:.4g}")
        if full.success and full.J < nominal.J:
            break       # a minimum below the nominal J outside the bounds: the later starts reach the same one
    say(f"{context} and no damped re-estimation converged inside the bounds below the nominal J ({why})")
    return math.inf, {p: values[p] for p in names}, None


def score_pairs(nominal: EstimationResult, singles: Sequence[Candidate], library: Mapping[str, Effect],
                data: Measurements, nu: float, pairs: int = 3,
                log: Callable[[str], None] | None = None) -> list[Candidate]:
    """The ``pairs`` best singles that reduce J — the best of each ``group`` of alternatives only, so
    that look-alikes (three friction laws) do not crowd out a genuine second effect — combined two
    by two, and the best single with every other one that reduces J (the second step of a forward
    selection: a second effect whose own score the first one masks, a small viscous term beside a
    large delay); each pair scored by one step from the members' parameters.

    A pair nests its better member, so a step that does no better has overshot.  Such a pair is
    re-estimated in full (:func:`fully_estimated`) where the weaker member's own gain matters
    (:data:`PAIR_REFIT`) or the better member was itself re-estimated in full; else its step
    stands.  On the README's rig record, Coulomb friction with the delay reached J 74.7 by one
    step, against 44.0 for the delay alone, 109.8 for the friction alone and the nominal 185; in
    full, 2.13.

    Where a pair's J stays above the nominal model's (the step blew up and no full re-estimation
    converged) and a member's effect nests a simpler one (Stribeck friction, Coulomb's), the pair
    is scored again with the simpler single in its place: a group counted once by its best member
    must not hide the pairs of its nested form (on the independent rig's load-side Coulomb record
    every step of Stribeck friction with a delay, an offset or a gain ended 11 to 40 times above
    the nominal J, and Coulomb friction with the delay, the record's effect, was never scored).
    An overshoot is re-estimated (above), not replaced."""
    say = log or (lambda s: None)
    order = [m for m in sorted(singles, key=lambda m: m.criterion) if math.isfinite(m.criterion) and m.J < nominal.J]
    by_effect = {m.effects[0]: m for m in order}        # the singles a pair may be formed of
    top, groups = [], set()
    for m in order:
        group = library[m.effects[0]].group
        if len(top) < max(pairs, 0) and (group is None or group not in groups):
            top.append(m)      # look-alike alternatives (three friction laws) count once
            groups.add(group)
    combos = list(itertools.combinations(top, 2))
    if pairs > 0:
        combos += [(order[0], m) for m in order[1:] if not any(m is x for x in top)]
    formed = {frozenset((ma.effects[0], mb.effects[0])) for ma, mb in combos}
    out = []
    for ma, mb in combos:               # grows by the nested forms of pairs whose step blew up
        a, b = library[ma.effects[0]], library[mb.effects[0]]
        if a.group is not None and a.group == b.group:
            continue
        clock = time.perf_counter()
        vals = dict(ma.parameters, **mb.parameters)
        base, weak = sorted((ma, mb), key=lambda m: m.J)    # the better member: a full re-estimate starts it
        why = []
        try:
            res = one_step(nominal, [a, b], data, vals, pinned=ma.shape + mb.shape,
                           start=base.result if base.full else None)
            J = res.J if math.isfinite(res.J) else math.inf
            par = {p: res.parameters[p] for p in vals}
            if not math.isfinite(J):
                why.append(f"the step's J is not finite ({brief(res.message)})")
        except Exception as exc:  # noqa: BLE001 - the pair is not scored, and says why
            res, J, par = None, math.inf, vals
            why.append(f"the step could not be taken ({type(exc).__name__}: {brief(str(exc))})")
        full = False
        if ((base.full or nominal.J - weak.J >= PAIR_REFIT * base.J)
                and not (J <= DIVERGED * base.J and _inside([a, b], par))):
            # the step did no better than the better member: re-estimated in full where that
            # member was (its linearisation about the nominal estimate failed) or where the
            # weaker one could add a gain that matters (PAIR_REFIT); a pair that cannot be
            # re-estimated then gives way to its nested forms (below); other pairs keep their step
            J, par, res = fully_estimated(nominal, [a, b], data, vals, [], why.append,
                                          "the step did no better than " + base.label)
            full = res is not None
        if not full and not J < nominal.J:     # blew up (a stiff model) or not re-estimated: nested forms
            for rich, other in ((ma, mb), (mb, ma)):
                for n in library[rich.effects[0]].nests:
                    if n in by_effect and frozenset((n, other.effects[0])) not in formed:
                        formed.add(frozenset((n, other.effects[0])))
                        combos.append((by_effect[n], other))
        k = ma.k + mb.k
        out.append(Candidate(effects=[a.name, b.name], k=k, J=J, parameters=par, result=res,
                             criterion=criterion(J, k, nu), shape=ma.shape + mb.shape, full=full))
        say(f"  {a.name} + {b.name}: {_outcome(J, nominal.J, why if full or not math.isfinite(J) else [])}, "
            f"{time.perf_counter() - clock:.1f} s")
    return out


def polish_leaders(nominal: EstimationResult, models: Sequence[Candidate], library: Mapping[str, Effect],
                   data: Measurements, nu: float, polish: int = 3, polish_steps: int = 3,
                   log: Callable[[str], None] | None = None) -> None:
    """Further steps for the ``polish`` leading models (in place) until J settles: the undamped step
    is exact only for a model linear in everything, so the few that compete for selection get up
    to ``polish_steps`` more (a single effect's first step can leave part of the error a pair then
    seems to explain)."""
    say = log or (lambda s: None)
    lead = sorted((m for m in models if m.effects and m.result is not None and math.isfinite(m.J)),
                  key=lambda m: m.criterion)[:max(polish, 0)]
    for m in lead:
        clock, J_before, steps = time.perf_counter(), m.J, 0
        for _ in range(polish_steps):
            try:
                res = one_step(nominal, [library[n] for n in m.effects], data, m.parameters, start=m.result)
            except Exception:  # noqa: BLE001 - keep the last step
                break
            if not (math.isfinite(res.J) and res.J < m.J and _inside([library[n] for n in m.effects], res.parameters)):
                break           # a step out of an effect's bounds is not taken (it may not integrate)
            gain = (m.J - res.J) / m.J
            m.update(res, nu)
            steps += 1
            if gain < 1e-3:
                break
        say(f"  polished {m.label}: J {J_before:.5g} -> {m.J:.5g} in {steps} more step{'s' if steps != 1 else ''}, "
            f"{time.perf_counter() - clock:.1f} s")


def outside_bounds(effects: Sequence[Effect], values: Mapping[str, float], fmt: str = ".4g") -> list[str]:
    """``p = v outside (lo, hi)`` for each of the effects' parameters in ``values`` that is not within
    its declared bounds (a NaN is not)."""
    return [f"{p} = {values[p]:{fmt}} outside ({lo:g}, {hi:g})" for e in effects
            for p, (lo, hi) in e.bounds.items() if p in values and not lo <= values[p] <= hi]


def _inside(effects: Sequence[Effect], values: Mapping[str, float]) -> bool:
    """Whether the effects' parameters in ``values`` are within their declared bounds."""
    return not outside_bounds(effects, values)


def rank(nominal: EstimationResult, effects: Sequence[Effect], data=None, *, floor_sigma: Mapping[str, float],
         n_eff: float, nu: float, J_floor: float | None = None, significant: bool = True,
         explained_min: float = 0.5, pair_gain: float = PAIR_GAIN, pairs: int = 3, shape_trials: int = 4,
         refine: int = 2, polish: int = 3, polish_steps: int = 3,
         log: Callable[[str], None] | None = None) -> dict:
    """Which (module docstring): :func:`~.screening.screen` and :func:`score` every candidate,
    :func:`score_pairs`, :func:`polish_leaders`, :func:`.selection.weigh`, :func:`.selection.select`.
    Returns the ranking of the single effects (dicts), the models (:class:`~.selection.Candidate`,
    best criterion first), the best, the selection and a plain-words verdict; candidates that are
    not identifiable next to the model's own parameters (:data:`COLLINEAR_SHARE`) are left out,
    with the reason (``not_identifiable``).  Where the residual is not ``significant`` each single
    is scored by one step from its screened start alone, without pairs or polish: nothing can be
    selected then."""
    data = Measurements.coerce(data) if data is not None else nominal.problem.data
    chans = sorted({c for e in effects for c in e.channels})
    design = regression_design(nominal, floor_sigma, n_eff, channel_reader(data, chans))
    J0 = nominal.J
    nu = max(float(nu), 2.0)
    by_name = {e.name: e for e in effects}
    none = Candidate(effects=[], k=0, J=J0, parameters={}, result=nominal, criterion=criterion(J0, 0, nu))
    # where the residual is not significant no score can change the verdict (select): the ranking is
    # then only shown, each single from its screened start by one step — no other starts, refining
    # steps, pairs or polish, and a diverged step not replaced by a full re-estimation (these would
    # take most of a clean record's time)
    if not significant:
        shape_trials, refine, pairs, polish = 1, 0, 0, 0
    scored = {e.name: score(nominal, e, design, data, nu, shape_trials, refine, log, in_full=significant)
              for e in effects}
    not_identifiable = {n: c.unidentifiable for n, c in scored.items() if c.unidentifiable}
    singles = {n: c for n, c in scored.items() if not c.unidentifiable}
    effects = [e for e in effects if e.name in singles]
    models = [none, *singles.values()]
    models += score_pairs(nominal, list(singles.values()), by_name, data, nu, pairs, log)
    polish_leaders(nominal, models, by_name, data, nu, polish, polish_steps, log)
    evidence = weigh(models, J0, J_floor, nu)
    ranking = ranking_table(effects, singles, models, none)
    best, selected, verdict = select(models, singles, ranking, J_floor, significant, explained_min, pair_gain)
    models.sort(key=lambda m: (-m.weight, m.criterion))
    return dict(ranking=ranking, models=models, selected=selected, verdict=verdict, best=best,
                not_identifiable=not_identifiable,
                selected_parameters=dict(best.parameters) if selected else {},
                explained_excess=best.explained_excess if selected else None, n=int(design.y.size), nu=nu,
                evidence=evidence,
                J_floor=J_floor, nuisance=design.nuisance, design=design)
