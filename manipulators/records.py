"""Example records of the mechanical systems for ``shootlab simulate`` (entry points
``shootlab.records``: ``msd``, ``sweep``, ``pd``; :class:`shootlab.registry.Record`).

Each record declares its options (``shootlab simulate NAME --help`` lists them); its recipe takes
``seed`` and every declared option as keywords and returns the columns, their order and a
one-line description.
"""
from __future__ import annotations

import numpy as np

from shootlab.registry import Option, Record

Table = tuple[dict[str, np.ndarray], list[str], str]

#: the rig's options, shared by ``sweep`` and ``pd``
_EFFECTS = Option("effects", str, "all", choices=("all", "friction", "none"),
                  help="the rig's effects: all (friction with variation, gain error, delay, zero-order hold, "
                       "quantisation, noise), friction (constant smooth Coulomb friction only), none (the linear "
                       "two-mass system)")
_RIG_NOISE = Option("noise", float, None, low=0.0, help="encoder noise std in rad (default the rig's 2e-4; 0 = none)")


def _msd(seed: int, noise: float, duration: float) -> Table:
    from .rig import msd_noisy_data
    duration = float(duration)
    n = int(round(100 * duration)) + 1 if duration > 0 else 0
    if n < 2:
        raise ValueError(f"duration {duration:g}: the msd record is sampled every 0.01, so at least 0.01 is needed")
    t = np.linspace(0.0, duration, n)
    d = msd_noisy_data(level=noise or 0.0, seed=seed, t=t)
    return d, ["t", "u", "s"], f"mass-spring-damper m = b = k = 1, noise {noise or 0:g} x RMS"


def _rig(kind: str, seed: int, noise: float | None, effects: str, duration: float) -> Table:
    from .rig import RigSettings, simulate_rig
    settings = {"all": RigSettings, "friction": RigSettings.friction_only, "none": RigSettings.ideal}[effects]()
    changes = dict(seed=seed)
    if noise is not None:
        changes.update(noise=noise > 0, noise_std=noise)
    d = simulate_rig(settings.replace(**changes), input=kind, duration=duration)
    label = "sine sweep 4-14 Hz (identification)" if kind == "sweep" else "PD tracking command (validation)"
    return (dict(t=d.t, u=d.u, s1=d.s1, s2=d.s2), ["t", "u", "s1", "s2"],
            f"virtual flexible-manipulator rig, {label}, effects {effects}")


def _sweep(seed: int, noise: float | None, effects: str, duration: float) -> Table:
    return _rig("sweep", seed, noise, effects, duration)


def _pd(seed: int, noise: float | None, effects: str, duration: float) -> Table:
    return _rig("pd", seed, noise, effects, duration)


#: the report's mass–spring–damper (§3.4), m = b = k = 1: ``t,u,s`` at 100 Hz
msd = Record(_msd, "mass-spring-damper m = b = k = 1 (report §3.4): t,u,s at 100 Hz", options=(
    Option("noise", float, 0.0, low=0.0, help="noise std as a fraction of each channel's RMS"),
    Option("duration", float, 10.0, low=0.0, strict=True, help="record length in s")))

#: the virtual flexible-manipulator rig under the identification sine sweep: ``t,u,s1,s2``
sweep = Record(_sweep, "virtual flexible-manipulator rig, identification sine sweep 4-14 Hz: t,u,s1,s2", options=(
    _RIG_NOISE, _EFFECTS, Option("duration", float, 1.0, low=0.0, strict=True, help="record length in s")))

#: the virtual rig under a PD controller's tracking command (validation): ``t,u,s1,s2``
pd = Record(_pd, "virtual flexible-manipulator rig under a PD controller's command (validation): t,u,s1,s2",
            options=(_RIG_NOISE, _EFFECTS,
                     Option("duration", float, 1.0, low=0.0, strict=True, help="record length in s")))
