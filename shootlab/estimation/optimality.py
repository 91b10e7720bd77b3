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
column-equilibrated V^½F (:class:`~shootlab.estimation.normal_equations.NormalEquations`) and the rank
test of FᵀVF.  The weights are vectors (diagonal), matrices, or functions of t returning either.
"""
from __future__ import annotations

import contextlib
import math
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch
from torch import Tensor

from .data import Interpolant, Measurements, runs_of
from .normal_equations import Band, NormalEquations, hamiltonian_blocks_lu
from shootlab.bvp.problem import BVP
from shootlab.bvp.tangents import outside_transforms

if TYPE_CHECKING:
    from .model import IdentificationModel

__all__ = ["EstimationProblem"]


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
    ``vmap``); the integrators take its Jacobian from :meth:`jacobian`, assembled from the
    model's derivatives; diagonal weights stay vectors."""

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
        self._parts: list[list] = []        # [t, X, _solve_once(t, X), bytes kept, key], oldest first
        self._index: dict[tuple, list[list]] = {}      # the same entries by key (_fingerprint)
        self._fcols: Tensor | None = None          # components of x that F depends on (_F_derivatives)
        self._band: Band | None | bool = None      # F's sparsity as a band (_band_for); False: none pays
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
    #: and at most this many points
    PARTS_CACHE_ENTRIES = 64

    @staticmethod
    def _fingerprint(t: Tensor, row_sums: Tensor) -> tuple:
        """The index key of plain values (t, X) among the kept results, from X's row sums: the
        number of rows, Σt and ΣX — equal values give equal keys (a block of rows of a larger X
        too), a key's entries are then compared in full."""
        return row_sums.shape, float(t.sum()), float(row_sums.sum())

    def _solve_parts(self, t: Tensor, X: Tensor) -> dict[str, Tensor]:
        """:meth:`_solve_once`, or the kept result for the same plain values of (t, X), or the kept
        results of blocks of its rows joined (:meth:`_joined`)."""
        plain = not (X.requires_grad or t.requires_grad or torch._C._functorch.is_functorch_wrapped_tensor(X)
                     or torch._C._functorch.is_functorch_wrapped_tensor(t))
        if plain:
            row_sums = X.sum(-1)
            key = self._fingerprint(t, row_sums)
            for tk, Xk, p, _, _ in self._index.get(key, ()):
                if tk.shape == t.shape and Xk.shape == X.shape and torch.equal(Xk, X) and torch.equal(tk, t):
                    return p
            joined = self._joined(t, X, row_sums) if X.ndim == 2 and t.shape == row_sums.shape else None
            if joined is not None:
                return joined
        p = self._solve_once(t, X)
        if plain and not p["xi"].requires_grad:          # not with ∂/∂data (uncertainty)
            size = sum(v.numel() * v.element_size() for v in (p["F"], p["normal"].factor_storage()))
            entry = [t.detach().clone(), X.detach().clone(), p, size, key]
            self._parts.append(entry)
            self._index.setdefault(key, []).append(entry)
            self._trim()
        return p

    def _joined(self, t: Tensor, X: Tensor, row_sums: Tensor) -> dict[str, Tensor] | None:
        """The kept results whose points, block after block of rows, make up (t, X), joined row-wise;
        None unless they cover every row.  An explicit scheme's step asks for the Jacobian at its
        stage points concatenated (:func:`~shootlab.bvp.integrators.explicit._rk_stages_sensitivity`),
        each of which its stages have just solved."""
        sizes = sorted({e[1].shape[0] for e in self._parts if e[1].ndim == 2 and e[1].shape[0] < X.shape[0]})
        blocks, start = [], 0
        while start < X.shape[0]:
            for rows in sizes:
                stop = start + rows
                if stop > X.shape[0]:
                    return None             # nor does any larger block fit
                key = self._fingerprint(t[start:stop], row_sums[start:stop])
                hit = next((p for tk, Xk, p, _, _ in reversed(self._index.get(key, ()))   # the stages were kept last
                            if Xk.shape[1:] == X.shape[1:] and tk.ndim == 1
                            and torch.equal(Xk, X[start:stop]) and torch.equal(tk, t[start:stop])), None)
                if hit is not None:
                    blocks.append(hit)
                    start = stop
                    break
            else:
                return None
        if not blocks:                      # no rows at all
            return None
        out = {k: (NormalEquations.joined([b[k] for b in blocks]) if k == "normal" else
                   blocks[0][k] if k == "v_diag" else torch.cat([b[k] for b in blocks]))
               for k in blocks[0] if k != "jacobian"}
        return out if out["normal"] is not None else None       # factorised alike (one band) or not at all

    def _trim(self) -> None:
        while len(self._parts) > 1 and (sum(e[3] for e in self._parts) > self.PARTS_CACHE_BYTES
                                        or len(self._parts) > self.PARTS_CACHE_ENTRIES):
            old = self._parts.pop(0)
            same = [e for e in self._index.pop(old[4]) if e is not old]
            if same:
                self._index[old[4]] = same

    def forget(self) -> None:
        """Drop the kept :meth:`_solve_parts` results (timing a fresh iterate)."""
        self._parts.clear()
        self._index.clear()

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
        normal = NormalEquations(Fd, V, v_diag, self._band_for(Fd) if v_diag else None)
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

    def _band_for(self, F: Tensor) -> Band | None:
        """The band of F's sparsity (:class:`~shootlab.estimation.normal_equations.Band`): found at the first call
        from where F is non-zero, checked at every later one — where F is non-zero outside it the
        pattern is widened (a law that switches on in some region), so that no entry is ever
        dropped; a call with non-finite values in F is factorised densely and widens nothing."""
        band = self._band
        if band is False:
            return None
        if band is not None and band.holds(F):
            return band
        if not bool(torch.isfinite(F).all()):
            return None
        pattern = (F != 0).flatten(0, -3).any(0)
        if band is not None:
            pattern |= ~band.outside
        new = Band.of(pattern)
        self._band = new if new is not None else False
        return new

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
        """``rhs(t, X)`` (m, 2nx) and its Jacobian (m, 2nx, 2nx), assembled from the model's own
        derivatives (:meth:`_assembled`), faster than reverse sweeps through the whole right-hand
        side (one per equation) at every size (``docs/benchmarks.md``).  The Jacobian met at a
        point kept with its normal equations (:meth:`_solve_parts`) is kept with them.  Raises
        :class:`~shootlab.bvp.tangents.NotTransformable` for a model that autograd cannot
        differentiate twice."""
        # compact copies: X is often a view into a larger buffer (the integrators pack [y | vec S])
        t, X = t.detach().contiguous(), X.detach().contiguous()
        if X.ndim != 2:
            f, J = self.jacobian(t.reshape(-1), X.reshape(-1, X.shape[-1]))
            return f.view(X.shape), J.view(*X.shape, X.shape[-1])
        kept = self._solve_parts(t, X)  # not under no_grad: the measurements it caches may carry ∂/∂data
        if "jacobian" in kept:          # an implicit scheme's Newton matrix at a point met before
            return kept["jacobian"]
        out = self._assembled(t, X, kept)
        entry = next((e for e in self._parts if e[2] is kept), None)
        if entry is not None:           # kept with its point's normal equations
            kept["jacobian"] = out
            entry[3] += out[1].numel() * out[1].element_size()
            self._trim()
        return out

    def _assembled(self, t: Tensor, X: Tensor, kept: dict) -> tuple[Tensor, Tensor]:
        """The Jacobian of eq. 2.7 assembled from the model's own derivatives instead of
        differentiating the whole right-hand side (docs/design.md §1, "The Jacobian of eq. 2.7,
        assembled"), at the point whose :meth:`_solve_parts` are ``kept``.

        With P = (FᵀVF)⁻¹, u = Vξ and, at the current ζ and u held fixed,

            C = ∂(f + Fζ)/∂x (r, nx),   T = ∂(Fᵀu)/∂x (nζ, nx),   Q = ∂²[uᵀ(f + Fζ)]/∂x² (nx, nx)

        and S = T − FᵀVC, the derivatives of ζ and of the two halves of eq. 2.7 are

            ∂ζ/∂x = P S,   ∂ζ/∂λ = P Bᵀ,   ∂x'/∂x = A + B P S,   ∂x'/∂λ = B P Bᵀ + W⁻¹
            ∂λ'/∂x = −Q + CᵀVC − Sᵀ P S,   ∂λ'/∂λ = −(∂x'/∂x)ᵀ        (Hamiltonian structure)

        C, T and Q are derivatives of f and F alone, by reverse over reverse mode
        (:func:`_second_derivatives`), F only along the components of x it depends on (found by
        probing, :meth:`_F_derivatives`: for the mixture, only K), so that no dense (r, nζ)
        derivative per direction of X is ever formed; the three blocks come from the normal
        equations' factor
        (:meth:`~shootlab.estimation.normal_equations.NormalEquations.hamiltonian_blocks`)."""
        from shootlab.bvp.tangents import NotTransformable
        nx, md = self.nx, self.model
        p = {k: (v.detach() if isinstance(v, Tensor) else v) for k, v in kept.items()}
        x, zeta, F, V, vd = X[:, :nx].contiguous(), p["zeta"], p["F"], p["V"], p["v_diag"]
        u = _apply(V, vd, p["xi"])
        try:
            eye = torch.eye(nx, dtype=x.dtype, device=x.device)
            Df, Qf = _second_derivatives(md.f, x, t, u, eye)                          # (m, r, nx), (m, nx, nx)
            cols, DF, QF = self._F_derivatives(t, x, u[..., :, None] * zeta[..., None, :])   # (m, r, nζ, c), (m, nx, c)
        except (RuntimeError, NotImplementedError, TypeError, ValueError, AttributeError) as exc:
            raise NotTransformable(str(exc)) from exc
        # contiguous copies: the sweeps hand the directions' axis back last, as a strided view, on
        # which the products with C below are markedly slower
        C, Q = Df.clone(memory_format=torch.contiguous_format), Qf.clone(memory_format=torch.contiguous_format)
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

    #: relative size of the random probes of :meth:`_F_derivatives`
    PROBE = 1e-3

    def _F_derivatives(self, t: Tensor, x: Tensor, cot: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The components ``cols`` of x on which the model's F depends, ∂F/∂x along them
        (m, r, nζ, c) and ∂/∂x[(∂F/∂x)ᵀ cot] along them (m, nx, c), by one batched sweep
        (:func:`_second_derivatives`).

        ``cols`` is found once by the derivatives of F along every component at three rows of the
        first batch, each moved by a random relative 1e-3 (an accidental zero derivative at the
        probe is then of probability zero); a non-finite derivative counts as a dependence.  Every
        later call also differentiates along one random direction in the other components (one
        more direction of the same sweep) and widens ``cols`` where F turns out to depend on them
        after all (a law that switches on in some region)."""
        F = self.model.F
        if self._fcols is None:
            gen = torch.Generator().manual_seed(0)
            rows = torch.unique(torch.tensor([0, x.shape[0] // 2, x.shape[0] - 1]))
            xp, tp = x[rows], t[rows]
            xp = xp + self.PROBE * (1 + xp.abs()) * torch.randn(xp.shape, generator=gen, dtype=xp.dtype).to(xp.device)
            DF, _ = _second_derivatives(F, xp, tp, torch.zeros_like(F(xp, tp)),
                                        torch.eye(self.nx, dtype=x.dtype, device=x.device))
            self._fcols = _depends(DF).nonzero().flatten().to(x.device)
            self._fcheck = torch.Generator().manual_seed(1)
        cols = self._fcols
        rest = torch.ones(self.nx, dtype=torch.bool)
        rest[cols.cpu()] = False
        dirs = torch.eye(self.nx, dtype=x.dtype, device=x.device)[cols]
        if rest.any():
            v = torch.randn(self.nx, generator=self._fcheck, dtype=x.dtype).to(x.device) * rest.to(x.device)
            dirs = torch.cat([dirs, v[None]])
        DF, QF = _second_derivatives(F, x, t, cot, dirs)
        if rest.any():
            if _depends(DF[..., -1:]).any():                     # F depends on more components
                widened, _ = _second_derivatives(F, x, t, cot, torch.eye(self.nx, dtype=x.dtype, device=x.device)[rest])
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
        return BVP(self.rhs, self.bc_a, self.bc_b, name=f"estimation[{self.model.name}]", jac=self.jacobian,
                   lower=lower if self.model.bounds else None, upper=upper if self.model.bounds else None)

    #: FᵀVF counts as singular where G = V^½F D, its square root with equilibrated columns (D: the
    #: reciprocal column norms, the units of ζ dropped), has reciprocal condition σ_min/σ_max
    #: below this (FᵀVF's own, cond(G)², below 1e-20).  The SVD is backward stable: an exactly
    #: rank-deficient G shows a ratio of about eps = 2.2e-16 times a small factor, whichever LAPACK
    #: path computed it, six orders below the threshold; a G as ill-conditioned as the threshold
    #: leaves no correct digit in the solves with FᵀVF (relative error about eps·cond(G)² ≈ 2e4)
    RCOND = 1e-10

    def input_rcond(self, t: Tensor, x: Tensor) -> Tensor:
        """The reciprocal condition σ_min/σ_max (…,) of the normal equations' square root at the
        times t (…,) and states x (…, nx): of G = R F D, where RᵀR = V on the rows with a sample
        (R = V^½ for a diagonal V, Λ^½Qᵀ from V = QΛQᵀ otherwise) and D equilibrates G's columns,
        so that the units of the inputs ζ drop out.  cond(D FᵀVF D) = cond(G)²; 0 where there are
        fewer weighted rows than inputs or an input is in no weighted row (a zero column), NaN
        where F is not finite.

        From the singular values of G itself, not of GᵀG = D FᵀVF D: the SVD is backward stable,
        so it resolves G's singular values down to about eps·σ_max(G), GᵀG's only down to
        eps·σ_max(GᵀG), i.e. G's down to √eps·σ_max(G)."""
        with torch.no_grad():
            _, mask = self.measurements(t)
            V, v_diag = _weight(self.model.V, t, self.r, x)
            F = self.model.F(x, t)
            if v_diag:
                G = (V * mask).clamp_min(0).sqrt()[..., None] * F
            else:
                lam, Q = torch.linalg.eigh(V * mask.unsqueeze(-1) * mask.unsqueeze(-2))
                G = lam.clamp_min(0).sqrt()[..., None] * (Q.transpose(-1, -2) @ F)
            G = G.expand(*t.shape, *G.shape[-2:])
            G = G / G.square().sum(-2, keepdim=True).sqrt().clamp_min(1e-300)      # D: equilibrated columns
            finite = torch.isfinite(G).all(-1).all(-1)
            if G.shape[-2] < G.shape[-1]:                   # fewer rows than inputs: rank < nζ
                return torch.where(finite, 0.0, math.nan).to(G)
            sv = torch.linalg.svdvals(torch.where(finite[..., None, None], G, 0.0))
            return torch.where(finite, sv[..., -1] / sv[..., 0].clamp_min(1e-300), math.nan)

    def check_regular(self, t: Tensor, X: Tensor) -> None:
        """Raise a clear ValueError when FᵀVF is singular along the approximation X (m, 2 nx) on
        the grid t (m,), before anything integrates: where the reciprocal condition of its square
        root (:meth:`input_rcond`) is below :attr:`RCOND` or not finite, at the shooting points
        and at the midpoint of every sampling interval (a missing sample)."""
        ts = torch.as_tensor(self.data.t, dtype=t.dtype, device=t.device)
        ts = ts[(ts >= t[0]) & (ts <= t[-1])]
        tq, _ = torch.sort(torch.cat([t, 0.5 * (ts[1:] + ts[:-1])]))
        tqn, tn, Xn = tq.cpu().numpy(), t.cpu().numpy(), X.detach().cpu().numpy()
        x = torch.stack([torch.as_tensor(np.interp(tqn, tn, Xn[:, j])) for j in range(self.nx)], -1).to(X)
        ratio = self.input_rcond(tq, x)
        bad = ~(ratio >= self.RCOND)                        # NaN: F not finite
        if bad.any():
            i = int(bad.nonzero()[0])
            raise ValueError(
                f"FᵀVF is singular at t = {float(tq[i]):.6g} (reciprocal condition of its square root "
                f"{float(ratio[i]):.2e}): "
                f"the inputs ζ = {self.model.inputs} are not all determined by the weighted equations "
                f"{self.model.equations}; give every input a row with positive weight in V"
                + self._missing_there(float(tq[i])))

    def _missing_there(self, t: float) -> str:
        """For :meth:`check_regular`'s message: the measured channels with no sample on the sampling
        interval around ``t`` (their rows have zero weight there), with the run of missing samples."""
        ts = self.data.t
        k = int(np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 2))
        out = []
        for name in self.interp.names:
            gap = np.isnan(self.data.channels[name])
            for i, j in runs_of(gap):
                if i <= k + 1 and j > k:
                    out.append(f"column {name!r} is empty in {self.data.span(i, j)}")
        return ("; " + ", ".join(out) + ": declare the channel given (its gaps are then filled) or fill it"
                if out else "")


def _depends(D: Tensor) -> Tensor:
    """Per direction (last axis of D (…, k)): is any derivative non-zero or non-finite?"""
    return ~(D.abs().flatten(0, -2).sum(0) == 0)          # a NaN or ∞ sum is a dependence


def _second_derivatives(g: Callable[[Tensor, Tensor], Tensor], x: Tensor, t: Tensor, cot: Tensor,
                        dirs: Tensor) -> tuple[Tensor, Tensor]:
    """Along each direction v of ``dirs`` (k, nx), for a row-wise g(x, t) (m, *s) and cotangents
    ``cot`` (m, *s): the derivative (∂g/∂x) v (m, *s, k) and the Hessian product
    ∇²(cotᵀg) v (m, nx, k), by reverse over reverse mode.  The pullback h(w) = (∂g/∂x)ᵀ w is
    linear in w, so the gradient of vᵀh at w = cot is the pair ((∂g/∂x) v, ∇²(cotᵀg) v): one sweep
    through g with its graph kept, and one batched sweep (``is_grads_batched``) over the k
    directions.  Plain autograd: forward over reverse mode under ``torch.func`` runs the second
    derivatives of small operations through torch's Python decompositions (docs/design.md §1)."""
    k = dirs.shape[0]
    with torch.enable_grad():
        xr = x.detach().requires_grad_(True)
        w = cot.detach().requires_grad_(True)
        out = g(xr, t)
        h = (torch.autograd.grad(out, xr, w, create_graph=True, allow_unused=True)[0]
             if out.requires_grad and k else None)
        if h is None:                                    # g does not depend on x
            return x.new_zeros(*out.shape, k), x.new_zeros(*x.shape, k)
        D, Q = torch.autograd.grad(h, (w, xr), dirs[:, None, :].expand(k, *x.shape), is_grads_batched=True,
                                   allow_unused=True)
    D = x.new_zeros(k, *out.shape) if D is None else D
    Q = x.new_zeros(k, *x.shape) if Q is None else Q                 # g linear in x
    return D.movedim(0, -1), Q.movedim(0, -1)
