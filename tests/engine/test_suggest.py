"""suggest_shooting_points: the stability functions of the integrators against their one-step maps,
the real stability limits, and the rule on a dichotomic pair."""
from __future__ import annotations
import math

import numpy as np
import pytest
import torch

import shootlab
from shootlab.bvp.suggest import stability_function, suggest_shooting_points

f64 = torch.float64


def diagonal_bvp(kappa: float) -> shootlab.BVP:
    """x1' = −κ x1, x2' = κ x2, x1(0) = 1, x2(1) = 1: eigenvalues ±κ (a dichotomic pair)."""
    return shootlab.BVP(lambda t, x: torch.stack([-kappa * x[..., 0], kappa * x[..., 1]], -1),
                        lambda xa: xa[:1] - 1.0, lambda xb: xb[1:] - 1.0)


def real_limit(name: str) -> float:
    R, _ = stability_function(name)
    lo, hi = 0.1, 10.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if abs(R(-mid)) <= 1 else (lo, mid)
    return lo


# -- the rule --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["euler", "rk4", "rkf45", "implicit_euler", "midpoint", "radau3"])
def test_stability_function_is_the_integrators_one_step_map(name):
    R, _ = stability_function(name)
    integ = shootlab.get_integrator(name, steps=1)
    for z in (-0.5, -2.0, -2.6, -7.0, 0.7):
        y = integ.integrate(lambda t, x: z * x, torch.zeros(1, dtype=f64), torch.ones(1, dtype=f64),
                            torch.ones(1, 1, dtype=f64)).y
        assert float(y) == pytest.approx(float(np.real(R(np.array(z + 0j)))), rel=1e-9, abs=1e-12)


def test_real_stability_limits():
    assert real_limit("euler") == pytest.approx(2.0, abs=1e-6)
    assert real_limit("rk4") == pytest.approx(2.785, abs=1e-3)


def test_suggest_on_a_dichotomic_pair():
    kappa = 200.0
    t = torch.linspace(0, 1, 11, dtype=f64)
    guess = (t, torch.zeros(11, 2, dtype=f64))
    prob = diagonal_bvp(kappa)
    s = suggest_shooting_points(prob, guess, "rk4", steps=1)
    assert s.limited_by == "stability" and s.kappa == pytest.approx(-kappa) and s.kappa_plus == pytest.approx(kappa)
    assert abs(s.m - (1 + kappa / 2.785)) <= 2                       # h·|κ| at RK4's real limit
    assert abs(suggest_shooting_points(prob, guess, "euler").m - (1 + kappa / 2)) <= 2
    # many steps per interval: the growing partner e^{κ h} limits the interval length
    g = math.log(1e-10 / np.finfo(float).eps)
    for name, steps in (("rk4", 32), ("ros4", 1)):
        s = suggest_shooting_points(prob, guess, name, steps=steps)
        assert s.limited_by == "growth"
        assert abs(s.m - (1 + kappa / g)) <= 2 and s.growth <= s.growth_limit
    # L-stable implicit Euler: its R(z) → 0 for z → +∞ turns the growing mode into a decaying one
    s = suggest_shooting_points(prob, guess, "implicit_euler")
    assert s.limited_by == "stability" and abs(s.m - (1 + kappa / 2)) <= 2
    # eigenvalues given directly; an Integrator instance carries its steps
    lam = torch.tensor([[-kappa, kappa]], dtype=torch.complex128)
    s2 = suggest_shooting_points(prob, None, shootlab.get_integrator("rk4", steps=1), eigenvalues=lam,
                                 interval=(0.0, 1.0))
    assert s2.m == suggest_shooting_points(prob, guess, "rk4").m
    with pytest.raises(ValueError):
        suggest_shooting_points(prob, torch.zeros(11, 2, dtype=f64), "rk4")        # no t
