"""Tests for manipulators.friction and manipulators.rig (fast: a few seconds)."""
import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy import signal
from scipy.linalg import expm

from manipulators import friction as fr
from manipulators.rig import (
    PDController,
    RigSettings,
    eigenfrequency_hz,
    linear_system_matrices,
    load_csv,
    msd_data,
    pd_validation_input,
    save_csv,
    simulate_rig,
    sine_sweep,
    smoothed_steps,
)

#: float64's machine epsilon (2.2e-16)
EPS = float(np.finfo(np.float64).eps)

# --------------------------------------------------------------------------- friction laws
LAWS = {
    "coulomb": (fr.smooth_coulomb, fr.smooth_coulomb_dv, dict(f_c=1.7, v_s=0.3)),
    "viscous": (fr.viscous, fr.viscous_dv, dict(b_v=0.8)),
    "stribeck": (fr.stribeck, fr.stribeck_dv, dict(f_c=1.0, f_s=1.6, v_st=0.5, v_s=0.3, b_v=0.2)),
}


@pytest.mark.parametrize("name", ["coulomb", "stribeck"])
def test_friction_c1_at_transition(name):
    f, df, kw = LAWS[name]
    v_s = kw["v_s"]
    for edge in (v_s, -v_s):
        for d in (1e-6, 1e-8):
            # value and slope continuous across ±v_s
            assert abs(f(edge - d, **kw) - f(edge + d, **kw)) < 10 * d
            assert abs(df(edge - d, **kw) - df(edge + d, **kw)) < 10 * d
    if name == "coulomb":
        f_c = kw["f_c"]
        assert f(v_s, **kw) == pytest.approx(f_c, abs=1e-15)
        assert f(-v_s, **kw) == pytest.approx(-f_c, abs=1e-15)
        assert f(10 * v_s, **kw) == f_c and f(-10 * v_s, **kw) == -f_c
        assert df(v_s * (1 - 1e-9), **kw) == pytest.approx(0.0, abs=1e-12)
        assert df(0.0, **kw) == pytest.approx(2 * f_c / v_s)
        assert f(0.0, **kw) == 0.0


@pytest.mark.parametrize("name", sorted(LAWS))
def test_friction_derivative_numpy_vs_finite_difference(name):
    f, df, kw = LAWS[name]
    v = np.linspace(-1.0, 1.0, 2001)  # includes ±v_s = ±0.3 exactly on the grid
    h = 1e-6
    fd = (f(v + h, **kw) - f(v - h, **kw)) / (2 * h)
    np.testing.assert_allclose(df(v, **kw), fd, atol=1e-6 * (1 + np.abs(fd).max()))
    assert isinstance(f(0.1, **kw), float)  # scalar in, float out


@pytest.mark.parametrize("name", sorted(LAWS))
def test_friction_autograd_batched_matches_analytic(name):
    f, df, kw = LAWS[name]
    torch.manual_seed(0)
    v = (torch.randn(3, 4, 50, dtype=torch.float64) * 0.6).requires_grad_(True)
    # one parameter per batch element (broadcast over the trailing dimension)
    kw_t = {k: torch.full((3, 4, 1), float(val), dtype=torch.float64) for k, val in kw.items()}
    out = f(v, **kw_t)
    assert out.shape == v.shape
    (g,) = torch.autograd.grad(out.sum(), v)
    np.testing.assert_allclose(g.numpy(), df(v.detach(), **kw_t).numpy(), rtol=1e-12, atol=1e-12)
    # torch and numpy paths agree
    np.testing.assert_allclose(out.detach().numpy(), f(v.detach().numpy(), **kw), rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("name", ["coulomb", "stribeck"])
def test_friction_scalar_path_equals_the_array_path(name):
    """A plain number (a simulator's call) takes math's scalar functions: the values of the numpy
    path to a few ulp, inside, at and outside ±v_s; NaN stays NaN; the sweep alike.  The two paths
    differ only in sin and exp (libm against numpy's SIMD loops, 1 ulp apart here on AVX-512, equal
    on numpy's baseline loops) and the four operations after them, which round their then
    different operands by up to ½ ulp each: 2 + 2 ulp, 4 eps relative."""
    f, _, kw = LAWS[name]
    v = np.concatenate([np.linspace(-1.0, 1.0, 2001), [0.0, -0.0, 0.3, -0.3, 1e-300, 50.0]])
    arr = f(v, **kw)
    for vi, ai in zip(v, arr):
        for x in (float(vi), np.float64(vi)):
            got = f(x, **kw)
            assert type(got) is float and got == pytest.approx(ai, rel=4 * EPS, abs=1e-300), (x, got, ai)
    assert math.isnan(f(float("nan"), **kw))
    t = np.linspace(-0.1, 1.1, 1201)
    np.testing.assert_allclose([sine_sweep(float(x)) for x in t], sine_sweep(t), rtol=0, atol=150 * 4 * EPS)


def test_friction_gradcheck_params():
    v = torch.linspace(-0.9, 0.9, 37, dtype=torch.float64)
    f_c = torch.tensor(1.3, dtype=torch.float64, requires_grad=True)
    v_s = torch.tensor(0.4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: fr.smooth_coulomb(v, a, b), (f_c, v_s))
    f_s = torch.tensor(1.9, dtype=torch.float64, requires_grad=True)
    v_st = torch.tensor(0.5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: fr.stribeck(v, a, b, c, 0.4, 0.1), (f_c, f_s, v_st))


def test_friction_classes():
    v = np.linspace(-2, 2, 11)
    law = fr.SmoothCoulomb(f_c=2.0, v_s=0.5) + fr.Viscous(b_v=0.3)
    np.testing.assert_allclose(law(v), fr.smooth_coulomb(v, 2.0, 0.5) + 0.3 * v)
    np.testing.assert_allclose(law.dv(v), fr.smooth_coulomb_dv(v, 2.0, 0.5) + 0.3)
    s = fr.Stribeck(f_c=1.0, f_s=2.0, v_st=0.2, v_s=0.05)
    assert s(10.0) == pytest.approx(1.0)      # Coulomb level at high speed
    assert s(0.05) == pytest.approx(1.0 + math.exp(-(0.25**2)), rel=1e-12)  # near f_s at v_s
    assert s(-10.0) == pytest.approx(-1.0)


# --------------------------------------------------------------------------- rig
def test_eigenfrequency():
    f = eigenfrequency_hz()  # report's extended-model estimates 5.40 / 0.47 / 1000
    assert f == pytest.approx(7.654, abs=1e-3)
    A, _ = linear_system_matrices(b=0.0)
    assert np.abs(np.linalg.eigvals(A).imag).max() / (2 * np.pi) == pytest.approx(f, rel=1e-10)
    # the report's prior values 4.7 / 0.39 / 978 give 8.29 Hz, near the quoted ~8.5 Hz
    assert eigenfrequency_hz(4.7, 0.39, 978.0) == pytest.approx(8.5, abs=0.25)
    assert RigSettings().eigenfrequency_hz == f


def test_linear_rig_matches_closed_form_sine():
    st = RigSettings.ideal()
    A, B = linear_system_matrices(st.m1, st.m2, st.k, st.b)
    amp, w = 100.0, 2 * np.pi * 6.0
    data = simulate_rig(st, lambda t: amp * np.sin(w * t), duration=0.5)
    # x = Im(G e^{iwt}) + e^{At} (x0 - x_p(0)),  G = (iw - A)^{-1} B amp
    G = np.linalg.solve(1j * w * np.eye(4) - A, B[:, 0] * amp)
    xp = np.imag(np.exp(1j * w * data.t)[:, None] * G[None, :])
    # homogeneous part by repeated multiplication with the one-step transition matrix
    phi = expm(A * (data.t[1] - data.t[0]))
    xh = [-xp[0]]
    for _ in data.t[1:]:
        xh.append(phi @ xh[-1])
    x = xp + np.array(xh)
    scale = np.abs(x).max(axis=0)
    assert np.all(np.abs(data.true_states - x).max(axis=0) <= 1e-8 * np.maximum(scale, 1.0))
    # all effects off: measured = true, applied = commanded
    np.testing.assert_array_equal(data.s1, data.s1_true)
    np.testing.assert_array_equal(data.u_applied, data.u)


def test_linear_rig_array_input_matches_lsim():
    st = RigSettings.ideal()
    A, B = linear_system_matrices()
    sys_ = signal.StateSpace(A, B, np.eye(4), np.zeros((4, 1)))
    t = np.arange(501) / 1000.0
    u = sine_sweep(t)
    data = simulate_rig(st, u, duration=0.5)  # linear interpolation of the samples
    _, _, x = signal.lsim(sys_, u, t, interp=True)
    np.testing.assert_allclose(data.true_states, x, rtol=0, atol=1e-8)


def test_gain_delay_zoh_match_lsim():
    # gain 0.9, delay 1.5 ms (not a multiple of the sample time), DAC zero-order hold
    st = RigSettings.ideal(zoh=True, gain_error=True, gain=0.9, delay_enabled=True, delay=0.0015)
    A, B = linear_system_matrices()
    sys_ = signal.StateSpace(A, B, np.eye(4), np.zeros((4, 1)))
    data = simulate_rig(st, "sweep", duration=0.3)
    # applied torque on a 0.5 ms grid: command j acts on [t_j + 1.5 ms, t_{j+1} + 1.5 ms)
    t2 = np.arange(601) / 2000.0
    j = np.floor(np.arange(601) / 2 - 1.5 + 1e-9).astype(int)
    ua = np.where(j >= 0, 0.9 * data.u[np.clip(j, 0, None)], 0.0)
    _, _, x = signal.lsim(sys_, ua, t2, interp=False)
    np.testing.assert_allclose(data.true_states, x[::2], rtol=0, atol=1e-8)
    np.testing.assert_allclose(data.u_applied, ua[::2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(data.u, sine_sweep(data.t), rtol=0, atol=1e-12)


def test_reproducible_and_seed_dependent():
    st = RigSettings()  # all realism effects on
    a = simulate_rig(st, "sweep", duration=0.15)
    b = simulate_rig(st, "sweep", duration=0.15)
    c = simulate_rig(st.replace(seed=1), "sweep", duration=0.15)
    for key in a.keys():
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a.s2, c.s2)
    assert not np.array_equal(a.f2_level, c.f2_level)
    # friction level varies by a few per cent, slowly
    rel = a.f2_level / st.f2 - 1
    assert 0 < np.abs(rel).max() <= st.friction_variation_amplitude + 1e-12
    assert np.abs(np.diff(a.f2_level)).max() < 1e-3 * st.f2


def test_quantization_and_noise():
    base = RigSettings(noise=False, friction_variation=False)
    q = base.quantization_step
    d = simulate_rig(base, "sweep", duration=0.3)
    for s, s_true in ((d.s1, d.s1_true), (d.s2, d.s2_true)):
        counts = s / q
        np.testing.assert_allclose(counts, np.round(counts), atol=1e-9)  # on the encoder grid
        assert np.all(np.abs(s - s_true) <= q / 2 + 1e-12)
        steps = np.abs(np.diff(counts))
        assert steps[steps > 0.5].min() == pytest.approx(1.0, abs=1e-9)  # one-count steps visible
        assert np.mean(steps < 0.5) > 0.05  # repeated readings (plateaus) exist
    # noise only: residual std ≈ noise_std, no quantisation
    dn = simulate_rig(base.replace(quantization=False, noise=True), "sweep", duration=0.3)
    res = np.concatenate([dn.s1 - dn.s1_true, dn.s2 - dn.s2_true])
    assert np.std(res) == pytest.approx(base.noise_std, rel=0.15)
    assert np.abs(np.round(dn.s1 / q) - dn.s1 / q).max() > 0.1


def test_pd_validation_input_differs_and_replays():
    st = RigSettings()
    closed = simulate_rig(st, "pd", duration=0.6, controller=PDController())
    t, u_pd = closed.t, closed.u
    u_sw = sine_sweep(t)
    corr = np.corrcoef(u_pd, u_sw)[0, 1]
    assert abs(corr) < 0.5
    assert np.sqrt(np.mean((u_pd - u_sw) ** 2)) > 0.5 * np.sqrt(np.mean(u_sw**2))
    assert np.abs(u_pd).max() > 50  # the controller really acts
    # the loop follows the reference (with lag): the end-effector correlates with it
    r = smoothed_steps(t)
    assert np.corrcoef(r, closed.s1_true)[0, 1] > 0.6
    assert np.sqrt(np.mean((r - closed.s1_true) ** 2)) < 0.9 * np.sqrt(np.mean(r**2))
    # pd_validation_input returns the same command (a shorter run is a prefix: same seed)
    t_short, u_short = pd_validation_input(st, duration=0.1)
    np.testing.assert_array_equal(u_short, u_pd[: t_short.size])
    # the recorded command, replayed open loop with the same seed, reproduces the closed loop
    replay = simulate_rig(st, u_pd, duration=0.6)
    np.testing.assert_allclose(replay.true_states, closed.true_states, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(replay.s2, closed.s2)


def test_friction_only_preset():
    st = RigSettings.friction_only()
    assert st.effective_gain == 1.0 and st.effective_delay == 0.0
    assert not (st.quantization or st.noise or st.zoh or st.friction_variation) and st.friction
    d = simulate_rig(st, "sweep", duration=0.2)
    np.testing.assert_array_equal(d.s2, d.s2_true)
    np.testing.assert_array_equal(d.u, d.u_applied)
    assert np.all(d.f2_level == st.f2)
    # the true states satisfy the documented equations of motion (4th-order differences)
    h = d.t[1] - d.t[0]

    def ddt(x):
        return (-x[4:] + 8 * x[3:-1] - 8 * x[1:-3] + x[:-4]) / (12 * h)

    a1, a2 = ddt(d.v1_true), ddt(d.v2_true)
    s1, s2, v1, v2 = (x[2:-2] for x in (d.s1_true, d.s2_true, d.v1_true, d.v2_true))
    spring = st.k * (s2 - s1) + st.b * (v2 - v1)
    r1 = st.m1 * a1 - (spring - fr.smooth_coulomb(v1, st.f1, st.v_s1))
    r2 = st.m2 * a2 - (d.u[2:-2] - spring - fr.smooth_coulomb(v2, st.f2, st.v_s2))
    # a wrong friction sign would leave 2 f1 = 2.5 and 2 f2 = 80; the largest misfit is the
    # difference-formula error where v2 crosses the friction transition
    assert np.abs(r1).max() < 0.1 and np.abs(r2).max() < 1.0
    assert np.median(np.abs(r1)) < 1e-3 and np.median(np.abs(r2)) < 1e-3


def test_csv_round_trip(tmp_path):
    d = simulate_rig(RigSettings(), "sweep", duration=0.05)
    p = save_csv(tmp_path / "rig.csv", d)
    assert p.read_text().splitlines()[0] == "t,u,s1,s2"
    back = load_csv(p)
    assert list(back) == ["t", "u", "s1", "s2"]
    for k in back:
        np.testing.assert_array_equal(back[k], d[k])
    m = msd_data(noise=0.01, seed=3)
    p2 = save_csv(tmp_path / "msd.csv", m)
    assert p2.read_text().splitlines()[0] == "t,u,s"
    back2 = load_csv(p2)
    for k in ("t", "u", "s"):
        np.testing.assert_array_equal(back2[k], m[k])


def test_msd_data():
    m = msd_data()
    assert m["t"][0] == 0.0 and m["t"][-1] == 10.0 and m["t"].size == 1001
    np.testing.assert_array_equal(m["s"], m["s_true"])
    h = m["t"][1] - m["t"][0]
    acc = (m["s"][2:] - 2 * m["s"][1:-1] + m["s"][:-2]) / h**2
    np.testing.assert_allclose(acc, m["a_true"][1:-1], atol=1e-4)
    np.testing.assert_allclose(m["a_true"] + m["v_true"] + m["s_true"], m["u"], atol=1e-12)
    assert np.ptp(m["s"]) > 0.5 and np.ptp(m["v_true"]) > 0.5  # really excited
    n1, n2, n3 = msd_data(noise=0.01, seed=1), msd_data(noise=0.01, seed=1), msd_data(noise=0.01, seed=2)
    np.testing.assert_array_equal(n1["s"], n2["s"])
    assert not np.array_equal(n1["s"], n3["s"])


def test_package_import_is_light():
    code = ("import sys, manipulators; "
            "assert 'torch' not in sys.modules and 'scipy' not in sys.modules; "
            "from manipulators import simulate_rig, SmoothCoulomb; "
            "assert 'torch' not in sys.modules")  # the numpy-only rig never imports torch
    subprocess.run([sys.executable, "-c", code], check=True)


def test_the_effect_rigs_validation_command_is_simulated_once_per_process():
    """The PD command of :func:`manipulators.rig_effects.validation_input` is the same for every
    record of a duration: simulated once, handed out as copies (a caller's edit changes nothing)."""
    from manipulators import rig_effects as re_
    re_._pd_command.cache_clear()
    t1, u1 = re_.validation_input(1.0)
    u1[:] = 0.0
    t2, u2 = re_.validation_input(1.0)
    assert re_._pd_command.cache_info().misses == 1 and np.abs(u2).max() > 1.0 and np.array_equal(t1, t2)
