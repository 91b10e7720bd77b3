"""An independently written simulator of the confined-compression experiment (issue 15, item 8).

Written from the continuous equations, not from :mod:`mixtures.confined` / :mod:`mixtures.effects`
(numpy and scipy only for the simulation; :mod:`shootlab.data` only to wrap the records).

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

from shootlab.data import Measurements

__all__ = ["data", "simulate", "identification_load", "validation_load", "EFFECTS", "MAGNITUDES",
           "NOMINAL_ELEMENTS", "CELLS", "relative_change"]

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


def identification_load():
    """Ramp to 1 over 0.1, then held."""
    return _pwl(_ramp_hold())


def validation_load():
    """Up to 0.6, partly unloaded to 0.2, reloaded to 1.2 (piecewise linear)."""
    return _pwl(_up_unload_reload())


# ------------------------------------------------------------------------------------------ simulator
def simulate(load, t, H=H_TRUE, K=K_TRUE, M=0.0, beta=0.0, resistance=0.0, length=LENGTH, cells=CELLS,
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


def _measured(effect, value, load, t):
    kw = {}
    if effect == "strain_dependent_permeability":
        kw["M"] = value
    elif effect == "nonlinear_solid":
        kw["beta"] = value
    elif effect == "filter_permeability":
        kw["resistance"] = value
    out = simulate(load, t, **kw)
    out = dict(out)
    if effect == "load_offset":
        out["load"] = out["load"] + value
    if effect == "machine_compliance":
        out["displacement"] = out["displacement"] + value * out["load"]
    return out


CHANNELS = ("load", "displacement", "pressure")


def _noise(y, noise, rng, dt):
    sd = float(noise) * float(np.std(y))
    if sd == 0.0:
        return y.copy()
    white = rng.normal(0.0, sd * np.sqrt(WHITE_SHARE), size=y.size)
    phi = np.exp(-dt / AR_TAU)
    innov = rng.normal(0.0, sd * np.sqrt(1.0 - WHITE_SHARE) * np.sqrt(1.0 - phi ** 2), size=y.size)
    ar = np.empty(y.size)
    ar[0] = rng.normal(0.0, sd * np.sqrt(1.0 - WHITE_SHARE))
    for i in range(1, y.size):
        ar[i] = phi * ar[i - 1] + innov[i]
    return y + white + ar


def relative_change(effected, clean):
    """RMS of the change / std of the clean channel, per measured channel."""
    return {c: float(np.sqrt(np.mean((effected[c] - clean[c]) ** 2)) / np.std(clean[c])) for c in CHANNELS}


def _record(effect, value, load, noise, seed, t):
    truth = _measured(effect, value, load, t)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 20261130]))
    dt = float(t[1] - t[0])
    return Measurements(t, {c: _noise(truth[c], noise, rng, dt) for c in CHANNELS}), truth


def data(effect: str | None, magnitude: str, noise: float, seed: int):
    """(identification record, validation record (seed + 1000), info) with the given effect at the
    given magnitude ("small", "moderate", "large" or a number); ``noise`` a fraction of each
    channel's std (0.01 = 1 %)."""
    if effect is not None and effect not in MAGNITUDES:
        raise ValueError(f"unknown mixture effect {effect!r}; known: {list(MAGNITUDES)}")
    t = np.linspace(0.0, 1.0, 401)
    if effect is None:
        value, params = 0.0, {}
    else:
        name, table = MAGNITUDES[effect]
        value = float(table[magnitude]) if isinstance(magnitude, str) else float(magnitude)
        params = {name: value}
    ident, truth_i = _record(effect, value, identification_load(), noise, seed, t)
    valid, truth_v = _record(effect, value, validation_load(), noise, seed + 1000, t)
    clean_i = _measured(None, 0.0, identification_load(), t)
    clean_v = _measured(None, 0.0, validation_load(), t)
    info = dict(relative_change=relative_change(truth_i, clean_i),
                relative_change_validation=relative_change(truth_v, clean_v),
                parameters=dict(H=H_TRUE, K=K_TRUE, length=LENGTH, **params),
                simulator=(f"benchmarks.independent.mixture: finite volumes in the strain, {CELLS} cells, "
                           f"scipy Radau; noise {noise:g} × channel std, {WHITE_SHARE:.0%} white + "
                           f"{1 - WHITE_SHARE:.0%} AR(1) (τ = {AR_TAU:g})"))
    return ident, valid, info
