"""Automatic choice per row between an explicit pair (``dop853`` or ``dopri5``, [HNW1] sec. II.10,
II.5) and ``ros4`` (A-stable Rosenbrock, [HW2] sec. IV.7): a row is
stiff when its local Jacobian at the start has a decaying mode with
``max_{Re λ<0} |λ| · |t1 − t0| > stiff_limit``; the stiff rows go to ``ros4``, the others to the
explicit pair, in two batches.
"""
from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .base import RHS, Integrator
from shootlab.bvp.tangents import _value_and_jacobian
from .dop853 import Dop853
from .dopri5 import Dopri5
from .ros4 import Ros4


class Auto(Integrator):
    """Automatic choice per row: an explicit pair where the local Jacobian allows it, ``ros4``
    (A-stable Rosenbrock) only on the rows that are stiff.

    The explicit pair is ``dop853`` (order 8), or ``dopri5`` (order 5) by ``explicit="dopri5"``:
    on the BVP test set at rtol 1e-8 (``benchmarks/bvp_testset.py``) the 8th order is the faster
    of the two, with smaller errors on the linear cases and often one Newton iteration instead of
    two: its loose Jacobian pass (``jacobian_rtol``) is already about as accurate as the
    tolerance asks for.

    A row is stiff when the local Jacobian ∂f/∂y at its start (t0, y0) has a decaying mode
    whose magnitude times the row's length exceeds :attr:`stiff_limit`:
    max_{Re λ < 0} |λ| · |t1 − t0| > stiff_limit.  An explicit scheme's step is bounded by its
    stability region (on the negative real axis |hλ| ≲ 6.4 for DOP853, 3.3 for Dormand–Prince
    5(4)), so such a row would take more than about stiff_limit / 6.4 explicit steps whatever the
    tolerance; the default (5000: over 800 steps) is where ``ros4`` with its forward
    sensitivities becomes the cheaper of the two (on the BVP test set an explicit pair is still
    much the faster at max|λ|·H ≈ 600).  Growing modes do not
    count: both schemes follow them with the steps the tolerance asks for (and multiple shooting
    keeps κ₊·H small).  Rows are split once per :meth:`integrate` call (two batches, never a loop
    over rows); the decision costs one batched Jacobian and its eigenvalues (on an accelerator a
    bound on them, :attr:`spectral`).

    ``steps``, ``rtol``, ``atol`` and ``max_abs`` go to both schemes (rtol default 1e-8).
    """

    name = "auto"
    order = 4
    kind = "adaptive"
    stable = "as the explicit pair on non-stiff rows, A-stable (ros4) on stiff rows"
    description = "dop853 (or dopri5) per row, ros4 on the rows whose local Jacobian is stiff"

    @classmethod
    def stability(cls, z):
        """No single one-step function (the scheme is chosen per row from |λ|·(t1 − t0) and both
        control their steps): exp(z), which both follow to their tolerance."""
        return np.exp(z)
    adaptive = True
    sensitivities = True
    stiff_limit: float = 5000.0
    #: rows whose rate along one direction, times their length, is below stiff_limit / this
    #: are taken as non-stiff without computing their Jacobian (a directional rate can
    #: underestimate |λ|, hence the margin; a stiff row missed would only cost explicit steps)
    screen_safety: float = 100.0
    #: how the stiff rows' |λ| is found (:func:`shootlab.bvp.shooting.spectral_bounds`): ``"auto"`` the
    #: eigenvalues on the CPU, the spectral radius bound from matrix products on an accelerator
    #: (all of |λ|, growing modes too: a row can only move to ``ros4``)
    spectral: str = "auto"

    def __init__(self, steps: int = 1, rtol: float | None = None, atol: float | None = None,
                 stiff_limit: float | None = None, explicit: str = "dop853", **options: Any):
        super().__init__(steps, rtol, atol)
        if stiff_limit is not None:
            self.stiff_limit = float(stiff_limit)
        schemes = {"dopri5": Dopri5, "dop853": Dop853}
        if explicit not in schemes:
            raise ValueError(f"explicit must be one of {sorted(schemes)}, got {explicit!r}")
        self.explicit = schemes[explicit](steps, rtol, atol, **options)
        self.stiff = Ros4(steps, rtol, atol, **options)
        #: rows integrated by each scheme over this integrator's life, e.g. {"dop853": k, "ros4": k}
        self.rows = {self.explicit.name: 0, "ros4": 0}

    def loosened(self, rtol: float | None = None) -> "Auto":
        """Both schemes loosened (:meth:`AdaptiveIntegrator.loosened`); the row counts shared."""
        loose = copy.copy(self)
        loose.explicit, loose.stiff = self.explicit.loosened(rtol), self.stiff.loosened(rtol)
        return loose

    def tolerances(self) -> tuple[float, float]:
        """(rtol, atol) of both schemes."""
        return self.explicit.tolerances()

    @property
    def error_order(self) -> int:
        """The explicit pair's (its steps are the ones carried between integrations)."""
        return self.explicit.error_order

    @property
    def max_abs(self) -> float:
        return self.explicit.max_abs

    @max_abs.setter
    def max_abs(self, value: float) -> None:
        self.explicit.max_abs = self.stiff.max_abs = float(value)

    def stiff_rows(self, rhs: RHS, t0: Tensor, t1: Tensor, y0: Tensor) -> Tensor:
        """Bool mask of the rows to integrate with the stiff scheme (class docstring)."""
        from shootlab.bvp.spectrum import batched_eigvals, spectral_method, spectral_radius_bound
        length = (t1 - t0).abs()
        with torch.no_grad():
            t0, y0 = t0.detach(), y0.detach()
            # screen: the rate along one direction v, from one extra rhs call; far below the
            # limit on every row, the Jacobian (an rhs call and a reverse sweep) is not needed
            size = 1.0 + y0.abs()
            v = size * y0.new_tensor([(-1.0) ** i for i in range(y0.shape[-1])])    # |v_i| = 1 + |y_i|
            delta = 1e-7 / size.amax(-1, keepdim=True)                              # |δ v|_∞ = 1e-7
            rate = (rhs(t0, y0 + delta * v) - rhs(t0, y0)).abs().amax(-1) / 1e-7
            if bool(torch.isfinite(rate).all()) and bool((rate * length * self.screen_safety <= self.stiff_limit).all()):
                return torch.zeros_like(length, dtype=torch.bool)
            J = _value_and_jacobian(rhs, t0, y0)[1].detach()
            finite = torch.isfinite(J).flatten(-2).all(-1)
            J = torch.where(finite[:, None, None], J, torch.zeros_like(J))
            bound = J.abs().sum(-1).amax(-1) * length        # ‖J‖∞·H ≥ |λ|·H: most calls end here
            if not bool((bound > self.stiff_limit).any()):
                return torch.zeros_like(length, dtype=torch.bool)
            if spectral_method(self.spectral, J) == "bound":
                rate = spectral_radius_bound(J)     # ≥ the decaying modes' |λ|: more rows to ros4, never fewer
            else:
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

