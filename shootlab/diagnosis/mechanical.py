"""Effects for any mechanical model: friction, spring and actuator candidates built from what the
model names — each axis's equation of motion and velocity, the measured command and, where there
is one, a deflection and its stiffness (``docs/diagnosis.md``, "Your own mechanical model").

Sign conventions.  An equation of motion is a model row ``0 = g(x, ζ)``; its *orientation* ``o`` is
the sign of ∂g/∂(velocity') — +1 for ``m a + b v − u`` — so a force opposing the motion enters as
``+ o · friction``.  The command enters the row with the coefficient ``c = ∂g/∂u`` (−1 above); an
effect that changes the applied command from ``u`` to ``ũ(u)`` adds ``c (ũ − u)``::

    coulomb          + o f σ(v; v_s)                            σ: smooth sign (:func:`smooth_sign`)
    viscous          + o b_v v
    stribeck         + o (f_c σ(v; v_s) + (f_s − f_c) e^{−(v/v_st)²} σ(v; v_h)),  v_h = v_st v_s/(v_st + v_s)
    backlash         spring k Δ → k dz(Δ; δ), dz = Δ − clip(Δ, ±δ)   (C¹ clip, :func:`smooth_clip`)
    cubic_spring     spring k Δ → k Δ + k3 Δ³
    input_gain       ũ = (1 + e) u            (reads the measured command)
    input_offset     ũ = u + c₀
    input_saturation ũ = clip(u, ±L)          (C¹ clip)
    input_delay      ũ = u(t − τ)

An axis with a ``tag`` suffixes its effects' names (``coulomb_m1``) and numbers its parameters
(``coulomb1_f``); a single untagged axis gives ``coulomb`` with ``coulomb_f``.

Units (:attr:`.effects.Effect.units`), from the model's: a friction level, a Stribeck level, the
cubic spring's k3 Δ³ are in the unit R of the equation of motion (so b_v in R per velocity unit,
k3 in R per deflection unit cubed), the Stribeck velocity in the velocity's unit, the backlash
width in the deflection's, an input offset and saturation limit in the command's (the command
enters its row with a pure-number coefficient), the delay in the unit of t; the gain error is
dimensionless (:func:`unit_product` composes them).  A library for a two-mass system (the
report's flexible manipulator) is this one for each of its masses and its spring.

A declared model (:func:`shootlab.model` with ``mechanics=``) gets :func:`mechanical_library`:
the orientation and the command coefficient are probed from its rows at compile time, the smooth
sign's half-width ``v_s`` is a fraction of the velocity's typical size on the record (or declared).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from fractions import Fraction
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

from shootlab.estimation.model import IdentificationModel
from .effects import Effect, Library
from .composition import Vars
from shootlab.estimation.mechanics import Mechanics

__all__ = ["smooth_sign", "smooth_clip", "Axis", "Command", "Spring", "mechanical_effects", "mechanical_library",
           "Mechanics", "FRICTION_WIDTH", "unit_product"]

#: the smooth sign's half-width as a fraction of the velocity's RMS on the record (a declared
#: model's default; ``mechanics={"friction_width": …}`` sets v_s itself)
FRICTION_WIDTH = 0.05

#: a Coulomb level's physical range: friction opposes the motion, and a negative level, which pushes
#: it, stands in for another velocity dependence (Stribeck's levels likewise, and its static level at
#: least its Coulomb level: :attr:`.effects.Effect.physical`)
DISSIPATIVE = (0.0, math.inf)

#: Stribeck friction started from a Coulomb estimate f: f_c = (1 − HUMP) f, f_s = (1 + HUMP) f
HUMP = 0.3


def smooth_sign(v: Tensor, v_s: float) -> Tensor:
    """σ(v; v_s) = v/v_s + sin(π v/v_s)/π for |v| < v_s, sign(v) beyond: C², slope 2/v_s at 0
    (the report's "sinusoidal acceleration" transition, §4.3)."""
    z = v / v_s
    inner = z + torch.sin(math.pi * z) / math.pi
    return torch.where(z.abs() < 1.0, inner, torch.sign(z))


def smooth_clip(x: Tensor, limit, width: float = 0.1) -> Tensor:
    """C¹ clip of ``x`` to ±``limit``: identity for |x| ≤ (1 − w) limit, constant beyond
    (1 + w) limit, a quadratic blend between (value and slope continuous)."""
    z = x / limit
    a = z.abs()
    lo, hi = 1.0 - width, 1.0 + width
    blend = a - (a - lo) ** 2 / (4.0 * width)
    inner = torch.where(a <= lo, a, torch.where(a >= hi, torch.ones_like(a), blend))
    return limit * torch.sign(z) * inner


_POWERS = {"²": 2, "³": 3, "⁴": 4}
_WRITTEN = {Fraction(2): "²", Fraction(3): "³", Fraction(4): "⁴", Fraction(1, 2): "^½"}
_TOKEN = re.compile(r"([^\s^²³⁴/]+)(?:\^(½|-?\d+(?:/\d+)?)|([²³⁴]))?")


def _read_unit(unit: str) -> dict[str, Fraction] | None:
    """A unit as symbol → exponent: ``"N s/m"`` → {N: 1, s: 1, m: −1}, ``"V^½/s"``, ``"m/s²"``;
    ``"-"`` (dimensionless) → {}; None for a form it does not read (brackets, two slashes)."""
    unit = unit.strip()
    if unit in ("-", "1"):
        return {}
    if not unit or any(c in unit for c in "()[]") or unit.count("/") > 1:
        return None
    out: dict[str, Fraction] = {}
    for part, sign in zip(unit.split("/"), (1, -1)):
        for tok in part.replace("·", " ").replace("*", " ").split():
            m = _TOKEN.fullmatch(tok)
            if m is None:
                return None
            sym, exp, sup = m.groups()
            if sym == "1" and exp is None and sup is None:
                continue
            e = Fraction(1, 2) if exp == "½" else Fraction(exp) if exp else Fraction(_POWERS.get(sup, 1))
            out[sym] = out.get(sym, Fraction(0)) + sign * e
    return {k: v for k, v in out.items() if v != 0}


def _write_unit(powers: Mapping[str, Fraction]) -> str:
    """:func:`_read_unit`'s inverse: ``N s/m``, ``1/rad³``, ``-`` for none."""
    def word(sym: str, e: Fraction) -> str:
        return sym if e == 1 else sym + _WRITTEN.get(e, f"^{e}")
    up = " ".join(word(k, e) for k, e in powers.items() if e > 0)
    down = [word(k, -e) for k, e in powers.items() if e < 0]
    if not up and not down:
        return "-"
    if not down:
        return up
    return f"{up or '1'}/{down[0] if len(down) == 1 else '(' + ' '.join(down) + ')'}"


def unit_product(*factors: tuple[str | None, int]) -> str | None:
    """The unit of a product of powers, ``(unit, exponent)`` each: ``unit_product(("N", 1),
    ("m/s", -1))`` is ``"N s/m"``; None when a factor's unit is unknown (None) or not readable."""
    total: dict[str, Fraction] = {}
    for unit, exp in factors:
        powers = _read_unit(unit) if unit is not None else None
        if powers is None:
            return None
        for k, e in powers.items():
            total[k] = total.get(k, Fraction(0)) + e * exp
    return _write_unit({k: e for k, e in total.items() if e != 0})


def _units(**named: str | None) -> dict[str, str]:
    """The declared ones of ``named`` (a parameter → its unit or None)."""
    return {k: u for k, u in named.items() if u}


@dataclass
class Axis:
    """One equation of motion: its row, its velocity, its orientation ``o`` (module docstring) and
    the smooth sign's half-width ``v_s``; ``viscous``/``coulomb``: offer those candidates (False
    where the model already has the term)."""

    row: str
    velocity: str
    v_s: float
    orientation: float = 1.0
    tag: str = ""
    number: str = ""
    viscous: bool = True
    coulomb: bool = True

    def name(self, effect: str) -> str:
        return f"{effect}_{self.tag}" if self.tag else effect

    def parameter(self, effect: str, what: str) -> str:
        return f"{effect}{self.number}_{what}"


@dataclass
class Command:
    """The measured command ``channel`` and the row it drives with coefficient ``coefficient`` (∂row/∂u)."""

    channel: str
    row: str
    coefficient: float = -1.0


@dataclass
class Spring:
    """A deflection Δ(v) with stiffness parameter ``stiffness``; the spring force k Δ enters each
    row in ``rows`` with its sign."""

    deflection: Callable[[Vars], Tensor]
    stiffness: str
    rows: Sequence[tuple[str, float]]
    label: str = "Δ"
    unit: str | None = None


def _friction(axis: Axis, units: Mapping[str, str]) -> list[Effect]:
    row, vel, vs, o = axis.row, axis.velocity, axis.v_s, axis.orientation
    R, V = units.get(row), units.get(vel)
    var = (f"{vel} (estimated)", lambda v: v[vel], V)
    where = f" on {axis.row}" if axis.tag else ""
    out = []
    if axis.coulomb:
        f = axis.parameter("coulomb", "f")
        out.append(Effect(
            name=axis.name("coulomb"), equations=[row], parameters={f: 0.0}, group=f"dry_{axis.tag}",
            term=lambda v: {row: o * v[f] * smooth_sign(v[vel], vs)}, physical={f: DISSIPATIVE}, scale={f: 1.0},
            variable=var,
            description=f"Coulomb friction{where}: f·σ({vel}; {vs:.3g})", units=_units(**{f: R})))
    if axis.viscous:
        bv = axis.parameter("viscous", "b")
        out.append(Effect(
            name=axis.name("viscous"), equations=[row], parameters={bv: 0.0},
            term=lambda v: {row: o * v[bv] * v[vel]}, scale={bv: 1.0}, variable=var,
            description=f"viscous friction{where}: b_v·{vel}", units=_units(**{bv: unit_product((R, 1), (V, -1))})))
    pc, ps, pv = (axis.parameter("stribeck", w) for w in ("fc", "fs", "vst"))

    def stribeck(v: Vars) -> dict:
        w = v[vel]
        # the hump's own sign no wider than the hump (v_st v_s/(v_st + v_s) < v_st): one ramped over
        # v_s hides a hump narrower than v_s (measured on the independent rig's load, v_st = 0.05
        # in a ramp of 0.1: Coulomb answered with confidence 1.00 on its Stribeck record)
        hump = (v[ps] - v[pc]) * torch.exp(-(w / v[pv]) ** 2) * smooth_sign(w, v[pv] * vs / (v[pv] + vs))
        return {row: o * (v[pc] * smooth_sign(w, vs) + hump)}

    def physical(p: Mapping[str, float]) -> list[str]:
        # dissipative levels, the static one at least the Coulomb one: a level that rises with
        # speed (f_s < f_c) stands in for viscous friction or drag
        out = [f"{q} = {p[q]:.3g} below 0" for q in (pc, ps) if p[q] < 0]
        if p[ps] < p[pc]:
            out.append(f"{ps} = {p[ps]:.3g} below {pc} = {p[pc]:.3g} (friction that rises with speed)")
        return out

    def imitates(p: Mapping[str, float]) -> str | None:
        # dissipative levels rising with speed: viscous friction's shape, up to a speed of about v_st
        return axis.name("viscous") if axis.viscous and 0.0 <= p[ps] < p[pc] else None

    def from_coulomb(nested: str, p: Mapping[str, float]) -> list[dict]:
        # a hump of ±HUMP around the Coulomb level, at each start of v_st (fs = fc would leave v_st
        # without influence: a singular Newton matrix)
        f = p[axis.parameter("coulomb", "f")]
        return [{pc: (1.0 - HUMP) * f, ps: (1.0 + HUMP) * f, pv: s} for s in (2.0 * vs, 1.0 * vs, 5.0 * vs)]
    out.append(Effect(
        name=axis.name("stribeck"), equations=[row], parameters={pc: 0.0, ps: 0.0, pv: 2.0 * vs}, term=stribeck,
        group=f"dry_{axis.tag}", bounds={pv: (0.2 * vs, 50.0 * vs)}, physical=physical, imitates=imitates,
        scale={pc: 1.0, ps: 1.0, pv: vs},
        nests=[axis.name("coulomb")] if axis.coulomb else [], embed=from_coulomb if axis.coulomb else None,
        starts={pv: [1.0 * vs, 5.0 * vs]}, variable=var, units=_units(**{pc: R, ps: R, pv: V}),
        description=f"Stribeck friction{where}: f_c·σ({vel}; {vs:.3g}) + (f_s − f_c) exp(−({vel}/v_st)²)·σ({vel}; v_h)"))
    return out


def _spring(spring: Spring, clip_width: float, units: Mapping[str, str]) -> list[Effect]:
    delta, rows, k = spring.deflection, list(spring.rows), spring.stiffness
    D, R = spring.unit, units.get(rows[0][0])
    var = (f"{spring.label} (estimated)", delta, D)

    def backlash(v: Vars) -> dict:
        dT = -v[k] * smooth_clip(delta(v), v.backlash_delta, clip_width)
        return {r: s * dT for r, s in rows}

    def cubic(v: Vars) -> dict:
        dT = v.cubic_k3 * delta(v) ** 3
        return {r: s * dT for r, s in rows}

    def cubic_range(v: Vars) -> dict:
        # k3 at which the cubic force at the deflection's RMS is 0.1 % ... 100 % of the linear one
        typical = float(v[k].abs().mean()) / max(float(delta(v).pow(2).mean()), 1e-300)
        return {"cubic_k3": (1e-3 * typical, typical)}
    return [
        Effect(name="backlash", equations=[r for r, _ in rows], parameters={"backlash_delta": 1e-3}, term=backlash,
               bounds={"backlash_delta": (1e-6, 0.2)}, scale={"backlash_delta": 1e-3},
               starts={"backlash_delta": [3e-4, 3e-3, 1e-2]}, group="spring", variable=var,
               units=_units(backlash_delta=D), description=f"backlash / dead-zone in the spring: {k}·dz({spring.label}; δ)"),
        Effect(name="cubic_spring", equations=[r for r, _ in rows], parameters={"cubic_k3": 0.0}, term=cubic,
               scale={"cubic_k3": 1e4}, group="spring", variable=var, units=_units(cubic_k3=unit_product((R, 1), (D, -3))),
               nonlinear=cubic_range,
               description=f"hardening (k3 > 0) / softening (k3 < 0) spring: + k3·({spring.label})³")]


def _actuator(cmd: Command, saturation_width: float, units: Mapping[str, str]) -> list[Effect]:
    row, c, u = cmd.row, cmd.coefficient, cmd.channel
    C, T = units.get(u) or units.get(row), units.get("t")      # the coefficient c is a pure number
    uvar = (f"{u} (measured)", lambda v: v.channel(u), C)

    def saturation(v: Vars) -> dict:
        um = v.channel(u)
        return {row: c * (smooth_clip(um, v.saturation_limit, saturation_width) - um)}

    def sat_starts(v: Vars) -> dict:
        top = float(v.channel(u).abs().max())
        return {"saturation_limit": [0.6 * top, 0.75 * top, 0.9 * top]}

    def delay(v: Vars) -> dict:
        return {row: c * (v.channel(u, v.t - v.input_delay) - v.channel(u))}

    def du(v: Vars, h: float = 1e-3) -> Tensor:
        return (v.channel(u, v.t + h) - v.channel(u, v.t - h)) / (2 * h)
    return [
        Effect(name="input_gain", equations=[row], parameters={"input_gain_error": 0.0}, channels=[u],
               term=lambda v: {row: c * v.input_gain_error * v.channel(u)}, scale={"input_gain_error": 0.05},
               variable=uvar, units={"input_gain_error": "-"}, description=f"actuator gain error: applied = (1 + e)·{u}"),
        Effect(name="input_offset", equations=[row], parameters={"input_offset": 0.0},
               term=lambda v: {row: c * v.input_offset * torch.ones_like(v.t)}, scale={"input_offset": 1.0},
               variable=("t", lambda v: v.t, T), units=_units(input_offset=C), description=f"input offset: applied = {u} + c"),
        Effect(name="input_saturation", equations=[row], parameters={"saturation_limit": 100.0}, channels=[u],
               term=saturation, bounds={"saturation_limit": (1e-6, float("inf"))}, scale={"saturation_limit": 10.0},
               starts=sat_starts, variable=uvar, units=_units(saturation_limit=C),
               description=f"input saturation: applied = clip({u}, ±L)"),
        Effect(name="input_delay", equations=[row], parameters={"input_delay": 1e-3}, channels=[u], term=delay,
               bounds={"input_delay": (0.0, 0.05)}, scale={"input_delay": 1e-3}, starts={"input_delay": [3e-3, 1e-2]},
               variable=(f"d{u}/dt (measured)", du, unit_product((C, 1), (T, -1))), units=_units(input_delay=T),
               description=f"input delay: applied = {u}(t − τ)")]


def mechanical_effects(axes: Sequence[Axis], command: Command | None = None, spring: Spring | None = None,
                       clip_width: float = 0.1, saturation_width: float = 0.02,
                       units: Mapping[str, str] | None = None) -> list[Effect]:
    """The candidates of the module docstring for these axes, command and spring.
    ``clip_width``/``saturation_width``: the relative half-width of the C¹ blend of the backlash
    and saturation clips (the saturation's must be narrow: its whole effect lives in the few %
    of the command above the limit).  ``units``: the model's (:attr:`IdentificationModel.units`),
    from which the effects' parameter units follow (module docstring)."""
    units = dict(units or {})
    effects = [e for axis in axes for e in _friction(axis, units)]
    if spring is not None:
        effects += _spring(spring, clip_width, units)
    if command is not None:
        effects += _actuator(command, saturation_width, units)
    return effects


def _typical_speed(model: IdentificationModel, velocity: str, data) -> float | None:
    """The RMS of the velocity's initial approximation on the record (None without data or when
    it is zero everywhere)."""
    if data is None:
        return None
    from shootlab.estimation.data import Measurements
    data = Measurements.coerce(data)
    t = torch.as_tensor(data.t, dtype=torch.float64)
    x0 = model.initial_states(data, t)
    col = x0[:, model.states.index(velocity)]
    col = col[torch.isfinite(col)]
    rms = float(col.pow(2).mean().sqrt()) if col.numel() else 0.0
    return rms if rms > 0 else None


def mechanical_library(model: IdentificationModel, data=None) -> Library:
    """The mechanical library of a model that declares ``mechanics`` (:class:`Mechanics` in its
    settings): one axis, its command, its spring.  ``data``: the record, for the smooth sign's
    half-width (:data:`FRICTION_WIDTH` × the velocity's RMS; 1e-2 without data)."""
    mech = model.settings.mechanics
    if not isinstance(mech, Mechanics):
        raise ValueError(f"model {model.name!r} declares no mechanics (shootlab.model(..., mechanics=...))")
    vs = mech.friction_width
    if vs is None:
        speed = _typical_speed(model, mech.velocity, data)
        vs = FRICTION_WIDTH * speed if speed else 1e-2
    axis = Axis(row=mech.motion, velocity=mech.velocity, v_s=float(vs), orientation=mech.orientation)
    command = Command(mech.command, mech.motion, mech.command_coefficient) if mech.command else None
    spring = None
    if mech.deflection is not None and mech.stiffness is not None:
        d = mech.deflection
        spring = Spring(deflection=lambda v: v[d], stiffness=mech.stiffness, rows=[(mech.motion, mech.orientation)],
                        label=d, unit=model.units.get(d))
    from .estimators import default_estimator
    return Library(name=f"mechanical[{model.name}]",
                   effects=mechanical_effects([axis], command, spring, units=model.units),
                   estimator=default_estimator, initial_state="rest",
                   description="shootlab.diagnosis.mechanical: friction, spring and actuator effects")


