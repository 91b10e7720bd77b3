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
  the best compatible singles in pairs; :func:`polish_leaders` — further steps for the leaders.
* :func:`weigh` and :func:`select` — the posterior weight of every model m of {no effect, singles,
  pairs} from the evidence of both records, each on its own effective sample size::

      −2 log w_m = ν log J_m + k_m log ν  +  ν_v log C_v,m  + const

  ν log J_m + k_m log ν is the Bayesian information criterion of the identification record
  (:func:`criterion`; J_m the TPBVP's cost after re-estimating m, k_m its effects' parameters),
  ν_v log C_v,m the Gaussian log-likelihood of the validation record with its variance profiled
  out (C_v,m = Σ ((y − z_m)/σ)² of m's free run there, no parameter term: nothing was fitted to
  it), present only where the models carry a ``validation_cost``; a model without one is given
  a reference C_v — the selection's where it is known: its odds against the selection stay those
  of the identification record (the validation record has not been asked), else the least of the
  others.  ν = min(ν_floor, Σ_c ν_c): ν_floor the
  effective samples of the floor's residuals (:func:`.where.locate`), ν_c
  :func:`.where.effective_samples` of the leading model's residual on each measured channel c —
  a residual that is still correlated (a part of the error left unexplained) carries fewer
  independent samples than it has, and a difference in J proves correspondingly less
  (:func:`effective_size`); ν_v likewise from the validation residual of the model with the least
  C_v (its ``validation_effective_samples``).  The confidence is the posterior inclusion
  probability.  Nothing is selected when the residual is not significant, or when the best model
  explains less than ``explained_min`` of the residual's excess over the floor.
* :func:`rivals` — *look-alikes*: effects outside the selection whose models together weigh at
  least :data:`LOOK_ALIKE` of the selection's own weight; the records cannot tell them apart
  (:mod:`.design` proposes an experiment that can).

Every model of the comparison is a :class:`Candidate`; :func:`rank` runs the steps in turn.
"""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

from .composition import channel_reader
from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from .estimators import damped, one_step, one_steps
from .effects import Effect
from .progress import brief
from .screening import Design, collinearity, regression_design, screen
from .where import effective_samples, residual_components

__all__ = ["Candidate", "criterion", "ranking_nu", "score", "score_pairs", "polish_leaders", "weigh", "effective_size",
           "ranking_table", "select", "rank", "outside_bounds", "rivals", "LOOK_ALIKE"]


#: a candidate with less than this share of its term outside the nominal parameters'
#: sensitivities is not identifiable next to them (:func:`~.screening.collinearity`): re-estimating
#: the model's own parameters reproduces it (an input offset next to a constant force, an actuator
#: gain next to a free mass, damping and stiffness)
COLLINEAR_SHARE = 0.05


#: effects whose models weigh together at least this share of the selection's own weight are named
#: beside it as look-alikes (:func:`rivals`): posterior odds of 8 : 1 or less, so that a verdict
#: with look-alikes has a confidence of at most 1/(1 + 1/8) = 0.89
LOOK_ALIKE = 0.125

#: a rival is a look-alike when the selection's free-run costs are lower than its own by less than
#: this many standard errors of their difference (:func:`.design.cost_difference`): Φ(1.2816) = 0.9
LOOK_ALIKE_Z = 1.2816

#: a pair is selected over its better member only where its second effect lowers J by this share of
#: what the member leaves above the floor (:func:`select`; :func:`.lookalikes.discriminate` weighs a
#: pair set aside by output error)
PAIR_GAIN = 0.3


#: a linearised step that leaves J above this multiple of the nominal J has diverged (an effect
#: that does not help leaves J where it was); :func:`score` re-estimates that candidate in full
DIVERGED = 1.01


# -- the typed candidate record ------------------------------------------------------------------
@dataclass
class Candidate:
    """One model of the comparison: the nominal model (no effect), a single effect or a pair.

    J          what the (linearised) re-estimation with these effects leaves (inf: not evaluated)
    k          the effects' number of parameters
    parameters the effects' parameters at that re-estimate
    result     the re-estimate (:func:`shootlab.diagnosis.estimators.one_step`); the nominal estimate for
               the no-effect model; None when it could not be evaluated
    criterion  ``ν log J + k log ν`` (:func:`criterion`)
    screened   a single's parameters from the screening regression (:func:`~.screening.screen`)
    shape      the parameters held at their screened values in the first step (the ones the term
               is not linear in)
    weight     posterior weight among all candidates (BIC weights, :func:`weigh`)
    explained  1 − J/J₀;  explained_excess: (J₀ − J) / (J₀ − J_floor)
    unidentifiable  why the effect cannot be told apart from the model's own parameters
               (:func:`~.screening.collinearity`), or None
    full       the result is a converged, full re-estimation (:func:`fully_estimated`; the leading
               candidates', :func:`shootlab.diagnosis.confirmation.confirm`), not a step
    why        why J was not reached (J = ∞): the step diverged and no full re-estimation converged
               (the solver's whole message; the progress line and report.md show its first sentence)
    linearised J of the one undamped step, where a full re-estimate replaced it (None: not replaced)
    failed     why the full re-estimate of a leading candidate did not converge (J is then ∞: a
               score computed from a failed re-estimate is none), or None
    validation_cost      C_v = Σ((z − y)/σ)² of the extended model's free run on the validation record
               with its full re-estimate (:func:`shootlab.diagnosis.confirmation.validation_costs`), or None
    validation_shrink    1 − C_v / C_v of the nominal model
    validation_explained (C_v,nominal − C_v) / (C_v,nominal − C_v,floor): the share of the nominal
               model's validation misfit beyond what the noise floor explains that the candidate removes
    validation_effective_samples  the effective number of samples of its validation residual
    """

    effects: list[str]
    k: int
    J: float
    parameters: dict[str, float]
    result: EstimationResult | None
    criterion: float = math.inf
    screened: dict[str, float] = field(default_factory=dict)
    shape: list[str] = field(default_factory=list)
    weight: float = 0.0
    explained: float = 0.0
    explained_excess: float = 0.0
    unidentifiable: str | None = None
    full: bool = False
    why: str | None = None
    linearised: float | None = None
    failed: str | None = None
    validation_cost: float | None = None
    validation_shrink: float | None = None
    validation_explained: float | None = None
    validation_effective_samples: float | None = None

    @property
    def label(self) -> str:
        return " + ".join(self.effects)

    def update(self, result: EstimationResult, nu: float) -> None:
        """Take a further step's re-estimate."""
        self.J, self.result = result.J, result
        self.parameters = {p: result.parameters[p] for p in self.parameters}
        self.criterion = criterion(self.J, self.k, nu)


def ranking_nu(which: dict, default: float) -> float:
    """The ν every criterion of :func:`rank`'s models is on — min(ν_floor, ν_res), :func:`weigh` —
    for a candidate re-estimated later (:meth:`Candidate.update`): criteria on different ν are not
    comparable (ν log J of a J above 1 grows with ν, of one below 1 falls).  ``default`` where
    ``which`` holds none (``which["nu"]`` is the floor's ν, not this one)."""
    return float((which.get("evidence") or {}).get("nu") or default)


def criterion(J: float, k: int, nu: float) -> float:
    """The information criterion ``ν log J + k log ν`` (ν: effective number of measured samples,
    k: the effects' parameters); inf for a J that is not finite."""
    return nu * math.log(max(J, 1e-300)) + k * math.log(nu) if math.isfinite(J) else math.inf


# -- scoring, pairs, polish, selection -----------------------------------------------------------
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
    large delay); each pair scored by one step from the members' parameters.  Where a pair's step
    blows up (J above the nominal model's) and a member's effect nests a simpler one (Stribeck
    friction, Coulomb's), the pair is scored again with the simpler single in its place: a group
    counted once by its best member must not hide the pairs of its nested form (measured on the
    independent rig's load-side Coulomb record: every step of Stribeck friction with a delay, an
    offset or a gain ended 11 to 40 times above the nominal J, and Coulomb friction with the
    delay, which names the record's effect, was never scored).  A step merely worse than its
    better member is an overshoot, and its pair stands (on a record with Stribeck friction,
    Coulomb friction with viscous friction, formed that way, took the selection from it)."""
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
        base = min((ma, mb), key=lambda m: m.J)     # a fully re-estimated member is the better start
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
        if base.full and not (J <= DIVERGED * base.J and _inside([a, b], par)):
            # a pair built on a fully re-estimated member (its linearisation about the nominal
            # estimate failed) is re-estimated in full as well; other pairs keep their step
            J, par, res = fully_estimated(nominal, [a, b], data, vals, [], why.append)
            full = res is not None
        if not full and not J < nominal.J:     # the step blew up (a stiff model), not a mere overshoot
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


def effective_size(result: EstimationResult | None) -> float:
    """Σ over the measured channels that are not given of :func:`.where.effective_samples` of the
    residual of ``result`` (its measured samples only): how many independent samples the residual
    is worth.  White noise keeps its sample count; a residual with lag-one autocorrelation ρ (an
    AR(1)) is worth about n (1 − ρ)/(1 + ρ).  inf without a result."""
    if result is None or getattr(result, "xi", None) is None:
        return math.inf
    model = result.problem.model
    total = 0.0
    for c in residual_components(result):
        if c["kind"] == "measurement" and c["channel"] not in model.given and c["mask"].any():
            total += effective_samples(c["values"][c["mask"]])
    return total if total > 0 else math.inf


def weigh(models: Sequence[Candidate], J0: float, J_floor: float | None, nu: float | None = None,
          reference: float | None = None) -> dict:
    """Posterior weights of ``models`` (module docstring, in place) and the share of J and of its
    excess over the floor each candidate explains.

    ``nu``: the effective samples of the floor's residuals, ν_floor; with it every criterion is
    recomputed on ν = min(ν_floor, ν_res), ν_res the :func:`effective_size` of the residual of the
    model that leads by the criterion on ``nu`` (without it the candidates' criteria stand).  A
    model's ``validation_cost`` (C_v = Σ ((y − z)/σ)² of its free run on the validation record),
    where some models have one, adds ν_v log C_v, ν_v the ``validation_effective_samples`` of the
    model with the least C_v (without it the validation term is left out); a model without a
    ``validation_cost`` takes ``reference`` (the selection's C_v), or without one the least C_v of
    the others.

    Returns the effective sizes used: ``nu`` (identification), ``nu_floor``, ``nu_residual`` and
    ``nu_validation`` (None where not used)."""
    out = dict(nu=nu, nu_floor=nu, nu_residual=None, nu_validation=None)
    if nu is not None:
        ranked = [m for m in models if m.result is not None and math.isfinite(m.J)]
        lead = min(ranked, key=lambda m: (m.criterion, m.J)) if ranked else None
        nu_res = effective_size(lead.result) if lead is not None else math.inf
        nu_id = max(min(float(nu), nu_res), 2.0)
        out.update(nu=nu_id, nu_residual=nu_res if math.isfinite(nu_res) else None)
        for m in models:
            m.criterion = criterion(m.J, m.k, nu_id)
    evidence = {id(m): m.criterion for m in models}
    costs = {id(m): getattr(m, "validation_cost", None) for m in models}
    costs = {i: float(c) for i, c in costs.items() if c is not None and math.isfinite(c) and c > 0}
    if costs:
        best = min(costs.values())
        holder = next(m for m in models if costs.get(id(m)) == best)
        nu_v = getattr(holder, "validation_effective_samples", None)
        if nu_v is not None and math.isfinite(nu_v) and nu_v > 0:
            out["nu_validation"] = float(nu_v)
            for m in models:
                evidence[id(m)] += float(nu_v) * math.log(costs.get(id(m), reference or best))
    finite = [e for e in evidence.values() if math.isfinite(e)]
    cmin = min(finite) if finite else 0.0
    wsum = sum(math.exp(-0.5 * (e - cmin)) for e in finite) or 1.0
    excess = J0 - (J_floor if J_floor is not None else 0.0)
    excess = excess if excess > 0 else 1e-12 * max(J0, 1e-300)
    for m in models:
        e = evidence[id(m)]
        m.weight = math.exp(-0.5 * (e - cmin)) / wsum if math.isfinite(e) else 0.0
        m.explained = (J0 - m.J) / J0 if math.isfinite(m.J) and J0 > 0 else 0.0
        m.explained_excess = (J0 - m.J) / excess if math.isfinite(m.J) else 0.0
    return out


def rivals(models: Sequence[Candidate], selected: Sequence[str], nests: Mapping[str, Sequence[str]],
           ratio: float = LOOK_ALIKE) -> tuple[float, list[dict]]:
    """The selection's own weight and its look-alikes.

    The selection's own weight is that of the models that name every ``selected`` effect; an
    effect e outside the selection is a look-alike when the models that contain e and do not name
    the whole selection weigh together at least ``ratio`` times as much (a richer effect that nests
    a selected one counts: Stribeck friction beside a Coulomb verdict, and so does the simpler
    one).  Each look-alike: ``effect``, ``weight`` (its models' weight), ``ratio`` (that over the
    selection's weight) and ``model`` (the heaviest of its models, the :class:`Candidate` an
    experiment is designed against); heaviest first.  Effects in the same model as the whole
    selection complement it and are not look-alikes."""
    chosen = set(selected)
    own = sum(m.weight for m in models if chosen and chosen <= set(m.effects))
    out = []
    names = dict.fromkeys(e for m in models for e in m.effects if e not in chosen)
    for e in names:
        theirs = [m for m in models if e in m.effects and not chosen <= set(m.effects)]
        w = sum(m.weight for m in theirs)
        if theirs and w > 0 and w >= ratio * own:
            out.append(dict(effect=e, weight=w, ratio=w / own if own > 0 else math.inf,
                            model=max(theirs, key=lambda m: m.weight),
                            nested=any(e in nests.get(s, ()) or s in nests.get(e, ()) for s in chosen)))
    out.sort(key=lambda r: -r["weight"])
    return own, out


def ranking_table(effects: Sequence[Effect], singles: Mapping[str, Candidate], models: Sequence[Candidate],
                  none: Candidate) -> list[dict]:
    """One row per single effect, best first: its share of J, its confidence (posterior inclusion
    probability: the weights of every model containing it), ``confidence_nested`` (the weights of
    every model containing it or a richer effect that nests it — Coulomb friction within Stribeck's:
    what :attr:`.outcome.Diagnosis.confidence` adds up for a verdict that selects it) and its
    criterion relative to ``none``."""
    nests = {e.name: set(e.nests) for e in effects}
    ranking = []
    for e in effects:
        sg = singles[e.name]
        conf = sum(m.weight for m in models if e.name in m.effects)
        held = sum(m.weight for m in models if any(n == e.name or e.name in nests.get(n, ()) for n in m.effects))
        ranking.append(dict(effect=e.name, score=sg.explained, confidence=conf, confidence_nested=held,
                            explained_excess=sg.explained_excess, why=sg.why,
                            criterion=sg.criterion - none.criterion, J=sg.J, parameters=sg.parameters,
                            screened=sg.screened, equations=list(e.equations), description=e.description))
    ranking.sort(key=lambda r: (r["criterion"], -r["score"]))
    return ranking


def heaviest(models: Sequence[Candidate]) -> Candidate:
    """The model of the largest weight (:func:`weigh`), the lower criterion between equal weights."""
    return max(models, key=lambda m: (m.weight, -m.criterion))


def select(models: Sequence[Candidate], singles: Mapping[str, Candidate], ranking: Sequence[dict],
           J_floor: float | None, significant: bool, explained_min: float = 0.5,
           pair_gain: float = PAIR_GAIN) -> tuple[Candidate, list[str], str]:
    """The model of the largest weight (:func:`weigh`; a pair only if its second effect removes ``pair_gain`` of
    what the better member leaves above the floor), what is selected and the verdict in plain
    words: nothing when the residual is not significant, or when the best explains less than
    ``explained_min`` of the residual's excess over the floor."""
    best = heaviest(models)
    if len(best.effects) == 2:
        better = min((singles[n] for n in best.effects), key=lambda m: m.J)
        left = max(better.J - (J_floor or 0.0), 1e-300)
        if (better.J - best.J) < pair_gain * left:
            best = better
    if not significant:
        return best, [], "no significant structural error: the residual is at the noise floor"
    if not best.effects:
        tp = ranking[0] if ranking else None
        return best, [], ("the residual is significantly above the noise floor but no candidate explains it"
                          + (f" (best: {tp['effect']}, {100 * max(tp['explained_excess'], 0):.0f} % of the excess)"
                             if tp else ""))
    if best.explained_excess < explained_min:
        return best, [], (f"the residual is significantly above the noise floor but no candidate explains it: the "
                          f"best, {best.label}, explains only {100 * max(best.explained_excess, 0):.0f} % of its "
                          f"excess over the floor")
    return best, list(best.effects), (f"structural error explained by {best.label} "
                                      f"({100 * min(best.explained_excess, 1.0):.0f} % of the residual's excess "
                                      f"over the noise floor)")


def rank(nominal: EstimationResult, effects: Sequence[Effect], data=None, *, floor_sigma: Mapping[str, float],
         n_eff: float, nu: float, J_floor: float | None = None, significant: bool = True,
         explained_min: float = 0.5, pair_gain: float = PAIR_GAIN, pairs: int = 3, shape_trials: int = 4,
         refine: int = 2, polish: int = 3, polish_steps: int = 3,
         log: Callable[[str], None] | None = None) -> dict:
    """Which (module docstring): :func:`~.screening.screen` and :func:`score` every candidate,
    :func:`score_pairs`, :func:`polish_leaders`, :func:`weigh`, :func:`select`.  Returns the ranking of the single
    effects (dicts), the models (:class:`Candidate`, best criterion first), the best, the selection
    and a plain-words verdict; candidates that are not identifiable next to the model's own
    parameters (:data:`COLLINEAR_SHARE`) are left out, with the reason (``not_identifiable``).
    Where the residual is not ``significant`` each single is scored by one step from its screened
    start alone, without pairs or polish: nothing can be selected then."""
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

