"""Newton strategies: affine covariance of the default, its globalisation, the kept Jacobian,
the undamped step, and the unit-independent rank test of the structured factorisation."""
import math
from types import SimpleNamespace

import pytest
import torch

import shootlab
from shootlab.bvp.linalg import SingularJacobianError, factorize
from shootlab.bvp.newton import CONVERGED, STEP_TOO_SMALL, get_newton

f64 = torch.float64


class DenseSystem:
    """F(s) = A g(s) for a small nonlinear g on s of shape (k, n), solved densely: the interface
    of ShootingSystem that the strategies use (residual, linearize, newton_step)."""

    def __init__(self, g, A=None):
        self.g, self.A, self.evaluations = g, A, 0

    def _F(self, s):
        F = self.g(s).reshape(-1)
        return F if self.A is None else self.A @ F

    def residual(self, s):
        self.evaluations += 1
        return SimpleNamespace(F=self._F(s))

    def linearize(self, s):
        J = torch.autograd.functional.jacobian(lambda v: self._F(v.reshape(s.shape)), s.reshape(-1))
        return torch.linalg.lu_factor(J)

    def newton_step(self, fac, F):
        lu, piv = fac
        return -torch.linalg.lu_solve(lu, piv, F.unsqueeze(-1)).squeeze(-1).reshape(-1, 2)


def arctan_system(s):
    """Componentwise arctan (Newton from |x| > 1.39 diverges undamped) coupled to a quadratic:
    root at x = (0, 0), (1, 2)."""
    x = s.reshape(-1, 2)
    return torch.stack([torch.atan(x[:, 0]), x[:, 1] ** 2 - 4.0 + x[:, 0]], -1)


def test_deuflhard_is_affine_covariant_press_is_not():
    """The iterates of the default strategy do not change when F is replaced by A F (A regular,
    badly scaled): its tests are on Newton corrections J⁻¹F, which A cancels out of.  Press's
    Armijo test on ½|F|² is not invariant: the same problem takes another path."""
    s0 = torch.tensor([[3.0, 5.0], [-2.5, 3.0]], dtype=f64)
    g = torch.Generator().manual_seed(0)
    A = torch.diag(torch.tensor([1e-6, 1.0, 1e4, 30.0], dtype=f64)) @ (
        torch.eye(4, dtype=f64) + 0.3 * torch.randn(4, 4, dtype=f64, generator=g))
    runs = {}
    for name in ("deuflhard", "armijo"):
        for key, mat in (("plain", None), ("scaled", A)):
            out = get_newton(name, tol=1e-12).run(DenseSystem(arctan_system, mat), s0.clone())
            runs[name, key] = out
    plain, scaled = runs["deuflhard", "plain"], runs["deuflhard", "scaled"]
    assert plain.status == CONVERGED and scaled.status == CONVERGED, (plain.message, scaled.message)
    assert plain.iterations == scaled.iterations
    assert [r["step"] for r in plain.history] == pytest.approx([r["step"] for r in scaled.history], rel=1e-9)
    expected = torch.tensor([[0.0, 2.0], [0.0, 2.0]], dtype=f64)
    assert torch.allclose(plain.s, expected, atol=1e-10) and torch.allclose(scaled.s, expected, atol=1e-10)
    press_steps = [[r["step"] for r in runs["armijo", k].history] for k in ("plain", "scaled")]
    assert press_steps[0] != press_steps[1]


def test_deuflhard_damps_where_the_full_step_diverges():
    """Undamped Newton on arctan from x = 3 diverges (|x| grows every step); the default damps the
    first steps (λ < 1) and converges to the root."""
    s0 = torch.tensor([[3.0, 2.0]], dtype=f64)
    out = get_newton("undamped", max_iter=5).run(DenseSystem(arctan_system), s0.clone())
    assert out.status != CONVERGED and abs(float(out.s[0, 0])) > 100.0
    out = get_newton("deuflhard").run(DenseSystem(arctan_system), s0.clone())
    assert out.status == CONVERGED, out.message
    assert out.history[1]["step"] < 1.0 and out.history[-1]["step"] == 1.0
    assert abs(float(out.s[0, 0])) < 1e-10 and abs(float(out.s[0, 1]) - 2.0) < 1e-10


def test_undamped_step_solves_a_linear_problem_at_once():
    A = torch.tensor([[2.0, 1.0], [1.0, 3.0]], dtype=f64)
    out = get_newton("undamped", max_iter=1).run(DenseSystem(lambda s: s @ A.T - 1.0), torch.zeros(1, 2, dtype=f64))
    assert out.status == CONVERGED and torch.allclose(out.s @ A.T, torch.ones(1, 2, dtype=f64), atol=1e-14)


def test_deuflhard_keeps_the_jacobian_while_it_contracts():
    t = torch.linspace(0.0, 1.0, 101, dtype=f64)
    prob = shootlab.BVP(lambda t, x: torch.stack([x[..., 1], 5.0 * torch.sinh(5.0 * x[..., 0])], -1),
                        lambda xa: xa[:1], lambda xb: xb[:1] - 1.0)
    res = shootlab.solve(prob, t, torch.stack([t, torch.ones_like(t)], -1), integrator="rk4", steps=8)
    assert res.success and res.jacobian_evaluations < res.iterations, res
    assert any(row["jacobian"] == "reused" for row in res.history)
    assert abs(float(res.x[0, 1]) - 0.0457504) < 1e-6          # Troesch μ = 5: y'(0)


def test_broyden_updates_of_a_kept_jacobian_end_on_a_linear_system():
    """Gay's theorem: good Broyden from a wrong J₀ solves an n-dimensional linear system in at most
    2n steps (exactly, up to rounding), where the simplified correction with J₀ only contracts."""
    from shootlab.bvp.newton import _Broyden
    torch.manual_seed(0)
    n = 6
    A = torch.eye(n, dtype=f64) * 3 + 0.5 * torch.randn(n, n, dtype=f64)
    J0 = A + 0.8 * torch.randn(n, n, dtype=f64) * A.abs().mean()
    b = torch.randn(n, dtype=f64)
    x_star = torch.linalg.solve(A, b)
    back = lambda x: -torch.linalg.solve(J0, A @ x - b)          # −J₀⁻¹F(x)
    d = torch.linspace(1.0, 3.0, n, dtype=f64)                   # any fixed scaling of the unknowns

    x = torch.zeros(n, dtype=f64)
    dx = back(x)
    broyden = _Broyden(dx, d)
    for _ in range(2 * n):
        x = x + dx
        dx = broyden.step(broyden.solve(back(x)))
    assert float((x - x_star).abs().max()) < 1e-9 * float(x_star.abs().max())

    y = torch.zeros(n, dtype=f64)                                # the simplified correction alone
    for _ in range(2 * n):
        y = y + back(y)
    assert float((y - x_star).abs().max()) > 1e-6 * float(x_star.abs().max())


def test_damping_floor_reported_with_the_iterate():
    """No root (arctan(x) = 2): the damping collapses; the message names the floor and the
    iteration, and the last iterate is returned, not garbage."""
    out = get_newton("deuflhard", max_iter=200).run(
        DenseSystem(lambda s: torch.atan(s) - 2.0), torch.tensor([[0.0, 0.0]], dtype=f64))
    assert out.status != CONVERGED
    assert ("damping factor below" in out.message or "maximum number" in out.message), out.message
    assert torch.isfinite(out.s).all()


def test_stall_ends_a_run_that_makes_no_progress():
    """x² + 1 = 0 has no real root (max|F| ≥ 1 everywhere): with ``stall=3`` the run ends at
    iteration 3, where three iterations have not halved the least max|F| before them, with the
    iterate and the reason; without it the damping has to collapse to 1e-8 first.  A run that
    converges (arctan, damped then full steps) takes the same steps with and without the test."""
    s0 = torch.tensor([[0.5, 3.0]], dtype=f64)
    plain = get_newton("deuflhard", max_iter=60).run(DenseSystem(lambda s: s ** 2 + 1.0), s0.clone())
    cut = get_newton("deuflhard", max_iter=60, stall=3).run(DenseSystem(lambda s: s ** 2 + 1.0), s0.clone())
    assert plain.status == STEP_TOO_SMALL and "damping factor below 1e-08" in plain.message
    assert cut.status == STEP_TOO_SMALL and cut.iterations == 3 < plain.iterations
    assert "max|F| not halved in 3 iterations at iteration 3" in cut.message, cut.message
    norms = [row["residual_norm"] for row in cut.history]
    assert min(norms[1:]) > 0.5 * norms[0] and torch.isfinite(cut.s).all()
    runs = [get_newton("deuflhard", **kw).run(DenseSystem(arctan_system), torch.tensor([[3.0, 2.0]], dtype=f64))
            for kw in ({}, {"stall": 3})]
    assert all(r.status == CONVERGED for r in runs)
    assert [r["step"] for r in runs[0].history] == [r["step"] for r in runs[1].history]
    assert runs[0].history[1]["step"] < 0.1                     # damped at first, yet not cut


def test_unknown_option_and_strategy_are_clear_errors():
    with pytest.raises(ValueError, match="unknown option"):
        get_newton("deuflhard", alpha=1e-4)
    with pytest.raises(ValueError, match="lambda0"):
        get_newton("deuflhard", lambda0=2.0)
    with pytest.raises(ValueError, match="min_damping"):
        get_newton("deuflhard", min_damping=0.0)
    with pytest.raises(ValueError, match="stall"):
        get_newton("deuflhard", stall=0)
    with pytest.raises(ValueError, match="deuflhard"):
        get_newton("newtonish")


def test_rank_test_does_not_depend_on_units():
    """A regular Newton matrix whose rows differ by 1e13 in scale (a position weighted like an
    encoder count next to a force) is not singular; a genuinely singular one still is."""
    m, n = 9, 2
    A = torch.tensor([[0.0, 1.0], [-4.0, -0.1]], dtype=f64)
    Y = torch.linalg.matrix_exp(A * 0.1).expand(m - 1, n, n).clone()
    Ba, Bb = torch.tensor([[1.0, 0.0]], dtype=f64), torch.tensor([[0.0, 1.0]], dtype=f64)
    D = torch.diag(torch.tensor([1.0, 1e13], dtype=f64))         # the second unknown in other units
    Ys, Bas, Bbs = D @ Y @ torch.linalg.inv(D), Ba @ torch.linalg.inv(D), Bb @ torch.linalg.inv(D)
    g = torch.Generator().manual_seed(2)
    ra, rm, rb = (torch.randn(1, dtype=f64, generator=g), torch.randn(m - 1, n, dtype=f64, generator=g),
                  torch.randn(1, dtype=f64, generator=g))
    d = factorize(Y, Ba, Bb).solve(ra, rm, rb)
    ds = factorize(Ys, Bas, Bbs).solve(ra, rm @ D.T, rb)           # the same system in the new units
    assert torch.allclose(ds @ torch.linalg.inv(D).T, d, rtol=1e-8, atol=1e-12)
    with pytest.raises(SingularJacobianError):
        factorize(torch.eye(n, dtype=f64).expand(m - 1, n, n).clone() * 1e13, Ba, Ba.clone())


def test_deuflhard_keeps_the_iterates_inside_the_bounds():
    """1/x = 1/2 from x = 5: the Newton step (−7.5) crosses the pole to x = −2.5.  With the bound
    x > 0 every trial point stays positive (fraction to the boundary 0.99) and the root 2 is found."""
    trials = []

    class Bounded(DenseSystem):
        prob = SimpleNamespace(lower=torch.tensor([0.0, -math.inf], dtype=f64), upper=None)

        def residual(self, s):
            trials.append(float(s[0, 0]))
            return super().residual(s)
    out = get_newton("deuflhard", tol=1e-13).run(Bounded(lambda s: torch.stack([1.0 / s[:, 0] - 0.5, s[:, 1]], -1)),
                                      torch.tensor([[5.0, 1.0]], dtype=f64))
    assert out.status == CONVERGED and abs(float(out.s[0, 0]) - 2.0) < 1e-10
    assert min(trials) > 0.0 and min(trials) >= 0.01 * 5.0 - 1e-12


def test_bounds_are_checked_against_the_guess():
    t = torch.linspace(0.0, 1.0, 5, dtype=f64)
    prob = shootlab.BVP(lambda t, x: torch.stack([x[..., 1], x[..., 0]], -1), lambda xa: xa[:1], lambda xb: xb[:1] - 1.0,
                        lower=torch.tensor([0.5, -math.inf], dtype=f64))
    with pytest.raises(ValueError, match="lower bound of component 0 at shooting point 0"):
        shootlab.solve(prob, t, torch.stack([t, torch.ones_like(t)], -1))


def test_an_inexact_first_residual_is_not_taken_for_convergence():
    """A system whose first residual comes from a looser pass (``Residual.exact`` False): here it
    is exactly zero at a point that is not the root.  Deuflhard must integrate F again at the
    tolerance and go on to the root; a small inexact first correction is not convergence."""
    A = torch.tensor([[2.0, 1.0], [1.0, 3.0]], dtype=f64)
    b = torch.tensor([1.0, 2.0], dtype=f64)

    class Loose(DenseSystem):
        prefetches_jacobian = True

        def residual(self, s, jacobian=False):
            self.evaluations += 1
            F = self._F(s)
            if jacobian:                              # the looser pass: off by F itself
                return SimpleNamespace(F=torch.zeros_like(F), exact=False)
            return SimpleNamespace(F=F, exact=True)

    root = torch.linalg.solve(A, b)
    system = Loose(lambda s: s.reshape(-1) @ A.T - b)
    system.newton_step = lambda fac, F: -torch.linalg.lu_solve(*fac, F.unsqueeze(-1)).squeeze(-1)
    out = get_newton("deuflhard", tol=1e-12).run(system, torch.zeros(2, dtype=f64))
    assert out.status == CONVERGED and (out.s - root).abs().max() < 1e-12
    assert system.evaluations >= 3                    # the loose F, F again at the tolerance, the step
