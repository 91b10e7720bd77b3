"""Optimal estimation: a model in augmented state form → the TPBVP of its optimality conditions.

Identification model (report eqs. 2.4–2.5), x = states and constant parameters, ζ = input
estimates, ε and ξ residuals::

    x' = A x + B ζ + ε
    E z_m(t) = f(x, t) + F(x, t) ζ + ξ          (model equations as zero pseudo-measurements
                                                 and the real measurement equations)

    J = ½ (x(a) − q_a)ᵀ W_a (x(a) − q_a) + ½ ∫ₐᵇ (εᵀ W ε + ξᵀ V ξ) dt                (eq. 2.6)

Stationarity of J gives the TPBVP (eq. 2.7) in (x, λ), 2·dim(x) equations::

    ζ  = (FᵀVF)⁻¹ [Bᵀλ + FᵀV (E z_m − f)]
    ε  = W⁻¹ λ,     ξ = E z_m − f − F ζ
    x' = A x + B ζ + W⁻¹ λ
    λ' = −Aᵀ λ − Cᵀ V ξ,       C = ∂f/∂x + ∂(F ζ)/∂x  (ζ held fixed; by autograd)
    λ(a) − W_a (x(a) − q_a) = 0,     λ(b) = 0
"""
from __future__ import annotations

import contextlib
import inspect
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .data import Interpolant, Measurements
from .problem import BVP, as_tensor
from .solver import ShootingResult, solve
from .tangents import outside_transforms


@dataclass
class IdentificationModel:
    """A model in augmented state form (module docstring).

    states, parameters  names; x = states + parameters (parameters have θ' = ε_θ)
    inputs              names of ζ
    equations           names of the rows of f and F
    channels            row name → data channel for the measurement rows; the other rows are
                        model equations (zero pseudo-measurements)
    A, B                constant (nx, nx), (nx, nζ); parameter rows are zero
    f(x, t), F(x, t)    batched torch functions: x (..., nx), t (...) → (..., r), (..., r, nζ)
    W, V, W_a           weights: a vector (diagonal), a matrix, or a function of t returning either
    q_a                 prior on x(a) (zeros by default; only components with W_a > 0 matter)
    prior               default initial parameter values
    given               the channels known when the model is *simulated* (its inputs, e.g. the
                        motor command); with the model-equation rows they determine ζ
    initial_states      (data, t) → (m, n_states) initial approximation of the states at t
    settings            defaults for estimate and the CLI: "points", "solve" (options of
                        shootlab.solve), optionally "weight_continuation": levels at which the
                        diagonal V is capped in stages estimated first, each warm-starting the
                        next (report §4.2), and
                        "initial_parameters": (data, params, t) →
                        params or None, called with the initial parameter values before the
                        initial approximation is built (raise ValueError for bad values, or
                        return refined ones)
    units               optional unit per name — "t", states, parameters, inputs, channels and
                        equation rows (the unit of the row's residual ξ) — for labels and
                        summaries, e.g. {"t": "s", "s": "m", "u": "N", "m": "kg"}; "-" for a
                        dimensionless quantity, no entry for an unknown unit
    bounds              optional (low, high) per state or parameter name that the Newton
                        iterates keep strictly inside, e.g. {"m": (0, inf)} for a positive mass
                        (IPOPT users give the same bounds)
    """

    name: str
    states: list[str]
    parameters: list[str]
    inputs: list[str]
    equations: list[str]
    channels: dict[str, str]
    A: Tensor
    B: Tensor
    f: Callable[[Tensor, Tensor], Tensor]
    F: Callable[[Tensor, Tensor], Tensor]
    W: object
    V: object
    W_a: object = None
    q_a: object = None
    prior: dict[str, float] = field(default_factory=dict)
    given: list[str] = field(default_factory=list)
    initial_states: Callable[[Measurements, Tensor], Tensor] | None = None
    settings: dict = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)

    def __post_init__(self):
        self.A = as_tensor(self.A, name="A")
        self.B = as_tensor(self.B, name="B")
        nx, nz, r = self.nx, len(self.inputs), len(self.equations)
        if tuple(self.A.shape) != (nx, nx):
            raise ValueError(f"A must be ({nx}, {nx}) for {nx} states + parameters, got {tuple(self.A.shape)}")
        if tuple(self.B.shape) != (nx, nz):
            raise ValueError(f"B must be ({nx}, {nz}), got {tuple(self.B.shape)}")
        unknown = set(self.channels) - set(self.equations)
        if unknown:
            raise ValueError(f"channels name rows {sorted(unknown)} that are not among the equations {self.equations}")
        bad_given = set(self.given) - set(self.channels.values())
        if bad_given:
            raise ValueError(f"given channels {sorted(bad_given)} are not measured channels")
        self.W_a = torch.zeros(nx, dtype=torch.float64) if self.W_a is None else self.W_a
        self.q_a = torch.zeros(nx, dtype=torch.float64) if self.q_a is None else as_tensor(self.q_a, name="q_a")
        for name, lohi in self.bounds.items():
            if name not in self.names:
                raise ValueError(f"bounds for {name!r}, which is not a state or parameter of {self.names}")
            if len(lohi) != 2 or not float(lohi[0]) < float(lohi[1]):
                raise ValueError(f"bounds for {name!r} must be (low, high) with low < high, got {lohi!r}")
        _check_weight(self.W, nx, "W", positive=True)
        _check_weight(self.V, r, "V", positive=False)
        _check_weight(self.W_a, nx, "W_a", positive=False)

    @property
    def names(self) -> list[str]:
        return list(self.states) + list(self.parameters)

    @property
    def nx(self) -> int:
        return len(self.states) + len(self.parameters)

    @property
    def measured(self) -> list[str]:
        return list(dict.fromkeys(self.channels.values()))

    def label(self, name: str) -> str:
        """'name [unit]' from :attr:`units` ('name' when the unit is not declared)."""
        unit = self.units.get(name)
        return f"{name} [{unit}]" if unit else name


# -- weights -----------------------------------------------------------------------------
def _check_weight(w, size: int, name: str, positive: bool) -> None:
    if callable(w):
        return
    w = as_tensor(w, name=name)
    if w.ndim == 1:
        if w.numel() != size:
            raise ValueError(f"{name} must have {size} diagonal entries, got {w.numel()}")
        if not torch.isfinite(w).all() or (w <= 0 if positive else w < 0).any():
            raise ValueError(f"{name} must be {'positive' if positive else 'non-negative'} (got {w.tolist()})")
    elif w.ndim == 2:
        if tuple(w.shape) != (size, size):
            raise ValueError(f"{name} must be ({size}, {size}), got {tuple(w.shape)}")
        ev = torch.linalg.eigvalsh(0.5 * (w + w.T))
        if (ev <= 0 if positive else ev < -1e-12 * ev.abs().max()).any():
            raise ValueError(f"{name} must be symmetric {'positive' if positive else 'non-negative'} definite")
    else:
        raise ValueError(f"{name} must be a vector (diagonal) or a matrix, got shape {tuple(w.shape)}")


def _weight(w, t: Tensor, size: int, like: Tensor) -> tuple[Tensor, bool]:
    """The weight at times t and whether it is diagonal: a vector (or a function returning
    (…, size)) is a diagonal, kept as its (…, size) entries; otherwise (…, size, size).  Constant
    weights are returned unexpanded (they broadcast)."""
    const = not callable(w)
    w = torch.as_tensor(w if const else w(t), dtype=like.dtype, device=like.device)
    diagonal = w.ndim == 1 if const else w.ndim == t.ndim + 1
    if w.shape[-1] != size or (not diagonal and w.shape[-2] != size):
        raise ValueError(f"a weight has shape {tuple(w.shape)}, expected (..., {size}) or (..., {size}, {size})")
    return w, diagonal


def _weight_matrix(w, t: Tensor, size: int, like: Tensor) -> Tensor:
    """(…, size, size) weight at times t; a vector (or a function returning (…, size)) is a diagonal."""
    w, diagonal = _weight(w, t, size, like)
    if diagonal:
        w = torch.diag_embed(w)
    return w.expand(*t.shape, size, size)


def _apply(w: Tensor, diagonal: bool, v: Tensor) -> Tensor:
    """w v for a weight from :func:`_weight` and vectors v (…, size)."""
    return w * v if diagonal else (w @ v.unsqueeze(-1)).squeeze(-1)


# -- the TPBVP ---------------------------------------------------------------------------
class EstimationProblem:
    """The TPBVP of eq. 2.7 for a model and data; X = [x, λ].

    The right-hand side (:meth:`rhs`) composes with ``torch.func`` transforms (``jvp``,
    ``vmap``), so that the shooting code takes its Jacobians by forward mode (forward over the
    reverse-mode product of the costate equation); diagonal weights stay vectors."""

    #: distinct time grids whose interpolated measurements are kept (:meth:`measurements`)
    CACHE = 32

    def __init__(self, model: IdentificationModel, data: Measurements, dtype=torch.float64, device=None):
        self.model, self.data = model, data
        self.nx = model.nx
        rows = model.equations
        self.meas_rows = [i for i, r in enumerate(rows) if r in model.channels]
        self.interp = Interpolant(data, [model.channels[rows[i]] for i in self.meas_rows], dtype, device)
        opts = dict(dtype=dtype, device=device)
        self.A, self.B = model.A.to(**opts), model.B.to(**opts)
        self.W_a = _weight_matrix(model.W_a, torch.zeros((), **opts), self.nx, self.A)
        self.q_a = model.q_a.to(**opts)
        self.r = len(rows)
        self._cache: dict[tuple, tuple[Tensor, Tensor, Tensor]] = {}
        self._fcols: Tensor | None = None          # components of x that F depends on (_F_columns)
        # W⁻¹ of a constant weight once (ε = W⁻¹ λ); a diagonal as the vector of reciprocals
        self._W_inv = None
        if not callable(model.W):
            w, diagonal = _weight(model.W, torch.zeros((), **opts), self.nx, self.A)
            self._W_inv = (1.0 / w, True) if diagonal else (torch.linalg.inv(w), False)

    def measurements(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """E z_m(t) (…, r) and the row mask (…, r): zero where a sample is missing.  The values
        of the last ``CACHE`` time grids are kept: the integrators visit the same stage times at
        every Newton iteration."""
        plain = not (t.requires_grad or torch._C._functorch.is_functorch_wrapped_tensor(t))  # else: ∂/∂t
        key = (tuple(t.shape), t.dtype, t.device, tuple(t.reshape(-1).tolist())) if plain and t.numel() <= 1 << 16 else None
        hit = self._cache.get(key) if key is not None else None
        if hit is not None:
            return hit[0], hit[1]
        with outside_transforms() if key is not None else contextlib.nullcontext():
            if self.meas_rows:
                z = self.interp.values(t)                           # (…, c) → scattered into (…, r)
                rows = torch.as_tensor(self.meas_rows, device=z.device)
                e = torch.zeros(len(self.meas_rows), self.r, dtype=z.dtype, device=z.device)
                e[torch.arange(len(self.meas_rows)), rows] = 1.0
                mask = 1.0 - (1.0 - self.interp.mask(t.detach())) @ e
                z = z @ e
            else:
                z, mask = t.new_zeros(*t.shape, self.r), t.new_ones(*t.shape, self.r)
        if key is not None:
            if len(self._cache) >= self.CACHE:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = (z, mask, t)
        return z, mask

    def weights(self, t: Tensor, like: Tensor) -> tuple[Tensor, Tensor]:
        """W (…, nx, nx) and V (…, r, r) at t, as matrices (for summaries)."""
        W = _weight_matrix(self.model.W, t, self.nx, like)
        V = _weight_matrix(self.model.V, t, self.r, like)
        return W, V

    def _solve_parts(self, t: Tensor, X: Tensor) -> dict[str, Tensor]:
        """ζ, ε, ξ, x', λ' at (t, X) — eq. 2.7, written for forward mode:

        * ζ solves the normal equations M ζ = Bᵀλ + FᵀV(E z_m − f), M = FᵀVF.  M is factorised
          on values without derivatives and ζ = ζ̄ + M⁻¹ (Bᵀλ + FᵀV ξ̄), ξ̄ = E z_m − f − F ζ̄, with
          ζ̄ = M⁻¹(…) on values: the correction is zero to rounding (one step of iterative
          refinement), and its derivative is the exact first derivative of ζ (implicit function
          theorem on the normal equations) — at the cost of matrix–vector products per tangent,
          where differentiating M = FᵀVF itself would cost a matrix product per tangent;
        * Cᵀ V ξ with ζ held fixed is one vector–Jacobian product of x ↦ (f, F) with the
          cotangents (Vξ, Vξ ζᵀ): ``torch.func.vjp``, which composes with jvp / vmap;
        * diagonal weights stay vectors.
        """
        m = self.model
        x, lam = X[..., :self.nx], X[..., self.nx:]
        z, mask = self.measurements(t)
        V, v_diag = _weight(m.V, t, self.r, X)
        V = V * mask if v_diag else V * mask.unsqueeze(-1) * mask.unsqueeze(-2)
        if (X.requires_grad or z.requires_grad or t.requires_grad      # z: derivatives in the data (uncertainty)
                or torch._C._functorch.peek_interpreter_stack() is not None):
            (f, F), pullback = torch.func.vjp(lambda xx: (m.f(xx, t), m.F(xx, t)), x)
        else:       # plain values (the residual F): the same product by autograd, without the transform's overhead
            with torch.enable_grad():
                xr = x.detach().requires_grad_(True)
                f_r, F_r = m.f(xr, t), m.F(xr, t)
            f, F = f_r.detach(), F_r.detach()

            def pullback(cot: tuple[Tensor, Tensor]) -> tuple[Tensor]:
                g, = torch.autograd.grad((f_r, F_r), xr, grad_outputs=cot, allow_unused=True)
                return (torch.zeros_like(xr) if g is None else g),
        Fd, fd, Bl = F.detach(), f.detach(), (lam @ self.B)
        normal = _NormalEquations(Fd, V, v_diag)
        rhs = Bl.detach() + _apply(V, v_diag, z - fd).unsqueeze(-2).matmul(Fd).squeeze(-2)
        zeta_bar = normal.solve(rhs)
        xi_bar = z - f - (F @ zeta_bar.unsqueeze(-1)).squeeze(-1)
        res = Bl + _apply(V, v_diag, xi_bar).unsqueeze(-2).matmul(F).squeeze(-2)        # Bᵀλ + FᵀVξ̄
        zeta = zeta_bar + normal.solve(res)
        # a singular FᵀVF at some iterate (e.g. a mass passing through 0) becomes a non-finite
        # value, which the integrator reports and the line search steps back from
        zeta = zeta.masked_fill(~normal.regular[..., None], math.nan)
        xi = z - f - (F @ zeta.unsqueeze(-1)).squeeze(-1)
        if self._W_inv is not None:
            eps = _apply(*self._W_inv, lam)
        else:
            W, w_diag = _weight(m.W, t, self.nx, X)
            eps = lam / W if w_diag else torch.linalg.solve(W, lam.unsqueeze(-1)).squeeze(-1)
        xdot = x @ self.A.T + zeta @ self.B.T + eps
        Vxi = _apply(V, v_diag, xi)
        CtVxi, = pullback((Vxi, Vxi.unsqueeze(-1) * zeta.unsqueeze(-2)))          # Cᵀ V ξ, ζ fixed
        lamdot = -lam @ self.A - CtVxi
        return dict(zeta=zeta, eps=eps, xi=xi, xdot=xdot, lamdot=lamdot, F=F, V=V, v_diag=v_diag, normal=normal)

    def parts(self, t: Tensor, X: Tensor) -> dict[str, Tensor]:
        """ζ, ε, ξ, x', λ' at (t, X) — eq. 2.7 — and the weights W, V (masked) and FᵀVF as
        matrices (for summaries and checks; :meth:`rhs` does without them)."""
        p = self._solve_parts(t, X)
        W, _ = self.weights(t, X)
        V = torch.diag_embed(p["V"]).expand(*t.shape, self.r, self.r) if p["v_diag"] else p["V"]
        F = p.pop("F")
        for k in ("v_diag", "normal"):
            p.pop(k)
        return dict(p, W=W, V=V, FVF=F.transpose(-1, -2) @ V @ F)

    def rhs(self, t: Tensor, X: Tensor) -> Tensor:
        p = self._solve_parts(t, X)
        return torch.cat([p["xdot"], p["lamdot"]], -1)

    # -- the Jacobian of eq. 2.7, assembled ------------------------------------------------
    def jacobian(self, t: Tensor, X: Tensor) -> tuple[Tensor, Tensor]:
        """``rhs(t, X)`` (m, 2nx) and its Jacobian (m, 2nx, 2nx), assembled from the model's own
        derivatives instead of differentiating the whole of eq. 2.7 (docs/design.md §1, "The
        Jacobian of eq. 2.7, assembled").

        With P = (FᵀVF)⁻¹, u = Vξ and, at the current ζ and u held fixed,

            C = ∂(f + Fζ)/∂x (r, nx),   T = ∂(Fᵀu)/∂x (nζ, nx),   Q = ∂²[uᵀ(f + Fζ)]/∂x² (nx, nx)

        the derivatives of ζ, ξ and of the two halves of eq. 2.7 are

            ∂ζ/∂x = P (T − FᵀV C),   ∂ζ/∂λ = P Bᵀ,   ∂ξ/∂· = −C [x only] − F ∂ζ/∂·
            ∂x'/∂x = A + B ∂ζ/∂x,    ∂x'/∂λ = B P Bᵀ + W⁻¹
            ∂λ'/∂x = −Q − Tᵀ ∂ζ/∂x − (VC)ᵀ ∂ξ/∂x,    ∂λ'/∂λ = −Aᵀ − Tᵀ ∂ζ/∂λ − (VC)ᵀ ∂ξ/∂λ

        C, T and Q are forward-mode derivatives of f and F alone, F only along the components
        of x it depends on (found by probing, :meth:`_F_columns`: for the mixture, only K), so
        that no dense (r, nζ) tangent per direction of X is ever formed; the rest is batched
        matrix algebra, O(n³) per row.  Raises :class:`~shootlab.tangents.NotTransformable`
        for a model that torch.func cannot differentiate."""
        from .tangents import NotTransformable
        # compact copies: X is often a view into a larger buffer (the integrators pack [y | vec S]),
        # and forward-mode tangents take the size of the primal's whole storage (measured at
        # n = 200: 6.9 GB for one Jacobian instead of 0.7 GB)
        t, X = t.detach().contiguous(), X.detach().contiguous()
        if X.ndim != 2:
            f, J = self.jacobian(t.reshape(-1), X.reshape(-1, X.shape[-1]))
            return f.view(X.shape), J.view(*X.shape, X.shape[-1])
        nx, md = self.nx, self.model
        p = self._solve_parts(t, X)     # not under no_grad: the measurements it caches may carry ∂/∂data
        p = {k: (v.detach() if isinstance(v, Tensor) else v) for k, v in p.items()}
        x, zeta, F, V, vd = X[:, :nx].contiguous(), p["zeta"], p["F"], p["V"], p["v_diag"]
        u = _apply(V, vd, p["xi"])
        try:
            cols = self._F_columns(t, x)
            Df = _directional(lambda xx: md.f(xx, t), x, None)                       # (m, r, nx)
            DF = _directional(lambda xx: md.F(xx, t), x, cols)                       # (m, r, nζ, c)
            Qf = _directional(lambda xx: _pull(md.f, xx, t, u), x, None)             # (m, nx, nx)
            QF = _directional(lambda xx: _pull(md.F, xx, t, u[..., :, None] * zeta[..., None, :]), x, cols)
        except (RuntimeError, NotImplementedError, TypeError, ValueError, AttributeError) as exc:
            raise NotTransformable(str(exc)) from exc
        C, T, Q = Df.clone(), X.new_zeros(X.shape[0], zeta.shape[-1], nx), Qf.clone()
        C[..., cols] += torch.einsum("mrzc,mz->mrc", DF, zeta)
        T[..., cols] = torch.einsum("mrzc,mr->mzc", DF, u)
        Q[..., cols] += QF
        VC = V[..., None] * C if vd else V.transpose(-1, -2) @ C
        Ft = F.transpose(-1, -2)
        normal = p["normal"]
        Z_x = normal.solve(T - Ft @ VC)                                              # ∂ζ/∂x
        Z_l = normal.solve(self.B.T.expand(X.shape[0], *self.B.T.shape))             # ∂ζ/∂λ
        Xi_x, Xi_l = -C - F @ Z_x, -(F @ Z_l)
        W_inv = self._W_inv_matrix(t, X)
        Tt, VCt = T.transpose(-1, -2), VC.transpose(-1, -2)
        J = torch.cat([torch.cat([self.A + self.B @ Z_x, self.B @ Z_l + W_inv], -1),
                       torch.cat([-Q - Tt @ Z_x - VCt @ Xi_x, -self.A.T - Tt @ Z_l - VCt @ Xi_l], -1)], -2)
        return torch.cat([p["xdot"], p["lamdot"]], -1), J

    def _W_inv_matrix(self, t: Tensor, like: Tensor) -> Tensor:
        if self._W_inv is not None:
            w, diagonal = self._W_inv
            return torch.diag_embed(w) if diagonal else w
        W, diagonal = _weight(self.model.W, t, self.nx, like)
        return torch.diag_embed(1.0 / W) if diagonal else torch.linalg.inv(W)

    #: from this many equations 2·nx on, the integrators take the assembled :meth:`jacobian`;
    #: below, one reverse sweep through the rhs is cheaper (its fixed cost of some 25 small
    #: operations dominates; measured at m = 201: n = 10 mixture 46 ms vs 17 ms, n = 16 equal,
    #: n = 20 32 vs 73 ms, n = 44 0.11 vs 0.68 s)
    ASSEMBLED_MIN_N = 16

    #: relative size of the random probes of :meth:`_F_columns`
    PROBE = 1e-3

    def _F_columns(self, t: Tensor, x: Tensor) -> Tensor:
        """Indices of the components of x on which the model's F depends.  Found once by the
        derivatives of F along every component at three rows of the first batch, each moved by a
        random relative 1e-3 (an accidental zero derivative at the probe is then of probability
        zero); a non-finite derivative counts as a dependence.  Every later call checks the other
        components along one random direction and widens the set where F turns out to depend on
        them after all (a law that switches on in some region)."""
        if self._fcols is None:
            gen = torch.Generator().manual_seed(0)
            rows = torch.unique(torch.tensor([0, x.shape[0] // 2, x.shape[0] - 1]))
            xp, tp = x[rows], t[rows]
            xp = xp + self.PROBE * (1 + xp.abs()) * torch.randn(xp.shape, generator=gen, dtype=xp.dtype).to(xp.device)
            DF = _directional(lambda xx: self.model.F(xx, tp), xp, None)
            self._fcols = _depends(DF).nonzero().flatten().to(x.device)
            self._fcheck = torch.Generator().manual_seed(1)
        rest = torch.ones(self.nx, dtype=torch.bool)
        rest[self._fcols.cpu()] = False
        if rest.any():
            v = torch.randn(self.nx, generator=self._fcheck, dtype=x.dtype).to(x.device) * rest.to(x.device)
            dF = torch.func.jvp(lambda xx: self.model.F(xx, t), (x,), (v.expand_as(x),))[1]
            if not torch.isfinite(dF).all() or (dF != 0).any():         # F depends on more components
                widened = _directional(lambda xx: self.model.F(xx, t), x, rest.nonzero().flatten().to(x.device))
                more = rest.nonzero().flatten()[_depends(widened).cpu()]
                self._fcols = torch.sort(torch.cat([self._fcols, more.to(x.device)]))[0]
        return self._fcols

    def bc_a(self, Xa: Tensor) -> Tensor:
        x, lam = Xa[:self.nx], Xa[self.nx:]
        return lam - self.W_a @ (x - self.q_a)

    def bc_b(self, Xb: Tensor) -> Tensor:
        return Xb[self.nx:]

    def bvp(self) -> BVP:
        """The TPBVP in X = [x, λ], with the model's bounds on x (none on λ)."""
        lower = torch.full((2 * self.nx,), -math.inf, dtype=self.A.dtype, device=self.A.device)
        upper = torch.full_like(lower, math.inf)
        for name, (lo, hi) in self.model.bounds.items():
            j = self.model.names.index(name)
            lower[j], upper[j] = float(lo), float(hi)
        jac = self.jacobian if 2 * self.nx >= self.ASSEMBLED_MIN_N else None
        return BVP(self.rhs, self.bc_a, self.bc_b, name=f"estimation[{self.model.name}]", jac=jac,
                   lower=lower if self.model.bounds else None, upper=upper if self.model.bounds else None)

    #: FᵀVF with equilibrated columns (the units of ζ dropped) counts as singular below this
    #: reciprocal condition: ζ would have fewer than about 6 correct digits (the normal
    #: equations are solved by QR of V^½F, whose condition is the square root of this one's)
    RCOND = 1e-20

    def check_regular(self, t: Tensor, X: Tensor) -> None:
        """Clear error when FᵀVF is singular along the initial approximation: checked at the
        shooting points and at the midpoint of every sampling interval (missing samples)."""
        ts = torch.as_tensor(self.data.t, dtype=t.dtype, device=t.device)
        ts = ts[(ts >= t[0]) & (ts <= t[-1])]
        tq, order = torch.sort(torch.cat([t, 0.5 * (ts[1:] + ts[:-1])]))
        x = torch.stack([torch.as_tensor(np.interp(tq.numpy(), t.numpy(), X[:, j].numpy()))
                         for j in range(self.nx)], -1).to(X)
        with torch.no_grad():
            _, mask = self.measurements(tq)
            _, V = self.weights(tq, x)
            V = V * mask.unsqueeze(-1) * mask.unsqueeze(-2)
            F = self.model.F(x, tq)
            FVF = F.transpose(-1, -2) @ V @ F
            d = torch.diagonal(FVF, dim1=-2, dim2=-1).clamp_min(1e-300).rsqrt()
            sv = torch.linalg.svdvals(d[..., :, None] * FVF * d[..., None, :])       # columns equilibrated
        ratio = sv[..., -1] / sv[..., 0].clamp_min(1e-300)
        bad = (~torch.isfinite(ratio)) | (ratio < self.RCOND)
        if bad.any():
            i = int(bad.nonzero()[0])
            raise ValueError(
                f"FᵀVF is singular at t = {float(tq[i]):.6g} (reciprocal condition {float(ratio[i]):.2e}): "
                f"the inputs ζ = {self.model.inputs} are not all determined by the weighted equations "
                f"{self.model.equations}; give every input a row with positive weight in V (a missing "
                f"sample of a channel that determines an input also does this)")


class _NormalEquations:
    """Solves with M = FᵀVF (…, nζ, nζ), factorised on plain values.

    The columns of F are equilibrated first (D = diag of the column norms' reciprocals in the
    V-norm: units of the inputs ζ drop out).  For a diagonal V the factor is the QR decomposition
    of G = V^½ F D, so that M⁻¹ b = D R⁻¹ R⁻ᵀ D b never forms M and has the conditioning of G, the
    square root of M's (the 48-element mixture: cond M 8e14, cond of D M D 3e10, cond G 2e5);
    otherwise the LU decomposition of D M D.  ``regular`` marks the rows where the factor is
    usable (:attr:`RCOND`: the reciprocal condition of G estimated from R's diagonal, or an LU
    pivot, above 1e-15)."""

    RCOND = 1e-15

    def __init__(self, F: Tensor, V: Tensor, diagonal: bool):
        self.diagonal = diagonal
        if diagonal:
            G = V.clamp_min(0).sqrt()[..., None] * F
            self.d = 1.0 / torch.linalg.vector_norm(G, dim=-2).clamp_min(1e-300)
            self.R = torch.linalg.qr(G * self.d[..., None, :], mode="r")[1]
            r = torch.diagonal(self.R, dim1=-2, dim2=-1).abs()
            ratio = r.amin(-1) / r.amax(-1).clamp_min(1e-300)
        else:
            M = F.transpose(-1, -2) @ V @ F
            self.d = torch.diagonal(M, dim1=-2, dim2=-1).clamp_min(1e-300).rsqrt()
            self.lu, self.piv, info = torch.linalg.lu_factor_ex(self.d[..., :, None] * M * self.d[..., None, :])
            u = torch.diagonal(self.lu, dim1=-2, dim2=-1).abs()
            ratio = torch.where(info == 0, u.amin(-1) / u.amax(-1).clamp_min(1e-300), torch.zeros_like(u[..., 0]))
        self.regular = torch.isfinite(ratio) & (ratio > self.RCOND)

    def solve(self, b: Tensor) -> Tensor:
        """M⁻¹ b for b (…, nζ) or (…, nζ, k)."""
        vec = b.dim() == self.d.dim()
        B = (b.unsqueeze(-1) if vec else b) * self.d[..., :, None]
        if self.diagonal:
            Rt = self.R.transpose(-1, -2)
            y = torch.linalg.solve_triangular(self.R, torch.linalg.solve_triangular(Rt, B, upper=False), upper=True)
        else:
            y = torch.linalg.lu_solve(self.lu, self.piv, B)
        y = y * self.d[..., :, None]
        return y.squeeze(-1) if vec else y


def _depends(D: Tensor) -> Tensor:
    """Per direction (last axis of D (…, k)): is any derivative non-zero or non-finite?"""
    return ((D != 0) | ~torch.isfinite(D)).flatten(0, -2).any(0)


def _directional(fn: Callable[[Tensor], Tensor], x: Tensor, cols: Tensor | None) -> Tensor:
    """Derivatives of a row-wise function ``fn`` of x (m, nx) along the unit vectors of the
    components ``cols`` (all for None): (m, *out, len(cols)), by forward mode vectorised over the
    directions (rows are independent, so one jvp per direction serves all rows)."""
    nx = x.shape[-1]
    eye = torch.eye(nx, dtype=x.dtype, device=x.device)
    dirs = eye if cols is None else eye[cols]
    if dirs.shape[0] == 0:
        out = fn(x)
        return out.new_zeros(*out.shape, 0)
    along = torch.func.vmap(lambda v: torch.func.jvp(fn, (x,), (v.expand_as(x),))[1])
    return along(dirs).movedim(0, -1)


def _pull(g: Callable[[Tensor, Tensor], Tensor], x: Tensor, t: Tensor, cot: Tensor) -> Tensor:
    """(∂g/∂x)ᵀ cot row by row: the gradient of cotᵀ g(x, t) with cot held fixed."""
    return torch.func.vjp(lambda xx: g(xx, t), x)[1](cot)[0]


# -- initial approximation helpers ---------------------------------------------------------
def central_difference(values: Tensor, t: Tensor) -> Tensor:
    """Derivative of samples (K, …) on a grid t (K,) by central differences (one-sided at the ends)."""
    return torch.gradient(values, spacing=(t,), dim=0, edge_order=2)[0]


def smoothed(values: Tensor, t: Tensor, deriv: int = 1, window: int = 11, order: int = 3) -> Tensor:
    """Noisy samples (K, …) smoothed (deriv=0) or differentiated (deriv=1) by a Savitzky–Golay
    filter (scipy.signal) on a uniform grid; plain values / central differences where the grid
    is irregular or shorter than the window.  Missing samples (NaN) are filled by linear
    interpolation first.  For initial approximations (report §3.4: derivatives from data)."""
    from scipy.signal import savgol_filter

    v = values.detach().cpu().numpy().reshape(values.shape[0], -1).copy()
    tn = t.detach().cpu().numpy()
    for j in range(v.shape[1]):
        ok = ~np.isnan(v[:, j])
        if not ok.all():
            v[:, j] = np.interp(tn, tn[ok], v[ok, j])
    dt = np.diff(tn)
    if tn.size < window or np.abs(dt - dt.mean()).max() > 1e-6 * abs(dt.mean()):
        d = np.gradient(v, tn, axis=0, edge_order=2) if deriv else v
    else:
        d = savgol_filter(v, window, order, deriv=deriv, delta=float(dt.mean()), axis=0)
    return torch.as_tensor(d.reshape(values.shape), dtype=values.dtype, device=values.device)


def measured_states(model: IdentificationModel, data: Measurements, t: Tensor) -> Tensor:
    """States that are measured channels taken from the data at t, the rest zero."""
    ip = Interpolant(data, [s for s in model.states if s in data.channels], t.dtype, t.device)
    out = t.new_zeros(t.numel(), len(model.states))
    vals = ip.values(t) if ip.names else None
    for j, name in enumerate(ip.names):
        out[:, model.states.index(name)] = vals[:, j]
    return out


# -- estimation ----------------------------------------------------------------------------
@dataclass
class EstimationResult:
    """Outcome of :func:`estimate`."""

    success: bool
    message: str
    parameters: dict[str, float]
    J: float
    t: Tensor                       # data sample times inside [a, b]
    x: dict[str, Tensor]            # smoothed states and parameter trajectories at t
    zeta: dict[str, Tensor]
    eps: dict[str, Tensor]          # ε per state/parameter
    xi: dict[str, Tensor]           # ξ per equation row
    shooting: ShootingResult
    problem: EstimationProblem
    seconds: float
    points: int
    _uncertainty: object = field(default=None, repr=False)

    @property
    def iterations(self) -> int:
        return self.shooting.iterations

    @property
    def uncertainty(self):
        """Linearised covariance of the parameters (:func:`shootlab.uncertainty.parameter_covariance`:
        Cov θ̂ = Σ_c σ̂_c² G_c G_cᵀ, G_c = dθ̂/dz_c), computed on first use; ``None`` for a
        failed estimate or when the Newton matrix at the solution is singular."""
        if self._uncertainty is None and self.success:
            from .linalg import SingularJacobianError
            from .uncertainty import parameter_covariance
            try:
                self._uncertainty = parameter_covariance(self)
            except (SingularJacobianError, RuntimeError):
                self._uncertainty = False
        return self._uncertainty or None

    @property
    def standard_errors(self) -> dict[str, float]:
        """Standard error of every parameter (NaN when not available, see :attr:`uncertainty`)."""
        u = self.uncertainty
        return u.standard_errors if u is not None else {p: float("nan") for p in self.parameters}

    @property
    def covariance(self) -> np.ndarray:
        """(p, p) covariance of the parameters, order ``problem.model.parameters`` (NaN when not available)."""
        u = self.uncertainty
        return u.covariance if u is not None else np.full((len(self.parameters),) * 2, np.nan)

    @property
    def correlation(self) -> np.ndarray:
        """(p, p) correlation matrix of the parameters (NaN when not available)."""
        u = self.uncertainty
        return u.correlation if u is not None else np.full((len(self.parameters),) * 2, np.nan)

    def simulate(self, data=None, parameters: Mapping[str, float] | None = None,
                 initial_state: Sequence[float] | None = None) -> dict[str, np.ndarray]:
        """Free-run prediction of the measured channels with θ̂ (or ``parameters``).

        ``data``: measurements holding at least the model's ``given`` channels (default: the
        identification data, starting from the estimated state x̂(a)).  On other data the
        states start from ``initial_state`` if given (e.g. at rest), else from the model's
        initial approximation; ζ follows from the model equations and the given channels.
        """
        if data is None and initial_state is None:
            initial_state = [float(self.x[name][0]) for name in self.problem.model.states]
        return simulate(self.problem.model, data if data is not None else self.problem.data,
                        dict(self.parameters, **(parameters or {})), initial_state)


def initial_approximation(model: IdentificationModel, data: Measurements, t: Tensor,
                          initial: Mapping[str, float] | None = None,
                          log: Callable[[str], None] | None = None) -> Tensor:
    """(m, 2 nx): states from the data (model.initial_states), parameters from the prior
    overridden by ``initial``, costates λ = 0 (the report's choice).  ``log`` (progress lines)
    goes to the model's ``initial_parameters`` hook if it takes a ``log`` argument."""
    params = dict(model.prior)
    for k, v in (initial or {}).items():
        if k not in model.parameters:
            raise ValueError(f"unknown parameter {k!r} for model {model.name!r}; it has {model.parameters}")
        params[k] = float(v)
    missing = [p for p in model.parameters if p not in params]
    if missing:
        raise ValueError(f"no initial value for parameter(s) {missing}")
    prepare = model.settings.get("initial_parameters")
    if prepare is not None:     # the model's own check (ValueError) or refinement of the values
        extra = {"log": log} if log is not None and "log" in inspect.signature(prepare).parameters else {}
        params = dict(prepare(data, dict(params), t, **extra) or params)
    states = model.initial_states(data, t) if model.initial_states else measured_states(model, data, t)
    theta = torch.tensor([params[p] for p in model.parameters], dtype=t.dtype, device=t.device)
    X = torch.cat([states, theta.expand(t.numel(), -1), t.new_zeros(t.numel(), model.nx)], -1)
    return X


def warm_start(model: IdentificationModel, previous: EstimationResult, t: Tensor, X0: Tensor) -> Tensor:
    """Initial approximation from a previous estimate (another model, weights or grid): every
    state, parameter and costate that the two models share by name is taken from ``previous``
    at t; the rest stays as in ``X0``.  This is the report's remedy for weights that are hard to
    start from: solve with easier ones, then restart from that solution (§4.2)."""
    old = previous.problem.model
    Xp = previous.shooting.sol(t.clamp(previous.shooting.t[0], previous.shooting.t[-1]))
    X0 = X0.clone()
    for j, name in enumerate(model.names):
        if name in old.names:
            i = old.names.index(name)
            X0[:, j], X0[:, model.nx + j] = Xp[:, i], Xp[:, old.nx + i]
    return X0


def estimate(model: IdentificationModel | str, data, n_points: int | None = None, initial: Mapping[str, float] | None = None,
             interval: tuple[float, float] | None = None, start: EstimationResult | None = None,
             **solve_options) -> EstimationResult:
    """Estimate states, inputs and parameters of ``model`` (or a built-in name, e.g. ``"msd"``) from
    ``data`` by multiple shooting on the TPBVP of eq. 2.7, with ``n_points`` equidistant shooting
    points on ``interval`` (default: the data's time range).  ``start``: warm start from a previous estimate (:func:`warm_start`);
    ``initial`` then overrides the parameters it names.  ``solve_options`` go to
    :func:`shootlab.solve`, over the model's defaults ``model.settings["solve"]``; ``n_points``
    defaults to ``model.settings["points"]`` (else 101)."""
    if isinstance(model, str):
        from .models import resolve_model
        model = resolve_model(model)
    solve_options = {**model.settings.get("solve", {}), **solve_options}
    n_points = n_points if n_points is not None else model.settings.get("points", 101)
    data = Measurements.coerce(data)
    stages = _weight_stages(model)
    if stages and start is None:        # continuation in the weights (report §4.2), each stage warm
        start = continue_in_weights(stages, data, n_points, initial, interval, solve_options)
        if not start.success:
            return start
        initial = None
    a, b = interval if interval is not None else (float(data.t[0]), float(data.t[-1]))
    if not b > a:
        raise ValueError(f"empty interval [{a}, {b}]")
    data.require(model.measured, a, b)
    if int(n_points) < 2:
        raise ValueError(f"n_points must be at least 2, got {n_points}")
    data.require_samples(model, a, b)
    prob = EstimationProblem(model, data)
    t = torch.linspace(a, b, int(n_points), dtype=torch.float64)
    X0 = initial_approximation(model, data, t, initial, log=print if solve_options.get("verbose") else None)
    if solve_options.get("verbose") and model.settings.get("initial_parameters") is not None and start is None:
        given = dict(model.prior, **{k: float(v) for k, v in (initial or {}).items()})
        used = {p: float(X0[0, model.names.index(p)]) for p in model.parameters}
        if used != given:
            print("initial parameters refined by the model: "
                  + ", ".join(f"{p} {given[p]:.6g} -> {used[p]:.6g}" for p in used), flush=True)
    if start is not None:
        X0 = warm_start(model, start, t, X0)
        for k, v in (initial or {}).items():
            X0[:, model.names.index(k)] = float(v)
    prob.check_regular(t, X0)
    clock = time.perf_counter()
    res = solve(prob.bvp(), t, X0, **solve_options)
    return _summarise(prob, res, a, b, time.perf_counter() - clock)


def _weight_stages(model: IdentificationModel) -> list[IdentificationModel]:
    """The easier models of ``settings["weight_continuation"]`` (levels L₁ < L₂ < …): the model with
    every entry of its constant diagonal V capped at each level below its largest entry."""
    levels = model.settings.get("weight_continuation")
    if not levels or callable(model.V) or as_tensor(model.V, name="V").ndim != 1:
        return []
    V = as_tensor(model.V, name="V").tolist()
    settings = {k: v for k, v in model.settings.items() if k != "weight_continuation"}
    return [replace(model, V=[min(v, float(lv)) for v in V], settings=settings)
            for lv in sorted(levels) if float(lv) < max(V)]


def continue_in_weights(stages: Sequence[IdentificationModel], data, n_points: int | None,
                        initial: Mapping[str, float] | None, interval, solve_options: dict) -> EstimationResult:
    """Estimate the easier models ``stages`` in turn, each from the previous solution: the report's
    remedy for weights that are hard to start from (§4.2; the diagnosis's weight-continuation
    estimator runs its stages here too).  The last stage's result; a failed
    stage is returned at once, its message naming the stage."""
    prev = None
    for i, stage in enumerate(stages):
        res = estimate(stage, data, n_points, initial=initial if prev is None else None, interval=interval,
                       start=prev, **solve_options)
        if solve_options.get("verbose"):
            print(f"-- weight continuation stage {i + 1}/{len(stages)}: {res.message}", flush=True)
        if not res.success:
            res.message = f"weight continuation stage {i + 1}/{len(stages)}: {res.message}"
            return res
        prev = res
    return prev


def _summarise(prob: EstimationProblem, res: ShootingResult, a: float, b: float, seconds: float) -> EstimationResult:
    m = prob.model
    ts = torch.as_tensor(prob.data.t, dtype=torch.float64)
    ts = ts[(ts >= a) & (ts <= b)]
    X = res.sol(ts)
    with torch.no_grad():
        p = prob.parts(ts, X)
    x = X[:, :m.nx]
    # parameters from the shooting-point values (finite even when a failed run's re-integration is not)
    theta, tk = res.x[:, len(m.states):m.nx], res.t
    params = {name: float(torch.trapezoid(theta[:, j], tk) / (tk[-1] - tk[0])) for j, name in enumerate(m.parameters)}
    integrand = (p["eps"] * (p["W"] @ p["eps"].unsqueeze(-1)).squeeze(-1)).sum(-1) \
        + (p["xi"] * (p["V"] @ p["xi"].unsqueeze(-1)).squeeze(-1)).sum(-1)
    d0 = X[0, :m.nx] - prob.q_a
    J = 0.5 * float(d0 @ prob.W_a @ d0) + 0.5 * float(torch.trapezoid(integrand, ts))
    return EstimationResult(
        success=res.success, message=res.message, parameters=params, J=J, t=ts,
        x={n: x[:, j] for j, n in enumerate(m.names)},
        zeta={n: p["zeta"][:, j] for j, n in enumerate(m.inputs)},
        eps={n: p["eps"][:, j] for j, n in enumerate(m.names)},
        xi={n: p["xi"][:, j] for j, n in enumerate(m.equations)},
        shooting=res, problem=prob, seconds=seconds, points=res.t.numel())


# -- free-run simulation ----------------------------------------------------------------------
def simulate(model: IdentificationModel, data, parameters: Mapping[str, float],
             initial_state: Sequence[float] | None = None, t=None) -> dict[str, np.ndarray]:
    """Free-run simulation x' = A x + B ζ(x, t), ε = 0, ζ from the model-equation rows and the
    rows of the ``given`` channels (least squares if over-determined); returns the predicted
    measured channels (the measurement rows f + F ζ) and the states at the sample times."""
    from scipy.integrate import solve_ivp

    data = Measurements.coerce(data)
    data.require(model.given, float(data.t[0]), float(data.t[-1]))
    rows = model.equations
    sim_rows = [i for i, r in enumerate(rows) if r not in model.channels or model.channels[r] in model.given]
    out_rows = [i for i, r in enumerate(rows) if r in model.channels and model.channels[r] not in model.given]
    given_rows = [i for i in sim_rows if rows[i] in model.channels]
    interp = Interpolant(data, [model.channels[rows[i]] for i in given_rows])
    theta = torch.tensor([float(parameters[p]) for p in model.parameters], dtype=torch.float64)
    ts = torch.as_tensor(data.t if t is None else np.asarray(t, dtype=np.float64), dtype=torch.float64)
    if initial_state is None:
        s0 = ((model.initial_states(data, ts[:1]) if model.initial_states else measured_states(model, data, ts[:1])))[0]
    else:
        s0 = torch.as_tensor(np.asarray(initial_state, dtype=np.float64))
    A, B = model.A.to(torch.float64), model.B.to(torch.float64)

    def zeta_of(x: Tensor, tt: Tensor):
        f, F = model.f(x, tt), model.F(x, tt)
        z = torch.zeros_like(f)
        if given_rows:
            z[..., given_rows] = interp.values(tt)
        Fs, rs = F[..., sim_rows, :], (z - f)[..., sim_rows]
        zeta = torch.linalg.lstsq(Fs, rs.unsqueeze(-1)).solution.squeeze(-1)
        return zeta, f, F

    def fun(tt, s):
        x = torch.cat([torch.as_tensor(s), theta])
        tt = torch.tensor(tt, dtype=torch.float64)
        zeta, _, _ = zeta_of(x, tt)
        return (A @ x + B @ zeta)[:len(model.states)].numpy()

    sol = solve_ivp(fun, (float(ts[0]), float(ts[-1])), s0.numpy(), method="LSODA", t_eval=ts.numpy(),
                    rtol=1e-8, atol=1e-10)
    if not sol.success:
        raise RuntimeError(f"free-run simulation failed: {sol.message}")
    S = torch.as_tensor(sol.y.T)
    X = torch.cat([S, theta.expand(S.shape[0], -1)], -1)
    zeta, f, F = zeta_of(X, ts[:S.shape[0]])
    pred = f + (F @ zeta.unsqueeze(-1)).squeeze(-1)
    out = {"t": ts.numpy()[:S.shape[0]]}
    for i in out_rows:
        out[model.channels[rows[i]]] = pred[:, i].numpy()
    for j, name in enumerate(model.states):
        out[f"state:{name}"] = S[:, j].numpy()
    return out
