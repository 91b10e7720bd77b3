"""Rig data with one (or more) *withheld* effects: the data generator of the diagnosis benchmark.

:mod:`manipulators.rig` simulates the flexible manipulator with its own realism switches
(friction, gain, delay, ZOH, quantisation, noise).  The diagnosis benchmark needs the opposite:
the nominal two-inertia system *plus exactly the effects under test*, by the names of the
mechanical candidate library (:mod:`manipulators.effects`), so that each effect can be withheld
from the nominal model and looked for.  This module is that variant of the rig.  It has no
dynamics of its own: both simulators integrate the one right-hand side of the plant,
:class:`manipulators.rig.TwoInertia`, and differ only in its hooks.  :func:`effect_plant` sets
them from the named effects (friction laws from :mod:`manipulators.friction`, the spring law,
the input transformation); :func:`simulate_effect_rig` integrates that plant and applies this
module's own noise convention (below) — none of rig.py's friction variation, gain/delay
switches, ZOH or quantisation.  The inputs are rig.py's (:func:`~manipulators.rig.sine_sweep`,
the PD validation command :func:`~manipulators.rig.pd_validation_input`).

Model (per unit motor constant c, sign conventions of :mod:`manipulators.rig`)::

    m1 v1' =  T_s − fr1(v1)
    m2 v2' =  u_app − T_s − fr2(v2)
    T_s    =  k · spring(s2 − s1) + b (v2 − v1)

The effects (each a dict of its physical parameters; the names are the library's):

==================  =====================================================================
``coulomb_m{i}``    ``fr_i += f · σ(v_i; v_s)``            (smooth sign, C², rig.py's law)
``viscous_m{i}``    ``fr_i += b_v · v_i``                  (absolute, not relative, damping)
``stribeck_m{i}``   ``fr_i += (f_c + (f_s − f_c) exp(−(v_i/v_st)²)) σ(v_i; v_s)``
``backlash``        ``spring(Δ) = Δ − clip(Δ, ±δ)``        (hard dead-zone of half-width δ)
``cubic_spring``    ``k · spring(Δ) += k3 Δ³``             (hardening k3 > 0, softening < 0)
``input_gain``      ``u_app = gain · u``
``input_offset``    ``u_app = u + offset``
``input_saturation`` ``u_app = clip(u, ±limit)``           (hard clip)
``input_delay``     ``u_app(t) = u(t − delay)``            (u = 0 for t < 0)
==================  =====================================================================

The input transformations compose in the order delay → gain → saturation → offset.

Noise: Gaussian, on the encoder channels only, with standard deviation ``noise`` times the
standard deviation of the noise-free channel over the record (``noise=0.01`` is "1 % noise");
the command u is the controller's digital output and is recorded exactly.  No quantisation.
"""
from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np
from scipy.integrate import solve_ivp

from .friction import smooth_coulomb, stribeck, viscous
from .rig import RigSettings, TwoInertia, pd_validation_input, sine_sweep

if TYPE_CHECKING:                   # shootlab.estimation.data imports torch; importing the rig needs none
    from shootlab.estimation.data import Measurements

__all__ = ["NOMINAL", "EFFECT_DEFAULTS", "MAGNITUDES", "TIED", "simulate_effect_rig", "relative_size",
           "identification_input", "validation_input", "effect_parameters", "effect_plant"]

#: the nominal two-inertia system (the report's extended-model estimates, rig.py's defaults)
NOMINAL = dict(m1=5.40, m2=0.47, k=1000.0, b=2.3)

#: every effect's parameters with the fixed shape values; the magnitude key is listed first
EFFECT_DEFAULTS: dict[str, dict[str, float]] = {
    "coulomb_m1": dict(f=1.0, v_s=0.1),
    "coulomb_m2": dict(f=5.0, v_s=1.0),
    "viscous_m1": dict(b_v=1.0),
    "viscous_m2": dict(b_v=0.5),
    "stribeck_m1": dict(f_c=1.0, f_s=3.0, v_st=0.3, v_s=0.1),
    "stribeck_m2": dict(f_c=5.0, f_s=15.0, v_st=2.0, v_s=1.0),
    "backlash": dict(delta=0.002),
    "cubic_spring": dict(k3=1e5),
    "input_gain": dict(gain=0.9),
    "input_offset": dict(offset=3.0),
    "input_saturation": dict(limit=120.0),
    "input_delay": dict(delay=0.003),
}

#: magnitudes of the benchmark: (small, moderate, large) value of each effect's first parameter
#: (for Stribeck, f_c; f_s stays 3 f_c).  Chosen so that the force the nominal model misses on the
#: identification sweep is about 2 % (small), 5 % (moderate) and 12 % (large) of the command's RMS
#: (:func:`relative_size`; the benchmark records the measured value).
MAGNITUDES: dict[str, dict[str, float]] = {
    "coulomb_m1": dict(small=1.5, moderate=4.0, large=10.0),
    "coulomb_m2": dict(small=2.0, moderate=6.0, large=15.0),
    "viscous_m1": dict(small=1.0, moderate=3.0, large=8.0),
    "viscous_m2": dict(small=0.2, moderate=0.5, large=1.2),
    "stribeck_m1": dict(small=1.0, moderate=3.0, large=8.0),
    "stribeck_m2": dict(small=2.0, moderate=5.0, large=12.0),
    "backlash": dict(small=0.0015, moderate=0.004, large=0.01),
    "cubic_spring": dict(small=15.0, moderate=40.0, large=100.0),
    "input_gain": dict(small=0.98, moderate=0.95, large=0.88),
    "input_offset": dict(small=2.0, moderate=5.0, large=12.0),
    "input_saturation": dict(small=140.0, moderate=130.0, large=110.0),
    "input_delay": dict(small=0.0004, moderate=0.001, large=0.0025),
}


#: the parameters that follow the first when a magnitude sets it, as multiples of it: f_s = 3 f_c
TIED = {"stribeck_m1": dict(f_s=3.0), "stribeck_m2": dict(f_s=3.0)}


def _resolve(effects: Mapping[str, Mapping[str, float] | float | str] | None) -> dict[str, dict[str, float]]:
    """Name -> parameter dict, or magnitude name / number (:data:`MAGNITUDES`, :data:`TIED`), to
    name -> parameters (:func:`shootlab.diagnosis.effects.withheld_effects`)."""
    from shootlab.diagnosis.effects import withheld_effects     # here: importing the rig needs no torch
    return withheld_effects(effects or {}, EFFECT_DEFAULTS, MAGNITUDES, "rig", TIED)


def effect_parameters(name: str, magnitude: str | float = "moderate") -> dict[str, float]:
    """The parameters of effect ``name`` at a named magnitude (``MAGNITUDES``) or with its first
    parameter set to a number; Stribeck keeps f_s = 3 f_c."""
    return _resolve({name: magnitude})[name]


# -- inputs ------------------------------------------------------------------------------------------
def identification_input(duration: float = 1.0, amplitude: float = 150.0) -> Callable[[float], float]:
    """The identification command: rig.py's linear sine sweep 4 → 14 Hz stretched over
    ``duration`` (whole cycles, 0 at both ends when 9·duration is an integer)."""
    def sweep(t):
        return sine_sweep(t, amplitude=amplitude, duration=duration)
    sweep.__name__ = "sweep"
    return sweep


def validation_input(duration: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A different input for validation: the command of rig.py's closed-loop PD controller
    (smoothed steps of the reference) on the ideal rig, recorded and replayed open loop (the
    same for every record of a duration: simulated once per process)."""
    t, u = _pd_command(float(duration))
    return t.copy(), u.copy()


@functools.lru_cache(maxsize=8)
def _pd_command(duration: float) -> tuple[np.ndarray, np.ndarray]:
    steps = (0.05, 0.35, 0.65)
    times = tuple(s * duration for s in steps)
    from .rig import PDController, smoothed_steps

    rise = 0.12 * duration
    ctrl = PDController(reference=lambda t: smoothed_steps(t, times=times, rise=rise),
                        reference_rate=lambda t: smoothed_steps(t, times=times, rise=rise, derivative=True))
    return pd_validation_input(RigSettings.ideal(), duration=duration, controller=ctrl)


# -- the simulator -------------------------------------------------------------------------------------
def relative_size(data: Measurements, truth: Mapping[str, Any]) -> float:
    """RMS of the residual the nominal equations of motion leave at the truth (both masses) over
    the RMS of the command: the size of the withheld effects, of a record ``(data, truth)`` of
    :func:`simulate_effect_rig`."""
    miss = truth["structural_residual"]
    return float(np.sqrt(np.mean(np.sum(miss ** 2, axis=1))) / np.sqrt(np.mean(data.channels["u"] ** 2)))


def _dead_zone(d, delta):
    return d - np.clip(d, -delta, delta)


def effect_plant(parameters: Mapping[str, float], effects: Mapping[str, Mapping[str, float]]) -> TwoInertia:
    """The rig's :class:`~manipulators.rig.TwoInertia` right-hand side with ``effects`` (name →
    parameter dict, missing keys from :data:`EFFECT_DEFAULTS`) as its friction, spring and input
    hooks; ``parameters`` override :data:`NOMINAL`.  With no effects it is the nominal system
    (the input hook still makes ``u = 0`` for ``t < 0``)."""
    p = dict(NOMINAL, **parameters)
    e = {k: dict(EFFECT_DEFAULTS[k], **v) for k, v in effects.items()}
    k = p["k"]

    def body_friction(i: int, v: float) -> float:
        out = 0.0
        if f"coulomb_m{i}" in e:
            c = e[f"coulomb_m{i}"]
            out += smooth_coulomb(v, c["f"], c["v_s"])
        if f"viscous_m{i}" in e:
            out += viscous(v, e[f"viscous_m{i}"]["b_v"])
        if f"stribeck_m{i}" in e:
            c = e[f"stribeck_m{i}"]
            out += stribeck(v, c["f_c"], c["f_s"], c["v_st"], c["v_s"])
        return float(out)

    def friction(t, v):
        return body_friction(1, v[0]), body_friction(2, v[1])

    def elastic(d: float) -> float:
        out = k * (_dead_zone(d, e["backlash"]["delta"]) if "backlash" in e else d)
        if "cubic_spring" in e:
            out += e["cubic_spring"]["k3"] * d ** 3
        return float(out)

    def applied(u_cmd: Callable[[float], float], t: float) -> float:
        if "input_delay" in e:
            t = t - e["input_delay"]["delay"]
        u = u_cmd(t) if t >= 0.0 else 0.0
        if "input_gain" in e:
            u = e["input_gain"]["gain"] * u
        if "input_saturation" in e:
            lim = e["input_saturation"]["limit"]
            u = min(max(u, -lim), lim)
        if "input_offset" in e:
            u = u + e["input_offset"]["offset"]
        return float(u)

    return TwoInertia(p["m1"], p["m2"], k, p["b"], friction=friction, elastic=elastic, input=applied)


def simulate_effect_rig(effects: Mapping[str, Mapping[str, float] | float | str] | None = None,
                        input: Any = "sweep", duration: float = 1.0, noise: float = 0.01, seed: int = 0,
                        parameters: Mapping[str, float] | None = None, sample_rate: float = 1000.0,
                        initial_state=(0.0, 0.0, 0.0, 0.0)) -> tuple[Measurements, dict]:
    """Simulate the two-inertia rig with the given effects on ``[0, duration]``, as
    ``(data, truth)``: the measured channels ``u``, ``s1``, ``s2`` and the noise-free truth — the
    encoder channels (``s1``, ``s2``), ``states`` (K, 4: s1, s2, v1, v2), the applied torque
    ``u_applied``, the ``accelerations`` (K, 2), the ``structural_residual`` (K, 2: what the
    nominal equations of motion leave per mass; :func:`relative_size`), ``effects`` (name ->
    parameters), ``parameters`` (the two-inertia system's) and ``noise_std`` (channel -> the
    noise's standard deviation).

    ``effects``: name → parameter dict (missing keys from :data:`EFFECT_DEFAULTS`), or a
    magnitude name / number (:func:`effect_parameters`).  ``input``: ``"sweep"``
    (:func:`identification_input`), ``"pd"`` (:func:`validation_input`), a callable ``u(t)``, an
    array on the sample times, or a ``(t, u)`` tuple (linear interpolation).  ``noise``: relative
    encoder noise (module docstring).  ``parameters`` override :data:`NOMINAL`.
    """
    eff = _resolve(effects)
    n = int(round(duration * sample_rate))
    t = np.arange(n + 1) / sample_rate
    knots = np.empty(0)           # the kinks of a piecewise-linear input
    if isinstance(input, str):
        if input == "sweep":
            fn = identification_input(duration)
        elif input == "pd":
            knots, ui = validation_input(duration)
            fn = _interp(knots, ui)
        else:
            raise ValueError(f"unknown input {input!r}: 'sweep', 'pd', a callable, an array or (t, u)")
    elif callable(input):
        fn = input
    elif isinstance(input, tuple) and len(input) == 2:
        fn, knots = _interp(*input), np.asarray(input[0], dtype=float)
    else:
        u_arr = np.asarray(input, dtype=float)
        if u_arr.shape != t.shape:
            raise ValueError(f"an array input needs one value per sample ({t.size}), got {u_arr.shape}")
        fn, knots = _interp(t, u_arr), t
    rig = effect_plant(parameters or {}, eff)
    f = rig.driven(fn)
    X = _integrate(f, t, np.asarray(initial_state, dtype=float), knots, max_step=1.0 / sample_rate)
    u = np.array([float(fn(tt)) for tt in t])
    ua = np.array([rig.applied(fn, tt) for tt in t])
    # the structural residual at the truth: what the nominal equations of motion leave, per mass
    # (ξ = E z − f − F ζ of the rows mass1, mass2 of manipulators.flexible with the true states,
    # accelerations and parameters, and the recorded command)
    f_nominal = effect_plant(parameters or {}, {}).driven(fn)
    acc = np.array([f(tt, x)[2:] for tt, x in zip(t, X)])
    miss = (np.array([f_nominal(tt, x)[2:] for tt, x in zip(t, X)]) - acc) * [rig.m1, rig.m2]
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    meas, std = {}, {}
    for j, ch in enumerate(("s1", "s2")):
        sd = float(noise) * float(np.std(X[:, j]))
        std[ch] = sd
        meas[ch] = X[:, j] + (rng.normal(0.0, sd, size=t.size) if sd > 0 else 0.0)
    from shootlab.estimation.data import Measurements     # here: importing the rig needs no torch
    return Measurements(t, dict(u=u, s1=meas["s1"], s2=meas["s2"])), dict(
        s1=X[:, 0], s2=X[:, 1], states=X, u_applied=ua, accelerations=acc, structural_residual=miss,
        effects=eff, parameters=dict(NOMINAL, **(parameters or {})), noise_std=std)


def _integrate(f: Callable, t: np.ndarray, x0: np.ndarray, knots: np.ndarray, max_step: float) -> np.ndarray:
    """The states (len(t), len(x0)) of ``x' = f(t, x)`` at the times t, by DOP853 at rtol 1e-10,
    from one knot of a piecewise-linear input to the next: no step straddles a kink of the input.
    (On the PD command, 1,001 knots, one integration over [0, 1] had rejected 5,300 of 9,600 steps
    and taken 2.1 s a record; knot to knot 0.4 s, and its error against a solution at rtol 1e-13
    1e-9 relative instead of 6e-7.)"""
    def solve(a: float, b: float, x: np.ndarray, t_eval: np.ndarray | None = None):
        sol = solve_ivp(f, (a, b), x, t_eval=t_eval, method="DOP853", rtol=1e-10, atol=1e-12, max_step=max_step)
        if not sol.success:  # pragma: no cover
            raise RuntimeError(f"effect rig integration failed on [{a:g}, {b:g}]: {sol.message}")
        return sol.y.T

    inner = knots[(knots > t[0]) & (knots < t[-1])]
    if not inner.size:
        return solve(t[0], t[-1], x0, t_eval=t).copy()
    edges = np.union1d(inner, t)
    out = np.empty((edges.size, x0.size))
    out[0] = x0
    for i, (a, b) in enumerate(zip(edges[:-1], edges[1:]), start=1):
        out[i] = solve(a, b, out[i - 1])[-1]
    return out[np.searchsorted(edges, t)]


def _interp(ti, ui) -> Callable[[float], float]:
    ti, ui = np.asarray(ti, dtype=float), np.asarray(ui, dtype=float)

    def fn(tt):
        return float(np.interp(tt, ti, ui))
    return fn
