"""Noise level of a measured record from the data alone (no model).

The spread of the 4th differences: a smooth signal sampled densely has tiny 4th differences,
white noise of standard deviation σ gives 4th differences of standard deviation √70 σ
(Σ binom(4, k)² = 70).  Used for the diagnosis's noise floor (:mod:`shootlab.diagnosis.floor`),
the parameter covariance (:mod:`shootlab.uncertainty`) and the noise-capped measurement weights of
:func:`shootlab.estimators.weight_continuation_estimator`.

It reads the noise at the top of the band, above the model's dynamics: coloured noise is read low
(80 % white + 20 % AR(1) with a correlation time of 4 samples: Var Δ⁴ = (0.8 + 0.2 · 9.9/70) of the
white value, 0.91 σ; measured 0.87–0.96 σ on the independent mixture records).  For the noise
floor that is the level that matters — the residual of a stiff model's estimate is made of that
band (:mod:`shootlab.diagnosis.floor`, where the floor's mean matched the simulator's own noise
to 1 %).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .data import Measurements

__all__ = ["noise_level"]


def noise_level(data, channels: Sequence[str] | None = None, exact_zero: bool = False) -> dict[str, float]:
    """Noise standard deviation per channel from the data alone: the spread of the 4th differences
    (robust: median absolute deviation; a smooth signal sampled densely has tiny 4th differences,
    white noise of std σ gives std √70 σ).  At least 1e-6 of the channel's std — or, with
    ``exact_zero``, 0 for a channel whose 4th differences are mostly exactly zero (a piecewise
    linear input recorded exactly: its few kinks are not noise)."""
    data = Measurements.coerce(data)
    out = {}
    for ch in channels if channels is not None else list(data.channels):
        y = data.channels[ch]
        y = y[~np.isnan(y)]
        if y.size < 8:
            out[ch] = 0.0
            continue
        d = np.diff(y, n=4)
        mad = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(70.0)
        rms = float(np.sqrt(np.mean(d * d)) / math.sqrt(70.0))
        if exact_zero and mad == 0:
            out[ch] = 0.0
            continue
        s = mad if mad > 0 else rms
        out[ch] = max(s, 1e-6 * float(np.std(y)))
    return out
