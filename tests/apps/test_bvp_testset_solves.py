"""The multiple-shooting engine on the problems of the BVP test set (:mod:`studies.bvp_testset`):
Troesch, Bratu, singular perturbation and the Cash & Mazzia layers against their references."""

import numpy as np
import pytest
import torch

import shootlab
from studies import bvp_testset as ts

f64 = torch.float64


def troesch(mu):
    return shootlab.BVP(lambda t, x: torch.stack([x[..., 1], mu * torch.sinh(mu * x[..., 0])], -1),
                        lambda xa: xa[:1], lambda xb: xb[:1] - 1.0)


def test_troesch_harder_mu_against_testset_reference():
    """mu = 8: boundary layer at t = 1; the straight line would blow up inside an interval,
    so start from y = 0 (an equilibrium of every IVP)."""
    p = ts.troesch(8.0)
    t = torch.linspace(0.0, 1.0, 201, dtype=f64)
    res = shootlab.solve(troesch(8.0), t, torch.zeros(201, 2, dtype=f64), integrator="rk4", steps=16)
    assert res.success, res.message
    tq = np.linspace(0, 1, 57)
    assert np.abs(res.sol(torch.as_tensor(tq)).numpy()[:, 0] - p.exact(tq)[:, 0]).max() < 1e-7
    assert abs(float(res.x[0, 1]) / ts.troesch_slope(8.0) - 1.0) < 1e-6


def test_bratu_lower_branch():
    p = ts.bratu()
    t = torch.linspace(0.0, 1.0, 51, dtype=f64)
    res = shootlab.solve(p.bvp(), t, torch.zeros(51, 2, dtype=f64))
    assert res.success, res.message
    tq = np.linspace(0, 1, 41)
    assert np.abs(res.sol(torch.as_tensor(tq)).numpy() - p.exact(tq)).max() < 1e-8


def _singular_perturbation_error(**options):
    p = ts.singular_perturbation(1e-3)
    t = torch.linspace(0.0, 1.0, 101, dtype=f64)
    res = shootlab.solve(p.bvp(), t, torch.as_tensor(p.straight_line_guess(t.numpy())), **options)
    assert res.success, res.message
    tq = np.linspace(0, 1, 201)
    ex = p.exact(tq)
    return (np.abs(res.sol(torch.as_tensor(tq)).numpy() - ex).max(0) / np.abs(ex).max(0)).max()


def test_singular_perturbation_with_stiff_integrator():
    """ε y'' + y' = 0, ε = 1e-3: 2-stage Radau IIA, 50 steps per interval (layer at t = 0)."""
    assert _singular_perturbation_error(integrator="radau3", steps=50) < 1e-6


@pytest.mark.slow
def test_singular_perturbation_default_settings():
    assert _singular_perturbation_error() < 1e-8


def _layer_solve(problem, **options):
    """solve() of a test-set layer problem from its straight-line guess at rtol 1e-8, as the BVP
    benchmark asks; (result, max relative error of y against the exact solution)."""
    t = torch.linspace(problem.a, problem.b, 101, dtype=f64)
    res = shootlab.solve(problem.bvp(), t, torch.as_tensor(problem.straight_line_guess(t.numpy())),
                         rtol=1e-8, atol=1e-10, **options)
    tq = np.linspace(problem.a, problem.b, 2001)
    exact = problem.exact(tq)[:, 0]
    y = res.sol(torch.as_tensor(tq))[:, 0].numpy()
    return res, float(np.abs(y - exact).max() / np.abs(exact).max())


def test_looser_jacobians_give_the_same_solution_with_fewer_rhs_calls():
    """jacobian_rtol="auto" (√rtol for the Jacobians' passes, the default with deuflhard) against
    Jacobians at rtol: the same solution to the tolerance, at a fraction of the rhs calls — the
    first pass from the straight-line guess resolves an initial transient in every interval
    (with dop853, auto's explicit pair, on ε = 1e-4; at 1e-3 its steps are about one per interval
    at both tolerances)."""
    loose, err_loose = _layer_solve(ts.bvpT3(1e-4))
    tight, err_tight = _layer_solve(ts.bvpT3(1e-4), jacobian_rtol=None)
    assert loose.success and tight.success
    assert err_loose < 1e-8 and err_tight < 1e-8          # measured 5e-12 for both
    assert (loose.x - tight.x).abs().max() < 1e-8
    assert loose._system.loose_jacobian and not tight._system.loose_jacobian
    assert loose._system.nfev < 0.85 * tight._system.nfev  # measured 0.72


def test_a_trial_point_that_meets_the_tolerance_is_the_solution():
    """bvpT5, ε = 1e-4, with refine's budget doubled (8143 points): after the first full step |F| is
    near the integrator's error level, where the corrections are noise; the next full step reaches
    |F| = 6.6e-9 ≤ tol·(1 + max|s|) = 4.1e-8 with Θ = 0.754 > 3/4.  Rejected by the monotonicity
    test, it had been damped down to the floor (status 4); accepted by its F, it converges."""
    import shootlab.bvp.solver as solver_module
    budget = solver_module.REFINE_BUDGET
    solver_module.REFINE_BUDGET = 2 * budget
    try:
        res, err = _layer_solve(ts.bvpT5(1e-4))
    finally:
        solver_module.REFINE_BUDGET = budget
    assert res.points > 8000
    assert res.success and res.iterations <= 3 and err < 1e-8      # measured 2 iterations, 4e-12


def test_intervals_too_long_fail_fast_with_advice():
    """ε y'' = y' at ε = 1e-4 grows like e^{t/ε}: 101 points give e^100 per interval."""
    p = [q for q in ts.cash_problems([1e-4]) if q.name == "bvpT2"][0]
    t = torch.linspace(p.a, p.b, 101, dtype=f64)
    res = shootlab.solve(p.bvp(), t, torch.as_tensor(p.straight_line_guess(t.numpy())), refine=False)
    assert not res.success and res.status == 5 and res.iterations == 0
    assert "more shooting points" in res.message and "interval" in res.message


def test_refine_adds_the_points_the_growth_asks_for():
    """The same problem with the default refine=True: the solver cuts the intervals itself
    (max|λ|·h ≤ 1), solves, and reports at the points it was given."""
    p = [q for q in ts.cash_problems([1e-4]) if q.name == "bvpT2"][0]
    t = torch.linspace(p.a, p.b, 101, dtype=f64)
    res = shootlab.solve(p.bvp(), t, torch.as_tensor(p.straight_line_guess(t.numpy())), rtol=1e-8, atol=1e-10)
    assert res.success and res.status == 0
    assert res.t is t and res.x.shape == (101, 2) and res.points > 101
    tq = ts.fine_grid(p)
    assert ts.relative_max_error(p, tq, res.sol(torch.as_tensor(tq)).numpy(), component=0) < 1e-6
    assert ts.relative_max_error(p, t.numpy(), res.x.numpy(), component=0) < 1e-6
    # a slow problem is left alone
    q = [r for r in ts.cash_problems([1e-1]) if r.name == "bvpT1"][0]
    t = torch.linspace(q.a, q.b, 11, dtype=f64)
    res = shootlab.solve(q.bvp(), t, torch.as_tensor(q.straight_line_guess(t.numpy())))
    assert res.success and res.points == 11
