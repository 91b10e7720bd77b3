"""Which model the records support (docs/design.md §4, step 2; ``docs/diagnosis.md``, "The weights").

Every model of the comparison — no effect, a single effect, a pair — is a :class:`Candidate`,
scored by :mod:`.which`.

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
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

from shootlab.estimation.fit import EstimationResult
from .effects import Effect
from .where import effective_samples, residual_components

__all__ = ["Candidate", "criterion", "ranking_nu", "weigh", "effective_size", "ranking_table", "select", "heaviest",
           "rivals", "LOOK_ALIKE", "LOOK_ALIKE_Z", "PAIR_GAIN"]


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
    full       the result is a converged, full re-estimation (:func:`.which.fully_estimated`; the
               leading candidates', :func:`shootlab.diagnosis.confirmation.confirm`), not a step
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
    """The ν every criterion of :func:`.which.rank`'s models is on — min(ν_floor, ν_res), :func:`weigh` —
    for a candidate re-estimated later (:meth:`Candidate.update`): criteria on different ν are not
    comparable (ν log J of a J above 1 grows with ν, of one below 1 falls).  ``default`` where
    ``which`` holds none (``which["nu"]`` is the floor's ν, not this one)."""
    return float((which.get("evidence") or {}).get("nu") or default)


def criterion(J: float, k: int, nu: float) -> float:
    """The information criterion ``ν log J + k log ν`` (ν: effective number of measured samples,
    k: the effects' parameters); inf for a J that is not finite."""
    return nu * math.log(max(J, 1e-300)) + k * math.log(nu) if math.isfinite(J) else math.inf


# -- the weights, the selection, its look-alikes ------------------------------------------------
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
