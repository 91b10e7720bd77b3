"""The common ground of the integrators: the result, the row ledger, the autograd Jacobians and
the base classes :class:`Integrator` (with the facts every scheme declares) and
:class:`FixedStepIntegrator`.

``rhs(t, y)`` receives ``y`` of shape ``(m, n)`` and ``t`` of shape ``(m,)`` and must treat the
rows independently; rows that finish or fail are dropped from the active set.  Everything used
only for control flow (error norms, step sizes, convergence tests) is computed from detached
values.  References of the schemes: [HNW1] E. Hairer, S.P. Norsett, G. Wanner, Solving Ordinary
Differential Equations I, 2nd ed., Springer 1993; [HW2] E. Hairer, G. Wanner, Solving Ordinary
Differential Equations II, 2nd ed., Springer 1996.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, ClassVar

import torch
from torch import Tensor

from shootlab.bvp.device import accelerator_paths

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
        h_next: adaptive schemes: per row, the step size |h| the control proposed when the
            row reached t1, h·safety·err^(−1/(q+1)) without the bounds on its growth and on the
            interval's length (NaN for a failed row, None for fixed-step schemes) — the ``h0`` of
            a next integration over the same intervals, at this or (scaled by the ratio of the
            tolerances to the power 1/(q+1)) another tolerance.
    """

    y: Tensor
    failed: Tensor
    reason: str | None
    nfev: int
    nsteps: int
    S: Tensor | None = None     # ∂y(t1)/∂y0 (..., n, n) when asked for (``sensitivity=True``)
    h_next: Tensor | None = None


# ---------------------------------------------------------------------------
# Jacobians by autograd
# ---------------------------------------------------------------------------


def _lincomb(coefs: Tensor, xs: list[Tensor]) -> Tensor:
    """``sum_j coefs[..., j] * xs[j]`` as one batched product; ``coefs`` has shape
    (k,) or, for per-row coefficients, (m, k); ``xs[j]`` has shape (m, n)."""
    return (torch.stack(xs, -1) @ coefs.unsqueeze(-1)).squeeze(-1)


def _matcomb(coefs: Tensor, Ms: list[Tensor]) -> Tensor:
    """``sum_j coefs[:, j] * Ms[j]`` for matrices ``Ms[j]`` (m, n, k) and per-row ``coefs`` (m, s),
    accumulated term by term (stacking the matrices for one batched product moves ten times the
    memory)."""
    out = Ms[0] * coefs[:, 0, None, None]
    for j in range(1, len(Ms)):
        out = out.addcmul(Ms[j], coefs[:, j, None, None])
    return out


# ---------------------------------------------------------------------------
# Bookkeeping shared by all schemes
# ---------------------------------------------------------------------------

def _interval_of(t: Tensor, tq: Tensor) -> Tensor:
    """Per time of tq the index i of the interval [t_i, t_i+1] of the increasing grid t that holds
    it (the last interval for t's last point)."""
    return (torch.searchsorted(t, tq, right=True) - 1).clamp(0, t.numel() - 2)


def _rms(x: Tensor) -> Tensor:
    """Root mean square over the last dimension, detached (for control flow only)."""
    return x.detach().pow(2).mean(-1).sqrt()


def all_finite(x: Tensor) -> Tensor:
    """Whether every entry of each row (last dimension) is finite.  On large arrays by the rows'
    sums first: a sum is finite only if all its entries are (an inf or a NaN carries into it), and
    the entrywise test runs only where some sum is not (a sum of finite entries may overflow), a
    tenth of the entrywise test's time on a state packed with its sensitivity matrix; below
    65,536 entries the entrywise test alone (as fast there).  On an accelerator
    the entrywise test alone: no host synchronisation (:func:`shootlab.bvp.device.accelerator_paths`)."""
    x = x.detach()
    if x.numel() < 1 << 16 or accelerator_paths(x):
        return torch.isfinite(x).all(-1)
    ok = torch.isfinite(x.sum(-1))
    return ok if bool(ok.all()) else torch.isfinite(x).all(-1)


class _Ledger:
    """Collects the final state of every row as rows finish or fail."""

    def __init__(self, m: int, device: torch.device, h0: Tensor | None = None):
        self.indices: list[Tensor] = []
        self.values: list[Tensor] = []
        self.failed = torch.zeros(m, dtype=torch.bool, device=device)
        self.reason: str | None = None
        self.h0 = h0                 # (m,) initial |h| per row (adaptive schemes), or None
        self.h_next: Tensor | None = None     # (m,) filled by the adaptive schemes

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

    # -- the facts every registered scheme declares (the registry's table, suggest and solver
    #    read them from here) --
    name: ClassVar[str]
    #: one line for tables and stage descriptions
    description: ClassVar[str]
    #: classical order of the solution the scheme advances with
    order: ClassVar[int]
    #: step sizes chosen by an error estimate against rtol / atol (``steps`` only bounds them)
    adaptive: ClassVar[bool] = False
    #: ``"explicit"``, ``"implicit"`` (stage equations or linear systems in the stiff directions)
    #: or ``"adaptive"``: the kind of stability that limits the interval length
    kind: ClassVar[str]
    #: the linear stability property in words ("A-stable", "L-stable", "conditionally stable", ...)
    stable: ClassVar[str]
    #: forward sensitivities of the discrete scheme implemented (``integrate(..., sensitivity=True)``)
    sensitivities: ClassVar[bool] = False

    @classmethod
    def stability(cls, z):
        """Stability function ``R(z)``: one step of size h on ``y' = λ y`` maps y to R(hλ) y.

        ``z`` a complex number or a numpy array (evaluated elementwise).  For the adaptive
        schemes it is the function of one step of the underlying method at a given h."""
        raise NotImplementedError(f"{cls.__name__}: no stability function")

    def __init__(self, steps: int = 1, rtol: float | None = None, atol: float | None = None):
        if int(steps) < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        self.steps = int(steps)
        self.rtol = rtol
        self.atol = atol

    def __repr__(self) -> str:
        return f"{type(self).__name__}(steps={self.steps}, rtol={self.rtol}, atol={self.atol})"

    def loosened(self, rtol: float | None = None) -> "Integrator":
        """A copy integrating to the relative tolerance ``rtol`` (default: the square root of its
        own), for the passes that only form interval Jacobians
        (:class:`~shootlab.bvp.shooting.ShootingSystem`); a fixed-step scheme has no tolerance and
        returns itself."""
        return self

    def integrate(self, rhs: RHS, t0: Tensor | float, t1: Tensor | float, y0: Tensor,
                  sensitivity: bool = False, h0: Tensor | None = None,
                  jacobian: Tensor | None = None) -> IntegrationResult:
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
                differentiated with its step sizes held fixed (:mod:`shootlab.bvp.tangents`;
                ``y0`` is then taken as a constant).  Raises
                :class:`~shootlab.bvp.tangents.NotTransformable` for a right-hand side that
                ``torch.func`` cannot differentiate, NotImplementedError for a scheme
                without it (``sensitivities`` False).
            h0: adaptive schemes: the initial |h| per row (shape ``y0.shape[:-1]``), e.g. the
                ``h_next`` of a previous integration over the same intervals (a Newton
                iteration's next residual); default, or when any row's is not finite and
                positive: every row from the starting step of [HNW1] p. 169.  Fixed-step schemes
                ignore it.
            jacobian: schemes that solve stage equations by simplified Newton
                (``holds_jacobian``): ∂f/∂y at (t0, y0) of every row (shape ``(..., n, n)``), the
                Jacobian of the Newton matrices of all the row's steps — one evaluation per
                interval instead of one per step ([HW2] sec. IV.8: the matrix is kept while the
                iteration contracts; a row that contracts slowly gets a fresh Jacobian at its
                iterate).  The solution is that of the scheme to the Newton tolerance either way.
                Not with ``sensitivity``; other schemes ignore it.
        """
        batch_shape, n = y0.shape[:-1], y0.shape[-1]
        y = y0.reshape(-1, n)
        bad = ~all_finite(y)
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
        held = {}
        if jacobian is not None and self.holds_jacobian and sens is None:
            held = dict(held=self._held_state(jacobian.detach().reshape(-1, n, n)))
        if self._unmasked and accelerator_paths(y):
            return self._integrate_unmasked(rhs, t0, t1, y, bad, sens, batch_shape, y0.shape, **held)
        idx = torch.arange(y.shape[0], device=y.device)
        ledger = _Ledger(y.shape[0], y.device,
                         None if h0 is None else torch.as_tensor(h0, dtype=y.dtype, device=y.device).reshape(-1))

        trivial = (t1 == t0) & ~bad
        run = ~(bad | trivial)
        nfev = nsteps = 0
        if run.all():
            nfev, nsteps = self._advance(rhs, t0, t1, y, idx, ledger, sens, **held)
        else:
            ledger.fail(idx[bad], y[bad], NONFINITE)
            ledger.finish(idx[trivial], y[trivial])
            if run.any():
                nfev, nsteps = self._advance(rhs, t0[run], t1[run], y[run], idx[run], ledger, sens,
                                             **{k: v[run] for k, v in held.items()})
        out, S = ledger.collect(y), None
        if sens:
            out, S = out[:, :n], out[:, n:].reshape(*batch_shape, n, n)
        h_next = None if ledger.h_next is None else ledger.h_next.reshape(batch_shape)
        return IntegrationResult(y=out.reshape(y0.shape), failed=ledger.failed.reshape(batch_shape),
                                 reason=ledger.reason, nfev=nfev, nsteps=nsteps, S=S, h_next=h_next)

    #: :meth:`_integrate_unmasked` implemented (used on an accelerator)
    _unmasked: ClassVar[bool] = False
    #: the Newton matrices of an interval's steps can be formed from one Jacobian given to
    #: :meth:`integrate` (``jacobian=``)
    holds_jacobian: ClassVar[bool] = False

    def _held_state(self, J: Tensor):
        """What the steps of one integration share from the given Jacobians J (…, n, n)
        (``holds_jacobian`` schemes; indexable by rows)."""
        raise NotImplementedError

    def _integrate_unmasked(self, rhs: RHS, t0: Tensor, t1: Tensor, y: Tensor, bad: Tensor, sens: int | None,
                            batch_shape: torch.Size, shape: torch.Size) -> IntegrationResult:
        raise NotImplementedError

    def _advance(self, rhs: RHS, t0: Tensor, t1: Tensor, y: Tensor, idx: Tensor,
                 ledger: _Ledger, sens: int | None = None) -> tuple[int, int]:
        """Integrate the rows ``idx`` (all finite, t1 != t0) and record them in
        ``ledger``; return ``(nfev, nsteps)``.  ``sens = n``: the rows are packed
        ``[y | vec S]`` (:meth:`integrate`)."""
        raise NotImplementedError

    def dense(self, rhs: RHS, t: Tensor, s: Tensor, tq: Tensor, grid: bool = False) -> Tensor:
        """Values (k, n) at the times tq (k,) of the solution through the points s (m, n) at the
        increasing times t (m,): each integrated by :meth:`integrate` from the nearest point of t
        at or before it (a fixed-step scheme in finer steps than its own on [t_i, t_i+1]; a failed
        row frozen at its last finite state).  ``grid``: the values of the scheme's own steps where
        it has a step grid (:meth:`FixedStepIntegrator.dense`)."""
        k = _interval_of(t, tq)
        return self.integrate(rhs, t[k], tq, s[k]).y

    def sweep(self, rhs: RHS, t: Tensor, s: Tensor, tq: Tensor) -> Tensor:
        """Values (k, n) at the increasing times tq (k,) in [t_0, t_{m−1}] of the solution through
        the points s (m, n) at the times t (m,), from one pass over all intervals: interval
        [t_i, t_{i+1}] is integrated once from s_i, from each of its times of tq to the next (the
        last interval to t_{m−1} too), all intervals as one batch — as many integrations of the
        m − 1 rows as the most crowded interval holds times, instead of one row per time
        (:meth:`dense`: each time from its shooting point).  A time at a shooting point t_i gets
        s_i.  Fixed-step schemes take steps no longer than their own, (t_{i+1} − t_i)/steps, and
        end them on the times of tq (where a data spline has its knots): an explicit scheme's
        values are of :meth:`dense`'s accuracy or better (an implicit one's on stiff growing
        modes depend on the step sizes: :meth:`shootlab.bvp.shooting.ShootingSystem.sweep`); a failed
        row is frozen at its last finite state.  Memory: (Q + 1)(m − 1)·n values, Q the most
        times in one interval — O(k·n) for times spread evenly over the intervals."""
        stops, row, col = _sweep_stops(t, tq)
        y, out = s[:-1], s.new_empty(stops.shape[1], *s[:-1].shape)
        out[0] = y
        h0 = None
        for j in range(1, stops.shape[1]):
            y, h0 = self._sweep_gap(rhs, t, stops[:, j - 1], stops[:, j], y, h0)
            out[j] = y
        return out[col, row]

    def _sweep_gap(self, rhs: RHS, t: Tensor, t0: Tensor, t1: Tensor, y: Tensor, h0: Tensor | None
                   ) -> tuple[Tensor, Tensor | None]:
        """One gap of :meth:`sweep` for every row: y integrated from t0 to t1 (t1 == t0: y itself);
        returns it and the ``h0`` of the next gap (adaptive schemes: this gap's ``h_next``)."""
        ok = h0 is not None and bool(torch.isfinite(h0).all()) and bool((h0 > 0).all())
        res = self.integrate(rhs, t0, t1, y, h0=h0 if ok else None)
        return res.y, res.h_next


def _sweep_stops(t: Tensor, tq: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The stops of :meth:`Integrator.sweep`: (m − 1, Q + 1) times per interval — t_i, then its
    times of tq in order, the last one repeated to fill the row (zero-length gaps) — and for every
    time of tq its row (interval) and column."""
    if tq.numel() and bool((tq[1:] < tq[:-1]).any()):
        raise ValueError("sweep needs increasing times tq")
    row = _interval_of(t, tq)
    counts = torch.bincount(row, minlength=t.numel() - 1)
    first = torch.cumsum(counts, 0) - counts
    col = torch.arange(tq.numel(), device=tq.device) - first[row] + 1
    width = int(counts.max()) + 1 if tq.numel() else 1
    stops = torch.full((t.numel() - 1, width), -math.inf, dtype=t.dtype, device=t.device)
    stops[:, 0] = t[:-1]
    stops[row, col] = tq
    stops = torch.cummax(stops, 1).values          # the rows' last time repeated
    return stops, row, col


class FixedStepIntegrator(Integrator):
    """``steps`` equal steps ``h = (t1 - t0) / steps`` per row.

    Subclasses implement one step, ``_step(rhs, t, y, h) -> (y_new, ok, nfev)``
    with ``ok`` a bool mask (False: implicit stage equations not converged; a scheme that
    ``holds_jacobian`` takes ``held=``, the Newton state its rows share over their interval), the stability
    function at matrices (:meth:`stability_matrix`) where it has one, and
    for forward sensitivities ``_step_sensitivity(rhs, t, y, S, h) -> (y_new,
    S_new, ok, nfev)`` with ``S_new = (∂y_new/∂y) S``; ``S`` None stands for the identity (the
    first step of an interval: S_0 = I, no product with it).

    On an accelerator (:func:`shootlab.bvp.device.accelerator_paths`) every row takes every step and
    a row that fails is frozen at its last finite state (:meth:`_integrate_unmasked`) instead of
    being dropped from the batch: the same values, and one host synchronisation per integration
    instead of one per step.
    """

    _unmasked = True

    def _step(self, rhs: RHS, t: Tensor, y: Tensor, h: Tensor) -> tuple[Tensor, Tensor, int]:
        raise NotImplementedError

    @classmethod
    def stability_matrix(cls, Z: Tensor) -> Tensor:
        """The stability function at matrices, R(Z) (…, n, n) for Z = hJ (…, n, n): one step of size
        h on y' = J y + g(t), J constant, maps a perturbation δy to R(hJ) δy."""
        raise NotImplementedError(f"{cls.__name__}: no stability function at matrices")

    def linear_map(self, J: Tensor, t0: Tensor, t1: Tensor) -> Tensor:
        """R(h J)^steps (…, n, n), h = (t1 − t0)/steps: ∂y(t1)/∂y(t0) of the scheme's ``steps`` steps on
        y' = J y + g(t) with J (…, n, n) constant over the interval [t0, t1] (…) — the interval
        Jacobian of the linearisation at the interval's start (exact for a linear system with a
        constant Jacobian)."""
        h = ((t1 - t0) / self.steps).to(J.dtype)[..., None, None]
        return torch.linalg.matrix_power(self.stability_matrix(h * J), self.steps)

    def _step_sensitivity(self, rhs: RHS, t: Tensor, y: Tensor, S: Tensor, h: Tensor
                          ) -> tuple[Tensor, Tensor, Tensor, int]:
        raise NotImplementedError

    def dense(self, rhs: RHS, t: Tensor, s: Tensor, tq: Tensor, grid: bool = False) -> Tensor:
        """:meth:`Integrator.dense`; with ``grid`` and every time of tq on the scheme's own step
        grid (to 1e-7 of a step), the discrete solution there: every interval [t_i, t_i+1]
        integrated once from s_i with its ``steps`` steps kept (those of :meth:`integrate`: the
        values the shooting residual is made of).  Where the samples of a record are the step grid
        (the rig's: 10 RK4 steps per interval of 10 samples) this costs one integration of the
        m − 1 intervals instead of one of every sample, and the values differ from the default's
        by the scheme's error at its step (the default integrates each time in finer steps).
        Times off the grid: the default for all (a mix of the two would not be one solution; the
        mixture's 2 midpoint steps per 8 samples: its J moves 600-fold between the two)."""
        on = self.on_grid(t, tq) if grid else None
        if on is None:
            return super().dense(rhs, t, s, tq)
        j, i = on
        return self.grid_values(rhs, t[:-1], t[1:], s[:-1])[j, i]

    def on_grid(self, t: Tensor, tq: Tensor) -> tuple[Tensor, Tensor] | None:
        """(step j, interval i) of every time of tq on the step grid of the intervals of t (to 1e-7
        of a step), or None when one of them is off it."""
        t0, h = t[:-1], (t[1:] - t[:-1]) / self.steps
        i = _interval_of(t, tq)
        j = torch.floor((tq - t0[i]) / h[i] + 1e-7).clamp(0, self.steps).long()
        if ((tq - (t0[i] + j * h[i])).abs() > 1e-7 * h[i]).any():
            return None
        return j, i

    def grid_values(self, rhs: RHS, t0: Tensor, t1: Tensor, y0: Tensor) -> Tensor:
        """The rows y0 (k, n) integrated from t0 to t1 (k,) with every step kept: (steps + 1, k, n),
        by the loop of :meth:`_advance` (the same points bit for bit); a failed row frozen at its
        last finite state."""
        h = (t1 - t0) / self.steps
        y, values = y0, [y0]
        alive = torch.ones(y.shape[0], dtype=torch.bool, device=y.device)
        for k in range(self.steps):
            y_new, ok, _ = self._step(rhs, t0 + k * h, y, h)
            alive = alive & ok & all_finite(y_new)
            y = torch.where(alive[:, None], y_new, y)
            values.append(y)
        return torch.stack(values)

    def _sweep_gap(self, rhs: RHS, t: Tensor, t0: Tensor, t1: Tensor, y: Tensor, h0: Tensor | None
                   ) -> tuple[Tensor, None]:
        """One gap of :meth:`Integrator.sweep`: every row's gap in the fewest equal steps that are no
        longer than the scheme's own step on the row's interval (a zero gap: no step)."""
        own = (t[1:] - t[:-1]) / self.steps          # row i is the interval [t_i, t_{i+1}]
        gap = t1 - t0
        count = max(1, int(torch.ceil(gap / own - 1e-9).max()))
        h = gap / count
        still = h == 0
        for k in range(count):
            y_new, ok, _ = self._step(rhs, t0 + k * h, y, h)
            y = torch.where((still | ~(ok & all_finite(y_new)))[:, None], y, y_new)
        return y, None
    def _integrate_unmasked(self, rhs, t0, t1, y, bad, sens, batch_shape, shape, held=None):
        """:meth:`Integrator.integrate` with every row through every step: a row whose step fails
        (stage equations not converged, a non-finite value) keeps its last finite state and a
        failure code 2k + 2 (not converged at step k) or 2k + 3 (non-finite at step k; 1: non-finite
        start) — the first failure in the order of the masked loop names ``reason``."""
        h = (t1 - t0) / self.steps
        start, trivial = y, (t1 == t0) & ~bad
        y = torch.where(bad[:, None], torch.zeros_like(y), y)     # a non-finite start is stepped as 0 and restored
        alive = ~bad
        code = bad.to(torch.int64)
        nfev = 0
        for k in range(self.steps):
            if sens is None:
                y_new, ok, nf = self._step(rhs, t0 + k * h, y, h, **({} if held is None else dict(held=held)))
            else:
                n = sens
                S = None if k == 0 else y[:, n:].view(-1, n, n)
                y1, S1, ok, nf = self._step_sensitivity(rhs, t0 + k * h, y[:, :n], S, h)
                y_new = torch.cat([y1, S1.reshape(-1, n * n)], -1)
            nfev += nf
            keep = ok & all_finite(y_new)
            code = torch.where(alive & ~keep, torch.where(ok, 2 * k + 3, 2 * k + 2), code)
            alive = alive & keep
            y = torch.where(alive[:, None], y_new, y)
        y = torch.where((trivial | bad)[:, None], start, y)         # t1 == t0: y0 itself
        code = torch.where(trivial, torch.zeros_like(code), code)
        failed = code > 0
        reason = None
        if bool(failed.any()):                              # the one host synchronisation
            first = int(torch.where(failed, code, torch.full_like(code, 1 << 62)).min())
            reason = NONFINITE if first % 2 else NO_CONVERGENCE
        S = None
        if sens:
            y, S = y[:, :sens], y[:, sens:].reshape(*batch_shape, sens, sens)
        return IntegrationResult(y=y.reshape(shape), failed=failed.reshape(batch_shape), reason=reason,
                                 nfev=nfev, nsteps=self.steps, S=S, h_next=None)

    def _advance(self, rhs, t0, t1, y, idx, ledger, sens=None, held=None):
        h = (t1 - t0) / self.steps
        nfev = nsteps = 0
        for k in range(self.steps):
            if sens is None:
                y_new, ok, nf = self._step(rhs, t0 + k * h, y, h, **({} if held is None else dict(held=held)))
            else:
                n = sens
                S = None if k == 0 else y[:, n:].view(-1, n, n)         # S_0 = I (packed in integrate)
                y1, S1, ok, nf = self._step_sensitivity(rhs, t0 + k * h, y[:, :n], S, h)
                y_new = torch.cat([y1, S1.reshape(-1, n * n)], -1)
            nfev, nsteps = nfev + nf, nsteps + 1
            finite = all_finite(y_new)
            for mask, reason in ((~ok, NO_CONVERGENCE), (ok & ~finite, NONFINITE)):
                ledger.fail(idx[mask], y[mask], reason)  # frozen at the last finite state
            keep = ok & finite
            if not keep.all():
                t0, h, idx, y_new = t0[keep], h[keep], idx[keep], y_new[keep]
                held = None if held is None else held[keep]
            y = y_new
            if not idx.numel():
                break
        ledger.finish(idx, y)
        return nfev, nsteps

