"""The mechanical candidate library for :mod:`shootlab.diagnosis`.

Effects a two-inertia manipulator (:mod:`manipulators.flexible`) or the mass–spring–damper
(:mod:`manipulators.msd`) may lack, each written as the term it adds to the model side of the
equations of motion (sign conventions of :mod:`manipulators.rig`: friction opposes the motion,
the spring torque ``T = k (s2 − s1) + b (v2 − v1)`` acts on mass 1 with ``+`` and on mass 2 with
``−``; the applied command enters mass 2's equation)::

    coulomb_m{i}      + f σ(v_i; v_s)                          mass i   σ: smooth sign (friction.py)
    viscous_m{i}      + b_v v_i                                mass i   (absolute damping; the model's
                                                                         b is relative)
    stribeck_m{i}     + (f_c + (f_s − f_c) e^{−(v_i/v_st)²}) σ(v_i; v_s)
    backlash          spring k Δ → k dz(Δ; δ), dz = Δ − clip(Δ, ±δ)  (C¹ clip)   both masses
    cubic_spring      spring k Δ → k Δ + k3 Δ³                                  both masses
    input_gain        applied = (1 + e) u                      mass 2   (reads the measured u)
    input_offset      applied = u + c                          mass 2
    input_saturation  applied = clip(u, ±L)                    mass 2   (C¹ clip, reads u)
    input_delay       applied = u(t − τ)                       mass 2   (reads u at t − τ)

with Δ = s2 − s1 (the msd: Δ = s, one mass, no viscous candidate — it is the model's own b).
New parameters: ``coulomb{i}_f``, ``viscous{i}_b``, ``stribeck{i}_fc``, ``stribeck{i}_fs``,
``stribeck{i}_vst``, ``backlash_delta``, ``cubic_k3``, ``input_gain_error``, ``input_offset``,
``saturation_limit``, ``input_delay``.

Identifiability.  Everything in these models is per unit motor constant: a pure actuator gain
error is absorbed exactly by scaling m1, m2, k, b (and any friction) — it leaves no residual
unless one parameter is known (e.g. the end-effector inertia m1 held by a prior W_a, as in the
benchmark).  Parameters with a prior (W_a > 0) are held in the diagnosis' regression.

The flexible family's estimator (:func:`flexible_estimator`) reaches the model's measurement
weights by continuation (as :func:`manipulators.chapter4.identify_plain` does) and caps the
encoder rows at 1/σ̂² (σ̂ the encoder noise estimated from the data): the report's V = 1e9 on the
encoders assumes ~3e-5 rad of noise; on noisier data the last stage does not converge (measured:
100 iterations without convergence at 1 % noise).
"""
from __future__ import annotations

import torch
from torch import Tensor

from shootlab.diagnosis import Effect, Library, default_estimator, weight_continuation_estimator
from shootlab.estimation import IdentificationModel

from .friction import smooth_sign

__all__ = ["library", "smooth_clip", "flexible_estimator", "MECHANICAL_EFFECTS"]

MECHANICAL_EFFECTS = ("coulomb_m1", "coulomb_m2", "viscous_m1", "viscous_m2", "stribeck_m1", "stribeck_m2",
                      "backlash", "cubic_spring", "input_gain", "input_offset", "input_saturation", "input_delay")


def smooth_clip(x: Tensor, limit, width: float = 0.1) -> Tensor:
    """C¹ clip of ``x`` to ±``limit``: identity for |x| ≤ (1 − w) limit, constant beyond
    (1 + w) limit, a quadratic blend between (value and slope continuous)."""
    z = x / limit
    a = z.abs()
    lo, hi = 1.0 - width, 1.0 + width
    blend = a - (a - lo) ** 2 / (4.0 * width)
    inner = torch.where(a <= lo, a, torch.where(a >= hi, torch.ones_like(a), blend))
    return limit * torch.sign(z) * inner


def flexible_estimator(**options):
    """Weight continuation to the model's V with the encoder rows capped at 1/σ̂² (module docstring)."""
    return weight_continuation_estimator(noise_weights=True, **options)


def _layout(model: IdentificationModel) -> dict:
    eq = model.equations
    if "mass1" in eq and "mass2" in eq:
        return dict(kind="flexible", masses=[("m1", "mass1", "v1"), ("m2", "mass2", "v2")],
                    delta=lambda v: v["s2"] - v["s1"], delta_label="s2 − s1",
                    spring_rows=[("mass1", -1.0), ("mass2", 1.0)], input_row=("mass2", -1.0), viscous=True)
    if "motion" in eq:
        return dict(kind="msd", masses=[("m1", "motion", "v")], delta=lambda v: v["s"], delta_label="s",
                    spring_rows=[("motion", 1.0)], input_row=("motion", -1.0), viscous=False)
    raise ValueError(f"model {model.name!r}: no equations of motion the mechanical library knows "
                     f"(mass1/mass2 or motion); rows are {eq}")


def library(model: IdentificationModel | None = None, v_s=(0.1, 1.0), u_channel: str = "u",
            stiffness: str = "k", clip_width: float = 0.1, saturation_width: float = 0.02) -> Library:
    """The mechanical library for ``model`` (the flexible manipulator by default).

    ``v_s``: the smooth-sign half-widths of the friction candidates per mass (the report's 0.1
    and 1.0 rad/s); ``u_channel``: the measured command; ``stiffness``: the spring parameter;
    ``clip_width``, ``saturation_width``: the relative half-width of the C¹ blend of the backlash
    and saturation clips (the saturation's must be narrow: its whole effect lives in the few %
    of the command above the limit)."""
    if model is None:
        from .flexible import plain_model
        model = plain_model()
    lay = _layout(model)
    effects: list[Effect] = []
    have = set(model.parameters)
    for idx, (tag, row, vel) in enumerate(lay["masses"]):
        i = idx + 1
        vs = float(v_s[min(idx, len(v_s) - 1)]) if lay["kind"] == "flexible" else float(v_s[0])
        var = (f"{vel} (estimated)", lambda v, _vel=vel: v[_vel])
        if not ({f"f{i}"} & have):          # the friction model already has Coulomb friction
            p = f"coulomb{i}_f"
            effects.append(Effect(
                name=f"coulomb_{tag}", equations=[row], parameters={p: 0.0}, group=f"dry_{tag}",
                term=lambda v, _p=p, _r=row, _vel=vel, _vs=vs: {_r: v[_p] * smooth_sign(v[_vel], _vs)},
                description=f"Coulomb friction on mass {i}: f·σ({vel}; {vs:g})", scale={p: 1.0}, variable=var))
        if lay["viscous"]:
            p = f"viscous{i}_b"
            effects.append(Effect(
                name=f"viscous_{tag}", equations=[row], parameters={p: 0.0},
                term=lambda v, _p=p, _r=row, _vel=vel: {_r: v[_p] * v[_vel]},
                description=f"viscous friction on mass {i} (absolute): b_v·{vel}", scale={p: 1.0}, variable=var))
        pc, ps, pv = f"stribeck{i}_fc", f"stribeck{i}_fs", f"stribeck{i}_vst"

        def stribeck(v, _pc=pc, _ps=ps, _pv=pv, _r=row, _vel=vel, _vs=vs):
            w = v[_vel]
            level = v[_pc] + (v[_ps] - v[_pc]) * torch.exp(-(w / v[_pv]) ** 2)
            return {_r: level * smooth_sign(w, _vs)}
        effects.append(Effect(
            name=f"stribeck_{tag}", equations=[row], parameters={pc: 0.0, ps: 0.0, pv: 2.0 * vs}, term=stribeck,
            group=f"dry_{tag}", bounds={pv: (0.2 * vs, 50.0 * vs)}, scale={pc: 1.0, ps: 1.0, pv: vs},
            nests=[f"coulomb_{tag}"] if not ({f"f{i}"} & have) else [],
            starts={pv: [1.0 * vs, 5.0 * vs]}, variable=var,
            description=f"Stribeck friction on mass {i}: (f_c + (f_s − f_c) exp(−({vel}/v_st)²))·σ({vel}; {vs:g})"))
    delta, rows = lay["delta"], lay["spring_rows"]
    dvar = (f"{lay['delta_label']} (estimated)", delta)

    def backlash(v):
        dT = -v[stiffness] * smooth_clip(delta(v), v["backlash_delta"], clip_width)
        return {r: s * dT for r, s in rows}
    effects.append(Effect(
        name="backlash", equations=[r for r, _ in rows], parameters={"backlash_delta": 1e-3}, term=backlash,
        bounds={"backlash_delta": (1e-6, 0.2)}, scale={"backlash_delta": 1e-3},
        starts={"backlash_delta": [3e-4, 3e-3, 1e-2]}, group="spring", variable=dvar,
        description=f"backlash / dead-zone in the spring: {stiffness}·dz({lay['delta_label']}; δ)"))

    def cubic(v):
        dT = v["cubic_k3"] * delta(v) ** 3
        return {r: s * dT for r, s in rows}
    effects.append(Effect(
        name="cubic_spring", equations=[r for r, _ in rows], parameters={"cubic_k3": 0.0}, term=cubic,
        scale={"cubic_k3": 1e4}, group="spring", variable=dvar,
        description=f"hardening (k3 > 0) / softening (k3 < 0) spring: + k3·({lay['delta_label']})³"))
    row, sign = lay["input_row"]
    u = u_channel
    uvar = (f"{u} (measured)", lambda v: v.channel(u))
    effects.append(Effect(
        name="input_gain", equations=[row], parameters={"input_gain_error": 0.0}, channels=[u],
        term=lambda v: {row: sign * v["input_gain_error"] * v.channel(u)}, scale={"input_gain_error": 0.05},
        variable=uvar, description=f"actuator gain error: applied = (1 + e)·{u}"))
    effects.append(Effect(
        name="input_offset", equations=[row], parameters={"input_offset": 0.0},
        term=lambda v: {row: sign * v["input_offset"] * torch.ones_like(v.t)}, scale={"input_offset": 1.0},
        variable=("t", lambda v: v.t), description=f"input offset: applied = {u} + c"))

    def saturation(v):
        um = v.channel(u)
        return {row: sign * (smooth_clip(um, v["saturation_limit"], saturation_width) - um)}

    def sat_starts(v):
        top = float(v.channel(u).abs().max())
        return {"saturation_limit": [0.6 * top, 0.75 * top, 0.9 * top]}
    effects.append(Effect(
        name="input_saturation", equations=[row], parameters={"saturation_limit": 100.0}, channels=[u],
        term=saturation, bounds={"saturation_limit": (1e-6, float("inf"))}, scale={"saturation_limit": 10.0},
        starts=sat_starts, variable=uvar, description=f"input saturation: applied = clip({u}, ±L)"))

    def delay(v):
        return {row: sign * (v.channel(u, v.t - v["input_delay"]) - v.channel(u))}

    def du(v, h=1e-3):
        return (v.channel(u, v.t + h) - v.channel(u, v.t - h)) / (2 * h)
    effects.append(Effect(
        name="input_delay", equations=[row], parameters={"input_delay": 1e-3}, channels=[u], term=delay,
        bounds={"input_delay": (0.0, 0.05)}, scale={"input_delay": 1e-3}, starts={"input_delay": [3e-3, 1e-2]},
        variable=(f"d{u}/dt (measured)", du), description=f"input delay: applied = {u}(t − τ)"))
    estimator = flexible_estimator() if lay["kind"] == "flexible" else default_estimator
    return Library(name=f"mechanical[{lay['kind']}]", effects=effects, estimator=estimator, initial_state="rest",
                   description="manipulators.effects: friction, spring and actuator effects")
