"""The measurement noise's colour (``docs/diagnosis.md``, "Coloured noise").

The noise level of a channel is read from the record's 4th differences
(:func:`shootlab.estimation.data.noise_level`): the top of the band, above the model's dynamics.
Coloured noise holds more of its variance lower down, where the structural errors are, and the 4th
differences read it low — an AR(1) process of pole 0.3 at 0.77 of its standard deviation, of pole 0.7
at 0.45.  Surrogate records drawn white at that level then give a noise floor that a right model's
residual exceeds (a clean pendulum record with AR(1) noise of pole 0.3: J 1.6 times the floor,
"significant").

The noise is modelled per measured channel as white plus AR(1) (:class:`NoiseShape`: the white
share of the variance and the pole per sample), fitted to the nominal estimate's residual where the
record holds noise alone (:func:`fit_shape`):

* above 1/8 of the sampling rate — lower down the estimator follows part of the noise, and the
  misfits a model leaves are there (from 1/16 the real cascaded tanks' misfit read as colour);
* where the record's power is at most twice the residual's — where the signal is, structural
  errors are;
* on the median of the Welch spectra over the record's segments — a structural error confined to
  part of the record (an overflow's episodes) moves only some of them.

The fit is a Whittle likelihood over a grid of shapes, and of the shapes that fit alike the least
coloured is taken.  Below the fitted band the shape is extrapolated — the model's assumption,
stated: a coloured noise that rises faster toward zero frequency than an AR(1) reads as a
structural error.

A shape is kept only where it matters (:data:`COLOUR_READS`): where the 4th differences would read
less than 0.85 of the noise's standard deviation.  Above that, colour alone makes a right model's
mean-square ratio at most 1/0.85² = 1.38, inside the tests' size thresholds (``ratio_min`` 1.5,
:data:`.floor.VALIDATION_RATIO` 2), and the noise is drawn white as before.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter, welch

from .where import residual_components

__all__ = ["NoiseShape", "WHITE", "COLOUR_READS", "fit_shape", "noise_shapes"]

_FOURTH = np.array([1.0, -4.0, 6.0, -4.0, 1.0])     # the 4th difference's weights; Σ w² = 70


@dataclass(frozen=True)
class NoiseShape:
    """White noise plus an AR(1) process, variance shares ``white`` and 1 − ``white``; ``phi`` the AR
    pole per sample.  Autocorrelation ρ(k) = white·δ_k0 + (1 − white)·φ^|k|."""

    phi: float = 0.0
    white: float = 1.0

    @property
    def coloured(self) -> bool:
        return self.white < 1.0 and self.phi > 0.0

    @property
    def reads(self) -> float:
        """What the 4th differences read of the noise's standard deviation: √(Σ w_i w_j ρ(i − j) / 70)."""
        k = np.abs(np.subtract.outer(np.arange(5), np.arange(5)))
        rho = (1.0 - self.white) * self.phi ** k + self.white * (k == 0)
        return math.sqrt(float(_FOURTH @ rho @ _FOURTH) / 70.0)

    def spectrum(self, f: np.ndarray) -> np.ndarray:
        """The spectral density at ``f`` cycles per sample, relative: 1 everywhere for white noise."""
        phi = self.phi
        ar = (1.0 - phi * phi) / (1.0 + phi * phi - 2.0 * phi * np.cos(2.0 * np.pi * np.asarray(f)))
        return self.white + (1.0 - self.white) * ar

    def draw(self, rng: np.random.Generator, sigma: float, n: int) -> np.ndarray:
        """``n`` samples of standard deviation ``sigma``; white noise is one call of ``rng.normal``."""
        if not self.coloured:
            return rng.normal(0.0, sigma, size=n)
        white = rng.normal(0.0, 1.0, size=n)
        innovations = rng.normal(0.0, math.sqrt(1.0 - self.phi ** 2), size=n)
        start = rng.normal(0.0, 1.0)              # the process's stationary state before the first sample
        ar = lfilter([1.0], [1.0, -self.phi], innovations, zi=[self.phi * start])[0]
        return sigma * (math.sqrt(self.white) * white + math.sqrt(1.0 - self.white) * ar)

    def describe(self) -> str:
        return (f"white {100 * self.white:.0f} % + AR(1) pole {self.phi:.2f}; 4th differences read "
                f"{self.reads:.2f} of it") if self.coloured else "white"


WHITE = NoiseShape()

#: a fitted shape is kept only where the 4th differences read less than this share of the noise's
#: standard deviation (module docstring)
COLOUR_READS = 0.85

#: the lowest frequency fitted, cycles per sample (module docstring)
BAND_FROM = 1.0 / 8.0
#: a frequency is fitted where the record's power is at most this many times the residual's
SIGNAL_SHARE = 2.0
#: the fewest frequencies (of a Welch spectrum of 2^k ≤ n/8, at most 256, samples a segment) that
#: tell a colour: fewer, and the noise is taken as white
MIN_BINS = 8
#: the shapes fitted: AR(1) poles 0–0.95 by 0.025, white shares 0–1 by 0.05
_GRID = [NoiseShape(float(phi), float(w)) for phi in np.linspace(0.0, 0.95, 39) for w in np.linspace(0.0, 1.0, 21)]
#: shapes whose Whittle log-likelihood is within this of the best one's fit the band alike (twice it,
#: 2, is χ²₂'s 63 % point)
LIKELIHOOD_SPAN = 1.0


def fit_shape(residual: np.ndarray, record: np.ndarray) -> NoiseShape:
    """The noise's shape fitted to a residual (module docstring): ``residual`` the nominal estimate's
    residual on a channel, ``record`` the channel's samples (for the band its signal fills); NaN
    where missing.  :data:`WHITE` where the record is short, the signal fills the band or the shape
    found is not coloured enough to matter (:data:`COLOUR_READS`)."""
    r = np.asarray(residual, dtype=float)
    y = np.asarray(record, dtype=float)
    keep = np.isfinite(r) & np.isfinite(y)
    r, y = r[keep], y[keep]
    if r.size < 128 or not np.any(r):
        return WHITE
    nperseg = int(min(256, 2 ** int(math.log2(r.size / 8))))
    # the median over segments: a structural error confined to part of the record (an overflow's
    # episodes) moves a minority of segments, the stationary noise all of them
    f, P = welch(r, nperseg=nperseg, detrend="linear", average="median")
    Py = welch(y, nperseg=nperseg, detrend="linear", average="median")[1]
    # noise alone: above BAND_FROM, where the record holds at most SIGNAL_SHARE times the residual's
    # power (a structural error of a tenth of the signal's amplitude then adds about 1/100 of the noise's)
    band = (f >= BAND_FROM) & (Py <= SIGNAL_SHARE * P) & (P > 0)
    if np.count_nonzero(band) < MIN_BINS:
        return WHITE
    f, P = f[band], P[band]
    # Whittle: Σ P/(s g) + log(s g), s profiled out (s = mean(P/g)): K log mean(P/g) + Σ log g per
    # segment; the record holds about n / nperseg independent segments
    objective = np.array([f.size * math.log(float(np.mean(P / g))) + float(np.sum(np.log(g)))
                          for g in (s.spectrum(f) for s in _GRID)])
    below_best = (objective - objective.min()) * (r.size / nperseg)
    # the least coloured shape the spectrum does not reject: the shapes that fit the band alike differ
    # most below it, where the shape is extrapolated
    shape = max((s for s, d in zip(_GRID, below_best) if d <= LIKELIHOOD_SPAN), key=lambda s: s.reads)
    return shape if shape.coloured and shape.reads < COLOUR_READS else WHITE


def noise_shapes(estimate, data) -> dict[str, NoiseShape]:
    """The shape of each measured channel's noise (not of the given inputs) from an estimate's
    measurement residuals (:func:`.where.residual_components`) on the record ``data``."""
    model = estimate.problem.model
    out = {}
    for c in residual_components(estimate):
        ch = c.get("channel")
        if c["kind"] != "measurement" or ch is None or ch in model.given or ch not in data.channels:
            continue
        r = np.where(c["mask"], c["values"], np.nan)
        y = np.asarray(data.channels[ch], dtype=float)
        if y.size != r.size:          # the estimate's grid is not the record's: no colour read
            continue
        out[ch] = fit_shape(r, y)
    return out
