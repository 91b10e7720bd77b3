"""Effects for any mechanical model: friction, spring and actuator candidates built from what the
model names — each axis's equation of motion and velocity, the measured command and, where there
is one, a deflection and its stiffness (``docs/diagnosis.md``, "Your own mechanical model").

Sign conventions.  An equation of motion is a model row ``0 = g(x, ζ)``; its *orientation* ``o`` is
the sign of ∂g/∂(velocity') — +1 for ``m a + b v − u`` — so a force opposing the motion enters as
``+ o · friction``.  The command enters the row with the coefficient ``c = ∂g/∂u`` (−1 above); an
effect that changes the applied command from ``u`` to ``ũ(u)`` adds ``c (ũ − u)``::

    coulomb          + o f σ(v; v_s)                            σ: smooth sign (:func:`smooth_sign`)
    viscous          + o b_v v
    stribeck         + o (f_c + (f_s − f_c) e^{−(v/v_st)²}) σ(v; v_s)
    backlash         spring k Δ → k dz(Δ; δ), dz = Δ − clip(Δ, ±δ)   (C¹ clip, :func:`smooth_clip`)
    cubic_spring     spring k Δ → k Δ + k3 Δ³
    input_gain       ũ = (1 + e) u            (reads the measured command)
    input_offset     ũ = u + c₀
    input_saturation ũ = clip(u, ±L)          (C¹ clip)
    input_delay      ũ = u(t − τ)

An axis with a ``tag`` suffixes its effects' names (``coulomb_m1``) and numbers its parameters
(``coulomb1_f``); a single untagged axis gives ``coulomb`` with ``coulomb_f``.  The flexible
manipulator's library (:mod:`manipulators.effects`) is this one with its two masses and spring.

A declared model (:func:`shootlab.model` with ``mechanics=``) gets :func:`mechanical_library`:
the orientation and the command coefficient are probed from its rows at compile time, the smooth
sign's half-width ``v_s`` is a fraction of the velocity's typical size on the record (or declared).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

from ..estimation import IdentificationModel
from .effects import Effect, Library, Vars

__all__ = ["smooth_sign", "smooth_clip", "Axis", "Command", "Spring", "mechanical_effects", "mechanical_library",
           "Mechanics", "FRICTION_WIDTH", "declared_mechanics"]

#: the smooth sign's half-width as a fraction of the velocity's RMS on the record (a declared
#: model's default; ``mechanics={"friction_width": …}`` sets v_s itself)
FRICTION_WIDTH = 0.05

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


def _friction(axis: Axis) -> list[Effect]:
    row, vel, vs, o = axis.row, axis.velocity, axis.v_s, axis.orientation
    var = (f"{vel} (estimated)", lambda v: v[vel])
    where = f" on {axis.row}" if axis.tag else ""
    out = []
    if axis.coulomb:
        f = axis.parameter("coulomb", "f")
        out.append(Effect(
            name=axis.name("coulomb"), equations=[row], parameters={f: 0.0}, group=f"dry_{axis.tag}",
            term=lambda v: {row: o * v[f] * smooth_sign(v[vel], vs)}, scale={f: 1.0}, variable=var,
            description=f"Coulomb friction{where}: f·σ({vel}; {vs:.3g})"))
    if axis.viscous:
        bv = axis.parameter("viscous", "b")
        out.append(Effect(
            name=axis.name("viscous"), equations=[row], parameters={bv: 0.0},
            term=lambda v: {row: o * v[bv] * v[vel]}, scale={bv: 1.0}, variable=var,
            description=f"viscous friction{where}: b_v·{vel}"))
    pc, ps, pv = (axis.parameter("stribeck", w) for w in ("fc", "fs", "vst"))

    def stribeck(v: Vars) -> dict:
        w = v[vel]
        level = v[pc] + (v[ps] - v[pc]) * torch.exp(-(w / v[pv]) ** 2)
        return {row: o * level * smooth_sign(w, vs)}

    def from_coulomb(nested: str, p: Mapping[str, float]) -> list[dict]:
        # a hump of ±HUMP around the Coulomb level, at each start of v_st (fs = fc would leave v_st
        # without influence: a singular Newton matrix)
        f = p[axis.parameter("coulomb", "f")]
        return [{pc: (1.0 - HUMP) * f, ps: (1.0 + HUMP) * f, pv: s} for s in (2.0 * vs, 1.0 * vs, 5.0 * vs)]
    out.append(Effect(
        name=axis.name("stribeck"), equations=[row], parameters={pc: 0.0, ps: 0.0, pv: 2.0 * vs}, term=stribeck,
        group=f"dry_{axis.tag}", bounds={pv: (0.2 * vs, 50.0 * vs)}, scale={pc: 1.0, ps: 1.0, pv: vs},
        nests=[axis.name("coulomb")] if axis.coulomb else [], embed=from_coulomb if axis.coulomb else None,
        starts={pv: [1.0 * vs, 5.0 * vs]}, variable=var,
        description=f"Stribeck friction{where}: (f_c + (f_s − f_c) exp(−({vel}/v_st)²))·σ({vel}; {vs:.3g})"))
    return out


def _spring(spring: Spring, clip_width: float) -> list[Effect]:
    delta, rows, k = spring.deflection, list(spring.rows), spring.stiffness
    var = (f"{spring.label} (estimated)", delta)

    def backlash(v: Vars) -> dict:
        dT = -v[k] * smooth_clip(delta(v), v["backlash_delta"], clip_width)
        return {r: s * dT for r, s in rows}

    def cubic(v: Vars) -> dict:
        dT = v["cubic_k3"] * delta(v) ** 3
        return {r: s * dT for r, s in rows}
    return [
        Effect(name="backlash", equations=[r for r, _ in rows], parameters={"backlash_delta": 1e-3}, term=backlash,
               bounds={"backlash_delta": (1e-6, 0.2)}, scale={"backlash_delta": 1e-3},
               starts={"backlash_delta": [3e-4, 3e-3, 1e-2]}, group="spring", variable=var,
               description=f"backlash / dead-zone in the spring: {k}·dz({spring.label}; δ)"),
        Effect(name="cubic_spring", equations=[r for r, _ in rows], parameters={"cubic_k3": 0.0}, term=cubic,
               scale={"cubic_k3": 1e4}, group="spring", variable=var,
               description=f"hardening (k3 > 0) / softening (k3 < 0) spring: + k3·({spring.label})³")]


def _actuator(cmd: Command, saturation_width: float) -> list[Effect]:
    row, c, u = cmd.row, cmd.coefficient, cmd.channel
    uvar = (f"{u} (measured)", lambda v: v.channel(u))

    def saturation(v: Vars) -> dict:
        um = v.channel(u)
        return {row: c * (smooth_clip(um, v["saturation_limit"], saturation_width) - um)}

    def sat_starts(v: Vars) -> dict:
        top = float(v.channel(u).abs().max())
        return {"saturation_limit": [0.6 * top, 0.75 * top, 0.9 * top]}

    def delay(v: Vars) -> dict:
        return {row: c * (v.channel(u, v.t - v["input_delay"]) - v.channel(u))}

    def du(v: Vars, h: float = 1e-3) -> Tensor:
        return (v.channel(u, v.t + h) - v.channel(u, v.t - h)) / (2 * h)
    return [
        Effect(name="input_gain", equations=[row], parameters={"input_gain_error": 0.0}, channels=[u],
               term=lambda v: {row: c * v["input_gain_error"] * v.channel(u)}, scale={"input_gain_error": 0.05},
               variable=uvar, description=f"actuator gain error: applied = (1 + e)·{u}"),
        Effect(name="input_offset", equations=[row], parameters={"input_offset": 0.0},
               term=lambda v: {row: c * v["input_offset"] * torch.ones_like(v.t)}, scale={"input_offset": 1.0},
               variable=("t", lambda v: v.t), description=f"input offset: applied = {u} + c"),
        Effect(name="input_saturation", equations=[row], parameters={"saturation_limit": 100.0}, channels=[u],
               term=saturation, bounds={"saturation_limit": (1e-6, float("inf"))}, scale={"saturation_limit": 10.0},
               starts=sat_starts, variable=uvar, description=f"input saturation: applied = clip({u}, ±L)"),
        Effect(name="input_delay", equations=[row], parameters={"input_delay": 1e-3}, channels=[u], term=delay,
               bounds={"input_delay": (0.0, 0.05)}, scale={"input_delay": 1e-3}, starts={"input_delay": [3e-3, 1e-2]},
               variable=(f"d{u}/dt (measured)", du), description=f"input delay: applied = {u}(t − τ)")]


def mechanical_effects(axes: Sequence[Axis], command: Command | None = None, spring: Spring | None = None,
                       clip_width: float = 0.1, saturation_width: float = 0.02) -> list[Effect]:
    """The candidates of the module docstring for these axes, command and spring.
    ``clip_width``/``saturation_width``: the relative half-width of the C¹ blend of the backlash
    and saturation clips (the saturation's must be narrow: its whole effect lives in the few %
    of the command above the limit)."""
    effects = [e for axis in axes for e in _friction(axis)]
    if spring is not None:
        effects += _spring(spring, clip_width)
    if command is not None:
        effects += _actuator(command, saturation_width)
    return effects


@dataclass
class Mechanics:
    """What a declared model names (``shootlab.model(mechanics=…)``), with the signs probed from
    its rows at compile time; kept in ``settings["mechanics"]``."""

    motion: str
    velocity: str
    orientation: float
    command: str | None = None
    command_coefficient: float = -1.0
    deflection: str | None = None
    stiffness: str | None = None
    friction_width: float | None = None


def _typical_speed(model: IdentificationModel, velocity: str, data) -> float | None:
    """The RMS of the velocity's initial approximation on the record (None without data or when
    it is zero everywhere)."""
    if data is None:
        return None
    from ..data import Measurements
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
    mech = model.settings.get("mechanics")
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
                        label=d)
    from ..estimators import default_estimator
    return Library(name=f"mechanical[{model.name}]", effects=mechanical_effects([axis], command, spring),
                   estimator=default_estimator, initial_state="rest",
                   description="shootlab.diagnosis.mechanical: friction, spring and actuator effects")


def declared_mechanics(spec: dict, states: Mapping[str, str], rows, channels: Mapping[str, str], F: Tensor) -> Mechanics:
    """The mechanics a declared model names (:func:`shootlab.model`, ``mechanics=``) checked, with
    the signs the library needs read from its rows' F (samples, r, nζ) at the default parameters:
    the orientation ∂motion/∂velocity' and the command's coefficient ∂motion/∂command.  ``rows``
    is the model's row set (``equations``, ``sizes``, ``x_at``, ``z_at``, ``row_at``,
    ``inputs``: :mod:`shootlab.declarative`)."""
    known = {"motion", "velocity", "command", "deflection", "stiffness", "friction_width"}
    bad = sorted(set(spec) - known)
    if bad:
        raise ValueError(f"mechanics: unknown key(s) {bad}; the keys are {', '.join(sorted(known))}")
    motion, velocity = spec.get("motion"), spec.get("velocity")
    if motion not in rows.equations or motion in channels or motion in rows.sizes:
        raise ValueError(f"mechanics: motion={motion!r} must name a model (not a measurement) row: "
                         f"{', '.join(r for r in rows.equations if r not in channels)}")
    if velocity not in states or states[velocity] not in rows.z_at or not isinstance(rows.x_at[velocity], int):
        raise ValueError(f"mechanics: velocity={velocity!r} must name a state whose derivative is an input "
                         f"(the acceleration), e.g. states={{'s': 'v', 'v': 'a'}}")
    i = rows.row_at[motion]

    def coefficient(j: int, what: str) -> float:
        c = F[:, i, j]
        if not (c > 0).all() and not (c < 0).all():
            raise ValueError(f"mechanics: the row {motion!r} must depend on {what} with one sign at the default "
                             f"parameters (found {c.min().item():.3g} … {c.max().item():.3g})")
        return float(c.mean())
    orientation = math.copysign(1.0, coefficient(rows.z_at[states[velocity]], f"{states[velocity]!r}"))
    out = Mechanics(motion=motion, velocity=velocity, orientation=orientation)
    command = spec.get("command")
    if command is not None:
        row = next((r for r, c in channels.items() if c == command), None)
        drivers = [] if row is None else [j for j in range(len(rows.inputs)) if F[:, rows.row_at[row], j].any()]
        if len(drivers) != 1:
            raise ValueError(f"mechanics: command={command!r} must be the channel of a measurement row that reads "
                             f"one input (as 'force': lambda x: x.u); channels are {', '.join(channels.values())}")
        j = drivers[0]
        out.command = command
        out.command_coefficient = coefficient(j, f"{rows.inputs[j]!r}") / float(F[:, rows.row_at[row], j].mean())
    d, k = spec.get("deflection"), spec.get("stiffness")
    if (d is None) != (k is None):
        raise ValueError("mechanics: deflection and stiffness go together (a spring's state and its parameter)")
    if d is not None:
        if d not in states or k not in rows.x_at or k in states:
            raise ValueError(f"mechanics: deflection={d!r} must be a state and stiffness={k!r} a parameter")
        out.deflection, out.stiffness = d, k
    if spec.get("friction_width") is not None:
        out.friction_width = float(spec["friction_width"])
        if not out.friction_width > 0:
            raise ValueError(f"mechanics: friction_width must be positive, got {spec['friction_width']!r}")
    return out
