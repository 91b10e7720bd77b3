"""The normal equations of eq. 2.7's inputs, factorised: M ζ = Bᵀλ + FᵀV(E z_m − f), M = FᵀVF
(report eq. 2.7; docs/design.md §1).

:class:`NormalEquations` factorises M once per point on plain values — the Householder QR of the
column-equilibrated V^½F for a diagonal V (the conditioning of M's square root, independent of
the units of ζ), the LU decomposition of the equilibrated M for a full V — marks the points where
M is singular, and solves with M.  From the same factor come the three blocks of the assembled
Jacobian of eq. 2.7 that involve P = M⁻¹ (docs/design.md §1, "The Jacobian of eq. 2.7,
assembled"), with S = T − FᵀVC::

    B P S,    B P Bᵀ,    CᵀVC − Sᵀ P S

(:meth:`NormalEquations.hamiltonian_blocks` from the QR factor, :func:`hamiltonian_blocks_lu` by
solves with the LU factor).  Used by :class:`shootlab.optimality.EstimationProblem`.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["NormalEquations", "hamiltonian_blocks_lu"]


class NormalEquations:
    """Solves with M = FᵀVF (…, nζ, nζ), factorised on plain values.

    The columns of F are equilibrated first (D = diag of the column norms' reciprocals in the
    V-norm: units of the inputs ζ drop out).  For a diagonal V the factor is the Householder QR
    decomposition G = V^½ F D = Q [R; 0] (kept as LAPACK's reflectors, so that Qᵀ can be applied
    later), and M⁻¹ b = D R⁻¹ R⁻ᵀ D b never forms M and has the conditioning of G, the square
    root of M's (the 48-element mixture: cond M 8e14, cond of D M D 3e10, cond G 2e5);
    otherwise the LU decomposition of D M D.  ``regular`` marks the rows where the factor is
    usable (:attr:`RCOND`: the reciprocal condition of G estimated from R's diagonal, or an LU
    pivot, above 1e-15)."""

    RCOND = 1e-15

    def __init__(self, F: Tensor, V: Tensor, diagonal: bool):
        self.diagonal = diagonal
        if diagonal:
            G = V.clamp_min(0).sqrt()[..., None] * F
            self.d = 1.0 / torch.linalg.vector_norm(G, dim=-2).clamp_min(1e-300)
            self.reflectors, self.tau = torch.geqrf(G * self.d[..., None, :])
            self.R = self.reflectors[..., :F.shape[-1], :].triu()      # compact: the solves would copy a view
            r = torch.diagonal(self.R, dim1=-2, dim2=-1).abs()
            ratio = r.amin(-1) / r.amax(-1).clamp_min(1e-300)
        else:
            M = F.transpose(-1, -2) @ V @ F
            self.d = torch.diagonal(M, dim1=-2, dim2=-1).clamp_min(1e-300).rsqrt()
            self.lu, self.piv, info = torch.linalg.lu_factor_ex(self.d[..., :, None] * M * self.d[..., None, :])
            u = torch.diagonal(self.lu, dim1=-2, dim2=-1).abs()
            ratio = torch.where(info == 0, u.amin(-1) / u.amax(-1).clamp_min(1e-300), torch.zeros_like(u[..., 0]))
        self.regular = torch.isfinite(ratio) & (ratio > self.RCOND)

    @classmethod
    def joined(cls, parts: list["NormalEquations"]) -> "NormalEquations":
        """The factors of several batches of points (…, leading axis the points), one after another."""
        out = cls.__new__(cls)
        out.diagonal = parts[0].diagonal
        for name in ("d", "reflectors", "tau", "R", "regular") if out.diagonal else ("d", "lu", "piv", "regular"):
            setattr(out, name, torch.cat([getattr(p, name) for p in parts]))
        return out

    def factor_storage(self) -> Tensor:
        """The largest tensor the factorisation keeps (for the size of a cache)."""
        return self.reflectors if self.diagonal else self.lu

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

    def hamiltonian_blocks(self, V: Tensor, C: Tensor, Tc: Tensor, cols: Tensor, B: Tensor
                           ) -> tuple[Tensor, Tensor, Tensor]:
        """B P S, B P Bᵀ and CᵀVC − Sᵀ P S for P = M⁻¹, S = T − FᵀVC (diagonal V only), where T
        is zero outside the columns ``cols`` (given there as Tc).  With the factor above,
        U = R⁻ᵀ D S = a − b for a = R⁻ᵀ D T and [b; g] = Qᵀ V^½ C, Y = R⁻ᵀ D Bᵀ:

            B P S = Yᵀ U,    B P Bᵀ = Yᵀ Y,    CᵀVC − SᵀPS = gᵀg − aᵀa + aᵀb + bᵀa

        (CᵀVC = bᵀb + gᵀg; the last form cancels bᵀb exactly instead of subtracting two large
        Gram matrices, and a has only the columns ``cols``).  One application of Qᵀ, one
        triangular solve and two (nx, nζ, nx) products per row."""
        nz = self.R.shape[-1]
        Qtc = torch.ormqr(self.reflectors, self.tau, V.clamp_min(0).sqrt()[..., None] * C,
                          left=True, transpose=True)
        b, g = Qtc[..., :nz, :], Qtc[..., nz:, :]
        k = Tc.shape[-1]
        sol = torch.linalg.solve_triangular(
            self.R.transpose(-1, -2), self.d[..., :, None] * torch.cat([Tc, B.T.expand(*Tc.shape[:-1], -1)], -1),
            upper=False)
        a, Y = sol[..., :k], sol[..., k:]
        U = -b
        U[..., cols] += a
        Yt = Y.transpose(-1, -2)
        G21 = g.transpose(-1, -2) @ g
        ab = a.transpose(-1, -2) @ b                                    # (…, k, nx)
        G21[..., cols, :] += ab
        G21[..., :, cols] += ab.transpose(-1, -2)
        G21[..., cols[:, None], cols] -= a.transpose(-1, -2) @ a
        return Yt @ U, Yt @ Y, G21


def hamiltonian_blocks_lu(normal: NormalEquations, F: Tensor, V: Tensor, C: Tensor, Tc: Tensor,
                           cols: Tensor, B: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:meth:`NormalEquations.hamiltonian_blocks` for a full weight matrix V, by solves with M."""
    VC = V.transpose(-1, -2) @ C
    S = -(F.transpose(-1, -2) @ VC)
    S[..., cols] += Tc
    PS = normal.solve(S)
    return B @ PS, B @ normal.solve(B.T.expand(*S.shape[:-1], -1)), C.transpose(-1, -2) @ VC - S.transpose(-1, -2) @ PS
