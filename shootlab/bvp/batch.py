"""Many TPBVPs of one structure solved together: ``shootlab.solve_batch``.

B problems that share their structure — a family x' = f(t, x, θ), g_a(x(a), θ) = 0,
g_b(x(b), θ) = 0 with one parameter vector θ_b per problem (:class:`ParametricBVP`: a stiffness
sweep, a parameter scan), or a list of :class:`~shootlab.BVP` with one right-hand side and their
own boundary conditions — on one grid t with one fixed-step integrator.  Every integration is one
batch of the B·(m − 1) intervals (θ rides along as constant states, θ' = 0), every Newton matrix
one batched structured factorisation (:func:`shootlab.bvp.linalg.factorize_batch`), and each problem
keeps its own damping, convergence test and status:

    fam = ParametricBVP(rhs, bc_a, bc_b, params)          # params (B, q)
    results = shootlab.solve_batch(fam, t, guess)          # one ShootingResult per problem

The Newton iteration is the error-oriented damped Newton of
:class:`~shootlab.bvp.newton.DeuflhardNewton` (Deuflhard 2004, §3.3) in its basic form, per problem:
the correction Δx_k = −J(x_k)⁻¹F(x_k); the trial x_k + λΔx_k is accepted when its simplified
correction Δ̄x_{k+1} = −J(x_k)⁻¹F(x_k + λΔx_k) passes the restricted monotonicity test
Θ = ‖Δ̄x_{k+1}‖/‖Δx_k‖ ≤ 1 − λ/4 (or F there already meets the tolerance); otherwise
λ ← max(min(μ, λ/2), λ/10), μ = ½‖Δx_k‖λ²/‖Δ̄x_{k+1} − (1 − λ)Δx_k‖, and an integration that
overflows cuts λ by 10.  Norms are the scaled root mean squares of that strategy.  Every trial
point is integrated with its interval Jacobians (forward sensitivities, one pass), which the
next iteration uses where the trial is accepted; a fresh Jacobian every iteration.  A problem
stops at max|F| ≤ tol·(1 + max|s|) (converged), at a singular Newton matrix, when λ falls below
``min_damping`` or after ``max_iter`` iterations — the others go on.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import Tensor

from .integrators import get_integrator
from .linalg import factorize_batch
from .newton import CONVERGED, INTEGRATION_FAILED, MAX_ITER, SINGULAR, STEP_TOO_SMALL
from .problem import BVP, as_tensor, check_grid, check_problem
from .shooting import ShootingSystem, _reverse_jacobian
from .solver import BLOWUP_FACTOR, DEFAULT_TOL, ShootingResult
from .tangents import NotTransformable

__all__ = ["ParametricBVP", "solve_batch"]


@dataclass
class ParametricBVP:
    """B TPBVPs of one family, x' = f(t, x, θ), g_a(x(a), θ) = 0, g_b(x(b), θ) = 0, one θ per problem.

    rhs(t, x, theta)   t (R,), x (R, n), theta (R, q) → (R, n); rows independent (as
                       :class:`~shootlab.BVP`'s rhs, with each row's parameters beside it)
    bc_a(x_a, theta)   x_a (B', n), theta (B', q) → (B', p): the boundary conditions of B' problems
    bc_b(x_b, theta)   → (B', n − p)
    params             (B, q) (or (B,) for q = 1): θ of every problem
    """

    rhs: Callable[[Tensor, Tensor, Tensor], Tensor]
    bc_a: Callable[[Tensor, Tensor], Tensor]
    bc_b: Callable[[Tensor, Tensor], Tensor]
    params: Tensor
    name: str = "family"

    def __post_init__(self):
        self.params = as_tensor(self.params, name="params")
        if self.params.ndim == 1:
            self.params = self.params[:, None]
        if self.params.ndim != 2 or self.params.shape[0] < 1:
            raise ValueError(f"params must be (B, q) or (B,), got shape {tuple(self.params.shape)}")
        if not torch.isfinite(self.params).all():
            i = int((~torch.isfinite(self.params)).any(-1).nonzero()[0])
            raise ValueError(f"params of problem {i} are not finite: {self.params[i].tolist()}")

    def __len__(self) -> int:
        return self.params.shape[0]

    def member(self, i: int) -> BVP:
        """Problem i as a plain :class:`~shootlab.BVP` (for :func:`shootlab.solve`)."""
        theta = self.params[i]

        def rhs(t: Tensor, x: Tensor) -> Tensor:
            return self.rhs(t, x, theta.to(x).expand(*x.shape[:-1], theta.numel()))

        return BVP(rhs, lambda xa: self.bc_a(xa[None], theta.to(xa)[None])[0],
                   lambda xb: self.bc_b(xb[None], theta.to(xb)[None])[0], name=f"{self.name}[{i}]")


class _Family:
    """The batch's right-hand side and boundary conditions on members' rows (internal)."""

    def __init__(self, problems, device, dtype):
        if isinstance(problems, ParametricBVP):
            self.fam, self.B = problems, len(problems)
            self.theta = problems.params.to(device=device, dtype=dtype)
            self.q = self.theta.shape[1]
            f = problems.rhs
            n_of = self

            def rhs(t: Tensor, xa: Tensor) -> Tensor:         # [x, θ]' = [f(t, x, θ), 0]
                n = n_of.n
                x, th = xa[..., :n], xa[..., n:]
                return torch.cat([f(t, x, th), torch.zeros_like(th)], -1)
            self.rhs = rhs
            self.members = [None] * self.B
        else:
            probs = list(problems)
            if not probs or not all(isinstance(p, BVP) for p in probs):
                raise ValueError("problems must be a ParametricBVP or a non-empty list of shootlab.BVP")
            if any(p.rhs is not probs[0].rhs for p in probs):
                raise ValueError("a list of problems must share one right-hand side object (the same vector field, "
                                 "each its own boundary conditions); give a family whose parameters differ as a "
                                 "ParametricBVP(rhs(t, x, theta), bc_a, bc_b, params)")
            self.fam, self.B, self.q, self.theta = None, len(probs), 0, None
            self.rhs = probs[0].rhs
            self.members = probs
        self.n = 0

    def member(self, i: int) -> BVP:
        return self.fam.member(i) if self.fam is not None else self.members[i]

    def bcs(self, idx: Tensor, xa: Tensor, xb: Tensor) -> tuple[Tensor, Tensor]:
        """g_a, g_b (b, p), (b, n − p) of the members idx (b,) at their ends xa, xb (b, n)."""
        if self.fam is not None:
            th = self.theta[idx]
            return (self.fam.bc_a(xa, th).reshape(xa.shape[0], -1), self.fam.bc_b(xb, th).reshape(xb.shape[0], -1))
        ga = [self.members[i].bc_a(xa[j]).reshape(-1) for j, i in enumerate(idx.tolist())]
        gb = [self.members[i].bc_b(xb[j]).reshape(-1) for j, i in enumerate(idx.tolist())]
        return torch.stack(ga), torch.stack(gb)

    def bc_jacobians(self, idx: Tensor, xa: Tensor, xb: Tensor) -> tuple[Tensor, Tensor]:
        """∂g_a/∂x_a (b, p, n) and ∂g_b/∂x_b (b, n − p, n): one reverse sweep per boundary row,
        all members at once (their conditions are independent)."""
        with torch.enable_grad():
            xa, xb = xa.detach().requires_grad_(True), xb.detach().requires_grad_(True)
            ga, gb = self.bcs(idx, xa, xb)
            out = []
            for g, x in ((ga, xa), (gb, xb)):
                rows = []
                for i in range(g.shape[1]):
                    d = torch.autograd.grad(g[:, i].sum(), x, retain_graph=True, allow_unused=True)[0] \
                        if g.requires_grad else None
                    rows.append(torch.zeros_like(x) if d is None else d)
                out.append(torch.stack(rows, 1) if rows else x.new_zeros(x.shape[0], 0, x.shape[1]))
        return out[0].detach(), out[1].detach()


class _MemberSystem:
    """``ShootingResult.sol`` of one member: its :class:`~shootlab.bvp.shooting.ShootingSystem`, made
    when first asked for."""

    def __init__(self, family: _Family, i: int, t: Tensor, integrator):
        self.family, self.i, self.t, self.integrator, self._system = family, i, t, integrator, None

    def dense(self, tq: Tensor, s: Tensor, grid: bool = False) -> Tensor:
        if self._system is None:
            self._system = ShootingSystem(self.family.member(self.i), self.t, self.integrator)
        return self._system.dense(tq, s, grid)


def _guesses(guesses, B: int, m: int, device, dtype) -> Tensor:
    if isinstance(guesses, (list, tuple)):
        if len(guesses) != B:
            raise ValueError(f"{len(guesses)} guesses for {B} problems")
        g = torch.stack([as_tensor(x, dtype=dtype, device=device, name=f"guesses[{i}]") for i, x in enumerate(guesses)])
    else:
        g = as_tensor(guesses, dtype=dtype, device=device, name="guesses")
        if g.ndim == 2:
            g = g.expand(B, *g.shape)
    if g.ndim != 3 or g.shape[0] != B or g.shape[1] != m:
        raise ValueError(f"guesses must be (B, m, n) = ({B}, {m}, n), one (m, n) for all, or a list of B (m, n); "
                         f"got shape {tuple(g.shape)}")
    if not torch.isfinite(g).all():
        i = int((~torch.isfinite(g)).flatten(1).any(-1).nonzero()[0])
        raise ValueError(f"guesses[{i}] contains NaN or inf")
    return g.detach().clone()


def solve_batch(problems: ParametricBVP | Sequence[BVP], t, guesses, *, integrator: str = "rk4",
                steps: int = 4, tol: float | None = None, max_iter: int = 100, min_damping: float = 1e-8,
                device: str | torch.device | None = None, verbose: bool = False) -> list[ShootingResult]:
    """Solve B TPBVPs of one structure together on one grid (module docstring).

    Parameters
    ----------
    problems : ParametricBVP or sequence of BVP
        A family with one parameter vector per problem, or B :class:`~shootlab.BVP` sharing one
        ``rhs`` object (each its own boundary conditions).
    t : Tensor or array_like, shape (m,)
        Shooting points, the same for every problem.
    guesses : Tensor, shape (B, m, n) or (m, n), or list of B tensors (m, n)
        Initial approximations; one (m, n) guess serves every problem.
    integrator : str, optional
        A fixed-step scheme of ``shootlab.INTEGRATORS`` (default ``rk4``); the adaptive schemes
        are refused (every row of a batch would take the steps of the slowest).
    steps : int, optional
        Steps per interval (default 4).
    tol : float, optional
        Per problem: stop at max|F| ≤ tol·(1 + max|s|) (default 1e−10).
    max_iter : int, optional
        Newton iterations per problem (default 100).
    min_damping : float, optional
        A problem stops (status 4) when its damping factor λ falls below this (default 1e−8).
    device : str or torch.device, optional
        Where to solve (``"cpu"``, ``"cuda"``, ``"auto"``); default the guesses' device, else
        the CPU.  The data are moved there once.
    verbose : bool, optional
        Print one line per Newton iteration of the batch.

    Returns
    -------
    list of ShootingResult
        One per problem, in order, each with its own ``status`` and ``message``; ``seconds`` is
        the batch's wall time divided by B.

    Raises
    ------
    ValueError
        Bad input (shapes, an adaptive integrator, tol ≤ 0, max_iter < 1, min_damping outside
        (0, 1]).  A problem that fails numerically does not stop the others.
    """
    from .device import resolve_device

    g0 = guesses[0] if isinstance(guesses, (list, tuple)) and guesses else guesses
    dev = resolve_device(device) if device is not None else (g0.device if isinstance(g0, Tensor) else torch.device("cpu"))
    dtype = g0.dtype if isinstance(g0, Tensor) and g0.is_floating_point() else torch.float64
    fam = _Family(problems, dev, dtype)
    t = as_tensor(t, dtype=dtype, device=dev, name="t").reshape(-1)
    check_grid(t)
    m, B = t.numel(), fam.B
    s = _guesses(guesses, B, m, dev, dtype)
    fam.n = s.shape[-1]
    check_problem(fam.member(0), t, s[0])          # shapes, bc counts, a finite rhs at the first guess
    integ = get_integrator(integrator, steps=steps)
    if getattr(integ, "adaptive", False):
        raise ValueError(f"solve_batch needs a fixed-step integrator, got the adaptive {integrator!r} "
                         "(rk4, euler, midpoint, radau3, …)")
    if hasattr(integ, "max_abs"):
        integ.max_abs = BLOWUP_FACTOR * (1.0 + float(s.abs().max()))
    tol = DEFAULT_TOL if tol is None else float(tol)
    if not tol > 0 or int(max_iter) < 1 or not 0 < min_damping <= 1:
        raise ValueError(f"need tol > 0, max_iter >= 1 and 0 < min_damping <= 1; got {tol}, {max_iter}, {min_damping}")
    return _Newton(fam, t, integ, tol, int(max_iter), float(min_damping), verbose).run(s)


class _Newton:
    """The batched damped Newton of :func:`solve_batch` (module docstring)."""

    def __init__(self, fam: _Family, t: Tensor, integ, tol: float, max_iter: int, min_damping: float, verbose: bool):
        self.fam, self.t, self.integ = fam, t, integ
        self.tol, self.max_iter, self.min_damping, self.verbose = tol, max_iter, min_damping, verbose
        self.t0, self.t1 = t[:-1], t[1:]
        self._mode = None             # "forward" (sensitivities) or "reverse" (sweeps): decided once

    # -- one batch of integrations ------------------------------------------------------------
    def integrate(self, idx: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor, str | None]:
        """For the members idx (b,) at s (b, m, n): F (b, N), the interval Jacobians
        Y (b, m−1, n, n), whether each member's intervals and F are finite (b,), and the first
        failure's reason."""
        fam, n = self.fam, self.fam.n
        b, m = s.shape[0], s.shape[1]
        s0 = s[:, :-1].reshape(b * (m - 1), n)
        if fam.q:
            s0 = torch.cat([s0, fam.theta[idx].repeat_interleave(m - 1, 0)], -1)
        t0, t1 = self.t0.repeat(b), self.t1.repeat(b)
        Y = None
        if self._mode != "reverse":
            try:
                res = self.integ.integrate(fam.rhs, t0, t1, s0, sensitivity=True)
                self._mode = "forward"
                Y = res.S[:, :n, :n]
            except NotTransformable:
                self._mode = "reverse"
        if Y is None:
            with torch.enable_grad():
                x = s0.detach().clone().requires_grad_(True)
                res = self.integ.integrate(fam.rhs, t0, t1, x)
                Y = _reverse_jacobian(res.y, x)[:, :n, :n].detach()
        ends = res.y[:, :n].detach().reshape(b, m - 1, n)
        ok = ~res.failed.reshape(b, m - 1).any(-1)
        with torch.no_grad():
            ga, gb = fam.bcs(idx, s[:, 0], s[:, -1])
            F = torch.cat([ga, (ends - s[:, 1:]).reshape(b, -1), gb], -1)
        Y = Y.reshape(b, m - 1, n, n)
        ok = ok & torch.isfinite(F).all(-1) & torch.isfinite(Y).flatten(1).all(-1)
        return F, Y, ok, res.reason

    def converged(self, F: Tensor, s: Tensor) -> Tensor:
        return F.abs().amax(-1) <= self.tol * (1.0 + s.abs().flatten(1).amax(-1))

    def solve(self, fac, F: Tensor) -> Tensor:
        """−J⁻¹F (b, m, n) with the batched factorisation."""
        p, n, m = fac.p, fac.n, fac.m
        return -fac.solve(F[:, :p], F[:, p:p + (m - 1) * n].reshape(-1, m - 1, n), F[:, p + (m - 1) * n:])

    # -- the iteration ------------------------------------------------------------------------
    def run(self, s: Tensor) -> list[ShootingResult]:
        fam, B = self.fam, self.fam.B
        clock = time.perf_counter()
        dev = s.device
        every = torch.arange(B, device=dev)
        status = torch.full((B,), -1, dtype=torch.int64, device=dev)
        iters = torch.zeros(B, dtype=torch.int64, device=dev)
        lam_next = torch.ones(B, dtype=s.dtype, device=dev)
        F, Y, ok, reason = self.integrate(every, s)
        status = torch.where(ok, status, torch.full_like(status, INTEGRATION_FAILED))
        F = torch.where(ok[:, None], F, torch.full_like(F, math.inf))
        history: list[list[dict]] = [[] for _ in range(B)]
        notes: dict[int, str] = {}
        failed0 = (~ok).nonzero().flatten().tolist()
        for i in failed0:
            notes[i] = f"integration failed at the initial guess: {reason or 'non-finite value (overflow)'}"
        steps_taken = torch.zeros(B, dtype=s.dtype, device=dev)
        for it in range(self.max_iter + 1):
            undecided = status < 0
            status = torch.where(undecided & self.converged(F, s), torch.full_like(status, CONVERGED), status)
            norms = F.abs().amax(-1).tolist()                 # one transfer per iteration (progress, history)
            active_list, lams = undecided.tolist(), steps_taken.tolist()
            elapsed = time.perf_counter() - clock
            for i in range(B):
                if active_list[i]:
                    history[i].append(dict(iteration=it, residual_norm=norms[i], step=lams[i] if it else 0.0,
                                           jacobian="fresh", elapsed=elapsed, stage=0))
            active = status < 0
            if self.verbose:
                print(f"{it:4d} undecided {int(active.sum()):6d} of {B}  max|F| {max(norms):11.3e}  {elapsed:8.2f} s",
                      flush=True)
            if it == self.max_iter:
                status = torch.where(active, torch.full_like(status, MAX_ITER), status)
                break
            idx = active.nonzero().flatten()
            if idx.numel() == 0:
                break
            sa, Fa, Ya = s[idx], F[idx], Y[idx]
            Ba, Bb = fam.bc_jacobians(idx, sa[:, 0], sa[:, -1])
            fac, singular = factorize_batch(Ya, Ba, Bb)
            dx = self.solve(fac, Fa)
            dx = torch.where(singular[:, None, None], torch.zeros_like(dx), dx)
            d = torch.maximum(sa.abs().amax(1), (sa + dx).abs().amax(1))          # NLEQ scaling per component
            d = torch.maximum(d, 1e-6 * d.amax(-1, keepdim=True)).clamp_min(1e-300)
            ndx = _rms(dx, d)
            lam = lam_next[idx].clone()
            pending = ~singular
            new_status = torch.where(singular, torch.full_like(idx, SINGULAR), torch.full_like(idx, -1))
            s_new, F_new, Y_new, lam_used = sa.clone(), Fa.clone(), Ya.clone(), torch.zeros_like(lam)
            while True:
                rows = pending.nonzero().flatten()
                if rows.numel() == 0:
                    break
                s_try = sa[rows] + lam[rows, None, None] * dx[rows]
                F_try, Y_try, fine, _ = self.integrate(idx[rows], s_try)
                F_safe = torch.where(fine[:, None], F_try, torch.zeros_like(F_try))
                sub = fac if rows.numel() == idx.numel() else _select(fac, rows)
                dbar = self.solve(sub, F_safe)
                lr, ndx_r, d_r = lam[rows], ndx[rows], d[rows]
                theta = _rms(dbar, d_r) / ndx_r.clamp_min(1e-300)
                done = fine & (self.converged(F_try, s_try) | (theta <= 1.0 - lr / 4.0))
                take = rows[done]
                s_new[take], F_new[take], Y_new[take], lam_used[take] = s_try[done], F_try[done], Y_try[done], lr[done]
                den = _rms(dbar - (1.0 - lr)[:, None, None] * dx[rows], d_r)
                mu = torch.where(den > 0, 0.5 * ndx_r * lr * lr / den.clamp_min(1e-300), torch.full_like(den, math.inf))
                shorter = torch.where(fine, torch.maximum(torch.minimum(mu, 0.5 * lr), 0.1 * lr), 0.1 * lr)
                lam[rows] = torch.where(done, lr, shorter)
                stuck = ~done & (lam[rows] < self.min_damping)
                new_status[rows[stuck]] = STEP_TOO_SMALL
                pending[rows] = ~done & ~stuck
            moved = new_status < 0
            s[idx], F[idx], Y[idx] = s_new, F_new, Y_new
            status[idx] = new_status
            iters[idx] += moved.to(iters.dtype)
            steps_taken[idx] = lam_used
            lam_next[idx] = torch.where(lam_used >= 1.0, torch.ones_like(lam_used), (10.0 * lam_used).clamp(max=1.0))
            for j in (~moved).nonzero().flatten().tolist():
                i, k = int(idx[j]), it + 1
                norm = norms[i]
                notes[i] = (f"iteration {k}: singular Newton matrix" if int(new_status[j]) == SINGULAR else
                            f"damping factor below {self.min_damping:g} at iteration {k} (|F| = {norm:.3e}): the "
                            f"Newton path leaves the region where the linearisation holds; try a better initial "
                            f"guess, more shooting points or tolerance continuation")
        seconds = (time.perf_counter() - clock) / B
        return self._results(s, F, status, iters, history, notes, seconds)

    def _results(self, s, F, status, iters, history, notes, seconds) -> list[ShootingResult]:
        status_l, iters_l = status.tolist(), iters.tolist()
        norms = F.abs().amax(-1).tolist()
        out = []
        for i in range(self.fam.B):
            st, k, norm = status_l[i], iters_l[i], norms[i]
            if st == CONVERGED:
                message = f"converged: |F|_inf = {norm:.3e} after {k} iterations"
            elif st == MAX_ITER:
                message = f"maximum number of iterations ({self.max_iter}) reached, |F| = {norm:.3e}"
            else:
                message = notes.get(i, "failed")
            out.append(ShootingResult(
                success=st == CONVERGED, status=st, message=message, t=self.t, x=s[i], iterations=k,
                jacobian_evaluations=k + (st != INTEGRATION_FAILED), residual_norm=norm, history=history[i],
                stages=[dict(settings=f"{self.integ.name}, steps={self.integ.steps}, batched", success=st == CONVERGED,
                             status=st, message=message, iterations=k, residual_norm=norm)],
                seconds=seconds, points=self.t.numel(), _system=_MemberSystem(self.fam, i, self.t, self.integ),
                _x_all=s[i]))
        return out


def _rms(v: Tensor, d: Tensor) -> Tensor:
    """Per member the scaled norm rms(v_i / d_i) of v (b, m, n) with d (b, n)."""
    return (v / d[:, None, :]).pow(2).flatten(1).mean(-1).sqrt()


def _select(fac, rows: Tensor):
    """The batched factorisation of the members ``rows`` only."""
    from dataclasses import replace

    levels = [replace(lev, reflectors=lev.reflectors[rows], tau=lev.tau[rows], T12=lev.T12[rows], R=lev.R[rows],
                      scale=lev.scale[rows], wy=None if lev.wy is None else (lev.wy[0][rows], lev.wy[1][rows]))
              for lev in fac.levels]
    return replace(fac, levels=levels, scale=fac.scale[rows], lu=fac.lu[rows], pivots=fac.pivots[rows],
                   row_scale=fac.row_scale[rows])
