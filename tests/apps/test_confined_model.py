"""Tests of the confined-compression mixture model (mixtures.confined) and Terzaghi's solution."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mixtures.confined import ConfinedCompression
from mixtures.laws import ConstantPermeability, ExponentialPermeability, ExponentialSolid, LinearSolid
from mixtures.loads import CallableHistory, RampHoldLoad, SampledHistory, StepLoad
from mixtures.simulation import MEASUREMENT_COLUMNS, simulate, simulated_measurements, stress_relaxation
from mixtures.terzaghi import (
    ramp_hold_pressure,
    ramp_hold_settlement,
    terzaghi_pressure,
    terzaghi_settlement,
)
from shootlab.estimation.data import Measurements

D = torch.float64


def T(x):
    return torch.as_tensor(x, dtype=D)


# ----------------------------------------------------------------------------------------------
# assembled matrices
# ----------------------------------------------------------------------------------------------
def test_rstar_three_elements_matches_report():
    m = ConfinedCompression(3)
    R, *_ = m.matrices(torch.zeros(3, dtype=D), 2.0, 1.0)
    expected = 0.5 * T([[1, 0, 0], [0, 1, 0], [-1, 0, 1]])
    assert torch.equal(R, expected)


@pytest.mark.parametrize("N", [1, 2, 4, 7])
def test_rstar_is_half_identity_minus_double_shift(N):
    R = ConfinedCompression(N).matrices(torch.zeros(N, dtype=D), 1.0, 1.0).Rstar
    J2 = torch.diag(torch.ones(max(N - 2, 0), dtype=D), -2) if N > 2 else torch.zeros(N, N, dtype=D)
    assert torch.equal(R, 0.5 * (torch.eye(N, dtype=D) - J2))


def test_two_element_matrices_by_hand():
    # N = 2, L = 1, h = 1/2: ∫N'N' element matrix = 2[[1,-1],[-1,1]];
    # full 3x3 assembly [[2,-2,0],[-2,4,-2],[0,-2,2]].  Pressure nodes 1,2 -> [[2,-2],[-2,4]];
    # displacement nodes 2,3 -> [[4,-2],[-2,2]].  R*: rows p1,p2 of the assembled
    # ½[[-1,1],[-1,1]] blocks, columns s2,s3 -> ½ I.
    H, K = 3.0, 0.7
    m = ConfinedCompression(2, length=1.0)
    s = T([-0.1, -0.3])
    R, Km, Sm, F, Hu = m.matrices(s, H, K)
    assert torch.allclose(R, T([[0.5, 0.0], [0.0, 0.5]]), atol=0, rtol=0)
    assert torch.allclose(Km, K * T([[2.0, -2.0], [-2.0, 4.0]]), atol=1e-15, rtol=0)
    assert torch.allclose(Sm, H * T([[4.0, -2.0], [-2.0, 2.0]]), atol=1e-15, rtol=0)
    assert torch.equal(F, torch.zeros(2, dtype=D))
    assert torch.equal(Hu, T([0.0, -1.0]))
    # momentum by hand: p = R*^-T (S s + e_2 u) = 2 (S s + e_2 u); mass: v = -2 K p
    u = 0.25
    Ss = H * T([4 * -0.1 - 2 * -0.3, -2 * -0.1 + 2 * -0.3])
    p_hand = 2 * (Ss + T([0.0, u]))
    v_hand = -2 * (K * T([[2.0, -2.0], [-2.0, 4.0]]) @ p_hand)
    assert torch.allclose(m.pressure(s, u, H, K), p_hand, atol=1e-14, rtol=0)
    assert torch.allclose(m.velocity(s, u, H, K), v_hand, atol=1e-13, rtol=0)
    # length scaling: L = 2 doubles h, halves K and S, leaves R* alone
    m2 = ConfinedCompression(2, length=2.0)
    R2, Km2, Sm2, _, _ = m2.matrices(s, H, K)
    assert torch.equal(R2, R) and torch.allclose(Km2, Km / 2) and torch.allclose(Sm2, Sm / 2)


@pytest.mark.parametrize("solid,perm", [
    (LinearSolid(), ConstantPermeability()),
    (ExponentialSolid(1.5), ExponentialPermeability(2.0)),
])
def test_matrix_free_functions_match_dense_matrices(solid, perm):
    torch.manual_seed(0)
    N = 5
    m = ConfinedCompression(N, solid=solid, permeability=perm)
    s = -0.05 * torch.rand(4, N, dtype=D).cumsum(-1)
    H = 1 + torch.rand(4, dtype=D)
    K = 1 + torch.rand(4, dtype=D)
    u = torch.rand(4, dtype=D)
    R, Km, Sm, F, Hu = m.matrices(s, H, K)
    rhs = (Sm @ s.unsqueeze(-1)).squeeze(-1) - F - Hu * u.unsqueeze(-1)
    p_dense = torch.linalg.solve(R.transpose(-1, -2), rhs)
    v_dense = -torch.linalg.solve(R, (Km @ p_dense.unsqueeze(-1)).squeeze(-1))
    p = m.pressure(s, u, H, K)
    v = m.velocity(s, u, H, K)
    assert torch.allclose(p, p_dense, rtol=1e-12, atol=1e-12)
    assert torch.allclose(v, v_dense, rtol=1e-10, atol=1e-10)
    mass, mom = m.residuals(s, v, p, u, H, K)
    assert mass.abs().max() < 1e-9 and mom.abs().max() < 1e-12
    # S s - F is the assembled solid stress
    e = m.element_strain(s)
    sig = solid.stress(e, H.unsqueeze(-1))
    f = torch.nn.functional.pad(sig, (1, 0)) - torch.nn.functional.pad(sig, (0, 1))
    assert torch.allclose(rhs + Hu * u.unsqueeze(-1), f[..., 1:], atol=1e-13)


def test_batching_broadcasts_state_and_parameters():
    N = 4
    m = ConfinedCompression(N, permeability=ExponentialPermeability(1.0))
    s = -0.1 * torch.rand(2, 3, N, dtype=D)
    H = T([1.0, 2.0, 3.0])
    out = m.matrices(s, H, 0.5)
    assert out.Rstar.shape == (2, 3, N, N) and out.Kmat.shape == (2, 3, N, N)
    assert out.Smat.shape == (2, 3, N, N)
    assert out.Fvec.shape == (2, 3, N) and out.Hu.shape == (2, 3, N)
    for i in range(2):
        for j in range(3):
            one = m.matrices(s[i, j], H[j], 0.5)
            for a, b in zip(out, one):
                assert torch.allclose(a[i, j], b)
    assert m.velocity(s, T(0.3), H, 0.5).shape == (2, 3, N)


# ----------------------------------------------------------------------------------------------
# forward simulation
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("N,L", [(3, 1.0), (5, 1.5)])
def test_creep_steady_state_is_PL_over_H(N, L):
    P, H, K = 0.7, 2.5, 1.3
    # slowest decay rate: c π²/(4 L²) ≈ 3.6 for L = 1.5  ->  t = 15 leaves e^-53
    t = np.array([0.0, 1.0, 15.0])
    sim = simulate(ConfinedCompression(N, length=L), t, load=P, H=H, K=K)
    assert sim.displacement[-1] == pytest.approx(P * L / H, rel=1e-8)
    assert abs(sim.pressure[-1]) < 1e-8
    # uniform strain -P/H: nodal displacements linear in z
    z = np.linspace(0, L, N + 1)[1:]
    assert np.allclose(sim.s[-1], -P / H * z, atol=1e-9)
    # undrained response at t = 0+: no deformation (incompressible constituents)
    assert np.all(sim.s[0] == 0) and sim.load[0] == P


def test_nonlinear_creep_reaches_equilibrium():
    m = ConfinedCompression(3, solid=ExponentialSolid(1.0),
                            permeability=ExponentialPermeability(1.0))
    sim = simulate(m, [0.0, 0.5, 10.0], load=1.0, H=2.0, K=1.0, rtol=1e-8, atol=1e-10)
    s_eq = m.equilibrium(1.0, 2.0).numpy()
    assert np.allclose(sim.s[-1], s_eq, atol=1e-8)
    # strain-stiffening: less compression than the linear P L / H
    assert 0 < sim.displacement[-1] < 0.5


def _max_errors(N, t):
    # the simulation starts unloaded at t_eval[0] = 0; errors are taken on t only
    sim = simulate(ConfinedCompression(N), np.concatenate([[0.0], t]), load=StepLoad(1.0),
                   H=2.0, K=1.0)
    ew = np.abs(sim.displacement[1:] - terzaghi_settlement(t, 1.0, 2.0, 1.0))
    ep = np.abs(sim.pressure[1:] - terzaghi_pressure(0.0, t, 1.0, 2.0, 1.0))
    return ew.max(), ep.max()


def test_step_load_converges_to_terzaghi_at_second_order():
    # Linear elements for s and p: eliminating s turns the scheme into Galerkin diffusion with the
    # one-point (midpoint) quadrature mass matrix, whose eigenvalues are O(h²) accurate.  Away
    # from the singular start (t ≥ 0.05) the errors should therefore fall like h²: a factor 16
    # from N = 6 to N = 24.  Require 8 (observed order ≥ 1.5) for both channels.
    t = np.linspace(0.05, 1.0, 40)
    ew6, ep6 = _max_errors(6, t)
    ew24, ep24 = _max_errors(24, t)
    assert ew24 < ew6 / 8
    assert ep24 < ep6 / 8
    # and the fine mesh is close in absolute terms (compression scale P L / H = 0.5)
    assert ew24 < 1e-3 and ep24 < 1e-2


def test_ramp_hold_matches_analytic_solution():
    t = np.linspace(0.0, 1.0, 51)
    for N, tol_w, tol_p in ((12, 1e-3, 1e-2),):
        sim = simulate(ConfinedCompression(N), t, load=RampHoldLoad(1.0, 0.1))
        assert np.abs(sim.displacement - ramp_hold_settlement(t, 1.0, 0.1)).max() < tol_w
        assert np.abs(sim.pressure - ramp_hold_pressure(0.0, t, 1.0, 0.1)).max() < tol_p


def test_modal_and_nodal_integration_agree():
    # a 0-d tensor M = 0 makes the law 'non-linear' in the eyes of simulate (nodal coordinates,
    # autograd Jacobian) while being mathematically identical to the constant law
    t = np.linspace(0.0, 1.0, 21)
    lin = simulate(ConfinedCompression(4), t, load=RampHoldLoad(1.0, 0.1))
    nod = simulate(ConfinedCompression(4, permeability=ExponentialPermeability(torch.tensor(0.0))),
                   t, load=RampHoldLoad(1.0, 0.1), rtol=1e-8, atol=1e-10)
    assert lin.info["coordinates"] == "modal" and nod.info["coordinates"] == "nodal"
    assert np.allclose(lin.s, nod.s, atol=1e-7)
    assert np.allclose(lin.pressure, nod.pressure, atol=1e-7)


def test_stress_relaxation_and_round_trip_through_creep():
    H, K, d = 2.0, 1.0, 0.1
    t = np.linspace(0.0, 2.0, 41)
    m = ConfinedCompression(4)
    rel = stress_relaxation(m, t, d=d, t_ramp=0.1, H=H, K=K)
    assert np.allclose(rel.displacement, RampHoldLoad(d, 0.1)(t), atol=1e-14)
    assert rel.load[-1] == pytest.approx(H * d / m.L, rel=1e-6)  # drained: H · strain
    assert rel.load.max() > 2 * H * d  # fluid pressurisation during the ramp
    # smooth (C¹) compression history -> continuous load; feed the load back as a creep input
    def dfun(x):
        return d * 0.5 * (1 - math.cos(math.pi * min(x, 0.2) / 0.2))

    def ddfun(x):
        return d * 0.5 * math.pi / 0.2 * math.sin(math.pi * x / 0.2) if x < 0.2 else 0.0

    tt = np.linspace(0.0, 1.0, 801)
    tol = dict(rtol=1e-9, atol=1e-11)
    rel = simulate(m, tt, displacement=CallableHistory(dfun, ddfun, breakpoints=[0.2]), H=H, K=K,
                   **tol)
    cr = simulate(m, tt, load=(tt, rel.load), H=H, K=K, **tol)
    # piecewise-linear interpolation of the load: O(Δt²) discrepancy
    assert np.abs(cr.displacement - rel.displacement).max() < 1e-5


def test_lai_mow_permeability_reduces_to_constant_at_M0():
    torch.manual_seed(1)
    s = -0.1 * torch.rand(3, 4, dtype=D).cumsum(-1)
    a = ConfinedCompression(4).matrices(s, 2.0, 1.5)
    b = ConfinedCompression(4, permeability=ExponentialPermeability(0.0),
                            solid=ExponentialSolid(0.0)).matrices(s, 2.0, 1.5)
    for x, y in zip(a, b):
        assert torch.allclose(x, y, rtol=1e-14, atol=1e-14)
    # M > 0: compression (negative strain) lowers the permeability
    c = ConfinedCompression(4, permeability=ExponentialPermeability(3.0)).matrices(s, 2.0, 1.5)
    assert torch.all(torch.diagonal(c.Kmat, dim1=-2, dim2=-1)
                     < torch.diagonal(a.Kmat, dim1=-2, dim2=-1))
    assert ConfinedCompression(4, permeability=ExponentialPermeability(0.0)).is_linear


# ----------------------------------------------------------------------------------------------
# gradients
# ----------------------------------------------------------------------------------------------
def _torch_step_response(model, H, K, t, P=1.0):
    """Exact semi-discrete creep response ``s(t) = M⁻¹(e^{Mt} − I) b P``, with ``M`` and ``b`` read
    off the torch ``velocity`` function (linear in s and u)."""
    N = model.N
    eye = torch.eye(N, dtype=D)
    M = model.velocity(eye, torch.zeros(N, dtype=D), H.expand(N), K.expand(N)).T
    b = model.velocity(torch.zeros(N, dtype=D), T(1.0), H, K)
    return torch.linalg.solve(M, (torch.linalg.matrix_exp(M * t) - eye) @ (b * P))


def test_autograd_displacement_gradient_matches_finite_differences_of_simulate():
    model = ConfinedCompression(3)
    H = T(2.0).requires_grad_(True)
    K = T(1.0).requires_grad_(True)
    t_obs = 0.3
    w = model.filter_displacement(_torch_step_response(model, H, K, t_obs))
    gH, gK = torch.autograd.grad(w, (H, K))
    # the same quantity from the scipy integrator, central differences
    def sim(Hv, Kv):
        return simulate(model, [0.0, t_obs], load=1.0, H=Hv, K=Kv).displacement[-1]

    assert float(w.detach()) == pytest.approx(sim(2.0, 1.0), rel=1e-8)
    eps = 1e-5
    fdH = (sim(2.0 + eps, 1.0) - sim(2.0 - eps, 1.0)) / (2 * eps)
    fdK = (sim(2.0, 1.0 + eps) - sim(2.0, 1.0 - eps)) / (2 * eps)
    assert float(gH) == pytest.approx(fdH, rel=1e-5)
    assert float(gK) == pytest.approx(fdK, rel=1e-5)
    assert float(gH) < 0 < float(gK)  # stiffer -> less compression; more permeable -> faster


def test_gradcheck_nonlinear_pressure_and_velocity():
    m = ConfinedCompression(3, solid=ExponentialSolid(0.8),
                            permeability=ExponentialPermeability(1.2))
    s = (-0.1 * torch.rand(2, 3, dtype=D).cumsum(-1)).requires_grad_(True)
    H = T([2.0, 3.0]).requires_grad_(True)
    K = T([1.0, 0.5]).requires_grad_(True)
    u = T([0.4, 1.0]).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda s, u, H, K: m.velocity(s, u, H, K), (s, u, H, K))
    assert torch.autograd.gradcheck(lambda s, u, H: m.pressure(s, u, H), (s, u, H))
    assert torch.autograd.gradcheck(lambda s, H, K: tuple(m.matrices(s, H, K)[1:4]), (s, H, K))


# ----------------------------------------------------------------------------------------------
# the report's stiffness check (docs/design.md §3): TPBVP local Jacobian eigenvalues ≈ ±4896
# ----------------------------------------------------------------------------------------------
def test_tpbvp_local_jacobian_has_report_eigenvalues():
    N = 3
    model = ConfinedCompression(N)
    u_m, d_m, p_m = 1.0, 0.3, 0.4  # any data: the eigenvalues do not depend on it much
    z_m = T([u_m, d_m, p_m])

    def f_and_F(x):
        s, H, K = x[:N], x[N], x[N + 1]
        R, Km, Sm, Fv, Hu = model.matrices(s, H, K)
        f = torch.cat([torch.zeros(N, dtype=D), Sm @ s - Fv, torch.zeros(1, dtype=D),
                       model.filter_displacement(s).reshape(1), torch.zeros(1, dtype=D)])
        F = torch.zeros(2 * N + 3, 2 * N + 1, dtype=D)
        F[:N, :N], F[:N, N:2 * N] = R, Km
        F[N:2 * N, N:2 * N], F[N:2 * N, 2 * N] = -R.T, -Hu
        F[2 * N, 2 * N] = 1.0
        F[2 * N + 2, N] = 1.0
        return f, F

    B = torch.zeros(N + 2, 2 * N + 1, dtype=D)
    B[:N, :N] = torch.eye(N, dtype=D)
    Ez = torch.cat([torch.zeros(2 * N, dtype=D), z_m])

    def hamiltonian_rhs(y):  # W = V = I, A = 0
        x, lam = y[:N + 2], y[N + 2:]
        f, F = f_and_F(x)
        zeta = torch.linalg.solve(F.T @ F, B.T @ lam + F.T @ (Ez - f))
        xi = Ez - f - F @ zeta
        zc = zeta.detach()
        C = torch.func.jacrev(lambda xx: (lambda fF: fF[0] + fF[1] @ zc)(f_and_F(xx)))(x)
        return torch.cat([B @ zeta + lam, -C.T @ xi])

    x0 = torch.cat([-d_m * T([1 / 3, 2 / 3, 1.0]), T([4.0, 4.0])])
    y0 = torch.cat([x0, torch.zeros(N + 2, dtype=D)])
    J = torch.func.jacrev(hamiltonian_rhs)(y0).numpy()
    ev = np.linalg.eigvals(J)
    assert ev.real.max() == pytest.approx(4896, rel=1e-3)
    assert ev.real.min() == pytest.approx(-4896, rel=1e-3)


# ----------------------------------------------------------------------------------------------
# Terzaghi
# ----------------------------------------------------------------------------------------------
def test_terzaghi_series_and_image_forms_agree_and_limits():
    from mixtures import terzaghi as tz
    z = np.linspace(0, 0.95, 20)
    for T_ in (0.03, 0.1, 0.3):
        lam = (2 * np.arange(4000) + 1) * np.pi / 2
        sgn = (-1.0) ** np.arange(4000)
        series = np.sum(2 * sgn / lam * np.cos(lam * z[:, None]) * np.exp(-lam ** 2 * T_), axis=-1)
        assert np.allclose(tz._step_pressure_unit(z, np.full_like(z, T_)), series, atol=1e-12)
    # early time: w ≈ 2 P sqrt(c t / π) / H ; late: P L / H ; t = 0+: undrained p = P
    P, H, K = 1.0, 2.0, 1.0
    t = 1e-6
    early = 2 * P * math.sqrt(H * K * t / math.pi) / H
    assert terzaghi_settlement(t, P, H, K) == pytest.approx(early, rel=1e-9)
    assert terzaghi_settlement(50.0, P, H, K) == pytest.approx(P / H, rel=1e-14)
    assert terzaghi_pressure(0.0, 0.0, P, H, K) == P and terzaghi_pressure(1.0, 0.5) == 0.0
    # a very fast ramp approaches the step
    tt = np.array([0.2, 0.5])
    assert np.allclose(ramp_hold_settlement(tt, P, 1e-6), terzaghi_settlement(tt, P), atol=1e-6)


# ----------------------------------------------------------------------------------------------
# measurements, CSV and bad input
# ----------------------------------------------------------------------------------------------
def test_simulated_measurements_and_csv_round_trip(tmp_path):
    t = np.linspace(0, 1, 21)
    clean = simulated_measurements(t)
    assert isinstance(clean, Measurements)
    assert ("t",) + tuple(clean.channels) == MEASUREMENT_COLUMNS == ("t", "load", "displacement", "pressure")
    c = clean.channels
    assert c["load"][0] == 0 and c["load"][-1] == 1.0
    assert 0.45 < c["displacement"][-1] < 0.5 and c["pressure"].max() > 0.5
    noisy = simulated_measurements(t, noise=0.01, seed=3)
    again = simulated_measurements(t, noise=0.01, seed=3)

    def table(m):
        return np.column_stack([m.t] + [m.channels[k] for k in MEASUREMENT_COLUMNS[1:]])
    assert np.array_equal(table(noisy), table(again))
    assert np.array_equal(noisy.t, t) and 0.003 < np.std(noisy.channels["pressure"] - c["pressure"]) < 0.03
    path = tmp_path / "cc.csv"
    noisy.to_csv(path)
    assert path.read_text().splitlines()[0] == "t,load,displacement,pressure"
    back = Measurements.from_csv(path)
    assert isinstance(back, Measurements)
    assert np.array_equal(table(back), table(noisy))      # full float precision


def test_bad_inputs_raise_value_error():
    m = ConfinedCompression(3)
    t = np.linspace(0, 1, 5)
    with pytest.raises(ValueError):
        ConfinedCompression(0)
    with pytest.raises(ValueError):
        ConfinedCompression(2.5)
    with pytest.raises(ValueError):
        ConfinedCompression(3, length=0.0)
    with pytest.raises(ValueError):
        simulate(m, t, load=1.0, H=0.0)
    with pytest.raises(ValueError):
        simulate(m, t, load=1.0, K=-1.0)
    with pytest.raises(ValueError):
        simulate(m, [0.0, 0.5, 0.5, 1.0], load=1.0)
    with pytest.raises(ValueError):
        simulate(m, [0.0, 0.7, 0.3], load=1.0)
    with pytest.raises(ValueError):  # sampled history ends before the simulation does
        simulate(m, t, load=(np.array([0.0, 0.5]), np.array([0.0, 1.0])))
    with pytest.raises(ValueError):
        SampledHistory([0.0, 1.0, 0.5], [0.0, 1.0, 1.0])
    with pytest.raises(ValueError):
        simulate(m, t)  # neither load nor displacement
    with pytest.raises(ValueError):
        simulate(m, t, load=1.0, displacement=RampHoldLoad(0.1, 0.1))
    with pytest.raises(ValueError):  # compression must start at 0
        simulate(m, t, displacement=lambda x: 0.1 + x)
    with pytest.raises(ValueError):
        stress_relaxation(m, t, t_ramp=0.0)
    with pytest.raises(ValueError):
        m.pressure(torch.zeros(4, dtype=D), 1.0, 2.0)
    with pytest.raises(ValueError):
        terzaghi_settlement(0.5, H=-2.0)
    with pytest.raises(ValueError):
        simulated_measurements(t, noise=-1.0)
