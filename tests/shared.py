"""Helpers shared by tests/engine and tests/apps; they use the engine alone (``tests/conftest.py``
puts this folder on the import path)."""
from __future__ import annotations

import warnings

import numpy as np
import torch
from scipy.integrate import solve_ivp

import shootlab
from shootlab.bvp.shooting import ShootingSystem


# -- interval Jacobians ------------------------------------------------------------------------------------------
def central_differences(system: ShootingSystem, s: torch.Tensor, delta: float = 1e-5) -> torch.Tensor:
    """(m−1, n, n) by central differences of the integrated interval ends."""
    s0 = s[:-1]
    n = s0.shape[1]
    cols = []
    for j in range(n):
        e = torch.zeros(n, dtype=s.dtype)
        e[j] = delta
        plus = system.integrator.integrate(system.prob.rhs, system.t0, system.t1, s0 + e)
        minus = system.integrator.integrate(system.prob.rhs, system.t0, system.t1, s0 - e)
        assert not (plus.failed.any() or minus.failed.any()), (plus.reason, minus.reason)
        cols.append((plus.y - minus.y) / (2 * delta))
    return torch.stack(cols, -1)


def both(prob: shootlab.BVP, t, s, integrator) -> tuple[torch.Tensor, torch.Tensor, ShootingSystem]:
    new = ShootingSystem(prob, t, integrator, jacobian="autograd")
    old = ShootingSystem(prob, t, integrator, jacobian="reverse")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)       # no fallback on these right-hand sides
        Y = new.interval_jacobians(s)
    return Y, old.interval_jacobians(s), new


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


# -- the one-axis drive of docs/your_own_model.md -----------------------------------------------------------------
#: its true parameters
DRIVE = dict(m=2.0, b=0.5, c=0.3)


def drive_record(noise: float, seed: int = 3) -> dict:
    """m a + b v + c = u simulated by scipy on its own right-hand side, 100 Hz for 10 s."""
    t = np.linspace(0.0, 10.0, 1001)

    def u(tt):
        return 0.4 + np.sin(1.3 * tt) + 0.6 * np.sin(3.1 * tt + 1.0) + 0.3 * np.sin(7.0 * tt)
    sol = solve_ivp(lambda tt, x: [x[1], (u(tt) - DRIVE["b"] * x[1] - DRIVE["c"]) / DRIVE["m"]], (0, 10), [0.0, 0.0],
                    t_eval=t, method="DOP853", rtol=1e-12, atol=1e-13)
    rng = np.random.default_rng(seed)
    return {"t": t, "force": u(t) + noise * rng.standard_normal(t.size),
            "position": sol.y[0] + 0.1 * noise * rng.standard_normal(t.size)}


def axis(reverse: bool = False, **mechanics):
    """The drive of docs/your_own_model.md, its motion row written either way round."""
    sign = -1.0 if reverse else 1.0
    return shootlab.model(
        name="axis", states={"s": "v", "v": "a"}, inputs=["a", "u"], parameters={"m": 1.0, "b": 1.0, "c": 0.0},
        equations={"motion": lambda x: sign * (x.m * x.a + x.b * x.v + x.c - 2.0 * x.u),
                   "position": lambda x: x.s, "force": lambda x: x.u},
        channels={"position": "position", "force": "force"},
        mechanics=dict(dict(motion="motion", velocity="v", command="force"), **mechanics))
