"""The outcome of a diagnosis (docs/design.md §4; ``docs/diagnosis.md``): :class:`Diagnosis`, the record
:func:`shootlab.diagnosis.diagnose` returns, with its status and the JSON of ``diagnosis.json``
(:meth:`Diagnosis.to_dict`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from shootlab.estimation.model import IdentificationModel
from shootlab.outputs import fmt as _fmt, json_ready
from .effects import Library
from .floor import NoiseFloor
from .lookalike_words import UNRESOLVED

__all__ = ["Diagnosis", "Status", "json_ready", "fmt"]


class Status(str, Enum):
    """How a diagnosis ended: ``.meaning`` says it in words, ``.definite`` whether it is an answer
    the diagnosis stands by (``shootlab diagnose`` then exits 0, else 1).  A ``str`` whose value is
    what ``diagnosis.json`` writes (``"confirmed"``), so that ``status == "confirmed"`` holds."""

    CONFIRMED = "confirmed"
    SELECTED = "selected"
    NO_STRUCTURAL_ERROR = "no_structural_error"
    UNEXPLAINED = "unexplained"
    NUMERICAL = "numerical"
    NOT_CONFIRMED = "not_confirmed"
    INCONCLUSIVE = "inconclusive"

    @property
    def meaning(self) -> str:
        return _MEANING[self]

    @property
    def definite(self) -> bool:
        """Whether the command exits 0 with this status: every status but ``not_confirmed`` and
        ``inconclusive``."""
        return self not in (Status.NOT_CONFIRMED, Status.INCONCLUSIVE)

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


_MEANING = {
    Status.CONFIRMED: "the selected effects explain the misfit and shrink it on the validation record",
    Status.SELECTED: "the selected effects explain the identification record's misfit (no validation record to "
                     "confirm them)",
    Status.NO_STRUCTURAL_ERROR: "the identification residual is at its noise floor and the validation free run "
                                "within what the noise explains",
    Status.UNEXPLAINED: "the misfit is significant on the identification or the validation record, and no "
                        "candidate explains it",
    Status.NUMERICAL: "the misfit is the model's own numerics: more shooting points or its declared refinement "
                      "bring it to the floor",
    Status.NOT_CONFIRMED: "the candidates explain the identification record, but none shrinks the validation misfit",
    Status.INCONCLUSIVE: "an estimate the verdict needs did not converge",
}


@dataclass
class Diagnosis:
    """Outcome of :func:`shootlab.diagnosis.diagnose` (``to_dict()`` is the JSON of ``diagnosis.json``)."""

    model: IdentificationModel
    library: Library
    data: Measurements
    validation: Measurements | None
    nominal: EstimationResult
    floor: NoiseFloor | None
    noise: dict[str, float]
    where: list[dict]
    significant: bool
    which: dict
    selected: list[str]
    verdict: str
    extended: EstimationResult | None
    shrink: dict | None
    skipped: dict[str, str]
    seconds: dict[str, float]
    notes: list[str] = field(default_factory=list)
    #: how it ended (:class:`Status`; a string value is taken as its member)
    status: Status = Status.SELECTED
    #: the numerical checks (:func:`shootlab.diagnosis.numerics.numerical_check`), None when not run
    numerical: dict | None = None
    #: the free-run screen (:func:`shootlab.diagnosis.free_run_screen.screen`), None when not run
    free_run: dict | None = None
    #: the validation record's evidence (:func:`shootlab.diagnosis.shrinkage.validation_evidence`), None
    #: without a validation record
    evidence: dict | None = None
    #: effects the records given cannot tell from the selection (:func:`shootlab.diagnosis.selection.rivals`)
    lookalikes: list[str] = field(default_factory=list)
    #: the look-alikes' weights, the validation evidence on them and the proposed experiment
    #: (:func:`shootlab.diagnosis.lookalikes.discriminate`), None when not run
    discrimination: dict | None = None
    #: the ways the selection's estimate is not physical (:func:`.effects.unphysical`: ``"p = v outside
    #: (lo, hi)"`` or the effect's words): the selection stands in for an effect outside the library
    unphysical: list[str] = field(default_factory=list)

    def __post_init__(self):
        self.status = Status(self.status)

    @property
    def success(self) -> bool:
        """False when the diagnosis could not reach a verdict it can stand by (:attr:`Status.definite`):
        the command line then exits non-zero."""
        return self.status.definite

    @property
    def confidence(self) -> float | None:
        """The verdict's confidence, None without a selection: beside look-alikes the weight of the
        models that name the whole selection (:func:`shootlab.diagnosis.selection.rivals`); the free-run
        screen's weight when it decided, else the posterior weight of the models that contain every selected effect —
        itself or a richer effect that nests it (a Coulomb verdict preferred by the nested test
        gets Stribeck's weight too: Stribeck friction is Coulomb friction and more).  At most
        :data:`.lookalike_words.UNRESOLVED` where the answer leaves the validation misfit beyond its own
        noise floor (``evidence["selection"]["left"]``: an effect outside the library remains) or its
        estimate is not physical (:attr:`unphysical`)."""
        if not self.selected:
            return None
        left = ((self.evidence or {}).get("selection") or {}).get("left")
        cap = UNRESOLVED if left or self.unphysical else 1.0
        if self.discrimination and self.discrimination.get("confidence") is not None:
            return min(float(self.discrimination["confidence"]), cap)   # the selection's own weight beside look-alikes
        if self.free_run and self.free_run.get("selected"):
            c = self.free_run.get("confidence")
            return None if c is None else min(float(c), cap)

        def holds(effect: str, model) -> bool:
            return any(e == effect or effect in self.library[e].nests for e in model.effects)
        return min(float(sum(m.weight for m in self.which.get("models", []) if all(holds(e, m) for e in self.selected))),
                   cap)

    def selected_parameters(self) -> dict[str, float]:
        """The answer's own parameters (its effects') from its estimate: the TPBVP's, or the
        output-error fit's for an answer estimated by output error — not the ranking's, whose
        selection a look-alike weighing may have replaced."""
        if not self.selected:
            return {}
        names = [p for e in self.selected if e in self.library.names for p in self.library[e].parameters]
        fit = (self.extended.parameters if self.extended is not None
               else ((self.free_run or {}).get("extended") or {}).get("parameters") or {})
        if names and all(p in fit for p in names):
            return {p: float(fit[p]) for p in names}
        return dict(self.which.get("selected_parameters", {}))

    def to_dict(self) -> dict:
        def est(r: EstimationResult | None, effects=None):
            if r is None:
                return None
            out = dict(model=r.problem.model.name, parameters=dict(r.parameters), J=r.J, success=bool(r.success),
                       iterations=int(r.iterations), points=int(r.points), message=r.message)
            if effects is not None:
                out["effects"] = list(effects)
            return out
        ranking = [{k: v for k, v in r.items()} for r in self.which.get("ranking", [])]
        models = [dict(effects=m.effects, criterion=m.criterion, weight=m.weight, explained=m.explained,
                       parameters=m.parameters) for m in self.which.get("models", [])[:20]]
        sh = None
        if self.shrink is not None:
            sh = {k: ({kk: vv for kk, vv in v.items() if kk != "predictions"} if v is not None else None)
                  for k, v in self.shrink.items()}
        return json_ready(dict(
            model=self.model.name, library=self.library.name, verdict=self.verdict, status=self.status.value,
            confidence=self.confidence, significant=self.significant, nominal=est(self.nominal),
            extended=(est(self.extended, self.selected) if self.extended is not None
                      else (self.free_run or {}).get("extended") or (
                          est(self.nominal, []) if self.status is not Status.INCONCLUSIVE else None)),
            noise=self.noise, floor=floor_summary(est, self.floor), where=self.where, ranking=ranking, models=models,
            selected=self.selected, selected_parameters=self.selected_parameters(),
            regression=dict(samples=self.which.get("n"), effective_samples=self.which.get("n_eff"),
                            nuisance_parameters=self.which.get("nuisance")),
            shrink=sh, numerical=self.numerical, free_run=_free_run_summary(self.free_run), evidence=self.evidence,
            effective_sizes=self.which.get("evidence"), lookalikes=self.lookalikes, unphysical=self.unphysical,
            discrimination=_discrimination_summary(self.discrimination),
            skipped_effects=self.skipped, seconds=self.seconds,
            units=dict(self.model.units, **{p: u for e in self.library.effects for p, u in (e.units or {}).items()}),
            notes=self.notes))


def _free_run_summary(fr: dict | None) -> dict | None:
    """The free-run screen without its validation predictions (kept in ``shrink``)."""
    if fr is None:
        return None
    out = {k: v for k, v in fr.items() if k not in ("shrink", "order")}
    if fr.get("shrink"):
        out["validation_shrink"] = fr["shrink"]["validation"].get("shrink")
    return out


def _discrimination_summary(d: dict | None) -> dict | None:
    """The look-alike analysis without the experiment's samples (``--design FILE`` writes them) or
    the switched selection's estimate (under ``extended``)."""
    if d is None:
        return None
    out = {k: v for k, v in d.items() if k not in ("experiment", "switch", "propose")}
    if d.get("switch"):
        out["switch"] = {k: v for k, v in d["switch"].items() if k not in ("result", "free_run")}
    ex = d.get("experiment")
    out["experiment"] = None if ex is None else {k: v for k, v in ex.items() if k not in ("t", "values")}
    return out


def fmt(v, spec: str = ".3g") -> str:
    """A number of the report as text ('–' for None and non-finite values)."""
    return _fmt(v, spec, missing="–")


def floor_summary(est, floor: NoiseFloor | None) -> dict | None:
    """The floor's summary: its first surrogate estimate's (``est``), J the mean over the surrogate
    records, each record's J in ``J_draws`` and the noise shapes of the channels whose noise is not
    white Gaussian in ``noise_shapes`` (white share, AR(1) pole, tails, what the 4th differences read
    of it)."""
    if floor is None:
        return None
    out = est(floor.draws[0])
    if out is not None:
        out.update(J=floor.J, J_draws=[r.J for r in floor.draws],
                   noise_shapes={c: dict(white=s.white, pole=s.phi, tails=s.tails, reads=s.reads)
                                 for c, s in floor.shapes.items()})
    return out
