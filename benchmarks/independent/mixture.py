"""An independently written simulator of the confined-compression experiment.

Written from the continuous equations, not from :mod:`mixtures.confined` / :mod:`mixtures.effects`
(numpy and scipy only for the simulation; :mod:`shootlab.estimation.data` only to wrap the records).

Continuous model (z from the impermeable, rigid bottom z = 0 to the filter z = L; strain
e = ∂s/∂z, extension positive; pore pressure p and load u compression positive)::

    momentum   ∂/∂z (σ(e) − p) = 0,  σ(e) − p = −u(t) at the top   ⇒   p(z, t) = σ(e(z, t)) + u(t)
    mass       ∂e/∂t = ∂/∂z (k(e) ∂p/∂z)          (solid velocity v = k ∂p/∂z, v(0) = 0)
    bottom     k ∂p/∂z = 0                          (impermeable)
    top        −k ∂p/∂z = p/ρ                       (Robin: outflow through a filter of resistance ρ;
                                                     ρ = 0 is the free-draining p(L) = 0)

Discretisation: cell-centred finite volumes in the *strain* (``CELLS`` = 120 cells, unknowns the
cell strains), p = σ(e) + u per cell, face permeability k at the mean strain of the two cells,
the top half-cell closed by the Robin condition; the method of lines is integrated by scipy's
Radau (banded Jacobian sparsity, rtol 1e-9), piecewise between the breakpoints of the load.
Channels: ``load`` = u (+ c with a load-cell offset), ``displacement`` = compression
−s(L) = −h Σ e_j (+ C·u with a machine compliance), ``pressure`` = p(0), extrapolated with the
zero-gradient condition, (9 p_1 − p_2)/8.

Effects (the physical meaning of :mod:`mixtures.effects`):

    strain_dependent_permeability   k(e) = K exp(M e)
    nonlinear_solid                 σ(e) = −(H/β) expm1(−β e)
    filter_permeability             the Robin condition above, resistance ρ
    load_offset                     measured load = u + c
    machine_compliance              measured displacement = compression + C·u

Noise model (unlike the benchmark's white Gaussian): per channel, total std ``noise`` × the std of
the noise-free measured channel, 80 % of the variance white Gaussian and 20 % an AR(1) process with
correlation time 0.01 (4 samples) — a slowly wandering sensor; the load channel is recorded with
noise, as in the benchmark.

Magnitudes: chosen here so that the moderate effect changes the most affected measured channel of
the identification record by about 3 % of its std (RMS of the noise-free change / std of the clean
channel, as :mod:`benchmarks.diagnosis` measures it); small / large at about half / double.
Measured: the moderate change is 2.8 % (permeability, pressure), 2.9 % (solid, displacement),
3.2 % (filter, both), 3.1 % (offset, load), 3.2 % (compliance, displacement).  Most of it is
absorbed by H and K: refitting the linear model (H, K) to the noise-free moderate identification
record leaves an RMS residual of only 0.2–1.1 % of the channel's std (solid 0.21 / 0.39 %,
compliance 0.67 / 0.18 %, permeability 0.20 / 0.59 %, filter 1.07 / 0.28 %, displacement /
pressure), i.e. about the 1 % noise: at 1 % noise these are hard cases by construction.

Entry points: :func:`data` (the benchmark's identification and validation records) and
:func:`simulate` (the same test under any load given by its samples — a discriminating experiment
read from a CSV — linear between them, the sample undeformed at the first time).

Look-alikes (:data:`LOOKALIKES`, the magnitude ``"lookalike"``; :data:`LOOKALIKE_FITS`, measured by
``python -m benchmarks.independent.mixture``, :func:`calibrate_lookalike`).  The second member of
each pair is the first's best look-alike on the identification load: H, K and its parameter fitted
to the first member's noise-free record (:func:`lookalike_fit`, channels weighted by 1 / std).
ΔJ = 401 · Σ misfit² / 0.01² is the misfit's size at 1 % white noise; a one-parameter difference
below χ²₁(95 %) = 3.84 is not resolved, one above χ²₁(99 %) = 6.63 is detected.

* ``nonlinear_solid`` β = 0.017 (stiffening) and ``strain_dependent_permeability`` M = −0.01558 (a
  permeability that *grows* under compression — the look-alike of a stiffening solid; the library
  allows either sign): the permeability law refitted to the solid's record leaves ΔJ = 3.5, the
  solid refitted to the permeability's record 2.2 (at β = 0.0106); the nominal model refitted to
  the solid's record 9.3.  These two stay alike at every magnitude: the best look-alike always
  leaves about 38 % of the nominal model's ΔJ (measured at β = 0.1: 117 against 311), so the only
  magnitude where they are look-alikes at 1 % noise is one where the effect is barely detected.
* ``filter_permeability`` ρ = 0.03 (the "large" magnitude) and ``machine_compliance`` C = −0.01378
  (the transducer reads less than the sample's compression): ΔJ = 3.4 and 3.5 (the reverse, at
  ρ = 0.0298), against 1,863 for the nominal model — plainly detected, and still look-alikes.

Checks (401 samples, ramp and hold): against the analytic Terzaghi solution
(:mod:`mixtures.terzaghi`) the max error is 4.4e-5 / 4.0e-5 (displacement / bottom pressure) with
60 cells, 1.1e-5 / 1.0e-5 with 120, 2.7e-6 / 2.5e-6 with 240 (second order); against
``mixtures.effects.simulate_mixture`` on a 60-element FE mesh ≤ 1.4e-5 / 9.2e-5 clean and with each
effect (same signs); against the default 3 elements 4.2e-3 / 4.4e-2.
"""
from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp
from scipy.sparse import diags

from shootlab.estimation.data import Measurements

__all__ = ["data", "simulate", "integrate", "identification_load", "validation_load", "sampled_load", "EFFECTS",
           "MAGNITUDES", "LOOKALIKES", "LOOKALIKE_FITS", "INPUT", "NOMINAL_ELEMENTS", "CELLS", "relative_change",
           "effect_parameters", "lookalike_fit", "lookalike_misfit"]

INPUT = "load"           # the input channel of a record and of an input CSV

EFFECTS = ("strain_dependent_permeability", "nonlinear_solid", "filter_permeability", "load_offset",
           "machine_compliance")

#: effect -> (parameter name, {small, moderate, large}); calibrated below (module docstring)
MAGNITUDES = {
    "strain_dependent_permeability": ("M", dict(small=0.04, moderate=0.08, large=0.16)),
    "nonlinear_solid": ("beta", dict(small=0.025, moderate=0.05, large=0.1)),
    "filter_permeability": ("resistance", dict(small=0.0075, moderate=0.015, large=0.03)),
    "load_offset": ("offset", dict(small=0.0028, moderate=0.0055, large=0.011)),
    "machine_compliance": ("compliance", dict(small=0.0022, moderate=0.0045, large=0.009)),
}

#: look-alike pairs: pair -> {member: its parameter}, the first member the reference, the second its
#: best look-alike on the identification load (module docstring, "Look-alikes")
LOOKALIKES = {
    "solid_permeability": {"nonlinear_solid": dict(beta=0.017), "strain_dependent_permeability": dict(M=-0.01558)},
    "filter_compliance": {"filter_permeability": dict(resistance=0.03), "machine_compliance": dict(compliance=-0.01378)},
}
#: the calibration of each pair (:func:`lookalike_fit`): H and K with which the second member
#: reproduces the first's noise-free identification record, the RMS misfit per channel over its
#: std (:func:`lookalike_misfit`), the samples, and the statistics at 1 % white noise,
#: ΔJ = samples · Σ misfit² / 0.01²: of the first member's record against the refitted nominal model
#: (``dJ_nominal``) and of the second's record against the refitted first member (``dJ_reverse``)
LOOKALIKE_FITS = {
    "solid_permeability": dict(nominal=dict(H=2.007877, K=0.995157), samples=401,
                               misfit=dict(load=0.0, displacement=0.0008287, pressure=0.0004393), dJ_nominal=9.32,
                               dJ_reverse=2.21),
    "filter_compliance": dict(nominal=dict(H=1.946689, K=0.969194), samples=401,
                              misfit=dict(load=0.0, displacement=0.0006997, pressure=0.0005930), dJ_nominal=1862.6,
                              dJ_reverse=3.50),
}
_MEMBER = {e: pair for pair, members in LOOKALIKES.items() for e in members}

CELLS = 120
H_TRUE, K_TRUE, LENGTH = 2.0, 1.0, 1.0
WHITE_SHARE, AR_TAU = 0.8, 0.01

#: the resolution of the diagnosed model for these data.  Measured (clean record, 1 % noise, seed 0,
#: diagnose(model(elements=N), ident, library(model), validation=valid, seed=0), 2 shared cores):
#: N = 3 -> status "numerical" ("use 12 elements": free-run misfit above the noise 3.1 σ -> 0.71 σ;
#: the 3-element discretisation error of the bottom pressure is 0.044, 17 % of its std), 107 s;
#: N = 6 -> "no significant structural error", 161 s.  So the model must run at 6 elements (or more)
#: on fine-grid data, or the diagnosis answers "numerical" and hides the effects.
NOMINAL_ELEMENTS = 6


# ------------------------------------------------------------------------------------------ loads
def _ramp_hold():
    return np.array([0.0, 0.1]), np.array([0.0, 1.0])


def _up_unload_reload():
    return (np.array([0.0, 0.05, 0.35, 0.42, 0.65, 0.72]), np.array([0.0, 0.6, 0.6, 0.2, 0.2, 1.2]))


def _pwl(knots):
    tk, yk = knots

    def u(t):
        return np.interp(t, tk, yk)            # held at the last value after the last knot
    u.breakpoints = tk
    return u


def sampled_load(t, load):
    """The load of an experiment given by its samples: linear between them, held after the last;
    the integration restarts where the slope changes."""
    t = np.asarray(t, dtype=float)
    load = np.asarray(load, dtype=float)
    kinks = np.abs(np.diff(np.diff(load) / np.diff(t))) > 1e-12 * (1.0 + np.abs(load).max() / (t[-1] - t[0]))
    u = _pwl((t, load))
    u.breakpoints = np.concatenate([t[:1], t[1:-1][kinks], t[-1:]])
    return u


def identification_load():
    """Ramp to 1 over 0.1, then held."""
    return _pwl(_ramp_hold())


def validation_load():
    """Up to 0.6, partly unloaded to 0.2, reloaded to 1.2 (piecewise linear)."""
    return _pwl(_up_unload_reload())


# ------------------------------------------------------------------------------------------ simulator
def integrate(load, t, H=H_TRUE, K=K_TRUE, M=0.0, beta=0.0, resistance=0.0, length=LENGTH, cells=CELLS,
              rtol=1e-9, atol=1e-12):
    """Noise-free true channels: dict(t, load, displacement (compression), pressure (bottom))."""
    n = int(cells)
    h = float(length) / n
    t = np.asarray(t, dtype=float)

    def sigma(e):
        if beta == 0.0:
            return H * e
        return -(H / beta) * np.expm1(-beta * e)

    def perm(e):
        return K * np.exp(M * e) if M != 0.0 else K * np.ones_like(e)

    def rhs(tt, e):
        p = sigma(e) + load(tt)
        kf = perm(0.5 * (e[1:] + e[:-1]))
        flux = np.empty(n + 1)                 # k ∂p/∂z at the faces 0 … n
        flux[0] = 0.0
        flux[1:n] = kf * (p[1:] - p[:-1]) / h
        kt = perm(e[-1:])[0]
        g = 2.0 * kt / h                       # conductance of the top half cell
        p_top = 0.0 if resistance == 0.0 else resistance * g * p[-1] / (1.0 + resistance * g)
        flux[n] = g * (p_top - p[-1])
        return (flux[1:] - flux[:-1]) / h

    sparsity = diags([1.0, 1.0, 1.0], [-1, 0, 1], shape=(n, n))
    edges = sorted({t[0], t[-1], *[b for b in load.breakpoints if t[0] < b < t[-1]]})
    E = np.zeros((t.size, n))
    y = np.zeros(n)
    for a, b in zip(edges[:-1], edges[1:]):
        mask = (t > a) & (t <= b) if a > t[0] else (t >= a) & (t <= b)
        t_out = np.unique(np.concatenate([t[mask], [b]]))
        sol = solve_ivp(rhs, (a, b), y, method="Radau", t_eval=t_out, rtol=rtol, atol=atol,
                        jac_sparsity=sparsity)
        if not sol.success:  # pragma: no cover
            raise RuntimeError(sol.message)
        keep = np.isin(t_out, t[mask])
        E[mask] = sol.y.T[keep]
        y = sol.y[:, -1]
    u = load(t)
    P = sigma(E) + u[:, None]
    return dict(t=t, load=u, displacement=-h * E.sum(axis=1), pressure=(9.0 * P[:, 0] - P[:, 1]) / 8.0)


#: effect -> the keyword of :func:`integrate` its parameter is (the sensor effects act on the channels)
_INTEGRATE = {"strain_dependent_permeability": "M", "nonlinear_solid": "beta", "filter_permeability": "resistance"}


def effect_parameters(effect: str | None, magnitude: str | float = "moderate") -> dict[str, float]:
    """The system's parameters: H, K and the effect's parameter (named as in :data:`MAGNITUDES`) at
    a named magnitude — "small", "moderate", "large", or "lookalike" for a member of a look-alike
    pair (:data:`LOOKALIKES`) — or with the value ``magnitude``."""
    p = dict(H=H_TRUE, K=K_TRUE)
    if effect is None:
        return p
    if effect not in MAGNITUDES:
        raise ValueError(f"unknown mixture effect {effect!r}; known: {list(MAGNITUDES)}")
    name, table = MAGNITUDES[effect]
    if magnitude == "lookalike":
        if effect not in _MEMBER:
            raise ValueError(f"{effect} is in no look-alike pair; the pairs: {list(LOOKALIKES)}")
        p[name] = float(LOOKALIKES[_MEMBER[effect]][effect][name])
    elif isinstance(magnitude, str):
        if magnitude not in table:
            raise ValueError(f"unknown magnitude {magnitude!r} of {effect}; known: {list(table)}, lookalike "
                             f"or a number ({name})")
        p[name] = float(table[magnitude])
    else:
        p[name] = float(magnitude)
    return p


def _channels(effect, p, load, t):
    """The noise-free measured channels of the system ``p`` (:func:`effect_parameters`)."""
    kw = {}
    if effect in _INTEGRATE:
        kw[_INTEGRATE[effect]] = p[MAGNITUDES[effect][0]]
    out = dict(integrate(load, t, H=p["H"], K=p["K"], **kw))
    if effect == "load_offset":
        out["load"] = out["load"] + p["offset"]
    if effect == "machine_compliance":
        out["displacement"] = out["displacement"] + p["compliance"] * out["load"]
    return out


CHANNELS = ("load", "displacement", "pressure")


def _noise(y, noise, rng, dt):
    """``y`` plus noise (module docstring); ``dt`` the sample spacing: one number (a uniform grid)
    or one per interval."""
    sd = float(noise) * float(np.std(y))
    if sd == 0.0:
        return y.copy()
    white = rng.normal(0.0, sd * np.sqrt(WHITE_SHARE), size=y.size)
    phi = np.exp(-np.asarray(dt, dtype=float) / AR_TAU)
    innov = rng.normal(0.0, sd * np.sqrt(1.0 - WHITE_SHARE) * np.sqrt(1.0 - phi ** 2), size=y.size - 1 + (phi.ndim == 0))
    if phi.ndim:                           # per interval: innovation i drives sample i + 1
        innov = np.concatenate([[0.0], innov])
    phi = np.broadcast_to(phi, (y.size - 1,))
    ar = np.empty(y.size)
    ar[0] = rng.normal(0.0, sd * np.sqrt(1.0 - WHITE_SHARE))
    for i in range(1, y.size):
        ar[i] = phi[i - 1] * ar[i - 1] + innov[i]
    return y + white + ar


def relative_change(effected, clean):
    """RMS of the change / std of the clean channel, per measured channel."""
    return {c: float(np.sqrt(np.mean((effected[c] - clean[c]) ** 2)) / np.std(clean[c])) for c in CHANNELS}


def _record(effect, p, load, noise, seed, t):
    truth = _channels(effect, p, load, t)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 20261130]))
    dt = np.diff(t)
    if np.abs(dt - dt[0]).max() <= 1e-9 * dt[0]:          # a uniform grid: one spacing
        dt = float(t[1] - t[0])
    return Measurements(t, {c: _noise(truth[c], noise, rng, dt) for c in CHANNELS}), truth


def simulate(effect: str | None, magnitude: str | float, input_t, input_u, noise: float = 0.0,
             seed: int = 0) -> Measurements:
    """The record (channels ``load``, ``displacement``, ``pressure`` at the times ``input_t``) of
    the test with ``effect`` at ``magnitude`` (:func:`effect_parameters`) under the load samples
    ``input_u`` (linear between them; the sample undeformed at the first time), measured with
    ``noise`` (a fraction of each channel's std) drawn from ``seed``.

    Raises
    ------
    ValueError
        for an unknown effect or magnitude, input arrays of different lengths, fewer than two
        samples, non-increasing times, or a load that is not finite.
    """
    t = np.asarray(input_t, dtype=float).reshape(-1)
    u = np.asarray(input_u, dtype=float).reshape(-1)
    if t.size != u.size:
        raise ValueError(f"mixture simulator: input t has {t.size} samples, load has {u.size}")
    if t.size < 2 or not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise ValueError("mixture simulator: input t needs at least two finite, strictly increasing times")
    bad = np.nonzero(~np.isfinite(u))[0]
    if bad.size:
        raise ValueError(f"mixture simulator: load is not finite at sample {int(bad[0])} (t = {t[bad[0]]:g})")
    rec, _ = _record(effect, effect_parameters(effect, magnitude), sampled_load(t, u), noise, seed, t)
    rec.source = f"independent confined compression ({effect or 'clean'})"
    return rec


def data(effect: str | None, magnitude: str | float, noise: float, seed: int):
    """(identification record, validation record (seed + 1000), info) with the given effect at the
    given magnitude ("small", "moderate", "large", "lookalike" or a number); ``noise`` a fraction
    of each channel's std (0.01 = 1 %)."""
    p = effect_parameters(effect, magnitude)
    t = np.linspace(0.0, 1.0, 401)
    ident, truth_i = _record(effect, p, identification_load(), noise, seed, t)
    valid, truth_v = _record(effect, p, validation_load(), noise, seed + 1000, t)
    clean_i = _channels(None, effect_parameters(None), identification_load(), t)
    clean_v = _channels(None, effect_parameters(None), validation_load(), t)
    info = dict(relative_change=relative_change(truth_i, clean_i),
                relative_change_validation=relative_change(truth_v, clean_v),
                parameters=dict(p, length=LENGTH),
                simulator=(f"benchmarks.independent.mixture: finite volumes in the strain, {CELLS} cells, "
                           f"scipy Radau; noise {noise:g} × channel std, {WHITE_SHARE:.0%} white + "
                           f"{1 - WHITE_SHARE:.0%} AR(1) (τ = {AR_TAU:g})"))
    if magnitude == "lookalike" and effect is not None:
        pair = _MEMBER[effect]
        info.update(pair=pair, partner=next(e for e in LOOKALIKES[pair] if e != effect))
    return ident, valid, info


# ------------------------------------------------------------------------------------------ look-alikes
def lookalike_misfit(pair: str) -> dict[str, float]:
    """RMS difference per channel, over the first member's std (0 where it has none: the load),
    between the first member's noise-free identification record and the second member's with the
    calibrated H and K (:data:`LOOKALIKE_FITS`)."""
    first, second = list(LOOKALIKES[pair])
    t = np.linspace(0.0, 1.0, 401)
    a = _channels(first, effect_parameters(first, "lookalike"), identification_load(), t)
    b = _channels(second, dict(effect_parameters(second, "lookalike"), **LOOKALIKE_FITS[pair]["nominal"]),
                  identification_load(), t)
    return {c: float(np.sqrt(np.mean((b[c] - a[c]) ** 2)) / np.std(a[c])) if np.std(a[c]) > 0 else 0.0
            for c in CHANNELS}


def lookalike_fit(effect: str | None, target: dict, load, t, start: float | None = None) -> dict:
    """Calibration of the look-alike pairs: the system with ``effect`` (None: the nominal one),
    its H, K and the effect's parameter fitted by least squares to the noise-free channels
    ``target`` (each channel weighted by 1 / its std) under ``load`` at ``t``.  Returns the fitted
    parameters and the RMS residual per channel over that channel's std — the misfit a noise of
    that fraction would hide."""
    from scipy.optimize import least_squares

    names = ["H", "K"] + ([MAGNITUDES[effect][0]] if effect else [])
    x0 = np.array([H_TRUE, K_TRUE] + ([start if start is not None else MAGNITUDES[effect][1]["moderate"]]
                                      if effect else []), dtype=float)
    sd = {c: float(np.std(target[c])) for c in CHANNELS}

    def resid(x):
        out = _channels(effect, dict(zip(names, x)), load, t)
        return np.concatenate([(out[c] - target[c]) / sd[c] for c in CHANNELS])

    lower = [1e-6, 1e-6] + ([0.0] if effect == "filter_permeability" else [-np.inf] if effect else [])
    fit = least_squares(resid, x0, bounds=(lower, np.inf), x_scale=np.maximum(np.abs(x0), 1e-3), diff_step=1e-6,
                        xtol=1e-10, ftol=1e-12)
    r = fit.fun.reshape(len(CHANNELS), -1)
    return dict(parameters=dict(zip(names, map(float, fit.x))),
                misfit={c: float(np.sqrt(np.mean(r[j] ** 2))) for j, c in enumerate(CHANNELS)})


def calibrate_lookalike(pair: str, noise: float = 0.01) -> dict:
    """The numbers of :data:`LOOKALIKE_FITS` for ``pair``, measured: the first member's record
    refitted by the nominal model and by the second member (from its stored look-alike value), and
    the second member's record refitted by the first; ΔJ at white noise of ``noise`` × each
    channel's std.  Minutes: every fit integrates the 120-cell model some 20–60 times."""
    first, second = list(LOOKALIKES[pair])
    t = np.linspace(0.0, 1.0, 401)
    load = identification_load()

    def dj(fit):
        return t.size * sum(v ** 2 for v in fit["misfit"].values()) / noise ** 2
    a = _channels(first, effect_parameters(first, "lookalike"), load, t)
    nominal = lookalike_fit(None, a, load, t)
    twin = lookalike_fit(second, a, load, t, start=LOOKALIKES[pair][second][MAGNITUDES[second][0]])
    b = _channels(second, effect_parameters(second, "lookalike"), load, t)
    reverse = lookalike_fit(first, b, load, t, start=LOOKALIKES[pair][first][MAGNITUDES[first][0]])
    return dict(nominal=nominal, twin=twin, reverse=reverse, dJ_nominal=dj(nominal), dJ_twin=dj(twin),
                dJ_reverse=dj(reverse))


if __name__ == "__main__":      # python -m benchmarks.independent.mixture: the look-alike calibration
    for pair in LOOKALIKES:
        print(pair, calibrate_lookalike(pair), f"stored twin: {lookalike_misfit(pair)}", flush=True)
