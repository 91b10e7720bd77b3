"""Device-agnostic engine: spectral bounds from matrix products against the exact eigenvalues,
the accelerator's code paths (run on the CPU) against the CPU's, ``resolve_device`` and
``solve_batch`` on problems of the tests' own."""
from __future__ import annotations

import math

import pytest
import torch

import shootlab
from shootlab.bvp.batch import solve_batch
from shootlab.bvp.device import accelerator_paths, forced_accelerator_paths, resolve_device
from shootlab.bvp.integrators import get_integrator
from shootlab.bvp.linalg import apply_qt, dense_matrix, factorize, householder_qr
from shootlab.bvp.spectrum import abscissa_bound, spectral_radius_bound
from shootlab.bvp.shooting import spectral_bounds


f64 = torch.float64


# -- spectral bounds ----------------------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 3, 6, 12])
def test_bounds_lie_above_the_exact_values_on_random_matrices(n):
    g = torch.Generator().manual_seed(n)
    # rows scaled over six decades: far from normal, complex pairs and real eigenvalues mixed
    J = torch.randn(400, n, n, generator=g, dtype=f64) * torch.logspace(-3, 3, n, dtype=f64)[None, :, None]
    rho, kappa = spectral_bounds(J, "exact")
    rho_b, kappa_b = spectral_bounds(J, "bound")
    # from the right side: the exact values carry LAPACK's backward error, ~n ε ‖J‖
    slack = 1e-12 * rho
    assert bool((rho_b >= rho - slack).all()) and bool((kappa_b >= kappa - slack).all())
    # and close: the excess of 48 squarings is log κ(V) / 2^48 (relative), far below 1e-9
    assert bool((rho_b <= rho * (1 + 1e-9)).all()) and bool((kappa_b <= kappa + 1e-9 * rho).all())


def test_bounds_of_special_matrices():
    J = torch.tensor([[[0.0, 1.0], [0.0, 0.0]],          # nilpotent: ρ = 0, max Re λ = 0
                      [[0.0, 0.0], [0.0, 0.0]],
                      [[0.0, 1.0], [-1e6, 0.0]],          # oscillator ±1000i: max Re λ = 0
                      [[-1e4, 1e3], [0.0, 1.0]]], dtype=f64)  # stiff decay beside growth 1
    rho, kappa = spectral_radius_bound(J), abscissa_bound(J)
    assert rho[:2].tolist() == [0.0, 0.0]
    assert rho[2] == pytest.approx(1000.0, rel=1e-12) and rho[3] == pytest.approx(1e4, rel=1e-12)
    assert 0.0 <= float(kappa[0]) < 1e-12 and float(kappa[1]) == 0.0
    assert 0.0 <= float(kappa[2]) < 1e-9 * 1000.0          # (the bound is above the exact 0)
    assert float(kappa[3]) == pytest.approx(1.0, rel=1e-9) and float(kappa[3]) >= 1.0 - 1e-15


# -- the accelerator's code paths on the CPU -------------------------------------------------------
def test_forced_accelerator_paths_switch_and_restore():
    x = torch.zeros(1)
    assert not accelerator_paths(x)
    with forced_accelerator_paths():
        assert accelerator_paths(x)
    assert not accelerator_paths(x)


@pytest.mark.parametrize("name", ["rk4", "euler", "radau3"])
@pytest.mark.parametrize("sensitivity", [False, True])
def test_unmasked_integration_equals_the_masked_one(name, sensitivity):
    """Every row through every step, failures frozen: the same values, failures and reason as the
    loop that drops failed rows — with a row that overflows, one that starts non-finite and one of
    zero length."""
    def rhs(t, y):
        return torch.stack([y[:, 1], 30.0 * y[:, 0] ** 2], -1)
    g = torch.Generator().manual_seed(1)
    y0 = torch.randn(7, 2, generator=g, dtype=f64)
    y0[4, 0], y0[5, 0] = math.nan, 1e200
    t0, t1 = torch.zeros(7, dtype=f64), torch.ones(7, dtype=f64)
    t1[2] = 0.0
    integ = get_integrator(name, steps=4)
    a = integ.integrate(rhs, t0, t1, y0, sensitivity=sensitivity)
    with forced_accelerator_paths():
        b = integ.integrate(rhs, t0, t1, y0, sensitivity=sensitivity)
    assert torch.equal(a.failed, b.failed) and a.reason == b.reason and bool(a.failed[4]) and bool(a.failed[5])
    assert torch.equal(a.y[~a.failed], b.y[~b.failed])
    assert torch.equal(b.y[2], y0[2])
    if sensitivity:
        assert torch.equal(a.S[~a.failed], b.S[~b.failed])


def test_householder_qr_and_the_wy_form_equal_linalg_qr():
    g = torch.Generator().manual_seed(2)
    A = torch.randn(50, 9, 4, generator=g, dtype=f64)
    b = torch.randn(50, 9, 3, generator=g, dtype=f64)
    Q, R = torch.linalg.qr(A)
    refl, tau, R2 = householder_qr(A)
    assert torch.equal(R2, R)
    qtb = apply_qt(refl, tau, b)
    assert float((qtb[:, :4] - Q.mT @ b).abs().max()) < 1e-14
    with forced_accelerator_paths():
        qtb_wy = apply_qt(refl, tau, b)
    assert float((qtb_wy - qtb).abs().max()) < 1e-14


def test_factorisation_on_the_accelerator_path_solves_the_newton_system():
    g = torch.Generator().manual_seed(3)
    L, n, p = 37, 4, 2
    Y = torch.randn(L, n, n, generator=g, dtype=f64) * 0.5
    Ba, Bb = torch.randn(p, n, generator=g, dtype=f64), torch.randn(n - p, n, generator=g, dtype=f64)
    r = torch.randn(L * n + n, generator=g, dtype=f64)
    x_dense = torch.linalg.solve(dense_matrix(Y, Ba, Bb), r).reshape(L + 1, n)
    cond = float(torch.linalg.cond(dense_matrix(Y, Ba, Bb)))
    fac = factorize(Y, Ba, Bb)
    x_cpu = fac.solve(r[:p], r[p:p + L * n].reshape(L, n), r[p + L * n:])
    with forced_accelerator_paths():
        fac = factorize(Y, Ba, Bb)
        x_acc = fac.solve(r[:p], r[p:p + L * n].reshape(L, n), r[p + L * n:])
    bound = 100 * cond * 2.2e-16 * float(x_dense.abs().max())
    assert float((x_cpu - x_dense).abs().max()) < bound and float((x_acc - x_dense).abs().max()) < bound


# -- device= --------------------------------------------------------------------------------------
def test_resolve_device():
    assert resolve_device(None) == torch.device("cpu") and resolve_device("CPU") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="unknown device 'tpu'"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            resolve_device("cuda")


def test_solve_batch_takes_a_list_of_problems_sharing_one_rhs():
    """y″ = −y with y(0) = 0 and y(1) = c: one vector field, each its own boundary condition;
    exact y = c sin t / sin 1 up to RK4's error."""
    def rhs(t, x):
        return torch.stack([x[..., 1], -x[..., 0]], -1)
    probs = [shootlab.BVP(rhs, lambda xa: xa[:1], (lambda c: lambda xb: xb[:1] - c)(c)) for c in (1.0, -2.0, 0.5)]
    t = torch.linspace(0, 1, 51, dtype=f64)
    res = solve_batch(probs, t, torch.zeros(51, 2, dtype=f64))
    for r, c in zip(res, (1.0, -2.0, 0.5)):
        assert r.success
        assert float((r.x[:, 0] - c * torch.sin(t) / math.sin(1.0)).abs().max()) < 1e-9
