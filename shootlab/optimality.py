"""The TPBVP of the optimality conditions (report eq. 2.7) for a model and data.

With an :class:`~shootlab.estimation.IdentificationModel` (x' = A x + B ζ + ε, E z_m = f + F ζ + ξ,
weights W, V, W_a) and measurements, :class:`EstimationProblem` is the right-hand side in
X = [x, λ] (docs/design.md §1)::

    ζ  = (FᵀVF)⁻¹ [Bᵀλ + FᵀV (E z_m − f)],   ε = W⁻¹ λ,   ξ = E z_m − f − F ζ
    x' = A x + B ζ + W⁻¹ λ
    λ' = −Aᵀ λ − Cᵀ V ξ,       C = ∂f/∂x + ∂(F ζ)/∂x  (ζ held fixed)
    λ(a) − W_a (x(a) − q_a) = 0,     λ(b) = 0

with its boundary conditions, its Jacobian assembled from the model's derivatives
(:meth:`EstimationProblem.jacobian`), the normal equations solved by QR of the
column-equilibrated V^½F (:class:`~shootlab.normal_equations.NormalEquations`) and the rank
test of FᵀVF.  The weights are vectors (diagonal), matrices, or functions of t returning either.
"""
from __future__ import annotations

import contextlib
import math
import time
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch
from torch import Tensor

from .data import Interpolant, Measurements
from .normal_equations import NormalEquations, hamiltonian_blocks_lu
from .problem import BVP, as_tensor
from .tangents import outside_transforms

if TYPE_CHECKING:
    from .estimation import IdentificationModel

__all__ = ["EstimationProblem"]

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
#: :meth:`EstimationProblem.jacobian`'s choice per model and batch size (at most 256 kept)
_WAYS: dict[tuple, str] = {}


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
        self._parts: list[list] = []        # [t, X, _solve_once(t, X), bytes kept], oldest first
        #: how :meth:`jacobian` takes the Jacobian: "assembled", "reverse", or None (not chosen yet)
        self.way: str | None = None
        self._fcols: Tensor | None = None          # components of x that F depends on (_F_derivatives)
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

    #: bytes of :meth:`_solve_parts` results (and :meth:`jacobian`'s) kept for plain (t, X)
    #: values: a Newton iteration integrates the residual and then, at the same iterate, the
    #: Jacobian — an explicit scheme visits the same stage points bitwise, whose factorised normal
    #: equations are then reused, and an implicit one builds its Newton matrices at the same points
    PARTS_CACHE_BYTES = 512 << 20
    #: and at most this many points (each lookup compares the values with every kept point)
    PARTS_CACHE_ENTRIES = 64

    def _solve_parts(self, t: Tensor, X: Tensor) -> dict[str, Tensor]:
        """:meth:`_solve_once`, or the kept result for the same plain values of (t, X)."""
        # kept only where the assembled Jacobian can use them (it is offered from ASSEMBLED_MIN_N
        # equations on, and not used once the reverse sweeps were found faster)
        keep = 2 * self.nx >= self.ASSEMBLED_MIN_N and self.way != "reverse"
        plain = keep and not (X.requires_grad or t.requires_grad or torch._C._functorch.is_functorch_wrapped_tensor(X)
                              or torch._C._functorch.is_functorch_wrapped_tensor(t))
        if plain:
            for tk, Xk, p, _ in self._parts:
                if tk.shape == t.shape and Xk.shape == X.shape and torch.equal(Xk, X) and torch.equal(tk, t):
                    return p
        p = self._solve_once(t, X)
        if plain and not p["xi"].requires_grad:          # not with ∂/∂data (uncertainty)
            size = sum(v.numel() * v.element_size() for v in (p["F"], p["normal"].factor_storage()))
            self._parts.append([t.detach().clone(), X.detach().clone(), p, size])
            self._trim()
        return p

    def _trim(self) -> None:
        while len(self._parts) > 1 and (sum(e[3] for e in self._parts) > self.PARTS_CACHE_BYTES
                                        or len(self._parts) > self.PARTS_CACHE_ENTRIES):
            self._parts.pop(0)

    def forget(self) -> None:
        """Drop the kept :meth:`_solve_parts` results (timing a fresh iterate)."""
        self._parts.clear()

    def _solve_once(self, t: Tensor, X: Tensor) -> dict[str, Tensor]:
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
            (f, F), pullback = torch.func.vjp(lambda xx: m.f_and_F(xx, t), x)
        else:       # plain values (the residual F): the same product by autograd, without the transform's overhead
            with torch.enable_grad():
                xr = x.detach().requires_grad_(True)
                f_r, F_r = m.f_and_F(xr, t)
            f, F = f_r.detach(), F_r.detach()

            def pullback(cot: tuple[Tensor, Tensor]) -> tuple[Tensor]:
                g, = torch.autograd.grad((f_r, F_r), xr, grad_outputs=cot, allow_unused=True)
                return (torch.zeros_like(xr) if g is None else g),
        Fd, fd, Bl = F.detach(), f.detach(), (lam @ self.B)
        normal = NormalEquations(Fd, V, v_diag)
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
        p = dict(self._solve_parts(t, X))
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
        """``rhs(t, X)`` (m, 2nx) and its Jacobian (m, 2nx, 2nx): assembled from the model's own
        derivatives (:meth:`_assembled`) or by reverse sweeps through the whole right-hand side,
        whichever was faster on the first batch of at least :attr:`CHOOSE_ROWS` rows (each timed
        on its second call, after torch's first-use costs; from :attr:`CHOOSE_BELOW_N` equations
        on, assembled).  The assembled form wins on large or
        structured models (the 20-element mixture, n = 44: 0.11 s against 0.68 s); on small
        models of many cheap operations the second derivatives of forward over reverse mode run
        through torch's Python decompositions, and the sweeps win (the flexible rig, n = 20:
        24 ms against 8 ms).  The Jacobian met at a point kept with its normal equations
        (:meth:`_solve_parts`) is kept with them.  Raises
        :class:`~shootlab.tangents.NotTransformable` for a model that torch.func cannot
        differentiate."""
        from .tangents import reverse_jacobian
        # compact copies: X is often a view into a larger buffer (the integrators pack [y | vec S]),
        # and forward-mode tangents take the size of the primal's whole storage (measured at
        # n = 200: 6.9 GB for one Jacobian instead of 0.7 GB)
        t, X = t.detach().contiguous(), X.detach().contiguous()
        if X.ndim != 2:
            f, J = self.jacobian(t.reshape(-1), X.reshape(-1, X.shape[-1]))
            return f.view(X.shape), J.view(*X.shape, X.shape[-1])
        if self.way == "reverse":       # the sweeps evaluate the rhs themselves
            return reverse_jacobian(self.rhs, t, X)
        kept = self._solve_parts(t, X)  # not under no_grad: the measurements it caches may carry ∂/∂data
        if "jacobian" in kept:          # an implicit scheme's Newton matrix at a point met before
            return kept["jacobian"]
        if self.way is None and 2 * self.nx >= self.CHOOSE_BELOW_N:
            self.way = "assembled"
        elif self.way is None and X.shape[0] >= self.CHOOSE_ROWS:
            md = self.model
            key = (md.name, tuple(md.names), tuple(md.inputs), tuple(md.equations), X.shape[0])
            if key not in _WAYS:
                if len(_WAYS) >= 256:
                    _WAYS.clear()
                _WAYS[key] = self._faster_way(t, X, kept)
            self.way = _WAYS[key]
            if self.way == "reverse":
                return reverse_jacobian(self.rhs, t, X)
        out = self._assembled(t, X, kept)
        entry = next((e for e in self._parts if e[2] is kept), None)
        if entry is not None:           # kept with its point's normal equations
            kept["jacobian"] = out
            entry[3] += out[1].numel() * out[1].element_size()
            self._trim()
        return out

    #: rows of the batch on which :meth:`jacobian` times its two ways once
    CHOOSE_ROWS = 16
    #: from this many equations on the assembled Jacobian is taken without timing the sweeps, whose
    #: cost grows with n² per row (the 20-element mixture, n = 44: 0.11 s against 0.68 s per call,
    #: where timing them would cost the command 1.4 s)
    CHOOSE_BELOW_N = 32

    #: the sweeps are taken only when faster than the assembled Jacobian by this factor: the two
    #: agree to rounding, not bit for bit, and a choice that flips with the machine's load between
    #: two runs can change a marginal Newton path (measured: the 12-element mixture with a filter
    #: resistance converged in one run and stalled in the next); beyond the margin the choice is
    #: stable (the flexible rig's declared model, n = 20: 8 ms against 24 ms)
    REVERSE_MARGIN = 2.0

    def _faster_way(self, t: Tensor, X: Tensor, kept: dict) -> str:
        """``"assembled"`` or ``"reverse"``: ``"reverse"`` when its time on this batch is below the
        assembled one's by :attr:`REVERSE_MARGIN`, each timed on its second call.  Remembered per
        model (its name and the names of its unknowns, inputs and rows) and batch size in
        :data:`_WAYS`: the diagnosis estimates the same extended models again and again, and the
        timing cost 8 % of its time."""
        from .tangents import reverse_jacobian

        def seconds(fn: Callable[[], object]) -> float:
            fn()
            start = time.perf_counter()
            fn()
            return time.perf_counter() - start
        assembled = seconds(lambda: self._assembled(t, X, kept))
        reverse = seconds(lambda: reverse_jacobian(self.rhs, t, X))
        return "reverse" if self.REVERSE_MARGIN * reverse < assembled else "assembled"

    def _assembled(self, t: Tensor, X: Tensor, kept: dict) -> tuple[Tensor, Tensor]:
        """The Jacobian of eq. 2.7 assembled from the model's own derivatives instead of
        differentiating the whole right-hand side (docs/design.md §1, "The Jacobian of eq. 2.7,
        assembled"), at the point whose :meth:`_solve_parts` are ``kept``.

        With P = (FᵀVF)⁻¹, u = Vξ and, at the current ζ and u held fixed,

            C = ∂(f + Fζ)/∂x (r, nx),   T = ∂(Fᵀu)/∂x (nζ, nx),   Q = ∂²[uᵀ(f + Fζ)]/∂x² (nx, nx)

        and S = T − FᵀVC, the derivatives of ζ and of the two halves of eq. 2.7 are

            ∂ζ/∂x = P S,   ∂ζ/∂λ = P Bᵀ,   ∂x'/∂x = A + B P S,   ∂x'/∂λ = B P Bᵀ + W⁻¹
            ∂λ'/∂x = −Q + CᵀVC − Sᵀ P S,   ∂λ'/∂λ = −(∂x'/∂x)ᵀ        (Hamiltonian structure)

        C, T and Q are forward-mode derivatives of f and F alone, F only along the components
        of x it depends on (found by probing, :meth:`_F_derivatives`: for the mixture, only K), so
        that no dense (r, nζ) tangent per direction of X is ever formed; the three blocks come
        from the normal equations' factor
        (:meth:`~shootlab.normal_equations.NormalEquations.hamiltonian_blocks`)."""
        from .tangents import NotTransformable
        nx, md = self.nx, self.model
        p = {k: (v.detach() if isinstance(v, Tensor) else v) for k, v in kept.items()}
        x, zeta, F, V, vd = X[:, :nx].contiguous(), p["zeta"], p["F"], p["V"], p["v_diag"]
        u = _apply(V, vd, p["xi"])
        try:
            eye = torch.eye(nx, dtype=x.dtype, device=x.device)
            Df, Qf = _along(lambda xx: _value_and_pull(md.f, xx, t, u), x, eye)       # (m, r, nx), (m, nx, nx)
            cols, DF, QF = self._F_derivatives(t, x, u[..., :, None] * zeta[..., None, :])   # (m, r, nζ, c), (m, nx, c)
        except (RuntimeError, NotImplementedError, TypeError, ValueError, AttributeError) as exc:
            raise NotTransformable(str(exc)) from exc
        C, Q = Df.clone(), Qf.clone()
        C[..., cols] += torch.einsum("mrzc,mz->mrc", DF, zeta)
        Tc = torch.einsum("mrzc,mr->mzc", DF, u)                                     # T, its columns cols
        Q[..., cols] += QF
        normal = p["normal"]
        if normal.diagonal:
            BPS, BPB, G21 = normal.hamiltonian_blocks(V, C, Tc, cols, self.B)
        else:
            BPS, BPB, G21 = hamiltonian_blocks_lu(normal, F, V, C, Tc, cols, self.B)
        J = X.new_empty(X.shape[0], 2 * nx, 2 * nx)
        J11 = torch.add(BPS, self.A, out=J[:, :nx, :nx])
        torch.add(BPB, self._W_inv_matrix(t, X), out=J[:, :nx, nx:])
        torch.sub(G21, Q, out=J[:, nx:, :nx])
        torch.neg(J11.transpose(-1, -2), out=J[:, nx:, nx:])
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

    #: relative size of the random probes of :meth:`_F_derivatives`
    PROBE = 1e-3

    def _F_derivatives(self, t: Tensor, x: Tensor, cot: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The components ``cols`` of x on which the model's F depends, ∂F/∂x along them
        (m, r, nζ, c) and ∂/∂x[(∂F/∂x)ᵀ cot] along them (m, nx, c), by one forward-mode call.

        ``cols`` is found once by the derivatives of F along every component at three rows of the
        first batch, each moved by a random relative 1e-3 (an accidental zero derivative at the
        probe is then of probability zero); a non-finite derivative counts as a dependence.  Every
        later call also differentiates along one random direction in the other components (one
        more lane of the same call) and widens ``cols`` where F turns out to depend on them after
        all (a law that switches on in some region)."""
        F = self.model.F
        if self._fcols is None:
            gen = torch.Generator().manual_seed(0)
            rows = torch.unique(torch.tensor([0, x.shape[0] // 2, x.shape[0] - 1]))
            xp, tp = x[rows], t[rows]
            xp = xp + self.PROBE * (1 + xp.abs()) * torch.randn(xp.shape, generator=gen, dtype=xp.dtype).to(xp.device)
            DF, = _along(lambda xx: (F(xx, tp),), xp, torch.eye(self.nx, dtype=x.dtype, device=x.device))
            self._fcols = _depends(DF).nonzero().flatten().to(x.device)
            self._fcheck = torch.Generator().manual_seed(1)
        cols = self._fcols
        rest = torch.ones(self.nx, dtype=torch.bool)
        rest[cols.cpu()] = False
        dirs = torch.eye(self.nx, dtype=x.dtype, device=x.device)[cols]
        if rest.any():
            v = torch.randn(self.nx, generator=self._fcheck, dtype=x.dtype).to(x.device) * rest.to(x.device)
            dirs = torch.cat([dirs, v[None]])
        DF, QF = _along(lambda xx: _value_and_pull(F, xx, t, cot), x, dirs)
        if rest.any():
            if _depends(DF[..., -1:]).any():                     # F depends on more components
                widened, = _along(lambda xx: (F(xx, t),), x, torch.eye(self.nx, dtype=x.dtype, device=x.device)[rest])
                more = rest.nonzero().flatten()[_depends(widened).cpu()]
                self._fcols = torch.sort(torch.cat([cols, more.to(x.device)]))[0]
                return self._F_derivatives(t, x, cot)
            DF, QF = DF[..., :-1], QF[..., :-1]
        return cols, DF, QF

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


def _depends(D: Tensor) -> Tensor:
    """Per direction (last axis of D (…, k)): is any derivative non-zero or non-finite?"""
    return ~(D.abs().flatten(0, -2).sum(0) == 0)          # a NaN or ∞ sum is a dependence


def _along(fn: Callable[[Tensor], tuple[Tensor, ...]], x: Tensor, dirs: Tensor) -> tuple[Tensor, ...]:
    """Derivatives of a row-wise function ``fn`` of x (m, nx), returning a tuple, along the
    directions ``dirs`` (k, nx): one (m, *out, k) per output, by forward mode vectorised over the
    directions (rows are independent, so one jvp per direction serves all rows)."""
    if dirs.shape[0] == 0:
        return tuple(out.new_zeros(*out.shape, 0) for out in fn(x))
    along = torch.func.vmap(lambda v: torch.func.jvp(fn, (x,), (v.expand_as(x),))[1])
    return tuple(d.movedim(0, -1) for d in along(dirs))


def _value_and_pull(g: Callable[[Tensor, Tensor], Tensor], x: Tensor, t: Tensor, cot: Tensor) -> tuple[Tensor, Tensor]:
    """g(x, t) and (∂g/∂x)ᵀ cot row by row (the gradient of cotᵀ g with cot held fixed)."""
    out, pullback = torch.func.vjp(lambda xx: g(xx, t), x)
    return out, pullback(cot)[0]
