"""Look-alike candidates and an experiment that tells them apart (``docs/diagnosis.md``,
"Confidence and look-alikes").

Two candidate models are *look-alikes* when the records given cannot tell them apart
(:func:`discriminate`): their posterior weights — from the identification record's TPBVP cost and,
where a validation record is given, the free run's cost there (:func:`.which.weigh`) — are within
:data:`.which.LOOK_ALIKE` of each other (:func:`.which.rivals`), or the difference of their
free-run costs on the records is within :data:`LOOK_ALIKE_Z` standard errors of its own spread
(:func:`cost_difference`).  :func:`propose` then looks for an input under which their
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
channel over the records given, from its first value u₀ (the plant at rest), with ``room`` the
distance from u₀ to the nearer bound — or, where that is less than a quarter of the range (a load
that starts at its least value), one-sided inputs towards the farther bound and ``room`` its
distance:

* steps: u₀ → u₀ ± a·room at t = T/10, held;
* ramps: u₀ → u₀ ± a·room over [T/10, T/2], then held;
* sines: u₀ + a·room·sin 2πft (one-sided: u₀ ± a·room (1 − cos 2πft)/2), the frequencies f
  log-spaced from one period over the record to :data:`SAMPLES_PER_PERIOD` samples per period
  (:data:`FREQUENCIES` of them): every time scale the record's length and sampling can show;
* the identification input scaled: u₀ + a (u_id − u₀), a < 1;

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
from .shrinkage import free_run_start, misfit
from .where import effective_samples
from .which import LOOK_ALIKE, Candidate, criterion, rivals, weigh

__all__ = ["Probe", "probes", "propose", "write_input", "free_run_cost", "pointwise_cost", "cost_difference",
           "discriminate", "unresolved_beside", "UNRESOLVED", "AMPLITUDES", "FREQUENCIES", "SAMPLES_PER_PERIOD",
           "OUTPUT_MARGIN", "RIVALS", "SCOPE", "LOOK_ALIKE_Z"]

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


def _residuals(model: IdentificationModel, effects: Sequence, record: Measurements, parameters: Mapping[str, float],
               how, sigma: Mapping[str, float] | None, measured: dict | None = None
               ) -> dict[str, np.ndarray] | None:
    """(free run − z)/σ per measured channel of ``record`` that is not given (NaN at missing samples;
    σ the record's noise level unless given); None where the free run fails.  ``measured``: the
    validation evidence (:func:`.floor.validation_evidence`), whose measure then makes the
    prediction (a fitted start: the samples after the fitted stretch only)."""
    chans = [c for c in model.measured if c not in model.given and c in record.channels]
    sigma = dict(sigma) if sigma is not None else noise_level(record, chans)
    if measured is not None:
        try:
            ext = extend(model, list(effects), data=record) if effects else model
            run = misfit(ext, record, parameters, measured["measure"], how, sigma=sigma)["prediction"]
        except Exception:  # noqa: BLE001 - a run that fails is no prediction
            return None
        if run is None:
            return None
        rows = np.searchsorted(record.t, run["t"])
    else:
        run, rows = _run(model, effects, record, parameters, how), slice(None)
        if run is None:
            return None
    out = {c: (np.asarray(run[c]) - record.channels[c][rows]) / max(sigma[c], 1e-300) for c in chans}
    return out if all(np.isfinite(r[np.isfinite(record.channels[c][rows])]).all() for c, r in out.items()) else None


def _validation_cost(model: IdentificationModel, effects: Sequence, record: Measurements,
                     parameters: Mapping[str, float], how, sigma: Mapping[str, float] | None,
                     measured: dict | None) -> tuple[float, float]:
    """The validation cost of ``model`` extended with ``effects`` and its effective samples, by the
    validation evidence's measure where there is one (``measured``: the same measure as every other
    validation cost of the diagnosis), else the free run from the library's start (:func:`free_run_cost`)."""
    if measured is None:
        return free_run_cost(model, effects, record, parameters, how, sigma)
    res = _residuals(model, effects, record, parameters, how, measured["noise"], measured)
    if res is None:
        return math.inf, 0.0
    cost, n_eff = 0.0, 0.0
    for r in res.values():
        r = r[np.isfinite(r)]
        cost += float(np.sum(r * r))
        n_eff += effective_samples(r) if r.size > 3 else float(r.size)
    return cost, n_eff


def free_run_cost(model: IdentificationModel, effects: Sequence, record: Measurements,
                  parameters: Mapping[str, float], how, sigma: Mapping[str, float] | None = None
                  ) -> tuple[float, float]:
    """C = Σ ((free run − z)/σ)² over the measured channels of ``record`` that are not given (σ the
    record's noise level unless given) and the residual's effective samples (Σ over the channels of
    :func:`.where.effective_samples`); (inf, 0) where the free run fails."""
    res = _residuals(model, effects, record, parameters, how, sigma)
    if res is None:
        return math.inf, 0.0
    cost, n_eff = 0.0, 0.0
    for r in res.values():
        r = r[np.isfinite(r)]
        cost += float(np.sum(r * r))
        n_eff += effective_samples(r) if r.size > 3 else float(r.size)
    return cost, n_eff


def pointwise_cost(residuals: Mapping[str, np.ndarray]) -> np.ndarray:
    """Σ_c r_c² at each sample (a missing sample adds 0)."""
    return sum(np.nan_to_num(r * r, nan=0.0) for r in residuals.values())


def cost_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """ΔC = Σ_k (b_k − a_k) of two models' pointwise costs on one record, and its standard error
    over the spread of the differences d_k, their autocorrelation counted: se² = n² var(d) / n_eff(d)
    (:func:`.where.effective_samples`) — what ΔC would vary by over records like this one, whichever
    model (if either) is right (Vuong's test of non-nested models, on correlated samples)."""
    d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
    n = d.size
    var = float(np.var(d))
    n_eff = effective_samples(d) if n > 3 and var > 0 else float(n)
    return float(np.sum(d)), float(n * math.sqrt(var / max(n_eff, 1.0)))


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
#: the heaviest effects outside the selection whose free runs are compared with the selection's
RIVALS = 2
#: effects outside the selection whose models weigh less than this share of the selection's are not
#: compared (their weight leaves no doubt)
SCOPE = 1e-6
#: a rival is a look-alike when the selection's free-run costs are lower than its own by less than
#: this many standard errors of their difference (:func:`cost_difference`): Φ(1.2816) = 0.9
LOOK_ALIKE_Z = 1.2816


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
       costs there (:func:`free_run_cost`) enter the weights (:func:`.which.weigh`); a rival that
       then outweighs the selection becomes the selection (``switch``: its effects and estimate).
    2. The selection and each of those rivals (weighing at least :data:`SCOPE` of it) are run freely
       on both records; ΔC, the sum over the records of the rival's cost minus the selection's,
       against its standard error (:func:`cost_difference`) gives z, and Φ(z) the probability that
       the selection's costs stay the lower over records like these — whichever model is right.
       S = Σ((y_A − y_B)/σ)², the separation of their free runs on the records, bounds what the
       records can tell: were one of the two exact, ΔC would be ±S with spread s = max(2√S, se)
       (2√S on white noise, se where the residuals are correlated), and the right one would have
       the lower cost with probability Φ(S/s) — where ΔC is far larger, what decides is a misfit
       both leave, not the difference between them.
    3. A rival is a look-alike when its models weigh at least :data:`.which.LOOK_ALIKE` of the
       selection's (:func:`.which.rivals`) or min(z, S/s) < :data:`LOOK_ALIKE_Z` (:func:`_told`);
       the confidence is the weight of the selection's models (with look-alikes: of the models
       that name it), at most Φ(min(z, S/s)) of every rival compared — below 0.9 beside a
       look-alike.

    Returns None without a selection (or one the ranking did not weigh), else a dict:
    ``lookalikes`` (effect names), ``rivals`` (each: effect, its model's effects, weight, ratio to the
    selection's weight, whether nested, validation cost, and ΔC, its standard error, z, S and
    Φ(S/s) where compared), ``confidence``, ``evidence`` (the effective sizes), ``switch``, ``experiment`` (or None)
    and ``words`` (what the verdict adds)."""
    say = log or (lambda s: None)
    if not selected or not which:
        return None
    nests = {e.name: tuple(e.nests) for e in library.effects}
    model = nominal.problem.model
    how = library.initial_state
    chans = [c for c in model.measured if c not in model.given]
    sigma = {c: sigma[c] for c in chans if c in sigma} if sigma else noise_level(data, chans)
    sigma_v = noise_level(validation, chans) if validation is not None else None
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
    if near and validation is not None and not screened:
        for m in [mine] + [r["model"] for r in near[:RIVALS]]:
            if fitted(m) is not None and getattr(m, "validation_cost", None) is None:
                m.validation_cost, m.validation_effective_samples = _validation_cost(
                    model, [effect(n) for n in m.effects], validation, params[frozenset(m.effects)], how, sigma_v,
                    measured)
                say(f"  {m.label}: validation free-run cost {m.validation_cost:.5g} "
                    f"({m.validation_effective_samples:.0f} effective samples)")
        evidence.update({k: v for k, v in weigh(models, nominal.J, which.get("J_floor"),
                                                reference=getattr(mine, "validation_cost", None)).items()
                         if k == "nu_validation"})
        own, near = rivals(models, selected, nests, ratio=SCOPE)
        # a nested rival is not switched to by the weights: between nested models the likelihood-ratio
        # test decides (reestimation.prefer_nested), and a richer form left unresolved caps the confidence
        best = max((r["model"] for r in near if frozenset(r["model"].effects) in params and not r["nested"]),
                   key=lambda m: m.weight, default=None)
        if best is not None and best.weight > mine.weight:
            old = mine
            mine, selected = best, list(best.effects)
            own, near = rivals(models, selected, nests, ratio=SCOPE)
            switch = dict(effects=list(selected), result=getattr(best, "refit", None) or best.result,
                          replaced=list(old.effects), weight=best.weight, replaced_weight=old.weight,
                          explained_excess=best.explained_excess)
    # the free runs of the selection and its heaviest rivals on both records, pointwise
    records = [(data, sigma)] + ([(validation, sigma_v)] if validation is not None else [])
    runs: dict = {}

    def residuals(m) -> list[dict] | None:
        key = frozenset(m.effects)
        if key not in runs:
            p = fitted(m)
            res = [None if p is None else _residuals(model, [effect(n) for n in m.effects], rec, p, how, sg,
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
        r["power"] = _phi(S / max(2.0 * math.sqrt(S), se) if S > 0 else 0.0)
        say(f"  {mine.label} against {r['model'].label}: free-run costs {dC:+.4g} ± {se:.3g} (z = {r['z']:.3g}), "
            f"separation of their free runs {S:.4g} noise units")
    alike = [r for r in near if r["ratio"] >= LOOK_ALIKE or _told(r) < LOOK_ALIKE_Z]
    held = sum(m.weight for m in models if all(any(e == s or s in nests.get(e, ()) for e in m.effects)
                                                   for s in selected))
    confidence = own if alike else held
    zs = [_told(r) for r in near if "z" in r]
    if zs:
        confidence = min(confidence, _phi(min(zs)))
    out = dict(lookalikes=[r["effect"] for r in alike], confidence=confidence if (alike or zs or screened) else None,
               evidence=evidence, switch=switch, experiment=None, threshold=LOOK_ALIKE, threshold_z=LOOK_ALIKE_Z,
               unresolved=[] if switch else [m.label for m in unresolved], unexplained=None,
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
        return propose(model, library, [(list(selected), pa), (list(rival.effects), pb)], data, sigma, validation,
                       effects_of=effect, log=say)
    if alike and design:
        out["experiment"] = experiment(alike[0]["model"])
    elif near:              # on request (``--design``): against the heaviest rival, look-alike or not
        out["propose"] = lambda: experiment(near[0]["model"])
    out["words"] = _words(out, selected)
    return out


def _richer_at_their_minimum(models: list, mine, selected: Sequence[str], library: Library, fitted, evidence: dict,
                             J0: float, which: dict, say: Callable[[str], None]) -> list:
    """The selection with one effect replaced by a richer one that nests it (Stribeck friction for
    Coulomb friction) has its minimum at or below the selection's J.  Where that model was not
    scored (a pair the ranking did not form: it is added to ``models``), or its score lies above
    the selection's (its own start found another minimum) or is no converged re-estimate, it is
    re-estimated (``fitted(m, again=True)``: also from the selection's solution) and, with a lower
    J, takes that estimate's score; the weights are then made again (:func:`.which.weigh`, on the
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


#: the confidence of a selection beside a richer model that contains it and could not be estimated,
#: where the selection leaves the validation misfit beyond the noise: even odds at most
UNRESOLVED = 0.5


def unresolved_beside(told: dict | None, selected: Sequence[str], left: str | None) -> None:
    """A verdict whose richer form could not be estimated (``told["unresolved"]``, :func:`discriminate`)
    while the selection leaves a validation misfit beyond what the noise explains (``left``: that
    misfit in words, None when it is at its floor): the richer models are named beside it as
    look-alikes and the confidence is at most :data:`UNRESOLVED` — the records have not weighed
    them.  In place; the words are made again."""
    if not told or not told.get("unresolved") or left is None:
        return
    told["unexplained"] = left
    told["lookalikes"] = list(dict.fromkeys(told["lookalikes"] + [e for m in told["unresolved"]
                                                                  for e in m.split(" + ") if e not in selected]))
    told["confidence"] = min(told["confidence"] if told["confidence"] is not None else 1.0, UNRESOLVED)
    told["words"] = _words(told, selected)


def _told(rival: dict) -> float:
    """How far the records tell a compared rival from the selection, in standard deviations: the
    smaller of z (the costs' difference over its spread) and S / max(2√S, se) (S the separation of
    their free runs: were either model exact, ΔC would be ±S, with spread 2√S on white noise and
    the measured standard error se of ΔC where the residuals are correlated); inf where not
    compared."""
    if "z" not in rival:
        return math.inf
    S = max(rival["separation"], 0.0)
    spread = max(2.0 * math.sqrt(S), rival.get("standard_error") or 0.0)
    return min(rival["z"], S / spread if spread > 0 else 0.0)


def _phi(z: float) -> float:
    """The standard normal distribution function."""
    return 0.5 * math.erfc(-z / math.sqrt(2.0))


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


def _words(told: dict, selected: Sequence[str]) -> str:
    """What a verdict adds about look-alikes: a selection the validation record changed, the
    look-alikes that remain with what makes them alike and the confidence they leave, and the
    proposed experiment."""
    text = ""
    sw = told.get("switch")
    if sw:
        still = any(set(r["effects"]) == set(sw["replaced"]) and r["lookalike"] for r in told["rivals"])
        text += (f"; {' + '.join(selected)} rather than {' + '.join(sw['replaced'])}, alike on the identification "
                 f"record: " + ("with the validation record its weight is " if still else
                                "the validation record tells them apart (weight ")
                 + f"{sw['weight']:.2g} against {sw['replaced_weight']:.2g}" + ("" if still else ")"))
    alike = [r for r in told["rivals"] if r["lookalike"]]
    if alike:
        why = []
        for r in alike:
            bits = [f"its models weigh {r['ratio']:.2g} of the selection's"]
            if r.get("z") is not None:
                bits.append(f"their free-run costs differ by {r['cost_difference']:+.3g} ± {r['standard_error']:.2g} "
                            f"(z = {r['z']:.2g}), their free runs by {r['separation']:.3g} noise units")
            why.append(f"{r['effect']} ({', '.join(bits)})")
        text += (f"; look-alike{'s' if len(alike) > 1 else ''}: {'; '.join(why)} — the records given cannot tell "
                 f"{'them' if len(alike) > 1 else 'it'} from {' + '.join(selected)}: confidence "
                 f"{told['confidence']:.2f}")
    compared = [r for r in told["rivals"] if not r["lookalike"] and r.get("z") is not None]
    if compared and not alike:
        r = compared[0]
        text += (f"; against the nearest rival, {r['effect']}, on the records given: free-run costs "
                 f"{r['cost_difference']:+.3g} ± {r['standard_error']:.2g} (z = {r['z']:.2g}), their free runs "
                 f"{r['separation']:.3g} noise units apart: confidence {told['confidence']:.2f}")
    if told.get("unexplained"):
        text += (f"; {' and '.join(told['unresolved'])}, which contain{'s' if len(told['unresolved']) == 1 else ''} "
                 f"{' + '.join(selected)}, could not be estimated, and {' + '.join(selected)} leaves "
                 f"{told['unexplained']}: confidence {told['confidence']:.2f}")
    ex = told.get("experiment")
    if ex:
        text += (f"; an experiment that can: {ex['input']['label']} separates their free runs by "
                 f"{ex['separation']:.3g} noise units (Σ((y₁ − y₂)/σ)²; the identification input: "
                 f"{_number(ex['separation_identification'])}) — `--design FILE` writes it")
    return text


def _number(v) -> str:
    return f"{v:.3g}" if v is not None and math.isfinite(v) else "–"
