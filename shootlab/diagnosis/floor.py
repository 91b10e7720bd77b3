"""The noise floor (DESIGN §4, step 1; ``docs/diagnosis.md``, "Where"): what noise alone leaves
through this model, these weights and this estimator.

The noise level of each measured channel comes from the data alone (:func:`shootlab.noise.noise_level`,
4th differences).  The *surrogate* record (:func:`surrogate_data`) is the nominal model's own
free-run response to the recorded inputs plus Gaussian noise at that level — and a noisy input
is recorded with fresh noise at its own level, as the record's input is a noisy reading of what
drove the plant (an exact input, one whose 4th differences are mostly exactly zero, as it is):
the model is exactly right on it by construction.  (Driving the surrogate by the nominal
estimate's fitted input instead was measured and rejected: the fitted input has absorbed part
of the misfit — a 6-element confined model on a fine-grid record: floor J 0.046 against 0.124,
the nominal's being 0.120.)  The same model estimated the same way on the surrogate
(:func:`noise_floor`) leaves the floor residuals that :func:`shootlab.diagnosis.where.locate`
compares the nominal residuals with (smoother residuals are coloured, so a whiteness test alone
cannot tell).
"""
from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

from ..data import Measurements
from ..estimation import EstimationResult, IdentificationModel, simulate
from ..noise import noise_level

__all__ = ["noise_level", "surrogate_data", "noise_floor"]


def surrogate_data(model: IdentificationModel, data, parameters: Mapping[str, float], sigma: Mapping[str, float],
                   initial_state=None, seed: int = 0) -> Measurements:
    """A record on which ``model`` is exactly right: its free-run response (with ``parameters``,
    from ``initial_state``) to the given channels of ``data``, plus Gaussian noise of std
    ``sigma[channel]`` on the other measured channels — and on the given channels themselves,
    so that the surrogate's input is as noisy a reading of what drove the response as the
    record's is; missing samples stay missing."""
    data = Measurements.coerce(data)
    pred = simulate(model, data, parameters, initial_state)
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


def noise_floor(nominal: EstimationResult, data: Measurements, estimator: Callable[..., EstimationResult],
                seed: int = 0, log: Callable[[str], None] | None = None
                ) -> tuple[dict[str, float], EstimationResult | None, list[str]]:
    """The channels' noise levels, the estimate of the nominal model on its surrogate record (None
    when it could not be made: the diagnosis then goes on without a floor) and notes."""
    say = log or (lambda s: None)
    nm = nominal.problem.model
    sigma = noise_level(data, [c for c in nm.measured if c not in nm.given])
    given_sigma = noise_level(data, [c for c in nm.given if c in data.channels], exact_zero=True)
    say("noise floor: surrogate record (the nominal model's free run + noise " +
        ", ".join(f"{k} {v:.3g}" for k, v in dict(sigma, **given_sigma).items()) + ") ...")
    notes = []
    try:
        x0 = [float(nominal.x[s][0]) for s in nm.states]
        sur = surrogate_data(nm, data, nominal.parameters, dict(sigma, **given_sigma), x0, seed=seed)
        floor = estimator(nm, sur, initial=dict(nominal.parameters))
        if not floor.success:
            notes.append(f"the noise-floor estimate did not converge ({floor.message}); its residuals are used anyway")
    except Exception as exc:  # noqa: BLE001 - reported, the diagnosis goes on without a floor
        notes.append(f"no noise floor: {type(exc).__name__}: {exc}")
        floor = None
    return sigma, floor, notes
