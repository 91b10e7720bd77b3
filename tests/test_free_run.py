"""Free runs (shootlab/free_run.py): the stiff path by Radau IIA against exact and LSODA solutions."""
import numpy as np
import pytest
import torch

import shootlab.estimation.free_run as fr
from mixtures.identification import model as confined
from mixtures.simulation import simulated_measurements

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


@pytest.mark.parametrize("elements", [3, 6])
def test_stiff_free_run_agrees_with_lsoda(elements, monkeypatch):
    data = simulated_measurements(elements=elements, noise=0.0)
    md = confined(elements=elements)
    params, x0 = dict(H=2.0, K=1.0), np.zeros(elements)
    radau = fr.simulate(md, data, params, x0)
    monkeypatch.setattr(fr, "_radau_on_samples", lambda *a, **k: None)          # the LSODA fallback
    lsoda = fr.simulate(md, data, params, x0)
    for ch in ("displacement", "pressure"):
        assert np.abs(radau[ch] - lsoda[ch]).max() <= 1e-4 * np.ptp(lsoda[ch]), ch
    # and both reproduce the finite-element simulation that made the record (no noise), up to the
    # load between samples: the record's simulator had the exact ramp, the free run its samples
    assert np.abs(radau["displacement"] - data.channels["displacement"]).max() <= 3e-4 * np.ptp(lsoda["displacement"])


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


def test_the_free_runs_jacobian_is_central_differences_of_its_rhs(monkeypatch):
    """The free run's own Jacobian (ζ's derivative from the least squares' QR factor; F
    differenced only where it moves with the states) against central differences of the whole
    right-hand side: the confined model (F independent of the states) and with a strain-dependent
    permeability (F moves with them), to 1e-8 of the largest entry."""
    from mixtures.effects import library as mixture_library
    from shootlab.diagnosis.composition import extend
    from shootlab.bvp.tangents import VectorField

    data = simulated_measurements(elements=3, noise=0.0)
    md = confined(elements=3)
    seen = []
    run = fr._radau_in_parallel
    monkeypatch.setattr(fr, "_radau_in_parallel", lambda rhs, *a, **k: seen.append(rhs) or run(rhs, *a, **k))
    lib = mixture_library(md)
    richer = extend(md, [lib["strain_dependent_permeability"]], data=data)
    for m in (md, richer):
        params = dict(m.prior, H=2.0, K=1.0)
        params.update({k: 0.5 for k in params if k not in ("H", "K")})
        fr.simulate(m, data, params, np.zeros(3))
        field = seen[-1]
        assert isinstance(field, VectorField)
        gen = torch.Generator().manual_seed(0)
        s = 1e-2 * torch.randn(50, 3, generator=gen, dtype=D)
        tt = torch.linspace(0.1, float(data.t[-1]), 50, dtype=D)
        own = field.jacobian(tt, s)[1]
        fd = fr._jacobian(field.fun, tt, s)
        assert float((own - fd).abs().max()) <= 1e-8 * float(fd.abs().max()), m.name


def test_simulate_many_equals_one_run_per_parameter_set():
    """Several parameter sets as one batch give each set's own free run: the stiff path (the
    confined model, Radau IIA, to 1e-10 of each channel's range) and the non-stiff one (the
    mass–spring–damper, RK4, to 1e-12); mismatched starts are a clear error."""
    from manipulators.msd import model as msd_model
    from manipulators.rig import msd_data
    from shootlab.estimation.data import Measurements

    data = simulated_measurements(elements=3, noise=0.0)
    sets = [dict(H=2.0, K=1.0), dict(H=2.00002, K=1.0), dict(H=1.5, K=0.7)]
    md = confined(elements=3)
    many = fr.simulate_many(md, data, sets, [np.zeros(3)] * 3)
    for ps, run in zip(sets, many):
        one = fr.simulate(md, data, ps, np.zeros(3))
        for ch in ("displacement", "pressure"):
            assert np.abs(run[ch] - one[ch]).max() <= 1e-10 * np.ptp(one[ch]), (ps, ch)
    t = np.linspace(0.0, 2.0, 201)
    d = msd_data(t=t, m=2.0, b=0.5, k=3.0, noise=0.0, seed=0)
    rec = Measurements(d["t"], {"u": d["u"], "s": d["s"]})
    sets = [dict(m=2.0, b=0.5, k=3.0), dict(m=1.0, b=0.1, k=5.0)]
    starts = [[0.0, 0.0], [0.01, -0.02]]
    many = fr.simulate_many(msd_model(), rec, sets, starts)
    for ps, x0, run in zip(sets, starts, many):
        one = fr.simulate(msd_model(), rec, ps, x0)
        assert np.abs(run["s"] - one["s"]).max() <= 1e-12 * np.ptp(one["s"])
        assert np.array_equal(run["t"], one["t"])
    with pytest.raises(ValueError, match="2 parameter sets but 1 initial states"):
        fr.simulate_many(msd_model(), rec, sets, starts[:1])


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
