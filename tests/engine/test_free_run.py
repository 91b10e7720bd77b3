"""Free runs (shootlab/estimation/free_run.py): the stiff path by Radau IIA against exact solutions,
the parallel scans against the sample-by-sample runs, the least-squares solution of ζ."""
import math

import pytest
import torch

import shootlab.estimation.free_run as fr

D = torch.float64


def test_radau_on_samples_is_third_order_and_damps_the_stiff_mode():
    """s' = λ (s − g(t)) + g'(t) with g = sin t and λ = −1e5: s = g + (s0 − g(0)) e^{λt}; the
    stiff transient is gone after the first sample and the slow part is followed to order 3."""
    lam = -1e5

    def rhs(t, s):
        return lam * (s - torch.sin(t)[..., None]) + torch.cos(t)[..., None]

    errors = []
    for samples in (21, 41):
        ts = torch.linspace(0.0, 2.0, samples, dtype=D)
        S = fr._radau_on_samples(rhs, torch.tensor([1.0], dtype=D), ts)
        exact = torch.sin(ts)                 # the transient e^{λt} is below 1e-200 after one sample
        errors.append(float((S[1:, 0] - exact[1:]).abs().max()))
    assert errors[1] < 1e-6
    assert errors[1] < errors[0] / 4            # halving the samples' spacing: order ≥ 2 seen


def test_radau_on_samples_reports_a_failed_iteration_as_none():
    def rhs(t, s):                       # a finite-time blow-up: Newton cannot follow it
        return 1e6 * s ** 3

    assert fr._radau_on_samples(rhs, torch.tensor([1.0], dtype=D), torch.linspace(0, 1, 5, dtype=D)) is None


def test_radau_contraction_estimate_keeps_a_nonlinear_stiff_run_accurate():
    """s' = λ (s − sin t) + cos t − s³/10 (stiff, non-linear: the Jacobian taken once per sample is
    not exact within it): the stopping rule on the contraction's error estimate leaves the run
    within 1e-9 of the same scheme iterated to a correction of 1e-14."""
    lam = -1e4

    def rhs(t, s):
        return lam * (s - torch.sin(t)[..., None]) + torch.cos(t)[..., None] - s ** 3 / 10

    ts = torch.linspace(0.0, 2.0, 41, dtype=D)
    loose = fr._radau_on_samples(rhs, torch.tensor([1.0], dtype=D), ts)
    tight = fr._radau_on_samples(rhs, torch.tensor([1.0], dtype=D), ts, tol=1e-14, max_newton=50)
    assert float((loose - tight).abs().max()) < 1e-9


def test_radau_in_parallel_is_the_sample_by_sample_run(monkeypatch):
    """All sample intervals at once (multiple shooting of the free run by the engine, the samples
    as shooting points) give the sample-by-sample states to 1e-9: a linear stiff system in one
    Newton step (the frozen interval Jacobians R(hJ)⁴ are exact for it), a non-linear one (a
    quasi-Newton) in at most five; two systems as one batch.
    A run Newton cannot follow gives None (the caller then goes sample by sample)."""
    steps = []
    together = fr.solve_together

    def counted(*a, **k):
        out = together(*a, **k)
        steps.append([r.iterations if r else None for r in out[0]])
        return out
    monkeypatch.setattr(fr, "solve_together", counted)
    ts = torch.linspace(0.0, 2.0, 41, dtype=D)
    s0 = torch.tensor([[1.0], [-0.5]], dtype=D)
    for cubic, most in ((0.0, 1), (0.1, 5)):
        def rhs(t, s):
            return -1e4 * (s - torch.sin(t)[..., None]) + torch.cos(t)[..., None] - cubic * s ** 3
        par = fr._radau_in_parallel(rhs, s0, ts)
        seq = fr._radau_on_samples(rhs, s0, ts)
        assert par.shape == seq.shape == (41, 2, 1)
        assert float((par - seq).abs().max()) < 1e-9
        assert all(1 <= k <= most for k in steps[-1]), steps
    assert fr._radau_in_parallel(lambda t, s: 1e6 * s ** 3, torch.tensor([1.0], dtype=D),
                                 torch.linspace(0, 1, 5, dtype=D)) is None


def test_rk4_in_parallel_is_the_sample_by_sample_run():
    """A damped Duffing oscillator driven by cos t (non-linear: Y_k = R(h J_k) from the Jacobian at
    the interval's start is a quasi-Newton), two systems as one batch, 201 samples: the run with
    all intervals at once equals RK4 sample by sample to a tenth of the Newton test's 1e-9 (1 + max|S|)
    (the last correction, with Y_k frozen, leaves the defect times the contraction rate);
    a stiff system is refused as such, and a run whose sweeps run out is not called stiff (the
    caller then goes sample by sample)."""
    def rhs(t, s):
        x, v = s[..., 0], s[..., 1]
        return torch.stack([v, -0.3 * v - x - 2.0 * x ** 3 + torch.cos(t)], -1)

    ts = torch.linspace(0.0, 10.0, 201, dtype=D)
    s0 = torch.tensor([[1.0, 0.0], [-0.5, 0.3]], dtype=D)
    par, stiff = fr._rk4_in_parallel(rhs, s0, ts)
    seq = fr._rk4_on_samples(rhs, s0, ts)
    assert not stiff and par.shape == seq.shape == (201, 2, 2)
    assert float((par - seq).abs().max()) < 1e-10 * (1 + float(seq.abs().max()))
    assert fr._rk4_in_parallel(lambda t, s: -1e4 * s, s0, ts) == (None, True)
    assert fr._rk4_in_parallel(rhs, s0, ts, sweeps=3) == (None, False)     # not converged: not stiff either


def test_least_squares_solution_matches_lstsq_and_falls_back_on_rank_deficiency():
    """ζ of the free run: LU for square F_s, QR for tall, both equal to ``torch.linalg.lstsq`` to
    rounding; a batch with a singular (square) or rank-deficient (tall) row takes the minimum-norm
    least squares (``lstsq`` itself differs from call to call in the last digits)."""
    gen = torch.Generator().manual_seed(3)
    for rows in (7, 9):
        Fs = torch.randn(50, rows, 7, generator=gen, dtype=D)
        rs = torch.randn(50, rows, generator=gen, dtype=D)
        want = torch.linalg.lstsq(Fs, rs.unsqueeze(-1)).solution.squeeze(-1)
        got = fr._least_squares_solution(Fs, rs)
        assert torch.allclose(got, want, rtol=1e-10, atol=1e-12)
        Fs[17, :, 3] = Fs[17, :, 5]                 # two equal columns: rank 6
        got = fr._least_squares_solution(Fs, rs)
        want = torch.linalg.lstsq(Fs, rs.unsqueeze(-1)).solution.squeeze(-1)
        assert torch.allclose(got, want, rtol=1e-10, atol=1e-12)
        assert abs(float(got[17, 3] - got[17, 5])) < 1e-12      # the minimum norm: no part along e3 − e5


def test_least_squares_solution_of_a_blown_up_row_is_nan_and_the_others_unchanged():
    """A run gone non-finite (NaN in F_s, inf in r_s) gets NaN ζ on its own rows only."""
    gen = torch.Generator().manual_seed(4)
    for rows in (7, 9):
        Fs = torch.randn(5, rows, 7, generator=gen, dtype=D)
        rs = torch.randn(5, rows, generator=gen, dtype=D)
        want = fr._least_squares_solution(Fs, rs)
        Fs[1, 2, 3], rs[3, 0] = math.nan, math.inf
        got = fr._least_squares_solution(Fs, rs)
        assert bool(torch.isnan(got[[1, 3]]).all())
        assert torch.allclose(got[[0, 2, 4]], want[[0, 2, 4]], rtol=1e-12, atol=1e-14)


def test_a_run_whose_sweeps_fail_over_the_whole_record_is_run_in_windows():
    """Van der Pol's oscillator (μ = 1) from near its unstable rest, 40 s at 10 Hz, two systems as one
    batch: the sweeps about the constant start fail over the whole record (the linearisation there
    grows as e^{t/2}); in windows, shortened where they fail and lengthened where they converge, the
    run equals RK4 sample by sample to the Newton test's 1e-9 (1 + max|S|), no window going sample
    by sample.  Where every window fails, each of MIN_WINDOW intervals is run by the fallback from
    where the one before ended — the fallback's own run."""
    def rhs(t, s):
        x, v = s[..., 0], s[..., 1]
        return torch.stack([v, (1 - x ** 2) * v - x], -1)

    ts = torch.linspace(0.0, 40.0, 401, dtype=D)
    s0 = torch.tensor([[0.01, 0.0], [-0.02, 0.01]], dtype=D)
    assert fr._rk4_in_parallel(rhs, s0, ts) == (None, False)
    widths = []

    def shoot(s, t):
        widths.append(t.numel() - 1)
        return fr._shoot_samples(fr._rk4(), rhs, s, t)
    run = fr._in_windows(shoot, s0, ts, lambda s, t: pytest.fail("a window went sample by sample"))
    seq = fr._rk4_on_samples(rhs, s0, ts)
    assert run.shape == seq.shape == (401, 2, 2)
    assert float((run - seq).abs().max()) <= 1e-9 * (1 + float(seq.abs().max()))
    assert widths[0] == 100 and min(widths) < 100, widths                     # cut where one failed
    assert any(b == 2 * a for a, b in zip(widths, widths[1:])), widths        # doubled where one converged
    alone = []
    run = fr._in_windows(lambda s, t: None, s0[0], ts[:41],
                         lambda s, t: alone.append(t.numel() - 1) or fr._rk4_on_samples(rhs, s, t))
    assert alone == [fr.MIN_WINDOW] * 5 and torch.equal(run, fr._rk4_on_samples(rhs, s0[0], ts[:41]))
