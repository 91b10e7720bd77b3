"""Tests for shootlab.bvp.integrators: orders, tolerances, stiffness, failures, AD."""
import math

import pytest
import torch
import torch.autograd.forward_ad as fwAD

from shootlab.bvp.integrators import (INTEGRATORS, IntegrationResult, Integrator, Ros4,
                                  batch_jacobian, get_integrator)

F64 = torch.float64
FIXED_STEP = ["euler", "rk4", "rkf45", "implicit_euler", "midpoint", "radau3"]
ADAPTIVE = ["dopri5", "dop853", "ros4", "auto"]


def tensor(x):
    return torch.tensor(x, dtype=F64)


# --- test problems -----------------------------------------------------------

A_OSC = tensor([[-1.0, 2.0], [-2.0, -1.0]])  # eigenvalues -1 +- 2i


def linear_rhs(t, y):
    return y @ A_OSC.T


def linear_exact(t0, t1, y0, a=A_OSC):
    return (torch.linalg.matrix_exp((t1 - t0)[:, None, None] * a) @ y0[..., None])[..., 0]


def logistic_rhs(t, y):
    """y1' = y1 (1 - y1) (logistic), y2' = -y2^2."""
    return torch.stack([y[..., 0] * (1 - y[..., 0]), -y[..., 1] ** 2], -1)


def logistic_exact(t0, t1, y0):
    d = t1 - t0
    return torch.stack([1 / (1 + (1 / y0[:, 0] - 1) * torch.exp(-d)),
                        y0[:, 1] / (1 + y0[:, 1] * d)], -1)


def forced_rhs(t, y):
    """Nonlinear, non-autonomous 2-d system (no closed form; used for AD checks)."""
    y1, y2 = y.unbind(-1)
    return torch.stack([-y2 + 0.3 * torch.sin(t) * y1 ** 2,
                        y1 - 0.5 * torch.cos(t) * y2 - 0.1 * y2 ** 3], -1)


# per-element intervals, including backwards ones
T0 = tensor([0.0, 1.0, 2.0, -1.0, 0.5])
T1 = tensor([1.5, 0.5, 2.1, 2.0, -0.3])
Y0 = tensor([[0.1, 1.0], [0.5, 0.7], [0.9, 0.2], [0.01, 0.5], [0.3, 0.9]])


def scaled_error(y, exact, rtol, atol):
    return ((y - exact).abs() / (atol + rtol * exact.abs())).max().item()


# --- registry and API --------------------------------------------------------

def test_registry_and_get_integrator():
    assert set(INTEGRATORS) == set(FIXED_STEP + ADAPTIVE)
    for name in INTEGRATORS:
        integ = get_integrator(name, steps=4, rtol=None, atol=None)
        assert isinstance(integ, Integrator) and integ.name == name
    with pytest.raises(ValueError, match="rk4.*ros4|ros4.*rk4"):
        get_integrator("rk5")


@pytest.mark.parametrize("name", FIXED_STEP + ADAPTIVE)
def test_zero_length_interval_returns_y0(name):
    t0 = tensor([0.0, 1.0, 2.0])
    t1 = tensor([0.0, 1.5, 2.0])
    y0 = tensor([[1.0, 2.0], [0.5, -0.5], [3.0, 4.0]])
    res = get_integrator(name, steps=3).integrate(linear_rhs, t0, t1, y0)
    assert isinstance(res, IntegrationResult)
    assert torch.equal(res.y[[0, 2]], y0[[0, 2]])
    assert not res.failed.any() and res.reason is None
    res = get_integrator(name).integrate(linear_rhs, t0[[0, 2]], t1[[0, 2]], y0[[0, 2]])
    assert torch.equal(res.y, y0[[0, 2]]) and res.nfev == 0


def test_leading_batch_shape_and_broadcast_times():
    y0 = torch.randn(3, 4, 2, generator=torch.Generator().manual_seed(0), dtype=F64)
    t0, t1 = torch.zeros(4, dtype=F64), torch.linspace(0.5, 1.0, 4, dtype=F64)
    res = get_integrator("ros4").integrate(linear_rhs, t0, t1, y0)
    assert res.y.shape == (3, 4, 2) and res.failed.shape == (3, 4)
    exact = linear_exact(t0.repeat(3), t1.repeat(3), y0.reshape(-1, 2)).reshape(3, 4, 2)
    assert (res.y - exact).abs().max() < 1e-7


def test_nonfinite_initial_value_is_flagged():
    y0 = tensor([[1.0, 0.0], [math.nan, 0.0]])
    res = get_integrator("ros4").integrate(linear_rhs, tensor([0.0, 0.0]), tensor([1.0, 1.0]), y0)
    assert res.failed.tolist() == [False, True] and "non-finite" in res.reason
    assert torch.allclose(res.y[0], linear_exact(tensor([0.0]), tensor([1.0]), y0[:1])[0])


# --- convergence orders ------------------------------------------------------

@pytest.mark.parametrize("name,order", [("euler", 1), ("rk4", 4), ("rkf45", 4),
                                        ("implicit_euler", 1), ("midpoint", 2), ("radau3", 3)])
def test_fixed_step_convergence_order(name, order):
    y0 = tensor([[1.0, 0.0], [0.3, -0.7], [-0.5, 0.2]])
    t0, t1 = tensor([0.0, 1.0, 2.0]), tensor([1.0, 0.2, 3.5])  # one backwards
    exact = linear_exact(t0, t1, y0)
    errors = [(get_integrator(name, steps=s).integrate(linear_rhs, t0, t1, y0).y - exact)
              .abs().max().item() for s in (16, 32, 64)]
    observed = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert abs(observed[-1] - order) < 0.2, observed


def ros4_fixed_steps(rhs, t0, t1, y0, steps):
    """Ros4 steps of equal size (no control), to measure the scheme's order."""
    integ = Ros4()
    h = (t1 - t0) / steps
    y, t = y0, t0
    for _ in range(steps):
        y = integ._attempt(rhs, t, y, h, None)[0]
        t = t + h
    return y


def test_ros4_coefficients_have_order_4_and_error_estimate_order_3():
    t0, t1, y0 = tensor([0.0, 1.0]), tensor([2.0, -0.5]), tensor([[1.0, 0.5], [0.2, -0.4]])
    ref = get_integrator("dopri5", rtol=1e-13, atol=1e-14).integrate(forced_rhs, t0, t1, y0).y
    errors = [(ros4_fixed_steps(forced_rhs, t0, t1, y0, s) - ref).abs().max().item()
              for s in (10, 20, 40)]
    observed = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(abs(p - 4) < 0.15 for p in observed), observed
    # the embedded (3rd-order) estimate is a local error ~ h^4
    local = [Ros4()._attempt(forced_rhs, t0, y0, (t1 - t0) / s, None)[1].abs().max().item()
             for s in (10, 20, 40)]
    observed = [math.log2(local[i] / local[i + 1]) for i in range(2)]
    assert all(abs(p - 4) < 0.15 for p in observed), observed


def test_ros4_is_a_stable():
    """|R(z)| <= 1 on the left half plane (sampled), R(-inf) = 1/3."""
    integ = Ros4()
    one = torch.ones(1, dtype=F64)
    for re in [-1e-2, -1.0, -10.0, -1e3, -1e6, 0.0]:
        for im in [0.0, 0.5, 3.0, 1e2, 1e4]:
            a = tensor([[re, -im], [im, re]])  # y' = (re + i im) y as a real system
            y, _, _, _ = integ._attempt(lambda t, y: y @ a.T, 0 * one, tensor([[1.0, 0.0]]), one,
                                        None)
            assert y.norm() <= 1 + 1e-12, (re, im, y.norm())
    y, _, _, _ = integ._attempt(lambda t, y: -1e9 * y, 0 * one, tensor([[1.0]]), one, None)
    assert abs(y.item() - 1 / 3) < 1e-6


# --- adaptive accuracy -------------------------------------------------------

@pytest.mark.parametrize("name", ADAPTIVE)
def test_adaptive_reaches_tolerance(name):
    exact = logistic_exact(T0, T1, Y0)
    res = get_integrator(name).integrate(logistic_rhs, T0, T1, Y0)  # defaults 1e-8 / 1e-10
    assert not res.failed.any() and res.reason is None
    assert scaled_error(res.y, exact, 1e-8, 1e-10) <= 10
    loose = get_integrator(name, rtol=1e-5, atol=1e-7).integrate(logistic_rhs, T0, T1, Y0)
    assert scaled_error(loose.y, exact, 1e-5, 1e-7) <= 10
    assert loose.nsteps < res.nsteps
    # steps=k caps |h| at |t1 - t0| / k
    capped = get_integrator(name, steps=200).integrate(logistic_rhs, T0, T1, Y0)
    assert capped.nsteps >= 200


def test_batch_of_1000_in_one_call():
    g = torch.Generator().manual_seed(0)
    t0 = 2 * torch.rand(1000, generator=g, dtype=F64)
    t1 = t0 + 3 * torch.rand(1000, generator=g, dtype=F64) - 1
    y0 = 0.1 + 0.8 * torch.rand(1000, 2, generator=g, dtype=F64)
    res = get_integrator("ros4").integrate(logistic_rhs, t0, t1, y0)
    assert res.y.shape == (1000, 2) and not res.failed.any()
    assert scaled_error(res.y, logistic_exact(t0, t1, y0), 1e-8, 1e-10) <= 10
    assert res.nfev == 2 + 3 * res.nsteps  # one batched call per stage, not per element


# --- stiffness and failures --------------------------------------------------

A_STIFF = tensor([[-1.0, 0.0], [1e6, -1e6]])  # eigenvalues -1, -1e6
T0_S, T1_S = tensor([0.0, 1.0]), tensor([1.0, 3.0])
Y0_S = tensor([[1.0, 2.0], [-0.5, 1.0]])


def stiff_rhs(t, y):
    return y @ A_STIFF.T


@pytest.mark.parametrize("name,kwargs,tol", [("ros4", {}, 1e-7),
                                             ("radau3", {"steps": 10}, 2e-3),
                                             ("implicit_euler", {"steps": 10}, 5e-2)])
def test_stiff_stable_schemes(name, kwargs, tol):
    exact = linear_exact(T0_S, T1_S, Y0_S, A_STIFF)
    res = get_integrator(name, **kwargs).integrate(stiff_rhs, T0_S, T1_S, Y0_S)
    assert not res.failed.any()
    assert (res.y - exact).abs().max() < tol
    # ros4 spends its steps on resolving the fast transient to 1e-8; an explicit
    # scheme would need more than 1e6 * 2 / 3.3 steps just for stability
    assert res.nsteps <= 500


@pytest.mark.parametrize("name", ["euler", "rk4", "rkf45"])
def test_explicit_schemes_blow_up_on_stiff_problem_and_report_it(name):
    res = get_integrator(name, steps=100).integrate(stiff_rhs, T0_S, T1_S, Y0_S)
    assert res.failed.all()
    assert "non-finite" in res.reason or "overflow" in res.reason
    assert torch.isfinite(res.y).all()  # frozen at the last finite state


def test_dopri5_max_steps_on_stiff_problem():
    res = get_integrator("dopri5", max_steps=200).integrate(stiff_rhs, T0_S, T1_S, Y0_S)
    assert res.failed.all() and res.reason == "maximum number of steps exceeded"
    assert res.nsteps == 200 and torch.isfinite(res.y).all()


@pytest.mark.parametrize("name,reason", [("dopri5", "step size underflow"),
                                         ("ros4", "step size underflow"),
                                         ("rk4", "non-finite value (overflow)"),
                                         ("radau3", "implicit stage equations did not converge"),
                                         ("implicit_euler",
                                          "implicit stage equations did not converge")])
def test_blow_up_fails_only_that_element(name, reason):
    """y' = y^2 blows up at t = 1 for y0 = 1; the other rows are unaffected."""
    y0, t0, t1 = tensor([[0.2], [1.0], [0.5]]), tensor([0.0, 0.0, 0.0]), tensor([2.0, 2.0, 1.0])
    res = get_integrator(name, steps=50, rtol=1e-5, atol=1e-7).integrate(
        lambda t, y: y ** 2, t0, t1, y0)
    assert res.failed.tolist() == [False, True, False]
    assert res.reason == reason
    assert torch.isfinite(res.y).all()
    exact = y0[[0, 2], 0] / (1 - y0[[0, 2], 0] * t1[[0, 2]])
    assert (res.y[[0, 2], 0] - exact).abs().max() < 2e-2


# --- derivatives -------------------------------------------------------------

def test_batch_jacobian_matches_finite_differences_and_carries_tangents():
    g = torch.Generator().manual_seed(1)
    y = torch.randn(3, 4, 2, generator=g, dtype=F64)
    t = torch.rand(3, 4, generator=g, dtype=F64)
    jac = batch_jacobian(forced_rhs, t, y)
    assert jac.shape == (3, 4, 2, 2)
    d, eye = 1e-6, torch.eye(2, dtype=F64)
    fd = torch.stack([(forced_rhs(t, y + d * eye[j]) - forced_rhs(t, y - d * eye[j])) / (2 * d)
                      for j in range(2)], -1)
    assert (jac - fd).abs().max() < 1e-8
    # forward-over-reverse: tangent of J along v is dJ/dy . v
    v = torch.randn(3, 4, 2, generator=g, dtype=F64)
    with fwAD.dual_level():
        jac_tangent = fwAD.unpack_dual(batch_jacobian(forced_rhs, t, fwAD.make_dual(y, v))).tangent
    fd = (batch_jacobian(forced_rhs, t, y + d * v)
          - batch_jacobian(forced_rhs, t, y - d * v)) / (2 * d)
    assert (jac_tangent - fd).abs().max() < 1e-7
    # reverse mode: J is differentiable w.r.t. y
    yr = y.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(batch_jacobian(forced_rhs, t, yr).sum(), yr)
    # sum of the entries of J = 0.6 sin(t) y1 - 0.5 cos(t) - 0.3 y2^2
    assert torch.allclose(grad, torch.stack([0.6 * torch.sin(t), -0.6 * y[..., 1]], -1))


AD_T0, AD_T1 = tensor([0.0, 1.0, 2.0]), tensor([1.0, 0.2, 2.5])
AD_Y0 = tensor([[1.0, 0.5], [0.3, -0.7], [-0.2, 0.4]])
AD_OPTIONS = {"dopri5": {"rtol": 1e-10, "atol": 1e-12}, "dop853": {"rtol": 1e-10, "atol": 1e-12}, "ros4": {"rtol": 1e-8, "atol": 1e-10}}


def fd_jacobian(integ, d=1e-6):
    cols = []
    for j in range(2):
        e = torch.zeros(2, dtype=F64)
        e[j] = d
        plus = integ.integrate(forced_rhs, AD_T0, AD_T1, AD_Y0 + e).y
        minus = integ.integrate(forced_rhs, AD_T0, AD_T1, AD_Y0 - e).y
        cols.append((plus - minus) / (2 * d))
    return torch.stack(cols, -1)  # (B, n_out, n_in)


@pytest.mark.parametrize("name", FIXED_STEP + ADAPTIVE)
def test_forward_mode_jacobian_matches_finite_differences(name):
    integ = get_integrator(name, steps=5, **AD_OPTIONS.get(name, {}))
    (b, n) = AD_Y0.shape
    with fwAD.dual_level():
        # replicate each interval n times with identity tangents, as the shooting code does
        y0 = fwAD.make_dual(AD_Y0.expand(n, b, n).clone(),
                            torch.eye(n, dtype=F64)[:, None, :].expand(n, b, n).clone())
        res = integ.integrate(forced_rhs, AD_T0, AD_T1, y0)
        tangent = fwAD.unpack_dual(res.y).tangent
    assert not res.failed.any() and not res.y.requires_grad
    jac = tangent.permute(1, 2, 0)  # [b, out, in]
    fd = fd_jacobian(integ)
    assert ((jac - fd).abs().max() / fd.abs().max()).item() < 1e-6


@pytest.mark.parametrize("name", FIXED_STEP)
def test_reverse_mode_jacobian_matches_finite_differences(name):
    integ = get_integrator(name, steps=5)
    y0 = AD_Y0.clone().requires_grad_(True)
    y1 = integ.integrate(forced_rhs, AD_T0, AD_T1, y0).y
    jac = torch.stack([torch.autograd.grad(y1[:, i].sum(), y0, retain_graph=True)[0]
                       for i in range(2)], 1)
    fd = fd_jacobian(integ)
    assert ((jac - fd).abs().max() / fd.abs().max()).item() < 1e-6


def test_midpoint_is_symmetric_on_a_hamiltonian_pair():
    # y' = diag(λ, −λ) y: the implicit midpoint map R(z) = (1 + z/2)/(1 − z/2) keeps R(−z) = 1/R(z), so
    # the growing and the decaying mode stay reciprocal however stiff (an L-stable scheme damps both)
    lam = 400.0
    rhs = lambda t, y: torch.stack([lam * y[..., 0], -lam * y[..., 1]], -1)  # noqa: E731
    y0 = tensor([[1.0, 1.0]])
    y = get_integrator("midpoint", steps=2).integrate(rhs, tensor([0.0]), tensor([0.1]), y0).y
    assert float(y[0, 0] * y[0, 1]) == pytest.approx(1.0, rel=1e-10)
    z = lam * 0.05
    assert float(y[0, 0]) == pytest.approx(((1 + z / 2) / (1 - z / 2)) ** 2, rel=1e-10)


# ---------------------------------------------------------------------------
# The facts every scheme declares
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(INTEGRATORS))
def test_every_scheme_declares_its_facts(name):
    """order, adaptive, kind, stability function and description are the class's own, and the
    stability function of a fixed-step scheme is its one-step map on y' = λ y; for the
    adaptive pairs, one attempted step at the same h."""
    cls = INTEGRATORS[name]
    assert cls.name == name and isinstance(cls.order, int) and cls.order >= 1
    assert isinstance(cls.adaptive, bool) and cls.kind in ("explicit", "implicit", "adaptive")
    assert cls.adaptive == (cls.kind == "adaptive")
    assert isinstance(cls.description, str) and cls.description and "\n" not in cls.description
    assert isinstance(cls.stable, str) and cls.stable
    assert cls.stability.__func__ is not Integrator.stability.__func__
    assert abs(complex(cls.stability(0j)) - 1) < 1e-15
    # order: R(z) − e^z = O(z^{p+1}) (the adaptive schemes' R is that of one step of the method)
    if name != "auto":                          # auto: exp(z) (no single one-step function)
        z0 = 0.1 if cls.order <= 5 else 0.5    # an 8th order's error at 0.05 is below rounding
        errs = [abs(complex(cls.stability(z + 0j)) - math.exp(z)) for z in (z0, z0 / 2)]
        assert math.log(errs[0] / errs[1], 2) == pytest.approx(cls.order + 1, abs=0.3)
    hz = (-0.5, -2.0, -2.6, -7.0, 0.7, -1.0 + 2.0j)
    if not cls.adaptive:
        integ = get_integrator(name, steps=1)
        for z in hz:
            lam = torch.tensor(z, dtype=torch.complex128)
            # a complex λ as a real 2×2 system: y = (Re, Im)
            A = torch.tensor([[lam.real, -lam.imag], [lam.imag, lam.real]], dtype=F64)
            y1 = integ.integrate(lambda t, x: x @ A.T, torch.zeros(1, dtype=F64), torch.ones(1, dtype=F64),
                                 torch.tensor([[1.0, 0.0]], dtype=F64)).y[0]
            assert abs(complex(cls.stability(complex(z))) - complex(y1[0], y1[1])) < 1e-12
    elif name != "auto":
        integ = get_integrator(name)
        for z in (z for z in hz if not isinstance(z, complex)):
            rhs = (lambda t, x, z=z: z * x)
            y = torch.ones(1, 1, dtype=F64)
            f = rhs(None, y) if cls.fsal else None
            y1 = integ._attempt(rhs, torch.zeros(1, dtype=F64), y, torch.ones(1, dtype=F64), f)[0]
            assert abs(complex(cls.stability(complex(z))) - float(y1)) < 1e-12


def test_dop853_is_of_order_8_and_its_estimate_follows():
    """One DOP853 step on y' = y (exact e^h): the local error falls by 2⁹ per halving of h (order
    8), and the estimate handed to the step size control is positive and within 1000x of the true
    error."""
    from shootlab.bvp.integrators import Dop853
    integ = Dop853(rtol=1e-12, atol=1e-14)
    rhs = lambda t, y: y                                                    # noqa: E731
    y0 = torch.ones(1, 1, dtype=torch.float64)
    errors = []
    for h in (0.4, 0.2, 0.1):
        hh = torch.full((1,), h, dtype=torch.float64)
        y1, est, f1, nfev = integ._attempt(rhs, torch.zeros(1, dtype=torch.float64), y0, hh, rhs(0.0, y0))
        errors.append(abs(float(y1) - math.exp(h)))
        assert nfev == 12 and torch.allclose(f1, y1)                       # FSAL: f at the new point
        assert 0 < float(est.abs().max()) < 1e3 * max(errors[-1], 1e-16) + 1e-12
    assert 2 ** 8.5 < errors[0] / errors[1] < 2 ** 9.5


@pytest.mark.parametrize("name", ["dopri5", "dop853", "ros4", "auto"])
def test_a_next_integration_starts_from_the_proposed_steps(name):
    """``h_next`` of an adaptive integration, given as ``h0`` to the next one over the same
    intervals, saves the starting-step estimate and attempts, and the result agrees to the
    tolerance; a fixed-step scheme proposes nothing."""
    integ = get_integrator(name, rtol=1e-8, atol=1e-10)
    first = integ.integrate(forced_rhs, AD_T0, AD_T1, AD_Y0)
    assert first.h_next is not None and first.h_next.shape == AD_T0.shape
    assert torch.isfinite(first.h_next).all() and (first.h_next > 0).all()
    again = integ.integrate(forced_rhs, AD_T0, AD_T1, AD_Y0, h0=first.h_next)
    assert again.nfev < first.nfev and again.nsteps <= first.nsteps
    assert (again.y - first.y).abs().max() < 1e-6
    cold = integ.integrate(forced_rhs, AD_T0, AD_T1, AD_Y0, h0=torch.full_like(AD_T0, math.nan))
    assert cold.nfev == first.nfev and torch.equal(cold.y, first.y)      # not finite: the usual start
    assert get_integrator("rk4", steps=4).integrate(forced_rhs, AD_T0, AD_T1, AD_Y0).h_next is None


@pytest.mark.parametrize("name", FIXED_STEP)
def test_dense_values_on_the_step_grid(name):
    """``dense(..., grid=True)`` with every time on the scheme's step grid: the value after that
    many of its steps from the shooting point (the default, finer steps from the shooting point,
    differs by the scheme's error only); with one time off the grid: the default for all."""
    integ = get_integrator(name, steps=5)
    t = tensor([0.0, 0.5, 1.0, 2.0])
    s = tensor([[0.3, 0.9], [0.5, 0.2], [0.1, -0.4], [0.0, 0.0]])
    tq = tensor([0.0, 0.2, 0.5, 0.6 + 0.1 / 3, 1.4, 2.0])
    on = tq[[0, 1, 2, 4, 5]]
    got = integ.dense(forced_rhs, t, s, on, grid=True)
    # 0.2 = 2 steps of 0.1 from 0; 1.4 = 2 steps of 0.2 from 1.0
    for q, (t0, y0) in {1: (0.0, s[0]), 3: (1.0, s[2])}.items():
        want = get_integrator(name, steps=2).integrate(forced_rhs, tensor(t0), on[q], y0[None]).y[0]
        torch.testing.assert_close(got[q], want, rtol=1e-13, atol=1e-14)
    assert torch.equal(got[[0, 2]], s[[0, 1]])
    # the last time is the end of the last interval's integration (the residual's value)
    assert torch.equal(got[4], integ.integrate(forced_rhs, t[2], t[3], s[2][None]).y[0])
    finer = integ.dense(forced_rhs, t, s, on)
    assert 0 < (got - finer).abs().max() < {1: 3e-2, 2: 3e-3}.get(integ.order, 1e-4)
    assert torch.equal(integ.dense(forced_rhs, t, s, tq, grid=True), integ.dense(forced_rhs, t, s, tq))


def test_a_zero_state_starts_with_an_error_based_step():
    """From y = 0 (the straight-line guess of y'' = f with y' = 0) the starting step of [HNW1]
    p. 169 falls back to h0 = 1e-6, and 100·h0 had made dopri5 take four steps over an interval
    of 0.01 at any tolerance; the error-based h1 alone: two at rtol 1e-8, one at 1e-4.
    y'' = −e^y, y(0) = y'(0) = 0."""
    rhs = lambda t, y: torch.stack([y[..., 1], -torch.exp(y[..., 0])], -1)
    y0 = torch.zeros(1, 2, dtype=torch.float64)
    ref = get_integrator("dopri5", rtol=1e-13, atol=1e-15).integrate(rhs, 0.0, 0.01, y0)
    for rtol, steps in ((1e-8, 2), (1e-4, 1)):
        res = get_integrator("dopri5", rtol=rtol, atol=rtol / 100).integrate(rhs, 0.0, 0.01, y0)
        assert res.nsteps == steps and (res.y - ref.y).abs().max() < rtol * 1e-2


def test_a_loosened_copy_leaves_the_integrator_as_it_was():
    integ = get_integrator("auto", rtol=1e-8, atol=1e-10)
    loose = integ.loosened()
    for scheme in (loose.explicit, loose.stiff):
        assert scheme.tolerances() == pytest.approx((1e-4, 1e-6))
    assert integ.explicit.tolerances() == (1e-8, 1e-10) and integ.stiff.tolerances() == (1e-8, 1e-10)
    assert get_integrator("dopri5", rtol=1e-6).loosened().tolerances()[0] == pytest.approx(1e-3)
    assert get_integrator("dopri5", rtol=1e-3).loosened(1e-4).tolerances()[0] == 1e-3   # never tighter
    fixed = get_integrator("rk4", steps=4)
    assert fixed.loosened() is fixed


@pytest.mark.parametrize("name", FIXED_STEP + ADAPTIVE)
def test_sweep_is_one_pass_over_the_intervals(name):
    """``sweep``: the solution through the shooting points at 81 increasing times from one pass
    over the 3 intervals — every right-hand side call holds the intervals' rows (at most one
    per stage of an implicit step), never one row per time — with the exact flow
    e^{A(t − t_i)} s_i to within the error of ``dense`` (each time in its own steps from t_i,
    none longer than the sweep's), s_i itself at a shooting point, and bad input refused."""
    t = tensor([0.0, 0.5, 1.0, 2.0])
    s = tensor([[0.3, 0.9], [0.5, 0.2], [0.1, -0.4], [0.0, 0.0]])
    tq = torch.linspace(0.0, 2.0, 81, dtype=F64)
    i = (torch.searchsorted(t, tq, right=True) - 1).clamp(0, 2)
    exact = linear_exact(t[i], tq, s[i])
    rows = []

    def counted(tt, y):
        rows.append(y.shape[0])
        return linear_rhs(tt, y)
    integ = get_integrator(name, steps=5, rtol=1e-10, atol=1e-12)
    got = integ.sweep(counted, t, s, tq)
    assert max(rows) <= 2 * (t.numel() - 1) < tq.numel()
    err = float((got - exact).abs().max())
    assert err <= float((integ.dense(linear_rhs, t, s, tq) - exact).abs().max()) + 1e-13, err
    assert torch.equal(got[torch.isin(tq, t[:-1])], s[:-1])
    with pytest.raises(ValueError, match="increasing"):
        integ.sweep(linear_rhs, t, s, tq.flip(0))


@pytest.mark.parametrize("name", FIXED_STEP)
def test_stability_function_at_matrices(name):
    """R(Z) at a diagonalisable Z = V diag(z) V⁻¹ is V diag(R(z)) V⁻¹ (real eigenvalues −3 … 0.5 and
    a complex pair), to 1e-12 of its size; and one step on y' = J y maps y_0 to R(hJ) y_0 (an
    implicit scheme to its Newton tolerance)."""
    scheme = INTEGRATORS[name]
    gen = torch.Generator().manual_seed(5)
    V = torch.eye(4, dtype=F64) + 0.3 * torch.randn(4, 4, generator=gen, dtype=F64)
    block = torch.tensor([[-0.5, 1.2], [-1.2, -0.5]], dtype=F64)          # eigenvalues −0.5 ± 1.2i
    D = torch.block_diag(torch.diag(tensor([-3.0, 0.5])), block)
    Z = V @ D @ torch.linalg.inv(V)
    z, W = torch.linalg.eig(D)                                          # D = W diag(z) W⁻¹
    Rz = torch.tensor([complex(scheme.stability(complex(zi))) for zi in z.tolist()], dtype=torch.complex128)
    VW = V.to(torch.complex128) @ W
    want = (VW @ torch.diag(Rz) @ torch.linalg.inv(VW)).real
    got = scheme.stability_matrix(Z)
    assert float((got - want).abs().max()) <= 1e-12 * float(want.abs().max())
    y0 = torch.randn(3, 4, generator=gen, dtype=F64)
    h = 0.7
    y1 = get_integrator(name, steps=1).integrate(lambda t, y: y @ (Z / h).T, 0.0, h, y0).y
    assert float((y1 - y0 @ got.T).abs().max()) <= 1e-9 * float(y0.abs().max())


def test_a_held_jacobian_takes_the_same_steps_with_one_jacobian_per_interval():
    """Radau IIA, 4 steps per interval, on y' = −1e4 (y − sin t) + cos t − y³/10 (stiff, non-linear)
    over 40 intervals as one batch: with each interval's Jacobian at its start given
    (``jacobian=``), held for the Newton matrices of its four steps, the ends agree with those of
    a fresh Jacobian per step to the Newton tolerance, and the integration forms no Jacobian of
    its own (where it formed one per step)."""
    from shootlab.bvp.tangents import count_jacobians, rhs_jacobian

    def rhs(t, y):
        return -1e4 * (y - torch.sin(t)[:, None]) + torch.cos(t)[:, None] - y ** 3 / 10

    t0 = torch.linspace(0.0, 2.0, 41, dtype=F64)[:-1]
    t1 = t0 + 0.05
    y0 = torch.sin(t0)[:, None] + 0.1 * torch.cos(3 * t0)[:, None]
    integ = get_integrator("radau3", steps=4)
    with count_jacobians() as fresh:
        alone = integ.integrate(rhs, t0, t1, y0)
    J = rhs_jacobian(rhs, t0, y0)[1]
    with count_jacobians() as kept:
        held = integ.integrate(rhs, t0, t1, y0, jacobian=J)
    assert not alone.failed.any() and not held.failed.any()
    assert float((held.y - alone.y).abs().max()) <= 1e-9
    assert fresh.evaluations == 4 and kept.evaluations == 0
