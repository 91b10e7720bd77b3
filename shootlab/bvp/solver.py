"""``shootlab.solve``: multiple shooting for a TPBVP, with tolerance continuation (report ch. 5).

Continuation: ``continuation=[stage, stage, …]`` is a list of dicts of solver settings
(``integrator``, ``steps``, ``rtol``, ``atol``, ``tol``, ``max_iter``, ``newton``,
``newton_options``), from loose to tight — typically one explicit Euler step per interval
first, as in the report.  Each stage starts from the previous stage's solution; settings
not given in a stage are those passed to ``solve``.  The result records every stage.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import torch
from torch import Tensor

from .integrators import INTEGRATORS, get_integrator
from .newton import CONVERGED, INTERVALS_TOO_LONG, MAX_ITER, STEP_TOO_SMALL, NewtonOutcome, get_newton, stalled
from .problem import BVP, as_tensor, check_problem
from .spectrum import SPECTRAL_METHODS
from .shooting import ShootingBatch, ShootingSystem, interval_growth, local_spectrum

DEFAULT_INTEGRATOR = "auto"      # dop853 per interval, ros4 only on the intervals whose local Jacobian is stiff
DEFAULT_RTOL, DEFAULT_ATOL = 1e-10, 1e-12
DEFAULT_TOL = 1e-10     # Newton: max|F| ≤ tol·(1 + max|s|)
BLOWUP_FACTOR = 1e12    # an IVP value 1e12 x the guess's scale counts as overflow

_STAGE_KEYS = {"integrator", "steps", "rtol", "atol", "tol", "max_iter", "newton", "newton_options", "jacobian",
               "jacobian_rtol"}


@dataclass
class ShootingResult:
    """Outcome of :func:`solve` (fields as in ``scipy.integrate.solve_bvp``'s result, plus history)."""

    success: bool
    status: int
    message: str
    t: Tensor
    x: Tensor
    iterations: int
    jacobian_evaluations: int
    residual_norm: float
    history: list[dict]
    stages: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    points: int = 0                    # shooting points used (those of t plus any added by ``refine``)
    _system: Any = field(default=None, repr=False)
    _x_all: Any = field(default=None, repr=False)       # the state at all ``points``

    def sol(self, tq, grid: bool = False) -> Tensor:
        """Solution at times tq (k,), shape (k, n), re-integrated from the shooting points;
        ``grid``: a fixed-step scheme's values on its own step grid, at the cost of one
        integration of the intervals (:meth:`~shootlab.bvp.integrators.Integrator.dense`)."""
        return self._system.dense(self._times(tq), self.x if self._x_all is None else self._x_all, grid)

    def swept(self, tq) -> Tensor:
        """Solution at the increasing times tq (k,), shape (k, n), from one pass over all intervals
        (:meth:`~shootlab.bvp.shooting.ShootingSystem.sweep`: a fixed-step scheme's own step values
        where tq lies on its step grid, else each interval integrated through its times of tq;
        an implicit scheme off its grid as :meth:`sol`, in batches); time and memory linear in
        k, for the samples of a long record."""
        return self._system.sweep(self._times(tq), self.x if self._x_all is None else self._x_all)

    def _times(self, tq) -> Tensor:
        """tq as a flat tensor of this solution's dtype; ValueError for a time that is not finite
        or lies outside [t_1, t_m]."""
        tq = as_tensor(tq, dtype=self.t.dtype, device=self.t.device, name="tq").reshape(-1)
        if not torch.isfinite(tq).all():
            raise ValueError("tq contains NaN or inf")
        lo, hi = float(self.t[0]), float(self.t[-1])
        if (tq < lo).any() or (tq > hi).any():
            raise ValueError(f"tq must lie in [{lo}, {hi}]")
        return tq

    def __repr__(self) -> str:
        return (f"ShootingResult(success={self.success}, status={self.status}, message={self.message!r}, "
                f"iterations={self.iterations}, residual_norm={self.residual_norm:.3e}, m={self.t.numel()})")


def solve(prob: BVP, t, x_guess, *, integrator: str | None = None, steps: int | None = None,
          rtol: float | None = None, atol: float | None = None, newton: str = "deuflhard",
          jacobian: str = "autograd", jacobian_rtol: float | str | None = "auto",
          tol: float | None = None, max_iter: int = 100,
          continuation: Sequence[dict] | None = None, verbose: bool = False,
          newton_options: dict | None = None, max_growth: float | None = 20.0,
          refine: bool = True, spectral: str = "auto") -> ShootingResult:
    """Solve the TPBVP ``prob`` by multiple shooting on the grid ``t`` from ``x_guess``.

    The m − 1 initial value problems y_k(t_k) = s_k are integrated at once as one batch, and the
    shooting equations g_a(s_1) = 0, y_k(t_{k+1}; s_k) − s_{k+1} = 0, g_b(s_m) = 0 (report eqs.
    3.5–3.11) are solved for s by a damped Newton iteration with a structured factorisation of
    the block-bidiagonal Newton matrix.

    Parameters
    ----------
    prob : BVP
        The problem: right-hand side and boundary conditions.
    t : Tensor or array_like, shape (m,)
        Shooting points a = t_1 < … < t_m = b.
    x_guess : Tensor or array_like, shape (m, n)
        Initial approximation of the state at the shooting points.  The solve runs on its device
        and in its dtype (``t`` follows it).
    integrator : str, optional
        A name from ``shootlab.INTEGRATORS``; default ``auto`` (rtol 1e−10, atol 1e−12): adaptive
        ``dop853`` on every interval, the A-stable Rosenbrock ``ros4`` only on the intervals whose
        local Jacobian has a decaying mode too fast for an explicit scheme over the interval
        (:class:`shootlab.bvp.integrators.Auto`).
    steps : int, optional
        Steps per interval of a fixed-step integrator (default 4); for an adaptive one a bound
        |h| ≤ (interval length) / steps on its steps (default none: the tolerance chooses them).
    rtol, atol : float, optional
        Tolerances of an adaptive integrator (default its own).
    newton : str, optional
        ``deuflhard`` (default: affine-covariant damped Newton, the Jacobian kept while the
        iteration contracts), ``armijo`` (line search on ½|F|² with a fixed Jacobian, report §3.3),
        ``appendix_a`` (the report's appendix-A baseline), ``trust_region`` (Powell's dogleg) or
        ``undamped``; see :mod:`shootlab.bvp.newton`.
    jacobian : {"autograd", "reverse", "fd", "frozen"}, optional
        Interval Jacobians by forward-mode differentiation through the integrator (default), by
        reverse sweeps through its graph, by the report's finite differences (eq. 3.7), or, for
        a fixed-step scheme, from the linearisation at each interval's start, R(hJ)^steps with R
        the scheme's stability function (a quasi-Newton; :mod:`shootlab.bvp.shooting`).
    jacobian_rtol : float, "auto" or None, optional
        Adaptive integrators: the relative tolerance of the passes that form the interval
        Jacobians (with the first residual).  ``"auto"`` (default): √rtol with ``deuflhard``,
        rtol with the others; None: rtol.  The residuals keep rtol, so the solution is the same
        (:class:`~shootlab.bvp.shooting.ShootingSystem`).
    tol : float, optional
        Stop when max|F| ≤ tol·(1 + max|s|); default 1e−10, or the adaptive integrator's rtol
        when that is larger (F carries the integrator's error, about rtol·|y|, so a tighter test
        cannot be met).
    max_iter : int, optional
        Newton iterations (default 100), over all continuation stages.
    continuation : sequence of dict, optional
        Stage settings from loose to tight (module docstring), each stage warm-started from the
        previous one's solution (report ch. 5).
    verbose : bool, optional
        Print one line per Newton iteration.
    newton_options : dict, optional
        Options of the Newton strategy (e.g. ``min_damping``, ``stall`` for ``deuflhard``).
    max_growth : float or None, optional
        Fail at once (status 5) when an interval's growth exponent κ₊·h, estimated from the
        local Jacobians at the guess, exceeds this (default 20: an IVP amplified by e^20 ≈ 5e8
        leaves the matching conditions about half of float64's digits).  None disables it.
    refine : bool, optional
        Adaptive integrators only (default True): cut interval k of ``t`` into
        ⌈ρ_k h_k / REFINE_LIMIT⌉ equal pieces, ρ_k = max|λ(∂f/∂x)| at its two ends, up to
        REFINE_BUDGET / n² intervals in all, the guess interpolated linearly.  All intervals run
        as one batch, so shorter intervals are faster and grow less.  False: exactly the points
        of ``t``.
    spectral : {"auto", "exact", "bound"}, optional
        How ``refine``, ``max_growth`` and ``auto`` find max|λ| and max Re λ of the local
        Jacobians (:func:`~shootlab.bvp.shooting.spectral_bounds`): eigenvalues, or upper bounds
        from batched matrix products (a finer grid or a refusal, never a coarser grid);
        ``"auto"``: exact on the CPU, bounds on an accelerator.

    Returns
    -------
    ShootingResult
        ``success``, ``status`` (:class:`~shootlab.bvp.newton.Status`), ``message``; ``t`` and
        ``x`` (m, n) at the points of ``t``; ``sol(tq)`` the solution between them; the
        iterations, Jacobian evaluations, residual norm, per-iteration ``history`` and
        per-stage ``stages``.

    Raises
    ------
    ValueError
        Bad input (shapes, a grid that is not increasing, the wrong number of boundary
        conditions, a guess that is not finite, an unknown option), before any work.  Numerical
        failure (overflow, a singular Newton matrix, a stalled line search, ``max_iter``) does not
        raise: it returns ``success=False`` with a message naming the interval and iteration.
    """
    x_guess = as_tensor(x_guess, name="x_guess")
    t = as_tensor(t, dtype=x_guess.dtype, device=x_guess.device, name="t")
    check_problem(prob, t, x_guess)
    if spectral not in SPECTRAL_METHODS:
        raise ValueError(f"spectral must be one of {', '.join(SPECTRAL_METHODS)}, got {spectral!r}")
    base = dict(integrator=integrator, steps=steps, rtol=rtol, atol=atol, tol=tol, max_iter=max_iter,
                newton=newton, newton_options=newton_options or {}, jacobian=jacobian,
                jacobian_rtol=jacobian_rtol)
    stages = [base] if not continuation else [_stage(base, c, i) for i, c in enumerate(continuation)]
    scale = float(x_guess.abs().max())
    systems = [_build(prob, t, st, scale, spectral) for st in stages]      # validate every stage before any work

    start = time.perf_counter()
    user_t, user_pos = t, None
    spectrum = None             # (max|λ|, max Re λ) at the points of t: for refine and max_growth
    if refine and all(getattr(system.integrator, "adaptive", False) for system, _ in systems):
        spectrum = local_spectrum(prob, t, x_guess, spectral)
        fine = refined_grid(prob, t, x_guess, rates=spectrum[0])
        if fine is not None:
            t, x_guess, user_pos = fine
            systems = [_build(prob, t, st, scale, spectral) for st in stages]
    if max_growth is not None:
        if spectrum is None:
            growth = interval_growth(prob, t, x_guess, spectral)
        else:                   # eq. 5.6 from the same Jacobians; a cut interval's pieces share its κ₊
            kappa = spectrum[1].clamp_min(0.0)
            kappa = torch.maximum(kappa[:-1], kappa[1:])
            if user_pos is not None:
                kappa = torch.repeat_interleave(kappa, user_pos.diff())
            growth = kappa * (t[1:] - t[:-1])
        k = int(growth.argmax())
        if float(growth[k]) > max_growth:
            return ShootingResult(
                success=False, status=INTERVALS_TOO_LONG, t=user_t,
                x=(x_guess if user_pos is None else x_guess[user_pos]).detach().clone(), iterations=0,
                jacobian_evaluations=0, residual_norm=float("inf"), history=[], seconds=time.perf_counter() - start,
                message=(f"shooting intervals too long for the problem: on interval {k} [t = {float(t[k]):.6g}, "
                         f"{float(t[k + 1]):.6g}] the local Jacobian at the guess grows like e^{float(growth[k]):.0f} "
                         f"(κ₊·h > {max_growth:g}); use more shooting points (shootlab.suggest_shooting_points) "
                         f"or pass max_growth=None to try anyway"),
                points=t.numel(), _system=systems[0][0], _x_all=x_guess.detach().clone())
    s, history, records = x_guess.detach().clone(), [], []
    iters = jevals = 0
    out = NewtonOutcome(s=s, status=CONVERGED, message="")
    for i, (st, (system, strategy)) in enumerate(zip(stages, systems)):
        if verbose and len(stages) > 1:
            print(f"-- stage {i + 1}/{len(stages)}: {_describe(st)}", flush=True)
        strategy.verbose = verbose
        out = strategy.run(system, s)
        iters += out.iterations
        jevals += out.jacobian_evaluations
        history += [dict(row, stage=i) for row in out.history]
        records.append(dict(settings=_describe(st), success=out.status == CONVERGED, status=out.status,
                            message=out.message, iterations=out.iterations,
                            jacobian_evaluations=out.jacobian_evaluations, residual_norm=out.residual_norm))
        s = out.s
        if out.status != CONVERGED:
            if len(stages) > 1:
                out.message = f"stage {i + 1}/{len(stages)} ({_describe(st)}): {out.message}"
            break
    s_all = s
    if user_pos is not None:
        s = s[user_pos]
    if out.status == CONVERGED and len(stages) > 1:        # the count of the whole continuation
        out.message = (f"converged: |F|_inf = {out.residual_norm:.3e} after {iters} iterations in {len(stages)} "
                       f"stages ({' + '.join(str(r['iterations']) for r in records)})")
    return ShootingResult(success=out.status == CONVERGED, status=out.status, message=out.message, t=user_t,
                          x=s, iterations=iters, jacobian_evaluations=jevals,
                          residual_norm=out.residual_norm, history=history, stages=records,
                          seconds=time.perf_counter() - start, points=t.numel(),
                          _system=systems[len(records) - 1][0], _x_all=s_all)


def solve_together(probs: Sequence[BVP], t, guesses: Sequence[Tensor], *, integrator: str | None = None,
                   steps: int | None = None, rtol: float | None = None, atol: float | None = None,
                   newton: str = "undamped", jacobian: str = "autograd", jacobian_rtol: float | str | None = "auto",
                   tol: float | None = None, max_iter: int = 1, newton_options: dict | None = None,
                   continuation: Sequence[dict] | None = None, max_growth: float | None = None,
                   refine: bool = True, verbose: bool = False, final_step: bool = False,
                   stall: int | None = None) -> tuple[list[ShootingResult | None], Callable[[Tensor], list[Tensor]]] | None:
    """:func:`solve` with ``newton="undamped"`` for several TPBVPs that share their right-hand side
    (one vector field, each its own boundary conditions and guess) on one grid with a fixed-step
    integrator: each takes the full steps x_{k+1} = x_k − J(x_k)⁻¹F(x_k) until its own test
    holds or ``max_iter`` (:class:`~shootlab.bvp.newton.UndampedNewton`'s), and every integration is
    one batch of all their intervals (:class:`~shootlab.bvp.shooting.ShootingBatch`); ``probs[0].rhs``
    is integrated for all.  For a fixed number of full steps from good guesses (the diagnosis's
    one-step re-estimates).  Returns each problem's result — None for one that could not be
    integrated or whose Newton matrix was singular (solve it alone: :func:`solve` shortens a step
    that cannot be integrated and reports a failure) — and a function of times on the
    integrator's step grid giving each solution there from one pass; None where the problems
    cannot be solved together at all (another strategy or integrator, continuation, a growth
    check).  ``refine`` and ``verbose`` are accepted and unused (no grid refinement for fixed-step
    schemes, no progress lines).  ``final_step``: a problem whose test holds takes one more full
    step, with the Jacobian of the pass that integrated its last residual — its ``x`` is then
    accurate to about the square of that residual with exact interval Jacobians, to that residual
    times the contraction rate with ``jacobian="frozen"`` (``residual_norm`` is the residual before
    the step), and depends smoothly on the problem's data, as a forward-difference Jacobian of the
    solutions needs.  ``stall`` = k: a problem whose max|F| has not fallen below half its least
    value before its last k iterations stops there, unconverged (STEP_TOO_SMALL;
    :func:`~shootlab.bvp.newton.stalled`, the test of ``deuflhard``'s ``stall``)."""
    if newton != "undamped" or continuation or max_growth is not None or len(probs) != len(guesses) or not probs:
        return None
    guesses = [as_tensor(g, name="x_guess") for g in guesses]
    t = as_tensor(t, dtype=guesses[0].dtype, device=guesses[0].device, name="t")
    for prob, guess in zip(probs, guesses):
        check_problem(prob, t, guess)
    st = dict(integrator=integrator, steps=steps, rtol=rtol, atol=atol, tol=tol, max_iter=max_iter, newton=newton,
              newton_options=newton_options or {}, jacobian=jacobian, jacobian_rtol=jacobian_rtol)
    first, strategy = _build(probs[0], t, st, max(float(g.abs().max()) for g in guesses))
    if getattr(first.integrator, "adaptive", False):
        return None
    systems = [first] + [ShootingSystem(p, t, first.integrator, jacobian=jacobian) for p in probs[1:]]
    batch = ShootingBatch(systems)
    clock = time.perf_counter()
    s = torch.cat(guesses).detach().clone()
    Fs = batch.residuals(s, jacobian=True)
    iterations = [0] * len(probs)
    history: list[list[dict]] = [[] for _ in probs]

    def record(i: int, F: Tensor, step: float) -> None:
        history[i].append(dict(iteration=iterations[i], residual_norm=float(F.abs().max()), step=step,
                               jacobian="fresh", elapsed=time.perf_counter() - clock, stage=0))
    for i, F in enumerate(Fs):
        if F is not None:
            record(i, F, 0.0)
    stuck: set[int] = set()
    for k in range(strategy.max_iter):
        stuck |= {i for i in range(len(probs)) if stalled([row["residual_norm"] for row in history[i]], stall)}
        moving = [i for i, (F, si) in enumerate(zip(Fs, batch.split(s)))
                  if F is not None and not strategy.converged(F, si) and i not in stuck]
        if not moving:
            break
        ds = torch.zeros_like(s)
        for i, d in batch.newton_steps(s, Fs, moving).items():
            if d is None:
                Fs[i] = None
            else:
                batch.split(ds)[i].copy_(d)
        s = s + ds
        new = batch.residuals(s, jacobian=k + 1 < strategy.max_iter)
        Fs = [None if F is None else F_new for F, F_new in zip(Fs, new)]       # a failed one stays failed
        for i in moving:
            if Fs[i] is not None:
                iterations[i] += 1
                record(i, Fs[i], 1.0)
    if final_step:
        done = [i for i, (F, si) in enumerate(zip(Fs, batch.split(s))) if F is not None and strategy.converged(F, si)]
        for i, d in batch.newton_steps(s, Fs, done).items():
            if d is not None:
                batch.split(s)[i].add_(d)          # a view of s
    seconds = (time.perf_counter() - clock) / len(probs)
    results: list[ShootingResult | None] = []
    for i, (system, si, F) in enumerate(zip(systems, batch.split(s), Fs)):
        if F is None:
            results.append(None)
            continue
        done, norm = strategy.converged(F, si), float(F.abs().max())
        message = (f"converged: |F|_inf = {norm:.3e} after {iterations[i]} iterations" if done else
                   f"max|F| not halved in {stall} iterations (|F| = {norm:.3e}): the iteration makes "
                   f"no progress" if i in stuck else
                   f"{strategy.max_iter} undamped Newton step(s) taken, |F| = {norm:.3e}")
        status = CONVERGED if done else STEP_TOO_SMALL if i in stuck else MAX_ITER
        results.append(ShootingResult(
            success=done, status=status, message=message, t=t, x=si, iterations=iterations[i],
            jacobian_evaluations=iterations[i], residual_norm=norm, history=history[i],
            stages=[dict(settings=_describe(st), success=done, status=status, message=message,
                         iterations=iterations[i], jacobian_evaluations=iterations[i], residual_norm=norm)],
            seconds=seconds, points=t.numel(), _system=system, _x_all=si))
    return results, (lambda tq: batch.dense(as_tensor(tq, dtype=t.dtype, device=t.device, name="tq"), s))


#: target max|λ|·h per shooting interval for ``refine`` (on the BVP test set the fastest grids
#: have max|λ|·h ≈ 0.5–10)
REFINE_LIMIT = 0.5
#: ``refine`` adds intervals up to (intervals)·n² ≤ REFINE_BUDGET (for n = 2: 4096 intervals)
REFINE_BUDGET = 2 ** 14


def refined_grid(prob: BVP, t: Tensor, x: Tensor, limit: float | None = None, budget: int | None = None,
                 rates: Tensor | None = None):
    """(t_fine, x_fine, positions of t in t_fine) for ``solve(..., refine=True)``, or None when
    no interval needs cutting (``solve``'s docstring).  ``rates``: max|λ(∂f/∂x)| at the points of
    t if already known (:func:`shootlab.bvp.shooting.local_spectrum`).  Vectorised: no loop over
    intervals."""
    limit = REFINE_LIMIT if limit is None else limit
    budget = REFINE_BUDGET if budget is None else budget
    m, n = x.shape
    cap = max(m - 1, budget // max(1, n * n))
    if cap <= m - 1:
        return None
    with torch.no_grad():
        lam = local_spectrum(prob, t, x)[0] if rates is None else rates
        rho = torch.maximum(lam[:-1], lam[1:])
        h = t[1:] - t[:-1]
        k = torch.ceil(rho * h / limit).clamp(1, cap)
        total = float(k.sum())
        if total <= m - 1:
            return None
        if total > cap:            # over budget: cut the pieces down in proportion
            k = torch.floor(k * (cap - (m - 1)) / total).clamp_min(0) + 1
        k = k.to(torch.long)
        if int(k.sum()) <= m - 1:
            return None
        idx = torch.repeat_interleave(torch.arange(m - 1, device=t.device), k)
        first = torch.cumsum(k, 0) - k
        frac = (torch.arange(idx.numel(), device=t.device) - first[idx]).to(t.dtype) / k[idx].to(t.dtype)
        t_f = torch.cat([t[idx] + frac * h[idx], t[-1:]])
        x_f = torch.cat([x[idx] + frac[:, None] * (x[idx + 1] - x[idx]), x[-1:]])
        pos = torch.cat([first, first.new_tensor([idx.numel()])])
    return t_f, x_f, pos


def _stage(base: dict, stage: dict, i: int) -> dict:
    if not isinstance(stage, dict):
        raise ValueError(f"continuation stage {i} must be a dict of settings, got {type(stage).__name__}")
    unknown = set(stage) - _STAGE_KEYS
    if unknown:
        raise ValueError(f"continuation stage {i}: unknown setting(s) {sorted(unknown)}; allowed: {sorted(_STAGE_KEYS)}")
    merged = dict(base)
    if "integrator" in stage:     # a new integrator does not inherit the previous one's tolerances
        merged.update(rtol=None, atol=None)
    merged.update(stage)
    return merged


def _build(prob: BVP, t: Tensor, st: dict, scale: float = 1.0, spectral: str = "auto"):
    name = st["integrator"] or DEFAULT_INTEGRATOR
    rtol, atol = st["rtol"], st["atol"]
    if st["integrator"] is None:
        rtol = DEFAULT_RTOL if rtol is None else rtol
        atol = DEFAULT_ATOL if atol is None else atol
    integ = get_integrator(name, steps=_steps(name, st), rtol=rtol, atol=atol)
    if hasattr(integ, "max_abs"):     # blow-up detection: far beyond any state of the guess
        integ.max_abs = BLOWUP_FACTOR * (1.0 + float(scale))
    if hasattr(integ, "spectral"):    # the auto integrator's stiffness test
        integ.spectral = spectral
    tol = st["tol"]
    if tol is None:
        tol = DEFAULT_TOL
        if rtol is not None and getattr(integ, "adaptive", False):
            tol = max(tol, float(rtol))
    strategy = get_newton(st["newton"], tol=tol, max_iter=st["max_iter"], **st["newton_options"])
    jacobian_rtol = st["jacobian_rtol"]
    if jacobian_rtol == "auto" and not strategy.loose_jacobian_ok:
        jacobian_rtol = None
    system = ShootingSystem(prob, t, integ, jacobian=st["jacobian"], jacobian_rtol=jacobian_rtol)
    return system, strategy


def _steps(name: str, st: dict) -> int:
    """The stage's ``steps``: given, or 4 for a fixed-step scheme and 1 (no bound) for an adaptive one."""
    if st["steps"] is not None:
        return int(st["steps"])
    scheme = INTEGRATORS.get(name)
    return 1 if scheme is not None and scheme.adaptive else 4


def _describe(st: dict) -> str:
    name = st["integrator"] or DEFAULT_INTEGRATOR
    parts = [name]
    scheme = INTEGRATORS.get(name)
    if scheme is not None and not scheme.adaptive:      # the fixed-step schemes: steps per interval
        parts.append(f"steps={_steps(name, st)}")
    if st["rtol"] is not None:
        parts.append(f"rtol={st['rtol']:g}")
    parts.append(f"newton={st['newton']}")
    return ", ".join(parts)
