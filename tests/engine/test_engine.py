"""The multiple-shooting engine: structured solve, Jacobians, Newton strategies, failures, input checks."""
import os
import math

import numpy as np
import pytest
import torch

import shootlab
from shootlab.bvp.linalg import SingularJacobianError, dense_matrix, factorize

f64 = torch.float64


def lin400():
    """y'' = 400 y, y(0) = 1, y(1) = e^-20: exact e^{-20 t}; single shooting loses ~e^20."""
    return shootlab.BVP(lambda t, x: torch.stack([x[..., 1], 400.0 * x[..., 0]], -1),
                        lambda xa: xa[:1] - 1.0, lambda xb: xb[:1] - math.exp(-20.0))


def troesch(mu):
    return shootlab.BVP(lambda t, x: torch.stack([x[..., 1], mu * torch.sinh(mu * x[..., 0])], -1),
                        lambda xa: xa[:1], lambda xb: xb[:1] - 1.0)


def line_guess(t):
    return torch.stack([t, torch.ones_like(t)], -1)


# -- structured linear solve ------------------------------------------------------------
@pytest.mark.parametrize("m", [2, 3, 5, 8, 17, 100])
def test_structured_solve_matches_dense(m):
    A = torch.tensor([[0.0, 1.0], [400.0, 0.0]], dtype=f64)
    Y = torch.linalg.matrix_exp(A / (m - 1)).expand(m - 1, 2, 2).clone()
    Y = Y + 0.01 * torch.randn(m - 1, 2, 2, dtype=f64, generator=torch.Generator().manual_seed(m))
    Ba, Bb = torch.tensor([[1.0, 0.0]], dtype=f64), torch.tensor([[1.0, 0.5]], dtype=f64)
    g = torch.Generator().manual_seed(1)
    ra, rm, rb = torch.randn(1, dtype=f64, generator=g), torch.randn(m - 1, 2, dtype=f64, generator=g), torch.randn(1, dtype=f64, generator=g)
    d = factorize(Y, Ba, Bb).solve(ra, rm, rb).reshape(-1)
    J, r = dense_matrix(Y, Ba, Bb), torch.cat([ra, rm.reshape(-1), rb])
    # backward stable: small residual relative to |J| |d|, and forward error within cond(J)·eps
    assert (J @ d - r).abs().max() <= 1e-13 * float(J.abs().max() * d.abs().max() + r.abs().max())
    ref = torch.linalg.solve(J, r)
    assert (d - ref).abs().max() <= 1e-14 * float(torch.linalg.cond(J)) * float(ref.abs().max()) + 1e-14


def test_batched_reverse_sweeps_equal_one_sweep_per_row(monkeypatch):
    """The Jacobian in chunks of cotangents (3 does not divide n = 5), one by one, and by the
    fallback when vmap fails, on a coupled non-linear system with a VJP inside the rhs."""
    from shootlab.bvp import shooting
    from shootlab.bvp.integrators import get_integrator
    A = torch.tensor([[0.0, 1.0, 0.0, 0.2, 0.0], [-1.0, 0.0, 0.3, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0, 0.1],
                      [0.0, -2.0, 0.0, 0.0, 0.0], [0.1, 0.0, 0.0, 0.0, -0.5]], dtype=f64)

    def rhs(t, x):                              # x' = A x + ∇_x (½ Σ sin(x)²): a VJP in the rhs
        with torch.enable_grad():
            xx = x if x.requires_grad else x.detach().requires_grad_(True)
            g, = torch.autograd.grad(0.5 * (torch.sin(xx) ** 2).sum(), xx, create_graph=x.requires_grad)
        return x @ A.T + g
    bvp = shootlab.BVP(rhs, lambda xa: xa[:2], lambda xb: xb[:3])
    t = torch.linspace(0.0, 1.0, 7, dtype=f64)
    s = torch.linspace(-1.0, 1.0, 35, dtype=f64).reshape(7, 5)
    sysm = shooting.ShootingSystem(bvp, t, get_integrator("rk4", steps=4))
    monkeypatch.setattr(shooting, "JACOBIAN_CHUNK", 3)
    Y3 = sysm.interval_jacobians(s)
    monkeypatch.setattr(shooting, "JACOBIAN_CHUNK", 1)
    Y1 = sysm.interval_jacobians(s)
    torch.testing.assert_close(Y3, Y1, rtol=1e-13, atol=1e-13)
    h = 1e-6                                    # and both against central differences
    cols = [(sysm.residual(s + h * e).ends - sysm.residual(s - h * e).ends) / (2 * h) for e in torch.eye(5, dtype=f64)]
    torch.testing.assert_close(Y1, torch.stack(cols, -1), rtol=1e-6, atol=1e-7)
    real_grad = torch.autograd.grad

    def no_vmap(*args, **kw):
        if kw.get("is_grads_batched"):
            raise RuntimeError("vmap: no batching rule")
        return real_grad(*args, **kw)
    monkeypatch.setattr(shooting, "JACOBIAN_CHUNK", 16)
    monkeypatch.setattr(torch.autograd, "grad", no_vmap)
    torch.testing.assert_close(sysm.interval_jacobians(s), Y1, rtol=1e-13, atol=1e-13)


def test_singular_newton_matrix_detected():
    m, n = 6, 2
    Y = torch.eye(n, dtype=f64).expand(m - 1, n, n).clone()
    Ba = torch.tensor([[1.0, 0.0]], dtype=f64)
    with pytest.raises(SingularJacobianError):
        factorize(Y, Ba, Ba.clone())          # y' = 0 with y1(a) and y1(b) fixed: y2 free


# -- Jacobians ---------------------------------------------------------------------------
@pytest.mark.parametrize("integrator", ["rk4", "dopri5", "ros4", "radau3", "implicit_euler"])
def test_autograd_interval_jacobians_match_finite_differences(integrator):
    from shootlab.bvp.integrators import get_integrator
    from shootlab.bvp.shooting import ShootingSystem
    t = torch.linspace(0.0, 1.0, 6, dtype=f64)
    s = line_guess(t) + 0.1
    sysA = ShootingSystem(troesch(2.0), t, get_integrator(integrator, steps=8, rtol=1e-10, atol=1e-12), "autograd")
    Ya = sysA.interval_jacobians(s)
    # central differences of the interval map, independent of the engine's own fd path
    h = 1e-6
    cols = []
    for j in range(2):
        e = torch.zeros(2, dtype=f64); e[j] = h
        cols.append((sysA.residual(s + e).ends - sysA.residual(s - e).ends) / (2 * h))
    Yfd = torch.stack(cols, -1)
    assert torch.allclose(Ya, Yfd, rtol=1e-5, atol=1e-6)
    Yrep = ShootingSystem(troesch(2.0), t, get_integrator(integrator, steps=8, rtol=1e-10, atol=1e-12), "fd").interval_jacobians(s)
    assert torch.allclose(Ya, Yrep, rtol=1e-4, atol=1e-5)      # report eq. 3.7, one-sided


# -- known solutions -------------------------------------------------------------------------
def test_linear_unstable_problem():
    t = torch.linspace(0.0, 1.0, 41, dtype=f64)
    res = shootlab.solve(lin400(), t, torch.zeros(41, 2, dtype=f64))
    assert res.success, res.message
    tq = torch.linspace(0.0, 1.0, 333, dtype=f64)
    exact = torch.stack([torch.exp(-20 * tq), -20 * torch.exp(-20 * tq)], -1)
    assert (res.sol(tq) - exact).abs().max() < 1e-8 * 20
    assert (res.x[:, 0] - torch.exp(-20 * t)).abs().max() < 1e-8


def test_troesch_mu5_reference_slope():
    t = torch.linspace(0.0, 1.0, 101, dtype=f64)
    res = shootlab.solve(troesch(5.0), t, line_guess(t))
    assert res.success, res.message
    assert abs(float(res.x[0, 1]) - 0.04575046) < 1e-7


# -- Newton strategies and continuation -----------------------------------------------------------
def test_fixed_jacobian_strategy_saves_jacobians():
    t = torch.linspace(0.0, 1.0, 101, dtype=f64)
    res = shootlab.solve(troesch(5.0), t, line_guess(t), integrator="rk4", steps=8)
    assert res.success and res.jacobian_evaluations < res.iterations
    assert any(row["jacobian"] == "reused" for row in res.history)


def test_a_kept_jacobian_gets_the_full_step_only():
    """With a stale Jacobian the line search tries λ = 1 once and gives up (the Jacobian is then
    refreshed); with a fresh one it backtracks."""
    from types import SimpleNamespace
    from shootlab.bvp.step_length import armijo_search
    calls = []

    class Quadratic:                 # F(s) = s − 1 along the direction δ = 4 (1 − s): overshoots
        def residual(self, s):
            calls.append(float(s[0]))
            return SimpleNamespace(F=s - 1.0)
    s, F = torch.zeros(1, dtype=f64), -torch.ones(1, dtype=f64)
    delta = torch.full((1,), 4.0, dtype=f64)
    assert armijo_search(Quadratic(), s, F, delta, full_only=True) is None and calls == [4.0]
    calls.clear()
    found = armijo_search(Quadratic(), s, F, delta)
    assert found is not None and found[3] < 1.0 and len(calls) > 1 and abs(found[0][0] - 1.0) < 0.9


def test_looser_jacobians_only_for_the_strategy_that_takes_them():
    t = torch.linspace(0.0, 1.0, 21, dtype=f64)
    for newton, loose in (("deuflhard", True), ("armijo", False), ("appendix_a", False)):
        res = shootlab.solve(lin400(), t, line_guess(t), newton=newton, rtol=1e-8, atol=1e-10)
        assert res.success and res._system.loose_jacobian is loose
    with pytest.raises(ValueError, match="jacobian_rtol"):
        shootlab.solve(lin400(), t, line_guess(t), jacobian_rtol=-1.0)


def test_damped_steps_toward_a_root_at_infinity_are_not_convergence():
    """atan(x(0)) = 2 has no root: the damped steps push x(0) out to ~1e9, where the relative test
    max|F| ≤ tol·(1 + max|s|) had passed with |F| = 0.43 (success with garbage).  The test's scale
    is that of the last iterate a full step reached: the damping floor is reported, with the hint
    to form the Jacobians at the residual's tolerance only where they were looser."""
    bvp = shootlab.BVP(lambda t, x: torch.stack([x[..., 1], torch.zeros_like(x[..., 0])], -1),
                       lambda xa: torch.atan(xa[:1]) - 2.0, lambda xb: xb[:1] - 1.0)
    t = torch.linspace(0.0, 1.0, 11, dtype=f64)
    for jacobian_rtol, hint in (("auto", True), (None, False)):
        res = shootlab.solve(bvp, t, line_guess(t), integrator="dopri5", rtol=1e-8, atol=1e-10,
                             jacobian_rtol=jacobian_rtol)
        assert not res.success and res.status == 4 and res.residual_norm > 0.4
        assert ("jacobian_rtol=None" in res.message) is hint


def test_musn_baseline_runs_and_converges_on_easy_problem():
    t = torch.linspace(0.0, 1.0, 101, dtype=f64)
    res = shootlab.solve(troesch(5.0), t, line_guess(t), integrator="rk4", steps=8, newton="appendix_a")
    assert res.success, res.message
    assert abs(float(res.x[0, 1]) - 0.04575046) < 1e-6


def test_continuation_records_stages_and_reaches_final_accuracy():
    t = torch.linspace(0.0, 1.0, 101, dtype=f64)
    res = shootlab.solve(troesch(5.0), t, line_guess(t),
                         continuation=[dict(integrator="euler", steps=1, tol=1e-6), dict(integrator="rk4", steps=2),
                                       dict(integrator="ros4", rtol=1e-10, atol=1e-12)])
    assert res.success, res.message
    assert len(res.stages) == 3 and all(s["success"] for s in res.stages)
    assert abs(float(res.x[0, 1]) - 0.04575046) < 1e-7
    counts = [s["iterations"] for s in res.stages]            # the message counts the whole continuation
    assert res.iterations == sum(counts)
    assert f"after {sum(counts)} iterations in 3 stages ({' + '.join(map(str, counts))})" in res.message


# -- failures are reported, never raised or hidden ------------------------------------------------
def test_overflow_is_reported_cleanly_by_musn():
    # one shooting interval on Troesch mu = 10 with an Euler start: the IVP overflows
    t = torch.linspace(0.0, 1.0, 3, dtype=f64)
    g = line_guess(t)
    g[:, 1] = 50.0
    res = shootlab.solve(troesch(10.0), t, g, integrator="rk4", steps=4, newton="appendix_a", max_growth=None)
    assert not res.success
    assert res.status in (2, 4) and ("interval" in res.message or "damping" in res.message)


def test_press_names_overflowing_steps_when_it_runs_out_of_iterations():
    # F(s) = s − 10 whose IVPs "overflow" more than 0.5 beyond the last point integrated: every full
    # Newton step fails, press cuts it back instead of stopping (MUSN would stop), and when it runs
    # out of iterations it says why
    from types import SimpleNamespace

    from shootlab.bvp.newton import ArmijoNewton
    from shootlab.bvp.shooting import IntegrationFailure

    class Stub:
        last = 0.0

        def residual(self, s):
            if float(s.max()) > self.last + 0.5:
                raise IntegrationFailure("non-finite value (overflow)", 0, 0.0, 1.0)
            self.last = float(s.max())
            return SimpleNamespace(F=s - 10.0)

        def linearize(self, s):
            return None

        def newton_step(self, fac, F):
            return -F
    out = ArmijoNewton(max_iter=3).run(Stub(), torch.zeros(2, dtype=f64))
    assert out.status == 1 and out.iterations == 3
    assert "diverging" in out.message and "3 of 3 iterations" in out.message and "overflow" in out.message


def test_max_iter_reported():
    t = torch.linspace(0.0, 1.0, 21, dtype=f64)
    res = shootlab.solve(troesch(5.0), t, line_guess(t), max_iter=1)
    assert not res.success and res.status == 1 and "maximum number of iterations" in res.message
    assert res.residual_norm > 1e-10


def test_verbose_prints_one_line_per_iteration(capsys):
    t = torch.linspace(0.0, 1.0, 21, dtype=f64)
    res = shootlab.solve(troesch(5.0), t, line_guess(t), integrator="rk4", steps=8, verbose=True)
    lines = [l for l in capsys.readouterr().out.splitlines() if l.strip() and l.split()[0].isdigit()]
    assert len(lines) == res.iterations + 1


# -- bad input ------------------------------------------------------------------------------------
def test_bad_input_raises_clear_errors():
    prob = troesch(5.0)
    t = torch.linspace(0.0, 1.0, 11, dtype=f64)
    with pytest.raises(ValueError, match="strictly increasing"):
        shootlab.solve(prob, t.flip(0), line_guess(t))
    with pytest.raises(ValueError, match="shape"):
        shootlab.solve(prob, t, line_guess(t)[:-1])
    bad = line_guess(t); bad[3, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        shootlab.solve(prob, t, bad)
    wrong_bc = shootlab.BVP(prob.rhs, lambda xa: xa, lambda xb: xb[:1] - 1.0)
    with pytest.raises(ValueError, match="equations"):
        shootlab.solve(wrong_bc, t, line_guess(t))
    with pytest.raises(ValueError, match="unknown"):
        shootlab.solve(prob, t, line_guess(t), integrator="nope")
    with pytest.raises(ValueError, match="unknown newton"):
        shootlab.solve(prob, t, line_guess(t), newton="nope")


def test_numpy_inputs_accepted():
    t = np.linspace(0.0, 1.0, 21)
    res = shootlab.solve(troesch(5.0), t, np.stack([t, np.ones_like(t)], -1), integrator="rk4", steps=8)
    assert res.success and res.x.dtype == f64


def test_interval_growth_survives_a_lapack_failure_and_non_finite_jacobians(monkeypatch):
    from shootlab.bvp import shooting, spectrum
    J = torch.tensor([[[0.0, 1.0], [4.0, 0.0]], [[-3.0, 0.0], [0.0, 2.0]]], dtype=torch.float64)
    real = torch.linalg.eigvals

    def flaky(A):   # LAPACK's batched QR iteration gives up (as it did on a nearly defective matrix)
        if A.ndim == 3:
            raise torch.linalg.LinAlgError("failed to converge")
        return real(A)
    monkeypatch.setattr(torch.linalg, "eigvals", flaky)
    torch.testing.assert_close(spectrum.spectral_bounds(J)[1], torch.tensor([2.0, 2.0], dtype=torch.float64))

    def second_fails(A):   # ... and on one matrix even alone: its row is NaN, the bound is Gershgorin's
        if A.ndim == 3 or A[0, 0] == -3.0:
            raise torch.linalg.LinAlgError("failed to converge")
        return real(A)
    monkeypatch.setattr(torch.linalg, "eigvals", second_fails)
    ev = spectrum.batched_eigvals(J)
    assert torch.isnan(ev[1]).all() and sorted(ev[0].real.tolist()) == pytest.approx([-2.0, 2.0])
    torch.testing.assert_close(spectrum.spectral_bounds(J)[1], torch.tensor([2.0, 2.0], dtype=torch.float64))
    monkeypatch.undo()
    bvp = shootlab.BVP(lambda t, y: torch.stack([y[..., 1], y[..., 0] ** 2 * 1e308 * 1e10], -1),
                       lambda ya: ya[..., :1], lambda yb: yb[..., :1])
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    g = shooting.interval_growth(bvp, t, torch.ones(5, 2, dtype=torch.float64))
    assert g.shape == (4,) and torch.isfinite(g).all()


def test_press_line_search_backtracks_monotonically_after_an_overflow():
    # an overflow at λ = 1 sets λ = 0.1; the quadratic model must then use λ = 0.1, not 1 (written for
    # λ = 1 it proposed λ ≥ 0.5 again, overflowed, and cycled for ever on confined N = 3, rk4, m = 340)
    from types import SimpleNamespace

    from shootlab.bvp.step_length import armijo_search
    from shootlab.bvp.shooting import IntegrationFailure

    trials = []

    class Stub:
        def residual(self, s):
            lam = float(s[0])
            trials.append(lam)
            if lam > 0.2:
                raise IntegrationFailure("non-finite value (overflow)", 0, 0.0, 1.0)
            return SimpleNamespace(F=torch.tensor([1.0 + 50.0 * lam], dtype=f64))   # uphill: keep backtracking

    s0 = torch.zeros(1, dtype=f64)
    F0 = torch.ones(1, dtype=f64)
    assert armijo_search(Stub(), s0, F0, torch.ones(1, dtype=f64), min_step=1e-6) is None
    assert trials[0] == 1.0 and trials[1] == pytest.approx(0.1)
    assert all(b < a for a, b in zip(trials[1:], trials[2:])) and len(trials) < 40


def test_allocator_settings_are_applied_on_linux_glibc():
    """shootlab.bvp.allocator: the heap settings that keep large tensors out of fresh mmap pages are in
    effect after import (on glibc; elsewhere tune() reports False and changes nothing)."""
    import platform

    from shootlab.bvp.allocator import tune
    libc, _ = platform.libc_ver()
    assert tune() is (libc == "glibc" and os.environ.get("SHOOTLAB_MALLOC", "").lower() != "default")


def test_problems_solved_together_are_each_solved_alone():
    """Two TPBVPs with one right-hand side — x'' = −x on [0, 1] with x(0) = a, x(1) = b — and their
    own boundary values, one undamped step each from different guesses (exact for a linear
    problem) as one batch of intervals (``solve_together``): each solution x = a cos t +
    (b − a cos 1)/sin 1 · sin t to the RK4 error, and each as ``solve`` alone gives it bit for bit;
    an adaptive integrator is not run together (None)."""
    def rhs(t, y):
        return torch.stack([y[..., 1], -y[..., 0]], -1)

    ends = [(0.5, -1.0), (2.0, 3.0)]
    probs = [shootlab.BVP(rhs, lambda ya, a=a: ya[:1] - a, lambda yb, b=b: yb[:1] - b) for a, b in ends]
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    guesses = [torch.zeros(11, 2, dtype=torch.float64), torch.ones(11, 2, dtype=torch.float64)]
    opts = dict(integrator="rk4", steps=4, newton="undamped", max_iter=1, max_growth=None)
    together, values = shootlab.bvp.solver.solve_together(probs, t, guesses, **opts)
    for (a, b), res, guess, prob in zip(ends, together, guesses, probs):
        exact = a * torch.cos(t) + (b - a * math.cos(1.0)) / math.sin(1.0) * torch.sin(t)
        assert res.success and float((res.x[:, 0] - exact).abs().max()) < 1e-6
        alone = shootlab.solve(prob, t, guess, **opts)
        assert torch.equal(res.x, alone.x) and res.message == alone.message
    on_steps = torch.linspace(0.0, 1.0, 41, dtype=torch.float64)
    for X, res in zip(values(on_steps), together):
        assert torch.equal(X, res.sol(on_steps, grid=True))
    assert shootlab.bvp.solver.solve_together(probs, t, guesses, **dict(opts, integrator="dopri5")) is None


def test_a_problem_solved_together_whose_step_cannot_be_integrated_is_left_alone():
    """x'' = e^x with x(0) = 0, x(1) = b from x = 0: for b = 0.1 the step is taken together and is
    the one ``solve`` takes alone; for b = 800 the full step puts e^x beyond float64's range, so
    that problem comes back as None (``solve`` alone shortens that step) and the other is not
    disturbed."""
    def rhs(t, y):
        return torch.stack([y[..., 1], torch.exp(y[..., 0])], -1)

    probs = [shootlab.BVP(rhs, lambda ya: ya[:1], lambda yb, b=b: yb[:1] - b) for b in (0.1, 800.0)]
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    guesses = [torch.zeros(11, 2, dtype=torch.float64)] * 2
    opts = dict(integrator="rk4", steps=4, newton="undamped", max_iter=1, max_growth=None)
    (small, large), _ = shootlab.bvp.solver.solve_together(probs, t, guesses, **opts)
    assert large is None
    alone = shootlab.solve(probs[0], t, guesses[0], **opts)
    assert torch.equal(small.x, alone.x) and small.message == alone.message
    assert shootlab.solve(probs[1], t, guesses[1], **opts).history[-1]["step"] < 1.0


def test_swept_values_at_many_times():
    """ShootingResult.swept at increasing times: on the step grid the scheme's own values (as
    sol(grid=True)), off it one pass through the intervals for an explicit scheme — the exact flow
    from each interval's shooting point to 1e-12 (RK4 steps ≤ 0.003), closer than each time's own
    four steps (sol) — and, for an implicit scheme, each time from its shooting point as sol gives
    it, bit for bit."""
    def rhs(t, y):
        return torch.stack([y[..., 1], -y[..., 0]], -1)

    prob = shootlab.BVP(rhs, lambda ya: ya[:1] - 0.5, lambda yb: yb[:1] + 1.0)
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    on = torch.linspace(0.0, 1.0, 41, dtype=torch.float64)
    off = torch.linspace(0.0, 1.0, 333, dtype=torch.float64)
    for name in ("rk4", "midpoint"):
        res = shootlab.solve(prob, t, torch.zeros(11, 2, dtype=torch.float64), integrator=name, steps=4,
                             max_growth=None)
        assert res.success, res.message
        assert torch.equal(res.swept(on), res.sol(on, grid=True))
        if name == "midpoint":
            assert torch.equal(res.swept(off), res.sol(off))
        else:
            i = (torch.searchsorted(t, off, right=True) - 1).clamp(0, 9)
            c, s = torch.cos(off - t[i]), torch.sin(off - t[i])
            y0 = res.x[i]
            flow = torch.stack([c * y0[:, 0] + s * y0[:, 1], -s * y0[:, 0] + c * y0[:, 1]], -1)
            err = float((res.swept(off) - flow).abs().max())
            assert err < 1e-12 and err < float((res.sol(off) - flow).abs().max())
    with pytest.raises(ValueError, match="must lie in"):
        res.swept(torch.tensor([2.0], dtype=torch.float64))


@pytest.mark.parametrize("m", [2, 3, 17, 38])
def test_initial_value_conditions_solve_by_forward_substitution(m):
    """All n conditions at a (B_a regular, none at b): the log-depth scan of
    ``solve_initial_value`` is the dense solution of the Newton system to 1e-12 of its size, two
    systems at once; a singular B_a is flagged."""
    from shootlab.bvp.linalg import solve_initial_value

    g = torch.Generator().manual_seed(m)
    Y = 0.5 * torch.randn(2, m - 1, 3, 3, dtype=f64, generator=g)
    Ba = torch.eye(3, dtype=f64) + 0.3 * torch.randn(2, 3, 3, dtype=f64, generator=g)
    ra, rm = torch.randn(2, 3, dtype=f64, generator=g), torch.randn(2, m - 1, 3, dtype=f64, generator=g)
    d, singular = solve_initial_value(Y, Ba, ra, rm)
    for k in range(2):
        J = dense_matrix(Y[k], Ba[k], torch.zeros(0, 3, dtype=f64))
        want = torch.linalg.solve(J, torch.cat([ra[k], rm[k].reshape(-1)])).reshape(m, 3)
        assert float((d[k] - want).abs().max()) <= 1e-12 * float(want.abs().max())
    assert not singular.any()
    assert solve_initial_value(Y, torch.zeros_like(Ba), ra, rm)[1].all()


@pytest.mark.parametrize("name,steps", [("rk4", 3), ("radau3", 2), ("implicit_euler", 2)])
def test_frozen_interval_jacobians_are_exact_for_a_linear_system(name, steps):
    """y'' = 400 y (constant Jacobian): the linearisation at each interval's start, R(hJ)^steps
    (``jacobian="frozen"``), is the scheme's interval Jacobian — the forward sensitivities to 1e-12
    of their size — so one undamped Newton step solves the TPBVP, to the same shooting points as
    with the forward sensitivities; an adaptive scheme has no such map and is refused."""
    t = torch.linspace(0.0, 1.0, 21, dtype=f64)
    s = line_guess(t)
    integ = shootlab.bvp.integrators.get_integrator(name, steps=steps)
    frozen = shootlab.bvp.shooting.ShootingSystem(lin400(), t, integ, jacobian="frozen").interval_jacobians(s)
    exact = shootlab.bvp.shooting.ShootingSystem(lin400(), t, integ).interval_jacobians(s)
    assert float((frozen - exact).abs().max()) <= 1e-12 * float(exact.abs().max())
    opts = dict(integrator=name, steps=steps, newton="undamped", max_growth=None)
    quasi = shootlab.solve(lin400(), t, s, jacobian="frozen", **opts)
    forward = shootlab.solve(lin400(), t, s, **opts)
    assert quasi.success and quasi.iterations == forward.iterations == 1
    assert float((quasi.x - forward.x).abs().max()) <= 1e-10
    with pytest.raises(ValueError, match="frozen"):
        shootlab.solve(lin400(), t, s, integrator="dopri5", jacobian="frozen")


def test_problems_solved_together_give_up_where_they_stall():
    """atan(x(0)) = 0 with x' = 0 from x = 2: each full Newton step overshoots further (x = 2 → −3.5
    → 13.9 → …, |F| → π/2), so max|F| never halves: with ``stall=3`` ``solve_together`` stops that
    problem after 3 steps with STEP_TOO_SMALL, where without it runs to ``max_iter``; the other
    problem, atan(x(0)) = 0 from x = 0.5, converges in the steps it takes alone (its corrections
    by forward substitution instead of cyclic reduction: the same to rounding)."""
    probs = [shootlab.BVP(lambda t, x: 0.0 * x, lambda xa: torch.atan(xa[:1]), lambda xb: xb[:0])] * 2
    t = torch.linspace(0.0, 1.0, 3, dtype=f64)
    guesses = [torch.full((3, 1), 2.0, dtype=f64), torch.full((3, 1), 0.5, dtype=f64)]
    opts = dict(integrator="rk4", steps=1, newton="undamped", max_iter=4, max_growth=None)
    (stuck, fine), _ = shootlab.bvp.solver.solve_together(probs, t, guesses, stall=3, **opts)
    assert stuck.status == shootlab.Status.STEP_TOO_SMALL and stuck.iterations == 3
    alone = shootlab.solve(probs[1], t, guesses[1], **opts)
    assert fine.success and alone.success and fine.iterations == alone.iterations
    assert float((fine.x - alone.x).abs().max()) <= 1e-15
    (running, _), _ = shootlab.bvp.solver.solve_together(probs, t, guesses, **opts)
    assert running.status == shootlab.Status.MAX_ITER
