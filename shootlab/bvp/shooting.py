"""The multiple-shooting system F(s) = 0 and its Jacobian (report §3.2, eqs. 3.5–3.11).

Unknowns s_1 … s_m (the state at the shooting points t_1 < … < t_m); y_k(t) solves
the IVP x' = f(t, x), y_k(t_k) = s_k on [t_k, t_{k+1}].  The equations are

    g_a(s_1) = 0,    y_k(t_{k+1}; s_k) − s_{k+1} = 0  (k = 1 … m−1),    g_b(s_m) = 0.

All m − 1 IVPs are integrated at once as one batch.  The interval Jacobians
Y_k = ∂y_k(t_{k+1})/∂s_k are computed for all intervals together (``jacobian=``):

``"autograd"``  forward sensitivities of the discrete scheme (Bock's internal numerical
                differentiation, exact to rounding): S = ∂y/∂s_k is propagated with y through
                every stage of every step, all intervals as one batch, the stage derivatives by
                ``torch.func`` (:mod:`shootlab.bvp.tangents`); implicit schemes by the implicit
                function theorem at their converged stages (:mod:`shootlab.bvp.integrators`).
                A right-hand side that torch.func cannot transform falls back to ``"reverse"``,
                one that autograd cannot differentiate at all to ``"fd"`` — with a warning, once.
``"reverse"``   reverse sweeps through the recorded integrator graph, one per state component
                (the intervals are independent, so the sweep for component i gives row i of
                every Y_k at once), ``JACOBIAN_CHUNK`` cotangents per sweep.
``"fd"``        the report's one-sided finite differences (eq. 3.7), one batch of n + 1 copies.
``"frozen"``    the linearisation at the interval's start: Y_k = R(h J_k)^steps, R the fixed-step
                scheme's stability function at matrices and J_k = ∂f/∂x(t_k, s_k), one batched
                Jacobian per pass — exact for a linear system with a constant Jacobian, a
                quasi-Newton otherwise (linear convergence).  The same J_k forms the Newton
                matrices of an implicit scheme's steps in that pass (``Integrator.integrate``'s
                ``jacobian``): one Jacobian per interval in all.  For many cheap, mildly non-linear
                intervals whose exact sensitivities cost more than the iterations they save
                (the free run of :mod:`shootlab.estimation.free_run` on the samples of a record).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from shootlab.bvp.integrators.base import IntegrationResult, Integrator
from .tangents import batch_jacobian
from shootlab.bvp.integrators.base import all_finite
from .linalg import BlockFactorization, SingularJacobianError, factorize, factorize_batch, solve_initial_value
from .problem import BVP
from .spectrum import spectral_bounds
from .tangents import NotTransformable, known_untransformable, rhs_jacobian, untransformable


def interval_growth(prob: BVP, t: Tensor, x: Tensor, method: str = "auto") -> Tensor:
    """Estimated growth exponent κ₊·h_k of every interval from the local Jacobians ∂f/∂x at the
    shooting points (report eq. 5.6, for the growing modes): κ₊ = max Re λ(∂f/∂x), the larger of
    the values at the two ends of the interval.  e^{κ₊h} is the amplification an IVP suffers
    over the interval; beyond e^{36} ≈ 1/ε_machine the matching conditions carry no digits.
    ``method``: :func:`spectral_bounds`'s."""
    kappa = local_spectrum(prob, t, x, method)[1].clamp_min(0.0)
    return torch.maximum(kappa[:-1], kappa[1:]) * (t[1:] - t[:-1])


def local_spectrum(prob: BVP, t: Tensor, x: Tensor, method: str = "auto") -> tuple[Tensor, Tensor]:
    """(max|λ|, max Re λ) of the local Jacobian ∂f/∂x at every point (t (k,), x (k, n)), from one
    batched Jacobian (:func:`spectral_bounds` with ``method``).  Non-finite Jacobians count as 0
    (the IVPs report them)."""
    with torch.no_grad():
        J = batch_jacobian(prob.rhs, t, x.detach())
        finite = torch.isfinite(J).flatten(-2).all(-1)
        return spectral_bounds(torch.where(finite[:, None, None], J, torch.zeros_like(J)), method)


#: unit cotangents per batched reverse sweep in :func:`_reverse_jacobian` (bounds the extra
#: memory); 1: one sweep per row (benchmarks/engine.py times both)
JACOBIAN_CHUNK = 16


def _reverse_jacobian(y: Tensor, x: Tensor) -> Tensor:
    """J[k] = ∂y_k/∂x_k, shape (L, n, n), for rows y_k that depend only on their own x_k.

    Row i of every J[k] is one reverse sweep with the cotangent e_i on all k at once; the sweeps
    go ``JACOBIAN_CHUNK`` at a time through the recorded graph (``is_grads_batched``: vmap over
    the cotangents) — faster than one by one on the estimation problems, whose right-hand side
    holds a VJP of its own (``benchmarks/engine.py``).  Where vmap has no rule for an
    operation, one sweep per row."""
    L, n = x.shape
    if JACOBIAN_CHUNK > 1:
        eye = torch.eye(n, dtype=y.dtype, device=y.device)
        try:
            blocks = []
            for i in range(0, n, JACOBIAN_CHUNK):
                e = eye[i:i + JACOBIAN_CHUNK, None, :].expand(-1, L, n)
                g, = torch.autograd.grad(y, x, grad_outputs=e, is_grads_batched=True, retain_graph=True,
                                         allow_unused=True)
                blocks.append(torch.zeros_like(e) if g is None else g)
            return torch.cat(blocks, 0).transpose(0, 1)
        except RuntimeError:
            pass
    rows = [torch.autograd.grad(y[:, i].sum(), x, retain_graph=True, allow_unused=True)[0] for i in range(n)]
    return torch.stack([r if r is not None else torch.zeros_like(x) for r in rows], 1)


def _rows_jacobian(g, x: Tensor) -> Tensor:
    """∂g/∂x (k, n) of a boundary condition g at x (n,): one reverse sweep per row of g (cheaper
    than ``torch.autograd.functional.jacobian``'s set-up for the few rows of a boundary)."""
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        out = g(x).reshape(-1)
        if not out.requires_grad:           # g does not depend on x
            return x.new_zeros(out.numel(), x.numel())
        rows = [torch.autograd.grad(out[i], x, retain_graph=True, allow_unused=True)[0]
                for i in range(out.numel())]
    return torch.stack([torch.zeros_like(x) if r is None else r for r in rows]) if rows else x.new_zeros(0, x.numel())


def _failed_rows(res: IntegrationResult) -> Tensor:
    """Rows of an integration with sensitivities that failed or whose y or S is not finite."""
    return res.failed | ~all_finite(res.y) | ~all_finite(res.S.flatten(1))


def _has_linear_map(integrator: Integrator) -> bool:
    """Whether the scheme has a stability function at matrices (``jacobian="frozen"``)."""
    try:
        type(integrator).stability_matrix(torch.zeros(1, 1, dtype=torch.float64))
    except (NotImplementedError, AttributeError):
        return False
    return True


class IntegrationFailure(RuntimeError):
    """An IVP of the shooting system could not be integrated (overflow, NaN, step underflow)."""

    def __init__(self, reason: str, interval: int, t0: float, t1: float):
        super().__init__(f"{reason} on shooting interval {interval} [t = {t0:.6g}, {t1:.6g}]")
        self.reason, self.interval = reason, interval


@dataclass
class Residual:
    F: Tensor          # flat residual [g_a; matching; g_b]
    ends: Tensor       # (m−1, n) y_k(t_{k+1})
    exact: bool = True  # False: integrated with the Jacobian's looser tolerance (``jacobian_rtol``)


class ShootingSystem:
    """F(s), its structured Jacobian and the Newton solve for one problem, grid and integrator."""

    def __init__(self, prob: BVP, t: Tensor, integrator: Integrator, jacobian: str = "autograd",
                 jacobian_rtol: float | str | None = None):
        """``jacobian_rtol``: with an adaptive integrator, the relative tolerance of the passes that
        form the interval Jacobians by forward sensitivities (``"auto"``: the square root of the
        integrator's; None: its own).  A Jacobian accurate to δ only makes Newton's convergence
        linear with a rate of about δ — two corrections of a linear problem reach δ² = rtol — while
        the residual keeps the integrator's tolerance, so the solution does not change.  The first
        residual, integrated in the same pass as its Jacobian, is then an inexact Newton residual
        (``Residual.exact`` False).  The saving: from a straight-line guess every interval of a
        layer problem starts off its slow manifold, and a pass at rtol resolves that transient
        in all of them (bvpT3, ε = 1e−4: about a third fewer right-hand-side calls at √rtol)."""
        if jacobian not in ("autograd", "reverse", "fd", "frozen"):
            raise ValueError(f"jacobian must be 'autograd', 'reverse', 'fd' or 'frozen', got {jacobian!r}")
        if jacobian == "frozen" and not _has_linear_map(integrator):
            raise ValueError(f"jacobian='frozen' needs a fixed-step scheme with a stability function at matrices, "
                             f"not {getattr(integrator, 'name', integrator)!r}")
        self.prob, self.t, self.integrator, self.jacobian = prob, t, integrator, jacobian
        if jacobian_rtol is not None and not (jacobian_rtol == "auto" or float(jacobian_rtol) > 0):
            raise ValueError(f"jacobian_rtol must be a positive number, 'auto' or None, got {jacobian_rtol!r}")
        self._loose = (integrator if jacobian_rtol is None
                       else integrator.loosened(None if jacobian_rtol == "auto" else float(jacobian_rtol)))
        self.t0, self.t1 = t[:-1], t[1:]
        self.nfev = 0
        #: the step sizes an adaptive integrator proposed at the end of each interval in the last
        #: integration over the grid: the next one starts there (a Newton iteration's residuals
        #: then take one attempt per interval instead of two).
        #: The first integration tries every interval in one step: a grid is fine where the
        #: dynamics are fast (``solve``'s ``refine``), a rejected attempt is followed by the
        #: control's error-based step, and [HNW1]'s starting step takes 4–5 steps per interval to
        #: grow to a length the tolerance often allows at once
        self._h0: Tensor | None = (t[1:] - t[:-1]).abs()
        self._last = integrator           # the integrator (tolerance) that proposed _h0

    def _run(self, s0: Tensor, sensitivity: bool = False):
        """One integration of every interval of the grid from s0 (m−1, n), started from the
        step sizes of the last one; with ``sensitivity``, at the Jacobian's tolerance."""
        integ = self._loose if sensitivity else self.integrator
        h0 = self._h0
        if h0 is not None and integ is not self._last:      # step sizes scale as tol^(1/(q+1))
            h0 = h0 * (integ.tolerances()[0] / self._last.tolerances()[0]) ** (1.0 / (integ.error_order + 1))
        res = integ.integrate(self.prob.rhs, self.t0, self.t1, s0, sensitivity=sensitivity, h0=h0)
        self.nfev += res.nfev
        if res.h_next is not None:
            self._h0, self._last = res.h_next, integ
        return res

    # -- integration -------------------------------------------------------------------
    def _integrate(self, s0: Tensor, copies: int = 1) -> Tensor:
        """Integrate every interval from rows of s0 (copies·(m−1), n); failures raise."""
        if copies == 1:
            res = self._run(s0)
        else:                           # finite differences: every copy from its own start
            res = self.integrator.integrate(self.prob.rhs, self.t0.repeat(copies), self.t1.repeat(copies), s0)
            self.nfev += res.nfev
        y = res.y
        bad = res.failed | ~all_finite(y)
        if bad.any():
            k = int(bad.nonzero()[0]) % self.t0.numel()
            raise IntegrationFailure(res.reason or "non-finite value (overflow)", k,
                                     float(self.t0[k]), float(self.t1[k]))
        return y

    @property
    def loose_jacobian(self) -> bool:
        """Whether the Jacobians are formed at a looser tolerance than the residual."""
        return self._loose is not self.integrator

    #: ``residual(s, jacobian=True)`` is understood (Newton strategies ask for it where a
    #: Jacobian at s is about to be needed)
    prefetches_jacobian = True

    def residual(self, s: Tensor, jacobian: bool = False) -> Residual:
        """F(s).  ``jacobian=True``: with forward sensitivities (``jacobian="autograd"``), the
        interval Jacobians at s are integrated in the same pass (the step sizes are controlled
        on the states alone, so F is that of a plain integration to the tolerance; equal to it
        bit for bit with a fixed-step scheme) and kept for :meth:`linearize` at this s — one
        integration fewer per Newton iteration that needs a fresh Jacobian.  That pass runs at the
        Jacobian's tolerance (``jacobian_rtol``): F is then inexact (``Residual.exact`` False),
        and a plain ``residual(s)`` at the same s keeps the Jacobian for :meth:`linearize`."""
        if jacobian:
            self._pending = None
            ends = self._ends_with_jacobians(s)
            if ends is not None:
                return self._residual(s, ends, exact=not self.loose_jacobian)
        with torch.no_grad():
            ends = self._integrate(s[:-1])
        return self._residual(s, ends)

    def _ends_with_jacobians(self, s: Tensor) -> Tensor | None:
        s0 = s[:-1].detach()
        if self.jacobian == "frozen":
            res, Y = self.frozen_pass(self.t0, self.t1, s0)
            self.nfev += res.nfev
            if _failed_rows(res).any():
                return None
            self._pending = (s.detach().clone(), Y)
            return res.y
        if self.jacobian != "autograd" or self._autograd_mode(s0) != "autograd":
            return None
        try:
            res = self._run(s0, sensitivity=True)
        except NotTransformable:
            return None
        if _failed_rows(res).any():
            return None                    # the plain integration reports the failure
        self._pending = (s.detach().clone(), res.S)
        return res.y

    def _residual(self, s: Tensor, ends: Tensor, exact: bool = True) -> Residual:
        with torch.no_grad():
            F = torch.cat([self.prob.bc_a(s[0]).reshape(-1), (ends - s[1:]).reshape(-1),
                           self.prob.bc_b(s[-1]).reshape(-1)])
        return Residual(F, ends, exact)

    # -- Jacobian ----------------------------------------------------------------------
    def interval_jacobians(self, s: Tensor) -> Tensor:
        """Y_k = ∂y_k(t_{k+1})/∂s_k for all k at once, shape (m−1, n, n) (module docstring)."""
        pending, self._pending = getattr(self, "_pending", None), None
        if pending is not None and torch.equal(pending[0], s.detach()):
            return pending[1]
        s0 = s[:-1].detach()
        mode = self.jacobian
        if mode == "frozen":
            with torch.no_grad():
                J = rhs_jacobian(self.prob.rhs, self.t0, s0)[1]
                return self.integrator.linear_map(J, self.t0, self.t1)
        if mode == "autograd":
            mode = self._autograd_mode(s0)
        if mode == "autograd":
            try:
                return self._forward_jacobians(s0)
            except NotTransformable as exc:
                untransformable(self.prob.rhs, exc.__cause__ or exc, "reverse sweeps through the integrator")
                mode = "reverse"
        if mode == "reverse":
            return self._reverse_jacobians(s0)
        return self._fd_jacobians(s0)

    def frozen_pass(self, t0: Tensor, t1: Tensor, s0: Tensor) -> tuple[IntegrationResult, Tensor]:
        """The intervals [t0, t1] integrated from s0 (L, n) with the Jacobians J_k = ∂f/∂x(t0, s0)
        of one batched evaluation held for an implicit scheme's Newton matrices, and the
        ``"frozen"`` interval Jacobians R(h J_k)^steps (module docstring): (the integration with
        ``S`` set to them, Y (L, n, n))."""
        with torch.no_grad():
            J = rhs_jacobian(self.prob.rhs, t0, s0)[1]
            res = self.integrator.integrate(self.prob.rhs, t0, t1, s0, jacobian=J)
            Y = self.integrator.linear_map(J, t0, t1)
        res.S = Y
        return res, Y

    def _autograd_mode(self, s0: Tensor) -> str:
        """"autograd", or the fallback for a right-hand side that torch.func cannot transform
        ("reverse") or that autograd cannot differentiate at all ("fd", the user is told once);
        decided on one row, once per system."""
        if getattr(self, "_mode", None) is None:
            rhs, mode = self.prob.rhs, "autograd"
            try:
                with torch.enable_grad():
                    x = s0[:1].clone().requires_grad_(True)
                    differentiable = rhs(self.t0[:1], x).requires_grad
            except RuntimeError as exc:          # e.g. numpy on a tensor that requires grad
                differentiable, why = False, exc
            else:
                why = ValueError("rhs(t, x) does not depend on x through torch operations")
            if not differentiable:
                mode = "fd"
                untransformable(rhs, why, "finite differences (report eq. 3.7) for the interval Jacobians")
            elif known_untransformable(rhs) or not self.integrator.sensitivities:
                mode = "reverse"
            self._mode = mode
        return self._mode

    def _forward_jacobians(self, s0: Tensor) -> Tensor:
        """Forward sensitivities of the discrete scheme: Y_k = S(t_{k+1}) from S(t_k) = I,
        all intervals as one batch (``Integrator.integrate(..., sensitivity=True)``)."""
        res = self._run(s0, sensitivity=True)
        bad = _failed_rows(res)
        if bad.any():
            k = int(bad.nonzero()[0])
            raise IntegrationFailure(res.reason or "non-finite value (overflow)", k,
                                     float(self.t0[k]), float(self.t1[k]))
        return res.S

    def _reverse_jacobians(self, s0: Tensor) -> Tensor:
        """Reverse sweeps through the recorded integrator graph (:func:`_reverse_jacobian`)."""
        with torch.enable_grad():
            s0 = s0.clone().requires_grad_(True)
            y = self._integrate(s0)
            if y.grad_fn is None:
                raise ValueError("rhs(t, x) does not depend on x through torch operations: "
                                 "use jacobian='fd' for a non-differentiable rhs")
            return _reverse_jacobian(y, s0)

    def _fd_jacobians(self, s0: Tensor) -> Tensor:
        """Report eq. 3.7: one-sided differences, δ_j = √ε · max(|s_j|, 1), one batch of n+1 copies."""
        L, n = s0.shape
        with torch.no_grad():
            delta = torch.finfo(s0.dtype).eps ** 0.5 * s0.abs().clamp_min(1.0)       # (L, n)
            pert = s0.expand(n + 1, L, n).clone()
            pert[1:] += torch.eye(n, dtype=s0.dtype, device=s0.device)[:, None, :] * delta[None]
            y = self._integrate(pert.reshape((n + 1) * L, n), copies=n + 1).reshape(n + 1, L, n)
            return ((y[1:] - y[0]) / delta.T[:, :, None]).permute(1, 2, 0).contiguous()

    def bc_jacobians(self, s: Tensor) -> tuple[Tensor, Tensor]:
        """B_a = ∂g_a/∂s_1 (p, n) and B_b = ∂g_b/∂s_m (n − p, n)."""
        return _rows_jacobian(self.prob.bc_a, s[0]), _rows_jacobian(self.prob.bc_b, s[-1])

    def linearize(self, s: Tensor) -> BlockFactorization:
        """Factorised Newton matrix at s (may raise SingularJacobianError / IntegrationFailure)."""
        Y = self.interval_jacobians(s)
        Ba, Bb = self.bc_jacobians(s)
        return factorize(Y, Ba, Bb)

    def newton_step(self, fac: BlockFactorization, F: Tensor) -> Tensor:
        """δ = −J⁻¹ F, shape (m, n)."""
        p, n, m = fac.p, fac.n, fac.m
        r_match = F[p:p + (m - 1) * n].reshape(m - 1, n)
        return -fac.solve(F[:p], r_match, F[p + (m - 1) * n:])

    def dense(self, tq: Tensor, s: Tensor, grid: bool = False) -> Tensor:
        """Values at tq of the solution through the shooting points s, each integrated from the
        nearest shooting point at or before it; ``grid``: a fixed-step scheme's values on its own
        step grid (:meth:`~shootlab.bvp.integrators.Integrator.dense`)."""
        with torch.no_grad():
            return self.integrator.dense(self.prob.rhs, self.t, s, tq, grid)

    #: times per batch of an implicit scheme's values off its step grid (:meth:`sweep`)
    DENSE_ROWS = 1 << 14

    def sweep(self, tq: Tensor, s: Tensor) -> Tensor:
        """Values at the increasing times tq of the solution through the shooting points s: a
        fixed-step scheme's own step values where every time lies on its step grid (:meth:`dense`
        with ``grid``), else one pass over all intervals through the times of tq
        (:meth:`~shootlab.bvp.integrators.Integrator.sweep`).

        An implicit scheme off its step grid keeps :meth:`dense` (each time from its shooting
        point in the scheme's ``steps`` steps), in batches of :data:`DENSE_ROWS` times: it is
        used where the TPBVP's growing modes are stiff, and its values between steps depend on
        the step sizes taken there — the implicit midpoint rule's R(z) = (1 + z/2)/(1 − z/2) has
        its pole at z = 2 on the growing modes, so steps of the sample spacing amplify what its
        own steps keep bounded: on the 6-element mixture (2 midpoint steps per interval of 8
        samples, 1 % noise) J = 229 from a sweep through the samples against 1.24 from
        :meth:`dense`, to which the mixture's diagnosis is calibrated."""
        integ = self.integrator
        with torch.no_grad():
            if getattr(integ, "on_grid", None) is not None and integ.on_grid(self.t, tq) is not None:
                return integ.dense(self.prob.rhs, self.t, s, tq, grid=True)
            if getattr(integ, "kind", None) == "implicit":
                return torch.cat([integ.dense(self.prob.rhs, self.t, s, part) for part in tq.split(self.DENSE_ROWS)])
            return integ.sweep(self.prob.rhs, self.t, s, tq)


class ShootingBatch:
    """Several shooting systems on one grid with one integrator and one right-hand side (the same
    vector field; each its own boundary conditions), integrated together: s stacks theirs,
    (T·m, n), and every integration is one batch of all their intervals — on a model whose
    right-hand side costs mostly per-call overhead, T problems cost little more than one (the
    rig's one-step re-estimates: one pass of interval Jacobians 0.12, 0.15, 0.28 and 0.46 s for
    T = 1, 2, 4, 8).  Residuals, Newton matrices and steps stay per system
    (:func:`shootlab.bvp.solver.solve_together` drives them)."""

    def __init__(self, systems: Sequence[ShootingSystem]):
        self.systems = list(systems)
        first = self.systems[0]
        if any(s.integrator is not first.integrator or s.prob.rhs != first.prob.rhs or not torch.equal(s.t, first.t)
               for s in self.systems):
            raise ValueError("a ShootingBatch needs one grid, one integrator and one right-hand side")
        if getattr(first.integrator, "adaptive", False):
            raise ValueError("a ShootingBatch needs a fixed-step integrator (an adaptive one steps all rows alike)")
        T = len(self.systems)
        self.m, self.first = first.t.numel(), first
        self.t0, self.t1 = first.t0.repeat(T), first.t1.repeat(T)

    def split(self, s: Tensor) -> list[Tensor]:
        """Each system's rows of the stacked s (T·m, …)."""
        return list(s.split(self.m))

    def _starts(self, s: Tensor) -> Tensor:
        return torch.cat([si[:-1] for si in self.split(s)]).detach()

    def residuals(self, s: Tensor, jacobian: bool = False) -> list[Tensor | None]:
        """Each system's F at its rows of s, None where an interval could not be integrated or F is
        not finite; ``jacobian``: with the interval Jacobians from the same pass (as
        :meth:`ShootingSystem.residual`), kept by each system for its ``linearize`` at s."""
        first, s0 = self.first, self._starts(s)
        res, S = None, None
        if jacobian and first.jacobian == "frozen":
            res, S = first.frozen_pass(self.t0, self.t1, s0)
        elif jacobian and first.jacobian == "autograd" and first._autograd_mode(s0) == "autograd":
            try:
                res = first.integrator.integrate(first.prob.rhs, self.t0, self.t1, s0, sensitivity=True)
                S = res.S
            except NotTransformable:
                res = None
        if res is None:
            with torch.no_grad():
                res = first.integrator.integrate(first.prob.rhs, self.t0, self.t1, s0)
        bad = _failed_rows(res) if S is not None else res.failed | ~all_finite(res.y)
        out: list[Tensor | None] = []
        for i, (system, si) in enumerate(zip(self.systems, self.split(s))):
            rows = slice(i * (self.m - 1), (i + 1) * (self.m - 1))
            F = None if bool(bad[rows].any()) else system._residual(si, res.y[rows]).F
            if F is not None and not bool(torch.isfinite(F).all()):
                F = None
            if F is not None and S is not None:
                system._pending = (si.detach().clone(), S[rows])
            out.append(F)
        return out

    def newton_steps(self, s: Tensor, Fs: Sequence[Tensor | None], which: Sequence[int]) -> dict[int, Tensor | None]:
        """The Newton corrections δ = −J⁻¹F (m, n) of the systems ``which`` at their rows of s, for
        their residuals ``Fs``: their Newton matrices factorised as one batch
        (:func:`~shootlab.bvp.linalg.factorize_batch`, where their boundary conditions have one
        shape; else one by one), or, where every condition is at a (initial-value problems), solved
        by forward substitution (:func:`~shootlab.bvp.linalg.solve_initial_value`) — None for a
        system whose matrix is singular or whose interval Jacobians could not be integrated."""
        out: dict[int, Tensor | None] = {}
        parts = self.split(s)
        blocks = []
        for i in which:
            system = self.systems[i]
            try:
                Y = system.interval_jacobians(parts[i])
            except IntegrationFailure:
                out[i] = None
                continue
            blocks.append((i, Y, *system.bc_jacobians(parts[i])))
        if blocks and all(Bb.shape[0] == 0 for _, _, _, Bb in blocks):     # initial-value conditions
            idx = [b[0] for b in blocks]
            F = torch.stack([Fs[i] for i in idx])
            n = blocks[0][1].shape[-1]
            d, singular = solve_initial_value(torch.stack([b[1] for b in blocks]), torch.stack([b[2] for b in blocks]),
                                              F[:, :n], F[:, n:].reshape(len(idx), -1, n))
            for j, i in enumerate(idx):
                out[i] = None if bool(singular[j]) else -d[j]
            return out
        if len({(Ba.shape, Bb.shape) for _, _, Ba, Bb in blocks}) > 1:
            for i, Y, Ba, Bb in blocks:
                try:
                    out[i] = self.systems[i].newton_step(factorize(Y, Ba, Bb), Fs[i])
                except SingularJacobianError:
                    out[i] = None
            return out
        if blocks:
            idx = [b[0] for b in blocks]
            fac, singular = factorize_batch(*(torch.stack([b[j] for b in blocks]) for j in (1, 2, 3)))
            p, n, m = fac.p, fac.n, fac.m
            F = torch.stack([Fs[i] for i in idx])
            d = -fac.solve(F[:, :p], F[:, p:p + (m - 1) * n].reshape(-1, m - 1, n), F[:, p + (m - 1) * n:])
            for j, i in enumerate(idx):
                out[i] = None if bool(singular[j]) else d[j]
        return out

    def dense(self, tq: Tensor, s: Tensor) -> list[Tensor]:
        """Each system's values at tq, on the scheme's own step grid where tq lies on it
        (:meth:`ShootingSystem.dense` with ``grid``) from one pass over all their intervals: the
        stage points of the last residual at s again, whose right-hand side values a problem that
        keeps them (the estimation TPBVP) does not compute twice."""
        first = self.first
        on = first.integrator.on_grid(first.t, tq)
        if on is None:
            return [system.dense(tq, si) for system, si in zip(self.systems, self.split(s))]
        j, i = on
        with torch.no_grad():
            values = first.integrator.grid_values(first.prob.rhs, self.t0, self.t1, self._starts(s))
        return [v[j, i] for v in values.split(self.m - 1, dim=1)]
