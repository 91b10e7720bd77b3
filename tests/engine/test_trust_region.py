"""The trust-region (dogleg) Newton strategy (shootlab.bvp.trust_region) and the fallback of the
estimate to it (shootlab.estimation.fit.solve_falling_back): its products with the block Jacobian
against the dense matrix, a solve where the default Newton's damping collapses, the same root as
the default where both converge, a singular start, and the chain deuflhard → armijo →
trust_region."""
import math

import pytest
import torch

import shootlab
from shootlab.estimation.fit import solve_falling_back
from shootlab.bvp.linalg import dense_matrix, factorize
from shootlab.bvp.newton import CONVERGED, SINGULAR, STEP_TOO_SMALL, get_newton
from shootlab.bvp.trust_region import ShootingJacobian

f64 = torch.float64
FIXED = dict(integrator="rk4", steps=8, max_growth=None, refine=False)


def rotating(g_a, g_b) -> shootlab.BVP:
    """x' = (−x2, x1) (a rotation by t) with one nonlinear condition at each end."""
    return shootlab.BVP(lambda t, x: torch.stack([-x[..., 1], x[..., 0]], -1),
                        lambda xa: g_a(xa).reshape(1), lambda xb: g_b(xb).reshape(1))


#: x(a) on the circle |x| = 2, x(b) on the curve e^x1 + x2 = 1: x(b) is one of the curve's two
#: crossings of the circle (a rotation keeps |x|), where the determinant of the Newton matrix
#: changes sign in between — a fold of the Newton path for starts far to the right
CIRCLE = rotating(lambda x: x[0] ** 2 + x[1] ** 2 - 4.0, lambda x: torch.exp(x[0]) + x[1] - 1.0)
GRID = torch.linspace(0.0, 1.0, 6, dtype=f64)


def constant(x0) -> torch.Tensor:
    return torch.tensor(x0, dtype=f64).expand(GRID.numel(), 2).clone()


def crossings() -> torch.Tensor:
    """The two points where e^x + y = 1 crosses x² + y² = 4 (Newton on the scalar equation)."""
    out = []
    for x in (-1.8, 1.0):
        for _ in range(50):
            y, dy = 1.0 - math.exp(x), -math.exp(x)
            x -= (x * x + y * y - 4.0) / (2.0 * x + 2.0 * y * dy)
        out.append([x, 1.0 - math.exp(x)])
    return torch.tensor(out, dtype=f64)


def test_products_with_the_blocks_equal_those_with_the_dense_matrix():
    """J δ, Jᵀ v, the row equilibration D and the column norms of D J from the blocks (no dense
    matrix) against the dense Newton matrix of linalg.dense_matrix; D is the factorisation's."""
    g = torch.Generator().manual_seed(4)
    m, n, p = 7, 3, 1
    Y = torch.randn(m - 1, n, n, dtype=f64, generator=g) * torch.logspace(-3, 3, m - 1, dtype=f64)[:, None, None]
    B_a, B_b = torch.randn(p, n, dtype=f64, generator=g), 1e4 * torch.randn(n - p, n, dtype=f64, generator=g)
    jac, J = ShootingJacobian(Y, B_a, B_b), dense_matrix(Y, B_a, B_b)
    d, v = torch.randn(m, n, dtype=f64, generator=g), torch.randn(m * n, dtype=f64, generator=g)

    def rel(a, b):
        return float((a - b).norm() / b.norm())
    assert rel(jac.matvec(d), J @ d.reshape(-1)) < 1e-12
    assert rel(jac.rmatvec(v).reshape(-1), J.T @ v) < 1e-12
    D = jac.row_scale()
    fac = factorize(Y, B_a, B_b)
    assert torch.equal(D[p:p + (m - 1) * n], fac.scale.reshape(-1))
    assert torch.allclose(D[:p], 1.0 / fac.row_scale[:p]) and torch.allclose(D[p + (m - 1) * n:], 1.0 / fac.row_scale[p + n:])
    assert rel(jac.column_norms(D).reshape(-1), (D[:, None] * J).norm(dim=0)) < 1e-12


def test_trust_region_solves_where_the_default_damping_collapses():
    """From x = (6, 1) the default Newton's damping falls below 1e-8 (the Newton path folds back
    where the Newton matrix is singular); the dogleg, which minimises |DF|² instead of following
    that path, converges to a solution: |x(a)| = 2, x(b) on the curve and at one of its crossings
    of the circle (to the rotation's RK4 error, 1e-9)."""
    x0 = constant([6.0, 1.0])
    default = shootlab.solve(CIRCLE, GRID, x0, **FIXED)
    assert default.status == STEP_TOO_SMALL and "damping factor below 1e-08" in default.message
    res = shootlab.solve(CIRCLE, GRID, x0, newton="trust_region", **FIXED)
    assert res.success, res.message
    xa, xb = res.x[0], res.x[-1]
    assert abs(float(xa @ xa) - 4.0) < 1e-10 and abs(math.exp(float(xb[0])) + float(xb[1]) - 1.0) < 1e-10
    assert float((crossings() - xb).norm(dim=1).min()) < 1e-9


@pytest.mark.parametrize("x0", [(5.0, 5.0), (3.0, -3.0), (4.23, 0.23)])
def test_same_root_as_the_default_where_both_converge(x0):
    res = {nt: shootlab.solve(CIRCLE, GRID, constant(x0), newton=nt, **FIXED) for nt in ("deuflhard", "trust_region")}
    assert all(r.success for r in res.values()), {k: r.message for k, r in res.items()}
    assert torch.allclose(res["trust_region"].x, res["deuflhard"].x, rtol=0, atol=1e-9)


def test_troesch_root_and_quadratic_convergence():
    """Troesch μ = 5 from the straight line (as the default in test_newton): y'(0) = 0.0457504616
    (the default's value to 1e-9); the radius is the Newton step's, and the last steps are full
    Newton steps that square |F| (measured: 1.2e-3, 1.4e-6, 1.9e-12)."""
    t = torch.linspace(0.0, 1.0, 101, dtype=f64)
    prob = shootlab.BVP(lambda t, x: torch.stack([x[..., 1], 5.0 * torch.sinh(5.0 * x[..., 0])], -1),
                        lambda xa: xa[:1], lambda xb: xb[:1] - 1.0)
    res = shootlab.solve(prob, t, torch.stack([t, torch.ones_like(t)], -1), integrator="rk4", steps=8,
                         newton="trust_region")
    assert res.success, res.message
    assert abs(float(res.x[0, 1]) - 0.0457504616) < 1e-9
    norms = [row["residual_norm"] for row in res.history]
    assert res.history[-1]["step"] == res.history[-2]["step"] == 1.0
    assert norms[-1] < 10.0 * norms[-2] ** 2 and norms[-2] < 10.0 * norms[-3] ** 2


def test_a_singular_start_takes_the_gradient_step():
    """Powell's example as a TPBVP with constant states (F = (x1, 10 x1/(x1 + 0.1) + 2 x2²)): at
    x = (3, 0) the Newton matrix is singular (∂F/∂x2 = 0) and the line-search strategies stop at
    once; the dogleg takes the scaled steepest-descent step alone and reaches the root (0, 0)."""
    prob = shootlab.BVP(lambda t, x: 0.0 * x, lambda xa: xa[:1],
                        lambda xb: (10.0 * xb[0] / (xb[0] + 0.1) + 2.0 * xb[1] ** 2).reshape(1))
    t = torch.linspace(0.0, 1.0, 3, dtype=f64)
    x0 = torch.tensor([3.0, 0.0], dtype=f64).expand(3, 2).clone()
    assert shootlab.solve(prob, t, x0, integrator="rk4", steps=1, max_growth=None, refine=False).status == SINGULAR
    res = shootlab.solve(prob, t, x0, integrator="rk4", steps=1, max_growth=None, refine=False, newton="trust_region")
    assert res.success, res.message
    assert float(res.x.abs().max()) < 1e-10


def test_options_are_checked():
    with pytest.raises(ValueError, match="eta"):
        get_newton("trust_region", eta=0.5)
    with pytest.raises(ValueError, match="min_radius"):
        get_newton("trust_region", min_radius=0.0)
    with pytest.raises(ValueError, match="slow"):
        get_newton("trust_region", slow=0)
    with pytest.raises(ValueError, match="unknown option"):
        get_newton("trust_region", min_damping=1e-4)


#: x(a) on atan(x1) + 0.2 x2² = 0.2, x(b) on x2³ = x1 + 1: from (−6.8, 0.4) the default's damping
#: and armijo's line search both collapse
ARCTAN = rotating(lambda x: torch.atan(x[0]) + 0.2 * x[1] ** 2 - 0.2, lambda x: x[1] ** 3 - x[0] - 1.0)


def test_the_fallback_chain_tries_armijo_then_trust_region(capsys):
    x0 = constant([-6.832, 0.423])
    res, attempts = solve_falling_back(ARCTAN, GRID, x0, dict(FIXED, verbose=True))
    assert res.success and res.message.endswith("(newton=trust_region; deuflhard, armijo stopped)"), res.message
    assert [(a["newton"], a["success"], a["status"]) for a in attempts] == [
        ("deuflhard", False, STEP_TOO_SMALL), ("armijo", False, STEP_TOO_SMALL), ("trust_region", True, CONVERGED)]
    out = capsys.readouterr().out
    assert "deuflhard stopped: damping factor below 1e-08 at iteration" in out
    assert "armijo stopped: step length below the floor" in out and "trying newton=trust_region from the same start" in out
    direct = shootlab.solve(ARCTAN, GRID, x0, newton="trust_region", **FIXED)
    assert torch.equal(res.x, direct.x)                  # from the same start, not from where armijo stopped
    # a given strategy falls back too (to the others of the chain); fallback=False: as it stopped
    res, attempts = solve_falling_back(ARCTAN, GRID, x0, dict(FIXED, newton="armijo"))
    assert res.success and [a["newton"] for a in attempts] == ["armijo", "trust_region"]
    res, attempts = solve_falling_back(ARCTAN, GRID, x0, FIXED, fallback=False)
    assert not res.success and res.status == STEP_TOO_SMALL and len(attempts) == 1


def test_when_every_strategy_stops_the_first_result_is_returned_with_the_others_messages():
    """x1(a)² + 1 = 0 has no real solution (|F| ≥ 1, least at x1 = 0): every strategy stops; the
    default's iterate and message are returned, the others' appended."""
    prob = rotating(lambda x: x[0] ** 2 + 1.0, lambda x: x[1])
    res, attempts = solve_falling_back(prob, GRID, constant([0.5, 0.5]), FIXED)
    assert not res.success and [a["newton"] for a in attempts] == ["deuflhard", "armijo", "trust_region"]
    assert res.message.startswith(attempts[0]["message"].split("; try")[0]) and "the fallbacks stopped too: armijo:" in res.message
    assert "trust_region: |DF| lowered by less than 0.1 % in 10 iterations" in res.message
    assert abs(float(res.x[0, 0])) < 1e-3 and torch.isfinite(res.x).all()       # at the minimum of |F|


def test_a_maximum_of_iterations_and_undamped_steps_are_not_retried():
    res, attempts = solve_falling_back(CIRCLE, GRID, constant([6.0, 1.0]), dict(FIXED, max_iter=2))
    assert not res.success and res.status == 1 and len(attempts) == 1
    res, attempts = solve_falling_back(CIRCLE, GRID, constant([6.0, 1.0]), dict(FIXED, newton="undamped", max_iter=3))
    assert len(attempts) == 1
