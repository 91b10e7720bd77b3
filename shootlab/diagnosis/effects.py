"""Candidate effects and their libraries (docs/design.md §4, step 2; ``docs/diagnosis.md``, "Adding an
effect").

An :class:`Effect` is a term added to some rows of the model side ``f + Fζ`` of a model's equations
(:func:`shootlab.diagnosis.composition.extend` builds the extended model); a :class:`Library` is the set of
candidates for a family of models and how that family is estimated.  :func:`library_for` finds the
library of a model: its own (``settings.diagnosis_library``), the installed one for its name
(entry points ``shootlab.libraries``, :mod:`shootlab.registry`) or :func:`generic_library` (an
offset per measured channel).  :func:`withheld_effects` reads the effects a family's data generator
adds to its records, by name and magnitude.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

from torch import Tensor

from .composition import Vars, probe_terms
from shootlab.estimation.fit import EstimationResult
from shootlab.estimation.model import IdentificationModel

__all__ = ["Vars", "Effect", "Library", "withheld_effects", "unphysical"]


@dataclass
class Effect:
    """A candidate unmodelled effect.

    name        stable identifier (``coulomb_m2``)
    equations   the rows of the model it enters
    parameters  its new parameters → initial value (also the value its signature is drawn with)
    term        ``term(v) -> {row: tensor}``: what it adds to the model side ``f + Fζ`` of those rows,
                written with torch on ``v`` (:class:`Vars`); it must be C¹ in the states and
                parameters and affine in the inputs ζ (checked)
    description one line for reports
    bounds      parameter → (low, high) for the fit (default unbounded)
    physical    parameter → (low, high) where the term means what its name says (a friction level
                at least 0: friction opposes the motion), or ``physical(values) -> [why]``: the ways
                an estimate (the effect's parameters by name) is not physical, for a relation
                between parameters (Stribeck's static level at least its Coulomb level).  An
                estimate that is not stays an estimate — it explains the misfit — but of another
                effect the term stands in for: the verdict says so, and its confidence is at most
                :data:`.lookalike_words.UNRESOLVED` (:func:`unphysical`)
    imitates    ``imitates(values) -> name or None``: another effect of the library whose law an
                estimate that is not physical takes the shape of (Stribeck friction whose level
                rises with speed: viscous friction on the same axis) — where that effect's model
                was compared and the records do not prefer the imitation, it is the answer
                (:func:`.lookalikes.discriminate`, step 6)
    scale       parameter → typical size (fit scaling; default |initial| or 1)
    starts      parameter → extra starting values for the fit, or ``starts(v) -> dict`` computed
                from the estimated variables (e.g. from the command's range)
    channels    measured channels the term reads through ``v.channel`` (bound at :func:`extend`)
    group       effects of the same group are alternatives and are not combined in pairs
    variable    optional ``(label, fn(v) -> tensor)`` or ``(label, fn, unit)``: the x-axis of the
                signature figure (without a unit: the model's unit of the label's first word)
    nests       names of simpler effects this one contains as a special case (Stribeck friction
                contains Coulomb friction): the richer one is kept only when a likelihood-ratio
                test on the converged re-estimates says its extra parameters are needed
    embed       ``embed(nested, parameters) -> [starts]``: this effect's parameters that reproduce
                (or come close to) the nested effect ``nested`` at its estimate ``parameters`` (by
                name) — starts for re-estimating the richer model from the simpler one's converged
                solution when it cannot be estimated from its own start (Stribeck from Coulomb)
    units       parameter → unit, in the model's units (``"N"``, ``"s"``; ``"-"`` dimensionless; no
                entry for an unknown unit): the report and the extended model's summaries show them
    nonlinear   parameter → (low, high): the parameters the extended model's response is far from
                linear in over their plausible range, although the term may be linear in them (a
                stiffness multiplying a power of a state: k3·Δ³ stiffens the very motion that
                makes Δ), so that the one undamped step from the nominal solution misjudges the
                effect; the range of magnitudes |p| to scan, log-spaced, with both signs the bounds
                allow, when the candidate is re-estimated in full
                (:func:`shootlab.diagnosis.confirmation.scan_starts`) — or ``nonlinear(v) -> {p: (low,
                high)}`` computed from the estimated variables (from the linear stiffness and the
                deflection's RMS)
    """

    name: str
    equations: Sequence[str]
    parameters: Mapping[str, float]
    term: Callable[[Vars], Mapping[str, Tensor]]
    description: str = ""
    bounds: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    physical: Mapping[str, tuple[float, float]] | Callable[[Mapping[str, float]], Sequence[str]] = \
        field(default_factory=dict)
    imitates: Callable[[Mapping[str, float]], str | None] | None = None
    scale: Mapping[str, float] = field(default_factory=dict)
    starts: Mapping[str, Sequence[float]] | Callable[[Vars], Mapping[str, Sequence[float]]] = field(default_factory=dict)
    channels: Sequence[str] = ()
    group: str | None = None
    variable: tuple[str, Callable[[Vars], Tensor]] | tuple[str, Callable[[Vars], Tensor], str | None] | None = None
    nests: Sequence[str] = ()
    embed: Callable[[str, Mapping[str, float]], Sequence[Mapping[str, float]]] | None = None
    units: Mapping[str, str] = field(default_factory=dict)
    nonlinear: Mapping[str, tuple[float, float]] | Callable[[Vars], Mapping[str, tuple[float, float]]] = \
        field(default_factory=dict)

    def __post_init__(self):
        if not self.name or not isinstance(self.name, str):
            raise ValueError("an effect needs a name")
        self.equations = list(self.equations)
        self.parameters = {str(k): float(v) for k, v in self.parameters.items()}
        if not self.parameters:
            raise ValueError(f"effect {self.name!r} has no parameters")
        if not callable(self.term):
            raise ValueError(f"effect {self.name!r}: term must be callable")
        for what in ("bounds", "units") + tuple(w for w in ("physical", "nonlinear") if not callable(getattr(self, w))):
            bad = set(getattr(self, what)) - set(self.parameters)
            if bad:
                raise ValueError(f"effect {self.name!r}: {what} for unknown parameters {sorted(bad)}")
        self.units = {str(k): str(v) for k, v in self.units.items() if v}

    def applies_to(self, model: IdentificationModel) -> str | None:
        """None if the effect fits the model, else why not."""
        missing = [r for r in self.equations if r not in model.equations]
        if missing:
            return f"rows {missing} not in the model"
        clash = [p for p in self.parameters if p in model.names or p in model.inputs]
        if clash:
            return f"parameter names {clash} already used by the model"
        try:
            probe_terms(model, [self])
        except KeyError as exc:
            return f"needs {exc.args[0] if exc.args else exc}"
        return None


def unphysical(effects: Sequence[Effect], values: Mapping[str, float], fmt: str = ".3g") -> list[str]:
    """The ways the estimate ``values`` (by name) of the effects' parameters is not physical
    (:attr:`Effect.physical`): ``p = v outside (lo, hi)`` for a parameter outside its range, or the
    effect's own words; empty where it is physical."""
    out: list[str] = []
    for e in effects:
        if callable(e.physical):
            if all(p in values for p in e.parameters):
                out += list(e.physical({p: float(values[p]) for p in e.parameters}))
        else:
            out += [f"{p} = {values[p]:{fmt}} outside ({lo:g}, {hi:g})" for p, (lo, hi) in e.physical.items()
                    if p in values and not lo <= values[p] <= hi]
    return out


@dataclass
class Library:
    """Candidate effects for a family of models, and how that family is estimated.

    estimator       ``estimator(model, data, initial=None, start=None) -> EstimationResult``:
                    the nominal estimation strategy (default:
                    :func:`shootlab.diagnosis.estimators.default_estimator`); also
                    used for the noise-floor surrogate and, with ``start``, for the extended model
    initial_state   where every free run of the diagnosis starts: ``"rest"`` (measured states from
                    the first samples, others zero), ``"fitted"`` (that start estimated: with the
                    parameters in an output-error fit, else by least squares over the record,
                    :func:`shootlab.diagnosis.shrinkage.free_run_start`), ``"data"`` (the model's
                    initial approximation) or ``fn(model, data) -> sequence`` (``fn(model, data,
                    parameters)``: also the parameters of the run, e.g. to start a level at its
                    reading less an offset)
    free_run_screen when the TPBVP's verdict is not a confirmed one and a validation record is
                    given, judge the candidates by output-error fits and the validation free run
                    (:mod:`shootlab.diagnosis.free_run_screen`): for stiff models whose TPBVP J
                    the model errors absorb (the mixture)
    """

    name: str
    effects: list[Effect]
    estimator: Callable[..., EstimationResult] | None = None
    initial_state: str | Callable = "rest"
    description: str = ""
    free_run_screen: bool = False

    def __post_init__(self):
        names = [e.name for e in self.effects]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"library {self.name!r}: duplicate effect names {dup}")

    def __getitem__(self, name: str) -> Effect:
        for e in self.effects:
            if e.name == name:
                return e
        raise KeyError(f"library {self.name!r} has no effect {name!r}; it has {self.names}")

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.effects]

    def add(self, effect: Effect) -> "Library":
        """A copy with ``effect`` added (or replacing the one of the same name)."""
        return replace(self, effects=[e for e in self.effects if e.name != effect.name] + [effect])

    def applicable(self, model: IdentificationModel) -> tuple[list[Effect], dict[str, str]]:
        ok, skipped = [], {}
        for e in self.effects:
            why = e.applies_to(model)
            if why is None:
                ok.append(e)
            else:
                skipped[e.name] = why
        return ok, skipped


def withheld_effects(effects: Mapping[str, Mapping[str, float] | float | str], defaults: Mapping[str, Mapping[str, float]],
                     magnitudes: Mapping[str, Mapping[str, float]], family: str,
                     tied: Mapping[str, Mapping[str, float]] | None = None) -> dict[str, dict[str, float]]:
    """The parameters of the effects a data generator adds to its records (name -> parameter dict).

    ``effects`` maps an effect name (a key of ``defaults``) to a dict of parameters (the missing
    ones from ``defaults[name]``), or to a magnitude name (a key of ``magnitudes[name]``: small,
    moderate, large) or a number, which sets the effect's first parameter; ``tied[name]``: the
    parameters that then follow it, as multiples of it (Stribeck friction: ``{"f_s": 3.0}``).
    ``family`` names the generator in the error for an unknown effect."""
    out = {}
    for name, spec in effects.items():
        if name not in defaults:
            raise ValueError(f"unknown {family} effect {name!r}; known: {sorted(defaults)}")
        p = dict(defaults[name])
        if isinstance(spec, (str, int, float)):
            value = magnitudes[name][spec] if isinstance(spec, str) else float(spec)
            p[next(iter(p))] = value
            p.update({k: r * value for k, r in (tied or {}).get(name, {}).items()})
        else:
            p.update(spec)
        out[name] = p
    return out
