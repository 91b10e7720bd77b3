"""The automatic integrator choice (``integrator="auto"``, the solver's default): an explicit scheme
where the local Jacobian allows it, the stiff one only on the stiff rows; and ``refine``."""
import math
import torch

import shootlab
from shootlab.bvp.integrators import Auto, get_integrator

f64 = torch.float64


def harmonic():
    """y'' = -y, y(0) = 0, y(π/2) = 1: exact sin t (not stiff: |λ| = 1)."""
    return shootlab.BVP(lambda t, x: torch.stack([x[..., 1], -x[..., 0]], -1),
                        lambda xa: xa[:1], lambda xb: xb[:1] - 1.0)


def test_default_is_auto():
    assert shootlab.bvp.solver.DEFAULT_INTEGRATOR == "auto"
    assert isinstance(get_integrator("auto"), Auto) and get_integrator("auto").adaptive


def test_auto_picks_the_explicit_scheme_on_a_non_stiff_problem():
    t = torch.linspace(0.0, math.pi / 2, 11, dtype=f64)
    res = shootlab.solve(harmonic(), t, torch.stack([t, torch.ones_like(t)], -1))
    integ = res._system.integrator
    assert res.success and isinstance(integ, Auto)
    assert integ.rows["dop853"] > 0 and integ.rows["ros4"] == 0      # the default explicit pair
    assert res.points == 11                                     # nothing to refine
    assert (res.x[:, 0] - torch.sin(t)).abs().max() < 1e-9      # default rtol 1e-10
    tq = torch.linspace(0.0, math.pi / 2, 101, dtype=f64)
    assert (res.sol(tq)[:, 0] - torch.sin(tq)).abs().max() < 1e-9


def test_auto_splits_rows_by_stiffness():
    """One batch, two kinds of rows: y' = λ (y − cos t) − sin t (exact cos t) with λ = −1e4 on
    some rows and λ = −1 on others: the stiff rows go to ros4, the others to dop853, and every
    row meets the tolerance."""
    lam = torch.tensor([-1e4, -1.0, -1e4, -1.0], dtype=f64)

    def rhs(t, y):
        return (lam[:y.shape[0], None] * (y - torch.cos(t)[:, None]) - torch.sin(t)[:, None])
    integ = get_integrator("auto", rtol=1e-6, atol=1e-8)
    t0, t1 = torch.zeros(4, dtype=f64), torch.ones(4, dtype=f64)
    stiff = integ.stiff_rows(rhs, t0, t1, torch.ones(4, 1, dtype=f64))
    assert stiff.tolist() == [True, False, True, False]
    # integrate the two kinds separately (rhs rows must be independent of their position)
    for rows, kind in ((slice(0, 1), "ros4"), (slice(1, 2), "dop853")):
        before = dict(integ.rows)
        r = integ.integrate(lambda t, y, _l=lam[rows]: _l[:, None] * (y - torch.cos(t)[:, None]) - torch.sin(t)[:, None],
                            t0[rows], t1[rows], torch.ones(1, 1, dtype=f64))
        assert not r.failed.any()
        assert abs(float(r.y[0, 0]) - math.cos(1.0)) < 1e-5
        assert integ.rows[kind] == before[kind] + 1


def test_a_newton_iterations_residual_starts_from_the_last_integrations_steps():
    """The shooting system hands the step sizes proposed at the end of each interval to its
    next integration over the grid: the second residual at the same point costs fewer rhs calls
    and gives the same F to the tolerance.  (Two intervals of π/4: the first integration's attempt
    of each interval in one step is rejected; measured 37 rhs calls, then 25.)"""
    from shootlab.bvp.shooting import ShootingSystem
    t = torch.linspace(0.0, math.pi / 2, 3, dtype=f64)
    s = torch.stack([t, torch.ones_like(t)], -1)
    system = ShootingSystem(harmonic(), t, get_integrator("auto", rtol=1e-8, atol=1e-10))
    F1 = system.residual(s).F
    cold = system.nfev
    F2 = system.residual(s).F
    assert system.nfev - cold < cold and (F1 - F2).abs().max() < 1e-8
