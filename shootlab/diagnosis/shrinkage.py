"""How far the misfit shrinks (DESIGN §4, step 3; ``docs/diagnosis.md``, "How far it shrinks").

The model extended with the selected effects (:func:`shootlab.composition.extend`) is re-estimated
warm-started from the nominal estimate, and the weighted residual J, the per-row residual energies
and — on validation data with another input — the free-run simulation error of the measured
channels (:func:`free_run_error`) are reported before and after, with ``shrink = 1 − after/before``.
"""
from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np

from ..composition import Term, extend
from ..data import Measurements
from ..estimation import EstimationResult, IdentificationModel, simulate
from ..noise import noise_level
from .where import row_energy

__all__ = ["shrink", "free_run_error", "free_run_start", "shrink_ratio", "validation_summary"]


def free_run_start(model: IdentificationModel, data: Measurements, how) -> list[float] | None:
    """The initial state of a free run on ``data`` (:attr:`shootlab.diagnosis.Library.initial_state`):
    ``"rest"`` measured states from the first samples, others zero; ``"data"`` None (the model's own
    initial approximation); or ``how(model, data)``."""
    if callable(how):
        return [float(v) for v in how(model, data)]
    if how == "data":
        return None
    if how != "rest":
        raise ValueError(f"initial_state must be 'rest', 'data' or a function, got {how!r}")
    out = []
    for s in model.states:
        if s in data.channels:
            v = data.channels[s][:5]
            v = v[~np.isnan(v)]
            out.append(float(np.mean(v)) if v.size else 0.0)
        else:
            out.append(0.0)
    return out



def free_run_error(model: IdentificationModel, data: Measurements, parameters: Mapping[str, float],
                   initial_state="rest", sigma: Mapping[str, float] | None = None) -> dict:
    """Free-run simulation of the measured (non-given) channels on ``data``: RMS error per channel,
    relative to the channel's standard deviation, and overall (quadratic mean of the relative
    errors); infinite when the simulation does not reach the end of the record.  With ``sigma``
    (the channels' noise levels) also the error *above the noise*, √max(MSE − σ², 0): what the
    model gets wrong, without the measurement noise no model can predict."""
    chans = [c for c in model.measured if c not in model.given]
    x0 = free_run_start(model, data, initial_state)
    try:
        pred = simulate(model, data, parameters, x0)
        ok = pred["t"].size == data.t.size
    except Exception as exc:  # noqa: BLE001 - a diverging model is a result, not a crash
        pred, ok = {"t": data.t[:0], "error": f"{type(exc).__name__}: {exc}"}, False
    per, rel, rel_n = {}, [], []
    for ch in chans:
        y = data.channels[ch]
        if ok and np.all(np.isfinite(pred[ch])):
            m = ~np.isnan(y)
            e = pred[ch][m] - y[m]
            mse = float(np.mean(e * e))
        else:
            mse = math.inf
        sd = float(np.nanstd(y)) or 1.0
        rms = math.sqrt(mse)
        per[ch] = dict(rms=rms, relative=rms / sd)
        rel.append(rms / sd)
        if sigma is not None:
            above = math.sqrt(max(mse - float(sigma.get(ch, 0.0)) ** 2, 0.0)) if math.isfinite(mse) else math.inf
            per[ch]["above_noise"] = above
            rel_n.append(above / sd)
    overall = float(np.sqrt(np.mean(np.square(rel)))) if rel else math.nan
    out = dict(per_channel=per, overall=overall, prediction=pred if ok else None, complete=ok)
    if sigma is not None:
        out["overall_above_noise"] = float(np.sqrt(np.mean(np.square(rel_n)))) if rel_n else math.nan
    return out


def shrink_ratio(before: float, after: float) -> float | None:
    """1 − after/before (None without a finite ``before``; −inf when ``after`` is not finite)."""
    if before is None or after is None or not math.isfinite(before):
        return None
    if before <= 0:
        return 0.0
    return 1.0 - after / before if math.isfinite(after) else -math.inf


def shrink(nominal: EstimationResult, extended: EstimationResult, validation=None, initial_state="rest",
           nominal_model: IdentificationModel | None = None, effects: Sequence[Term] = ()) -> dict:
    """How far it shrinks (module docstring): J and the rows' residual energies before/after on the
    identification record, and the free-run misfit before/after on ``validation`` (if given)."""
    nm = nominal_model or nominal.problem.model
    e0, e1 = row_energy(nominal), row_energy(extended)
    ident = dict(before=nominal.J, after=extended.J, shrink=shrink_ratio(nominal.J, extended.J),
                 per_channel={r: dict(before=e0[r], after=e1.get(r), shrink=shrink_ratio(e0[r], e1.get(r))) for r in e0})
    out = dict(identification=ident)
    if validation is not None:
        val = Measurements.coerce(validation)
        ext_model = extend(nm, effects, data=val) if effects else nm
        out["validation"] = validation_summary(nm, ext_model, val, nominal.parameters, extended.parameters,
                                                initial_state)
    return out


def validation_summary(before_model: IdentificationModel, after_model: IdentificationModel | None,
                       val: Measurements, before_params: Mapping[str, float],
                       after_params: Mapping[str, float] | None, initial_state) -> dict:
    """The free-run misfit on the validation record before/after (``after_model`` None: the
    nominal model alone), per channel and overall, also above the record's noise."""
    chans = [c for c in before_model.measured if c not in before_model.given]
    sigma = noise_level(val, chans)
    b = free_run_error(before_model, val, before_params, initial_state, sigma)
    a = free_run_error(after_model, val, after_params, initial_state, sigma) if after_model is not None else b
    per = {}
    for ch in b["per_channel"]:
        B, A = b["per_channel"][ch], a["per_channel"][ch]
        per[ch] = dict(before=B["rms"], after=A["rms"], shrink=shrink_ratio(B["rms"], A["rms"]),
                       before_above_noise=B["above_noise"], after_above_noise=A["above_noise"],
                       shrink_above_noise=shrink_ratio(B["above_noise"], A["above_noise"]))
    return dict(before=b["overall"], after=a["overall"], shrink=shrink_ratio(b["overall"], a["overall"]),
                before_above_noise=b["overall_above_noise"], after_above_noise=a["overall_above_noise"],
                shrink_above_noise=shrink_ratio(b["overall_above_noise"], a["overall_above_noise"]),
                per_channel=per, noise=sigma,
                measure="free-run RMS error per channel; overall: quadratic mean over the channels of RMS error / "
                        "channel std; *_above_noise: sqrt(max(MSE - noise^2, 0)), the noise estimated from the "
                        "validation record",
                predictions=dict(before=b["prediction"], after=a["prediction"] if after_model is not None else None))
