"""Boundary-value test problems for ``shootlab`` (definitions only, no solver calls).

Every problem is a scalar second-order Dirichlet problem

    y'' = f(t, y, y'),   a <= t <= b,   y(a) = alpha,   y(b) = beta,

written as the first-order system ``x = (y, y')`` with one separated boundary
condition at each end (``p = 1`` condition at ``a``, ``n - p = 1`` at ``b``).
Each :class:`TestProblem` carries the same problem in two forms:

* torch (for ``shootlab.BVP``): ``rhs_torch(t, x)`` is batched over leading
  dimensions (``x`` has shape ``(..., 2)``, ``t`` has shape ``x.shape[:-1]`` or
  is a scalar); ``bc_a_torch(x_a)`` / ``bc_b_torch(x_b)`` return shape ``(1,)``
  for ``x_a``, ``x_b`` of shape ``(2,)``;
* numpy, in the form ``scipy.integrate.solve_bvp`` expects: ``fun_np(t, y)``
  with ``y`` of shape ``(2, m)`` and ``bc_np(ya, yb)`` returning residuals of
  shape ``(2,)``.

The right-hand sides are written once against a tiny array namespace
(``_NP`` / ``_TORCH``) so that the two forms cannot drift apart.

Sources of the problem statements and exact solutions (facts only; no code
was copied):

* J. R. Cash and F. Mazzia, "Test set for BVP solvers" (BVPTestSet), problems
  bvpT1 ... bvpT33, https://archimede.uniba.it/~bvpsolvers/testsetbvpsolvers/
  (formerly http://www.dm.uniba.it/~bvpsolve); F. Mazzia and J. R. Cash,
  "A Fortran test set for boundary value problem solvers", AIP Conf. Proc.
  1648 (2015); F. Mazzia, J. R. Cash and K. Soetaert, "Solving boundary value
  problems in the open source software R: package bvpSolve", Opuscula Math.
  34(2) (2014) 387-403 (the R package ``bvpTests`` ships the same problems).
  Every exact solution below was re-derived / checked by substitution
  (``tests/apps/test_bvp_testset_defs.py`` checks them numerically).
* Troesch's problem: B. A. Troesch, J. Comput. Phys. 21 (1976) 279-290;
  it is also bvpT23 of the test set.  Reference slopes y'(0) = 4.575046e-2
  (mu = 5) and 3.5833778e-4 (mu = 10) are the literature values; here the
  solution is computed semi-analytically (see :func:`troesch`).
* Bratu's problem (lambda = 1): the classical closed-form lower branch, see
  e.g. U. M. Ascher, R. M. M. Mattheij and R. D. Russell, "Numerical Solution
  of Boundary Value Problems for ODEs" (SIAM, 1995).

Notes on conventions
--------------------
* The sign convention of bvpT5 follows the test-set authors' R/Fortran code
  (``eps y'' = y + t y' - (1 + eps pi^2) cos(pi t) + pi t sin(pi t)``); the
  exact solution ``cos(pi t)`` is the same for either sign of the ``t y'``
  term.
* bvpT9 is the only problem here whose leading coefficient is not ``eps``
  (``(eps + t^2) y'' = ...``).
* ``exact_kind`` is ``"closed-form"`` for every problem except Troesch, which
  is ``"semi-analytic"`` (first integral + Gauss-Legendre quadrature +
  Newton, accurate to ~1e-14; no numerical BVP solver is involved).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Callable, Optional, Sequence

import numpy as np
import torch
from scipy import special as _sp
from scipy.optimize import brentq

__all__ = [
    "TestProblem",
    "cash_problems",
    "classic_problems",
    "all_problems",
    "linear_unstable",
    "troesch",
    "bratu",
    "singular_perturbation",
    "troesch_slope",
    "bratu_theta",
    "fine_grid",
    "relative_max_error",
    "CASH_PROBLEM_NAMES",
    "DEFAULT_EPS",
    "bvpT1", "bvpT2", "bvpT3", "bvpT4", "bvpT5", "bvpT6", "bvpT7", "bvpT9", "bvpT10", "bvpT20", "bvpT21",
]

DEFAULT_EPS = (1e-1, 1e-2, 1e-3, 1e-4)

# --------------------------------------------------------------------------
# array namespaces: the right-hand sides are written once against these
# --------------------------------------------------------------------------
_NP = SimpleNamespace(
    cos=np.cos, sin=np.sin, exp=np.exp, sinh=np.sinh, cosh=np.cosh,
    tanh=np.tanh, erf=_sp.erf, pi=math.pi,
)
_TORCH = SimpleNamespace(
    cos=torch.cos, sin=torch.sin, exp=torch.exp, sinh=torch.sinh,
    cosh=torch.cosh, tanh=torch.tanh, erf=torch.special.erf, pi=math.pi,
)


def _logcosh(z):
    """log(cosh(z)) without overflow (numpy)."""
    z = np.abs(np.asarray(z, dtype=float))
    return z + np.log1p(np.exp(-2.0 * z)) - math.log(2.0)


# --------------------------------------------------------------------------
# the dataclass
# --------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class TestProblem:
    """One two-point BVP ``x' = rhs(t, x)``, ``bc_a(x(a)) = 0``, ``bc_b(x(b)) = 0``.

    ``exact(t)`` returns an array of shape ``(len(t), n)`` (``None`` if the
    problem had no exact / reference solution; all problems defined here do).
    """

    __test__ = False  # keep pytest from trying to collect this class

    name: str
    eps: Optional[float]
    a: float
    b: float
    n: int
    rhs_torch: Callable
    bc_a_torch: Callable
    bc_b_torch: Callable
    fun_np: Callable
    bc_np: Callable
    exact: Optional[Callable]
    description: str
    # --- extras (defaults) -------------------------------------------------
    n_left: int = 1                    # number of boundary conditions at a
    bc_values: tuple = (0.0, 0.0)      # (y(a), y(b)) -> straight-line guess
    layers: tuple = ()                 # locations of boundary/interior layers
    params: dict = field(default_factory=dict)
    exact_kind: str = "closed-form"    # "closed-form" | "semi-analytic" | "scipy-reference"
    source: str = ""

    # ------------------------------------------------------------------
    @property
    def label(self) -> str:
        """Short human label, e.g. ``'bvpT1 eps=1e-03'`` or ``'troesch mu=10'``."""
        if self.eps is not None:
            return f"{self.name} eps={self.eps:.0e}"
        if self.params:
            return self.name + " " + " ".join(f"{k}={v:g}" for k, v in self.params.items())
        return self.name

    @property
    def param_str(self) -> str:
        """The parameter column of a table: ``'1e-03'``, ``'mu=10'`` or ``'-'``."""
        if self.eps is not None:
            return f"{self.eps:.0e}"
        if self.params:
            return ",".join(f"{k}={v:g}" for k, v in self.params.items())
        return "-"

    def straight_line_guess(self, t) -> np.ndarray:
        """Straight line between the Dirichlet values: ``(m, n)`` numpy array.

        ``y`` is linear from ``y(a)`` to ``y(b)``; ``y'`` is the constant slope.
        """
        t = np.asarray(t, dtype=float)
        ya, yb = self.bc_values
        slope = (yb - ya) / (self.b - self.a)
        x = np.empty((t.size, self.n))
        x[:, 0] = ya + slope * (t - self.a)
        x[:, 1] = slope
        return x

    def bvp(self):
        """``shootlab.BVP(rhs_torch, bc_a_torch, bc_b_torch)`` (imported lazily)."""
        import shootlab

        return shootlab.BVP(self.rhs_torch, self.bc_a_torch, self.bc_b_torch)


# --------------------------------------------------------------------------
# generic constructor for y'' = f(t, y, y'), y(a) = alpha, y(b) = beta
# --------------------------------------------------------------------------
def _as_t(t, x):
    if not torch.is_tensor(t):
        t = torch.as_tensor(t, dtype=x.dtype, device=x.device)
    return t


def _second_order(
    name: str,
    eps: Optional[float],
    a: float,
    b: float,
    f: Callable,            # f(t, y, yp, xp) -> y''
    alpha: float,
    beta: float,
    exact_y: Optional[Callable],    # numpy: (y(t), y'(t))
    description: str,
    *,
    layers: Sequence[float] = (),
    params: Optional[dict] = None,
    exact_kind: str = "closed-form",
    source: str = "",
) -> TestProblem:
    alpha = float(alpha)
    beta = float(beta)

    def rhs_torch(t, x):
        t = _as_t(t, x)
        y, yp = x[..., 0], x[..., 1]
        ypp = f(t, y, yp, _TORCH)
        ypp = ypp + torch.zeros_like(y)  # broadcast constants / scalar-t cases
        return torch.stack((yp, ypp), dim=-1)

    def bc_a_torch(xa):
        return xa[..., :1] - alpha

    def bc_b_torch(xb):
        return xb[..., :1] - beta

    def fun_np(t, y):
        t = np.asarray(t, dtype=float)
        y = np.asarray(y, dtype=float)
        ypp = f(t, y[0], y[1], _NP) + np.zeros_like(y[0])
        return np.vstack((y[1], ypp))

    def bc_np(ya, yb):
        return np.array([ya[0] - alpha, yb[0] - beta])

    def exact(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        y, yp = exact_y(t)
        return np.column_stack((np.broadcast_to(y, t.shape), np.broadcast_to(yp, t.shape)))

    return TestProblem(
        name=name, eps=eps, a=float(a), b=float(b), n=2,
        rhs_torch=rhs_torch, bc_a_torch=bc_a_torch, bc_b_torch=bc_b_torch,
        fun_np=fun_np, bc_np=bc_np, exact=exact if exact_y is not None else None, description=description,
        n_left=1, bc_values=(alpha, beta), layers=tuple(float(c) for c in layers),
        params=dict(params or {}), exact_kind=exact_kind, source=source,
    )


_CASH = "Cash & Mazzia BVP test set"


# --------------------------------------------------------------------------
# Cash / Mazzia test set problems (all with closed-form solutions)
# --------------------------------------------------------------------------
def bvpT1(eps: float) -> TestProblem:
    """bvpT1: eps y'' - y = 0 on [0, 1], y(0) = 1, y(1) = 0.

    Exact: y = (exp(-t/s) - exp((t-2)/s)) / (1 - exp(-2/s)), s = sqrt(eps).
    Boundary layer of width sqrt(eps) at t = 0.
    """
    s = math.sqrt(eps)
    den = -math.expm1(-2.0 / s)

    def f(t, y, yp, xp):
        return y / eps

    def ex(t):
        e1, e2 = np.exp(-t / s), np.exp((t - 2.0) / s)
        return (e1 - e2) / den, (-e1 - e2) / (s * den)

    return _second_order(
        "bvpT1", eps, 0.0, 1.0, f, 1.0, 0.0, ex,
        "eps*y'' - y = 0, y(0)=1, y(1)=0; exact (e^{-t/sqrt(eps)} - e^{(t-2)/sqrt(eps)})/(1 - e^{-2/sqrt(eps)})",
        layers=(0.0,), source=_CASH + ", bvpT1",
    )


def bvpT2(eps: float) -> TestProblem:
    """bvpT2: eps y'' - y' = 0 on [0, 1], y(0) = 1, y(1) = 0.

    Exact: y = (1 - exp((t-1)/eps)) / (1 - exp(-1/eps)).  Layer of width eps at t = 1.
    """
    den = -math.expm1(-1.0 / eps)

    def f(t, y, yp, xp):
        return yp / eps

    def ex(t):
        e = np.exp((t - 1.0) / eps)
        return (1.0 - e) / den, -e / (eps * den)

    return _second_order(
        "bvpT2", eps, 0.0, 1.0, f, 1.0, 0.0, ex,
        "eps*y'' - y' = 0, y(0)=1, y(1)=0; exact (1 - e^{(t-1)/eps})/(1 - e^{-1/eps})",
        layers=(1.0,), source=_CASH + ", bvpT2",
    )


def bvpT3(eps: float) -> TestProblem:
    """bvpT3: eps y'' + (2 + cos(pi t)) y' - y = -(1 + eps pi^2) cos(pi t) - (2 + cos(pi t)) pi sin(pi t)
    on [-1, 1], y(-1) = y(1) = -1.  Exact: y = cos(pi t) (no layer in the solution).
    """
    pi = math.pi

    def f(t, y, yp, xp):
        c, sn = xp.cos(pi * t), xp.sin(pi * t)
        return (-(2.0 + c) * yp + y - (1.0 + eps * pi * pi) * c - (2.0 + c) * pi * sn) / eps

    def ex(t):
        return np.cos(pi * t), -pi * np.sin(pi * t)

    return _second_order(
        "bvpT3", eps, -1.0, 1.0, f, -1.0, -1.0, ex,
        "eps*y'' + (2+cos(pi t)) y' - y = -(1+eps pi^2) cos(pi t) - (2+cos(pi t)) pi sin(pi t), "
        "y(-1)=y(1)=-1; exact cos(pi t)",
        layers=(-1.0,), source=_CASH + ", bvpT3",
    )


def bvpT4(eps: float) -> TestProblem:
    """bvpT4: eps y'' + y' - (1 + eps) y = 0 on [-1, 1],
    y(-1) = 1 + exp(-2), y(1) = 1 + exp(-2 (1 + eps)/eps).

    Exact: y = exp(t - 1) + exp(-(1 + eps)(1 + t)/eps).  Layer of width eps at t = -1.
    """
    k = (1.0 + eps) / eps

    def f(t, y, yp, xp):
        return (-yp + (1.0 + eps) * y) / eps

    def ex(t):
        e1, e2 = np.exp(t - 1.0), np.exp(-k * (1.0 + t))
        return e1 + e2, e1 - k * e2

    return _second_order(
        "bvpT4", eps, -1.0, 1.0, f, 1.0 + math.exp(-2.0), 1.0 + math.exp(-2.0 * k), ex,
        "eps*y'' + y' - (1+eps) y = 0, y(-1)=1+e^{-2}, y(1)=1+e^{-2(1+eps)/eps}; "
        "exact e^{t-1} + e^{-(1+eps)(1+t)/eps}",
        layers=(-1.0,), source=_CASH + ", bvpT4",
    )


def bvpT5(eps: float) -> TestProblem:
    """bvpT5 (turning point): eps y'' = y + t y' - (1 + eps pi^2) cos(pi t) + pi t sin(pi t)
    on [-1, 1], y(-1) = y(1) = -1.  Exact: y = cos(pi t).

    Sign convention of the authors' R/Fortran code; the exact solution is the
    same with ``-t y'`` / ``-pi t sin`` (the two terms cancel on cos(pi t)).
    """
    pi = math.pi

    def f(t, y, yp, xp):
        return (y + t * yp - (1.0 + eps * pi * pi) * xp.cos(pi * t) + pi * t * xp.sin(pi * t)) / eps

    def ex(t):
        return np.cos(pi * t), -pi * np.sin(pi * t)

    return _second_order(
        "bvpT5", eps, -1.0, 1.0, f, -1.0, -1.0, ex,
        "eps*y'' - t y' - y = -(1+eps pi^2) cos(pi t) + pi t sin(pi t), y(-1)=y(1)=-1; exact cos(pi t)",
        layers=(0.0,), source=_CASH + ", bvpT5",
    )


def _turning_point(name: str, eps: float, c: float, alpha: float, beta: float, ex: Callable,
                   description: str) -> TestProblem:
    """bvpT6 / bvpT7: eps y'' + t y' - c y = -(c + eps pi^2) cos(pi t) - pi t sin(pi t) on [-1, 1]
    (a layer at the turning point t = 0); ``ex``: the exact (y, y')."""
    pi = math.pi

    def f(t, y, yp, xp):
        return (-t * yp + c * y - (c + eps * pi * pi) * xp.cos(pi * t) - pi * t * xp.sin(pi * t)) / eps

    return _second_order(name, eps, -1.0, 1.0, f, alpha, beta, ex, description, layers=(0.0,),
                         source=f"{_CASH}, {name}")


def bvpT6(eps: float) -> TestProblem:
    """bvpT6 (interior shock layer): eps y'' + t y' = -eps pi^2 cos(pi t) - pi t sin(pi t)
    on [-1, 1], y(-1) = -2, y(1) = 0.

    Exact: y = cos(pi t) + erf(t/sqrt(2 eps)) / erf(1/sqrt(2 eps)).  Layer of width sqrt(eps) at t = 0.
    """
    pi = math.pi
    s = math.sqrt(2.0 * eps)
    E = math.erf(1.0 / s)

    def ex(t):
        y = np.cos(pi * t) + _sp.erf(t / s) / E
        yp = -pi * np.sin(pi * t) + 2.0 / (math.sqrt(pi) * s) * np.exp(-(t / s) ** 2) / E
        return y, yp

    return _turning_point("bvpT6", eps, 0.0, -2.0, 0.0, ex,
                          "eps*y'' + t y' = -eps pi^2 cos(pi t) - pi t sin(pi t), y(-1)=-2, y(1)=0; "
                          "exact cos(pi t) + erf(t/sqrt(2 eps))/erf(1/sqrt(2 eps))")


def bvpT7(eps: float) -> TestProblem:
    """bvpT7 (turning point, corner layer): eps y'' + t y' - y = -(1 + eps pi^2) cos(pi t) - pi t sin(pi t)
    on [-1, 1], y(-1) = -1, y(1) = 1.

    Exact: y = cos(pi t) + t + (t erf(t/s) + (s/sqrt(pi)) exp(-t^2/s^2)) / D,
    s = sqrt(2 eps), D = erf(1/s) + (s/sqrt(pi)) exp(-1/s^2).
    """
    pi = math.pi
    s = math.sqrt(2.0 * eps)
    c0 = s / math.sqrt(pi)
    D = math.erf(1.0 / s) + c0 * math.exp(-1.0 / (s * s))

    def ex(t):
        erf = _sp.erf(t / s)
        y = np.cos(pi * t) + t + (t * erf + c0 * np.exp(-(t / s) ** 2)) / D
        yp = -pi * np.sin(pi * t) + 1.0 + erf / D
        return y, yp

    return _turning_point("bvpT7", eps, 1.0, -1.0, 1.0, ex,
                          "eps*y'' + t y' - y = -(1+eps pi^2) cos(pi t) - pi t sin(pi t), y(-1)=-1, y(1)=1; "
                          "exact cos(pi t) + t + (t erf(t/s) + s/sqrt(pi) e^{-t^2/s^2})/(erf(1/s) + "
                          "s/sqrt(pi) e^{-1/s^2}), s=sqrt(2 eps)")


def bvpT9(eps: float) -> TestProblem:
    """bvpT9: (eps + t^2) y'' + 4 t y' + 2 y = 0 on [-1, 1], y(-1) = y(1) = 1/(1 + eps).

    Exact: y = 1/(eps + t^2) (peak 1/eps at t = 0, width sqrt(eps)).
    """

    def f(t, y, yp, xp):
        return -(4.0 * t * yp + 2.0 * y) / (eps + t * t)

    def ex(t):
        d = eps + t * t
        return 1.0 / d, -2.0 * t / (d * d)

    v = 1.0 / (1.0 + eps)
    return _second_order(
        "bvpT9", eps, -1.0, 1.0, f, v, v, ex,
        "(eps + t^2) y'' + 4 t y' + 2 y = 0, y(-1)=y(1)=1/(1+eps); exact 1/(eps + t^2)",
        layers=(0.0,), source=_CASH + ", bvpT9",
    )


def bvpT10(eps: float) -> TestProblem:
    """bvpT10 (interior shock): eps y'' + t y' = 0 on [-1, 1], y(-1) = 0, y(1) = 2.

    Exact: y = 1 + erf(t/sqrt(2 eps)) / erf(1/sqrt(2 eps)).
    """
    s = math.sqrt(2.0 * eps)
    E = math.erf(1.0 / s)

    def f(t, y, yp, xp):
        return -t * yp / eps

    def ex(t):
        return 1.0 + _sp.erf(t / s) / E, 2.0 / (math.sqrt(math.pi) * s) * np.exp(-(t / s) ** 2) / E

    return _second_order(
        "bvpT10", eps, -1.0, 1.0, f, 0.0, 2.0, ex,
        "eps*y'' + t y' = 0, y(-1)=0, y(1)=2; exact 1 + erf(t/sqrt(2 eps))/erf(1/sqrt(2 eps))",
        layers=(0.0,), source=_CASH + ", bvpT10",
    )


def bvpT20(eps: float) -> TestProblem:
    """bvpT20 (nonlinear, corner layer): eps y'' + (y')^2 - 1 = 0 on [0, 1],
    y(0) = 1 + eps ln cosh(-0.745/eps), y(1) = 1 + eps ln cosh(0.255/eps).

    Exact: y = 1 + eps ln cosh((t - 0.745)/eps), y' = tanh((t - 0.745)/eps).
    """
    c = 0.745

    def f(t, y, yp, xp):
        return (1.0 - yp * yp) / eps

    def ex(t):
        z = (t - c) / eps
        return 1.0 + eps * _logcosh(z), np.tanh(z)

    ya = 1.0 + eps * float(_logcosh(-c / eps))
    yb = 1.0 + eps * float(_logcosh((1.0 - c) / eps))
    return _second_order(
        "bvpT20", eps, 0.0, 1.0, f, ya, yb, ex,
        "eps*y'' + (y')^2 - 1 = 0, y(0)=1+eps ln cosh(-0.745/eps), y(1)=1+eps ln cosh(0.255/eps); "
        "exact 1 + eps ln cosh((t-0.745)/eps)",
        layers=(c,), source=_CASH + ", bvpT20",
    )


def bvpT21(eps: float) -> TestProblem:
    """bvpT21 (nonlinear): eps y'' = y + y^2 - exp(-2 t/sqrt(eps)) on [0, 1],
    y(0) = 1, y(1) = exp(-1/sqrt(eps)).   Exact: y = exp(-t/sqrt(eps)).
    """
    s = math.sqrt(eps)

    def f(t, y, yp, xp):
        return (y + y * y - xp.exp(-2.0 * t / s)) / eps

    def ex(t):
        e = np.exp(-t / s)
        return e, -e / s

    return _second_order(
        "bvpT21", eps, 0.0, 1.0, f, 1.0, math.exp(-1.0 / s), ex,
        "eps*y'' = y + y^2 - e^{-2t/sqrt(eps)}, y(0)=1, y(1)=e^{-1/sqrt(eps)}; exact e^{-t/sqrt(eps)}",
        layers=(0.0,), source=_CASH + ", bvpT21",
    )


_CASH_BUILDERS = {
    "bvpT1": bvpT1,
    "bvpT2": bvpT2,
    "bvpT3": bvpT3,
    "bvpT4": bvpT4,
    "bvpT5": bvpT5,
    "bvpT6": bvpT6,
    "bvpT7": bvpT7,
    "bvpT9": bvpT9,
    "bvpT10": bvpT10,
    "bvpT20": bvpT20,
    "bvpT21": bvpT21,
}
CASH_PROBLEM_NAMES = tuple(_CASH_BUILDERS)


def cash_problems(eps_values: Sequence[float] = DEFAULT_EPS,
                  names: Optional[Sequence[str]] = None) -> list[TestProblem]:
    """The singularly perturbed Cash/Mazzia problems, one instance per ``eps``.

    ``names`` restricts the selection (default: all of :data:`CASH_PROBLEM_NAMES`).
    Order: problem-major, then ``eps`` in the order given.
    """
    names = CASH_PROBLEM_NAMES if names is None else tuple(names)
    unknown = set(names) - set(_CASH_BUILDERS)
    if unknown:
        raise ValueError(f"unknown Cash problem(s) {sorted(unknown)}; known: {CASH_PROBLEM_NAMES}")
    return [_CASH_BUILDERS[nm](float(e)) for nm in names for e in eps_values]


# --------------------------------------------------------------------------
# classic problems used by the solver's tests
# --------------------------------------------------------------------------
def linear_unstable() -> TestProblem:
    """y'' = 400 y on [0, 1], y(0) = 1, y(1) = exp(-20).  Exact: y = exp(-20 t).

    The classic example of single shooting failing: the complementary
    solution exp(20 t) amplifies initial-value errors by ~e^20 ~ 5e8.
    """

    def f(t, y, yp, xp):
        return 400.0 * y

    def ex(t):
        e = np.exp(-20.0 * t)
        return e, -20.0 * e

    return _second_order(
        "linear_unstable", None, 0.0, 1.0, f, 1.0, math.exp(-20.0), ex,
        "y'' = 400 y, y(0)=1, y(1)=e^{-20}; exact e^{-20 t}",
        layers=(0.0,), source="classic shooting-instability example",
    )


# ---- Troesch: semi-analytic solution via the first integral -------------
# y'' = mu sinh(mu y) has the first integral y'^2 = s^2 + 4 sinh^2(mu y / 2),
# s = y'(0).  With sinh(mu y/2) = (s/2) sinh(T) the inverse map is
#     mu x = int_0^T dtau / sqrt(1 + (s^2/4) sinh^2 tau)          (*)
# (equivalently y = (2/mu) asinh((s/2) sc(mu x | 1 - s^2/4)), Jacobi sc).
# The integrand in (*) is smooth and O(1), so Gauss-Legendre is accurate to
# machine precision; this avoids the loss of accuracy of incomplete elliptic
# integrals for parameter m = 1 - s^2/4 within ~1e-8 of 1 (mu = 10).
_GL_X, _GL_W = np.polynomial.legendre.leggauss(256)


def _troesch_integral(T, s):
    T = np.asarray(T, dtype=float)[..., None]
    tau = 0.5 * T * (_GL_X + 1.0)
    h = 1.0 / np.sqrt(1.0 + (0.25 * s * s) * np.sinh(tau) ** 2)
    return 0.5 * T[..., 0] * np.sum(h * _GL_W, axis=-1)


_TROESCH_CACHE: dict = {}


def troesch_slope(mu: float) -> float:
    """y'(0) of Troesch's problem (mu=5: 4.5750461e-2, mu=10: 3.5833778e-4)."""
    mu = float(mu)
    if mu not in _TROESCH_CACHE:
        def g(log_s):
            s = math.exp(log_s)
            T1 = math.asinh(2.0 / s * math.sinh(0.5 * mu))
            return float(_troesch_integral(T1, s)) / mu - 1.0

        log_s = brentq(g, math.log(1e-30), math.log(1.999), xtol=1e-16, rtol=1e-15, maxiter=500)
        _TROESCH_CACHE[mu] = math.exp(log_s)
    return _TROESCH_CACHE[mu]


def _troesch_exact(mu: float, s: float, x: np.ndarray):
    x = np.asarray(x, dtype=float)
    target = mu * x
    T = target.copy()                       # h ~ 1 for small tau
    polish = 0
    for _ in range(100):
        F = _troesch_integral(T, s) - target
        h = 1.0 / np.sqrt(1.0 + (0.25 * s * s) * np.sinh(T) ** 2)
        dT = F / h
        T = T - dT
        # quadratic convergence: once below 1e-9, two more steps reach the
        # round-off floor (~1e-14 relative in T, ~1e-15 in y)
        if np.all(np.abs(dT) <= 1e-9 * (1.0 + np.abs(T))):
            polish += 1
            if polish > 2:
                break
    y = (2.0 / mu) * np.arcsinh(0.5 * s * np.sinh(T))
    yp = np.sqrt(s * s + 4.0 * np.sinh(0.5 * mu * y) ** 2)
    return y, yp


def troesch(mu: float = 10.0) -> TestProblem:
    """Troesch's problem (bvpT23): y'' = mu sinh(mu y) on [0, 1], y(0) = 0, y(1) = 1.

    The solution is semi-analytic (first integral, see ``_troesch_integral``);
    y'(0) = 4.575046e-2 for mu = 5 and 3.5833778e-4 for mu = 10 (literature
    values, reproduced to all quoted digits).  Boundary layer at t = 1.
    """
    mu = float(mu)
    s = troesch_slope(mu)

    def f(t, y, yp, xp):
        return mu * xp.sinh(mu * y)

    def ex(t):
        return _troesch_exact(mu, s, t)

    return _second_order(
        "troesch", None, 0.0, 1.0, f, 0.0, 1.0, ex,
        f"y'' = mu sinh(mu y), mu={mu:g}, y(0)=0, y(1)=1; y'(0)={s:.10e} "
        "(semi-analytic: y = (2/mu) asinh((s/2) sc(mu t | 1 - s^2/4)))",
        layers=(1.0,), params={"mu": mu}, exact_kind="semi-analytic",
        source="Troesch (1976); Cash & Mazzia BVP test set, bvpT23",
    )


def bratu_theta() -> float:
    """Smaller root of theta = sqrt(2) cosh(theta/4) (~1.5171646)."""
    return brentq(lambda th: th - math.sqrt(2.0) * math.cosh(0.25 * th), 0.0, 4.0, xtol=1e-16, rtol=1e-15)


def bratu() -> TestProblem:
    """Bratu's problem (lambda = 1): y'' + exp(y) = 0 on [0, 1], y(0) = y(1) = 0, lower branch.

    Exact: y = -2 ln(cosh((t - 1/2) theta/2) / cosh(theta/4)), theta the smaller
    root of theta = sqrt(2) cosh(theta/4).
    """
    th = bratu_theta()
    c4 = math.cosh(0.25 * th)

    def f(t, y, yp, xp):
        return -xp.exp(y)

    def ex(t):
        z = 0.5 * th * (t - 0.5)
        return -2.0 * np.log(np.cosh(z) / c4), -th * np.tanh(z)

    return _second_order(
        "bratu", None, 0.0, 1.0, f, 0.0, 0.0, ex,
        f"y'' + e^y = 0, y(0)=y(1)=0 (lower branch); exact -2 ln(cosh((t-1/2) th/2)/cosh(th/4)), th={th:.12f}",
        params={"lambda": 1.0}, source="Bratu (1914); closed form e.g. Ascher-Mattheij-Russell (1995)",
    )


def singular_perturbation(eps: float = 1e-3) -> TestProblem:
    """eps y'' + y' = 0 on [0, 1], y(0) = 0, y(1) = 1.

    Exact: y = (1 - exp(-t/eps)) / (1 - exp(-1/eps)).  Layer of width eps at t = 0
    (cf. bvpT8 of the test set, which has the same equation with y(0)=1, y(1)=2).
    """
    eps = float(eps)
    den = -math.expm1(-1.0 / eps)

    def f(t, y, yp, xp):
        return -yp / eps

    def ex(t):
        e = np.exp(-t / eps)
        return -np.expm1(-t / eps) / den, e / (eps * den)

    return _second_order(
        "singular_perturbation", eps, 0.0, 1.0, f, 0.0, 1.0, ex,
        "eps*y'' + y' = 0, y(0)=0, y(1)=1; exact (1 - e^{-t/eps})/(1 - e^{-1/eps})",
        layers=(0.0,), source="classic; cf. Cash & Mazzia BVP test set, bvpT8",
    )


def classic_problems(eps_values: Sequence[float] = DEFAULT_EPS,
                     troesch_mus: Sequence[float] = (5.0, 10.0)) -> list[TestProblem]:
    """linear_unstable, troesch(mu) for each mu, bratu, singular_perturbation(eps) for each eps."""
    probs = [linear_unstable()]
    probs += [troesch(mu) for mu in troesch_mus]
    probs.append(bratu())
    probs += [singular_perturbation(e) for e in eps_values]
    return probs


def all_problems(eps_values: Sequence[float] = DEFAULT_EPS) -> list[TestProblem]:
    """:func:`cash_problems` followed by :func:`classic_problems`."""
    return cash_problems(eps_values) + classic_problems(eps_values)


# --------------------------------------------------------------------------
# error measurement helpers (shared by the tests and the benchmark)
# --------------------------------------------------------------------------
def fine_grid(problem: TestProblem, n_uniform: int = 2001, n_layer: int = 241) -> np.ndarray:
    """Sorted evaluation grid on [a, b]: ``n_uniform`` uniform points plus points
    clustered geometrically (offsets 1e-9 ... 1 times (b - a)) on both sides of
    every layer location, so that layers of any width >= ~1e-8 are resolved.
    """
    a, b = problem.a, problem.b
    pts = [np.linspace(a, b, n_uniform)]
    offs = (b - a) * np.logspace(-9, 0, n_layer)
    for c in problem.layers:
        pts.append(c + offs)
        pts.append(c - offs)
        pts.append(np.array([c]))
    g = np.concatenate(pts)
    g = g[(g >= a) & (g <= b)]
    return np.unique(g)


def relative_max_error(problem: TestProblem, t: np.ndarray, x_num: np.ndarray,
                       component: Optional[int] = 0) -> float:
    """max |x_num - exact| / max |exact| over ``t``.

    ``component=0`` (default) measures the solution y only; ``None`` takes the
    worst component, each normalised by its own max magnitude.
    """
    if problem.exact is None:
        raise ValueError(f"{problem.label} has no exact/reference solution")
    ex = problem.exact(t)
    x_num = np.asarray(x_num, dtype=float).reshape(ex.shape)
    comps = range(problem.n) if component is None else [component]
    worst = 0.0
    for i in comps:
        scale = float(np.max(np.abs(ex[:, i])))
        scale = scale if scale > 0.0 else 1.0
        err = float(np.max(np.abs(x_num[:, i] - ex[:, i]))) / scale
        worst = max(worst, err) if np.isfinite(err) else math.inf
    return worst


def _main(argv: Sequence[str] | None = None) -> int:
    """``python -m studies.bvp_testset``: list the problems (this module only defines them; the
    comparison with scipy's solve_bvp is ``python benchmarks/bvp_testset.py``)."""
    import argparse
    ap = argparse.ArgumentParser(prog="python -m studies.bvp_testset", description=__doc__.splitlines()[0],
                                 epilog="Solve them with: python benchmarks/bvp_testset.py (--help for its options)")
    ap.add_argument("--eps", type=float, nargs="+", default=list(DEFAULT_EPS),
                    help="perturbation parameters of the Cash & Mazzia problems to list (default %(default)s)")
    args = ap.parse_args(argv)
    for p in cash_problems(args.eps) + [linear_unstable(), troesch(), bratu(), singular_perturbation()]:
        print(f"{p.label:<28} [{p.a:g}, {p.b:g}]" + ("" if p.exact is None else "  exact/reference solution"))
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
