"""Example records of the mechanical systems for ``shootlab simulate`` (entry points
``shootlab.records``: ``msd``, ``sweep``, ``pd``; :mod:`shootlab.registry`).

Each recipe takes ``seed`` and the ``simulate`` options given on the command line as keywords
(an option that a recipe does not name is refused there) and returns the columns, their order and
a one-line description.
"""
from __future__ import annotations

import numpy as np

Record = tuple[dict[str, np.ndarray], list[str], str]


def msd(noise: float | None = None, seed: int = 0, duration: float | None = None, **_) -> Record:
    """The report's mass–spring–damper (§3.4), m = b = k = 1: ``t,u,s`` at 100 Hz on [0, 10],
    noise std ``noise`` × the RMS of each channel."""
    from .rig import msd_noisy_data
    duration = 10.0 if duration is None else float(duration)
    n = int(round(100 * duration)) + 1 if duration > 0 else 0
    if n < 2:
        raise ValueError(f"duration {duration:g}: the msd record is sampled every 0.01, so at least 0.01 is needed")
    t = np.linspace(0.0, duration, n)
    d = msd_noisy_data(level=noise or 0.0, seed=seed, t=t)
    return d, ["t", "u", "s"], f"mass-spring-damper m = b = k = 1, noise {noise or 0:g} x RMS"


def sweep(noise: float | None = None, seed: int = 0, effects: str = "all", duration: float | None = None,
          **_) -> Record:
    """The virtual flexible-manipulator rig under the identification sine sweep: ``t,u,s1,s2``."""
    return _rig("sweep", noise, seed, effects, duration)


def pd(noise: float | None = None, seed: int = 0, effects: str = "all", duration: float | None = None,
       **_) -> Record:
    """The virtual rig under a PD controller's tracking command (validation): ``t,u,s1,s2``."""
    return _rig("pd", noise, seed, effects, duration)


def _rig(kind: str, noise: float | None, seed: int, effects: str, duration: float | None) -> Record:
    from .rig import RigSettings, simulate_rig
    settings = {"all": RigSettings, "friction": RigSettings.friction_only, "none": RigSettings.ideal}[effects]()
    changes = dict(seed=seed)
    if noise is not None:
        changes.update(noise=noise > 0, noise_std=noise)
    d = simulate_rig(settings.replace(**changes), input=kind, duration=1.0 if duration is None else duration)
    label = "sine sweep 4-14 Hz (identification)" if kind == "sweep" else "PD tracking command (validation)"
    return (dict(t=d.t, u=d.u, s1=d.s1, s2=d.s2), ["t", "u", "s1", "s2"],
            f"virtual flexible-manipulator rig, {label}, effects {effects}")
