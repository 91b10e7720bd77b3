"""Newton strategies for the shooting equations F(s) = 0, chosen by name (:data:`NEWTON`).

``deuflhard``   the default: error-oriented, affine-covariant damped Newton (Deuflhard's
                NLEQ-ERR) with bounds and a Jacobian kept while the iteration contracts
                (:class:`DeuflhardNewton`).
``armijo``      the globally convergent Newton of the report §3.3 (Press
                et al., *Numerical Recipes* 2nd ed. §9.7): minimise f = ½ FᵀF along the Newton
                direction with the Armijo rule f(s + λδ) ≤ f(s) + α λ ∇f·δ, α = 1e−4 (eq.
                3.17); λ = 1 first, then the minimiser of a quadratic (eq. 3.19) and later cubic
                models (eqs. 3.20–3.21), λ ≥ 0.1·λ_prev, with a floor λ_min
                (:func:`shootlab.bvp.step_length.armijo_search`).  Combined with the
                *fixed-Jacobian strategy* (eq. 3.22): after a full step the factorised Jacobian is
                kept as long as ‖F_{j+1}‖ ≤ ρ ‖F_j‖.  A kept Jacobian is given the full step only:
                if that fails the Armijo test, the Jacobian is refreshed at once rather than
                backtracking along a stale direction (on the 20-element mixture such a search
                took most of the iteration's residual evaluations).  An integration failure at
                a trial point (overflow) is not fatal: the step is shortened, which MUSN could
                not do.
``appendix_a``  the baseline of the report's appendix A (MUSN, Mattheij &
                Staarink): a step is accepted when the Newton *correction* ξ = −J⁻¹F does not
                grow, ‖ξ_{j+1}‖ ≤ ‖ξ_j‖; otherwise the damping λ is halved, down to 0.007
                ("necessary damping factor too small").  Integration failures are fatal, as
                they were in MUSN (there they crashed the program).
``undamped``    plain full Newton steps (:class:`UndampedNewton`).

Every strategy returns a :class:`NewtonOutcome` whose ``status`` is a :class:`Status`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Callable

import torch
from torch import Tensor

from .linalg import SingularJacobianError
from .shooting import IntegrationFailure, ShootingSystem
from .step_length import armijo_search, step_to_boundary

class Status(IntEnum):
    """How a solve ended (as in scipy's ``solve_bvp``, 0 is success): the one status of every
    estimate — the shooting runs' Newton and the output-error fit
    (:mod:`shootlab.estimation.output_error`) — written to ``estimate.json`` as its number; ``.meaning``
    says what it is (the README's table is this one)."""

    CONVERGED = 0
    MAX_ITER = 1
    INTEGRATION_FAILED = 2
    SINGULAR = 3
    STEP_TOO_SMALL = 4
    INTERVALS_TOO_LONG = 5

    @property
    def meaning(self) -> str:
        return _MEANING[self]


_MEANING = {
    Status.CONVERGED: "converged",
    Status.MAX_ITER: "iteration limit reached: max_iter Newton iterations (output error: max_evaluations free runs)",
    Status.INTEGRATION_FAILED: ("integration failed (overflow / NaN / step-size underflow) on a named interval "
                                "(output error: the free run at the final parameters)"),
    Status.SINGULAR: "singular Newton matrix",
    Status.STEP_TOO_SMALL: ("damping below its floor (deuflhard: min_damping, 1e-8 by default; appendix_a: 0.007), "
                            "line search stalled (armijo), trust radius below its floor or 10 steps each lowering |DF| by less "
                            "than 0.1 % (trust_region), or, with deuflhard's stall=k (off by default), k "
                            "iterations without halving max|F|"),
    Status.INTERVALS_TOO_LONG: ("intervals too long: the local Jacobian at the guess grows like e^(κ₊h) with κ₊h > "
                                "max_growth (20) on some interval — use more shooting points"),
}
CONVERGED, MAX_ITER, INTEGRATION_FAILED, SINGULAR, STEP_TOO_SMALL, INTERVALS_TOO_LONG = Status


@dataclass
class NewtonOutcome:
    s: Tensor
    status: int
    message: str
    iterations: int = 0
    jacobian_evaluations: int = 0
    residual_norm: float = math.inf
    history: list[dict] = field(default_factory=list)


class NewtonStrategy:
    """Base class: ``run(system, s0)`` drives F(s) to zero and never raises on numerical failure."""

    name = "base"
    #: ``solve(jacobian_rtol="auto")`` loosens the Jacobians' tolerance only for a strategy that
    #: takes an inexact first residual and accepts a trial point by its F (:class:`DeuflhardNewton`)
    loose_jacobian_ok = False
    after_step_hint = ""      # appended to a singular-matrix message after an accepted step

    def __init__(self, tol: float = 1e-10, max_iter: int = 100, verbose: bool = False,
                 log: Callable[[str], None] = print, **options):
        if options:
            raise ValueError(f"unknown option(s) for newton={self.name!r}: {sorted(options)}")
        if not tol > 0:
            raise ValueError(f"tol must be positive, got {tol}")
        if int(max_iter) < 1:
            raise ValueError(f"max_iter must be at least 1, got {max_iter}")
        self.tol, self.max_iter, self.verbose, self.log = tol, int(max_iter), verbose, log

    def run(self, system: ShootingSystem, s0: Tensor) -> NewtonOutcome:
        out = NewtonOutcome(s=s0, status=MAX_ITER, message="")
        self._t0 = time.perf_counter()
        if self.verbose:
            self.log(f"{'iter':>4} {'|F|_inf':>11} {'step':>9} {'jacobian':>9} {'time [s]':>9}")
        try:
            self._iterate(system, s0, out)
        except IntegrationFailure as exc:
            out.status, out.message = INTEGRATION_FAILED, f"integration failed at iteration {out.iterations}: {exc}"
        except SingularJacobianError as exc:
            out.status, out.message = SINGULAR, f"iteration {out.iterations}: {exc}"
            if out.iterations > 1 and self.after_step_hint:
                out.message += self.after_step_hint
        return out

    def _record(self, out: NewtonOutcome, norm: float, step: float, fresh: bool) -> None:
        row = dict(iteration=out.iterations, residual_norm=norm, step=step,
                   jacobian="fresh" if fresh else "reused", elapsed=time.perf_counter() - self._t0)
        out.history.append(row)
        out.residual_norm = norm
        if self.verbose:
            self.log(f"{row['iteration']:4d} {norm:11.3e} {step:9.2e} {row['jacobian']:>9} {row['elapsed']:9.2f}")

    def _first_residual(self, system, s: Tensor, inexact: bool = False) -> tuple[Tensor, bool]:
        """(F(s0), whether it is exact): the first iteration needs the Jacobian at s0, integrated
        with F where the system can (``prefetches_jacobian``).  That pass may run at the Jacobian's
        looser tolerance (:class:`~shootlab.bvp.shooting.ShootingSystem`'s ``jacobian_rtol``); its F is
        then integrated again at the tolerance — unless the strategy takes an ``inexact`` first
        residual and it does not already pass the convergence test."""
        if not getattr(system, "prefetches_jacobian", False):
            return system.residual(s).F, True
        res = system.residual(s, jacobian=True)
        if res.exact or (inexact and not self.converged(res.F, s)):
            return res.F, res.exact
        return system.residual(s).F, True          # the Jacobian at s is kept for linearize

    def _out_of_iterations(self, out: NewtonOutcome, s: Tensor, note: str = "") -> None:
        """Ends the run at s with MAX_ITER; ``note`` is appended to the message."""
        out.s, out.status = s, MAX_ITER
        out.message = f"maximum number of iterations ({self.max_iter}) reached, |F| = {out.residual_norm:.3e}{note}"

    def _stalled(self, out: NewtonOutcome, s: Tensor, floor: str, why: str) -> None:
        """Ends the run at s with STEP_TOO_SMALL: the step length fell below its ``floor`` (what it
        is, said in words), which means ``why``."""
        out.s, out.status = s, STEP_TOO_SMALL
        out.message = (f"{floor} at iteration {out.iterations} (|F| = {out.residual_norm:.3e}): {why}; try a "
                       f"better initial guess, more shooting points or tolerance continuation")

    def converged(self, F: Tensor, s: Tensor) -> bool:
        """max|F| ≤ tol·(1 + max|s|) (also for a correction in place of F)."""
        return float(F.abs().max()) <= self.tol * (1.0 + float(s.abs().max()))

    def _iterate(self, system: ShootingSystem, s: Tensor, out: NewtonOutcome) -> None:
        raise NotImplementedError


class ArmijoNewton(NewtonStrategy):
    """Line-search Newton with the fixed-Jacobian strategy (module docstring)."""

    name = "armijo"
    #: on the noisy mass–spring–damper from m = b = k = 50 a full step that lowers |F| throws the
    #: parameters to −2400, where the Newton matrix is singular; appendix_a converges
    after_step_hint = ("; the matrix became singular at the point the last accepted step reached, which "
                       "happens when a step that lowers |F| throws the iterate far off (the parameters): "
                       "try the default newton='deuflhard' (or 'appendix_a'), whose acceptance test is "
                       "affine invariant, or a closer start")

    def __init__(self, rho: float = 0.25, alpha: float = 1e-4, min_step: float = 1e-8, **kw):
        super().__init__(**kw)
        self.rho, self.alpha, self.min_step = rho, alpha, min_step

    def _iterate(self, system, s, out):
        F = self._first_residual(system, s)[0]
        self._record(out, float(F.abs().max()), 0.0, True)
        fac, keep = None, False
        overflows, last_overflow = 0, None
        while not self.converged(F, s):
            if out.iterations >= self.max_iter:
                return self._out_of_iterations(out, s, (
                    f"; diverging: the Newton step overflowed and was cut back in {overflows} of {out.iterations} "
                    f"iterations (last: {last_overflow}) — use tolerance continuation, a better guess or more "
                    f"shooting points") if overflows else "")
            out.iterations += 1
            fresh = fac is None or not keep
            if fresh:
                fac = system.linearize(s)
                out.jacobian_evaluations += 1
            found = armijo_search(system, s, F, system.newton_step(fac, F), self.alpha, self.min_step,
                                  full_only=not fresh)
            if found is None and not fresh:        # stale Jacobian: refresh once and retry
                fac, fresh = system.linearize(s), True
                out.jacobian_evaluations += 1
                found = armijo_search(system, s, F, system.newton_step(fac, F), self.alpha, self.min_step)
            if found is None:
                return self._stalled(out, s, f"step length below the floor {self.min_step:g}",
                                     "the iteration is stuck near a local minimum of |F|^2 or the Newton "
                                     "direction is wrong")
            s_new, F_new, _, lam, failure = found
            if failure is not None:
                overflows, last_overflow = overflows + 1, failure
            keep = lam == 1.0 and float(F_new.norm()) <= self.rho * float(F.norm())  # eq. 3.22
            s, F = s_new, F_new
            out.s = s
            self._record(out, float(F.abs().max()), lam, fresh)
        out.s, out.status = s, CONVERGED
        out.message = f"converged: |F|_inf = {out.residual_norm:.3e} after {out.iterations} iterations"


class AppendixANewton(NewtonStrategy):
    """The report's appendix-A iteration (MUSN): monotonicity of the Newton correction.

    Our reading of the (garbled) appendix: ξ_j = −J(x_k)⁻¹ F(x_j); accept x_{j+1} = x_j + λ ξ_j
    when ‖ξ_{j+1}‖ ≤ ‖ξ_j‖; after an acceptance λ is doubled (at most 1) when the previous
    step was accepted with the same λ; the Jacobian is re-evaluated at the new point unless
    a full step shrank the correction below 0.6‖ξ_j‖; after a rejection λ is halved and the
    trial corrections use the Jacobian of the base point; the iteration fails when
    λ < 0.007 and stops when ‖ξ‖ falls below tol.
    """

    name = "appendix_a"

    def __init__(self, min_damping: float = 0.007, contraction: float = 0.6, **kw):
        super().__init__(**kw)
        self.min_damping, self.contraction = min_damping, contraction

    def _iterate(self, system, s, out):
        F = self._first_residual(system, s)[0]
        fac = system.linearize(s)
        out.jacobian_evaluations += 1
        xi = system.newton_step(fac, F)
        self._record(out, float(F.abs().max()), 0.0, True)
        lam, lam_prev, rejected, jac = 1.0, 1.0, False, True
        while not self.converged(xi, s):        # ‖ξ‖ below tol
            if out.iterations >= self.max_iter:
                return self._out_of_iterations(out, s)
            out.iterations += 1
            s_new = s + lam * xi
            F_new = system.residual(s_new).F            # overflow here ends the run, as in MUSN
            fac_new = fac
            if jac:
                try:
                    fac_new = system.linearize(s_new)
                    out.jacobian_evaluations += 1
                except SingularJacobianError:            # no correction at the trial point: reject
                    fac_new = None
            xi_new = system.newton_step(fac_new, F_new) if fac_new is not None else None
            if xi_new is not None and float(xi_new.norm()) <= float(xi.norm()):   # accept
                full = lam == 1.0
                shrink = float(xi_new.norm()) < self.contraction * float(xi.norm())
                s, F, fac = s_new, F_new, fac_new
                out.s = s
                lam_next = min(1.0, 2.0 * lam) if (lam == lam_prev and not rejected) else lam
                self._record(out, float(F.abs().max()), lam, jac)
                if not (full and shrink) and not jac:                   # re-evaluate J at the new point
                    fac = system.linearize(s)
                    out.jacobian_evaluations += 1
                    xi_new = system.newton_step(fac, F)
                jac = not (full and shrink)
                xi, lam_prev, lam, rejected = xi_new, lam, lam_next, False
            else:                                                       # reject: halve the damping
                lam_prev, lam, rejected = lam, 0.5 * lam, True
                jac = False                                             # trials use J(x_k), k = j
                if lam < self.min_damping:
                    out.s, out.status = s, STEP_TOO_SMALL
                    out.message = (f"necessary damping factor too small (λ = {lam:.4g} < {self.min_damping}) "
                                   f"at iteration {out.iterations}, |F| = {out.residual_norm:.3e}")
                    return
        out.s, out.status = s, CONVERGED
        out.message = f"converged: Newton correction below tol after {out.iterations} iterations"


class DeuflhardNewton(NewtonStrategy):
    """Error-oriented, affine-covariant damped Newton (Deuflhard, *Newton Methods for Nonlinear
    Problems*, 2004, §3.3: the global Newton method NLEQ-ERR), the default.

    With the Newton correction Δx_k = −J(x_k)⁻¹F(x_k), a trial x_{k+1} = x_k + λΔx_k is tested
    with the *simplified correction* Δ̄x_{k+1} = −J(x_k)⁻¹F(x_{k+1}) (same factorisation, one
    residual and one back-substitution).  Everything below is measured in the scaled norm
    ‖v‖ = rms(v_i / d_i), d the magnitude of each unknown (:func:`_typical_magnitude`), so the
    iteration does not depend on the units of F (affine covariance) nor, through d, on those of x:

    * contraction       Θ_k = ‖Δ̄x_{k+1}‖ / ‖Δx_k‖;  accept when Θ_k ≤ 1 − λ/4
                        (restricted natural monotonicity test);
    * corrector         λ' = min(1, μ'_k),  μ'_k = ½‖Δx_k‖λ² / ‖Δ̄x_{k+1} − (1−λ)Δx_k‖
                        (an estimate of the Kantorovich quantity); a rejected λ is replaced by
                        min(μ'_k, λ/2), but not below λ/10 (μ' measured far out in a strongly
                        nonlinear region is far too pessimistic); a first trial λ that passes is
                        retried once as λ' when λ' ≥ 4λ;
    * predictor         λ_{k+1} = min(1, μ_{k+1}),
                        μ_{k+1} = ‖Δx_k‖‖Δ̄x_{k+1}‖ / (‖Δ̄x_{k+1} − Δx_{k+1}‖‖Δx_{k+1}‖) · λ_k;
    * bounds            a step is shortened to stay inside the problem's bounds (``BVP.lower``,
                        ``upper``; fraction to the boundary 0.99, as IPOPT's:
                        :func:`shootlab.bvp.step_length.step_to_boundary`);
    * back-off          if the Newton matrix is singular at an accepted point, the step is taken
                        again from its start with λ/4 (the test accepted a step into a region
                        where the model degenerates, e.g. a mass through 0);
    * kept Jacobian     after a full step that contracted well (Θ ≤ ρ), the Jacobian is kept (the
                        fixed-Jacobian strategy of the report §3.3, tested by contraction instead
                        of ‖F‖) and improved by Broyden's rank-1 updates in the error-oriented form
                        of Deuflhard's QNERR (§2.1.4, :class:`_Broyden`): the next correction is
                        Δx_{k+1} = Δ̄x_{k+1}/(1 − α_k), α_k = ⟨Δx_k, Δ̄x_{k+1}⟩/‖Δx_k‖², with no
                        new Jacobian and one back-substitution, superlinear where the plain
                        simplified correction converges linearly; if a kept Jacobian's step fails
                        the test, the Jacobian is refreshed at once;
    * looser Jacobians  the system may form its Jacobians at a looser tolerance than F
                        (``jacobian_rtol``): the first residual, from the same pass, makes Δx_0 an
                        inexact Newton step (every later F is integrated at the tolerance, and a
                        small Δx_0 is not taken as convergence);
    * convergence       max|F| ≤ tol·(1 + max|s|), s the last iterate a *full* step reached (or
                        x_0: damped steps toward a root at infinity, arctan(x) = 2, had grown
                        max|s| to 1e9 and passed the test with |F| = 0.43).  A trial point that
                        meets it is the solution whatever its Θ (its simplified correction is
                        not formed: one back-substitution fewer): there the corrections are at the
                        integrator's error level and Θ is noise (bvpT5, ε = 1e−4 on 8143 points:
                        a full step to |F| = 6.6e−9 ≤ 4.1e−8 rejected at Θ = 0.754, then damped
                        down to the floor).  Or: a full step whose simplified correction (or a
                        fresh Jacobian's correction) is below tol·(1 + max|s|), the same s (the
                        correction is then added: quadratic convergence makes the result
                        accurate to about its square) — unless F at the accepted point already
                        passes the first test: then it is the result as it stands (the
                        correction would cost one more integration of every interval).

    Unlike ``armijo``'s test on ½‖F‖², which a step that lowers ‖F‖ but throws the
    parameters far away passes, the monotonicity test measures the step in the unknowns and is
    invariant under F → AF, as IPOPT's filter on the (scaled) problem is in effect.  An
    integration failure at a trial point shortens λ by 10.

    Giving up: λ below ``min_damping`` (1e-8 by default: Deuflhard's NLEQ codes take 1e-4 for
    highly nonlinear problems, 1e-8 for extremely nonlinear ones), and, with ``stall`` = k, an
    iteration that has not brought max|F| below half its least value before the last k iterations
    — the norm of the convergence test; off by default.  For callers that have something better to
    do with a failure than wait for ``max_iter`` (the diagnosis's candidate re-estimates:
    ``shootlab.diagnosis.estimators.GIVE_UP``).
    """

    name = "deuflhard"
    loose_jacobian_ok = True

    def __init__(self, rho: float = 0.25, lambda0: float = 1.0, min_damping: float = 1e-8,
                 stall: int | None = None, **kw):
        super().__init__(**kw)
        if not 0.0 < lambda0 <= 1.0:
            raise ValueError(f"lambda0 must lie in (0, 1], got {lambda0}")
        if not 0.0 < min_damping <= 1.0:
            raise ValueError(f"min_damping must lie in (0, 1], got {min_damping}")
        if stall is not None and int(stall) < 1:
            raise ValueError(f"stall must be a positive number of iterations or None, got {stall}")
        self.rho, self.lambda0, self.min_damping = rho, lambda0, min_damping
        self.stall = None if stall is None else int(stall)

    def _stalls(self, out: NewtonOutcome) -> bool:
        return stalled([row["residual_norm"] for row in out.history], self.stall)

    def _iterate(self, system, s, out):
        # F(x_0) may come from the Jacobian's looser pass: an inexact Newton step (class docstring)
        F, exact = self._first_residual(system, s, inexact=True)
        self._record(out, float(F.abs().max()), 0.0, True)
        self._ref = s                   # the scale of the convergence test: the last x_k a full step reached
        fac, keep, lam = None, False, self.lambda0
        prev = None                     # (‖Δx_k‖, Δ̄x_{k+1}, λ_k, d) of the last accepted step
        back = None                     # (x_k, F_k, factorisation, Δx_k, λ_k) of the last fresh step
        dbar = broyden = None
        self._overflows = 0
        while not self.converged(F, self._ref):
            if out.iterations >= self.max_iter:
                return self._out_of_iterations(out, s, (
                    f"; a trial step overflowed and was shortened {self._overflows} times — use tolerance "
                    f"continuation, a better guess or more shooting points") if self._overflows else "")
            out.iterations += 1
            step = None
            fresh = fac is None or not keep
            if not fresh:               # kept Jacobian: the quasi-Newton correction is the next step
                step = self._correct(system, s, broyden.step(dbar), fac, 1.0, full_only=True, update=broyden)
                fresh = step is None    # it failed the test: refresh the Jacobian at once
            if fresh:
                try:
                    fac = system.linearize(s)
                except SingularJacobianError:
                    # the accepted step reached a point where the Newton matrix is singular (a mass
                    # through 0): it went too far; take it again from where it started, 4x shorter
                    if back is None or back[4] / 4.0 < self.min_damping:
                        raise
                    s, F, fac, dx, lam_back = back
                    step = self._correct(system, s, dx, fac, lam_back / 4.0, grow=False)
                    if step is None:
                        raise
                    back = (s, F, fac, dx, step[3])
                else:
                    out.jacobian_evaluations += 1
                    dx = system.newton_step(fac, F)
                    if exact and self.converged(dx, self._ref):  # the test's scale, as for F
                        s = s + dx                               # converged in the correction
                        F = system.residual(s).F
                        out.s = s
                        self._record(out, float(F.abs().max()), 1.0, True)
                        break
                    if prev is not None:                         # predictor
                        ndx_prev, dbar_prev, lam_prev, d = prev
                        den = _rms(dbar_prev - dx, d) * _rms(dx, d)
                        mu = ndx_prev * _rms(dbar_prev, d) / den * lam_prev if den > 0 else 1.0
                        lam = max(min(1.0, mu), self.min_damping)
                    step = self._correct(system, s, dx, fac, lam)
                    if step is None:
                        self._stalled(out, s, f"damping factor below {self.min_damping:g}",
                                      "the Newton path leaves the region where the linearisation holds")
                        if getattr(system, "loose_jacobian", False):
                            out.message += ", or jacobian_rtol=None (Jacobians at the residual's tolerance)"
                        return
                    back = (s, F, fac, dx, step[3])
                broyden = _Broyden(dx, step[6])      # the updates start from the fresh correction, in its scaling d
            s, F, dbar, lam, theta, ndx, d = step
            if dbar is None:                # the trial point met the tolerance (_correct)
                out.s = s
                self._record(out, float(F.abs().max()), lam, fresh)
                break
            exact = True
            if lam == 1.0:
                self._ref = s
            keep = lam == 1.0 and theta <= self.rho and broyden.room()
            prev = (ndx, dbar, lam, d)
            out.s = s
            self._record(out, float(F.abs().max()), lam, fresh)
            if (lam == 1.0 and self.converged(dbar, self._ref)
                    and not self.converged(F, self._ref)):      # (if F already passes: done, one integration fewer)
                s = s + broyden.step(dbar)                       # converged in the correction
                F = system.residual(s).F
                out.s = s
                out.residual_norm = float(F.abs().max())
                break
            if self._stalls(out):
                return self._stalled(out, s, f"max|F| not halved in {self.stall} iterations",
                                     "the iteration makes no progress")
        out.s, out.status = s, CONVERGED
        out.message = f"converged: |F|_inf = {out.residual_norm:.3e} after {out.iterations} iterations"

    def _correct(self, system, s: Tensor, dx: Tensor, fac, lam: float, full_only: bool = False,
                 grow: bool = True, update: _Broyden | None = None):
        """The damping loop along dx (corrector, class docstring): the accepted
        (s_new, F_new, Δ̄x, λ, Θ, ‖Δx‖, d), or None when λ falls below its floor (with
        ``full_only``: when the full step fails).  ``grow=False``: λ is never raised.
        ``update``: the kept Jacobian's rank-1 updates, applied to the simplified correction."""
        d = _typical_magnitude(s, dx)
        ndx = _rms(dx, d)
        reduced = False
        inside = step_to_boundary(getattr(system, "prob", None), s, dx)
        if inside < lam:                          # the bounds of the unknowns cut the step
            if full_only:
                return None
            lam, reduced = inside, True
        while lam >= self.min_damping:
            s_new = s + lam * dx
            try:
                F_new = system.residual(s_new).F
            except IntegrationFailure:            # overflow at the trial point: shorten the step
                self._overflows += 1
                if full_only:
                    return None
                lam *= 0.1
                continue
            if self.converged(F_new, self._ref):  # F meets the tolerance: the solution, whatever Θ
                return s_new, F_new, None, lam, 0.0, ndx, d          # (no simplified correction needed)
            dbar = system.newton_step(fac, F_new)
            if update is not None:
                dbar = update.solve(dbar)
            ndbar = _rms(dbar, d)
            if not math.isfinite(ndbar):
                if full_only:
                    return None
                lam *= 0.1
                continue
            theta = ndbar / ndx
            den = _rms(dbar - (1.0 - lam) * dx, d)
            mu = 0.5 * ndx * lam * lam / den if den > 0 else math.inf
            if theta > 1.0 - lam / 4.0:           # restricted natural monotonicity test fails
                if full_only:
                    return None
                lam, reduced = max(min(mu, 0.5 * lam), 0.1 * lam), True
                continue
            lam_new = min(1.0, mu)
            if lam_new >= 4.0 * lam and not reduced and not full_only and grow:   # the first trial was too timid
                lam, reduced = lam_new, True
                continue
            return s_new, F_new, dbar, lam, theta, ndx, d
        return None


class _Broyden:
    """Broyden's "good" rank-1 updates of a kept Jacobian J₀ in the error-oriented form of
    Deuflhard's QNERR (*Newton Methods for Nonlinear Problems*, 2004, §2.1.4), in the scaled inner
    product ⟨u, v⟩ = Σ u_i v_i / d_i² of the strategy.  With the secant update
    J_{k+1} = J_k + F(x_{k+1}) Δx_kᵀ/‖Δx_k‖², Sherman–Morrison gives

        J_{k+1}⁻¹ = (I + Δx_{k+1} Δx_kᵀ/‖Δx_k‖²) J_k⁻¹,   Δx_{k+1} = Δ̄x_{k+1}/(1 − α_k),

    Δ̄x_{k+1} = −J_k⁻¹F(x_{k+1}) and α_k = ⟨Δx_k, Δ̄x_{k+1}⟩/‖Δx_k‖²: only the corrections are
    stored (at most :attr:`limit`), and J₀'s factorisation serves every step."""

    limit = 20

    def __init__(self, dx0: Tensor, d: Tensor):
        self.steps, self.w = [dx0], 1.0 / (d * d)

    def _dot(self, u: Tensor, v: Tensor) -> Tensor:
        return (u * v * self.w).sum()

    def solve(self, v: Tensor) -> Tensor:
        """−J_k⁻¹F from v = −J₀⁻¹F: the updates of the steps taken so far, oldest first."""
        for old, new in zip(self.steps[:-1], self.steps[1:]):
            v = v + new * (self._dot(old, v) / self._dot(old, old))
        return v

    def step(self, dbar: Tensor) -> Tensor:
        """The quasi-Newton correction Δx_{k+1} from Δ̄x_{k+1} (:meth:`solve`'s), recorded."""
        last = self.steps[-1]
        alpha = float(self._dot(last, dbar) / self._dot(last, last))
        dx = dbar / (1.0 - alpha) if alpha < 0.5 else dbar    # |α| ≤ Θ < ½ while it contracts
        self.steps.append(dx)
        return dx

    def room(self) -> bool:
        return len(self.steps) < self.limit


def _typical_magnitude(s: Tensor, dx: Tensor) -> Tensor:
    """d_i: the scale of state component i, its largest magnitude over the shooting points at the
    iterate and at the full Newton point (NLEQ's max(|x_k|, |x_{k+1}|) per component), floored at
    1e-6 of the largest where a component is near 0.  An elementwise scale does not converge on the
    Euler stage of the report's confined compression, where this one does."""
    d = torch.maximum(s.abs().amax(0), (s + dx).abs().amax(0))
    top = float(d.max())
    return d.clamp_min(1e-6 * top if top > 0 else 1.0)


def stalled(norms: list[float], k: int | None) -> bool:
    """Whether max|F| (``norms``, one per residual) stayed above half its least value before the
    last ``k`` iterations through all of them (never with ``k`` None)."""
    return k is not None and len(norms) > k and min(norms[-k:]) > 0.5 * min(norms[:-k])


def _rms(v: Tensor, d: Tensor) -> float:
    """The scaled norm ‖v‖ = rms(v_i / d_i) of the Deuflhard strategy."""
    return float((v / d).pow(2).mean().sqrt())


class UndampedNewton(NewtonStrategy):
    """Plain Newton: the full step x_{k+1} = x_k − J(x_k)⁻¹F(x_k), with no acceptance test (a
    step whose trial point cannot be integrated is shortened by 10 until it can).  For a fixed
    small number of steps from a good start, e.g. the linearised re-estimation of the diagnosis
    (``max_iter=1``: exact for a model linear in the new parameters)."""

    name = "undamped"

    def _iterate(self, system, s, out):
        F = self._first_residual(system, s)[0]
        self._record(out, float(F.abs().max()), 0.0, True)
        while not self.converged(F, s):
            if out.iterations >= self.max_iter:
                out.s, out.status = s, MAX_ITER
                out.message = f"{self.max_iter} undamped Newton step(s) taken, |F| = {out.residual_norm:.3e}"
                return
            out.iterations += 1
            fac = system.linearize(s)
            out.jacobian_evaluations += 1
            dx, lam = system.newton_step(fac, F), 1.0
            while True:
                try:
                    F_new = system.residual(s + lam * dx).F
                    if bool(torch.isfinite(F_new).all()):
                        break
                except IntegrationFailure:
                    pass
                lam *= 0.1
                if lam < 1e-12:
                    raise IntegrationFailure("the Newton step cannot be integrated even shortened to 1e-12",
                                             -1, math.nan, math.nan)
            s, F = s + lam * dx, F_new
            out.s = s
            self._record(out, float(F.abs().max()), lam, True)
        out.s, out.status = s, CONVERGED
        out.message = f"converged: |F|_inf = {out.residual_norm:.3e} after {out.iterations} iterations"


#: the strategies by name (``trust_region``: its own module adds it, the package imports it)
NEWTON = {cls.name: cls for cls in (DeuflhardNewton, ArmijoNewton, AppendixANewton, UndampedNewton)}


def get_newton(name: str | NewtonStrategy, **options) -> NewtonStrategy:
    """The strategy ``name`` of :data:`NEWTON` with ``options`` (or ``name`` itself if it is one)."""
    if isinstance(name, NewtonStrategy):
        return name
    try:
        return NEWTON[name](**options)
    except KeyError:
        raise ValueError(f"unknown newton strategy {name!r}; choose one of {sorted(NEWTON)}") from None
