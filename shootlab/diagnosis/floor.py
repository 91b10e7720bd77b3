"""The noise floor (docs/design.md §4, step 1; ``docs/diagnosis.md``, "Where"): what noise alone leaves
through this model, these weights and this estimator.

The noise level of each measured channel comes from the data alone (:func:`shootlab.estimation.data.noise_level`,
4th differences).  The *surrogate* record (:func:`surrogate_data`) is the nominal model's own
free-run response to the recorded inputs plus Gaussian noise at that level — and a noisy input
is recorded with fresh noise at its own level, as the record's input is a noisy reading of what
drove the plant (an exact input, one whose 4th differences are mostly exactly zero, as it is):
the model is exactly right on it by construction.  (The surrogate is not driven by the nominal
estimate's fitted input: that input has absorbed part of the misfit, and the floor would come out
too low.)  The same model estimated the same way on the surrogate (:func:`noise_floor`) leaves the
floor residuals that :func:`shootlab.diagnosis.where.locate` compares the nominal residuals with
(smoother residuals are coloured, so a whiteness test alone cannot tell).

Two things make the floor what noise alone leaves on a record of *any* simulator (checked on the
independent confined-compression simulator :mod:`benchmarks.independent.mixture`, 120 finite
volumes, diagnosed with the 6-element model):

* **Where the surrogate starts.**  Its free run starts where every other free run of the
  diagnosis starts (:attr:`~shootlab.diagnosis.Library.initial_state`, "rest" for the mixture;
  :func:`.shrinkage.free_run_start`), not from the nominal estimate's state at the first sample:
  that is the smoother's least certain point and carries the sample's noise, and the free run
  would open with a fast relaxation that a coarse estimator (implicit midpoint, 4 samples a step)
  cannot follow, a J of its own on top of the noise's.  A ``"fitted"`` start is taken at rest
  (:func:`.shrinkage.made_start`): fitted with the nominal parameters to a record they do not explain,
  it would carry part of the structural error into the surrogate (on the independent rig's
  Stribeck record on the load the floor's J rose from 0.97 to 5.2, above the record's 2.7).
* **How sure one surrogate is.**  J of a stiff model's estimator varies over noise draws by tens of
  percent (one noise realisation's amplification through the discretised dynamics), like a χ² of
  far fewer degrees of freedom than the rows' autocorrelation counts.  The floor is the mean over
  :data:`FLOOR_DRAWS` surrogates with independent noise, and each row's test takes the smaller of
  the autocorrelation's effective samples and the degrees of freedom its mean square shows over
  the draws (:func:`shootlab.diagnosis.where.replicate_dof`: ν = 2 mean²/var of a χ²_ν/ν).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np

from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from shootlab.estimation.model import IdentificationModel
from .estimators import giving_up
from shootlab.estimation.free_run import simulate
from shootlab.estimation.data import noise_level
from .noise import WHITE, NoiseShape, noise_shapes
from .progress import brief, fit_line
from .shrinkage import free_run_error, free_run_start, made_start, measure_of, misfit
from .where import replicate_dof

__all__ = ["noise_level", "noise_levels", "surrogate_data", "noise_floor", "NoiseFloor", "FLOOR_DRAWS",
           "validation_evidence", "left_by", "beyond_floor", "VALIDATION_RATIO"]


def noise_levels(record: Measurements, channels, shapes: Mapping[str, NoiseShape] | None = None) -> dict[str, float]:
    """Each channel's noise standard deviation: its 4th-difference level over what those read of
    the channel's noise shape (:attr:`.noise.NoiseShape.reads`; white where ``shapes`` has none)."""
    shapes = shapes or {}
    return {c: s / shapes.get(c, WHITE).reads for c, s in noise_level(record, list(channels)).items()}


def surrogate_data(model: IdentificationModel, data, parameters: Mapping[str, float], sigma: Mapping[str, float],
                   initial_state=None, seed: int = 0, response: Mapping[str, np.ndarray] | None = None,
                   shapes: Mapping[str, NoiseShape] | None = None) -> Measurements:
    """A record on which ``model`` is exactly right: its free-run response (with ``parameters``,
    from ``initial_state``) to the given channels of ``data``, plus Gaussian noise of std
    ``sigma[channel]`` on the other measured channels (coloured as ``shapes[channel]`` says, white
    where it says nothing: :mod:`.noise`) — and white noise on the given channels themselves,
    so that the surrogate's input is as noisy a reading of what drove the response as the
    record's is; missing samples stay missing.  ``response``: that free run, if already made
    (the draws of a floor share one)."""
    shapes = shapes or {}
    data = Measurements.coerce(data)
    pred = simulate(model, data, parameters, initial_state) if response is None else response
    n = pred["t"].size
    if n != data.t.size:
        raise RuntimeError(f"the free-run simulation of {model.name} stopped at t = {pred['t'][-1]:.6g}")
    rng = np.random.default_rng(seed)
    chans = {}
    for ch, v in data.channels.items():
        if ch in model.measured and ch not in model.given:
            y = pred[ch] + shapes.get(ch, WHITE).draw(rng, float(sigma.get(ch, 0.0)), n)
        elif ch in model.given:     # the response is driven by the recorded input; its record gets
            y = v + rng.normal(0.0, float(sigma.get(ch, 0.0)), size=n)  # fresh noise, as the real one has
        else:
            y = v.copy()
        y[np.isnan(v)] = np.nan
        chans[ch] = y
    return Measurements(data.t.copy(), chans)


#: surrogate records per floor (independent noise draws, seeds ``seed … seed + FLOOR_DRAWS − 1``):
#: the floor's J is their mean and the spread of each row's mean square over them gives the test's
#: degrees of freedom (:func:`shootlab.diagnosis.where.locate`; module docstring)
FLOOR_DRAWS = 4


@dataclass
class NoiseFloor:
    """The nominal model estimated on surrogate records with independent noise (:func:`noise_floor`):
    the estimates in ``draws``; the floor's J is their mean (module docstring).  ``shapes``: the
    measured channels' noise shapes the surrogates were drawn with (:func:`.noise.noise_shapes`)."""

    draws: list[EstimationResult]
    shapes: dict[str, NoiseShape] = field(default_factory=dict)

    @property
    def J(self) -> float:
        return float(np.mean([r.J for r in self.draws]))


NOMINAL = "the nominal model's"         # whose free run the floor's surrogates are, by default


def noise_floor(nominal: EstimationResult, data: Measurements, estimator: Callable[..., EstimationResult],
                seed: int = 0, log: Callable[[str], None] | None = None, initial_state="rest",
                draws: int = FLOOR_DRAWS, whose: str | None = None,
                shapes: Mapping[str, NoiseShape] | None = None
                ) -> tuple[dict[str, float], NoiseFloor | None, list[str]]:
    """The channels' noise levels, the nominal model's estimates on its surrogate records (None
    when none could be made: the diagnosis then goes on without a floor) and notes.

    ``initial_state``: where the surrogate's free run starts, by the rule of every other free run
    of the diagnosis (:attr:`shootlab.diagnosis.Library.initial_state`, :func:`.shrinkage.free_run_start`:
    ``"rest"``, ``"data"`` or a function) — not the nominal estimate's state at the record's first
    sample, which carries that sample's noise (module docstring).  ``draws``: surrogate records
    with independent noise; the first starts from the nominal estimate, each later one from the
    first converged draw (a warm start: the estimator's solution on the draw, reached in fewer
    iterations; from the data's states where it does not converge).  ``whose``: the model the progress
    lines name ("pendulum+input_offset's"; None: the nominal model).  ``shapes``: the measured
    channels' noise shapes (:mod:`.noise`); None: fitted to ``nominal``'s residual."""
    say = log or (lambda s: None)
    nm = nominal.problem.model
    if shapes is None:
        shapes = {c: s for c, s in noise_shapes(nominal, data).items() if not s.plain}
    sigma = noise_levels(data, [c for c in nm.measured if c not in nm.given], shapes)
    given_sigma = noise_level(data, [c for c in nm.given if c in data.channels], exact_zero=True)
    draws = max(1, int(draws))
    say(f"noise floor: {draws} surrogate record(s) ({whose or NOMINAL} free run + noise " +
        ", ".join(f"{k} {v:.3g}" + (f" ({shapes[k].describe()})" if k in shapes else "")
                  for k, v in dict(sigma, **given_sigma).items()) + ") ...")
    notes = []
    found: list[EstimationResult] = []
    try:
        x0 = free_run_start(nm, data, made_start(initial_state), nominal.parameters)
        response = simulate(nm, data, nominal.parameters, x0)           # the same for every draw
        for k in range(draws):
            clock = time.perf_counter()
            sur = surrogate_data(nm, data, nominal.parameters, dict(sigma, **given_sigma), x0, seed=seed + k,
                                 response=response, shapes=shapes)
            # the later draws start from the first converged one: the same model and response,
            # another noise draw (the rig: the four estimates 6.8 -> 2.8 s, J the same to 9 digits);
            # the first from the nominal estimate (the rig: 5.0 -> 3.1 s, J the same to 3e-11)
            first = next((r for r in found if r.success), nominal if nominal.success else None)
            how = (f"from {'its' if whose else 'the nominal'} estimate" if first is nominal
                   else "from surrogate 1" if first else "")
            if first is None:
                res = estimator(nm, sur, initial=dict(nominal.parameters))
            else:
                # a warm start gives up as a candidate's re-estimate does (GIVE_UP): far from the
                # surrogate's solution (a nominal estimate that misses the record by far) it can
                # wander for max_iter iterations — 100 on the README's rig record, 37 s — where the
                # estimator's own start from the data's states converges
                res = estimator(nm, sur, initial=dict(nominal.parameters), start=first, **giving_up(nm, estimator))
                if not res.success:                                # from the data's states
                    how = f"from the data's states (the warm start: {brief(res.message)})"
                    res, warm = _not_above_the_record(
                        estimator(nm, sur, initial=dict(nominal.parameters)), nominal,
                        lambda sur=sur, first=first: estimator(nm, sur, initial=dict(nominal.parameters), start=first))
                    if warm:
                        how = "warm, with the fallback strategies (from the data's states: J above the record's)"
            say(fit_line(f"  surrogate {k + 1}/{draws}" + (f" {how}" if how else ""), res,
                         time.perf_counter() - clock))
            if not res.success:
                notes.append(f"the noise-floor estimate on surrogate {k + 1} did not converge ({res.message}); "
                             f"its residuals are used anyway")
            found.append(res)
        found = _second_starts(found, nm, estimator, nominal.parameters, say, notes)
    except Exception as exc:  # noqa: BLE001 - reported, the diagnosis goes on without a floor
        notes.append(f"no noise floor: {type(exc).__name__}: {exc}" if not found else
                     f"noise floor from {len(found)} surrogate(s) only: {type(exc).__name__}: {exc}")
    return sigma, (NoiseFloor(found, shapes) if found else None), notes


def _not_above_the_record(res: EstimationResult, nominal: EstimationResult,
                          warm: Callable[[], EstimationResult]) -> tuple[EstimationResult, bool]:
    """A surrogate's estimate from the data's states, or the warm start without giving up (``warm``:
    the estimator's fallback strategies allowed) where that one fits the surrogate worse than the
    nominal estimate fits the record: a surrogate carries no structural error, so an estimate of
    it with a J above the nominal one (which carries the record's noise and its structural error)
    may sit in a local minimum; the converged estimate with the lower J is kept.  On the
    independent tanks simulator's leak records the warm start gave up (damping below 1e-4) and
    the data's states converged to J = 2.4 against the nominal 1.78; without giving up the warm
    start converges to J = 0.67 at the surrogate's own parameters.  (estimate, whether it is the
    warm one)."""
    if not nominal.success or (res.success and res.J <= nominal.J):
        return res, False
    alt = warm()
    better = alt.success and (not res.success or alt.J < res.J)
    return (alt, True) if better else (res, False)


#: a surrogate estimate whose J exceeds this multiple of the least J over the draws is re-estimated
#: from the solution of that draw (:func:`_second_starts`)
LOCAL_MINIMUM = 2.0
#: a draw whose second start fails is left out of the floor above this multiple of the least J
OUTLIER = 10.0


def _second_starts(found: list[EstimationResult], model: IdentificationModel,
                   estimator: Callable[..., EstimationResult], parameters: Mapping[str, float],
                   say: Callable[[str], None], notes: list[str]) -> list[EstimationResult]:
    """The draws with each one whose J exceeds :data:`LOCAL_MINIMUM` times the least J of the
    converged draws re-estimated warm from that draw's solution, the lower J kept — and left out
    where that second start does not converge and the draw's J exceeds :data:`OUTLIER` times the
    least (on the stiff confined model converged draws of one floor spread over 2.75 times, and a
    second start confirms them; on the real tanks' own floor of an answer, in a trial of the
    noise's colour fit, one draw stood at 47 times the least and its second start failed).

    The surrogates differ only in their noise draw: J over draws spreads like a χ² (22–30 % std /
    mean on the 6-element confined model), so a draw at twice the least J has not found the
    estimator's minimum of its record but another, local one.  Counted as noise it inflates the
    floor's mean and spread — on the independent tanks simulator's overflow record one draw out of
    four converged from the data's states to J = 67.4 against 0.58–0.59 for the three others: a
    floor J of 17.3, the spread's degrees of freedom 0.5, and the level row (J 136) judged not
    significant; from the second draw's solution the first converges to J = 0.59."""
    ok = [r for r in found if r.success and r.J > 0]
    if len(ok) < 2:
        return found
    best = min(ok, key=lambda r: r.J)
    out = []
    for k, res in enumerate(found):
        if res is best or not res.J > LOCAL_MINIMUM * best.J:
            out.append(res)
            continue
        clock = time.perf_counter()
        again = estimator(model, res.problem.data, initial=dict(parameters), start=best,
                          **giving_up(model, estimator))
        say(fit_line(f"  surrogate {k + 1} again, from surrogate {found.index(best) + 1}'s solution (J {res.J:.5g} "
                     f"is {res.J / best.J:.3g} times the least)", again, time.perf_counter() - clock))
        if again.success and again.J < res.J:
            notes.append(f"the noise-floor estimate on surrogate {k + 1} had converged to a local minimum "
                         f"(J = {res.J:.5g}); from surrogate {found.index(best) + 1}'s solution: J = {again.J:.5g}")
            res = again
        elif not again.success and res.J > OUTLIER * best.J:       # not what the noise leaves
            notes.append(f"the noise-floor estimate on surrogate {k + 1} converged to J = {res.J:.5g}, "
                         f"{res.J / best.J:.3g} times the least, and its second start did not converge: "
                         f"left out, the floor is made of the other draws")
            continue
        out.append(res)
    return out


#: the least ratio of the validation misfit's mean square to the noise floor's that is evidence of a
#: structural error (with the F test of :func:`validation_evidence`): the 4th-difference noise level
#: reads 0.85–0.95 of a coloured noise's standard deviation (the Duffing simulator's anti-aliased
#: noise), which alone makes a right model's ratio up to 1/0.85² = 1.38
VALIDATION_RATIO = 2.0


def validation_evidence(nominal: EstimationResult, floor: NoiseFloor | None, validation: Measurements,
                        initial_state="rest", seed: int = 0, alpha: float = 0.01,
                        ratio_min: float = VALIDATION_RATIO, model: IdentificationModel | None = None) -> dict:
    """Whether the nominal model's misfit on the validation record is more than the noise explains.

    The measure is the validation misfit of the free run — from the initial state fitted to the
    whole record (``"fitted_start"``, :func:`.shrinkage.misfit`; the library's start where the
    model has no initial approximation of the states), or simulations restarted on windows where
    the free run drifts (:func:`.shrinkage.measure_of`) — as the cost C_v = Σ((z − y)/σ)² over the
    measured channels, σ the validation record's own noise level (4th differences), n its samples
    (:func:`.shrinkage.standardised_cost`).  What noise alone leaves is measured like the
    identification floor: on a surrogate validation record (:func:`surrogate_data`: the nominal
    model's free run under the validation record's inputs plus noise at its levels, the inputs
    re-read with fresh noise) each floor draw's estimate (the nominal model re-estimated on a
    surrogate identification record, :func:`noise_floor`) is run the same way — so the floor holds
    the noise and the prediction error of parameters estimated from a noisy record.  (The start is
    fitted because the surrogate's truth starts where the library's rule puts it, and a free run
    from that rule is then exact on it but not on the record: on the independent tanks simulator's
    clean record, whose upper level at the start is not the lower one the rule takes for it, the
    free run from the rule missed by 6.6 times the noise against 1.2 on the floor.)  The evidence
    is significant when the mean square C_v/n exceeds the floor draws' mean by an F test at level
    ``alpha`` — degrees of freedom the floor residuals' effective samples or what the spread of
    their mean squares over the draws shows (:func:`.where.replicate_dof`), whichever is smaller,
    times the draws on the floor's side — and by at least ``ratio_min`` (:data:`VALIDATION_RATIO`).
    Without a floor the reference is the noise alone (mean square 1, the data residual's effective
    samples).

    ``model``: the nominal estimate's model as the validation record binds it (an extended model
    whose terms read a channel, :func:`.composition.extend` with ``data=validation``); default the
    estimate's own.

    Returns a dict: ``measure``, ``cost``, ``samples``, ``misfit`` (√(C_v/n): the RMS misfit in
    units of the noise), ``floor_misfit`` (the same for the floor's mean square), ``floor_costs``,
    ``ratio``, ``dof`` and ``dof_floor`` (the test's degrees of freedom), ``p_value``,
    ``significant`` (:func:`beyond_floor`), ``noise`` (σ per channel), ``relative`` (the RMS
    misfit over the channels' std, :func:`.shrinkage.free_run_error`'s ``overall``)."""
    nm = model or nominal.problem.model
    val = Measurements.coerce(validation)
    chans = [c for c in nm.measured if c not in nm.given]
    shapes = floor.shapes if floor is not None else {}
    sigma = noise_levels(val, chans, shapes)
    given_sigma = noise_level(val, [c for c in nm.given if c in val.channels], exact_zero=True)
    first = free_run_error(nm, val, nominal.parameters, initial_state, sigma=sigma)
    measure = measure_of(nm, first)
    if measure == "free_run" and nm.initial_states is not None:
        measure = "fitted_start"        # the record's state at its start is not known: fitted, as the floor's
    data = first if measure == "free_run" else misfit(nm, val, nominal.parameters, measure, sigma=sigma)
    cost, n, n_eff_data = data["cost"], data["samples"], data["effective_samples"]
    ms = cost / n if n else math.inf
    floor_costs, floor_ms, floor_neff = [], [], []
    draws = [r for r in (floor.draws if floor is not None else []) if r.success]
    if draws:
        x0 = free_run_start(nm, val, made_start(initial_state), nominal.parameters)
        truth = simulate(nm, val, nominal.parameters, x0)
        for k, r in enumerate(draws):
            sur = surrogate_data(nm, val, nominal.parameters, dict(sigma, **given_sigma), x0, seed=seed + 1000 + k,
                                 response=truth, shapes=shapes)
            m = misfit(nm, sur, r.parameters, measure, initial_state, sigma=sigma)
            if m["samples"] and math.isfinite(m["cost"]):
                floor_costs.append(m["cost"])
                floor_ms.append(m["cost"] / m["samples"])
                floor_neff.append(m["effective_samples"])
    if floor_ms:
        ref = float(np.mean(floor_ms))
        dof = min(float(np.mean(floor_neff)), replicate_dof(floor_ms))
        dof_ref = dof * len(floor_ms)
    else:                   # the noise alone: a mean square of 1 known exactly
        ref, dof, dof_ref = 1.0, max(n_eff_data, 1.0), math.inf
    out = dict(measure=measure, window=data.get("window"), cost=cost, samples=n, effective_samples=n_eff_data,
               misfit=math.sqrt(ms) if math.isfinite(ms) else math.inf, floor_misfit=math.sqrt(ref),
               floor_costs=floor_costs, dof=dof, dof_floor=dof_ref, alpha=alpha, ratio_min=ratio_min, noise=sigma,
               relative=data["overall"])
    ratio, p, significant = beyond_floor(cost, out)
    out.update(ratio=ratio, p_value=p, significant=significant,
                definition="cost: sum over the measured channels of ((prediction - record) / noise)^2; misfit: "
                           "sqrt(cost / samples), the RMS misfit in units of the noise; floor_misfit: the same for "
                           "the floor draws' estimates on surrogate validation records (the nominal model's free "
                           "run plus noise); significant: F test of the mean squares at alpha and ratio >= ratio_min")
    return out


def left_by(extended: EstimationResult, data: Measurements, validation: Measurements,
            estimator: Callable[..., EstimationResult], on_validation: IdentificationModel,
            initial_state="rest", seed: int = 0, alpha: float = 0.01,
            log: Callable[[str], None] | None = None, shapes: Mapping[str, NoiseShape] | None = None
            ) -> dict | None:
    """What an answer leaves on the validation record against its own noise floor: the extended
    model taken as the truth — its surrogate records, re-estimated by ``estimator``
    (:func:`noise_floor`) — so that the floor holds the noise and the estimation error of the
    answer's own parameters, which a record where the plant drifts amplifies (an input offset
    estimated to a few per cent).  :func:`validation_evidence` of ``extended``, run on the
    validation record as ``on_validation`` (the extended model bound to that record); None where
    no surrogate could be made.  ``log``: the floor's progress lines.  ``shapes``: the noise's shapes
    (the nominal floor's, so that both validation misfits are in the same units of the noise)."""
    _, own, _ = noise_floor(extended, data, estimator, seed=seed, log=log, initial_state=initial_state,
                            whose=f"{extended.problem.model.name}'s", shapes=shapes)
    if own is None:
        return None
    return validation_evidence(extended, own, validation, initial_state, seed=seed, alpha=alpha, model=on_validation)


def beyond_floor(cost: float, evidence: dict) -> tuple[float, float, bool]:
    """The test of :func:`validation_evidence` for a validation cost ``cost`` on the same record and
    measure (the nominal model's, or an extended model's: does it still leave more than the noise
    explains?): the ratio of its mean square to the floor's, the p value and whether it is
    significant."""
    from scipy import stats

    ms = cost / evidence["samples"] if evidence["samples"] else math.inf
    ratio = ms / evidence["floor_misfit"] ** 2 if evidence["floor_misfit"] > 0 else math.inf
    dof, dof_ref = evidence["dof"], evidence["dof_floor"]
    if not math.isfinite(ratio):
        p = 0.0
    elif math.isfinite(dof_ref):
        p = float(stats.f.sf(ratio, max(dof, 1e-6), max(dof_ref, 1e-6)))
    else:
        p = float(stats.chi2.sf(ratio * dof, dof))
    return ratio, p, bool(p < evidence["alpha"] and ratio >= evidence["ratio_min"])
