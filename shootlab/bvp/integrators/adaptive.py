"""Embedded pairs with per-row step size control ([HNW1] sec. II.4): the base of ``dopri5`` and
``ros4``.  With the local error estimate e of an attempted step::

    err = rms(e / (atol + rtol max(|y|, |y+|))),   accept if err ≤ 1,
    h_new = h · min(max_factor, max(min_factor, safety · err^(−1/(q+1)))),

q the order of the embedded solution; initial step of [HNW1] p. 169.
"""
from __future__ import annotations

import copy
import math
from typing import ClassVar

import torch
from torch import Tensor

from .base import MAX_STEPS, NONFINITE, RHS, UNDERFLOW, Integrator, _rms, all_finite


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
    kind = "adaptive"
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

    def tolerances(self) -> tuple[float, float]:
        """(rtol, atol), the defaults 1e-8 and 1e-10 where not given."""
        return (1e-8 if self.rtol is None else self.rtol,
                1e-10 if self.atol is None else self.atol)

    def loosened(self, rtol: float | None = None) -> "AdaptiveIntegrator":
        """A copy with relative tolerance ``rtol`` (default √rtol) and atol scaled in proportion;
        itself when its own rtol is not tighter."""
        own, atol = self.tolerances()
        rtol = math.sqrt(own) if rtol is None else float(rtol)
        if rtol <= own:
            return self
        loose = copy.copy(self)
        loose.rtol, loose.atol = rtol, atol * rtol / own
        return loose

    def _initial_step(self, rhs: RHS, t0: Tensor, y0: Tensor, f0: Tensor, direction: Tensor,
                      hmax: Tensor) -> Tensor:
        """Starting step of [HNW1] p. 169 (one extra rhs call), signed."""
        rtol, atol = self.tolerances()
        y0, f0 = y0.detach(), f0.detach()
        scale = atol + rtol * y0.abs()
        d0, d1 = _rms(y0 / scale), _rms(f0 / scale)
        fallback = (d0 < 1e-5) | (d1 < 1e-5)
        h0 = torch.where(fallback, torch.full_like(d0, 1e-6), 0.01 * d0 / d1)
        h0 = torch.minimum(h0, hmax)
        f1 = rhs(t0 + direction * h0, y0 + (direction * h0)[:, None] * f0)
        d2 = _rms((f1 - f0) / scale) / h0
        dmax = torch.maximum(d1, d2)
        h1 = torch.where(dmax <= 1e-15, torch.clamp(h0 * 1e-3, min=1e-6),
                         (0.01 / dmax) ** (1.0 / (self.error_order + 1)))
        # h1 alone where h0 is the fallback 1e-6 (a zero state: the straight-line guess of
        # y'' = f with y' = 0): 100·h0 would start every interval at 1e-4 and take four steps to
        # grow to an interval of 0.01 (bratu: 4 -> 1 step per pass)
        h = torch.where(torch.isfinite(d2), torch.where(fallback, h1, torch.minimum(100 * h0, h1)), h0)
        return direction * torch.minimum(h, hmax)

    def _attempt_sensitivity(self, rhs: RHS, t: Tensor, y: Tensor, S: Tensor, h: Tensor,
                             f: tuple[Tensor, Tensor] | None
                             ) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, Tensor] | None, int]:
        """:meth:`_attempt` with the sensitivity ``S = ∂y/∂y0`` carried along (step size held
        fixed): ``(y_new, S_new, error_estimate, (f, J S) at the new point or None, nfev)``."""
        raise NotImplementedError

    def _advance(self, rhs, t0, t1, y, idx, ledger, sens=None):
        rtol, atol = self.tolerances()
        eps = torch.finfo(y.dtype).eps
        n = y.shape[-1] if sens is None else sens
        t, t_end = t0, t1
        direction = torch.sign(t1 - t0)
        hmax = (t1 - t0).abs() / self.steps
        # f at the start: for the starting step, and for the first attempt of an FSAL scheme —
        # but with sensitivities (f, J S) come from that attempt, its point among the stage
        # points of one batched Jacobian call (a call of its own cost more than the rest of a
        # one-step pass's Jacobians: bvpT1 at 101 points)
        fsal = self.fsal and sens is None
        h0 = None if ledger.h0 is None else ledger.h0[idx]
        if h0 is not None and bool((torch.isfinite(h0) & (h0 > 0)).all()):
            h = direction * torch.minimum(h0, hmax)         # the caller's (IntegrationResult.h_next)
            f, nfev = (rhs(t, y[:, :n]), 1) if fsal else (None, 0)
        else:
            f = rhs(t, y[:, :n])
            h, nfev = self._initial_step(rhs, t, y[:, :n], f, direction, hmax), 2
            f = f if fsal else None
        if ledger.h_next is None:
            ledger.h_next = torch.full(ledger.failed.shape, math.nan, dtype=t0.dtype, device=t0.device)
        # a step after a rejection may not grow: its factor is capped at 1 (a rejected step's own
        # factor is below safety < 1, so the cap need not know whether this one is accepted)
        cap = torch.full_like(t, self.max_factor)
        grow, hold, low = t.new_tensor(self.max_factor), t.new_tensor(1.0), t.new_tensor(self.min_factor)
        exponent = -1.0 / (self.error_order + 1)
        habs = h.abs()
        # |h| below 10 eps max(|t|, |t1|) is an underflow; the bound over all rows gates the test
        tiny_bound = 10 * eps * float(torch.maximum(t.abs(), t_end.abs()).max())
        nsteps = 0
        while idx.numel():
            if nsteps == self.max_steps:
                ledger.fail(idx, y, MAX_STEPS)
                break
            nsteps += 1
            remaining = t_end - t
            # within rounding of the end: take it, or a sliver of ~1e-19 would be left as a step
            last = habs * (1.0 + 1e-10) >= remaining.abs()
            wanted = habs                       # the control's step, before the end cuts it
            h = torch.where(last, remaining, h)
            if f is None and self.fsal:
                nfev += 1                       # the first stage is evaluated afresh
            if sens is None:
                y_new, err, f_new, nf = self._attempt(rhs, t, y, h, f)
            else:
                fS = None if f is None else (f[:, :n], f[:, n:].view(-1, n, n))
                y1, S1, err, fS, nf = self._attempt_sensitivity(rhs, t, y[:, :n], y[:, n:].view(-1, n, n), h, fS)
                y_new = torch.cat([y1, S1.flatten(1)], -1)
                f_new = None if fS is None else torch.cat([fS[0], fS[1].flatten(1)], -1)
            nfev += nf

            # step size control, on detached values only (the solution, not its sensitivity)
            size_new = y_new[:, :n].detach().abs()
            err = _rms(err / (atol + rtol * torch.maximum(y[:, :n].detach().abs(), size_new)))
            finite = torch.isfinite(err) & all_finite(y_new.detach())
            accept = finite & (err <= 1.0)
            raw = self.safety * err.clamp_min(1e-300).pow(exponent)     # the control's factor, unbounded
            factor = torch.where(finite, raw.clamp_min(self.min_factor).minimum(cap), low)
            cap = torch.where(accept, grow, hold)

            blown = accept & (size_new.amax(-1) > self.max_abs)
            done = accept & last & ~blown
            if done.any():
                ledger.h_next[idx[done]] = torch.maximum(wanted, (h * raw).abs())[done]
            t = torch.where(accept, torch.where(last, t_end, t + h), t)
            y = torch.where(accept[:, None], y_new, y)
            if f is not None:
                f = torch.where(accept[:, None], f_new, f)
            elif f_new is not None and bool(accept.all()):     # FSAL from here on
                f = f_new
            habs = torch.minimum((h * factor).abs(), hmax)
            h = direction * habs

            stop = done | blown
            underflow = None
            if float(habs.min()) < tiny_bound:
                underflow = (habs < 10 * eps * torch.maximum(t.abs(), t_end.abs())) & ~stop
                stop = stop | underflow
            if not stop.any():
                continue
            ledger.finish(idx[done], y[done])
            ledger.fail(idx[blown], y[blown], NONFINITE)
            if underflow is not None and underflow.any():
                nonfinite_last = (underflow & ~finite).any()
                ledger.fail(idx[underflow], y[underflow],
                            NONFINITE if nonfinite_last else UNDERFLOW)
            keep = ~stop
            idx, t, t_end, h, habs, hmax, direction, y, cap = (
                x[keep] for x in (idx, t, t_end, h, habs, hmax, direction, y, cap))
            f = f[keep] if f is not None else None
        return nfev, nsteps

