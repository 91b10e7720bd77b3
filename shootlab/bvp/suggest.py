"""How many shooting points?  A rule from the local Jacobian's eigenvalues and the integrator's
stability function — the report's "rules to tune the number of shooting points" (ch. 5, future work).

    sug = shootlab.suggest_shooting_points(prob, (t, x_guess), "rk4", steps=1)
    sug.m, sug.limited_by, print(sug)

The rule (see :func:`suggest_shooting_points`) is validated against observed sweeps
(docs/design.md §2).  An estimate's default number of points
(:func:`shootlab.estimation.fit.default_points`) reads the same eigenvalues (:func:`local_eigenvalues`
at the initial approximation) to set the record's length against the model's fastest time scale.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from shootlab.bvp.integrators.base import Integrator
from .tangents import batch_jacobian
from .integrators import get_integrator
from .spectrum import batched_eigvals

__all__ = ["suggest_shooting_points", "Suggestion", "local_eigenvalues", "stability_function", "real_stability_limit"]

#: allowed spurious growth (or decay) of one mode over the whole interval [a, b]
SPURIOUS_GROWTH = 10.0
#: the per-interval growth of the growing modes is allowed up to GROWTH_SAFETY · tol / ε
GROWTH_SAFETY = 1.0


# -- eigenvalues -----------------------------------------------------------------------------
def local_eigenvalues(rhs: Callable[[Tensor, Tensor], Tensor], t: Tensor, x: Tensor) -> Tensor:
    """Eigenvalues of the local Jacobian ∂f/∂x at every point: complex tensor (k, n) for t (k,),
    x (k, n).  The report's stiffness measure is κ(t) = min Re λ (eq. 5.6).  A point whose
    eigenvalues LAPACK cannot compute gets NaN (:func:`shootlab.bvp.spectrum.batched_eigvals`).
    The Jacobians are formed on the device of x; the eigenvalues are computed on the CPU (an
    accelerator's batched eigenvalue solver loops over the matrices) and returned there."""
    t = torch.as_tensor(t, dtype=x.dtype, device=x.device)
    with torch.no_grad():
        J = batch_jacobian(rhs, t, x.detach())
    return batched_eigvals(J.detach().cpu())


# -- stability functions ---------------------------------------------------------------------
def stability_function(integrator: str | Integrator) -> tuple[Callable[[np.ndarray], np.ndarray], str]:
    """(R, kind) for one step of the integrator: y_{k+1} = R(τλ) y_k on y' = λ y.

    Both are the scheme's own facts (:mod:`shootlab.bvp.integrators`: ``stability`` and ``kind``):
    the polynomial of the Butcher tableau for the explicit Runge–Kutta schemes, 1/(1 − z) for
    ``implicit_euler``, (1 + z/2)/(1 − z/2) for ``midpoint``, (1 + z/3)/(1 − 2z/3 + z²/6) for
    ``radau3``; for the adaptive schemes (``dopri5``, ``ros4``, ``auto``) exp(z), because their
    step-size control keeps them stable (``dopri5`` at the price of many steps on stiff intervals).
    kind is ``"explicit"``, ``"implicit"`` or ``"adaptive"``."""
    cls = type(get_integrator(integrator) if isinstance(integrator, str) else integrator)
    own = getattr(cls.stability, "__func__", cls.stability)
    declared = getattr(cls, "kind", None) is not None and own is not Integrator.stability.__func__
    if cls.adaptive or not declared:     # (a user's scheme without the facts: as an adaptive one)
        return np.exp, "adaptive"
    return cls.stability, cls.kind


def real_stability_limit(integrator: str | Integrator, hi: float = 1e3) -> float:
    """The largest x ≤ ``hi`` with |R(−t)| ≤ 1 on [0, x] in the sense of bisection: the real
    stability limit −hλ of one step (2 for Euler, 2.785 for RK4; ``hi`` for A-stable schemes)."""
    R, _ = stability_function(integrator)
    if abs(R(-hi)) <= 1:
        return float(hi)
    lo = 0.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if abs(R(-mid)) <= 1 else (lo, mid)
    return lo


# -- the rule ----------------------------------------------------------------------------------
@dataclass
class Suggestion:
    """Outcome of :func:`suggest_shooting_points` (all eigenvalue numbers over the probe points)."""

    m: int                     # suggested number of shooting points (the larger of the two below)
    m_stability: int           # smallest m with no mode spuriously growing / decaying over [a, b]
    m_growth: int              # smallest m with per-interval growth ≤ growth_limit
    limited_by: str            # "stability", "growth" or "none" (m = 2 suffices)
    integrator: str
    steps: int
    kind: str                  # explicit / implicit / adaptive
    interval: tuple[float, float]
    kappa: float               # κ = min Re λ (report eq. 5.6)
    kappa_plus: float          # max Re λ (the Hamiltonian partner)
    rho: float                 # max |λ|
    h: float                   # interval length at m
    kappa_h: float             # κ·h at m (the report's stiffness measure per interval)
    growth: float              # largest per-interval amplification max |R(hλ/steps)|^steps at m
    growth_limit: float
    spurious_growth: float

    def as_dict(self) -> dict:
        return asdict(self)

    def __str__(self) -> str:
        return (f"{self.integrator} (steps={self.steps}): m = {self.m} shooting points "
                f"(stability {self.m_stability}, growth {self.m_growth}; limited by {self.limited_by}); "
                f"κ = {self.kappa:.4g}, κ₊ = {self.kappa_plus:.4g}, max|λ| = {self.rho:.4g}, "
                f"h = {self.h:.3g}, κh = {self.kappa_h:.3g}, growth per interval {self.growth:.3g}")


def _as_points(guess, t):
    """(t, x) tensors from a (t, x) pair, a ShootingResult-like object or x with ``t``."""
    if hasattr(guess, "t") and hasattr(guess, "x"):
        return torch.as_tensor(guess.t), torch.as_tensor(guess.x)
    if isinstance(guess, (tuple, list)) and len(guess) == 2 and t is None:
        t, guess = guess
    if t is None:
        raise ValueError("give the guess as (t, x), as a ShootingResult, or pass t=")
    x = torch.as_tensor(guess, dtype=torch.float64) if not isinstance(guess, Tensor) else guess
    t = torch.as_tensor(t, dtype=x.dtype)
    if x.ndim != 2 or t.ndim != 1 or x.shape[0] != t.numel():
        raise ValueError(f"guess must be (k, n) at the k points of t, got x {tuple(x.shape)}, t {tuple(t.shape)}")
    return t, x


def _rhs_of(problem) -> Callable:
    if callable(getattr(problem, "rhs", None)):
        return problem.rhs
    if callable(getattr(problem, "bvp", None)):
        return problem.bvp().rhs
    if callable(problem):
        return problem
    raise ValueError("problem must be a shootlab.BVP, have an rhs(t, x) method, or be rhs itself")


def suggest_shooting_points(problem, guess, integrator: str | Integrator = "rk4", *, steps: int | None = None,
                            t=None, interval: tuple[float, float] | None = None, tol: float = 1e-10,
                            growth_limit: float | None = None, spurious_growth: float = SPURIOUS_GROWTH,
                            eigenvalues: Tensor | None = None, m_max: int = 10 ** 7) -> Suggestion:
    """Smallest number m of equidistant shooting points on [a, b] for which ``integrator`` with
    ``steps`` steps per interval stays stable and Newton can converge to ``tol``.

    problem   a :class:`shootlab.BVP` (only ``rhs`` is used) or an object with ``rhs``/``bvp()``
    guess     the initial approximation (or a solution) at some probe points: ``(t, x)``, a
              :class:`~shootlab.ShootingResult`, or ``x`` with ``t=``; the local Jacobians
              ∂f/∂x are evaluated there (``eigenvalues`` (k, n) may be given instead)
    interval  [a, b] (default: the probe grid's ends)

    The rule.  Let λ run over the eigenvalues of ∂f/∂x at the probe points (for an optimal-
    estimation TPBVP they come in Hamiltonian pairs ±λ), R the integrator's stability
    function (:func:`stability_function`), s = ``steps``, h = (b − a)/(m − 1) and τ = h/s;
    N = s (m − 1) steps cover [a, b].  Three conditions:

    1. *no decaying mode grows* (the integrator stays stable): for Re λ < 0,
       N·log|R(τλ)| ≤ log C — one step inside the stability region, up to a spurious growth
       C (``spurious_growth``, 10) over the whole interval, which lets a scheme whose
       region misses the imaginary axis (Euler) carry weakly damped oscillations;
    2. *no growing mode decays* (the dichotomy of the TPBVP survives — binds the L-stable
       implicit schemes, whose R(z) → 0 for z → +∞; they need τ max Re λ below ≈ 2 for
       implicit Euler and ≈ 6 for radau3): for Re λ > 0, N·log|R(τλ)| ≥ −log C;
    3. *the matching is well conditioned*: the per-interval amplification of every mode,
       G = max |R(τλ)|^s (≈ e^{κ₊ h} for an accurate scheme, κ₊ = max Re λ), must stay
       below G_max = tol/ε (``growth_limit``; ε the machine epsilon): an error ε|s_k| of a
       shooting value reaches y_k(t_{k+1}) as ε G |s_k|, and Newton cannot drive the
       matching residual below that, while it must reach tol·(1 + max|s|).

    m_stability is the smallest m meeting 1 and 2, m_growth the smallest meeting 3, and
    m = max(m_stability, m_growth, 2).  For real λ < 0 condition 1 is the classical
    h ≤ s·r/|κ| with r = 2 (Euler), 2.785 (RK4), 3.0 (RKF45 4th order), so with one step per
    interval m ≈ 1 + r⁻¹|κ|(b − a) — the report's "κ ≈ −5000 needs h ≈ 4e−4"; more steps per
    interval buy a longer interval until condition 3 takes over, at s·r ≈ log(tol/ε) ≈ 13:
    beyond about 4–5 RK4 steps per interval the explicit scheme no longer needs more steps,
    but the growing partner e^{κ₊h} forbids longer intervals.  The adaptive schemes (R = exp)
    only have condition 3.  The eigenvalues move during Newton's iteration (e.g. with the
    parameters): the rule is as good as the probe points (the guess or a solution).

    Validation (docs/design.md §2: the command, its table and figure): the mass–spring–damper with W_states = 1e-2 … 1e-6
    (κ ≈ −10 … −1000), the manipulator with V_s = 1e4 … 1e8 (κ ≈ −105 … −1e4) and the confined
    compression with N = 2, 3, 4, 6 elements (κ ≈ −290 … −1.5e4), each swept around the
    prediction.  With one step per interval (Euler, RK4) the observed minimal m at which Newton
    converges and the integrator stays stable is within a factor 2 of m in every case, and
    within 10 % once κ(b − a) ≳ 1000.  Not modelled: (i) accuracy — a first-order scheme can be
    stable and still too coarse (Euler on the lightly damped manipulator); (ii) Newton's
    *global* convergence from a far guess, which needs the solution resolved whatever the
    stiffness: with several RK4 steps per interval and weak stiffness (κ(b − a) of a few
    hundred) the observed minimum is up to ~5× the prediction (msd W_states = 1e-2: 36 points
    from m = b = k = 10, but 12 from the true values against the predicted 10).  So when
    κ(b − a) is below about a thousand the suggestion is a lower bound.
    """
    integ = get_integrator(integrator, steps=steps or 1) if isinstance(integrator, str) else integrator
    s = int(steps) if steps is not None else int(getattr(integ, "steps", 1))
    if s < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    R, kind = stability_function(integ)
    if eigenvalues is None:
        tt, x = _as_points(guess, t)
        lam = local_eigenvalues(_rhs_of(problem), tt, x)
    else:
        lam = torch.as_tensor(eigenvalues)
        tt = None if t is None and guess is None else _as_points(guess, t)[0]
    if interval is None:
        if tt is None:
            raise ValueError("give interval=(a, b) with eigenvalues=")
        interval = (float(tt[0]), float(tt[-1]))
    a, b = float(interval[0]), float(interval[1])
    if not b > a:
        raise ValueError(f"empty interval {interval}")
    T = b - a
    ev = lam.detach().cpu().numpy().astype(complex).reshape(-1)
    if not np.isfinite(ev).all():
        raise ValueError("the local Jacobian has non-finite eigenvalues at the probe points")
    ev = np.unique(np.round(ev, 12))
    G = growth_limit if growth_limit is not None else GROWTH_SAFETY * tol / np.finfo(np.float64).eps
    logC, logG = math.log(spurious_growth), math.log(G)
    dec, grow = ev.real < 0, ev.real > 0

    def log_amp(m: int) -> np.ndarray:
        tau = T / (s * (m - 1))
        with np.errstate(all="ignore"):
            r = np.abs(R(tau * ev))
            out = np.log(r)
        return np.where(np.isfinite(out), out, np.where(np.isnan(r), np.inf, out))

    def stable(m: int) -> bool:
        la, N = log_amp(m), s * (m - 1)
        ok = True
        if dec.any():
            ok &= bool(N * la[dec].max() <= logC)
        if grow.any():
            ok &= bool(N * la[grow].min() >= -logC)
        return ok

    def conditioned(m: int) -> bool:
        return bool(s * log_amp(m).max() <= logG)

    def smallest(pred) -> int:
        if pred(2):
            return 2
        hi = 3
        while not pred(hi):
            if hi >= m_max:
                return m_max
            hi = min(2 * hi, m_max)
        lo = hi // 2                  # pred(lo) False (or lo = 1)
        lo = max(lo, 2)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if pred(mid):
                hi = mid
            else:
                lo = mid
        return hi

    m_stab, m_grow = smallest(stable), smallest(conditioned)
    m = max(m_stab, m_grow, 2)
    limited = "none" if m == 2 else ("stability" if m_stab >= m_grow else "growth")
    h = T / (m - 1)
    kappa = float(ev.real.min())
    return Suggestion(m=int(m), m_stability=int(m_stab), m_growth=int(m_grow), limited_by=limited,
                      integrator=getattr(integ, "name", type(integ).__name__), steps=s, kind=kind,
                      interval=(a, b), kappa=kappa, kappa_plus=float(ev.real.max()),
                      rho=float(np.abs(ev).max()), h=h, kappa_h=kappa * h,
                      growth=float(math.exp(s * float(log_amp(m).max()))), growth_limit=float(G),
                      spurious_growth=float(spurious_growth))
