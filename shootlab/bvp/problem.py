"""The two-point boundary value problem (report eq. 3.1) and the checks on user input.

    x' = f(t, x),   t ∈ [a, b],   g_a(x(a)) = 0  (p equations),   g_b(x(b)) = 0  (n − p equations)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor

RHS = Callable[[Tensor, Tensor], Tensor]
BC = Callable[[Tensor], Tensor]


@dataclass
class BVP:
    """A TPBVP with separated boundary conditions (report eq. 3.1).

    x' = f(t, x) on [a, b], g_a(x(a)) = 0 (p equations), g_b(x(b)) = 0 (n − p equations).

    Parameters
    ----------
    rhs : callable
        ``rhs(t, x) -> dx/dt``, batched: ``x`` has shape (..., n) and ``t`` the shape
        ``x.shape[:-1]`` (one time per batch element); returns the shape of ``x``.  Write it with
        ``x[..., i]`` and ``torch.stack(..., -1)``; rows must not depend on one another.
    bc_a, bc_b : callable
        ``bc_a(x_a) -> (p,)`` and ``bc_b(x_b) -> (n − p,)``: the residuals of the boundary
        conditions at one state (n,) at a and at b.
    name : str, optional
        A label for messages.
    lower, upper : Tensor, optional
        Bounds (n,) on the state components (±inf where none) that the Newton iterates keep
        strictly inside (the default Newton's steps are shortened to stay there, as an
        interior-point method's are): e.g. a mass or a permeability > 0.
    jac : callable, optional
        ``jac(t, x) -> (f, J)``: the right-hand side's value and its Jacobian ∂f/∂x (..., n, n)
        together (scipy's ``fun_jac``), used instead of forward-mode differentiation of ``rhs``
        where the problem knows a cheaper way (:class:`shootlab.bvp.tangents.VectorField`).

    Raises
    ------
    ValueError
        If ``jac`` is given and is not callable.  The shapes are checked by
        :func:`shootlab.solve` against the grid and the guess, before any work.

    Examples
    --------
    Troesch's problem y'' = μ sinh(μ y), y(0) = 0, y(1) = 1:

    >>> mu = 5.0
    >>> prob = BVP(rhs=lambda t, x: torch.stack([x[..., 1], mu * torch.sinh(mu * x[..., 0])], -1),
    ...            bc_a=lambda xa: xa[:1], bc_b=lambda xb: xb[:1] - 1.0)
    """

    rhs: RHS
    bc_a: BC
    bc_b: BC
    name: str = "bvp"
    lower: Tensor | None = None
    upper: Tensor | None = None
    jac: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]] | None = None

    def __post_init__(self):
        if self.jac is not None and not callable(self.jac):
            raise ValueError(f"jac must be a function (t, x) -> (f, J), got {type(self.jac).__name__}")
        if self.jac is not None and getattr(self.rhs, "jacobian", None) is None:
            from .tangents import VectorField
            self.rhs = VectorField(self.rhs, self.jac)


def as_tensor(x, dtype: torch.dtype | None = None, device: torch.device | None = None,
              name: str = "input") -> Tensor:
    """Tensor or array-like -> tensor; float64 unless the input is a floating tensor already."""
    if isinstance(x, Tensor):
        if not x.is_floating_point():
            x = x.to(torch.float64)
        return x.to(dtype=dtype or x.dtype, device=device or x.device)
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a tensor or an array of numbers: {exc}") from None
    return torch.as_tensor(arr, dtype=dtype or torch.float64, device=device)


def check_grid(t: Tensor) -> None:
    if t.ndim != 1:
        raise ValueError(f"t must be a 1-D grid of shooting points, got shape {tuple(t.shape)}")
    if t.numel() < 2:
        raise ValueError("t needs at least two shooting points (a and b)")
    if not torch.isfinite(t).all():
        raise ValueError("t contains NaN or inf")
    dt = t[1:] - t[:-1]
    if (dt <= 0).any():
        i = int((dt <= 0).nonzero()[0])
        raise ValueError(f"t must be strictly increasing: t[{i}] = {float(t[i])!r} >= t[{i + 1}] = {float(t[i + 1])!r}")


def check_problem(prob: BVP, t: Tensor, x: Tensor) -> int:
    """Validate grid, guess and boundary conditions before any work; returns p = len(bc_a)."""
    if not isinstance(prob, BVP):
        raise ValueError(f"expected a shootlab.BVP, got {type(prob).__name__}")
    check_grid(t)
    m = t.numel()
    if x.ndim != 2 or x.shape[0] != m:
        raise ValueError(f"x_guess must have shape (m, n) = ({m}, n) to match t, got {tuple(x.shape)}")
    if not torch.isfinite(x).all():
        raise ValueError("x_guess contains NaN or inf")
    n = x.shape[1]
    with torch.no_grad():
        ga = torch.as_tensor(prob.bc_a(x[0])).reshape(-1)
        gb = torch.as_tensor(prob.bc_b(x[-1])).reshape(-1)
        f = prob.rhs(t, x)
    if ga.numel() + gb.numel() != n:
        raise ValueError(f"the boundary conditions give {ga.numel()} + {gb.numel()} = "
                         f"{ga.numel() + gb.numel()} equations, but the state has n = {n} components")
    if ga.numel() == 0 and gb.numel() == 0:
        raise ValueError("no boundary conditions")
    if tuple(f.shape) != tuple(x.shape):
        raise ValueError(f"rhs(t, x) must return the shape of x {tuple(x.shape)} for x of shape "
                         f"(m, n) and t of shape (m,), got {tuple(f.shape)}")
    if not torch.isfinite(f).all():
        i = int((~torch.isfinite(f)).any(-1).nonzero()[0])
        raise ValueError(f"rhs is not finite at the initial guess (shooting point {i}, t = {float(t[i])!r})")
    for name, bound, outside in (("lower", prob.lower, lambda b: x <= b), ("upper", prob.upper, lambda b: x >= b)):
        if bound is None:
            continue
        bound = as_tensor(bound, dtype=x.dtype, device=x.device, name=name)
        if bound.shape != (n,) or torch.isnan(bound).any():
            raise ValueError(f"{name} bounds must be {n} numbers (±inf where none), got shape {tuple(bound.shape)}")
        bad = outside(bound)
        if bad.any():
            k, j = (int(v) for v in bad.nonzero()[0])
            raise ValueError(f"the initial guess violates the {name} bound of component {j} at shooting point {k}: "
                             f"{float(x[k, j])!r} vs {float(bound[j])!r} (it must lie strictly inside)")
    return ga.numel()
