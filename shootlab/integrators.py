"""Batched initial value problem integrators.

Multiple shooting integrates many independent IVPs -- one per shooting
interval, each with its own start time ``t0``, end time ``t1`` and initial
value ``y0`` -- and this module advances all of them together as one tensor::

    integ = get_integrator("ros4", rtol=1e-8, atol=1e-10)
    res = integ.integrate(rhs, t0, t1, y0)      # t0, t1: (B,), y0: (B, n)
    res.y, res.failed, res.reason, res.nfev, res.nsteps

``rhs(t, y)`` receives ``y`` of shape ``(m, n)`` and ``t`` of shape ``(m,)``
and must treat the rows independently: the number of rows ``m`` changes
between calls, because rows that finished (or failed) are dropped from the
active set and implicit schemes stack stage values into one call.

Registry (:data:`INTEGRATORS`):

=================  =========================================================
``euler``          explicit Euler, ``steps`` equal steps
``rk4``            classical Runge--Kutta, ``steps`` equal steps
``rkf45``          Fehlberg 4(5), 4th-order solution, ``steps`` equal steps
``implicit_euler`` backward Euler + Newton, ``steps`` equal steps
``radau3``         2-stage Radau IIA (order 3, L-stable) + Newton
``dopri5``         Dormand--Prince 5(4), per-element adaptive steps
``ros4``           Shampine's Rosenbrock 4(3), per-element adaptive steps
``auto``           ``dopri5`` per row, ``ros4`` on the rows whose local Jacobian
                   is stiff over the row's length (:class:`Auto`)
=================  =========================================================

Failures never raise: a row whose values become non-finite, whose step size
underflows, which exceeds ``max_steps`` or whose implicit stage equations do
not converge is frozen at its last finite state, flagged in
``IntegrationResult.failed`` and dropped from the computation; the other rows
carry on.

Differentiation.  The state updates are ordinary differentiable torch
operations, so ``y0`` may be a forward-mode dual tensor (the shooting code
replicates each interval ``n`` times with identity tangents to obtain
``dy(t1)/dy0``) or may require grad (reverse mode).  Everything used only for
control flow -- error norms, step sizes, convergence tests -- is computed from
detached values, so step sizes carry no tangent.  Implicit stage equations are
solved by Newton's method on detached values; one final Newton correction is
then applied to the non-detached quantities, which by the implicit function
theorem gives the exact derivative of the converged stages.

References:
  [HNW1] E. Hairer, S.P. Norsett, G. Wanner, Solving Ordinary Differential
         Equations I, 2nd ed., Springer 1993.
  [HW2]  E. Hairer, G. Wanner, Solving Ordinary Differential Equations II,
         2nd ed., Springer 1996.
  [NR]   W.H. Press et al., Numerical Recipes in C, 2nd ed., 1992, sec. 16.6.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import torch
import torch.autograd.forward_ad as fwAD
from torch import Tensor

from .tangents import jacobian_product, rhs_jacobian, second_product, time_derivative

__all__ = ["Integrator", "IntegrationResult", "INTEGRATORS", "get_integrator", "batch_jacobian"]

RHS = Callable[[Tensor, Tensor], Tensor]

NONFINITE = "non-finite value (overflow)"
UNDERFLOW = "step size underflow"
MAX_STEPS = "maximum number of steps exceeded"
NO_CONVERGENCE = "implicit stage equations did not converge"


@dataclass
class IntegrationResult:
    """Outcome of :meth:`Integrator.integrate`.

    Attributes:
        y: values at ``t1``, same shape as ``y0``.  For failed rows: the last
            finite state reached (meaningless as a solution).
        failed: bool, shape ``y0.shape[:-1]``.
        reason: ``None`` or the kind of the first failure encountered.
        nfev: number of (batched) rhs calls, including those made to form
            Jacobians.
        nsteps: number of batched steps; for adaptive schemes the number of
            step attempts (accepted + rejected) of the slowest row.
    """

    y: Tensor
    failed: Tensor
    reason: str | None
    nfev: int
    nsteps: int
    S: Tensor | None = None     # ∂y(t1)/∂y0 (..., n, n) when asked for (``sensitivity=True``)


# ---------------------------------------------------------------------------
# Jacobians by autograd
# ---------------------------------------------------------------------------

def _is_dual(x: Tensor) -> bool:
    return fwAD.unpack_dual(x).tangent is not None


def _drop_graph(x: Tensor) -> Tensor:
    """Detach ``x`` from the reverse-mode graph but keep its forward tangent."""
    primal, tangent = fwAD.unpack_dual(x)
    if tangent is None:
        return x.detach()
    return fwAD.make_dual(primal.detach(), tangent.detach())


def _const(x: Any, like: Tensor) -> Tensor:
    """``x`` as a constant operand for arithmetic with ``like``.

    When ``like`` is a dual tensor the constant gets an explicit zero tangent:
    forward AD treats an operand *without* tangent through a slow generic path
    (about 0.3 ms per operation in torch 2.13 on CPU, versus a few us), so the
    integrators keep all operands of their own arithmetic dual.
    """
    x = torch.as_tensor(x, dtype=like.dtype, device=like.device)
    return fwAD.make_dual(x, torch.zeros_like(x)) if _is_dual(like) else x


def _lincomb(coefs: Tensor, xs: list[Tensor]) -> Tensor:
    """``sum_j coefs[..., j] * xs[j]`` as one batched product; ``coefs`` has shape
    (k,) or, for per-row coefficients, (m, k); ``xs[j]`` has shape (m, n)."""
    return (torch.stack(xs, -1) @ coefs.unsqueeze(-1)).squeeze(-1)


class _TrackedJacobian(torch.autograd.Function):
    """(f, J, df/dt) at a y that requires grad, without recording the sweep on y's graph.

    ``torch.autograd.grad`` walks the whole graph behind its outputs, so calling it at every
    step of an integration whose state carries a graph costs O(steps²) (measured: 0.2 s per
    call after 1200 steps).  Here the forward pass works on a detached copy and the backward
    pass recomputes f, J, df/dt on a fresh leaf and returns their vector–Jacobian product.
    """

    @staticmethod
    def forward(ctx, y, rhs, t, with_time):
        ctx.rhs, ctx.t, ctx.with_time = rhs, t, with_time
        ctx.save_for_backward(y)
        out, jac, dfdt = _value_and_jacobian(rhs, t, y.detach(), with_time)
        return out, jac, (dfdt if with_time else torch.zeros_like(out))

    @staticmethod
    def backward(ctx, g_out, g_jac, g_dfdt):
        y, = ctx.saved_tensors
        with torch.enable_grad():
            leaf = y.detach().requires_grad_(True)
            out, jac, dfdt = _value_and_jacobian(ctx.rhs, ctx.t, leaf, ctx.with_time, _direct=True)
            total = (out * g_out).sum() + (jac * g_jac).sum()
            if ctx.with_time:
                total = total + (dfdt * g_dfdt).sum()
            g_y, = torch.autograd.grad(total, leaf, allow_unused=True)
        return (torch.zeros_like(y) if g_y is None else g_y), None, None, None


def _value_and_jacobian(rhs: RHS, t: Tensor, y: Tensor, with_time: bool = False, _direct: bool = False
                        ) -> tuple[Tensor, Tensor, Tensor | None]:
    """``f = rhs(t, y)``, ``J = df/dy`` of shape (..., n, n) and, if asked, ``df/dt``.

    One rhs call plus one reverse sweep vectorised over the n output
    components (``is_grads_batched``).  If ``y`` is a dual tensor the sweep is
    recorded (``create_graph``), so that ``J`` carries forward tangents
    (forward-over-reverse); if ``y`` requires grad, f, J and df/dt are
    differentiable through :class:`_TrackedJacobian`.
    """
    dual, track = _is_dual(y), y.requires_grad
    if track and not dual and not _direct:
        out, jac, dfdt = _TrackedJacobian.apply(y, rhs, t, with_time)
        return out, jac, (dfdt if with_time else None)
    with torch.enable_grad():
        yr = y.clone()
        if not yr.requires_grad:
            yr.requires_grad_(True)
        tr = t.detach().clone().requires_grad_(with_time)
        out = rhs(tr, yr)
        n_out = out.shape[-1]
        if not out.requires_grad:  # rhs does not depend on (t, y)
            jac = _const(out.new_zeros(*out.shape, y.shape[-1]), y)
            return out, jac, (_const(torch.zeros_like(out), y) if with_time else None)
        basis = torch.eye(n_out, dtype=out.dtype, device=out.device)
        basis = basis.reshape(n_out, *([1] * (out.dim() - 1)), n_out).expand(n_out, *out.shape)
        if dual:
            basis = _const(basis.contiguous(), y)
        inputs = (yr, tr) if with_time else (yr,)
        grads = torch.autograd.grad(out, inputs, grad_outputs=basis, is_grads_batched=True,
                                    create_graph=dual or track, allow_unused=True)
    # unused inputs give None: the derivative is zero
    jac = (_const(out.new_zeros(*out.shape, y.shape[-1]), y) if grads[0] is None
           else grads[0].movedim(0, -2))
    dfdt = None
    if with_time:
        dfdt = (_const(out.new_zeros(out.shape), y) if grads[1] is None
                else grads[1].movedim(0, -1))
    if not track:  # forward mode only: keep the tangents, free the reverse graph
        out, jac = _drop_graph(out), _drop_graph(jac)
        dfdt = _drop_graph(dfdt) if dfdt is not None else None
    return out, jac, dfdt


def batch_jacobian(rhs: RHS, t: Tensor, y: Tensor) -> Tensor:
    """Jacobian ``d rhs(t, y) / d y`` at every batch element, shape (..., n, n).

    Computed by reverse-mode autograd (one rhs call, one batched backward
    sweep).  Works when ``y`` is a forward-mode dual tensor (the Jacobian then
    carries tangents) or requires grad (the Jacobian is then differentiable).
    """
    return _value_and_jacobian(rhs, t, y)[1]


# ---------------------------------------------------------------------------
# Bookkeeping shared by all schemes
# ---------------------------------------------------------------------------

def _rms(x: Tensor) -> Tensor:
    """Root mean square over the last dimension, detached (for control flow only)."""
    return x.detach().pow(2).mean(-1).sqrt()


def _all_finite(x: Tensor) -> Tensor:
    return torch.isfinite(x.detach()).all(-1)


class _Ledger:
    """Collects the final state of every row as rows finish or fail."""

    def __init__(self, m: int, device: torch.device):
        self.indices: list[Tensor] = []
        self.values: list[Tensor] = []
        self.failed = torch.zeros(m, dtype=torch.bool, device=device)
        self.reason: str | None = None

    def finish(self, idx: Tensor, y: Tensor) -> None:
        if idx.numel():
            self.indices.append(idx)
            self.values.append(y)

    def fail(self, idx: Tensor, y: Tensor, reason: str) -> None:
        if idx.numel():
            self.finish(idx, y)
            self.failed[idx] = True
            self.reason = self.reason or reason

    def collect(self, y0: Tensor) -> Tensor:
        """Reassemble the rows in their original order."""
        if not self.values:
            return y0
        order = torch.argsort(torch.cat(self.indices))
        return torch.cat(self.values)[order]


# ---------------------------------------------------------------------------
# Base classes
# ---------------------------------------------------------------------------

class Integrator:
    """Base class: ``integrate(rhs, t0, t1, y0) -> IntegrationResult``.

    Every scheme accepts ``steps``, ``rtol`` and ``atol`` so that callers can
    construct any of them the same way (:func:`get_integrator`).  Their
    meaning is given in each subclass.
    """

    name: ClassVar[str]
    #: step sizes chosen by an error estimate against rtol / atol (``steps`` only bounds them)
    adaptive: ClassVar[bool] = False
    #: forward sensitivities of the discrete scheme implemented (``integrate(..., sensitivity=True)``)
    sensitivities: ClassVar[bool] = False

    def __init__(self, steps: int = 1, rtol: float | None = None, atol: float | None = None):
        if int(steps) < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        self.steps = int(steps)
        self.rtol = rtol
        self.atol = atol

    def __repr__(self) -> str:
        return f"{type(self).__name__}(steps={self.steps}, rtol={self.rtol}, atol={self.atol})"

    def integrate(self, rhs: RHS, t0: Tensor | float, t1: Tensor | float, y0: Tensor,
                  sensitivity: bool = False) -> IntegrationResult:
        """Integrate ``y' = rhs(t, y)`` from ``(t0, y0)`` to ``t1``, row by row.

        Args:
            rhs: ``rhs(t, y) -> dy/dt``, rows independent (see module doc).
            t0, t1: start and end times, shape ``y0.shape[:-1]`` (or
                broadcastable to it).  ``t1 < t0`` integrates backwards;
                ``t1 == t0`` returns ``y0``.  Times are treated as constants
                (detached).
            y0: initial values, shape ``(..., n)``; may be dual or require grad.
            sensitivity: also return ``S = ∂y(t1)/∂y0`` (``result.S``, shape (..., n, n)) by
                forward sensitivities of the discrete scheme: ``S`` is propagated with ``y``
                through every stage, ``S_{j+1} = (∂Φ_h/∂y)(y_j) S_j``, the step map Φ_h
                differentiated with its step sizes held fixed (:mod:`shootlab.tangents`;
                ``y0`` is then taken as a constant).  Raises
                :class:`~shootlab.tangents.NotTransformable` for a right-hand side that
                ``torch.func`` cannot differentiate, NotImplementedError for a scheme
                without it (``sensitivities`` False).
        """
        batch_shape, n = y0.shape[:-1], y0.shape[-1]
        y = y0.reshape(-1, n)
        sens = None
        if sensitivity:
            if not self.sensitivities:
                raise NotImplementedError(f"{self.name}: no forward sensitivities")
            # the carried state is packed [y | vec S], S_0 = I, so that the row bookkeeping
            # (dropping finished and failed rows) moves y and S together
            eye = torch.eye(n, dtype=y.dtype, device=y.device).reshape(1, n * n)
            y, sens = torch.cat([y.detach(), eye.expand(y.shape[0], n * n)], -1), n
        t0 = torch.as_tensor(t0, dtype=y0.dtype, device=y0.device).detach()
        t1 = torch.as_tensor(t1, dtype=y0.dtype, device=y0.device).detach()
        t0 = t0.expand(batch_shape).reshape(-1)
        t1 = t1.expand(batch_shape).reshape(-1)
        idx = torch.arange(y.shape[0], device=y.device)
        ledger = _Ledger(y.shape[0], y.device)

        bad = ~_all_finite(y)
        ledger.fail(idx[bad], y[bad], NONFINITE)
        trivial = (t1 == t0) & ~bad
        ledger.finish(idx[trivial], y[trivial])
        run = ~(bad | trivial)
        nfev = nsteps = 0
        if run.any():
            nfev, nsteps = self._advance(rhs, t0[run], t1[run], y[run], idx[run], ledger, sens)
        out, S = ledger.collect(y), None
        if sens:
            out, S = out[:, :n], out[:, n:].reshape(*batch_shape, n, n)
        return IntegrationResult(y=out.reshape(y0.shape), failed=ledger.failed.reshape(batch_shape),
                                 reason=ledger.reason, nfev=nfev, nsteps=nsteps, S=S)

    def _advance(self, rhs: RHS, t0: Tensor, t1: Tensor, y: Tensor, idx: Tensor,
                 ledger: _Ledger, sens: int | None = None) -> tuple[int, int]:
        """Integrate the rows ``idx`` (all finite, t1 != t0) and record them in
        ``ledger``; return ``(nfev, nsteps)``.  ``sens = n``: the rows are packed
        ``[y | vec S]`` (:meth:`integrate`)."""
        raise NotImplementedError


class FixedStepIntegrator(Integrator):
    """``steps`` equal steps ``h = (t1 - t0) / steps`` per row.

    Subclasses implement one step, ``_step(rhs, t, y, h) -> (y_new, ok, nfev)``
    with ``ok`` a bool mask (False: implicit stage equations not converged), and
    for forward sensitivities ``_step_sensitivity(rhs, t, y, S, h) -> (y_new,
    S_new, ok, nfev)`` with ``S_new = (∂y_new/∂y) S``.
    """

    def _step(self, rhs: RHS, t: Tensor, y: Tensor, h: Tensor) -> tuple[Tensor, Tensor, int]:
        raise NotImplementedError

    def _step_sensitivity(self, rhs: RHS, t: Tensor, y: Tensor, S: Tensor, h: Tensor
                          ) -> tuple[Tensor, Tensor, Tensor, int]:
        raise NotImplementedError

    def _advance(self, rhs, t0, t1, y, idx, ledger, sens=None):
        h = (t1 - t0) / self.steps
        nfev = nsteps = 0
        for k in range(self.steps):
            if sens is None:
                y_new, ok, nf = self._step(rhs, t0 + k * h, y, h)
            else:
                n = sens
                y1, S1, ok, nf = self._step_sensitivity(rhs, t0 + k * h, y[:, :n], y[:, n:].view(-1, n, n), h)
                y_new = torch.cat([y1, S1.reshape(-1, n * n)], -1)
            nfev, nsteps = nfev + nf, nsteps + 1
            finite = _all_finite(y_new)
            for mask, reason in ((~ok, NO_CONVERGENCE), (ok & ~finite, NONFINITE)):
                ledger.fail(idx[mask], y[mask], reason)  # frozen at the last finite state
            keep = ok & finite
            if not keep.all():
                t0, h, idx, y_new = t0[keep], h[keep], idx[keep], y_new[keep]
            y = y_new
            if not idx.numel():
                break
        ledger.finish(idx, y)
        return nfev, nsteps


def _combine(y: Tensor, h: Tensor, coefs: tuple[float, ...], ks: list[Tensor]) -> Tensor:
    """``y + h * sum_j coefs[j] * ks[j]`` with ``h`` of shape (m,)."""
    hcoefs = h[:, None] * h.new_tensor(coefs)
    return y + _lincomb(_const(hcoefs, y), ks)


def _rk_stages(rhs: RHS, t: Tensor, y: Tensor, h: Tensor, c: tuple[float, ...],
               a: tuple[tuple[float, ...], ...], k1: Tensor | None = None) -> list[Tensor]:
    """Stage derivatives ``k_i = rhs(t + c_i h, y + h sum_j a_ij k_j)`` of an
    explicit Runge--Kutta method (``a`` strictly lower triangular, one row per
    stage after the first).  ``k1`` may be supplied (FSAL)."""
    ks = [rhs(t, y) if k1 is None else k1]
    for ci, ai in zip(c[1:], a):
        ks.append(rhs(t + ci * h, _combine(y, h, ai, ks)))
    return ks


def _matcomb(coefs: Tensor, Ms: list[Tensor]) -> Tensor:
    """``sum_j coefs[:, j] * Ms[j]`` for matrices ``Ms[j]`` (m, n, k) and per-row ``coefs`` (m, s)."""
    return (torch.stack(Ms, -1) @ coefs[:, None, :, None]).squeeze(-1)


def _rk_stages_sensitivity(rhs: RHS, t: Tensor, y: Tensor, S: Tensor, h: Tensor, c: tuple[float, ...],
                           a: tuple[tuple[float, ...], ...], k1: tuple[Tensor, Tensor] | None = None
                           ) -> tuple[list[Tensor], list[Tensor]]:
    """Stages ``k_i`` of :func:`_rk_stages` and their sensitivities ``K_i = ∂k_i/∂y0``::

        Y_i = y + h Σ_j a_ij k_j,      ∂Y_i/∂y0 = S + h Σ_j a_ij K_j,
        k_i = f(t + c_i h, Y_i),       K_i = J(t + c_i h, Y_i) ∂Y_i/∂y0,

    each ``(k_i, K_i)`` one forward-mode call (:func:`shootlab.tangents.jacobian_product`:
    J·(∂Y_i/∂y0) without forming J).  ``k1 = (k_1, K_1)`` may be supplied (FSAL)."""
    ks, Ks = ([k1[0]], [k1[1]]) if k1 is not None else ([], [])
    if not ks:
        k, K = jacobian_product(rhs, t, y, S)
        ks.append(k)
        Ks.append(K)
    for ci, ai in zip(c[1:], a):
        hc = h[:, None] * h.new_tensor(ai)
        k, K = jacobian_product(rhs, t + ci * h, y + _lincomb(hc, ks), S + _matcomb(hc, Ks))
        ks.append(k)
        Ks.append(K)
    return ks, Ks


class ExplicitRK(FixedStepIntegrator):
    """Explicit Runge--Kutta method with Butcher tableau ``(c, a, b)``,
    ``steps`` equal steps; ``rtol``/``atol`` are accepted and unused."""

    c: ClassVar[tuple[float, ...]]
    a: ClassVar[tuple[tuple[float, ...], ...]]
    b: ClassVar[tuple[float, ...]]

    sensitivities = True

    def _step(self, rhs, t, y, h):
        ks = _rk_stages(rhs, t, y, h, self.c, self.a)
        ok = torch.ones(y.shape[0], dtype=torch.bool, device=y.device)
        return _combine(y, h, self.b, ks), ok, len(ks)

    def _step_sensitivity(self, rhs, t, y, S, h):
        """``y+ = y + h Σ b_i k_i``,  ``S+ = S + h Σ b_i K_i`` (:func:`_rk_stages_sensitivity`)."""
        ks, Ks = _rk_stages_sensitivity(rhs, t, y, S, h, self.c, self.a)
        hb = h[:, None] * h.new_tensor(self.b)
        ok = torch.ones(y.shape[0], dtype=torch.bool, device=y.device)
        return y + _lincomb(hb, ks), S + _matcomb(hb, Ks), ok, len(ks)


class Euler(ExplicitRK):
    """Explicit Euler, ``y+ = y + h f(t, y)`` (order 1).  ``steps=1`` is a single
    Euler step over the whole interval."""

    name = "euler"
    c = (0.0,)
    a = ()
    b = (1.0,)


class RK4(ExplicitRK):
    """Classical 4-stage Runge--Kutta method of order 4 ([HNW1] sec. II.1)."""

    name = "rk4"
    c = (0.0, 0.5, 0.5, 1.0)
    a = ((0.5,), (0.0, 0.5), (0.0, 0.0, 1.0))
    b = (1 / 6, 1 / 3, 1 / 3, 1 / 6)


class RKF45(ExplicitRK):
    """Runge--Kutta--Fehlberg 4(5) without step control, advancing with the
    4th-order solution as the MUSN code did (E. Fehlberg, NASA TR R-315, 1969;
    [HNW1] sec. II.5).  The 4th-order weights do not use the 6th stage, which
    is therefore not evaluated: 5 rhs calls per step, order 4."""

    name = "rkf45"
    c = (0.0, 1 / 4, 3 / 8, 12 / 13, 1.0)
    a = ((1 / 4,),
         (3 / 32, 9 / 32),
         (1932 / 2197, -7200 / 2197, 7296 / 2197),
         (439 / 216, -8.0, 3680 / 513, -845 / 4104))
    b = (25 / 216, 0.0, 1408 / 2565, 2197 / 4104, -1 / 5)


# ---------------------------------------------------------------------------
# Implicit fixed-step schemes
# ---------------------------------------------------------------------------

def _simplified_newton(G: Callable[[Tensor, Tensor], Tensor], matrix: Callable[[Tensor, Tensor], Tensor],
                       z: Tensor, scale: Tensor, maxiter: int, theta_max: float = 0.25
                       ) -> tuple[Tensor, Tensor, int]:
    """Row-wise simplified Newton iteration for ``G(z) = 0`` on detached values ([HW2] sec. IV.8).

    ``matrix(rows, z_rows)`` gives the Newton matrix ``M ≈ G'(z)`` (r, N, N) of the rows ``rows``
    (indices into the batch); it is formed and LU-factored at the starting iterate and kept for
    ``z ← z − M⁻¹ G(z)`` (``G(rows, z_rows)`` (r, N)) while the iteration contracts fast,
    ``θ_k = ‖Δz_k‖ / ‖Δz_{k−1}‖ < theta_max``; a row that contracts more slowly (or grows) gets a
    fresh matrix at its new iterate — at worst full Newton.  Converged: ``rms(Δz / scale) ≤ 1``
    within ``maxiter`` iterations; a row with a non-finite correction or a singular matrix fails.

    Returns ``(z, converged, nfev)``; nfev counts the G calls and the matrix builds.
    """
    m = z.shape[0]
    z = z.detach().clone()
    converged = torch.zeros(m, dtype=torch.bool, device=z.device)
    rows = torch.arange(m, device=z.device)
    stale = torch.ones(m, dtype=torch.bool, device=z.device)
    prev = torch.full((m,), math.inf, dtype=z.dtype, device=z.device)
    lu = piv = None
    nfev = 0
    for _ in range(maxiter):
        if not rows.numel():
            break
        if stale.any():
            lu_s, piv_s, info = torch.linalg.lu_factor_ex(matrix(rows[stale], z[rows[stale]]))
            nfev += 1
            if lu is None:
                lu, piv = lu_s, piv_s
            else:
                lu[stale], piv[stale] = lu_s, piv_s
            usable = torch.ones_like(stale)
            usable[stale] = info == 0
            rows, lu, piv, prev = rows[usable], lu[usable], piv[usable], prev[usable]
            if not rows.numel():
                break
        dz = torch.linalg.lu_solve(lu, piv, G(rows, z[rows]).unsqueeze(-1)).squeeze(-1)
        nfev += 1
        err = _rms(dz / scale[rows])
        finite = torch.isfinite(err)
        z[rows[finite]] -= dz[finite]
        done = finite & (err <= 1.0)
        converged[rows[done]] = True
        go = finite & ~done
        stale = (err / prev >= theta_max)[go]
        rows, lu, piv, prev = rows[go], lu[go], piv[go], err[go]
    return z, converged, nfev


class _ImplicitFixedStep(FixedStepIntegrator):
    """Fixed-step implicit scheme.  The stage equations are solved by simplified Newton
    (:func:`_simplified_newton`: the Newton matrix from the rhs Jacobian at the start of the
    step, built once per step and refreshed only where the iteration stalls; the Jacobians by
    forward mode, :func:`shootlab.tangents.rhs_jacobian`).  Derivatives are not taken through
    the iteration but by the implicit function theorem at the converged stages: ``G(z, y) = 0``
    gives ``∂z/∂y = −G_z⁻¹ G_y`` with ``G_z`` the *exact* Newton matrix there — as forward
    sensitivities (``_step_sensitivity``), or, when ``y`` carries a graph or forward tangents
    (the reverse-sweep path), as one differentiable Newton correction
    ``z* − G_z⁻¹ G(z*, y)`` whose derivative in ``y`` is exactly that.

    ``rtol``/``atol`` (defaults 1e-10/1e-12) set the Newton stopping test
    ``rms(dz / (atol + rtol |y|)) <= 1``; at most ``newton_maxiter`` iterations; the Newton
    matrix is rebuilt where the contraction factor reaches ``newton_theta`` (0: full Newton).
    """

    sensitivities = True

    def __init__(self, steps: int = 1, rtol: float | None = None, atol: float | None = None,
                 newton_maxiter: int = 20, newton_theta: float = 0.25):
        super().__init__(steps, rtol, atol)
        self.newton_maxiter, self.newton_theta = int(newton_maxiter), float(newton_theta)

    def _newton_scale(self, y: Tensor) -> Tensor:
        rtol = 1e-10 if self.rtol is None else self.rtol
        atol = 1e-12 if self.atol is None else self.atol
        return atol + rtol * y.detach().abs()

    def _solve(self, G, matrix, z0: Tensor, scale: Tensor) -> tuple[Tensor, Tensor, int]:
        return _simplified_newton(G, matrix, z0, scale, self.newton_maxiter, self.newton_theta)


def _differentiable(y: Tensor) -> bool:
    return y.requires_grad or _is_dual(y)


def _lu_solve(M: Tensor, B: Tensor) -> Tensor:
    """``M⁻¹ B`` for batched matrices M (r, N, N) and B (r, N) or (r, N, k)."""
    lu, piv, _ = torch.linalg.lu_factor_ex(M)     # singular: non-finite values, reported as such
    return torch.linalg.lu_solve(lu, piv, B.unsqueeze(-1)).squeeze(-1) if B.dim() == 2 else \
        torch.linalg.lu_solve(lu, piv, B)


class ImplicitEuler(_ImplicitFixedStep):
    """Backward Euler, ``y+ = y + h f(t + h, y+)`` (order 1, L-stable).

    Simplified Newton on ``G(z) = z - y - h f(t+h, z)`` from ``z = y`` with
    ``M = I - h J(t+h, y)``.  Sensitivity (implicit function theorem):
    ``(I − h J(t+h, y+)) S+ = S``.
    """

    name = "implicit_euler"

    def _stages(self, rhs, t, y, h):
        n = y.shape[-1]
        t_new, hc, yd = t + h, h[:, None], y.detach()
        eye = torch.eye(n, dtype=y.dtype, device=y.device)
        z, ok, nfev = self._solve(lambda rows, z: z - yd[rows] - hc[rows] * rhs(t_new[rows], z),
                                  lambda rows, z: eye - hc[rows, :, None] * rhs_jacobian(rhs, t_new[rows], z)[1],
                                  yd, self._newton_scale(y))
        return z, ok, nfev, t_new, hc, eye

    def _step(self, rhs, t, y, h):
        z, ok, nfev, t_new, hc, eye = self._stages(rhs, t, y, h)
        if not _differentiable(y):
            return z, ok, nfev
        M = eye - hc[..., None] * rhs_jacobian(rhs, t_new, z)[1]
        zc = _const(z, y)
        g = zc - y - _const(hc, y) * rhs(t_new, z)
        return zc - _lu_solve(M, g), ok, nfev + 2

    def _step_sensitivity(self, rhs, t, y, S, h):
        z, ok, nfev, t_new, hc, eye = self._stages(rhs, t, y, h)
        _, J = rhs_jacobian(rhs, t_new, z)
        return z, _lu_solve(eye - hc[..., None] * J, S), ok, nfev + 1


class Radau3(_ImplicitFixedStep):
    """Two-stage Radau IIA method, order 3, L-stable, stiffly accurate
    ([HW2] sec. IV.5):

        c = (1/3, 1),   A = [[5/12, -1/12], [3/4, 1/4]],   b = (3/4, 1/4).

    Unknowns are the stage increments ``Z_i = h sum_j a_ij f(t + c_j h, y + Z_j)``
    (2n per row), found by simplified Newton from ``Z = 0`` with the 2n x 2n matrix
    ``I - h (A ⊗ J(t, y))``; both stages are evaluated in one rhs call.  ``y+ = y + Z_2``.
    Sensitivity (implicit function theorem, ``J_j`` at the converged stages):
    ``(I − h [a_ij J_j]) ∂Z/∂y = h [Σ_j a_ij J_j] S``,  ``S+ = S + ∂Z_2/∂y``.
    """

    name = "radau3"
    c = (1 / 3, 1.0)
    A = ((5 / 12, -1 / 12), (3 / 4, 1 / 4))

    def _blocks(self, a: Tensor, J: Tensor, h: Tensor) -> Tensor:
        """``I − h [a_ij J_j]`` (r, 2n, 2n) from the stage Jacobians J (r, 2, n, n)."""
        r, _, n, _ = J.shape
        blocks = a[None, :, :, None, None] * J[:, None]  # [r, i, j] = a_ij J_j
        eye = torch.eye(2 * n, dtype=J.dtype, device=J.device)
        return eye - h[:, None, None] * blocks.permute(0, 1, 3, 2, 4).reshape(r, 2 * n, 2 * n)

    def _stages(self, rhs, t, y, h, exact: bool = True):
        """Converged stage increments Z (m, 2, n) and, if ``exact``, the stage Jacobians
        J_j = J(t + c_j h, y + Z_j) (m, 2, n, n) (else None)."""
        m, n = y.shape
        a = torch.tensor(self.A, dtype=y.dtype, device=y.device)
        c = torch.tensor(self.c, dtype=y.dtype, device=y.device)
        t_st = t[:, None] + h[:, None] * c  # (m, 2) stage times
        hc, yd = h[:, None, None], y.detach()

        def G(rows, z):
            r = rows.numel()
            zz = z.view(r, 2, n)
            f = rhs(t_st[rows].reshape(-1), (yd[rows, None] + zz).reshape(-1, n)).view(r, 2, n)
            return (zz - hc[rows] * torch.einsum("ij,rjk->rik", a, f)).reshape(r, 2 * n)

        def matrix(rows, z):
            J = rhs_jacobian(rhs, t[rows], yd[rows])[1]
            return self._blocks(a, J[:, None].expand(-1, 2, n, n), h[rows])

        z, ok, nfev = self._solve(G, matrix, y.new_zeros(m, 2 * n), self._newton_scale(y).repeat(1, 2))
        z, J = z.view(m, 2, n), None
        if exact:
            J = rhs_jacobian(rhs, t_st.reshape(-1), (yd[:, None] + z).reshape(-1, n))[1].view(m, 2, n, n)
            nfev += 1
        return z, ok, nfev, a, t_st, J

    def _step(self, rhs, t, y, h):
        m, n = y.shape
        z, ok, nfev, a, t_st, J = self._stages(rhs, t, y, h, exact=_differentiable(y))
        if J is None:
            return y + z[:, 1], ok, nfev
        # the differentiable Newton correction with the exact matrix (carries the tangents / graph)
        zz = _const(z, y)
        f = rhs(t_st.reshape(-1), (y[:, None] + zz).reshape(-1, n)).view(m, 2, n)
        g = zz - _const(h[:, None, None], y) * torch.einsum("ij,rjk->rik", _const(a, y), f)
        zz = zz - _lu_solve(self._blocks(a, J, h), g.reshape(m, 2 * n)).view(m, 2, n)
        return y + zz[:, 1], ok, nfev + 1

    def _step_sensitivity(self, rhs, t, y, S, h):
        z, ok, nfev, a, _, J = self._stages(rhs, t, y, h)
        m, n = y.shape
        JS = J @ S[:, None]                                                   # (m, 2, n, n): J_j S
        R = h[:, None, None, None] * torch.einsum("ij,rjkl->rikl", a, JS)     # h Σ_j a_ij J_j S
        dZ = _lu_solve(self._blocks(a, J, h), R.reshape(m, 2 * n, n)).view(m, 2, n, n)
        return y + z[:, 1], S + dZ[:, 1], ok, nfev


class ImplicitMidpoint(_ImplicitFixedStep):
    """Implicit midpoint rule ``y+ = y + h f(t + h/2, (y + y+)/2)`` (order 2, A-stable,
    symmetric: ``R(−z) = 1/R(z)``, ``|R(z)| ≶ 1`` exactly when ``Re z ≶ 0``).

    The scheme for stiff *boundary value* problems with growing and decaying fast modes (a
    Hamiltonian TPBVP has both): it neither amplifies the growing modes beyond |R| → 1 (no
    overflow on long shooting intervals) nor turns them into decaying ones as L-stable schemes
    (radau3, implicit Euler) do — that would leave the conditions at b nothing to act on.
    Simplified Newton on ``G(z) = z − y − h f(t + h/2, (y + z)/2)`` from ``z = y`` with
    ``M = I − (h/2) J(t + h/2, y)``.  Sensitivity (implicit function theorem, J* at the
    converged midpoint): ``(I − h/2 J*) S+ = (I + h/2 J*) S``, i.e. ``S+ = 2 (I − h/2 J*)⁻¹ S − S``.
    """

    name = "midpoint"

    def _stages(self, rhs, t, y, h):
        n = y.shape[-1]
        tm, hc, yd = t + 0.5 * h, h[:, None], y.detach()
        eye = torch.eye(n, dtype=y.dtype, device=y.device)
        z, ok, nfev = self._solve(
            lambda rows, z: z - yd[rows] - hc[rows] * rhs(tm[rows], 0.5 * (yd[rows] + z)),
            lambda rows, z: eye - 0.5 * hc[rows, :, None] * rhs_jacobian(rhs, tm[rows], 0.5 * (yd[rows] + z))[1],
            yd, self._newton_scale(y))
        return z, ok, nfev, tm, hc, eye

    def _step(self, rhs, t, y, h):
        z, ok, nfev, tm, hc, eye = self._stages(rhs, t, y, h)
        if not _differentiable(y):
            return z, ok, nfev
        M = eye - 0.5 * hc[..., None] * rhs_jacobian(rhs, tm, 0.5 * (y.detach() + z))[1]
        zc = _const(z, y)
        g = zc - y - _const(hc, y) * rhs(tm, 0.5 * (y + zc))
        return zc - _lu_solve(M, g), ok, nfev + 2

    def _step_sensitivity(self, rhs, t, y, S, h):
        z, ok, nfev, tm, hc, eye = self._stages(rhs, t, y, h)
        _, J = rhs_jacobian(rhs, tm, 0.5 * (y + z))
        return z, 2.0 * _lu_solve(eye - 0.5 * hc[..., None] * J, S) - S, ok, nfev + 1


# ---------------------------------------------------------------------------
# Adaptive schemes
# ---------------------------------------------------------------------------

class AdaptiveIntegrator(Integrator):
    """Embedded pair with per-row step size control ([HNW1] sec. II.4).

    Every row has its own ``t`` and ``h``; all active rows attempt a step
    together, and rows that reach ``t1`` or fail are removed from the active
    set, so stragglers only cost work proportional to their number.

    Error norm ``err = rms(e / (atol + rtol max(|y|, |y+|)))``; a step is
    accepted if ``err <= 1`` and all values are finite.  New step
    ``h * min(max_factor, max(min_factor, safety * err^(-1/(q+1))))`` with q
    the order of the embedded solution; a step following a rejection may not
    grow; a non-finite attempt shrinks ``h`` by ``min_factor``.  Initial step:
    [HNW1] p. 169.

    Args:
        steps: ``|h| <= |t1 - t0| / steps`` (default 1: no restriction).
        rtol, atol: tolerances, default 1e-8 and 1e-10.
        max_steps: step attempts allowed per row.
        max_abs: a row whose accepted state exceeds this in magnitude is failed as an
            overflow at once (blow-up detection: without it a row heading for a
            singularity creeps towards it with ever smaller steps).
    """

    adaptive = True
    error_order: ClassVar[int]  # q
    fsal: ClassVar[bool] = False  # _attempt uses and returns f(t, y)

    def __init__(self, steps: int = 1, rtol: float | None = None, atol: float | None = None,
                 max_steps: int = 100_000, safety: float = 0.9, min_factor: float = 0.2,
                 max_factor: float = 5.0, max_abs: float = math.inf):
        super().__init__(steps, rtol, atol)
        self.max_steps, self.max_abs = int(max_steps), float(max_abs)
        self.safety, self.min_factor, self.max_factor = safety, min_factor, max_factor

    def _attempt(self, rhs: RHS, t: Tensor, y: Tensor, h: Tensor, f: Tensor | None
                 ) -> tuple[Tensor, Tensor, Tensor | None, int]:
        """One step of size ``h``: ``(y_new, error_estimate (detached), f(t+h, y_new) or
        None, nfev)``.  ``f`` is ``rhs(t, y)`` if the scheme is FSAL, else None."""
        raise NotImplementedError

    def _tolerances(self) -> tuple[float, float]:
        return (1e-8 if self.rtol is None else self.rtol,
                1e-10 if self.atol is None else self.atol)

    def _initial_step(self, rhs: RHS, t0: Tensor, y0: Tensor, f0: Tensor, direction: Tensor,
                      hmax: Tensor) -> Tensor:
        """Starting step of [HNW1] p. 169 (one extra rhs call), signed."""
        rtol, atol = self._tolerances()
        y0, f0 = y0.detach(), f0.detach()
        scale = atol + rtol * y0.abs()
        d0, d1 = _rms(y0 / scale), _rms(f0 / scale)
        h0 = torch.where((d0 < 1e-5) | (d1 < 1e-5), torch.full_like(d0, 1e-6), 0.01 * d0 / d1)
        h0 = torch.minimum(h0, hmax)
        f1 = rhs(t0 + direction * h0, y0 + (direction * h0)[:, None] * f0)
        d2 = _rms((f1 - f0) / scale) / h0
        dmax = torch.maximum(d1, d2)
        h1 = torch.where(dmax <= 1e-15, torch.clamp(h0 * 1e-3, min=1e-6),
                         (0.01 / dmax) ** (1.0 / (self.error_order + 1)))
        h = torch.where(torch.isfinite(d2), torch.minimum(100 * h0, h1), h0)
        return direction * torch.minimum(h, hmax)

    def _attempt_sensitivity(self, rhs: RHS, t: Tensor, y: Tensor, S: Tensor, h: Tensor,
                             f: tuple[Tensor, Tensor] | None
                             ) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, Tensor] | None, int]:
        """:meth:`_attempt` with the sensitivity ``S = ∂y/∂y0`` carried along (step size held
        fixed): ``(y_new, S_new, error_estimate, (f, J S) at the new point or None, nfev)``."""
        raise NotImplementedError

    def _advance(self, rhs, t0, t1, y, idx, ledger, sens=None):
        rtol, atol = self._tolerances()
        eps = torch.finfo(y.dtype).eps
        n = y.shape[-1] if sens is None else sens
        t, t_end = t0, t1
        direction = torch.sign(t1 - t0)
        hmax = (t1 - t0).abs() / self.steps
        f = rhs(t, y[:, :n])
        h = self._initial_step(rhs, t, y[:, :n], f, direction, hmax)
        nfev = 2
        if not self.fsal:
            f = None
        elif sens is not None:          # packed [f | vec(J S)] like the state
            f = torch.cat([f, jacobian_product(rhs, t, y[:, :n], y[:, n:].view(-1, n, n))[1].flatten(1)], -1)
            nfev += 1
        rejected = torch.zeros_like(t, dtype=torch.bool)
        exponent = -1.0 / (self.error_order + 1)
        nsteps = 0
        while idx.numel():
            if nsteps == self.max_steps:
                ledger.fail(idx, y, MAX_STEPS)
                break
            nsteps += 1
            remaining = t_end - t
            # within rounding of the end: take it, or a sliver of ~1e-19 would be left as a step
            last = h.abs() * (1.0 + 1e-10) >= remaining.abs()
            h = torch.where(last, remaining, h)
            if sens is None:
                y_new, err, f_new, nf = self._attempt(rhs, t, y, h, f)
            else:
                fS = None if f is None else (f[:, :n], f[:, n:].view(-1, n, n))
                y1, S1, err, fS, nf = self._attempt_sensitivity(rhs, t, y[:, :n], y[:, n:].view(-1, n, n), h, fS)
                y_new = torch.cat([y1, S1.flatten(1)], -1)
                f_new = None if fS is None else torch.cat([fS[0], fS[1].flatten(1)], -1)
            nfev += nf

            # step size control, on detached values only (the solution, not its sensitivity)
            yd, yd_new = y[:, :n].detach(), y_new[:, :n].detach()
            err = _rms(err / (atol + rtol * torch.maximum(yd.abs(), yd_new.abs())))
            finite = torch.isfinite(err) & _all_finite(y_new.detach())
            accept = finite & (err <= 1.0)
            factor = (self.safety * err.pow(exponent)).clamp(self.min_factor, self.max_factor)
            factor = torch.where(finite, factor, torch.full_like(factor, self.min_factor))
            factor = torch.where(accept & rejected, factor.clamp(max=1.0), factor)
            rejected = ~accept

            t = torch.where(accept, torch.where(last, t_end, t + h), t)
            y = torch.where(accept[:, None], y_new, y)
            if f is not None:
                f = torch.where(accept[:, None], f_new, f)
            h = direction * torch.minimum((h * factor).abs(), hmax)

            blown = accept & (yd_new.abs().amax(-1) > self.max_abs)
            done = accept & last & ~blown
            tiny = h.abs() < 10 * eps * torch.maximum(t.abs(), t_end.abs())
            underflow = tiny & ~done & ~blown
            ledger.finish(idx[done], y[done])
            ledger.fail(idx[blown], y[blown], NONFINITE)
            if underflow.any():
                nonfinite_last = (underflow & ~finite).any()
                ledger.fail(idx[underflow], y[underflow],
                            NONFINITE if nonfinite_last else UNDERFLOW)
            keep = ~(done | underflow | blown)
            if not keep.all():
                idx, t, t_end, h, hmax, direction, y, rejected = (
                    x[keep] for x in (idx, t, t_end, h, hmax, direction, y, rejected))
                f = f[keep] if f is not None else None
        return nfev, nsteps


class Dopri5(AdaptiveIntegrator):
    """Dormand--Prince 5(4) (J.R. Dormand, P.J. Prince, J. Comput. Appl. Math.
    6 (1980) 19-26; coefficients from [HNW1] Table II.5.2).  Advances with the
    5th-order solution; 7 stages, first-same-as-last, so 6 rhs calls per
    step.  Error estimate ``h sum_i (b_i - bhat_i) k_i`` is of order 4.
    """

    name = "dopri5"
    error_order = 4
    fsal = True
    c = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0)
    a = ((1 / 5,),
         (3 / 40, 9 / 40),
         (44 / 45, -56 / 15, 32 / 9),
         (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
         (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656))
    b = (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84)
    bhat = (5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40)
    e = tuple(bi - bh for bi, bh in zip(b + (0.0,), bhat))  # b_7 = 0 (FSAL stage)

    sensitivities = True

    def _attempt(self, rhs, t, y, h, f):
        ks = _rk_stages(rhs, t, y, h, self.c, self.a, k1=f)
        y_new = _combine(y, h, self.b, ks)
        ks.append(rhs(t + h, y_new))
        err = _lincomb(h[:, None] * h.new_tensor(self.e), [k.detach() for k in ks])
        return y_new, err, ks[-1], 6

    def _attempt_sensitivity(self, rhs, t, y, S, h, f):
        """Stages and their sensitivities (:func:`_rk_stages_sensitivity`), FSAL for both:
        the 7th stage is (f, J S) at (t + h, y+)."""
        ks, Ks = _rk_stages_sensitivity(rhs, t, y, S, h, self.c, self.a, k1=f)
        hb = h[:, None] * h.new_tensor(self.b)
        y_new, S_new = y + _lincomb(hb, ks), S + _matcomb(hb, Ks)
        k7, K7 = jacobian_product(rhs, t + h, y_new, S_new)
        err = _lincomb(h[:, None] * h.new_tensor(self.e), ks + [k7])
        return y_new, S_new, err, (k7, K7), 6


class Ros4(AdaptiveIntegrator):
    """Rosenbrock method 4(3) of Shampine, A-stable (L.F. Shampine, ACM TOMS 8
    (1982) 93-113), with the coefficients of [NR] routine ``stiff``.

    With ``W = I / (gamma h) - J``, ``J = df/dy(t, y)``, ``f_t = df/dt(t, y)``:

        W g1 = f(t, y)                             + c1x h f_t
        W g2 = f(t + a2x h, y + a21 g1)            + c2x h f_t + c21 g1 / h
        W g3 = f(t + a3x h, y + a31 g1 + a32 g2)   + c3x h f_t + (c31 g1 + c32 g2) / h
        W g4 = f(t + a3x h, y + a31 g1 + a32 g2)   + c4x h f_t + (c41 g1 + c42 g2 + c43 g3) / h
        y+   = y + sum_i b_i g_i,   error estimate sum_i e_i g_i (order 3).

    The 4th stage reuses the 3rd function value: 3 rhs calls per step, one of
    which also yields J and f_t by autograd; W is LU-factored once per step
    (batched).  A singular W counts as a non-finite attempt (step shrinks).

    The method is A-stable but not L-stable (``R(-inf) = 1/3``) and not
    stiffly accurate: on stiff problems driven by a time-dependent forcing
    (Prothero--Robinson type, ``y' = lam (y - g(t)) + g'(t)``) its error
    behaves like ``h^2``, so the controller takes many more steps there than
    on a linear stiff system or on chemical kinetics.
    """

    name = "ros4"
    error_order = 3
    gam = 1 / 2
    a = ((2.0,), (48 / 25, 6 / 25))  # a21; a31, a32 (stage 4 reuses stage 3)
    ax = (1.0, 3 / 5)  # a2x, a3x: stage times t + ax h
    c = ((), (-8.0,), (372 / 25, 12 / 5), (-112 / 125, -54 / 125, -2 / 5))  # c_ij, j < i
    cx = (1 / 2, -3 / 2, 121 / 50, 29 / 250)  # c1x..c4x
    b = (19 / 9, 1 / 2, 25 / 108, 125 / 108)
    e = (17 / 54, 7 / 36, 0.0, 125 / 108)

    def _attempt(self, rhs, t, y, h, f):
        n = y.shape[-1]
        f1, jac, dfdt = _value_and_jacobian(rhs, t, y, with_time=True)
        hc = h[:, None]
        eye = torch.eye(n, dtype=y.dtype, device=y.device)
        w = _const(eye / (self.gam * hc[..., None]), y) - jac
        lu, piv, info = torch.linalg.lu_factor_ex(w)

        def stage(i: int, f_i: Tensor, gs: list[Tensor]) -> Tensor:
            """g_i = W^-1 (f_i + c_ix h f_t + sum_j c_ij g_j / h)."""
            c_ij = hc.new_tensor(self.c[i]).expand(len(h), i)
            coefs = torch.cat([self.cx[i] * hc, c_ij / hc], -1)
            r = f_i + _lincomb(_const(coefs, y), [dfdt, *gs])
            return torch.linalg.lu_solve(lu, piv, r.unsqueeze(-1)).squeeze(-1)

        g1 = stage(0, f1, [])
        f2 = rhs(t + self.ax[0] * h, y + _lincomb(_const(self.a[0], y), [g1]))
        g2 = stage(1, f2, [g1])
        f3 = rhs(t + self.ax[1] * h, y + _lincomb(_const(self.a[1], y), [g1, g2]))
        g3 = stage(2, f3, [g1, g2])
        g4 = stage(3, f3, [g1, g2, g3])
        gs = [g1, g2, g3, g4]
        y_new = y + _lincomb(_const(self.b, y), gs)
        err = _lincomb(h.new_tensor(self.e), [g.detach() for g in gs])
        err = torch.where((info == 0)[:, None], err, torch.full_like(err, math.inf))
        return y_new, err, None, 3

    sensitivities = True

    def _attempt_sensitivity(self, rhs, t, y, S, h, f):
        """The stages of :meth:`_attempt` and their sensitivities ``G_i = ∂g_i/∂y0`` (h fixed).
        Differentiating ``W g_i = r_i``, ``W = I/(γh) − J(t, y)``::

            W G_i = F_i + Σ_j c_ij G_j / h + D_y[J g_i + c_ix h f_t] S,

        with ``F_i = J(t_i, Y_i) ∂Y_i/∂y0`` the sensitivity of the stage value f_i and the
        last term the second derivative of f (:func:`shootlab.tangents.second_product`,
        the derivative of W and f_t); ``S+ = S + Σ b_i G_i``."""
        n = y.shape[-1]
        f1, J = jacobian_product(rhs, t, y)
        dfdt = time_derivative(rhs, t, y)
        hc = h[:, None]
        eye = torch.eye(n, dtype=y.dtype, device=y.device)
        lu, piv, info = torch.linalg.lu_factor_ex(eye / (self.gam * hc[..., None]) - J)
        gs: list[Tensor] = []
        Gs: list[Tensor] = []

        def stage(i: int, f_i: Tensor, F_i: Tensor) -> None:
            c_ij = hc.new_tensor(self.c[i]).expand(len(h), i) / hc
            r = f_i + self.cx[i] * hc * dfdt + (_lincomb(c_ij, gs) if i else 0.0)
            g = torch.linalg.lu_solve(lu, piv, r.unsqueeze(-1)).squeeze(-1)
            R = F_i + second_product(rhs, t, y, g, self.cx[i] * h, S) + (_matcomb(c_ij, Gs) if i else 0.0)
            gs.append(g)
            Gs.append(torch.linalg.lu_solve(lu, piv, R))

        stage(0, f1, J @ S)
        a21 = hc.new_tensor(self.a[0]).expand(len(h), 1)
        f2, F2 = jacobian_product(rhs, t + self.ax[0] * h, y + _lincomb(a21, gs), S + _matcomb(a21, Gs))
        stage(1, f2, F2)
        a3 = hc.new_tensor(self.a[1]).expand(len(h), 2)
        f3, F3 = jacobian_product(rhs, t + self.ax[1] * h, y + _lincomb(a3, gs), S + _matcomb(a3, Gs))
        stage(2, f3, F3)
        stage(3, f3, F3)
        b = hc.new_tensor(self.b).expand(len(h), 4)
        err = _lincomb(h.new_tensor(self.e), gs)
        err = torch.where((info == 0)[:, None], err, torch.full_like(err, math.inf))
        return y + _lincomb(b, gs), S + _matcomb(b, Gs), err, None, 3


class Auto(Integrator):
    """Automatic choice per row: ``dopri5`` (explicit) where the local Jacobian allows it,
    ``ros4`` (A-stable Rosenbrock) only on the rows that are stiff.

    A row is stiff when the local Jacobian ∂f/∂y at its start (t0, y0) has a decaying mode
    whose magnitude times the row's length exceeds :attr:`stiff_limit`:
    max_{Re λ < 0} |λ| · |t1 − t0| > stiff_limit.  An explicit scheme's step is bounded by its
    stability region (Dormand–Prince: |hλ| ≲ 3.3 on the negative real axis), so such a row
    would take more than about stiff_limit / 3.3 explicit steps whatever the tolerance; the
    default (5000: over 1500 steps) is where ``ros4`` with its forward sensitivities becomes the
    cheaper of the two (measured on the BVP test set, benchmarks/bvp_testset.py: at
    max|λ|·H ≈ 600 ``dopri5`` is still 7x faster).  Growing modes do not count: both schemes
    follow them with the steps the tolerance asks for (and multiple shooting keeps
    κ₊·H small).  Rows are split once per :meth:`integrate` call (two batches, never a loop
    over rows); the decision costs one batched Jacobian and its eigenvalues.

    ``steps``, ``rtol``, ``atol`` and ``max_abs`` go to both schemes (rtol default 1e-8).
    """

    name = "auto"
    adaptive = True
    sensitivities = True
    stiff_limit: float = 5000.0
    #: rows whose rate along one direction, times their length, is below stiff_limit / this
    #: are taken as non-stiff without computing their Jacobian (a directional rate can
    #: underestimate |λ|, hence the margin; a stiff row missed would only cost explicit steps)
    screen_safety: float = 100.0

    def __init__(self, steps: int = 1, rtol: float | None = None, atol: float | None = None,
                 stiff_limit: float | None = None, **options: Any):
        super().__init__(steps, rtol, atol)
        if stiff_limit is not None:
            self.stiff_limit = float(stiff_limit)
        self.explicit = Dopri5(steps, rtol, atol, **options)
        self.stiff = Ros4(steps, rtol, atol, **options)
        #: rows integrated by each scheme over this integrator's life: {"dopri5": k, "ros4": k}
        self.rows = {"dopri5": 0, "ros4": 0}

    @property
    def max_abs(self) -> float:
        return self.explicit.max_abs

    @max_abs.setter
    def max_abs(self, value: float) -> None:
        self.explicit.max_abs = self.stiff.max_abs = float(value)

    def stiff_rows(self, rhs: RHS, t0: Tensor, t1: Tensor, y0: Tensor) -> Tensor:
        """Bool mask of the rows to integrate with the stiff scheme (class docstring)."""
        from .shooting import batched_eigvals
        length = (t1 - t0).abs()
        with torch.no_grad():
            t0, y0 = t0.detach(), y0.detach()
            # screen: the rate along one direction v, from one extra rhs call; far below the
            # limit on every row, the Jacobian (an rhs call and a reverse sweep) is not needed
            v = (1.0 + y0.abs()) * torch.where(torch.arange(y0.shape[-1], device=y0.device) % 2 == 0, 1.0, -1.0
                                               ).to(y0.dtype)
            delta = 1e-7 / v.abs().amax(-1, keepdim=True)
            rate = ((rhs(t0, y0 + delta * v) - rhs(t0, y0)).abs().amax(-1) / (delta[:, 0] * v.abs().amax(-1)))
            if bool(torch.isfinite(rate).all()) and bool((rate * length * self.screen_safety <= self.stiff_limit).all()):
                return torch.zeros_like(length, dtype=torch.bool)
            J = _value_and_jacobian(rhs, t0, y0)[1].detach()
            finite = torch.isfinite(J).flatten(-2).all(-1)
            J = torch.where(finite[:, None, None], J, torch.zeros_like(J))
            bound = J.abs().sum(-1).amax(-1) * length        # ‖J‖∞·H ≥ |λ|·H: most calls end here
            if not bool((bound > self.stiff_limit).any()):
                return torch.zeros_like(length, dtype=torch.bool)
            lam = batched_eigvals(J)
            decaying = torch.where(lam.real < 0, lam.abs(), torch.zeros_like(lam.real))
            rate = torch.nan_to_num(decaying, nan=0.0).amax(-1)
        return rate * length > self.stiff_limit

    def _advance(self, rhs, t0, t1, y, idx, ledger, sens=None):
        n = y.shape[-1] if sens is None else sens
        stiff = self.stiff_rows(rhs, t0, t1, y[:, :n])
        nfev = nsteps = 0
        for scheme, mask in ((self.explicit, ~stiff), (self.stiff, stiff)):   # two batches
            if mask.any():
                every = bool(mask.all())
                rows = (lambda x: x) if every else (lambda x: x[mask])
                nf, ns = scheme._advance(rhs, rows(t0), rows(t1), rows(y), rows(idx), ledger, sens)
                self.rows[scheme.name] += int(mask.sum())
                nfev, nsteps = nfev + nf, max(nsteps, ns)
        return nfev, nsteps


# ---------------------------------------------------------------------------
# Registry
# ---------------------------------------------------------------------------

INTEGRATORS: dict[str, type[Integrator]] = {
    cls.name: cls for cls in (Euler, RK4, RKF45, Dopri5, ImplicitEuler, ImplicitMidpoint, Radau3, Ros4, Auto)
}


def get_integrator(name: str, **options: Any) -> Integrator:
    """Instantiate the integrator registered as ``name`` (see :data:`INTEGRATORS`).

    ``options`` go to the constructor; all schemes accept ``steps``, ``rtol``
    and ``atol``.  Raises ValueError for an unknown name.
    """
    try:
        cls = INTEGRATORS[name]
    except KeyError:
        raise ValueError(f"unknown integrator {name!r}; available: "
                         f"{', '.join(sorted(INTEGRATORS))}") from None
    return cls(**options)
