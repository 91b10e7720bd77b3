"""Interval Jacobians by forward sensitivities of the discrete scheme (shooting jacobian="autograd")
equal the reverse sweeps through the recorded integrator graph (jacobian="reverse") and central
differences, to rounding; a right-hand side that torch.func cannot transform falls back, once told."""
from __future__ import annotations
import warnings

import numpy as np
import pytest
import torch

import shootlab
from shootlab.bvp import tangents
from shootlab.bvp.integrators import NO_CONVERGENCE, get_integrator
from shootlab.bvp.shooting import ShootingSystem
from shared import both, central_differences, rel

f64 = torch.float64
FIXED = ["euler", "rk4", "rkf45", "implicit_euler", "midpoint", "radau3"]
ADAPTIVE = ["dopri5", "dop853", "ros4"]
#: tight stage equations, so that central differences of the implicit schemes carry digits
OPTIONS = {"implicit_euler": dict(rtol=1e-13, atol=1e-15), "midpoint": dict(rtol=1e-13, atol=1e-15),
           "radau3": dict(rtol=1e-13, atol=1e-15), "dopri5": dict(rtol=1e-9, atol=1e-11), "dop853": dict(rtol=1e-9, atol=1e-11),
           "ros4": dict(rtol=1e-8, atol=1e-10)}


def forced(t, y):
    """Coupled, non-linear, non-autonomous 3-d system."""
    y1, y2, y3 = y.unbind(-1)
    return torch.stack([-y2 + 0.3 * torch.sin(t) * y1 ** 2 + 0.2 * y3,
                        y1 - 0.5 * torch.cos(t) * y2 - 0.1 * y2 ** 3,
                        -2.0 * y3 + torch.tanh(y1 * y2)], -1)


@pytest.fixture(params=[0, 32], ids=["torch.func", "small-n"])
def forward_min_n(request, monkeypatch):
    """Both ways of taking the stage Jacobians: forward mode by torch.func for every n, and the
    default (reverse sweeps for the stage Jacobians below FORWARD_MIN_N equations)."""
    monkeypatch.setattr(tangents, "FORWARD_MIN_N", request.param)
    return request.param


@pytest.mark.parametrize("name", FIXED + ADAPTIVE)
def test_forward_sensitivities_equal_reverse_sweeps_and_central_differences(name, forward_min_n):
    prob = shootlab.BVP(forced, lambda xa: xa[:1], lambda xb: xb[:2])
    t = torch.tensor([0.0, 0.4, 1.1, 1.5], dtype=f64)
    s = torch.tensor([[1.0, 0.5, -0.3], [0.3, -0.7, 0.2], [-0.2, 0.4, 0.9], [0.1, 0.1, 0.1]], dtype=f64)
    integ = get_integrator(name, steps=3, **OPTIONS.get(name, {}))
    Y, Y_old, system = both(prob, t, s, integ)
    assert Y.shape == (3, 3, 3)
    assert rel(Y, Y_old) < 1e-12, name
    if name not in ADAPTIVE:      # differences of an adaptive scheme move its step sizes
        assert rel(Y, central_differences(system, s)) < 1e-8, name


def test_stage_jacobians_in_one_call(monkeypatch):
    """Below FORWARD_MIN_N equations a right-hand side with its own Jacobian is asked for it once
    per RK4 step, at the four stage points of every interval together; from FORWARD_MIN_N on, once
    per stage.  Both give the same interval Jacobians (to rounding) and central differences."""
    rows = []

    def jac(t, y):
        rows.append(y.shape[0])
        return tangents.reverse_jacobian(forced, t, y)
    prob = shootlab.BVP(forced, lambda xa: xa[:1], lambda xb: xb[:2], jac=jac)
    t = torch.tensor([0.0, 0.4, 1.1, 1.5], dtype=f64)
    s = torch.tensor([[1.0, 0.5, -0.3], [0.3, -0.7, 0.2], [-0.2, 0.4, 0.9], [0.1, 0.1, 0.1]], dtype=f64)
    system = ShootingSystem(prob, t, get_integrator("rk4", steps=3))
    Y = system.interval_jacobians(s)
    assert rows == [4 * 3] * 3                      # 3 steps, each the 4 stages of the 3 intervals
    rows.clear()
    monkeypatch.setattr(tangents, "FORWARD_MIN_N", 0)
    Y_per_stage = system.interval_jacobians(s)
    assert rows == [3] * 12
    assert rel(Y, Y_per_stage) < 1e-14
    assert rel(Y, central_differences(system, s)) < 1e-8


# -- fallback -------------------------------------------------------------------------------------
class _Cube(torch.autograd.Function):
    """A user's own autograd op in the old style (no ``setup_context``): reverse mode only."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return x ** 3

    @staticmethod
    def backward(ctx, g):
        x, = ctx.saved_tensors
        return 3.0 * x ** 2 * g


def test_untransformable_rhs_falls_back_with_one_warning(monkeypatch):
    """A custom autograd.Function without torch.func support (and an in-place write, .item()):
    reverse sweeps instead, the same Jacobians, the user told once; the solve works."""
    monkeypatch.setattr(tangents, "FORWARD_MIN_N", 0)
    A = torch.tensor([[0.0, 1.0], [400.0, 0.0]], dtype=f64)

    def rhs(t, x):
        out = torch.zeros_like(x)
        out[..., 0] = x[..., 1]
        out[..., 1] = 400.0 * x[..., 0] + 1e-9 * _Cube.apply(x[..., 0]) * float(x.abs().max().item() > -1)
        return out

    prob = shootlab.BVP(rhs, lambda xa: xa[:1] - 1.0, lambda xb: xb[:1] - np.exp(-20.0))
    t = torch.linspace(0.0, 1.0, 11, dtype=f64)
    s = torch.stack([1.0 - t, -torch.ones_like(t)], -1)
    system = ShootingSystem(prob, t, get_integrator("rk4", steps=4))
    with pytest.warns(RuntimeWarning, match="torch.func"):
        Y = system.interval_jacobians(s)
    ref = torch.linalg.matrix_exp(A * 0.1)
    assert (Y - ref).abs().max() < 1e-3 * ref.abs().max()        # rk4 with h = 0.025
    assert rel(Y, ShootingSystem(prob, t, get_integrator("rk4", steps=4), jacobian="reverse").interval_jacobians(s)) < 1e-14
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)            # once: no second warning
        ShootingSystem(prob, t, get_integrator("midpoint", steps=2)).interval_jacobians(s)
        res = shootlab.solve(prob, t, s, integrator="rk4", steps=4)
    assert res.success
    assert abs(float(res.x[0, 1]) + 20.0) < 0.1


def test_numpy_rhs_falls_back_to_finite_differences_with_a_warning():
    def rhs(t, x):
        xn = x.detach().numpy()
        return torch.as_tensor(np.stack([xn[..., 1], -xn[..., 0]], -1))

    prob = shootlab.BVP(rhs, lambda xa: xa[:1], lambda xb: xb[:1] - 1.0)
    t = torch.linspace(0.0, 1.0, 6, dtype=f64)
    s = torch.stack([t, torch.ones_like(t)], -1)
    system = ShootingSystem(prob, t, get_integrator("rk4", steps=4))
    with pytest.warns(RuntimeWarning, match="finite differences"):
        Y = system.interval_jacobians(s)
    c, sn = np.cos(0.2), np.sin(0.2)
    assert (Y - torch.tensor([[c, sn], [-sn, c]], dtype=f64)).abs().max() < 1e-6
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = shootlab.solve(prob, t, s, integrator="rk4", steps=4)
    assert res.success and abs(float(res.x[0, 1]) - 1.0 / np.sin(1.0)) < 1e-6


# -- the stage iteration ----------------------------------------------------------------------------
def test_simplified_newton_reports_non_convergence():
    """Two iterations with one matrix cannot meet a 1e-14 tolerance on a non-linear stiff
    step: the rows are flagged, not silently accepted."""
    rhs = lambda t, y: -50.0 * y ** 3                                      # noqa: E731
    integ = get_integrator("implicit_euler", steps=1, rtol=1e-14, atol=1e-16, newton_maxiter=2, newton_theta=2.0)
    res = integ.integrate(rhs, torch.zeros(2, dtype=f64), torch.ones(2, dtype=f64), torch.tensor([[1.0], [2.0]], dtype=f64))
    assert res.failed.all() and res.reason == NO_CONVERGENCE
    ok = get_integrator("implicit_euler", steps=1, rtol=1e-14, atol=1e-16)
    res = ok.integrate(rhs, torch.zeros(2, dtype=f64), torch.ones(2, dtype=f64), torch.tensor([[1.0], [2.0]], dtype=f64))
    assert not res.failed.any()
    y = res.y[:, 0]
    assert torch.allclose(y + 50.0 * y ** 3, torch.tensor([1.0, 2.0], dtype=f64), rtol=1e-12)
