"""Helpers shared by tests/engine and tests/apps; they use the engine alone (``tests/conftest.py``
puts this folder on the import path)."""
from __future__ import annotations

import warnings

import numpy as np
import torch
from scipy.integrate import solve_ivp

import shootlab
from shootlab.bvp.shooting import ShootingSystem
from shootlab.estimation.data import Measurements


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


# -- a user's pendulum, J θ'' + b θ' + k sin θ = u, declared as docs/your_own_model.md shows, on records
# -- that scipy's Radau makes (also the records of benchmarks/free_run_windows.py) ------------------------
#: J θ'' + b θ' + k sin θ = u: the truth's inertia, damping and gravity stiffness
TRUTH = dict(J=0.2, b=0.1, k=2.0)


def pendulum():
    """The model, with its initial values J = 0.5, b = 0.5, k = 5 (not the truth)."""
    return shootlab.model(
        name="pendulum", states={"th": "w", "w": "al"}, inputs=["al", "u"],
        parameters={"J": 0.5, "b": 0.5, "k": 5.0},
        equations={"motion": lambda x: x.J * x.al + x.b * x.w + x.k * torch.sin(x.th) - x.u,
                   "angle": lambda x: x.th, "torque": lambda x: x.u},
        channels={"angle": "angle", "torque": "torque"}, bounds={"J": (0.0, float("inf"))},
        mechanics={"motion": "motion", "velocity": "w", "command": "torque"})


def torque(t: np.ndarray, validation: bool) -> np.ndarray:
    """A three-line multisine (identification) or a chirp of growing amplitude (validation)."""
    if validation:
        return (0.3 + 0.1 * t) * np.sin(0.5 * t + 0.25 * t ** 2)
    return 0.8 * np.sin(2.1 * t) + 0.5 * np.sin(4.7 * t + 0.5) + 0.3 * np.sin(9.3 * t + 1.0)


def friction(w: np.ndarray, law: str) -> np.ndarray:
    """Dry friction that switches over tanh(ω/0.01), narrower than the library's smooth sign:
    none, Coulomb's 0.1, or Stribeck's hump 0.08 + 0.32 exp(−|ω|/0.1), decaying exponentially."""
    if law == "none":
        return 0.0 * w
    if law == "coulomb":
        return 0.1 * np.tanh(w / 0.01)
    return (0.08 + 0.32 * np.exp(-np.abs(w) / 0.1)) * np.tanh(w / 0.01)


def friction_record(law: str, validation: bool, seed: int) -> Measurements:
    """12 s at 50 Hz from rest with :func:`friction` ``law``, 1 % noise on the angle, 0.01 N m on
    the torque."""
    J, b, k = TRUTH["J"], TRUTH["b"], TRUTH["k"]

    def rhs(t, x):
        return [x[1], (torque(t, validation) - b * x[1] - k * np.sin(x[0]) - friction(x[1], law)) / J]
    t = np.arange(0.0, 12.0 + 1e-9, 0.02)
    run = solve_ivp(rhs, (0.0, 12.0), [0.0, 0.0], t_eval=t, method="Radau", rtol=1e-10, atol=1e-12, max_step=0.005)
    rng = np.random.default_rng(seed)
    return Measurements(t, {"angle": run.y[0] + 0.01 * np.std(run.y[0]) * rng.standard_normal(t.size),
                            "torque": torque(t, validation) + 0.01 * rng.standard_normal(t.size)})
