"""An independently written simulator of a Duffing oscillator with an input offset.

Second kind of mechanical record for the diagnosis benchmark, shaped like the public electronic
Duffing-oscillator benchmark ("Silverbox", Wigren and Schoukens 2013): a lightly damped oscillator
with a hardening cubic spring, identified from a random-phase multisine of moderate amplitude (the
cubic force a few per cent of the linear spring's) and validated on an "arrow head" — band-limited
noise whose amplitude grows over the record, until the cubic term shows clearly.  Written from the
physics with numpy/scipy only; :class:`shootlab.estimation.data.Measurements` only wraps the returned arrays.

Truth (SI; the scale of the report's mass–spring–damper, §3.4)::

    m s'' + b s' + k s + k3 s³ = u(t) + c0        from rest at the first sample
    m = 1 kg, b = 0.1 N s/m, k = 1 N/m            (ω0 = 1 rad/s, damping ratio 0.05)
    c0 = 0.01 N                                   a DC offset of the force actuator, in every record

Nominal model: the linear mass–spring–damper :func:`manipulators.msd.model` (registered ``msd``,
channels ``t, u, s``).  Its library (:func:`manipulators.effects.library` for the msd) has both
effects of the truth: ``cubic_spring`` (+ k3 s³ in the motion row, parameter ``cubic_k3``, the
same sign convention as here) and ``input_offset`` (applied = u + c, parameter ``input_offset``).
The withheld effect of a record is the cubic spring (``effect = "cubic_spring"``); a "clean"
record has k3 = 0 but keeps the offset.  The offset is an effect of the system, not of the record,
so the benchmark counts it as *inherent* (``info["inherent"]``, as the independent rig's DAC
hold): naming ``input_offset`` with an estimate within a factor 2 of c0 answers a clean record
right, and a record with the cubic spring is answered by the first selected effect other than it.

Independence from the packages' generators.
* Input between samples: the generator's reconstruction is linear between the samples (a
  first-order hold); the model reads the samples through a cubic spline.
* Integration: each sample interval on its own (the input is a straight line there) by the
  fixed-step fifth-order Dormand–Prince formula, steps of at most 0.01 s, from rest at the first
  sample (:func:`integrate`).
* Noise: both channels are measured (an errors-in-variables record, as the Silverbox's two ADCs).
  Per channel, Gaussian noise of standard deviation ``noise`` × the standard deviation of the
  noise-free channel: half its variance the sensor's, through an anti-alias filter (4th-order
  Butterworth at 0.8 × the Nyquist frequency, applied at four times the sampling rate before the
  sampler keeps every 4th value), half the converter's own, white; then a 16-bit ADC over
  ±:data:`ADC_RANGE` (steps of 3.1e-4; no record reaches it).  ``noise = 0`` leaves only the
  quantisation.  The noise is not white at the top of the band:
  :func:`shootlab.estimation.data.noise_level` (4th differences) reads 0.85–0.95 σ (three draws of 3001 samples; the filtered half alone 0.77 σ).
* Inputs: identification — an odd random-phase multisine (lines at the odd multiples of 1/T up
  to 0.5 Hz, about three times the resonance; T = 60 s the record), faded in over 3 s, RMS 0.5 N;
  validation — an arrow head: Gaussian noise low-passed at 0.5 Hz (fourth-order Butterworth,
  forward–backward) under an envelope growing linearly from 0, its RMS over the last fifth of the
  record :data:`ARROW_GROWTH` = 2.5 times the identification RMS.  Both at :data:`RATE` = 50 Hz
  (about 300 samples per resonance period: the msd model's Savitzky–Golay window of 51 samples
  spans a sixth of it).

Magnitudes (:data:`MAGNITUDES`, k3 in N/m³): chosen so that the cubic force is about 1.5 / 3 / 6 %
of the linear spring force on the identification record (RMS over RMS, noise-free) — the
"few per cent" regime where a linear model still fits the identification record reasonably.
Measured (``python -m benchmarks.independent.duffing``)::

    magnitude  k3      cubic/spring ident.  valid.    cubic / RMS(u) ident.  valid.
    small      0.006   0.014                0.095     0.026                  0.186
    moderate   0.012   0.029                0.158     0.050                  0.295
    large      0.024   0.056                0.230     0.095                  0.402
    offset c0 = 0.01 N: c0 / RMS(u) = 0.020 (identification), 0.012 (validation)

(cubic / RMS(u) is the benchmark's ``relative_size``: the RMS of the force the nominal model
misses over the RMS of the command, as :mod:`benchmarks.independent.rig`.)

Entry points: :func:`data` (the benchmark's identification and validation records) and
:func:`simulate` (the same system under any input given by its samples, e.g. a discriminating
experiment read from a CSV).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.signal import butter, filtfilt, sosfilt

from shootlab.estimation.data import Measurements

__all__ = ["NOMINAL", "OFFSET", "EFFECTS", "MAGNITUDES", "RATE", "DURATION", "INPUT", "data", "simulate",
           "integrate", "identification_input", "validation_input", "cubic_share", "effect_parameters"]

NOMINAL = dict(m=1.0, b=0.1, k=1.0)
OFFSET = 0.01            # c0 [N], in every record
RATE = 50.0              # Hz
DURATION = 60.0          # s, both records
F_MAX = 0.5              # Hz, the inputs' band
ID_RMS = 0.5             # N, identification multisine
ARROW_GROWTH = 2.5       # validation RMS over its last fifth / ID_RMS
ADC_RANGE = 10.0         # ± full scale of the 16-bit ADCs (N and m), beyond every record's peak
INPUT = "u"              # the input channel of a record and of an input CSV

EFFECTS = ("cubic_spring",)

#: k3 [N/m³] of the cubic spring at each named magnitude (module docstring)
MAGNITUDES = {"cubic_spring": dict(small=0.006, moderate=0.012, large=0.024)}


def effect_parameters(effect: str | None, magnitude: str | float = "moderate") -> dict[str, float]:
    """The truth's parameters: the nominal m, b, k, the offset c0 and k3 (0 without the effect);
    ``magnitude`` a named one or the value of k3."""
    if effect is not None and effect not in MAGNITUDES:
        raise ValueError(f"unknown Duffing effect {effect!r}; known: {list(MAGNITUDES)}")
    if effect is None:
        k3 = 0.0
    elif isinstance(magnitude, str):
        if magnitude not in MAGNITUDES[effect]:
            raise ValueError(f"unknown magnitude {magnitude!r} of {effect}; known: {list(MAGNITUDES[effect])} "
                             f"or a number (k3 in N/m³)")
        k3 = MAGNITUDES[effect][magnitude]
    else:
        k3 = float(magnitude)
    return dict(NOMINAL, c0=OFFSET, k3=float(k3))


# -- inputs -------------------------------------------------------------------------------------------------
def sample_times(duration: float = DURATION, rate: float = RATE) -> np.ndarray:
    return np.arange(int(round(duration * rate)) + 1) / rate


def identification_input(t: np.ndarray, rms: float = ID_RMS, seed: int = 1) -> np.ndarray:
    """Odd random-phase multisine: equal amplitudes on the odd multiples of 1/T up to :data:`F_MAX`
    (T the record's length), phases uniform from ``seed``, faded in over 3 s, scaled to ``rms``."""
    t = np.asarray(t, dtype=float)
    T = t[-1] - t[0]
    lines = np.arange(1, int(F_MAX * T) + 1, 2) / T
    phases = np.random.default_rng(seed).uniform(0.0, 2 * np.pi, lines.size)
    u = np.sin(2 * np.pi * lines[:, None] * (t - t[0])[None, :] + phases[:, None]).sum(0)
    fade = 0.5 - 0.5 * np.cos(np.pi * np.clip((t - t[0]) / 3.0, 0.0, 1.0))
    u = u * fade
    return u * (rms / np.sqrt(np.mean(u ** 2)))


def validation_input(t: np.ndarray, seed: int = 2) -> np.ndarray:
    """Arrow head: low-passed Gaussian noise (0.5 Hz, 4th-order Butterworth, forward–backward)
    times an envelope growing linearly from 0; RMS over the last fifth = ARROW_GROWTH × ID_RMS."""
    t = np.asarray(t, dtype=float)
    rate = 1.0 / float(t[1] - t[0])
    bb, aa = butter(4, F_MAX / (0.5 * rate))
    w = filtfilt(bb, aa, np.random.default_rng(seed).normal(size=t.size))
    u = w * (t - t[0]) / (t[-1] - t[0])
    tail = t >= t[0] + 0.8 * (t[-1] - t[0])
    return u * (ARROW_GROWTH * ID_RMS / np.sqrt(np.mean(u[tail] ** 2)))


# -- the physics --------------------------------------------------------------------------------------------
#: Dormand–Prince 5(4) tableau, used here as a fixed-step fifth-order method (its 5th-order weights)
_DP_C = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0)
_DP_A = ((), (1 / 5,), (3 / 40, 9 / 40), (44 / 45, -56 / 15, 32 / 9),
         (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
         (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656))
_DP_B = (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84)
MAX_STEP = 0.01          # s, the largest step (ω h ≤ 0.03 up to the large validation amplitude)


def integrate(params: dict[str, float], t: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(K, 2) displacement and velocity at the sample times ``t`` of m s'' + b s' + k s + k3 s³ =
    u + c0, from rest at ``t[0]``, u linear between its samples (module docstring).

    Each sample interval is integrated on its own — u is a straight line there, so nothing is
    stepped over and the method keeps its order — by the fixed-step fifth-order Dormand–Prince
    formula with at least 2 steps and steps of at most :data:`MAX_STEP` (global error below 1e-9
    of the displacement's range, measured against the exact linear response)."""
    t = np.asarray(t, dtype=float)
    u = np.asarray(u, dtype=float)
    m, b, k, k3, c0 = (float(params[p]) for p in ("m", "b", "k", "k3", "c0"))
    out = np.zeros((t.size, 2))
    s = v = 0.0
    for i in range(t.size - 1):
        h_i = t[i + 1] - t[i]
        n = max(2, int(math.ceil(h_i / MAX_STEP)))
        h = h_i / n
        slope = (u[i + 1] - u[i]) / h_i
        for j in range(n):
            tau = j * h                               # time since t[i]
            ks, kv = [], []
            for c, a in zip(_DP_C, _DP_A):
                ss = s + h * sum(aa * kk for aa, kk in zip(a, ks))
                vv = v + h * sum(aa * kk for aa, kk in zip(a, kv))
                ks.append(vv)
                kv.append((u[i] + slope * (tau + c * h) + c0 - b * vv - k * ss - k3 * ss ** 3) / m)
            s += h * sum(bb * kk for bb, kk in zip(_DP_B, ks))
            v += h * sum(bb * kk for bb, kk in zip(_DP_B, kv))
        if not (math.isfinite(s) and math.isfinite(v)):
            raise RuntimeError(f"Duffing simulator: the state is not finite at t = {t[i + 1]:g}")
        out[i + 1] = s, v
    return out


def _acquisition_noise(n: int, sd: float, rng: np.random.Generator) -> np.ndarray:
    """Noise of standard deviation ``sd``: half its variance the sensor's, through the anti-alias
    filter (a 4th-order Butterworth at 0.8 × the Nyquist frequency, applied at four times the
    sampling rate before every 4th value is kept, as an analog filter before the sampler), half
    the converter's own, white."""
    over, lead = 4, 200
    sensor = sosfilt(butter(4, 0.8 / over, output="sos"), rng.normal(size=(n + lead) * over))[lead * over::over][:n]
    white = rng.normal(size=n)
    return sd * (math.sqrt(0.5) * sensor / np.std(sensor) + math.sqrt(0.5) * white)


def _adc(x: np.ndarray) -> np.ndarray:
    q = 2 * ADC_RANGE / 2 ** 16
    return q * np.round(np.clip(x, -ADC_RANGE, ADC_RANGE - q) / q)


def _measure(s: np.ndarray, u: np.ndarray, noise: float, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 3101]))
    out = {}
    for ch, true in (("u", u), ("s", s)):
        sd = float(noise) * float(np.std(true))
        out[ch] = _adc(true + _acquisition_noise(true.size, sd, rng) if sd > 0 else true)
    return out


def cubic_share(params: dict[str, float], s: np.ndarray) -> float:
    """RMS of the cubic force k3 s³ over the RMS of the linear spring force k s."""
    return float(np.sqrt(np.mean((params["k3"] * s ** 3) ** 2)) / np.sqrt(np.mean((params["k"] * s) ** 2)))


def simulate(effect: str | None, magnitude: str | float, input_t, input_u, noise: float = 0.0,
             seed: int = 0) -> Measurements:
    """The record (channels ``u``, ``s``) of the system with ``effect`` (``"cubic_spring"`` or
    None; the offset c0 is always there) at ``magnitude`` under the input samples ``input_u`` at
    the times ``input_t`` (from rest at the first), measured with ``noise`` (a fraction of each
    channel's std) drawn from ``seed``.

    Raises
    ------
    ValueError
        for an unknown effect or magnitude, input arrays of different lengths, fewer than two
        samples, non-increasing times or a non-finite input sample.
    """
    t = np.asarray(input_t, dtype=float).reshape(-1)
    u = np.asarray(input_u, dtype=float).reshape(-1)
    if t.size != u.size:
        raise ValueError(f"Duffing simulator: input t has {t.size} samples, u has {u.size}")
    if t.size < 2 or not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise ValueError("Duffing simulator: input t needs at least two finite, strictly increasing times")
    bad = np.nonzero(~np.isfinite(u))[0]
    if bad.size:
        raise ValueError(f"Duffing simulator: input u is not finite at sample {int(bad[0])} (t = {t[bad[0]]:g})")
    p = effect_parameters(effect, magnitude)
    X = integrate(p, t, u)
    return Measurements(t.copy(), _measure(X[:, 0], u, noise, seed),
                        source=f"independent Duffing oscillator ({effect or 'clean'})")


def data(effect: str | None, magnitude: str | float, noise: float, seed: int):
    """Identification record, validation record (noise seed ``seed + 1000``) and an info dict
    (sizes of the cubic force, the inherent offset, the parameters)."""
    p = effect_parameters(effect, magnitude)
    t = sample_times()
    records, info = [], {}
    for name, u, s in (("identification", identification_input(t), seed),
                       ("validation", validation_input(t), seed + 1000)):
        X = integrate(p, t, u)
        records.append(Measurements(t.copy(), _measure(X[:, 0], u, noise, s),
                                    source=f"independent Duffing oscillator ({effect or 'clean'}, {name})"))
        key = "" if name == "identification" else "_validation"
        info["relative_size" + key] = float(np.sqrt(np.mean((p["k3"] * X[:, 0] ** 3) ** 2)) / np.sqrt(np.mean(u ** 2)))
        info["cubic_share" + key] = cubic_share(p, X[:, 0])
        info["offset_share" + key] = OFFSET / float(np.sqrt(np.mean(u ** 2)))
    info.update(inherent={"input_offset": {"input_offset": OFFSET}}, effect=effect,
                magnitude=magnitude if effect else "-", parameters=p, noise=noise,
                simulator="benchmarks.independent.duffing: fixed-step Dormand–Prince 5 per sample interval under a "
                          "first-order-hold input, from rest; "
                          "anti-aliased + white noise on u and s, 16-bit ADCs; odd random-phase multisine / "
                          "arrow head")
    return records[0], records[1], info


if __name__ == "__main__":   # the table of magnitudes
    t = sample_times()
    print(f"{'magnitude':10s} {'k3':>7s} {'cubic/spring id':>16s} {'valid':>7s} {'cubic/RMS(u) id':>16s} {'valid':>7s}")
    for mag in ("small", "moderate", "large"):
        _, _, info = data("cubic_spring", mag, 0.0, 0)
        print(f"{mag:10s} {MAGNITUDES['cubic_spring'][mag]:7.3f} {info['cubic_share']:16.3f} "
              f"{info['cubic_share_validation']:7.3f} {info['relative_size']:16.3f} {info['relative_size_validation']:7.3f}")
    _, _, info = data(None, "-", 0.0, 0)
    print(f"offset c0 = {OFFSET} N: c0 / RMS(u) = {info['offset_share']:.3f} (identification), "
          f"{info['offset_share_validation']:.3f} (validation)")
