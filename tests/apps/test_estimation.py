"""Optimal estimation of the mass–spring–damper (report §3.4, DESIGN §1 and §3).

To keep the file fast on a small machine most estimations use 51 shooting points and RK4
with 5 steps per interval (step 0.04 on the 10 s record) instead of the model's default
101 points × 10 steps; the TPBVP, data and weights are the report's.  The CLI test runs
the model's own defaults once.
"""
from __future__ import annotations

import dataclasses
import json
import math
import textwrap

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline
from scipy.optimize import least_squares
from scipy.signal import savgol_filter

from manipulators import msd
from manipulators.rig import msd_data, msd_noisy_data, save_csv
from shootlab.cli import main
from shootlab.estimation.data import Interpolant, Measurements
from shootlab.estimation.optimality import EstimationProblem
from shootlab.estimation import estimate

TRUE = dict(m=1.0, b=1.0, k=1.0)
FAST = dict(n_points=51, integrator="rk4", steps=5)


def start(value: float) -> dict[str, float]:
    return dict(m=value, b=value, k=value)


def measured(d: dict) -> dict[str, np.ndarray]:
    return {k: d[k] for k in ("t", "u", "s")}


def rel_err(est: dict, ref: dict) -> float:
    return max(abs(est[k] - ref[k]) / abs(ref[k]) for k in ref)


@pytest.fixture(scope="module")
def clean():
    """Noise-free data on [0, 10], 1001 samples, the default multisine input."""
    return msd_data()


@pytest.fixture(scope="module")
def from10(clean):
    return estimate(msd.model(), measured(clean), initial=start(10.0), **FAST)


# -- noise-free recovery --------------------------------------------------------------------
def test_press_recovers_parameters_from_10(from10):
    res = from10
    assert res.success, res.message
    assert rel_err(res.parameters, TRUE) < 5e-3, res.parameters
    assert res.shooting.residual_norm < 1e-8
    assert res.J < 1e-6            # noise-free data: the true trajectory has (nearly) zero cost


def test_press_recovers_parameters_from_50(clean):
    res = estimate(msd.model(), measured(clean), initial=start(50.0), **FAST)
    assert res.success, res.message
    assert rel_err(res.parameters, TRUE) < 5e-3, res.parameters


# -- 1 % measurement noise ------------------------------------------------------------------
def _smoothed_states(data: Measurements, t: torch.Tensor) -> torch.Tensor:
    """Initial s, v from a Savitzky–Golay fit (window 0.5 s, cubic) instead of raw central
    differences, which amplify 1 % noise on s into ~70 % noise on v at dt = 0.01."""
    dt = float(data.t[1] - data.t[0])
    s = savgol_filter(data.channels["s"], 51, 3)
    v = savgol_filter(data.channels["s"], 51, 3, deriv=1, delta=dt)
    return Interpolant(Measurements(data.t, {"s": s, "v": v}), ["s", "v"], t.dtype, t.device).values(t)


def test_press_with_one_percent_noise():
    """1 % noise (std = 1 % of the RMS of s, resp. u): m, b, k within 5 % from 10, with a
    smoothed initial approximation of the states (the test below uses the model's default)."""
    model = dataclasses.replace(msd.model(), initial_states=_smoothed_states)
    res = estimate(model, measured(msd_noisy_data(0.01)), initial=start(10.0), **FAST)
    assert res.success, res.message
    assert rel_err(res.parameters, TRUE) < 0.05, res.parameters


def test_press_with_one_percent_noise_default_initial_approximation():
    res = estimate(msd.model(), measured(msd_noisy_data(0.01)), initial=start(10.0), max_iter=15, **FAST)
    assert res.success, res.message
    assert rel_err(res.parameters, TRUE) < 0.05, res.parameters


# -- independent check: output-error least squares -------------------------------------------
def test_matches_output_error_least_squares(clean, from10):
    """Simulate m a + b v + k s = u with the measured u (cubic spline) from a fitted (s0, v0)
    and fit m, b, k, s0, v0 to the measured s with scipy.optimize.least_squares."""
    t, u, s = clean["t"], clean["u"], clean["s"]
    u_of = CubicSpline(t, u)

    def residual(p):
        m, b, k, s0, v0 = p
        sol = solve_ivp(lambda tt, x: [x[1], (u_of(tt) - b * x[1] - k * x[0]) / m], (t[0], t[-1]),
                        [s0, v0], t_eval=t, method="DOP853", rtol=1e-10, atol=1e-12)
        return sol.y[0] - s

    v0 = float(np.gradient(s, t, edge_order=2)[0])
    lsq = least_squares(residual, [10.0, 10.0, 10.0, s[0], v0], x_scale="jac",
                        bounds=([1e-3] * 3 + [-np.inf] * 2, np.inf))
    assert lsq.success, lsq.message
    ls_params = dict(zip("mbk", lsq.x[:3]))
    assert rel_err(ls_params, TRUE) < 5e-3, ls_params
    assert from10.success
    assert rel_err(from10.parameters, ls_params) < 5e-3, (from10.parameters, ls_params)


# -- TPBVP right-hand side vs the Hamiltonian ---------------------------------------------------
def _random_spd(n, scale, gen):
    a = torch.randn(n, n, dtype=torch.float64, generator=gen)
    return scale * (a @ a.T / n + 0.5 * torch.eye(n, dtype=torch.float64))


@pytest.mark.parametrize("weights", ["report", "dense"])
def test_rhs_is_hamiltonian(clean, weights):
    """Sign convention (module docstring of shootlab.estimation): ε = W⁻¹λ and
    λ' = −Aᵀλ − CᵀVξ, i.e. λ is the multiplier in
    L = ½(εᵀWε + ξᵀVξ) + λᵀ(x' − A x − B ζ − ε), so λ = +Wε, λ(b) = 0, λ(a) = W_a(x(a) − q_a).
    With H(x, λ) = λᵀ(A x + B ζ) + ½ λᵀW⁻¹λ − ½ ξᵀVξ at the stationary ζ (∂H/∂ζ = Bᵀλ + FᵀVξ = 0,
    a maximum of H in ζ) the TPBVP is x' = +∂H/∂λ, λ' = −∂H/∂x.  Checked by central differences
    of H, with ζ re-made stationary at every perturbed point, at random (t, x, λ), for the
    report's diagonal weights and for random dense SPD W and V."""
    gen = torch.Generator().manual_seed(3)
    model = msd.model()
    if weights == "dense":
        model = dataclasses.replace(model, W=_random_spd(5, 2.0, gen), V=_random_spd(3, 1.0, gen))
    prob = EstimationProblem(model, Measurements.coerce(measured(clean)))
    nx, K = prob.nx, 6
    t = 10.0 * torch.rand(K, dtype=torch.float64, generator=gen)
    x = torch.cat([torch.randn(K, 2, dtype=torch.float64, generator=gen),
                   0.5 + 2.5 * torch.rand(K, 3, dtype=torch.float64, generator=gen)], -1)
    lam = torch.randn(K, nx, dtype=torch.float64, generator=gen)
    X = torch.cat([x, lam], -1)

    def H(tt, XX):
        p = prob.parts(tt, XX)
        xx, ll = XX[..., :nx], XX[..., nx:]
        flow = xx @ prob.A.T + p["zeta"] @ prob.B.T
        Winv_l = torch.linalg.solve(p["W"], ll.unsqueeze(-1)).squeeze(-1)
        Vxi = (p["V"] @ p["xi"].unsqueeze(-1)).squeeze(-1)
        return (ll * flow).sum(-1) + 0.5 * (ll * Winv_l).sum(-1) - 0.5 * (p["xi"] * Vxi).sum(-1)

    n = 2 * nx
    h = 1e-5 * X.abs().clamp_min(1.0)                                   # (K, n)
    E = torch.eye(n, dtype=torch.float64)
    Xp = X[:, None, :] + E[None] * h[:, None, :]                        # (K, n, n)
    Xm = X[:, None, :] - E[None] * h[:, None, :]
    tt = t[:, None].expand(K, n)
    with torch.no_grad():
        grad = (H(tt, Xp) - H(tt, Xm)) / (2.0 * h)                      # (K, n): [∂H/∂x, ∂H/∂λ]
    rhs = prob.rhs(t, X).detach()
    xdot, lamdot = rhs[:, :nx], rhs[:, nx:]
    scale = 1.0 + float(rhs.abs().max())
    assert torch.allclose(xdot, grad[:, nx:], rtol=1e-7, atol=1e-7 * scale), (xdot, grad[:, nx:])
    assert torch.allclose(lamdot, -grad[:, :nx], rtol=1e-7, atol=1e-7 * scale), (lamdot, -grad[:, :nx])
    # stationarity of ζ: ∂H/∂ζ = Bᵀλ + FᵀVξ = 0
    p = prob.parts(t, X)
    F = model.F(x, t)
    dHdz = lam @ prob.B + (F.transpose(-1, -2) @ (p["V"] @ p["xi"].unsqueeze(-1))).squeeze(-1)
    assert dHdz.abs().max() < 1e-10 * scale


def test_weight_continuation_stages_before_the_last_stop_at_the_loose_tolerance(clean, monkeypatch):
    """A stage that only starts the next one stops at STAGE_TOL, the model itself at the solver's
    tolerance; the estimate is the one that stages converged all the way give (parameters to
    1e-12, J to its rounding: the last stage converges to the same solution)."""
    from shootlab.estimation import fit as est_mod
    model = msd.model(V=(1.0, 1e4, 1e4))
    model = dataclasses.replace(model, settings=model.settings.replace(weight_continuation=[1.0, 100.0]))
    tols, solve = [], est_mod.solve
    monkeypatch.setattr(est_mod, "solve", lambda *a, **k: tols.append(k.get("tol")) or solve(*a, **k))
    loose = estimate(model, measured(clean), initial=start(10.0), **FAST)
    assert tols == [est_mod.STAGE_TOL, est_mod.STAGE_TOL, None]
    monkeypatch.setattr(est_mod, "STAGE_TOL", 1e-10)
    tight = estimate(model, measured(clean), initial=start(10.0), **FAST)
    assert loose.success and tight.success, (loose.message, tight.message)
    # J sums V ξ², and the residuals ξ of noise-free data cancel the terms of their rows down to
    # 1e-4 (motion) and 4e-7 (s, 15 % of J) of the measurements' size: J is rounded to about
    # eps·|z|/|ξ| ≈ 5e-12 and 5e-10 of those parts (measured 2e-12 – 1e-11 over MKL's code paths)
    assert loose.J == pytest.approx(tight.J, rel=1e-9, abs=0)
    assert rel_err(loose.parameters, tight.parameters) < 1e-12 and rel_err(loose.parameters, TRUE) < 5e-3


def test_weight_stages_cap_the_named_rows_at_each_level_below_their_largest(clean, monkeypatch):
    """One mechanism for both weight continuations: V = (1, 1e4, 1e4) at levels (100, 1, 1e5):
    every row capped at 1, then 100 (1e5 is above the largest V: no stage); rows 1 and 2 alone at
    levels (1, 10, 100, …, 1e6) leave row 0 at its own V; a stage does not continue again
    (``settings.weight_continuation`` None); a V that is a function of t has none.  The diagnosis's
    weight-continuation estimator runs exactly the stages of its geometric levels on the
    measurement rows, then the model."""
    from shootlab.estimation.fit import weight_stages
    import shootlab.diagnosis.estimators as est

    model = msd.model(V=(1.0, 1e4, 1e4))
    model = dataclasses.replace(model, settings=model.settings.replace(weight_continuation=(100.0, 1.0, 1e5)))
    stages = weight_stages(model, model.settings.weight_continuation)
    assert [list(m.V) for m in stages] == [[1.0, 1.0, 1.0], [1.0, 100.0, 100.0]]
    assert all(m.settings.weight_continuation is None for m in stages)
    meas = weight_stages(model, [10.0 ** k for k in range(7)], rows=[1, 2])
    assert [list(m.V) for m in meas] == [[1.0, 10.0 ** k, 10.0 ** k] for k in range(4)]
    assert weight_stages(dataclasses.replace(model, V=lambda t: torch.ones(3)), [1.0]) == []
    seen = []
    monkeypatch.setattr(est, "continue_in_weights", lambda stages, *a, **k: seen.append(stages))
    est.weight_continuation_estimator(factor=10.0)(model, measured(clean))
    rows = [i for i, r in enumerate(model.equations) if r in model.channels]
    assert [list(m.V) for m in seen[0][:-1]] == [list(m.V) for m in weight_stages(model, [1.0, 10.0, 100.0, 1e3], rows)]
    assert seen[0][-1].V is not None and list(seen[0][-1].V) == [1.0, 1e4, 1e4]


# -- missing samples ---------------------------------------------------------------------------
def test_missing_samples_of_s(clean):
    data = measured(clean)
    s = data["s"].copy()
    s[[3, 100, 250, 251, 252, 253, 600, 999]] = np.nan
    res = estimate(msd.model(), dict(data, s=s), initial=start(10.0), **FAST)
    assert res.success, res.message
    assert rel_err(res.parameters, TRUE) < 5e-3, res.parameters


@pytest.mark.parametrize("gap", [slice(33, 38), slice(196, 206)], ids=["between_points", "over_a_point"])
def test_missing_samples_of_u_are_interpolated(clean, gap):
    """u alone determines the input ζ_u, so its missing samples cannot have zero weight: a run of
    up to MAX_INPUT_GAP is filled by linear interpolation (a warning names the column and the
    samples) and the estimate on the 10 s record is as good as without the gap (5e-3, as
    test_press_recovers_parameters_from_10).  The fill's error h²/8 |u''| ≤ (0.11)²/8 · 3.7 = 6e-3
    on 0.1 s of the 10 s record."""
    from shootlab.estimation.data import MAX_INPUT_GAP
    assert gap.stop - gap.start <= MAX_INPUT_GAP
    data = measured(clean)
    u = data["u"].copy()
    u[gap] = np.nan
    with pytest.warns(UserWarning, match=rf"{gap.stop - gap.start} missing samples of input column 'u' "
                                         rf"interpolated linearly .*samples {gap.start}–{gap.stop - 1} "):
        res = estimate(msd.model(), dict(data, u=u), initial=start(10.0), **FAST)
    assert res.success, res.message
    filled = res.problem.data.channels["u"]
    ok = ~np.isnan(u)
    np.testing.assert_array_equal(filled, np.interp(clean["t"], clean["t"][ok], u[ok]))
    assert rel_err(res.parameters, TRUE) < 5e-3, res.parameters


def test_missing_samples_of_u_too_many_in_a_row(clean):
    """A run longer than MAX_INPUT_GAP is a ValueError naming the column and the samples, before any work."""
    from shootlab.estimation.data import MAX_INPUT_GAP
    data = measured(clean)
    u = data["u"].copy()
    u[300:301 + MAX_INPUT_GAP] = np.nan
    with pytest.raises(ValueError, match=rf"input column 'u' is empty in samples 300–{300 + MAX_INPUT_GAP} "
                                         rf"\(t = 3 … 3\.1\): {MAX_INPUT_GAP + 1} missing samples in a row"):
        estimate(msd.model(), dict(data, u=u), initial=start(10.0), **FAST)


def test_missing_samples_of_u_at_the_ends_leave_their_rows_out(clean):
    """Empty u at the start and the end: those rows are left out (a warning says which) and the
    estimate covers the rest of the record; an interval that asks for them is an error naming them."""
    data = measured(clean)
    u = data["u"].copy()
    u[:3] = np.nan
    u[-2:] = np.nan
    with pytest.warns(UserWarning) as notes:
        res = estimate(msd.model(), dict(data, u=u), initial=start(10.0), **FAST)
    assert [str(w.message) for w in notes] == [
        "samples 0–2 (t = 0 … 0.02) left out: input column 'u' is empty there, at the start of the record",
        "samples 999–1000 (t = 9.99 … 10) left out: input column 'u' is empty there, at the end of the record"]
    assert res.success, res.message
    assert float(res.t[0]) == clean["t"][3] and float(res.t[-1]) == clean["t"][-3]
    assert rel_err(res.parameters, TRUE) < 5e-3, res.parameters
    with pytest.raises(ValueError, match=r"input column 'u' is empty in samples 0–2 .* at the start of the record, "
                                         r"inside the interval \[0, 10\]"):
        estimate(msd.model(), dict(data, u=u), initial=start(10.0), interval=(0.0, 10.0), **FAST)


def test_free_run_fills_an_input_gap_and_refuses_an_empty_start(clean):
    """The free run is driven by the filled input (the run equals the one on a record filled by
    hand, bit for bit); it cannot start where the input is empty."""
    from shootlab.estimation.free_run import simulate
    data = measured(clean)
    u = data["u"].copy()
    u[400:404] = np.nan
    ok = ~np.isnan(u)
    with pytest.warns(UserWarning, match="4 missing samples of input column 'u'"):
        run = simulate(msd.model(), dict(data, u=u), TRUE, (0.0, 0.0))
    by_hand = simulate(msd.model(), dict(data, u=np.interp(clean["t"], clean["t"][ok], u[ok])), TRUE, (0.0, 0.0))
    np.testing.assert_array_equal(run["s"], by_hand["s"])
    u[:2] = np.nan
    with pytest.raises(ValueError, match=r"input column 'u' is empty in samples 0–1 \(t = 0 … 0\.01\) at the start"):
        simulate(msd.model(), dict(data, u=u), TRUE, (0.0, 0.0))


def test_output_error_leaves_out_rows_where_the_input_is_empty(tmp_path):
    """The output-error estimate drops the rows where u is empty at the start, as the TPBVP one
    does (the noise-free 4 s record: the truth to 1e-4), and its free_run.csv has the same rows
    when written from the record as given."""
    from shootlab.estimation.output_error import estimate_output_error
    from shootlab.outputs import write_output_error
    d = msd_data(t=np.linspace(0.0, 4.0, 41))
    u = d["u"].copy()
    u[:2] = np.nan
    data = dict(t=d["t"], u=u, s=d["s"])
    with pytest.warns(UserWarning, match=r"samples 0–1 \(t = 0 … 0\.1\) left out"):
        res = estimate_output_error(msd.model(), data, initial=dict(m=1.2, b=0.8, k=1.1))
    assert res.success and rel_err(res.parameters, TRUE) < 1e-4, res.parameters
    write_output_error(res, data, tmp_path, plots=False)
    table = np.loadtxt(tmp_path / "free_run.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(table[:, 0], d["t"][2:], rtol=1e-9)        # written with 10 digits


def test_diagnose_hands_its_estimator_the_filled_record(clean, monkeypatch):
    """diagnose fills the identification and the validation records' inputs before any estimate."""
    from shootlab.diagnosis import pipeline
    seen = []

    class Stop(Exception):
        pass

    def capture(estimator, model, data, say):
        seen.append(data)
        raise Stop
    monkeypatch.setattr(pipeline, "estimate_retrying", capture)
    data = measured(clean)
    u = data["u"].copy()
    u[500] = np.nan
    with pytest.warns(UserWarning) as notes, pytest.raises(Stop):
        pipeline.diagnose(msd.model(), dict(data, u=u), validation=dict(data, u=u))
    assert [str(w.message).startswith("1 missing sample of input column 'u'") for w in notes] == [True, True]
    assert seen[0].channels["u"][500] == pytest.approx(0.5 * (u[499] + u[501]), rel=1e-12)


def test_missing_samples_of_an_input_channel_not_declared_given_are_named(clean):
    """A channel that alone determines an input but is not declared ``given`` keeps zero weight
    where it is missing: FᵀVF is singular there, a ValueError before any work that names the
    column and the samples."""
    data = measured(clean)
    u = data["u"].copy()
    u[33:38] = np.nan
    with pytest.raises(ValueError, match=r"FᵀVF is singular at t = 0\.325 .*; column 'u' is empty in samples 33–37 "
                                         r"\(t = 0\.33 … 0\.37\): declare the channel given"):
        estimate(dataclasses.replace(msd.model(), given=[]), dict(data, u=u), initial=start(10.0), **FAST)


# -- bad input -------------------------------------------------------------------------------
def test_singular_FVF_is_a_value_error(clean):
    with pytest.raises(ValueError, match="FᵀVF is singular"):
        estimate(msd.model(V=(1.0, 0.0, 1.0)), measured(clean), initial=start(10.0), **FAST)


@pytest.mark.parametrize("scale", [1.0, 1e8])
def test_FVF_rank_test_is_decided_by_the_equilibrated_square_root(clean, scale):
    """Columns of F at an angle θ (tan θ = δ/√2): the equilibrated V^½F has singular values
    √(1 ± cos θ), reciprocal condition tan(θ/2), whatever the units of the second input (scale).
    Regular at δ = 1e-6, singular at δ = 1e-12 and at δ = 0 — where FᵀVF's reciprocal condition
    (1e-25, 0) lies below what an SVD of FᵀVF itself resolves (about eps), so that a test on it
    would pass or fail with the rounding of the LAPACK path."""
    from shootlab.estimation.fit import posed

    def model(delta: float):
        col = torch.tensor([[-1.0, -scale], [1.0, scale], [0.0, scale * delta]], dtype=torch.float64)
        return dataclasses.replace(msd.model(), F=lambda x, t: col.expand(*t.shape, 3, 2))

    data = Measurements.coerce(measured(clean))
    prob, t, X0, _ = posed(model(1e-6), data, 51, start(10.0), None, None)
    theta = math.atan2(1e-6 * math.sqrt(2.0), 2.0)           # |u₁ × u₂| / u₁·u₂ for u₁ = (−1, 1, 0), u₂ = (−1, 1, δ)
    # computed to about eps·σ_max: relative error eps / rcond ≈ 6e-10
    assert prob.input_rcond(t, X0[:, :prob.nx]).numpy() == pytest.approx(math.tan(theta / 2), rel=1e-8)
    for delta in (1e-12, 0.0):
        with pytest.raises(ValueError, match=r"FᵀVF is singular at t = 0 \(reciprocal condition of its square root"):
            posed(model(delta), data, 51, start(10.0), None, None)


@pytest.mark.parametrize("W", [(1e10, 1e10, 0.0, 1.0, 1.0), (1e10, -1.0, 1.0, 1.0, 1.0)])
def test_W_not_positive(W):
    with pytest.raises(ValueError, match="W must be positive"):
        msd.model(W=W)


def test_data_shorter_than_interval(clean):
    with pytest.raises(ValueError, match=r"shorter than the interval \[0, 20\]"):
        estimate(msd.model(), measured(clean), initial=start(10.0), interval=(0, 20), **FAST)


def test_channel_missing(clean):
    with pytest.raises(ValueError, match=r"lack channel\(s\) \['s'\]"):
        estimate(msd.model(), {"t": clean["t"], "u": clean["u"]}, initial=start(10.0), **FAST)


def test_unknown_parameter_name(clean):
    with pytest.raises(ValueError, match="unknown parameter 'q'"):
        estimate(msd.model(), measured(clean), initial=dict(m=10.0, q=10.0), **FAST)


def test_non_increasing_times(clean):
    data = measured(clean)
    t = data["t"].copy()
    t[10] = t[9]
    with pytest.raises(ValueError, match=r"duplicate time stamp t = 0\.09 at samples 9 and 10$"):
        estimate(msd.model(), dict(data, t=t), initial=start(10.0), **FAST)
    t[10] = t[8]
    with pytest.raises(ValueError, match="strictly increasing"):
        estimate(msd.model(), dict(data, t=t), initial=start(10.0), **FAST)


def test_csv_without_t_column(tmp_path, clean):
    path = tmp_path / "no_t.csv"
    save_csv(path, dict(time=clean["t"], u=clean["u"], s=clean["s"]), columns=("time", "u", "s"))
    with pytest.raises(ValueError, match="column 't'"):
        estimate(msd.model(), path, initial=start(10.0), **FAST)


# -- free-run simulation ----------------------------------------------------------------------
def test_simulate_identification_data(clean, from10):
    for params in (TRUE, None):                       # the true and the estimated parameters
        out = from10.simulate(parameters=params)
        np.testing.assert_allclose(out["t"], clean["t"])
        assert np.abs(out["s"] - clean["s"]).max() < 1e-4


def test_simulate_other_input(from10):
    """Validation with a different input (not the identification multisine)."""
    other = msd_data(input=lambda t: 0.8 * np.cos(0.9 * t) + 0.4 * np.sin(2.1 * t + 0.5) + 0.2)
    for params in (TRUE, None):
        out = from10.simulate(measured(other), parameters=params, initial_state=(0.0, 0.0))  # starts at rest
        assert np.abs(out["s"] - other["s"]).max() < 1e-4


# -- command line -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def csv_file(tmp_path_factory, clean):
    return str(save_csv(tmp_path_factory.mktemp("data") / "msd.csv", clean))


def test_cli_estimate_builtin_model(tmp_path, csv_file):
    out = tmp_path / "out"
    code = main(["estimate", "--model", "msd", "--data", csv_file, "--initial", "m=10", "b=10", "k=10",
                 "--out", str(out), "--quiet"])
    assert code == 0
    info = json.loads((out / "estimate.json").read_text())
    for key in ("success", "message", "parameters", "J", "iterations", "seconds", "points"):
        assert key in info, key
    assert info["success"] is True and info["points"] == 101 and info["iterations"] > 0
    assert rel_err(info["parameters"], TRUE) < 5e-3, info["parameters"]


USER_MODEL = '''
"""A mass-spring-damper under other names: mass*acc + damping*vel + stiffness*pos = force."""
import shootlab

model = shootlab.model(
    name="user_msd", states={"pos": "vel", "vel": "acc"}, inputs=["force", "acc"],
    parameters={"mass": 10.0, "damping": 10.0, "stiffness": 10.0},
    equations={"newton": lambda x: x.mass * x.acc + x.damping * x.vel + x.stiffness * x.pos - x.force,
               "force_m": lambda x: x.force, "pos_m": lambda x: x.pos},
    channels={"force_m": "u", "pos_m": "s"})
'''


def test_cli_user_model_file(tmp_path, csv_file):
    (tmp_path / "tmp").mkdir()
    path = tmp_path / "tmp" / "mymodel.py"
    path.write_text(textwrap.dedent(USER_MODEL))
    out = tmp_path / "out"
    code = main(["estimate", "--model", f"{path}:model", "--data", csv_file,
                 "--initial", "mass=10", "damping=10", "stiffness=10", "--points", "51",
                 "--integrator", "rk4", "--steps", "5", "--out", str(out), "--quiet", "--no-plots"])
    assert code == 0
    info = json.loads((out / "estimate.json").read_text())
    assert info["model"] == "user_msd" and info["success"] is True
    assert rel_err(info["parameters"], dict(mass=1.0, damping=1.0, stiffness=1.0)) < 5e-3, info["parameters"]


def test_cli_model_that_does_not_import(tmp_path, csv_file, capsys):
    bad = tmp_path / "broken.py"
    bad.write_text("import a_module_that_does_not_exist_42\nmodel = None\n")
    code = main(["estimate", "--model", f"{bad}:model", "--data", csv_file, "--out", str(tmp_path / "o"),
                 "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "does not import" in err and "a_module_that_does_not_exist_42" in err, err
    code = main(["estimate", "--model", f"{tmp_path / 'nowhere.py'}:model", "--data", csv_file,
                 "--out", str(tmp_path / "o"), "--quiet"])
    assert code == 2
    assert "model file not found" in capsys.readouterr().err


def test_press_thrown_off_by_a_full_step_says_so_and_the_default_newton_converges():
    """Noisy record, start m = b = k = 50: press's Armijo test on ½|F|² accepts a full step that
    lowers |F| but throws the parameters to about −2400, where the Newton matrix is singular; its
    message says what happened.  The default (deuflhard: natural monotonicity of the Newton
    correction, affine covariant) and musn converge to the truth within the noise; so does press
    with its fallback (the default), by the trust region from the same start."""
    data = measured(msd_noisy_data(0.01, seed=0))
    start = dict(m=50.0, b=50.0, k=50.0)
    res = estimate(msd.model(), data, initial=start, newton="armijo", fallback=False)
    assert not res.success and res.shooting.status == 3 and "newton='deuflhard'" in res.message, res.message
    res = estimate(msd.model(), data, initial=start, newton="armijo")
    assert res.success and [a["newton"] for a in res.attempts] == ["armijo", "trust_region"], res.message
    assert all(abs(v - 1.0) < 0.02 for v in res.parameters.values()), res.parameters
    for newton in ("deuflhard", "appendix_a"):
        res = estimate(msd.model(), data, initial=start, newton=newton)
        assert res.success, (newton, res.message)
        assert all(abs(v - 1.0) < 0.02 for v in res.parameters.values()), (newton, res.parameters)


# -- records of any length -------------------------------------------------------------------
@pytest.fixture(scope="module")
def long_record():
    """100 s of the demo record with 1 % noise: 10,001 samples, ten times the model's 10 s."""
    return measured(msd_noisy_data(0.01, seed=2, t=np.linspace(0.0, 100.0, 10001)))


def _probe_rho(model, data, points: int) -> float:
    """max|λ| of ∂f/∂x at the initial approximation from m = b = k = 10 on ``points`` points."""
    from shootlab.estimation import weights
    from shootlab.estimation.fit import initial_approximation
    from shootlab.bvp.suggest import local_eigenvalues
    data = Measurements.coerce(data)
    model = weights.from_data(model, data)
    t = torch.linspace(float(data.t[0]), float(data.t[-1]), points, dtype=torch.float64)
    X = initial_approximation(model, data, t, start(10.0))
    return float(local_eigenvalues(EstimationProblem(model, data).bvp().rhs, t, X).abs().max())


def test_default_points_follow_the_record_length(clean, long_record):
    """default_points: the model's 101 points (declared for 10 s) on the 10 s record; on 100 s the
    fewest that keep |λ|max·h ≤ 0.5 (INTERVAL_GROWTH), |λ|max the oscillator's √(k/m) = 1 at the
    probe; without a declared span the declared count stands; the CLI's --points and n_points
    are not changed by it."""
    from dataclasses import replace

    from shootlab.estimation.fit import INTERVAL_GROWTH, default_points
    model = msd.model()
    assert model.settings.span == 10.0 and model.settings.points == 101
    assert default_points(model, measured(clean), initial=start(10.0)) == 101
    m = default_points(model, long_record, initial=start(10.0))
    rho = _probe_rho(model, long_record, 101)
    assert rho == pytest.approx(1.0, abs=0.05)
    assert rho * 100.0 / (m - 1) <= INTERVAL_GROWTH < rho * 100.0 / (m - 2)
    assert m == 1 + int(np.ceil(rho * 100.0 / INTERVAL_GROWTH)) > 101
    plain = replace(model, settings=model.settings.replace(span=None))
    assert default_points(plain, long_record, initial=start(10.0)) == 101


def test_long_record_estimate_with_the_default_points(long_record):
    """The 100 s record from m = b = k = 10 with every default (the points of
    test_default_points_follow_the_record_length): converged, m, b, k within 4 standard errors
    of 1 (the linearised covariance of the estimate)."""
    from shootlab.estimation.fit import default_points
    res = estimate(msd.model(), long_record, initial=start(10.0))
    assert res.success, res.message
    assert res.points == default_points(msd.model(), long_record, initial=start(10.0))
    se = res.standard_errors
    for p in TRUE:
        assert abs(res.parameters[p] - 1.0) <= 4 * se[p], (p, res.parameters[p], se[p])
        assert 0 < se[p] < 2e-3


def test_failure_on_long_intervals_names_more_points(long_record):
    """A solve that stops at the damping floor, on a singular Newton matrix or on too long
    intervals, with |λ|max·h above INTERVAL_GROWTH at the initial approximation, names the
    number of points that keeps |λ|max·h ≤ INTERVAL_GROWTH (at least twice the intervals);
    another failure, or short intervals, add nothing."""
    from shootlab.estimation.fit import INTERVAL_GROWTH, _more_points_hint, posed
    from shootlab.bvp.newton import Status
    from shootlab.bvp.solver import ShootingResult

    model = msd.model()
    data = Measurements.coerce(long_record)

    def hint(points: int, status: Status) -> str:
        prob, t, X0, _ = posed(model, data, points, start(10.0), None, None)
        res = ShootingResult(success=False, status=status, message="", t=t, x=X0, iterations=0,
                             jacobian_evaluations=0, residual_norm=1.0, history=[])
        return _more_points_hint(res, prob, t, X0)
    rho = _probe_rho(model, data, 11)
    want = max(21, 1 + int(np.ceil(rho * 100.0 / INTERVAL_GROWTH)))
    for status in (Status.STEP_TOO_SMALL, Status.SINGULAR, Status.INTERVALS_TOO_LONG):
        text = hint(11, status)
        assert f"--points {want} (n_points={want})" in text and "|λ|max·h = " in text, text
    assert hint(11, Status.MAX_ITER) == ""
    assert hint(401, Status.STEP_TOO_SMALL) == ""                   # |λ|max·h = 0.25


def test_summary_off_the_step_grid_is_one_sweep_over_the_intervals():
    """41 points with 10 RK4 steps per interval on the 100 Hz record with 1 % noise: the samples
    lie off the step grid (steps of 0.025 s), so the summary's states come from one pass over the
    intervals through their samples (ShootingResult.swept), every right-hand side call of it
    holding at most the 40 intervals.  Its steps end on the samples, the
    knots of the data spline, whose third derivative jumps there (the noise): against each sample
    integrated from its shooting point in 100 RK4 steps its states agree to 1e-6 (measured
    3.5e-8), where each sample in 10 steps across the knots (ShootingResult.sol) is off by 3e-4;
    J and ξ agree with the reference's to the same accuracy."""
    from shootlab.estimation.fit import SUMMARY_ROWS, summarise
    from shootlab.bvp.integrators import get_integrator
    data = measured(msd_noisy_data(0.01, seed=1))
    res = estimate(msd.model(), data, n_points=41, initial=TRUE, integrator="rk4", steps=10)
    assert res.success, res.message
    sh, prob = res.shooting, res.problem
    rows, rhs = [], prob.rhs

    def counted(t, X):
        rows.append(X.shape[0])
        return rhs(t, X)
    system = sh._system
    fine = get_integrator("rk4", steps=100).dense(rhs, system.t, sh._x_all, res.t)
    prob.rhs = counted
    system.prob = prob.bvp()
    swept = summarise(prob, sh, 0.0, 10.0, 0.0)
    assert 0 < max(rows) <= 40 < res.t.numel() <= SUMMARY_ROWS
    X = torch.stack([swept.x[n] for n in prob.model.names], -1)
    assert float((X - fine[:, :prob.model.nx]).abs().max()) < 1e-6
    assert float((sh.sol(res.t) - fine).abs().max()) > 1e-4
    reference = summarise(prob, sh, 0.0, 10.0, 0.0, X=fine)
    assert swept.J == pytest.approx(reference.J, rel=1e-5)
    for row in swept.xi:
        assert float((swept.xi[row] - reference.xi[row]).abs().max()) < 1e-6


@pytest.mark.slow
def test_twenty_thousand_samples_with_every_default(tmp_path, capsys):
    """The record of `shootlab simulate msd --noise 0.01 --duration 199.99` (20,000 samples) by
    the command line with every default from m = b = k = 10: 409 shooting points (|λ|max·h ≤ 0.5
    over 200 s), converged, m, b, k within 4 standard errors of 1 (the 101 points of the 10 s
    record stop at the damping floor with m = 2056)."""
    path = tmp_path / "long.csv"
    assert main(["simulate", "msd", "--noise", "0.01", "--duration", "199.99", "--out", str(path)]) == 0
    assert main(["estimate", "--model", "msd", "--data", str(path), "--initial", "m=10", "b=10", "k=10",
                 "--out", str(tmp_path / "out"), "--no-plots"]) == 0
    assert "409 shooting points" in capsys.readouterr().out
    info = json.loads((tmp_path / "out" / "estimate.json").read_text())
    assert info["success"] and info["points"] == 409
    for p in TRUE:
        assert abs(info["parameters"][p] - 1.0) <= 4 * info["standard_errors"][p], (p, info)
