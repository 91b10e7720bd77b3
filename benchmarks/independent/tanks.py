"""An independently written simulator of two cascaded water tanks with an overflowing upper tank.

Shaped like the public cascaded-tanks benchmark (Schoukens, Mattsson, Wigren and Noël 2016; the
real record ``tanque.csv``, /work/shared/data/cascaded_tanks/README.md): a pump at voltage u fills
the upper tank, which drains through an orifice into the lower tank, which drains into the
reservoir; only the lower level is measured, by a capacitive sensor that clips at 10 V.  Written
from the physics in SI units with numpy/scipy only (:class:`shootlab.estimation.data.Measurements` only
wraps the records); the nominal model it is diagnosed with is ``examples/tanks.py:model``
(levels in the sensor's volts, x1' = k1 u − k2 √x1, x2' = k2 √x1 − k3 √x2).

Truth (levels h1, h2 in m, Torricelli outflows through orifices of area a and discharge
coefficient Cd)::

    A1 h1' = q_p(u) − q12 − q_s                 q12 = Cd a1 √(2 g h1)
    A2 h2' = q12 + β q_s − q2 − q_l2            q2  = Cd a2 √(2 g h2)
    y      = clip(G h2 + c, 0, 10 V)            (12-bit ADC over 0–10 V; a sample at 10 V is clipped)

q_p = κ u the pump (κ = 5.55e-6 m³/(s V)); A1 = 4.5e-3 m², A2 = 6.0e-3 m² (the tanks differ), Cd
= 0.6, a1 = 1.392e-5 m², a2 = 1.607e-5 m², G = 40 V/m.  In the model's units (x2 = G h2, x1 =
G (A1/A2) h1) these are k1 = 0.037 s⁻¹, k2 = 0.045 V^½/s, k3 = 0.045 V^½/s: the nominal model is
the truth without its effects.  The effects (each the physical meaning of a candidate of
``examples/tanks.py:library``, not its smoothed formula):

* ``overflow``: the upper tank is :math:`H_1` tall.  When it is full (h1 = H1) and the inflow
  exceeds the outflow, the level stays at H1 and the excess q_s = q_p − q12 spills over the rim;
  a fraction β = 0.6 of it falls into the lower tank, the rest is lost.  A hybrid system: the
  integration stops at the events h1 = H1 (filling) and q_p − q12(H1) = 0 (draining) and
  switches the equations there — no smoothing (the library smooths the switch over ±0.5 V).
  Magnitude: the height H1 (the smaller, the more overflow).  Without it the tank never fills.
* ``sensor_offset``: c ≠ 0 (volts).
* ``pump_dead_zone``: q_p = κ max(u − u0, 0) (a pump that stalls below u0 volts; a hard kink).
* ``leak_upper``, ``leak_lower``: a laminar leak q_l = λ h out of the tank (m²/s) — out of the
  upper tank as − λ1 h1 beside q12 and out of the lower one as q_l2.

Independence from the model and its library: SI units and the physical parameters above,
unequal cross-sections, the hard overflow switch (events), the hard dead zone, the input linear
between its samples (a first-order hold; the model reads the samples through a cubic spline),
scipy's RK45 per sample interval (rtol 1e-10) with event location; noise: Gaussian, white, standard
deviation ``noise`` × the std of the noise-free unclipped level, then the 12-bit quantisation
(2.4 mV steps); the pump voltage is recorded exactly (the command).  A clipped sample is written as
missing (NaN), as ``examples/tanks.py`` converts the real record.

Inputs like the real record's (Ts = 4 s, 1,024 samples): random-phase multisines with the real
inputs' spectrum — equal amplitudes on the lines 1…19 of 1/4096 s, a tenth of that on 20…59 (to
0.0144 Hz) — mean 2.8 V, std 1.0 V; one realisation of the phases for identification, another for
validation.  The multisine is periodic over the record, so a record starts in the periodic steady
state (the record is the second of two periods simulated from the steady state at the first
sample, the first dropped); :func:`simulate` under any other input starts from the steady state at
its first sample unless given initial levels.

Magnitudes (:data:`MAGNITUDES`): overflow — the tank's height H1, such that the upper tank is full
on about 3 / 5 / 13 % of the identification record (the real record's overflow model,
docs/diagnosis.md, has its upper level above L on 14 % of the samples); the other effects sized so
that refitting the nominal model leaves 2 / 4 / 8 % of the level's std (2, 4, 8 times the 1 %
noise).  Measured on the identification record (``python -m benchmarks.independent.tanks``;
change: RMS of y − y_clean over the unclipped samples over the std of y_clean; refit: the RMS
residual of the nominal model refitted to the noise-free record, :func:`nominal_refit`, over the
std of y — the clean record's is 0.0006, the fit's own accuracy)::

    clean: y 2.1 … 9.9 V, mean 5.3 V, std 1.6 V; 26 clipped samples (validation 16)
    effect          magnitude  value      change  refit   full    clipped
    overflow        small      0.34 m     0.164   0.138   3.0 %   26
                    moderate   0.28 m     0.282   0.231   5.4 %   22
                    large      0.24 m     0.379   0.296   12.6 %  16
    sensor_offset   s / m / l  −0.15 / −0.3 / −0.6 V        change 0.09 / 0.18 / 0.37, refit 0.024 / 0.048 / 0.093
    pump_dead_zone  s / m / l  0.075 / 0.15 / 0.3 V         change 0.17 / 0.34 / 0.65, refit 0.022 / 0.042 / 0.085
    leak_upper      s / m / l  1.75 / 3.5 / 7 × 1e-6 m²/s   change 0.14 / 0.27 / 0.49, refit 0.017 / 0.032 / 0.061
    leak_lower      s / m / l  2.5 / 5 / 10 × 1e-6 m²/s     change 0.15 / 0.28 / 0.51, refit 0.017 / 0.033 / 0.062

The overflow is a strong effect wherever it acts: even the small one leaves 14 times the 1 % noise
after refitting (the real record's nominal fit leaves 0.43 V, 20 % of its std).  The pump's voltage
never falls below 0.67 V, so the dead zones here act as a constant loss of inflow κ u0.

Entry points: :func:`data` (the benchmark's identification and validation records) and
:func:`simulate` (the same system under any pump voltage given by its samples).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

from shootlab.estimation.data import Measurements

__all__ = ["PHYSICAL", "EFFECTS", "MAGNITUDES", "TS", "SAMPLES", "CLIP", "INPUT", "data", "simulate",
           "integrate", "pump_input", "effect_parameters", "model_parameters", "steady_levels"]

G_ACC = 9.81
#: the physical parameters of the clean system (module docstring)
PHYSICAL = dict(A1=4.5e-3, A2=6.0e-3, Cd=0.6, a1=1.392e-5, a2=1.607e-5, kappa=5.55e-6, gain=40.0, beta=0.6)
TS = 4.0                 # s
SAMPLES = 1024
CLIP = 10.0              # V, the sensor's ceiling
ADC_BITS = 12
INPUT = "u"              # the input channel of a record and of an input CSV

EFFECTS = ("overflow", "sensor_offset", "pump_dead_zone", "leak_upper", "leak_lower")

#: effect -> (parameter, {small, moderate, large}); calibrated (module docstring)
MAGNITUDES = {
    "overflow": ("H1", dict(small=0.34, moderate=0.28, large=0.24)),
    "sensor_offset": ("offset", dict(small=-0.15, moderate=-0.3, large=-0.6)),
    "pump_dead_zone": ("u0", dict(small=0.075, moderate=0.15, large=0.3)),
    "leak_upper": ("leak1", dict(small=1.75e-6, moderate=3.5e-6, large=7e-6)),
    "leak_lower": ("leak2", dict(small=2.5e-6, moderate=5e-6, large=1e-5)),
}

#: the clean system's effect parameters: no overflow, no offset, no dead zone, no leaks
CLEAN = dict(H1=math.inf, offset=0.0, u0=0.0, leak1=0.0, leak2=0.0)


def effect_parameters(effect: str | None, magnitude: str | float = "moderate") -> dict[str, float]:
    """All parameters of the system with ``effect`` at ``magnitude`` (a named one or the value of
    the effect's parameter): :data:`PHYSICAL` and the effect parameters of :data:`CLEAN`."""
    p = dict(PHYSICAL, **CLEAN)
    if effect is None:
        return p
    if effect not in MAGNITUDES:
        raise ValueError(f"unknown tanks effect {effect!r}; known: {list(MAGNITUDES)}")
    name, table = MAGNITUDES[effect]
    if isinstance(magnitude, str):
        if magnitude not in table:
            raise ValueError(f"unknown magnitude {magnitude!r} of {effect}; known: {list(table)} or a number ({name})")
        p[name] = float(table[magnitude])
    else:
        p[name] = float(magnitude)
    return p


def model_parameters(p: dict[str, float] | None = None) -> dict[str, float]:
    """k1, k2, k3 of ``examples/tanks.py:model`` (levels in the sensor's volts) and the overflow
    level L in its x1 scale, from the physical parameters (module docstring)."""
    p = p or effect_parameters(None)
    r = math.sqrt(2 * G_ACC)
    k1 = p["gain"] * p["kappa"] / p["A2"]
    k2 = math.sqrt(p["gain"]) * p["Cd"] * p["a1"] * r / math.sqrt(p["A1"] * p["A2"])
    k3 = math.sqrt(p["gain"]) * p["Cd"] * p["a2"] * r / p["A2"]
    return dict(k1=k1, k2=k2, k3=k3, overflow_level=p["gain"] * p["A1"] / p["A2"] * p["H1"])


# -- the input -------------------------------------------------------------------------------------------------
def pump_input(seed: int, samples: int = SAMPLES, mean: float = 2.8, std: float = 1.0) -> np.ndarray:
    """Random-phase multisine with the real inputs' spectrum (module docstring), periodic over
    ``samples`` samples, mean ``mean`` and std ``std`` volts, within the pump's 0–10 V."""
    k = np.arange(1, 60)
    amp = np.where(k <= 19, 1.0, 0.1)
    ph = np.random.default_rng(seed).uniform(0.0, 2 * np.pi, k.size)
    n = np.arange(samples)
    u = (amp[:, None] * np.cos(2 * np.pi * k[:, None] * n[None, :] / samples + ph[:, None])).sum(0)
    return np.clip(mean + std * u / np.std(u), 0.0, 10.0)


# -- the physics ---------------------------------------------------------------------------------------------
class _Tanks:
    def __init__(self, p: dict[str, float]):
        self.p = p
        self.r = math.sqrt(2 * G_ACC)

    def pump(self, u):
        return self.p["kappa"] * max(u - self.p["u0"], 0.0)

    def q12(self, h1):
        return self.p["Cd"] * self.p["a1"] * self.r * math.sqrt(max(h1, 0.0))

    def q2(self, h2):
        return self.p["Cd"] * self.p["a2"] * self.r * math.sqrt(max(h2, 0.0))

    def rhs(self, full: bool, u):
        p = self.p

        def f(tt, x):
            h1, h2 = x[0], x[1]
            qp, q12 = self.pump(u(tt)), self.q12(h1)
            out1 = q12 + p["leak1"] * h1
            spill = qp - out1 if full else 0.0
            d1 = 0.0 if full else (qp - out1) / p["A1"]
            out2 = self.q2(h2) + p["leak2"] * h2
            d2 = (q12 + p["beta"] * spill - out2) / p["A2"]
            # the volumes that left the tanks: drained (outflow and leaks), and spilled past the lower tank
            return [d1, d2, out2 + p["leak1"] * h1, (1.0 - p["beta"]) * spill]
        return f

    def net_at_rim(self, u):
        """Inflow minus outflow of a full upper tank: the overflow ends where it falls through 0."""
        p = self.p

        def g(tt, x):
            return self.pump(u(tt)) - self.q12(p["H1"]) - p["leak1"] * p["H1"]
        g.terminal, g.direction = True, -1.0
        return g

    def rim(self):
        def g(tt, x):
            return x[0] - self.p["H1"]
        g.terminal, g.direction = True, 1.0
        return g


def steady_levels(p: dict[str, float], u: float) -> tuple[float, float]:
    """The levels (h1, h2) [m] in equilibrium at a constant pump voltage ``u`` (h1 capped at H1
    with the spill's share β into the lower tank), by bisection on each balance."""
    tk = _Tanks(p)

    def root(f, hi):
        lo = 0.0
        while f(hi) > 0:
            hi *= 2.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if f(mid) > 0 else (lo, mid)
        return 0.5 * (lo + hi)
    qp = tk.pump(u)
    h1 = root(lambda h: qp - tk.q12(h) - p["leak1"] * h, 1.0)
    spill = 0.0
    if h1 >= p["H1"]:
        h1 = p["H1"]
        spill = qp - tk.q12(h1) - p["leak1"] * h1
    inflow = tk.q12(h1) + p["beta"] * spill
    h2 = root(lambda h: inflow - tk.q2(h) - p["leak2"] * h, 1.0)
    return h1, h2


def integrate(p: dict[str, float], t: np.ndarray, u: np.ndarray, initial: tuple[float, float]
              ) -> tuple[np.ndarray, np.ndarray]:
    """(K, 4) states at the sample times — the levels h1, h2 [m] and the volumes [m³] that left
    the tanks since t[0]: drained (the lower outflow and both leaks) and spilled past the lower
    tank — and a (K,) flag "upper tank full", from the levels ``initial`` at t[0], the pump voltage
    linear between its samples (module docstring)."""
    tk = _Tanks(p)
    x = np.array([*initial, 0.0, 0.0], dtype=float)
    if x[0] > p["H1"]:
        raise ValueError(f"initial upper level {x[0]:g} m above the tank's height {p['H1']:g} m")
    full = bool(x[0] >= p["H1"] and tk.pump(u[0]) > tk.q12(p["H1"]) + p["leak1"] * p["H1"])
    X = np.zeros((t.size, 4))
    flag = np.zeros(t.size, dtype=bool)
    X[0], flag[0] = x, full
    for i in range(t.size - 1):
        a, b = float(t[i]), float(t[i + 1])
        slope = (u[i + 1] - u[i]) / (b - a)
        ui, ti = float(u[i]), a

        def uu(tt, ui=ui, ti=ti, slope=slope):
            return ui + slope * (tt - ti)
        while a < b:
            events = [tk.net_at_rim(uu)] if full else ([tk.rim()] if math.isfinite(p["H1"]) else [])
            sol = solve_ivp(tk.rhs(full, uu), (a, b), x, method="RK45", rtol=1e-10, atol=1e-13, events=events)
            if sol.status < 0:
                raise RuntimeError(f"tanks simulator: integration failed on [{a:g}, {b:g}] s: {sol.message}")
            x = sol.y[:, -1].copy()
            if sol.status == 1:                           # an event: switch the equations there
                a = float(sol.t_events[0][0])
                if not full:
                    x[0] = p["H1"]
                full = not full
                if b - a < 1e-9:
                    a = b
            else:
                a = b
        X[i + 1], flag[i + 1] = x, full
    return X, flag


def _sensor(p, h2):
    return p["gain"] * h2 + p["offset"]


def _measure(y_true: np.ndarray, noise: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 1024]))
    seen = y_true < CLIP
    sd = float(noise) * float(np.std(y_true[seen])) if seen.any() else 0.0
    y = y_true + (rng.normal(0.0, sd, y_true.size) if sd > 0 else 0.0)
    q = CLIP / 2 ** ADC_BITS
    y = q * np.round(np.clip(y, 0.0, CLIP) / q)
    return np.where(y >= CLIP, np.nan, y)          # clipped: missing


def _check_input(t, u):
    t = np.asarray(t, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(-1)
    if t.size != u.size:
        raise ValueError(f"tanks simulator: input t has {t.size} samples, u has {u.size}")
    if t.size < 2 or not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise ValueError("tanks simulator: input t needs at least two finite, strictly increasing times")
    bad = np.nonzero(~np.isfinite(u) | (u < 0))[0]
    if bad.size:
        raise ValueError(f"tanks simulator: pump voltage u at sample {int(bad[0])} (t = {t[bad[0]]:g}) is "
                         f"{u[bad[0]]:g}, not a finite voltage ≥ 0")
    return t, u


def simulate(effect: str | None, magnitude: str | float, input_t, input_u, noise: float = 0.0, seed: int = 0,
             initial: tuple[float, float] | None = None, truth: bool = False):
    """The record (channels ``u``, ``y``; a clipped y missing) of the tanks with ``effect`` at
    ``magnitude`` under the pump voltage samples ``input_u`` at times ``input_t``, from the levels
    ``initial`` (h1, h2 in m; default: the steady state at the first input sample), the level
    measured with ``noise`` (a fraction of its std) drawn from ``seed``.  With ``truth``, also a
    dict of the noise-free levels (m), the volumes drained and spilled past the lower tank since
    the first sample (m³, :func:`integrate`), the sensor reading (V) and the "upper tank full"
    flag.

    Raises
    ------
    ValueError
        for an unknown effect or magnitude, input arrays of different lengths, fewer than two
        samples, non-increasing times, or a pump voltage that is negative or not finite.
    """
    t, u = _check_input(input_t, input_u)
    p = effect_parameters(effect, magnitude)
    X, full = integrate(p, t, u, steady_levels(p, float(u[0])) if initial is None else initial)
    y = _sensor(p, X[:, 1])
    rec = Measurements(t.copy(), dict(u=u.copy(), y=_measure(y, noise, seed)),
                       source=f"independent cascaded tanks ({effect or 'clean'})")
    return (rec, dict(levels=X[:, :2], drained=X[:, 2], spilled=X[:, 3], y=y, full=full)) if truth else rec


def _periodic(p, u):
    """Levels and flags over one period of the periodic input ``u``, from the state one period
    earlier (the steady state at u[0] two periods before the record)."""
    t2 = TS * np.arange(2 * u.size + 1)
    u2 = np.concatenate([u, u, u[:1]])
    X, full = integrate(p, t2, u2, steady_levels(p, float(u[0])))
    return X[u.size:2 * u.size], full[u.size:2 * u.size]


def data(effect: str | None, magnitude: str | float, noise: float, seed: int):
    """Identification record, validation record (noise seed ``seed + 1000``) and an info dict:
    the change of the level against the clean system, the share of samples with the upper tank
    full, the clipped samples, the parameters (physical and in the model's units)."""
    p = effect_parameters(effect, magnitude)
    clean = effect_parameters(None)
    t = TS * np.arange(SAMPLES)
    records, info = [], {}
    for name, u, s in (("identification", pump_input(1), seed), ("validation", pump_input(2), seed + 1000)):
        X, full = _periodic(p, u)
        y = _sensor(p, X[:, 1])
        y0 = _sensor(clean, _periodic(clean, u)[0][:, 1]) if effect is not None else y
        meas = _measure(y, noise, s)
        records.append(Measurements(t.copy(), dict(u=u.copy(), y=meas),
                                    source=f"independent cascaded tanks ({effect or 'clean'}, {name})"))
        seen = (y < CLIP) & (y0 < CLIP)
        key = "" if name == "identification" else "_validation"
        info["relative_change" + key] = {"y": float(np.sqrt(np.mean((y - y0)[seen] ** 2)) / np.std(y0[seen]))}
        info["full_share" + key] = float(full.mean())
        info["clipped" + key] = int(np.isnan(meas).sum())
    info.update(effect=effect, magnitude=magnitude if effect else "-", parameters=p,
                model_parameters=model_parameters(p), noise=noise,
                simulator="benchmarks.independent.tanks: SI Torricelli tanks, hard overflow by events, RK45 per "
                          "sample interval under a first-order-hold pump voltage; white noise + 12-bit ADC, "
                          "clipped at 10 V (missing); multisines with the real inputs' spectrum")
    return records[0], records[1], info


def nominal_refit(record: Measurements, p: dict[str, float] | None = None) -> dict:
    """Calibration: the nominal model's equations (x1' = k1 u − k2 √x1, x2' = k2 √x1 − k3 √x2,
    y = x2, in volts; scipy's LSODA, u linear between samples) fitted to the unclipped levels of
    ``record`` by least squares over k1, k2, k3 and both initial levels, started from the values
    of the system ``p`` (default: the clean one).  Returns the RMS residual [V], it over the std of
    the level, and the fitted values: how much of an effect re-estimating the nominal parameters
    leaves — its detectability at a given noise."""
    from scipy.optimize import least_squares

    t, u, y = record.t, record.channels["u"], record.channels["y"]
    seen = ~np.isnan(y)
    mp = model_parameters(p or effect_parameters(None))
    y0 = float(np.nanmean(y[:5]))

    def level(th):
        k1, k2, k3, x10, x20 = th

        def f(tt, x):
            r1 = math.sqrt(max(x[0], 0.0))
            return [k1 * np.interp(tt, t, u) - k2 * r1, k2 * r1 - k3 * math.sqrt(max(x[1], 0.0))]
        return solve_ivp(f, (t[0], t[-1]), [x10, x20], t_eval=t, method="LSODA", rtol=1e-9, atol=1e-10).y[1]

    x0 = [mp["k1"], mp["k2"], mp["k3"], (mp["k3"] / mp["k2"]) ** 2 * y0, y0]
    fit = least_squares(lambda th: (level(th) - y)[seen], x0, x_scale=[0.01, 0.01, 0.01, 1.0, 1.0], diff_step=1e-7)
    rms = float(np.sqrt(np.mean(fit.fun ** 2)))
    return dict(rms=rms, relative=rms / float(np.nanstd(y)), values=dict(zip(("k1", "k2", "k3", "x1_0", "x2_0"), fit.x)))


if __name__ == "__main__":   # the table of magnitudes
    ident, valid, info = data(None, "-", 0.0, 0)
    y = ident.channels["y"]
    print(f"clean: y {np.nanmin(y):.1f} … {np.nanmax(y):.1f} V, mean {np.nanmean(y):.1f} V, std {np.nanstd(y):.1f} V, "
          f"{info['clipped']} clipped (validation {info['clipped_validation']}); model units {model_parameters()}")
    print(f"clean: nominal refit residual {nominal_refit(ident)['relative']:.4f} of the level's std")
    for eff in EFFECTS:
        for mag in ("small", "moderate", "large"):
            ident, _, inf = data(eff, mag, 0.0, 0)
            print(f"{eff:15s} {mag:9s} {MAGNITUDES[eff][1][mag]:8.3g}: change {inf['relative_change']['y']:.3f} / "
                  f"{inf['relative_change_validation']['y']:.3f}, full {inf['full_share']:.3f} / "
                  f"{inf['full_share_validation']:.3f}, clipped {inf['clipped']} / {inf['clipped_validation']}, "
                  f"nominal refit residual {nominal_refit(ident)['relative']:.4f}", flush=True)
