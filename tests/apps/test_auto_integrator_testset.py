"""The automatic integrator choice (``integrator="auto"``) and ``refine`` on the Cash & Mazzia
problems of the BVP test set (:mod:`studies.bvp_testset`)."""

import numpy as np
import torch

import shootlab
from studies import bvp_testset as ts

f64 = torch.float64


def test_auto_picks_the_stiff_scheme_on_a_stiff_problem():
    """ε y'' + y' − (1 + ε) y = 0 (bvpT4's equation) at ε = 1e-5 on [−0.9, 1], 5 points, not
    refined: the decaying mode λ ≈ −1/ε gives |λ|·h ≈ 5e4 on every interval (far beyond an
    explicit scheme's stability), the growing one is λ ≈ 1.  Every row goes to ros4, and the
    solution meets the stated tolerance against the exact one, e^{t−1} + e^{−(1+ε)(1+t)/ε}.
    (From the exact values: a guess off them starts a layer of width ε in every interval.)"""
    eps = 1e-5
    p = [q for q in ts.cash_problems([eps]) if q.name == "bvpT4"][0]
    a, b = -0.9, 1.0
    ya, yb = float(p.exact([a])[0, 0]), float(p.exact([b])[0, 0])
    bvp = shootlab.BVP(p.bvp().rhs, lambda xa: xa[:1] - ya, lambda xb: xb[:1] - yb)
    t = torch.linspace(a, b, 5, dtype=f64)
    exact = torch.as_tensor(p.exact(t.numpy()))
    res = shootlab.solve(bvp, t, exact, rtol=1e-8, atol=1e-10, refine=False)
    integ = res._system.integrator
    assert res.success, res.message
    assert integ.rows["ros4"] > 0 and integ.rows["dop853"] == 0
    assert ((res.x[:, 0] - exact[:, 0]).abs() / exact[:, 0].abs().max()).max() < 1e-7
    # the same rows with an explicit scheme would need |λ|h / 3.3 ≈ 1.4e4 steps each
    assert integ.stiff_rows(bvp.rhs, t[:-1], t[1:], exact[:-1]).all()


def test_refine_keeps_the_user_grid_in_the_result_and_is_exact_at_its_points():
    p = [q for q in ts.cash_problems([1e-3]) if q.name == "bvpT1"][0]
    t = torch.linspace(p.a, p.b, 21, dtype=f64)
    g = torch.as_tensor(p.straight_line_guess(t.numpy()))
    res = shootlab.solve(p.bvp(), t, g, rtol=1e-8, atol=1e-10)
    assert res.success and res.points > 21 and res.x.shape == (21, 2)
    exact = p.exact(t.numpy())[:, 0]
    assert np.abs(res.x[:, 0].numpy() - exact).max() < 1e-6
    off = shootlab.solve(p.bvp(), t, g, rtol=1e-8, atol=1e-10, refine=False)
    assert off.points == 21
    if off.success:
        assert np.abs(off.x[:, 0].numpy() - exact).max() < 1e-6
