"""An experiment that tells look-alike candidates apart (``docs/diagnosis.md``, "Look-alikes").

Two candidate models are *look-alikes* when the records given cannot tell them apart
(:func:`.which.rivals`): their posterior weights — from the identification record's TPBVP cost and,
where a validation record is given, the free run's cost there (:func:`.which.weigh`) — are within
:data:`.which.LOOK_ALIKE` of each other.  :func:`propose` then looks for an input under which their
free runs part: for each input u of a small family (:func:`probes`) both models, each with its own
re-estimated parameters, are run from rest by the general free run
(:func:`shootlab.estimation.free_run.simulate`) and scored by the predicted separation

    S(u) = Σ_c Σ_k ((y_A,c(t_k) − y_B,c(t_k)) / σ_c)²

over the measured channels c (σ_c the record's noise level, :func:`shootlab.estimation.data.noise_level`):
in noise units, the amount by which the wrong model's free-run cost C_v on a record made under u
exceeds the right one's (Σ over samples of the squared difference, the noise adding alike to both).
The input of the largest S is proposed — among those under which both free runs stay within the
range the records' measured channels visited, widened by :data:`OUTPUT_MARGIN` of it on either side
(the rig's travel, the sample's strain: an input that drives the plant off the records' range asks
for an experiment nobody ran, and lets parameter errors grow with the excursion).

The family, on the identification record's time grid, within the range [lo, hi] of the given
channel over the records given, from its first value u₀ (the plant at rest), with ``room`` = the
distance from u₀ to the nearer bound (one-sided inputs to the farther one where that is 0):

* steps: u₀ → u₀ ± a·room at t = T/10, held;
* ramps: u₀ → u₀ ± a·room over [T/10, T/2], then held;
* sines: u₀ + a·room·sin 2πft (one-sided: u₀ ± a·room (1 − cos 2πft)/2), the frequencies f
  log-spaced from one period over the record to :data:`SAMPLES_PER_PERIOD` samples per period
  (:data:`FREQUENCIES` of them): every time scale the record's length and sampling can show;
* the identification input scaled: u₀ + a (u_id − u₀);

a ∈ :data:`AMPLITUDES`.  The other given channels keep their identification trace.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from shootlab.estimation.data import Measurements, noise_level, write_table
from shootlab.estimation.free_run import simulate
from shootlab.estimation.model import IdentificationModel
from .composition import extend
from .effects import Library
from .libraries import library_for
from .shrinkage import free_run_start
from .where import effective_samples
from .which import LOOK_ALIKE, Candidate, criterion, rivals, weigh

__all__ = ["Probe", "probes", "propose", "write_input", "free_run_cost", "discriminate", "AMPLITUDES",
           "FREQUENCIES", "SAMPLES_PER_PERIOD", "OUTPUT_MARGIN", "RIVALS"]

#: the amplitudes of the family, as fractions of the room the input range leaves
AMPLITUDES = (1.0, 0.3, 0.1, 0.03)
#: the number of sine frequencies, log-spaced over the time scales the record can show
FREQUENCIES = 5
#: the fastest sine has this many samples per period
SAMPLES_PER_PERIOD = 10
#: a proposed input keeps both free runs within the measured channels' recorded range widened by
#: this share of it on either side
OUTPUT_MARGIN = 0.25


@dataclass
class Probe:
    """One input of the family: ``kind`` (step, ramp, sine, scaled), its amplitude (in the input's
    unit, signed) and frequency (sines), and the given channels' samples."""

    kind: str
    amplitude: float
    frequency: float | None
    channel: str
    values: dict[str, np.ndarray] = field(repr=False, default_factory=dict)

    @property
    def label(self) -> str:
        a = f"{self.amplitude:.3g}"
        if self.kind == "step":
            return f"a step of {a} in {self.channel}"
        if self.kind == "ramp":
            return f"a ramp of {a} in {self.channel} (then held)"
        if self.kind == "sine":
            return f"a sine of amplitude {a} at frequency {self.frequency:.3g} in {self.channel}"
        return f"the identification input of {self.channel} scaled by {self.amplitude:.3g}"

    def summary(self) -> dict:
        return dict(kind=self.kind, amplitude=self.amplitude, frequency=self.frequency, channel=self.channel,
                    label=self.label)


def probes(model: IdentificationModel, data: Measurements, validation: Measurements | None = None) -> list[Probe]:
    """The family of inputs (module docstring) on the time grid of ``data``; the varied channel is
    the first given channel of ``model`` that varies in ``data``.  [] when none does."""
    t = data.t
    given = [c for c in model.given if c in data.channels]
    span = {c: float(np.nanmax(data.channels[c]) - np.nanmin(data.channels[c])) for c in given}
    varied = next((c for c in given if span[c] > 0), None)
    if varied is None:
        return []
    u_id = data.channels[varied]
    recs = [data] + ([validation] if validation is not None and varied in validation.channels else [])
    lo = min(float(np.nanmin(r.channels[varied])) for r in recs)
    hi = max(float(np.nanmax(r.channels[varied])) for r in recs)
    u0 = float(np.clip(u_id[~np.isnan(u_id)][0], lo, hi))
    up, down = hi - u0, u0 - lo
    two_sided = min(up, down) >= 0.25 * (hi - lo)
    room = min(up, down) if two_sided else max(up, down)
    signs = (1.0, -1.0) if two_sided else ((1.0,) if up >= down else (-1.0,))
    T = float(t[-1] - t[0])
    tau = (t - t[0]) / T if T > 0 else np.zeros_like(t)
    fmax = 1.0 / (SAMPLES_PER_PERIOD * float(np.median(np.diff(t))))
    freqs = np.geomspace(1.0 / T, max(fmax, 1.0 / T), FREQUENCIES) if T > 0 else []
    others = {c: data.channels[c] for c in given if c != varied}
    out = []

    def add(kind: str, amp: float, f: float | None, u: np.ndarray) -> None:
        out.append(Probe(kind, amp, f, varied, dict(others, **{varied: np.clip(u, lo, hi)})))

    for a in AMPLITUDES:
        for sgn in signs:
            add("step", sgn * a * room, None, u0 + sgn * a * room * (tau >= 0.1))
            add("ramp", sgn * a * room, None, u0 + sgn * a * room * np.clip((tau - 0.1) / 0.4, 0.0, 1.0))
        for f in freqs:
            w = 2 * np.pi * f * (t - t[0])
            if two_sided:
                add("sine", a * room, float(f), u0 + a * room * np.sin(w))
            else:
                add("sine", signs[0] * a * room, float(f), u0 + signs[0] * a * room * 0.5 * (1 - np.cos(w)))
        if a < 1.0:
            add("scaled", a, None, u0 + a * (np.nan_to_num(u_id, nan=u0) - u0))
    return out


def _record(model: IdentificationModel, data: Measurements, probe: Probe) -> Measurements:
    """The record a probe asks for, as far as a free run needs it: the given channels of the probe
    and the measured ones held at their first values in ``data`` (where a start at rest reads them)."""
    chans = dict(probe.values)
    for c in model.measured:
        if c not in chans and c in data.channels:
            v = data.channels[c]
            head = v[~np.isnan(v)][:5]
            chans[c] = np.full(data.t.size, float(np.mean(head)) if head.size else 0.0)
    return Measurements(data.t.copy(), chans, source=probe.label)


def _run(model: IdentificationModel, effects: Sequence, record: Measurements, parameters: Mapping[str, float],
         how) -> dict | None:
    """The free run of ``model`` extended with ``effects`` on ``record`` from the library's start
    (None where it fails or does not reach the end)."""
    try:
        ext = extend(model, list(effects), data=record) if effects else model
        run = simulate(ext, record, parameters, free_run_start(ext, record, how, parameters))
    except Exception:  # noqa: BLE001 - a run that fails is no prediction
        return None
    return run if run["t"].size == record.t.size else None


def free_run_cost(model: IdentificationModel, effects: Sequence, record: Measurements,
                  parameters: Mapping[str, float], how, sigma: Mapping[str, float] | None = None
                  ) -> tuple[float, float]:
    """C = Σ ((free run − z)/σ)² over the measured channels of ``record`` that are not given (σ the
    record's noise level unless given) and the residual's effective samples (Σ over the channels of
    :func:`.where.effective_samples`); (inf, 0) where the free run fails."""
    chans = [c for c in model.measured if c not in model.given and c in record.channels]
    sigma = dict(sigma) if sigma is not None else noise_level(record, chans)
    run = _run(model, effects, record, parameters, how)
    if run is None:
        return math.inf, 0.0
    cost, n_eff = 0.0, 0.0
    for c in chans:
        r = (np.asarray(run[c]) - record.channels[c]) / max(sigma[c], 1e-300)
        r = r[np.isfinite(record.channels[c])]
        cost += float(np.sum(r * r))
        n_eff += effective_samples(r) if r.size > 3 else float(r.size)
    return (cost, n_eff) if math.isfinite(cost) else (math.inf, 0.0)


def propose(model: IdentificationModel, library: Library, rivals: Sequence[tuple[Sequence[str], Mapping[str, float]]],
            data: Measurements, sigma: Mapping[str, float], validation: Measurements | None = None,
            effects_of: Callable[[str], object] | None = None,
            log: Callable[[str], None] | None = None) -> dict | None:
    """The input of the family (:func:`probes`) that best separates the free runs of the first two
    ``rivals`` — each (its effects, its parameters) — relative to the noise ``sigma`` (module
    docstring), the two kept within the records' output range.  ``effects_of``: an effect by name
    (default ``library[name]``).

    Returns a dict: ``input`` (the chosen probe's summary), ``separation`` (S in noise units),
    ``separation_identification`` (S under the identification input itself), ``between`` (the two
    models' effects), ``t`` and ``values`` (the chosen input's samples per given channel),
    ``probes`` (every probe's summary with its S, None where a run failed, and whether it stays in
    range), ``seconds``; None when no probe of the family can be run."""
    say = log or (lambda s: None)
    clock = time.perf_counter()
    (ea, pa), (eb, pb) = rivals[0], rivals[1]
    get = effects_of or (lambda n: library[n])
    fa, fb = [get(n) for n in ea], [get(n) for n in eb]
    chans = [c for c in model.measured if c not in model.given and c in data.channels and sigma.get(c, 0) > 0]
    recs = [data] + ([validation] if validation is not None else [])
    bounds = {}
    for c in chans:
        lo = min(float(np.nanmin(r.channels[c])) for r in recs if c in r.channels)
        hi = max(float(np.nanmax(r.channels[c])) for r in recs if c in r.channels)
        bounds[c] = (lo - OUTPUT_MARGIN * (hi - lo), hi + OUTPUT_MARGIN * (hi - lo))
    how = library.initial_state

    def separation(record: Measurements) -> tuple[float | None, bool]:
        ya, yb = _run(model, fa, record, pa, how), _run(model, fb, record, pb, how)
        if ya is None or yb is None:
            return None, False
        S = sum(float(np.sum(((ya[c] - yb[c]) / sigma[c]) ** 2)) for c in chans)
        inside = all(bounds[c][0] <= float(np.min(y[c])) and float(np.max(y[c])) <= bounds[c][1]
                     for y in (ya, yb) for c in chans)
        return (S if math.isfinite(S) else None), inside

    family = probes(model, data, validation)
    if not family or not chans:
        return None
    S_id, _ = separation(data)
    table, best = [], None
    for p in family:
        S, inside = separation(_record(model, data, p))
        table.append(dict(p.summary(), separation=S, inside=inside))
        if S is not None and inside and (best is None or S > best[0]):
            best = (S, p)
    say(f"design: {len(family)} inputs, {sum(r['separation'] is not None for r in table)} run, "
        f"{sum(r['inside'] for r in table)} within the records' range, {time.perf_counter() - clock:.1f} s")
    if best is None:
        return None
    S, p = best
    return dict(input=p.summary(), separation=S, separation_identification=S_id, between=[list(ea), list(eb)],
                t=data.t.copy(), values={c: np.asarray(v, dtype=float) for c, v in p.values.items()},
                probes=table, seconds=time.perf_counter() - clock)


def write_input(path: str | Path, experiment: Mapping) -> Path:
    """The proposed input as a CSV: ``t`` and the given channels (:func:`propose`'s ``t`` and
    ``values``), for the rig and then ``shootlab diagnose … --validate`` of its record."""
    chans = list(experiment["values"])
    return write_table(path, dict(t=experiment["t"], **experiment["values"]), ["t", *chans])


# -- look-alikes in a verdict --------------------------------------------------------------------------------------
#: the look-alikes whose validation cost is measured (the heaviest first)
RIVALS = 2


def discriminate(nominal, library: Library, which: dict, selected: Sequence[str], data: Measurements,
                 validation: Measurements | None, sigma: Mapping[str, float], chosen=None,
                 free_run: dict | None = None, refit: Callable[[list[str], object], object] | None = None,
                 design: bool = True, log: Callable[[str], None] | None = None) -> dict | None:
    """Look-alikes of a settled selection, the validation record's evidence on them, and an
    experiment that would tell them apart (module docstring).

    ``nominal``: the nominal estimate; ``which``: :func:`.which.rank`'s result (its models weighed);
    ``chosen``: the converged re-estimate of the selection; ``free_run``: the free-run screen's
    result, when its verdict stands (its candidates are then weighed on their output-error costs:
    the identification record's and the validation record's, :func:`_screened`); ``refit(effects,
    candidate)``: a converged re-estimate of a look-alike that has none (or None), for its free run
    on the validation record; ``design``: propose an experiment (:func:`propose`) while look-alikes
    remain.

    With a validation record each look-alike's free-run cost there (:func:`free_run_cost`) enters
    its weight (:func:`.which.weigh`), and the selection passes to the look-alike that outweighs it
    (``switch``: its effects and re-estimate).  Returns None without a selection, else a dict:
    ``lookalikes`` (effect names), ``rivals`` (each: effect, its model's effects, weight, ratio to the
    selection's, validation cost), ``confidence`` (the selection's own weight where look-alikes
    remain, else None), ``evidence`` (the effective sizes), ``switch``, ``experiment`` (or None) and
    ``words`` (what the verdict adds)."""
    say = log or (lambda s: None)
    if not selected or not which:
        return None
    nests = {e.name: tuple(e.nests) for e in library.effects}
    model = nominal.problem.model
    how = library.initial_state
    chans = [c for c in model.measured if c not in model.given]
    sigma = {c: sigma[c] for c in chans if c in sigma} if sigma else noise_level(data, chans)
    switch = None
    effect = library.__getitem__
    screened = bool(free_run and free_run.get("selected"))
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
    own, found = rivals(models, selected, nests)
    if found and validation is not None and not screened:
        sigma_v = noise_level(validation, chans)
        for m in [mine] + [r["model"] for r in found[:RIVALS]]:
            key = frozenset(m.effects)
            if key not in params and refit is not None:
                res = refit(list(m.effects), m)
                if res is not None and res.success:
                    params[key] = dict(res.parameters)
                    m.refit = res
            if key in params and getattr(m, "validation_cost", None) is None:
                m.validation_cost, m.validation_effective_samples = free_run_cost(
                    model, [effect(n) for n in m.effects], validation, params[key], how, sigma_v)
                say(f"  {m.label}: validation free-run cost {m.validation_cost:.5g} "
                    f"({m.validation_effective_samples:.0f} effective samples)")
        evidence.update({k: v for k, v in weigh(models, nominal.J, which.get("J_floor")).items()
                         if k == "nu_validation"})
        own, found = rivals(models, selected, nests)
        best = max((r["model"] for r in found if frozenset(r["model"].effects) in params), key=lambda m: m.weight,
                   default=None)
        if best is not None and best.weight > mine.weight:
            switch = dict(effects=list(best.effects), result=getattr(best, "refit", None) or best.result,
                          replaced=list(selected), weight=best.weight)
            selected = list(best.effects)
            own, found = rivals(models, selected, nests)
    out = dict(lookalikes=[r["effect"] for r in found], confidence=own if found else None, evidence=evidence,
               rivals=[dict(effect=r["effect"], effects=list(r["model"].effects), weight=r["weight"],
                            ratio=r["ratio"], nested=r["nested"],
                            validation_cost=getattr(r["model"], "validation_cost", None)) for r in found],
               switch=switch, experiment=None, threshold=LOOK_ALIKE)
    if found and design:
        rival = found[0]["model"]
        pa = params.get(frozenset(selected))
        pb = params.get(frozenset(rival.effects))
        if pb is None and rival.result is not None:          # its linearised re-estimate
            pb = dict(rival.result.parameters)
        if pa is not None and pb is not None:
            out["experiment"] = propose(model, library, [(list(selected), pa), (list(rival.effects), pb)], data,
                                        sigma, validation, effects_of=effect, log=say)
    out["words"] = _words(out, selected)
    return out


def _criterion(J: float, k: int, nu: float) -> float:
    return criterion(J, k, max(nu, 2.0))


def _screened(model: IdentificationModel, library: Library, free_run: dict, data: Measurements):
    """The free-run screen's candidates as weighed models: the model it added them to (the nominal
    model's declared refinements walked to its name), an effect by name for that model (from its
    own library where it has one, :func:`.libraries.library_for`: an effect's terms name the rows of
    the model it was built for), a :class:`.which.Candidate` per converged candidate and one without
    an effect — ``J`` twice the output-error cost on the identification record (Σ ((y − z)/σ)²),
    ``validation_cost`` the free-run cost on the validation record (:mod:`.free_run_screen`) — and
    the fitted parameters by effects."""
    base = model
    for _ in range(4):
        if model.name == free_run.get("model"):
            break
        refine = model.settings.get("refine")
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


def _words(told: dict, selected: Sequence[str]) -> str:
    """What a verdict adds about look-alikes: a selection the validation record changed, the
    look-alikes that remain with the confidence they leave, and the proposed experiment."""
    text = ""
    sw = told.get("switch")
    if sw:
        old = next((r for r in told["rivals"] if set(r["effects"]) == set(sw["replaced"])), None)
        text += (f"; {' + '.join(selected)} rather than {' + '.join(sw['replaced'])}: alike on the identification "
                 f"record, the validation record tells them apart (weight {sw['weight']:.2f}"
                 + (f", the other's {old['weight']:.2g}" if old else "") + ")")
    if told["lookalikes"]:
        names = ", ".join(told["lookalikes"])
        ratio = max(r["ratio"] for r in told["rivals"])
        text += (f"; look-alike{'s' if len(told['lookalikes']) > 1 else ''}: {names} — the records given cannot "
                 f"tell {'them' if len(told['lookalikes']) > 1 else 'it'} from {' + '.join(selected)} (weight "
                 f"{ratio:.2g} of the selection's; confidence {told['confidence']:.2f})")
    ex = told.get("experiment")
    if ex:
        text += (f"; an experiment that can: {ex['input']['label']} separates their free runs by "
                 f"{ex['separation']:.3g} noise units (Σ((y₁ − y₂)/σ)²; the identification input: "
                 f"{_number(ex['separation_identification'])}) — `--design FILE` writes it")
    return text


def _number(v) -> str:
    return f"{v:.3g}" if v is not None and math.isfinite(v) else "–"
