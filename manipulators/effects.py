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

from shootlab.diagnosis import Library, default_estimator, weight_continuation_estimator
from shootlab.diagnosis.mechanical import Axis, Command, Spring, mechanical_effects, smooth_clip
from shootlab.estimation import IdentificationModel

__all__ = ["library", "smooth_clip", "flexible_estimator", "MECHANICAL_EFFECTS"]

MECHANICAL_EFFECTS = ("coulomb_m1", "coulomb_m2", "viscous_m1", "viscous_m2", "stribeck_m1", "stribeck_m2",
                      "backlash", "cubic_spring", "input_gain", "input_offset", "input_saturation", "input_delay")


def flexible_estimator(**options):
    """Weight continuation to the model's V with the encoder rows capped at 1/σ̂² (module docstring)."""
    return weight_continuation_estimator(noise_weights=True, **options)


def library(model: IdentificationModel | None = None, v_s=(0.1, 1.0), u_channel: str = "u",
            stiffness: str = "k", clip_width: float = 0.1, saturation_width: float = 0.02) -> Library:
    """The mechanical library for ``model`` (the flexible manipulator by default; the msd).

    ``v_s``: the smooth-sign half-widths of the friction candidates per mass (the report's 0.1
    and 1.0 rad/s); ``u_channel``: the measured command; ``stiffness``: the spring parameter;
    ``clip_width``, ``saturation_width``: see :func:`shootlab.diagnosis.mechanical.mechanical_effects`."""
    if model is None:
        from .flexible import plain_model
        model = plain_model()
    have = set(model.parameters)
    eq = model.equations
    if "mass1" in eq and "mass2" in eq:
        kind = "flexible"
        axes = [Axis(row=f"mass{i}", velocity=f"v{i}", v_s=float(v_s[min(i - 1, len(v_s) - 1)]), tag=f"m{i}",
                     number=str(i), coulomb=f"f{i}" not in have) for i in (1, 2)]
        spring = Spring(deflection=lambda v: v.s2 - v.s1, stiffness=stiffness,
                        rows=[("mass1", -1.0), ("mass2", 1.0)], label="s2 − s1", unit=model.units.get("s1"))
        command = Command(u_channel, "mass2", -1.0)
    elif "motion" in eq:
        kind = "msd"        # one mass; no viscous candidate — it is the model's own b
        axes = [Axis(row="motion", velocity="v", v_s=float(v_s[0]), tag="m1", number="1", viscous=False,
                     coulomb="f1" not in have)]
        spring = Spring(deflection=lambda v: v.s, stiffness=stiffness, rows=[("motion", 1.0)], label="s",
                        unit=model.units.get("s"))
        command = Command(u_channel, "motion", -1.0)
    else:
        raise ValueError(f"model {model.name!r}: no equations of motion the mechanical library knows "
                         f"(mass1/mass2 or motion); rows are {eq}")
    effects = mechanical_effects(axes, command, spring, clip_width, saturation_width, units=model.units)
    estimator = flexible_estimator() if kind == "flexible" else default_estimator
    return Library(name=f"mechanical[{kind}]", effects=effects, estimator=estimator, initial_state="rest",
                   description="manipulators.effects: friction, spring and actuator effects")
