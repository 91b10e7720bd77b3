"""Checks of the BVP test-set *definitions* in ``studies/bvp_testset.py``.

No solver is involved: the exact solutions must satisfy the ODE (finite
difference residual) and the boundary conditions, the torch and numpy forms
must agree, and the torch forms must be batched over leading dimensions.
"""

import math

import numpy as np
import pytest
import torch

from studies import bvp_testset as ts

PROBLEMS = ts.all_problems(ts.DEFAULT_EPS)
IDS = [p.label.replace(" ", "-") for p in PROBLEMS]


def test_inventory():
    names = {p.name for p in PROBLEMS}
    cash = [nm for nm in names if nm.startswith("bvpT")]
    assert len(cash) >= 6
    assert {"linear_unstable", "troesch", "bratu", "singular_perturbation"} <= names
    for nm in ts.CASH_PROBLEM_NAMES:
        assert sum(p.name == nm for p in PROBLEMS) == len(ts.DEFAULT_EPS)
    with pytest.raises(ValueError):
        ts.cash_problems(names=["bvpT999"])


@pytest.mark.parametrize("p", PROBLEMS, ids=IDS)
def test_fields(p):
    assert p.n == 2 and p.n_left == 1
    assert p.a < p.b
    assert p.exact is not None and p.exact_kind in ("closed-form", "semi-analytic")
    assert p.description and p.source
    for c in p.layers:
        assert p.a <= c <= p.b
    g = p.straight_line_guess(np.linspace(p.a, p.b, 7))
    assert g.shape == (7, p.n)
    assert g[0, 0] == pytest.approx(p.bc_values[0]) and g[-1, 0] == pytest.approx(p.bc_values[1])


@pytest.mark.parametrize("p", PROBLEMS, ids=IDS)
def test_exact_satisfies_ode(p):
    """4th-order central differences of exact(t) against fun_np(t, exact(t))."""
    h = 1e-7 * (p.b - p.a)  # far below every layer width here (>= 1e-4)
    g = ts.fine_grid(p, n_uniform=801, n_layer=81)
    g = g[(g > p.a + 3 * h) & (g < p.b - 3 * h)]
    ex = p.exact(g)
    assert ex.shape == (g.size, p.n) and np.all(np.isfinite(ex))
    d = (-p.exact(g + 2 * h) + 8 * p.exact(g + h) - 8 * p.exact(g - h) + p.exact(g - 2 * h)) / (12 * h)
    f = p.fun_np(g, ex.T).T
    assert f.shape == ex.shape
    scale = np.maximum(np.max(np.abs(f), axis=0), 1.0)
    res = np.max(np.abs(d - f), axis=0) / scale
    assert np.all(res < 1e-6), res


@pytest.mark.parametrize("p", PROBLEMS, ids=IDS)
def test_exact_satisfies_bcs(p):
    xa, xb = p.exact(p.a)[0], p.exact(p.b)[0]
    assert np.max(np.abs(p.bc_np(xa, xb))) < 1e-12
    ra = p.bc_a_torch(torch.as_tensor(xa, dtype=torch.float64))
    rb = p.bc_b_torch(torch.as_tensor(xb, dtype=torch.float64))
    assert ra.shape == (p.n_left,) and rb.shape == (p.n - p.n_left,)
    assert float(torch.max(torch.abs(torch.cat((ra, rb))))) < 1e-12


@pytest.mark.parametrize("p", PROBLEMS, ids=IDS)
def test_torch_matches_numpy_batched(p):
    rng = np.random.default_rng(0)
    ex = p.exact(np.linspace(p.a, p.b, 15))
    scale = np.max(np.abs(ex), axis=0)
    t = rng.uniform(p.a, p.b, size=(3, 5))
    x = p.exact(t.ravel()).reshape(3, 5, p.n) + 0.01 * scale * rng.standard_normal((3, 5, p.n))
    out = p.rhs_torch(torch.as_tensor(t), torch.as_tensor(x))
    assert out.shape == (3, 5, p.n) and out.dtype == torch.float64
    ref = p.fun_np(t.ravel(), x.reshape(-1, p.n).T).T.reshape(3, 5, p.n)
    np.testing.assert_allclose(out.numpy(), ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)))
    # unbatched call, and a scalar t broadcast against batched x
    o1 = p.rhs_torch(torch.as_tensor(t[1, 2]), torch.as_tensor(x[1, 2]))
    assert o1.shape == (p.n,)
    np.testing.assert_allclose(o1.numpy(), ref[1, 2], rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)))
    o2 = p.rhs_torch(torch.tensor(t[0, 0]), torch.as_tensor(x))
    assert o2.shape == (3, 5, p.n)
    # boundary conditions agree
    xa, xb = x[0, 0], x[2, 4]
    r_np = p.bc_np(xa, xb)
    r_t = torch.cat((p.bc_a_torch(torch.as_tensor(xa)), p.bc_b_torch(torch.as_tensor(xb))))
    np.testing.assert_allclose(r_t.numpy(), r_np, rtol=1e-14, atol=1e-14)
    # batched boundary conditions also work
    assert p.bc_a_torch(torch.as_tensor(x)).shape == (3, 5, p.n_left)


@pytest.mark.parametrize("p", [q for q in PROBLEMS if q.eps in (None, 1e-2)],
                         ids=lambda q: q.label.replace(" ", "-"))
def test_torch_rhs_differentiable(p):
    """Autograd Jacobian d rhs / d x (batched over points) matches finite differences.

    Plain ``torch.autograd`` keeps this fast; ``torch.func.vmap(jacrev(...))``
    works too but its first call costs several seconds of import time.
    """
    t = torch.linspace(p.a, p.b, 4, dtype=torch.float64)
    x = torch.as_tensor(p.exact(t.numpy())).requires_grad_(True)
    f = p.rhs_torch(t, x)
    rows = [torch.autograd.grad(f[:, i].sum(), x, retain_graph=True)[0] for i in range(p.n)]
    J = torch.stack(rows, dim=1).detach()            # (4, n, n): J[k, i, j] = d f_i / d x_j
    x = x.detach()
    for j in range(p.n):
        dx = torch.zeros(p.n, dtype=torch.float64)
        dx[j] = 1e-6 * max(1.0, float(x[:, j].abs().max()))
        fd = (p.rhs_torch(t, x + dx) - p.rhs_torch(t, x - dx)) / (2 * dx[j])
        torch.testing.assert_close(J[:, :, j], fd, rtol=1e-5, atol=1e-5 * float(fd.abs().max()) + 1e-8)


def test_reference_values():
    # literature values of y'(0) for Troesch's problem
    assert ts.troesch_slope(5.0) == pytest.approx(4.575046e-2, rel=2e-7)
    assert ts.troesch_slope(10.0) == pytest.approx(3.5833778e-4, rel=2e-7)
    for mu in (5.0, 10.0):
        p = ts.troesch(mu)
        assert p.exact(0.0)[0, 1] == pytest.approx(ts.troesch_slope(mu), rel=1e-10)
    # Bratu: smaller root of theta = sqrt(2) cosh(theta/4), y(1/2) = max
    th = ts.bratu_theta()
    assert th == pytest.approx(1.5171645990507543, rel=1e-12)
    assert th == pytest.approx(math.sqrt(2.0) * math.cosh(th / 4), rel=1e-14)
    assert ts.bratu().exact(0.5)[0, 0] == pytest.approx(0.1405392, rel=1e-6)
    # linear_unstable
    p = ts.linear_unstable()
    assert p.exact(1.0)[0, 0] == pytest.approx(math.exp(-20.0), rel=1e-14)


def test_fine_grid_and_error_helper():
    p = ts.bvpT2(1e-4)
    g = ts.fine_grid(p)
    assert g[0] == p.a and g[-1] == p.b and np.all(np.diff(g) > 0)
    assert np.sum(g > 1.0 - 1e-4) > 20          # the layer at t = 1 is resolved
    ex = p.exact(g)
    assert ts.relative_max_error(p, g, ex) == 0.0
    bumped = ex.copy()
    bumped[:, 0] += 1e-3
    assert ts.relative_max_error(p, g, bumped) == pytest.approx(1e-3)
    assert ts.relative_max_error(p, g, ex, component=None) == 0.0
