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
  cannot follow, a J of its own on top of the noise's.
* **How sure one surrogate is.**  J of a stiff model's estimator varies over noise draws by tens of
  percent (one noise realisation's amplification through the discretised dynamics), like a χ² of
  far fewer degrees of freedom than the rows' autocorrelation counts.  The floor is the mean over
  :data:`FLOOR_DRAWS` surrogates with independent noise, and each row's test takes the smaller of
  the autocorrelation's effective samples and the degrees of freedom its mean square shows over
  the draws (:func:`shootlab.diagnosis.where.replicate_dof`: ν = 2 mean²/var of a χ²_ν/ν).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np

from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from shootlab.estimation.model import IdentificationModel
from .estimators import giving_up
from shootlab.estimation.free_run import simulate
from shootlab.estimation.data import noise_level
from .progress import brief, fit_line
from .shrinkage import free_run_start

__all__ = ["noise_level", "surrogate_data", "noise_floor", "NoiseFloor", "FLOOR_DRAWS"]


def surrogate_data(model: IdentificationModel, data, parameters: Mapping[str, float], sigma: Mapping[str, float],
                   initial_state=None, seed: int = 0, response: Mapping[str, np.ndarray] | None = None
                   ) -> Measurements:
    """A record on which ``model`` is exactly right: its free-run response (with ``parameters``,
    from ``initial_state``) to the given channels of ``data``, plus Gaussian noise of std
    ``sigma[channel]`` on the other measured channels — and on the given channels themselves,
    so that the surrogate's input is as noisy a reading of what drove the response as the
    record's is; missing samples stay missing.  ``response``: that free run, if already made
    (the draws of a floor share one)."""
    data = Measurements.coerce(data)
    pred = simulate(model, data, parameters, initial_state) if response is None else response
    n = pred["t"].size
    if n != data.t.size:
        raise RuntimeError(f"the free-run simulation of {model.name} stopped at t = {pred['t'][-1]:.6g}")
    rng = np.random.default_rng(seed)
    chans = {}
    for ch, v in data.channels.items():
        if ch in model.measured and ch not in model.given:
            y = pred[ch] + rng.normal(0.0, float(sigma.get(ch, 0.0)), size=n)
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
    the estimates in ``draws``; the floor's J is their mean (module docstring)."""

    draws: list[EstimationResult]

    @property
    def J(self) -> float:
        return float(np.mean([r.J for r in self.draws]))


def noise_floor(nominal: EstimationResult, data: Measurements, estimator: Callable[..., EstimationResult],
                seed: int = 0, log: Callable[[str], None] | None = None, initial_state="rest",
                draws: int = FLOOR_DRAWS) -> tuple[dict[str, float], NoiseFloor | None, list[str]]:
    """The channels' noise levels, the nominal model's estimates on its surrogate records (None
    when none could be made: the diagnosis then goes on without a floor) and notes.

    ``initial_state``: where the surrogate's free run starts, by the rule of every other free run
    of the diagnosis (:attr:`shootlab.diagnosis.Library.initial_state`, :func:`.shrinkage.free_run_start`:
    ``"rest"``, ``"data"`` or a function) — not the nominal estimate's state at the record's first
    sample, which carries that sample's noise (module docstring).  ``draws``: surrogate records
    with independent noise; the first starts from the nominal estimate, each later one from the
    first converged draw (a warm start: the estimator's solution on the draw, reached in fewer
    iterations; from the data's states where it does not converge)."""
    say = log or (lambda s: None)
    nm = nominal.problem.model
    sigma = noise_level(data, [c for c in nm.measured if c not in nm.given])
    given_sigma = noise_level(data, [c for c in nm.given if c in data.channels], exact_zero=True)
    draws = max(1, int(draws))
    say(f"noise floor: {draws} surrogate record(s) (the nominal model's free run + noise " +
        ", ".join(f"{k} {v:.3g}" for k, v in dict(sigma, **given_sigma).items()) + ") ...")
    notes = []
    found: list[EstimationResult] = []
    try:
        x0 = free_run_start(nm, data, initial_state, nominal.parameters)
        response = simulate(nm, data, nominal.parameters, x0)           # the same for every draw
        for k in range(draws):
            clock = time.perf_counter()
            sur = surrogate_data(nm, data, nominal.parameters, dict(sigma, **given_sigma), x0, seed=seed + k,
                                 response=response)
            # the later draws start from the first converged one: the same model and response,
            # another noise draw (the rig: the four estimates 6.8 -> 2.8 s, J the same to 9 digits);
            # the first from the nominal estimate (the rig: 5.0 -> 3.1 s, J the same to 3e-11)
            first = next((r for r in found if r.success), nominal if nominal.success else None)
            how = "from the nominal estimate" if first is nominal else "from surrogate 1" if first else ""
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
                    res = estimator(nm, sur, initial=dict(nominal.parameters))
            say(fit_line(f"  surrogate {k + 1}/{draws}" + (f" {how}" if how else ""), res,
                         time.perf_counter() - clock))
            if not res.success:
                notes.append(f"the noise-floor estimate on surrogate {k + 1} did not converge ({res.message}); "
                             f"its residuals are used anyway")
            found.append(res)
    except Exception as exc:  # noqa: BLE001 - reported, the diagnosis goes on without a floor
        notes.append(f"no noise floor: {type(exc).__name__}: {exc}" if not found else
                     f"noise floor from {len(found)} surrogate(s) only: {type(exc).__name__}: {exc}")
    return sigma, (NoiseFloor(found) if found else None), notes
