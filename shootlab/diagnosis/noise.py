"""The measurement noise's colour and tails (``docs/diagnosis.md``, "Coloured noise").

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

**Heavy tails.**  The level is the median absolute deviation of the 4th differences, robust to a
signal's own kinks; the noise's variance is not.  Noise with heavy tails — occasional spikes, a
Student t — holds more variance than its median reads (1 % of samples at ±8σ beside Gaussian
noise: 1.21 times the level; Student t of 3 degrees of freedom: 1.22–1.26), and a right model's J
came out 1.6 times a floor drawn at the level (a clean pendulum record with spikes:
"significant").  ``tails`` is the ratio of the 4th differences' root mean square to their median's
reading (:func:`tail_factor`, the top 0.5 % clipped), taken on the record and on the residual and
the smaller kept: the record's own 4th differences hold the signal's kinks (the real cascaded
tanks: 1.08), the residual's the estimator's (the 6-element mixture model's: 1.6–1.8); noise
shows in both.  Read from :func:`tails_from` on, 1 + 3.3/√n: Gaussian noise's factor spreads as
1/√n.  The surrogates are drawn Gaussian at the variance it gives: their J matches the
record's in the mean, not in its spread.

A shape is kept only where it matters (:data:`KEEP_READS`): where the 4th differences would read
less than 0.85 of the noise's standard deviation.  Above that, colour and tails alone make a right
model's mean-square ratio at most 1/0.85² = 1.38, inside the tests' size thresholds (``ratio_min``
1.5, :data:`.floor.VALIDATION_RATIO` 2), and the noise is drawn white at the level as before.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter, welch
from scipy.stats import norm

from .where import residual_components

__all__ = ["NoiseShape", "WHITE", "KEEP_READS", "fit_shape", "tail_factor", "tails_from", "noise_shapes"]

_FOURTH = np.array([1.0, -4.0, 6.0, -4.0, 1.0])     # the 4th difference's weights; Σ w² = 70


@dataclass(frozen=True)
class NoiseShape:
    """White noise plus an AR(1) process, variance shares ``white`` and 1 − ``white``; ``phi`` the AR
    pole per sample.  Autocorrelation ρ(k) = white·δ_k0 + (1 − white)·φ^|k|.  ``tails``: the noise's
    standard deviation over what the median absolute deviation of its 4th differences reads of it
    (1 for Gaussian noise; :func:`tail_factor`)."""

    phi: float = 0.0
    white: float = 1.0
    tails: float = 1.0

    @property
    def coloured(self) -> bool:
        return self.white < 1.0 and self.phi > 0.0

    @property
    def plain(self) -> bool:
        """White and Gaussian: drawn at the 4th differences' level."""
        return not self.coloured and self.tails == 1.0

    @property
    def reads(self) -> float:
        """What the 4th differences' median reads of the noise's standard deviation:
        √(Σ w_i w_j ρ(i − j) / 70) / tails."""
        k = np.abs(np.subtract.outer(np.arange(5), np.arange(5)))
        rho = (1.0 - self.white) * self.phi ** k + self.white * (k == 0)
        return math.sqrt(float(_FOURTH @ rho @ _FOURTH) / 70.0) / self.tails

    def spectrum(self, f: np.ndarray) -> np.ndarray:
        """The spectral density at ``f`` cycles per sample, relative: 1 everywhere for white noise."""
        phi = self.phi
        ar = (1.0 - phi * phi) / (1.0 + phi * phi - 2.0 * phi * np.cos(2.0 * np.pi * np.asarray(f)))
        return self.white + (1.0 - self.white) * ar

    def draw(self, rng: np.random.Generator, sigma: float, n: int) -> np.ndarray:
        """``n`` samples of standard deviation ``sigma``, Gaussian (whatever ``tails``); white noise is
        one call of ``rng.normal``."""
        if not self.coloured:
            return rng.normal(0.0, sigma, size=n)
        white = rng.normal(0.0, 1.0, size=n)
        innovations = rng.normal(0.0, math.sqrt(1.0 - self.phi ** 2), size=n)
        start = rng.normal(0.0, 1.0)              # the process's stationary state before the first sample
        ar = lfilter([1.0], [1.0, -self.phi], innovations, zi=[self.phi * start])[0]
        return sigma * (math.sqrt(self.white) * white + math.sqrt(1.0 - self.white) * ar)

    def describe(self) -> str:
        if self.plain:
            return "white"
        words = [f"white {100 * self.white:.0f} % + AR(1) pole {self.phi:.2f}" if self.coloured else "white"]
        if self.tails != 1.0:
            words.append(f"heavy tails ({self.tails:.2f}× the median's reading)")
        return ", ".join(words) + f"; 4th differences read {self.reads:.2f} of it"


WHITE = NoiseShape()

#: a fitted shape is kept only where the 4th differences read less than this share of the noise's
#: standard deviation (module docstring)
KEEP_READS = 0.85

#: :func:`tail_factor` of Gaussian noise spreads by this over √n (n samples; 1.07–1.14 over 2,000 draws
#: each of 300 to 3,000 samples)
TAILS_SPREAD = 1.1
#: tails are read where :func:`tail_factor` is at least 1 + TAILS_Z · TAILS_SPREAD / √n: 1.165 on 400
#: samples, 1.06 on 3,000 — Gaussian noise exceeds it about once in 200 records (its 99th and 99.9th
#: percentiles: 1.14 and 1.20 on 400 samples, 1.05 and 1.07 on 3,000)
TAILS_Z = 3.0
#: the share of the 4th differences kept whole by :func:`tail_factor`; the rest clipped to its quantile
_TAIL_QUANTILE = 0.995
_CLIP = float(norm.ppf(0.5 + _TAIL_QUANTILE / 2.0))
#: E min(|Z|, c)² of a standard normal Z clipped at that quantile c of |Z|
_CLIPPED_GAUSSIAN = _TAIL_QUANTILE - 2.0 * _CLIP * float(norm.pdf(_CLIP)) + _CLIP ** 2 * (1.0 - _TAIL_QUANTILE)

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


def tail_factor(x: np.ndarray) -> float:
    """The root mean square of ``x``'s 4th differences (the top 0.5 % clipped to their quantile, as a
    Gaussian's would be) over what their median absolute deviation reads: about 1 for Gaussian
    noise, the noise's standard deviation over :func:`shootlab.estimation.data.noise_level` for
    noise with heavy tails; NaN where the 4th differences are too few or mostly zero."""
    x = np.asarray(x, dtype=float)
    d = np.diff(x, n=4)
    d = d[np.isfinite(d)]
    if d.size < 64:
        return math.nan
    mad = 1.4826 * float(np.median(np.abs(d - np.median(d))))
    if mad <= 0.0:
        return math.nan
    a = np.minimum(np.abs(d), np.quantile(np.abs(d), _TAIL_QUANTILE))
    return math.sqrt(float(np.mean(a * a)) / _CLIPPED_GAUSSIAN) / mad


def tails_from(n: int) -> float:
    """The least :func:`tail_factor` read as heavy tails on ``n`` samples (:data:`TAILS_Z`)."""
    return 1.0 + TAILS_Z * TAILS_SPREAD / math.sqrt(max(n, 1))


def fit_shape(residual: np.ndarray, record: np.ndarray) -> NoiseShape:
    """The noise's shape fitted to a residual (module docstring): ``residual`` the nominal estimate's
    residual on a channel, ``record`` the channel's samples (for the band its signal fills); NaN
    where missing.  :data:`WHITE` where the shape found does not matter (:data:`KEEP_READS`); the
    colour white where the record is short or the signal fills the band."""
    # tails: the smaller reading of the record's and the residual's, each before dropping samples; none
    # where either has no reading (min() would keep a NaN in first place and drop one in second)
    readings = (tail_factor(residual), tail_factor(record))
    n = int(np.count_nonzero(np.isfinite(np.asarray(residual, dtype=float))))
    tails = min(readings) if all(math.isfinite(t) for t in readings) else 1.0
    tails = tails if tails >= tails_from(n) else 1.0
    colour = _colour(residual, record)
    colour = colour if colour.coloured else WHITE
    shape = NoiseShape(colour.phi, colour.white, tails)
    return shape if shape.reads < KEEP_READS else WHITE


def _colour(residual: np.ndarray, record: np.ndarray) -> NoiseShape:
    """The white + AR(1) shape that fits the residual's spectrum where the record holds noise alone
    (module docstring); :data:`WHITE` where the record is short or the signal fills the band."""
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
    return max((s for s, d in zip(_GRID, below_best) if d <= LIKELIHOOD_SPAN), key=lambda s: s.reads)


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
