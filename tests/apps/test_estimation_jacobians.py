"""The Jacobian of the estimation TPBVP (eq. 2.7) on the project's models: forward sensitivities and
the assembled Jacobian against forward mode, reverse sweeps and central differences, the kept and
joined normal equations, the banded normal equations against the dense ones."""
from __future__ import annotations

import dataclasses
import pytest
import torch

from manipulators import msd
from manipulators.rig import msd_noisy_data
from mixtures.simulation import simulated_measurements
from mixtures.identification import as_data
from mixtures.identification import model as confined
from shootlab.bvp import tangents
from shootlab.estimation.data import Measurements
from shootlab.estimation.optimality import EstimationProblem
from shootlab.estimation.fit import initial_approximation
from shootlab.bvp.integrators import get_integrator
from shootlab.estimation.normal_equations import NormalEquations
from shootlab.bvp.shooting import ShootingSystem
from shared import both, central_differences, rel

f64 = torch.float64
#: tight stage equations, so that central differences of the implicit schemes carry digits
OPTIONS = {"implicit_euler": dict(rtol=1e-13, atol=1e-15), "midpoint": dict(rtol=1e-13, atol=1e-15),
           "radau3": dict(rtol=1e-13, atol=1e-15), "dopri5": dict(rtol=1e-9, atol=1e-11), "dop853": dict(rtol=1e-9, atol=1e-11),
           "ros4": dict(rtol=1e-8, atol=1e-10)}


def rounding_of_eq27(prob: EstimationProblem, t: torch.Tensor, X: torch.Tensor, J: torch.Tensor) -> float:
    """A bound on the rounding difference, relative to the largest entry (:func:`rel`), between
    two ways of computing the Jacobian J (m, n, n) of eq. 2.7 in float64 at (t, X):

        eps · (4 κ + 10 n Σ / max|J|)

    * κ = max over the points of cond(D FᵀVF D) = 1 / input_rcond², the solves with FᵀVF: a
      solve amplifies the rounding of its right-hand side by up to κ relative to its result
      (first-order bound; Higham, Accuracy and Stability of Numerical Algorithms, §7.1), and ζ
      is solved twice (ζ̄ and its correction) in each of the two computations;
    * Σ = the largest entry of |C|ᵀ|V||C| (C = ∂(f + Fζ)/∂x at ζ fixed) or of |J|: ∂λ′/∂x sums
      terms of that size, which cancel down to J's entries; an n-term sum of products is off by
      up to n·eps times its terms' size, and J is a short chain (≤ 10) of such sums.

    Measured on the cases below: at most 0.16 of this bound, over MKL's AMD and Intel code paths,
    MKL_CBWR=COMPATIBLE and OpenBLAS core types (the configurations of .ci/run)."""
    x = X[..., :prob.nx]
    p = prob.parts(t, X)
    zeta, V, model = p["zeta"].detach(), p["V"], prob.model
    # the rows are independent: the Jacobian of their sum holds each row's (r, nx)
    C = torch.autograd.functional.jacobian(
        lambda xx: (model.f(xx, t) + (model.F(xx, t) @ zeta[..., None])[..., 0]).sum(0), x).transpose(0, 1)
    big = float(J.abs().max())
    sigma = max(big, float((C.abs().transpose(-1, -2) @ V.abs() @ C.abs()).max()))
    kappa = float(prob.input_rcond(t, x).min()) ** -2
    return torch.finfo(X.dtype).eps * (4 * kappa + 10 * X.shape[-1] * sigma / big)


@pytest.fixture(params=[0, 32], ids=["torch.func", "small-n"])
def forward_min_n(request, monkeypatch):
    """Both ways of taking the stage Jacobians: forward mode by torch.func for every n, and the
    default (reverse sweeps for the stage Jacobians below FORWARD_MIN_N equations)."""
    monkeypatch.setattr(tangents, "FORWARD_MIN_N", request.param)
    return request.param


def msd_system(integrator: str, steps: int, m: int = 11):
    data = Measurements.coerce(msd_noisy_data())
    model = msd.model()
    prob = EstimationProblem(model, data)
    t = torch.linspace(0.0, 2.0, m, dtype=f64)
    s = initial_approximation(model, data, t)
    s[:, model.nx:] = 0.1 * torch.randn(m, model.nx, dtype=f64, generator=torch.Generator().manual_seed(0))
    return prob.bvp(), t, s, get_integrator(integrator, steps=steps, **OPTIONS.get(integrator, {}))


def confined_system(integrator: str, steps: int, elements: int = 3, m: int = 11, lam: float = 0.01):
    model = confined(elements=elements, prefit=False, coarse=0, states="simulated")
    data = Measurements.coerce(as_data(simulated_measurements(elements=elements)))
    t = torch.linspace(0.0, 1.0, m, dtype=f64)
    s = initial_approximation(model, data, t, dict(H=2.3, K=0.8))
    s[:, model.nx:] = lam * torch.randn(m, model.nx, dtype=f64, generator=torch.Generator().manual_seed(1))
    return EstimationProblem(model, data).bvp(), t, s, get_integrator(integrator, steps=steps,
                                                                      **OPTIONS.get(integrator, {}))


@pytest.mark.parametrize("case", [("msd", "rk4", 4, 11), ("msd", "midpoint", 2, 11), ("confined", "midpoint", 2, 11),
                                  ("confined", "radau3", 2, 11),
                                  # Rosenbrock's second derivatives of eq. 2.7 by torch.func: 100 s
                                  # a case (ros4 on a plain rhs: the test above and test_engine)
                                  pytest.param(("msd", "ros4", 1, 11), marks=pytest.mark.slow)])
def test_estimation_tpbvp_jacobians(case, forward_min_n):
    """The TPBVP of eq. 2.7 (its rhs holds a vector–Jacobian product): mass–spring–damper and
    confined compression with 3 elements (n = 10 each)."""
    problem, integrator, steps, m = case
    prob, t, s, integ = (msd_system if problem == "msd" else confined_system)(integrator, steps, m=m)
    Y, Y_old, system = both(prob, t, s, integ)
    assert rel(Y, Y_old) < 1e-11, case
    if integrator != "ros4":
        assert rel(Y, central_differences(system, s, delta=1e-6)) < 1e-6, case


def test_confined_with_more_elements_by_torch_func():
    """n = 2 (N + 2) = 16, the stage Jacobians by torch.func: 6 elements, implicit midpoint."""
    prob, t, s, integ = confined_system("midpoint", 2, elements=6, m=11, lam=1e-4)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(tangents, "FORWARD_MIN_N", 0)
        Y, Y_old, system = both(prob, t, s, integ)
    assert rel(Y, Y_old) < 1e-11
    assert rel(Y, central_differences(system, s, delta=1e-6)) < 1e-6


# -- the assembled Jacobian of eq. 2.7 ---------------------------------------------------------
def _plain_jacobian(prob: EstimationProblem, t, X):
    """∂rhs/∂X by forward mode through the whole of eq. 2.7 (the generic path)."""
    return torch.func.vmap(lambda v: torch.func.jvp(lambda xx: prob.rhs(t, xx), (X,), (v.expand_as(X),))[1],
                           out_dims=-1)(torch.eye(X.shape[-1], dtype=f64))


def _fd_jacobian(prob: EstimationProblem, t, X, delta=1e-6):
    cols = []
    for j in range(X.shape[-1]):
        e = torch.zeros_like(X)
        e[:, j] = delta * (1.0 + X[:, j].abs())
        cols.append((prob.rhs(t, X + e) - prob.rhs(t, X - e)) / (2 * e[:, j:j + 1]))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("problem,elements", [("msd", 0), ("confined", 3), ("confined", 20)])
def test_assembled_jacobian_equals_forward_mode_and_differences(problem, elements):
    """EstimationProblem.jacobian (C, T, Q of the model's f and F, then matrix algebra) equals
    forward mode through the whole rhs to rounding, and central differences to their own error;
    for the mixture F is differentiated along K only (the probed dependence)."""
    if problem == "msd":
        prob_bvp, t, s, _ = msd_system("rk4", 1, m=7)
    else:
        prob_bvp, t, s, _ = confined_system("rk4", 1, elements=elements, m=7, lam=0.1)
    prob = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
    f, J = prob.jacobian(t, s)
    assert torch.equal(f, prob.rhs(t, s))
    assert rel(J, _plain_jacobian(prob, t, s)) < rounding_of_eq27(prob, t, s, J)
    assert rel(J, _fd_jacobian(prob, t, s)) < 1e-5
    if problem == "confined":
        assert prob._fcols.tolist() == [elements + 1]            # F depends on K alone


def test_assembled_jacobian_finds_a_dependence_that_switches_on_later():
    """A model whose F depends on a state only beyond a threshold (not at the probes): the check
    along the other components widens the set as soon as a batch reaches that region."""
    import dataclasses
    prob_bvp, t, s, _ = msd_system("rk4", 1, m=7)
    base = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
    model = base.model
    F0 = model.F

    def F(x, tt):
        gate = torch.relu(x[..., :1] - 10.0)[..., None]          # zero while the position stays below 10
        return F0(x, tt) * (1.0 + gate)

    prob = EstimationProblem(dataclasses.replace(model, F=F), base.data)
    prob.jacobian(t, s)
    before = prob._fcols.tolist()
    assert 0 not in before
    far = s.clone()
    far[:, 0] += 20.0
    _, J = prob.jacobian(t, far)
    assert 0 in prob._fcols.tolist()
    assert rel(J, _plain_jacobian(prob, t, far)) < rounding_of_eq27(prob, t, far, J)


def test_assembled_jacobian_with_a_full_weight_matrix():
    """A V that is not diagonal takes the LU path of the normal equations: the assembled Jacobian
    still equals forward mode through the whole rhs and central differences."""
    import dataclasses
    prob_bvp, t, s, _ = confined_system("rk4", 1, elements=3, m=7, lam=0.1)
    base = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
    r = base.r
    L = torch.eye(r, dtype=f64) + 0.2 * torch.tril(torch.ones(r, r, dtype=f64), -1)
    prob = EstimationProblem(dataclasses.replace(base.model, V=L @ L.T), base.data)
    f, J = prob.jacobian(t, s)
    assert not prob._solve_parts(t, s)["normal"].diagonal
    assert torch.allclose(f, prob.rhs(t, s), rtol=1e-12, atol=1e-12)
    assert rel(J, _plain_jacobian(prob, t, s)) < rounding_of_eq27(prob, t, s, J)
    assert rel(J, _fd_jacobian(prob, t, s)) < 1e-5


def test_kept_normal_equations_are_those_of_the_same_point(monkeypatch):
    """The factorised normal equations kept from the residual's integration serve the Jacobian's
    integration at the same iterate (RK4 visits the same stage points bitwise): no stage is solved
    twice.  A point that differs in one component is solved afresh, and its Jacobian equals that
    of a problem that keeps nothing.  (The stages one Jacobian call each, as from FORWARD_MIN_N
    equations on; below, one call serves all four: test_stage_jacobians_in_one_call.)"""
    monkeypatch.setattr(tangents, "FORWARD_MIN_N", 0)
    prob_bvp, t, s, integ = confined_system("rk4", 1, elements=3, m=7, lam=0.01)
    prob = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
    solved = []
    once = prob._solve_once
    monkeypatch.setattr(prob, "_solve_once", lambda tt, X: solved.append(X.shape[0]) or once(tt, X))
    system = ShootingSystem(prob_bvp, t, integ)
    F = system.residual(s).F
    assert solved == [t.numel() - 1] * 4                           # the four RK4 stage batches
    Y = system.interval_jacobians(s)
    assert (t.numel() - 1) not in solved[4:]                       # none of them solved again
    assert torch.isfinite(Y).all() and torch.isfinite(F).all()
    other = s.clone()
    other[2, 0] += 1e-9
    before = len(solved)
    _, J = prob.jacobian(t, other)
    assert len(solved) == before + 1
    fresh = EstimationProblem(prob.model, prob.data)
    assert torch.equal(J, fresh.jacobian(t, other)[1])


def test_batched_stage_jacobian_joins_the_stages_kept_normal_equations(monkeypatch):
    """Below FORWARD_MIN_N equations RK4 asks for the Jacobian at its four stage points in one call;
    the stages have each just been solved, and their kept results are joined row-wise instead of
    solving the 4(m − 1) rows again.  The interval Jacobians equal those of a problem that joins
    nothing, bit for bit."""
    prob_bvp, t, s, integ = confined_system("rk4", 1, elements=3, m=7, lam=0.01)
    prob = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
    solved = []
    once = prob._solve_once
    monkeypatch.setattr(prob, "_solve_once", lambda tt, X: solved.append(X.shape[0]) or once(tt, X))
    Y = ShootingSystem(prob_bvp, t, integ).interval_jacobians(s)
    assert solved.count(t.numel() - 1) == 4 and 4 * (t.numel() - 1) not in solved   # the stages, not their join
    plain = EstimationProblem(prob.model, prob.data)
    monkeypatch.setattr(plain, "_joined", lambda *a: None)
    Y_plain = ShootingSystem(dataclasses.replace(prob_bvp, rhs=plain.rhs, jac=plain.jacobian), t, integ).interval_jacobians(s)
    assert torch.equal(Y, Y_plain)                                  # the rows are solved independently


def test_kept_results_join_only_when_their_blocks_cover_every_row():
    """The kept results are found by their fingerprint: a block of a larger X that was solved
    before is reused; rows that no kept block covers (here the last two, fewer than any kept
    block) make the join fail — and are then solved — instead of being searched for forever."""
    prob_bvp, t, s, integ = confined_system("rk4", 1, elements=3, m=7, lam=0.01)
    prob = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
    tt, X = t[:-1], s[:-1]                                   # 6 rows
    prob.rhs(tt[:4], X[:4])                                  # a block of 4 rows kept
    solved = []
    once = prob._solve_once
    prob._solve_once = lambda t_, X_: solved.append(X_.shape[0]) or once(t_, X_)
    both = torch.cat([X[:4], X[:4]])
    assert torch.equal(prob.rhs(torch.cat([tt[:4], tt[:4]]), both), torch.cat([prob.rhs(tt[:4], X[:4])] * 2))
    assert solved == []                                      # two kept blocks joined, nothing solved
    prob.rhs(tt, X)                                          # 4 kept rows + 2 no block covers
    assert solved == [6]


def test_confined_F_is_not_finite_outside_the_physical_domain():
    """An iterate with H ≤ 0 or K ≤ 0 gives a non-finite F, hence a non-finite ζ (the integrator
    reports it and the line search steps back)."""
    model = confined(elements=3, prefit=False, coarse=0)
    x = torch.tensor([[-0.01, -0.02, -0.03, 2.0, 1.0], [-0.01, -0.02, -0.03, -2.0, 1.0],
                      [-0.01, -0.02, -0.03, 2.0, 0.0]], dtype=f64)
    F = model.F(x, torch.zeros(3, dtype=f64))
    assert torch.isfinite(F[0]).all()
    assert not torch.isfinite(F[1]).all() and not torch.isfinite(F[2]).all()


def test_the_assembled_jacobian_equals_reverse_sweeps_through_the_whole_rhs():
    """The Jacobian of eq. 2.7 offered to the integrators (``BVP(jac=)``) is the assembled one at
    every size (no timed choice): it equals reverse sweeps through the whole right-hand side to
    rounding at n = 10, 16 and 44, and its rhs is the rhs."""
    from shootlab.bvp.tangents import reverse_jacobian
    for elements in (3, 6, 20):
        prob_bvp, t, s, _ = confined_system("rk4", 1, elements=elements, m=21, lam=0.1)
        prob = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
        assert prob_bvp.jac == prob.jacobian
        f, J = prob.jacobian(t, s)
        f_rev, J_rev = reverse_jacobian(prob.rhs, t, s)
        assert J.shape == (t.numel(), 2 * prob.nx, 2 * prob.nx)
        assert rel(J, J_rev) < rounding_of_eq27(prob, t, s, J)
        assert torch.allclose(f, f_rev, rtol=1e-13, atol=1e-14)


def test_banded_normal_equations_equal_the_dense_ones():
    """Where V^½F is sparse (the 30-element confined mixture: 63 × 61, 5 % non-zero) its QR runs on
    small windows of a banded ordering (normal_equations.Band); the solves, the rank test and the
    Jacobian's blocks equal those of the dense QR to rounding — also with rows of weight 0 (missing
    samples).  A dense pattern gets no band; an entry outside the band is noticed."""
    from shootlab.estimation.normal_equations import Band
    prob_bvp, t, s, _ = confined_system("rk4", 1, elements=30, m=9, lam=0.1)
    prob = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
    x = s[:, :prob.nx]
    F = prob.model.F(x, t)
    gen = torch.Generator().manual_seed(3)
    V = torch.rand(F.shape[:-1], dtype=f64, generator=gen) + 0.5
    V[2, -2] = 0.0                  # the displacement row (no ζ in it) unweighted: a missing sample
    V[3, 7] = 0.0                   # a balance row unweighted: M singular at that point, in both
    band = Band.of((F != 0).any(0))
    assert band is not None and len(band.blocks) >= 2 and band.holds(F)
    dense, banded = NormalEquations(F, V, True), NormalEquations(F, V, True, band)
    ok = dense.regular
    assert torch.equal(ok, banded.regular) and ok.tolist() == [i != 3 for i in range(F.shape[0])]
    b = torch.randn(F.shape[0], F.shape[-1], 3, dtype=f64, generator=gen)
    assert rel(banded.solve(b)[ok], dense.solve(b)[ok]) < 1e-10
    assert rel(banded.solve(b[..., 0])[ok], dense.solve(b[..., 0])[ok]) < 1e-10
    C = torch.randn(F.shape[0], F.shape[1], prob.nx, dtype=f64, generator=gen)
    cols = torch.tensor([prob.nx - 1])
    Tc = torch.randn(F.shape[0], F.shape[-1], 1, dtype=f64, generator=gen)
    for got, want in zip(banded.hamiltonian_blocks(V, C, Tc, cols, prob.B), dense.hamiltonian_blocks(V, C, Tc, cols, prob.B)):
        assert rel(got[ok], want[ok]) < 1e-10
    joined = NormalEquations.joined([banded, banded])
    assert rel(joined.solve(torch.cat([b, b]))[torch.cat([ok, ok])], torch.cat([dense.solve(b)[ok]] * 2)) < 1e-10
    assert NormalEquations.joined([banded, dense]) is None
    assert Band.of(torch.ones(63, 61, dtype=torch.bool)) is None
    G = F.clone()
    i, j = band.outside.nonzero()[0].tolist()
    G[4, i, j] = 1e-3
    assert not band.holds(G)


def test_the_band_of_F_widens_where_F_turns_non_zero_outside_it():
    """EstimationProblem finds F's band at its first call and checks it at every later one: an F
    non-zero outside it widens the pattern (the entry is never dropped); a non-finite F is
    factorised densely and widens nothing."""
    prob_bvp, t, s, _ = confined_system("rk4", 1, elements=30, m=9, lam=0.1)
    prob = getattr(prob_bvp.rhs, "fun", prob_bvp.rhs).__self__
    F = prob.model.F(s[:, :prob.nx], t)
    band = prob._band_for(F)
    assert band is not None and prob._band_for(F) is band
    G = F.clone()
    i, j = band.outside.nonzero()[-1].tolist()
    G[1, i, j] = 0.5
    wider = prob._band_for(G)
    assert wider is not band and wider.holds(G) and wider.holds(F)
    H = G.clone()
    i, j = wider.outside.nonzero()[0].tolist()
    H[0, i, j] = float("nan")
    assert prob._band_for(H) is None and prob._band is wider
