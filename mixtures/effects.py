"""The mixture candidate library for :mod:`shootlab.diagnosis`, and data with withheld effects.

Effects the confined-compression model (:mod:`mixtures.identification`, N linear elements, linear
solid, constant permeability, free-draining filter) may lack in a real test.  Each is the term it
adds to the model side of the rows (element strain e = (s_{i+1} − s_i)/h, s_1 = 0; sign
conventions of :mod:`mixtures.confined`)::

    strain_dependent_permeability  k(e) = K exp(M e) (Lai & Mow):    mass rows   + [K(s; M) − K(s; 0)] p
    nonlinear_solid                σ(e) = −(H/β) expm1(−β e):        momentum    + assembled (σ(e) − H e)
    filter_permeability            the filter resists the outflow, w(L) = p_{N+1}/ρ, so the top
                                   pressure is not zero: p_{N+1} = ρ (k/h · p_N − ½(v_{N+1} − v_N))
                                   / (1 + ρ k/h); it enters mass row N (− k/h · p_{N+1}) and the
                                   momentum rows of the top two nodes (∓ ½ p_{N+1})
    load_offset                    the load cell reads u + c:         load row    + c
    machine_compliance             the displacement transducer sees the sample's compression plus
                                   the load train's deflection C·u:   displacement row  + C u

``machine_compliance`` is our addition: in real confined-compression tests the displacement is
read at the loading piston or crosshead, which also sees the deflection of the porous platen,
the load cell and the frame — a "system compliance" that standard practice calibrates and
subtracts.  It is linear in the load, so it shows at once when the load changes, while the
sample's own compression lags behind by the consolidation time.

New parameters: ``permeability_M``, ``solid_beta``, ``filter_resistance``, ``load_offset``,
``compliance``.

Data (:func:`simulate_mixture`): the forward model of :mod:`mixtures.confined` with its pluggable
laws (:class:`~mixtures.laws.ExponentialPermeability`, :class:`~mixtures.laws.ExponentialSolid`)
for the first two effects; an independent finite-element simulation with the filter resistance
(:func:`simulate_filter`, the full N + 1 pressure unknowns and a Robin condition at the top) for the
third; the sensor effects added to the measured channels.  Noise: Gaussian, std ``noise`` times
the std of each noise-free channel (load, displacement, pressure).

Estimation strategy (:func:`output_error_estimator`): H, K first from the output-error prefit of
:mod:`mixtures.prefit` (:func:`~mixtures.prefit.output_error_fit`, re-exported here).
"""
from __future__ import annotations

from typing import Mapping

import numpy as np
import torch
from scipy.integrate import solve_ivp
from torch import Tensor

from shootlab.estimation.data import Measurements
from shootlab.diagnosis import Effect, Library, default_estimator
from shootlab.diagnosis.effects import withheld_effects
from shootlab.diagnosis.mechanical import unit_product
from shootlab.estimation import IdentificationModel

from .confined import ConfinedCompression
from .laws import ExponentialPermeability, ExponentialSolid
from .loads import DEFAULT_EXPERIMENT, SampledHistory, as_history
from .prefit import filter_system, output_error_fit
from .simulation import simulate

__all__ = ["library", "MIXTURE_EFFECTS", "EFFECT_DEFAULTS", "MAGNITUDES", "effect_parameters",
           "simulate_mixture", "simulate_filter", "output_error_fit", "output_error_estimator", "validation_load", "identification_load", "permeability_term",
           "solid_term", "filter_terms"]

MIXTURE_EFFECTS = ("strain_dependent_permeability", "nonlinear_solid", "filter_permeability", "load_offset",
                   "machine_compliance")

#: the effect's parameter in the data generator (one each)
EFFECT_DEFAULTS = {
    "strain_dependent_permeability": dict(M=1.0),
    "nonlinear_solid": dict(beta=0.6),
    "filter_permeability": dict(resistance=0.1),
    "load_offset": dict(offset=0.02),
    "machine_compliance": dict(compliance=0.04),
}

#: benchmark magnitudes (small, moderate, large) — see :mod:`benchmarks.diagnosis` for the measured
#: relative size of each effect on the measured channels
MAGNITUDES = {
    "strain_dependent_permeability": dict(small=0.06, moderate=0.15, large=0.4),
    "nonlinear_solid": dict(small=0.04, moderate=0.1, large=0.25),
    "filter_permeability": dict(small=0.01, moderate=0.025, large=0.06),
    "load_offset": dict(small=0.004, moderate=0.01, large=0.025),
    "machine_compliance": dict(small=0.003, moderate=0.008, large=0.02),
}


def _resolve(effects: Mapping[str, Mapping[str, float] | float | str] | None) -> dict[str, dict[str, float]]:
    """Name -> parameter dict, or magnitude name / number (:data:`MAGNITUDES`), to name ->
    parameters (:func:`shootlab.diagnosis.effects.withheld_effects`)."""
    return withheld_effects(effects or {}, EFFECT_DEFAULTS, MAGNITUDES, "mixture")


def effect_parameters(name: str, magnitude: str | float = "moderate") -> dict[str, float]:
    """The parameter of effect ``name`` at a named magnitude (:data:`MAGNITUDES`) or set to a number."""
    return _resolve({name: magnitude})[name]


# =============================================================================== terms (torch)
def _pad(x: Tensor, left: int, right: int) -> Tensor:
    return torch.nn.functional.pad(x, (left, right))


def _assemble(f: Tensor) -> Tensor:
    """Nodal vector Σ_e f_e [−1, +1] on nodes 1 … N+1 from element values (…, N)."""
    return _pad(f, 1, 0) - _pad(f, 0, 1)


def _strain(s: Tensor, h: float) -> Tensor:
    sf = _pad(s, 1, 0)
    return (sf[..., 1:] - sf[..., :-1]) / h


def permeability_term(s: Tensor, p: Tensor, K: Tensor, M: Tensor, h: float) -> Tensor:
    """[K(s; k = K e^{M e}) − K(s; k = K)] p on the mass rows (…, N)."""
    e = _strain(s, h)
    kel = K.unsqueeze(-1) * torch.expm1(M.unsqueeze(-1) * e)
    pf = _pad(p, 0, 1)                                       # p_{N+1} = 0
    g = kel * (pf[..., :-1] - pf[..., 1:]) / h
    return _assemble(-g)[..., :-1]


def solid_term(s: Tensor, H: Tensor, beta: Tensor, h: float) -> Tensor:
    """Assembled (σ_β(e) − H e) on the momentum rows (…, N) (nodes 2 … N+1)."""
    e = _strain(s, h)
    sigma = ExponentialSolid(beta.unsqueeze(-1)).stress(e, H.unsqueeze(-1))
    return _assemble(sigma - H.unsqueeze(-1) * e)[..., 1:]


def filter_terms(v: Tensor, p: Tensor, K: Tensor, rho: Tensor, h: float) -> tuple[Tensor, Tensor, Tensor]:
    """The top pressure p_{N+1} and its contributions to mass row N and the momentum rows (…, N)."""
    N = p.shape[-1]
    kh = K / h
    v_top = v[..., -1]
    v_below = v[..., -2] if N >= 2 else torch.zeros_like(v_top)
    p_top = rho * (kh * p[..., -1] - 0.5 * (v_top - v_below)) / (1.0 + rho * kh)
    mass = torch.zeros_like(p)
    mass = torch.cat([mass[..., :-1], (-kh * p_top).unsqueeze(-1)], -1)
    mom = [torch.zeros_like(p_top)] * N
    mom[-1] = -0.5 * p_top
    if N >= 2:
        mom[-2] = 0.5 * p_top
    return p_top, mass, torch.stack(mom, -1)


# =============================================================================== the library
def _layout(model: IdentificationModel, length: float | None):
    N = len(model.states)
    need = [f"s{j}" for j in range(2, N + 2)]
    if model.states != need or not {"H", "K"} <= set(model.parameters) or "u" not in model.inputs:
        raise ValueError(f"model {model.name!r} is not a confined-compression model "
                         f"(states {need}, parameters H, K, input u)")
    L = float(length if length is not None else model.settings.extra.get("length", 1.0))
    return N, L / N


def library(model: IdentificationModel | None = None, length: float | None = None) -> Library:
    """The mixture library for a confined-compression model (default: 3 elements).  ``length``:
    the sample height (default the model's ``settings.extra["length"]``, else 1)."""
    if model is None:
        from .identification import model as confined_model
        model = confined_model()
    N, h = _layout(model, length)
    S = [f"s{j}" for j in range(2, N + 2)]
    P = [f"p{i}" for i in range(1, N + 1)]
    Vv = [f"v{j}" for j in range(2, N + 2)]
    mass = [f"mass{i}" for i in range(1, N + 1)]
    mom = [f"momentum{j}" for j in range(2, N + 2)]

    def vec(v, names):
        return torch.stack([v[n] for n in names], -1)

    U = model.units                     # the effects' parameter units follow the model's
    top = (f"{S[-1]} (top displacement, estimated)", lambda v: v[S[-1]], U.get(S[-1]))
    # ρ: the filter's outflow velocity is p_{N+1}/ρ, so ρ is a pressure per velocity
    rho_unit = unit_product((U.get(P[-1]), 1), (U.get(S[-1]), -1), (U.get("t"), 1))

    def perm(v):
        t = permeability_term(vec(v, S), vec(v, P), v.K, v.permeability_M, h)
        return {r: t[..., i] for i, r in enumerate(mass)}

    def solid(v):
        t = solid_term(vec(v, S), v.H, v.solid_beta, h)
        return {r: t[..., i] for i, r in enumerate(mom)}

    def filt(v):
        _, tm, tp = filter_terms(vec(v, Vv), vec(v, P), v.K, v.filter_resistance, h)
        out = {mass[-1]: tm[..., -1], mom[-1]: tp[..., -1]}
        if N >= 2:
            out[mom[-2]] = tp[..., -2]
        return out

    effects = [
        Effect(name="strain_dependent_permeability", equations=mass, parameters={"permeability_M": 0.0}, term=perm,
               bounds={"permeability_M": (-20.0, 20.0)}, scale={"permeability_M": 1.0},
               starts={"permeability_M": [1.0, 3.0]}, variable=top, units={"permeability_M": "-"},
               description="strain-dependent permeability k = K exp(M e) (Lai & Mow)"),
        Effect(name="nonlinear_solid", equations=mom, parameters={"solid_beta": 0.0}, term=solid,
               bounds={"solid_beta": (-10.0, 30.0)}, scale={"solid_beta": 1.0}, starts={"solid_beta": [0.5, 2.0]},
               variable=top, units={"solid_beta": "-"}, description="strain-stiffening solid σ = (H/β)(exp(β ε_c) − 1) (β < 0: softening)"),
        Effect(name="filter_permeability", equations=[mass[-1]] + mom[-2:], parameters={"filter_resistance": 0.0},
               term=filt, bounds={"filter_resistance": (0.0, 100.0)}, scale={"filter_resistance": 0.1},
               starts={"filter_resistance": [0.05, 0.3]},
               variable=(f"{P[-1]} (estimated)", lambda v: v[P[-1]], U.get(P[-1])),
               units={"filter_resistance": rho_unit} if rho_unit else {}, description="finite filter permeability: resistance ρ, top pressure p_{N+1} ≠ 0"),
        Effect(name="load_offset", equations=["load"], parameters={"load_offset": 0.0},
               term=lambda v: {"load": v.load_offset * torch.ones_like(v.t)}, scale={"load_offset": 0.01},
               variable=("t", lambda v: v.t, U.get("t")), units={"load_offset": U.get("load") or U.get("u")},
               description="load-cell offset: measured load = u + c"),
        Effect(name="machine_compliance", equations=["displacement"], parameters={"compliance": 0.0},
               term=lambda v: {"displacement": v.compliance * v.u}, scale={"compliance": 0.01},
               variable=("u (estimated load)", lambda v: v.u, U.get("u")),
               units={"compliance": unit_product((U.get("displacement") or U.get(S[-1]), 1), (U.get("u"), -1))},
               description="machine compliance: measured displacement = compression + C·u"),
    ]
    # the TPBVP's J does not measure a misfit of this stiff model (benchmarks/mixture_misfit.py): with a
    # validation record the free run decides where the TPBVP's verdict is not a confirmed one
    return Library(name=f"mixture[N={N}]", effects=effects, estimator=output_error_estimator, initial_state="rest",
                   free_run_screen=True,
                   description="mixtures.effects: material-law, boundary and sensor effects of confined compression")


# =============================================================================== estimation strategy
def output_error_estimator(model: IdentificationModel, data, initial=None, start=None, **options):
    """The mixture family's estimator: without a warm start, H and K start from
    :func:`output_error_fit` (done here unless the model's own ``prefit`` does it); then
    :func:`shootlab.estimation.estimate` with the model's settings."""
    if start is None and not model.settings.extra.get("prefits_output_error"):
        initial = dict(initial or {}, **output_error_fit(model, data, initial))
    return default_estimator(model, data, initial=initial, start=start, **options)


# =============================================================================== data
def identification_load():
    """The identification experiment: the default ramp-and-hold creep load (ramp to 1 over 0.1)."""
    return DEFAULT_EXPERIMENT


def validation_load():
    """Another input: up, partly unloaded, reloaded higher (piecewise linear)."""
    return SampledHistory([0.0, 0.05, 0.35, 0.42, 0.65, 0.72, 1.0], [0.0, 0.6, 0.6, 0.2, 0.2, 1.2, 1.2])


def simulate_filter(t, load, H: float = 2.0, K: float = 1.0, resistance: float = 0.1, elements: int = 3,
                    length: float = 1.0):
    """Linear confined compression with a resisting filter (flux through the top w = p_{N+1}/ρ).

    Independent of the identification model's code: full element matrices on nodes 1 … N+1,
    unknowns v (nodes 2 … N+1) and p (nodes 1 … N+1)::

        R v + K p + (1/ρ) e_{N+1} p_{N+1} = 0        (N + 1 mass rows; the last multiplied by ρ)
        Rᵀ p = S s + e_N u                           (N momentum rows)

    s' = v is linear, s' = A s + b u; integrated with Radau.  ρ = 0 is the free-draining filter."""
    N = int(elements)
    A, b, P, q = filter_system(H, K, resistance, N, length)
    hist = as_history(load)
    t = np.asarray(t, dtype=float)
    bps = [x for x in getattr(hist, "breakpoints", ()) if t[0] < x < t[-1]]
    edges = [t[0]] + sorted(bps) + [t[-1]]
    Y = np.zeros((t.size, N))
    y = np.zeros(N)
    for a, c in zip(edges[:-1], edges[1:]):
        mask = (t > a) & (t <= c)
        t_out = t[mask] if mask.any() and t[mask][-1] == c else np.append(t[mask], c)
        sol = solve_ivp(lambda tt, yy: A @ yy + b * float(hist.value(tt, left=tt >= c)), (a, c), y, method="Radau",
                        t_eval=t_out, rtol=1e-10, atol=1e-12, jac=lambda tt, yy: A)
        if not sol.success:  # pragma: no cover
            raise RuntimeError(sol.message)
        Y[mask] = sol.y.T[:int(mask.sum())]
        y = sol.y[:, -1]
    u = np.asarray(hist.value(t), dtype=float) * np.ones_like(t)
    X = Y @ P.T + np.outer(u, q)                      # pressures p_1 … p_{N+1}
    V = Y @ A.T + np.outer(u, b)                      # velocities of nodes 2 … N+1
    return dict(t=t, load=u, displacement=-Y[:, -1], pressure=X[:, 0], s=Y, p=X, v=V)


def simulate_mixture(effects: Mapping[str, Mapping[str, float] | float | str] | None = None, load="identification",
                     t=None, noise: float = 0.01, seed: int = 0, H: float = 2.0, K: float = 1.0, elements: int = 3,
                     length: float = 1.0) -> tuple[Measurements, dict]:
    """A confined-compression record with the given effects (module docstring), as
    ``(data, truth)``: the measured channels ``load``, ``displacement``, ``pressure`` and the
    noise-free truth — the model's channels (same names), the channels the sensors read before
    the noise (``measured_load`` …), ``effects`` (name -> parameters) and ``noise_std`` (channel
    -> the noise's standard deviation).

    ``load``: ``"identification"`` (ramp and hold), ``"validation"`` (:func:`validation_load`) or any
    history :func:`mixtures.loads.as_history` takes; ``t``: 401 samples on [0, 1] by default."""
    eff = _resolve(effects)
    t = np.linspace(0.0, 1.0, 401) if t is None else np.asarray(t, dtype=float)
    hist = {"identification": identification_load(), "validation": validation_load()}.get(load, load) \
        if isinstance(load, str) else load
    if isinstance(load, str) and load not in ("identification", "validation"):
        raise ValueError(f"unknown load {load!r}: 'identification', 'validation' or a history")
    if "filter_permeability" in eff:
        if {"strain_dependent_permeability", "nonlinear_solid"} & set(eff):
            raise ValueError("the filter simulator has linear laws only")
        out = simulate_filter(t, hist, H, K, eff["filter_permeability"]["resistance"], elements, length)
        load_true, disp, pres = out["load"], out["displacement"], out["pressure"]
    else:
        perm = ExponentialPermeability(eff["strain_dependent_permeability"]["M"]) \
            if "strain_dependent_permeability" in eff else None
        solid = ExponentialSolid(eff["nonlinear_solid"]["beta"]) if "nonlinear_solid" in eff else None
        cc = ConfinedCompression(elements, length=length, solid=solid, permeability=perm)
        sim = simulate(cc, t, load=hist, H=H, K=K)
        load_true, disp, pres = sim.load, sim.displacement, sim.pressure
    load_m, disp_m = load_true.copy(), disp.copy()
    if "machine_compliance" in eff:
        disp_m = disp_m + eff["machine_compliance"]["compliance"] * load_true
    if "load_offset" in eff:
        load_m = load_m + eff["load_offset"]["offset"]
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    chans, std = {}, {}
    for name, y in (("load", load_m), ("displacement", disp_m), ("pressure", pres)):
        sd = float(noise) * float(np.std(y))
        std[name] = sd
        chans[name] = y + (rng.normal(0.0, sd, size=t.size) if sd > 0 else 0.0)
    return Measurements(t, chans), dict(load=load_true, displacement=disp, pressure=pres, measured_load=load_m,
                                        measured_displacement=disp_m, measured_pressure=pres, effects=eff,
                                        noise_std=std)
