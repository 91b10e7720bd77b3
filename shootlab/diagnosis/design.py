"""An experiment that tells look-alikes apart (``docs/diagnosis.md``, "Confidence and look-alikes"),
and the free-run measures the comparison of look-alikes takes (:mod:`.lookalikes`).

Two candidate models are look-alikes when the records given cannot tell them apart
(:func:`.lookalikes.discriminate`).  :func:`propose` then looks for an input under which their
free runs part: for each input u of a small family (:func:`probes`) both models, each with its own
re-estimated parameters, are run from rest by the general free run
(:func:`shootlab.estimation.free_run.simulate`) and scored by the predicted separation

    S(u) = Σ_c Σ_k ((y_A,c(t_k) − y_B,c(t_k)) / σ_c)²

over the measured channels c (σ_c the record's noise level, :func:`shootlab.estimation.data.noise_level`):
in noise units, the amount by which the wrong model's free-run cost C_v on a record made under u
exceeds the right one's (Σ over samples of the squared difference, the noise adding alike to both).
Where the validation evidence would judge such a record by simulations restarted on windows (the
nominal model's free run drifts on it, :func:`.shrinkage.measure_of`), S is taken the same way
(:func:`restarted`): free runs that part by their drift promise a separation the evidence never sees.
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
from scipy.special import ndtr

from shootlab.estimation.data import Measurements, noise_level, write_table
from shootlab.estimation.free_run import simulate
from shootlab.estimation.model import IdentificationModel
from .composition import extend
from .effects import Library
from .shrinkage import WINDOWS, free_run_error, free_run_start, made_start, measure_of, misfit, restart_windows
from .where import effective_samples

__all__ = ["Probe", "probes", "propose", "write_input", "free_run_cost", "free_run_residuals", "validation_cost",
           "pointwise_cost", "cost_difference", "separable", "separation_z", "separation_power", "AMPLITUDES",
           "FREQUENCIES", "SAMPLES_PER_PERIOD", "OUTPUT_MARGIN", "SEPARABLE"]

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


def restarted(model: IdentificationModel, effects: Sequence, record: Measurements, parameters: Mapping[str, float],
              reference: Mapping[str, np.ndarray], windows: int = WINDOWS, burn_in: float = 0.25
              ) -> dict[str, np.ndarray] | None:
    """The measured channels of ``model`` extended with ``effects`` simulated in ``windows`` equal
    windows of ``record``, each restarted from the states of the run ``reference`` (a
    :func:`shootlab.estimation.free_run.simulate` output, ``state:<name>``) at the window's start, NaN
    over the first ``burn_in`` of each window — :func:`.shrinkage.windowed_error` on a record that
    ``reference`` made, with its start states known rather than fitted.  None where a window's run
    fails or the model has a state ``reference`` lacks."""
    if any(f"state:{x}" not in reference for x in model.states):
        return None
    ext = extend(model, list(effects), data=record) if effects else model
    chans = [c for c in model.measured if c not in model.given and c in reference]
    out = {c: np.full(record.t.size, np.nan) for c in chans}
    for i0, i1, cut, piece in restart_windows(record, windows, burn_in):
        try:
            run = simulate(ext, piece, parameters, [float(reference[f"state:{x}"][i0]) for x in model.states])
        except Exception:  # noqa: BLE001 - a run that fails is no prediction
            return None
        if run["t"].size != piece.t.size:
            return None
        for c in chans:
            out[c][i0 + cut:i1 + 1] = run[c][cut:]
    return out


def free_run_residuals(model: IdentificationModel, effects: Sequence, record: Measurements, parameters: Mapping[str, float],
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


def validation_cost(model: IdentificationModel, effects: Sequence, record: Measurements,
                    parameters: Mapping[str, float], how, sigma: Mapping[str, float] | None,
                    measured: dict | None) -> tuple[float, float]:
    """:func:`free_run_cost` by the validation evidence's measure where there is one (``measured``,
    :func:`.floor.validation_evidence`: the same measure as every other validation cost of the
    diagnosis; its noise levels), else from the library's start."""
    return free_run_cost(model, effects, record, parameters, how,
                         measured["noise"] if measured is not None else sigma, measured)


def free_run_cost(model: IdentificationModel, effects: Sequence, record: Measurements,
                  parameters: Mapping[str, float], how, sigma: Mapping[str, float] | None = None,
                  measured: dict | None = None) -> tuple[float, float]:
    """C = Σ ((free run − z)/σ)² over the measured channels of ``record`` that are not given (σ the
    record's noise level unless given; the prediction by ``measured``'s measure where given,
    :func:`free_run_residuals`) and the residual's effective samples (Σ over the channels of
    :func:`.where.effective_samples`); (inf, 0) where the free run fails."""
    res = free_run_residuals(model, effects, record, parameters, how, sigma, measured)
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


#: seconds between the progress lines of :func:`propose`
PROGRESS_EVERY = 15.0


def propose(model: IdentificationModel, library: Library, rivals: Sequence[tuple[Sequence[str], Mapping[str, float]]],
            data: Measurements, sigma: Mapping[str, float], validation: Measurements | None = None,
            effects_of: Callable[[str], object] | None = None,
            log: Callable[[str], None] | None = None, nominal: Mapping[str, float] | None = None) -> dict | None:
    """The input of the family (:func:`probes`) that best separates the free runs of the first two
    ``rivals`` — each (its effects, its parameters) — relative to the noise ``sigma`` (module
    docstring), the two kept within the records' output range.  ``effects_of``: an effect by name
    (default ``library[name]``).

    Returns a dict: ``input`` (the chosen probe's summary), ``separation`` (S in noise units),
    ``separation_identification`` (S under the identification input itself), ``between`` (the two
    models' effects), ``t`` and ``values`` (the chosen input's samples per given channel),
    ``probes`` (every probe's summary with its S, None where a run failed, and whether it stays in
    range), ``seconds``; None when no probe of the family can be run.

    ``nominal``: the nominal model's parameters.  With them S is taken by the measure the
    validation evidence would take on the record (:func:`.shrinkage.measure_of`): where the nominal
    model's free run on a record that A made drifts, by B's simulations restarted on windows from
    A's states (:func:`restarted`), not by free runs that part by their drift — which the evidence
    would not see (``measure``: ``"windows"`` or ``"free_run"``; ``window``: a window's length)."""
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
    how = made_start(library.initial_state)        # free runs under inputs: experiments made from rest

    def drifts(record: Measurements, ya: dict) -> bool:
        # the validation evidence's measure on a record that A made (shrinkage.measure_of): where the
        # nominal model's free run drifts, simulations restarted on windows judge the record
        if nominal is None or model.initial_states is None:
            return False
        made = Measurements(record.t, dict(record.channels, **{c: ya[c] for c in chans}))
        return measure_of(model, free_run_error(model, made, nominal, how)) == "windows"

    def separation(record: Measurements) -> tuple[float | None, bool, str]:
        ya, yb = _run(model, fa, record, pa, how), _run(model, fb, record, pb, how)
        if ya is None or yb is None:
            return None, False, "free_run"
        inside = all(bounds[c][0] <= float(np.min(y[c])) and float(np.max(y[c])) <= bounds[c][1]
                     for y in (ya, yb) for c in chans)
        measure = "windows" if drifts(record, ya) else "free_run"
        if measure == "windows":
            yb = restarted(model, fb, record, pb, ya)
            if yb is None:
                return None, False, measure
        S = sum(float(np.nansum(((ya[c] - yb[c]) / sigma[c]) ** 2)) for c in chans)
        return (S if math.isfinite(S) else None), inside, measure

    family = probes(model, data, validation)
    if not family or not chans:
        return None
    S_id, _, _ = separation(data)
    table, best, last_line = [], None, time.perf_counter()
    for i, p in enumerate(family, 1):
        S, inside, measure = separation(_record(model, data, p))
        table.append(dict(p.summary(), separation=S, inside=inside, measure=measure))
        if S is not None and inside and (best is None or S > best[0]):
            best = (S, p, measure)
        if time.perf_counter() - last_line > PROGRESS_EVERY and i < len(family):  # stiff free runs: seconds each
            last_line = time.perf_counter()
            say(f"  design: {i} of {len(family)} inputs run, {last_line - clock:.0f} s")
    say(f"design: {len(family)} inputs, {sum(r['separation'] is not None for r in table)} run, "
        f"{sum(r['inside'] for r in table)} within the records' range, {time.perf_counter() - clock:.1f} s")
    if best is None:
        return None
    S, p, measure = best
    return dict(input=p.summary(), separation=S, separation_identification=S_id, measure=measure,
                window=float(data.t[-1] - data.t[0]) / WINDOWS if measure == "windows" else None,
                between=[list(ea), list(eb)],
                t=data.t.copy(), values={c: np.asarray(v, dtype=float) for c, v in p.values.items()},
                probes=table, seconds=time.perf_counter() - clock)


def write_input(path: str | Path, experiment: Mapping) -> Path:
    """The proposed input as a CSV: ``t`` and the given channels (:func:`propose`'s ``t`` and
    ``values``), for the rig and then ``shootlab diagnose … --validate`` of its record."""
    chans = list(experiment["values"])
    return write_table(path, dict(t=experiment["t"], **experiment["values"]), ["t", *chans])


# -- how far two free runs S noise units apart are told apart ------------------------------------------------
#: the least separation S of two free runs (noise units) for which an input is proposed: a record
#: under it gives the right model the lower cost with probability Φ(√S/2) ≈ 0.69 (below: no input)
SEPARABLE = 1.0


def separable(experiment: dict) -> bool:
    """Whether a proposed experiment separates the two free runs by :data:`SEPARABLE` noise units."""
    S = experiment.get("separation")
    return S is not None and S >= SEPARABLE


def separation_z(S: float, se: float = 0.0) -> float:
    """S / max(2√S, se): how far two models whose free runs are S noise units apart
    (Σ((y_A − y_B)/σ)²) are told apart, in standard deviations — were either exact, ΔC would be ±S
    with spread 2√S on white noise and ``se`` where the residuals are correlated
    (:func:`.lookalikes.discriminate`, step 2); 0 where S = 0."""
    return S / max(2.0 * math.sqrt(S), se) if S > 0 else 0.0


def separation_power(S: float, se: float = 0.0) -> float:
    """Φ(:func:`separation_z`): the probability that the right one of the two has the lower cost on
    records like these — for a proposed experiment, on white noise, Φ(√S/2)."""
    return float(ndtr(separation_z(S, se)))
