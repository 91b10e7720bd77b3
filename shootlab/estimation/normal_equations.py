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
solves with the LU factor).  Used by :class:`shootlab.estimation.optimality.EstimationProblem`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

__all__ = ["NormalEquations", "Band", "hamiltonian_blocks_lu"]


@dataclass(frozen=True, eq=False)          # compared by identity (NormalEquations.joined)
class Band:
    """Where V^½F is sparse: an ordering of its rows and columns that makes it banded, and the
    column blocks in which its Householder QR then runs (each on a small dense window).

    Columns: reverse Cuthill–McKee on the pattern of FᵀF (bandwidth of M); rows: by their first
    non-zero column.  Block b, columns [j0, j1), takes the rows [j0, rows_b) — every row whose first
    non-zero lies before j1 (the later rows are still zero there) — and the columns [j0, cols_b)
    those rows reach, after the fill of the blocks before it.  For the 48-element confined mixture
    (99 × 97, 3.5 % non-zero) the windows are 20 × 16 (and the 5 columns their rows reach) instead
    of 99 × 97: the F build of one Newton iteration at n = 100 (m = 201, RK4) 0.28 against 0.42 s
    (medians of eight, alternating), the same F and interval Jacobians to 1e-14."""

    rows: Tensor            # (r,) row order
    cols: Tensor            # (c,) column order
    blocks: tuple           # ((j0, j1, rows_b, cols_b), …)
    outside: Tensor         # (r, c) bool, original order: where F must be zero for this band to hold

    #: block width (columns per dense window)
    WIDTH = 16
    #: the band is used when its windows' QR work is below this share of the dense QR's
    SHARE = 0.25

    @classmethod
    def of(cls, pattern: Tensor) -> "Band | None":
        """The band for a (r, c) non-zero pattern, or None when it would not pay (class docstring:
        fewer than 2·WIDTH columns, more columns than rows, or windows' work above SHARE of the dense QR's)."""
        r, c = pattern.shape
        if c < 2 * cls.WIDTH or r < c:
            return None
        # imported here, past the size test: scipy.sparse takes 0.4 s to import, which a small
        # model's estimate (every one of them asks for its band once) need not pay
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        P = pattern.cpu().numpy().astype(bool)
        A = (P.T.astype(np.int64) @ P.astype(np.int64)) > 0
        cols = np.asarray(reverse_cuthill_mckee(csr_matrix(A), symmetric_mode=True), dtype=np.int64)
        Pc = P[:, cols]
        first = np.where(Pc.any(1), Pc.argmax(1), c)
        last = np.where(Pc.any(1), c - 1 - Pc[:, ::-1].argmax(1), -1)
        rows = np.argsort(first, kind="stable")
        first, last = first[rows], last[rows]
        blocks, reach, work = [], 0, 0.0
        for j0 in range(0, c, cls.WIDTH):
            j1 = min(j0 + cls.WIDTH, c)
            nr = max(int(np.searchsorted(first, j1, side="left")), min(r, j1))
            reach = max(reach, j1, int(last[:nr].max()) + 1 if nr else j1)
            blocks.append((j0, j1, nr, reach))
            w, k = nr - j0, j1 - j0
            work += 2.0 * w * k * k + 4.0 * w * k * (reach - j1)
        if work > cls.SHARE * (2.0 * r * c * c - 2.0 * c ** 3 / 3.0):
            return None
        dev = pattern.device
        return cls(torch.as_tensor(rows, device=dev), torch.as_tensor(cols, device=dev), tuple(blocks),
                   ~pattern.to(torch.bool))

    def holds(self, F: Tensor) -> bool:
        """Whether F (…, r, c) is zero wherever this band assumes it is (a NaN there is not)."""
        return int(torch.count_nonzero(F * self.outside)) == 0


class NormalEquations:
    """Solves with M = FᵀVF (…, nζ, nζ), factorised on plain values.

    The columns of F are equilibrated first (D = diag of the column norms' reciprocals in the
    V-norm: units of the inputs ζ drop out).  For a diagonal V the factor is the Householder QR
    decomposition G = V^½ F D = Q [R; 0] (kept as LAPACK's reflectors, so that Qᵀ can be applied
    later), and M⁻¹ b = D R⁻¹ R⁻ᵀ D b never forms M and has the conditioning of G, the square
    root of M's (the 48-element mixture: cond M 8e14, cond of D M D 3e10, cond G 2e5);
    otherwise the LU decomposition of D M D.  Where F is sparse (``band``, :class:`Band`) the QR
    runs on small windows of a banded ordering of G's rows and columns, ζ then in that order
    inside the factor (the solves take and return it in the original one).  ``regular`` marks the
    rows where the factor is usable (:attr:`RCOND`: the reciprocal condition of G estimated from
    R's diagonal, or an LU pivot, above 1e-13)."""

    #: a point where G (or D M D) is exactly rank deficient leaves a diagonal entry of R (or a
    #: pivot) of a few eps times the largest, not 0 — 8.9e-16 = 4 eps for the 30-element mixture
    #: with a balance row of weight 0, the amount depending on the LAPACK code path — so the
    #: threshold stands well above eps; ζ has no correct digit long before it (eps·cond(G)²)
    RCOND = 1e-13

    def __init__(self, F: Tensor, V: Tensor, diagonal: bool, band: Band | None = None):
        self.diagonal = diagonal
        self.band = band if diagonal else None
        if diagonal:
            G = V.clamp_min(0).sqrt()[..., None] * F
            self.d = 1.0 / G.square().sum(-2).sqrt().clamp_min(1e-300)      # (vector_norm over dim −2: 2.6x the time)
            if self.band is None:
                self.reflectors, self.tau = torch.geqrf(G * self.d[..., None, :])
                self.R = self.reflectors[..., :F.shape[-1], :].triu()      # compact: the solves would copy a view
            else:
                self._banded_qr(G * self.d[..., None, :])
            r = torch.diagonal(self.R, dim1=-2, dim2=-1).abs()
            ratio = r.amin(-1) / r.amax(-1).clamp_min(1e-300)
        else:
            M = F.transpose(-1, -2) @ V @ F
            self.d = torch.diagonal(M, dim1=-2, dim2=-1).clamp_min(1e-300).rsqrt()
            self.lu, self.piv, info = torch.linalg.lu_factor_ex(self.d[..., :, None] * M * self.d[..., None, :])
            u = torch.diagonal(self.lu, dim1=-2, dim2=-1).abs()
            ratio = torch.where(info == 0, u.amin(-1) / u.amax(-1).clamp_min(1e-300), torch.zeros_like(u[..., 0]))
        self.regular = torch.isfinite(ratio) & (ratio > self.RCOND)

    def _banded_qr(self, G: Tensor) -> None:
        """G = Q R with G's rows and columns in the band's order (:class:`Band`), block after block:
        the Householder QR of the block's columns on its rows, Qᵀ applied to the columns the rows
        reach.  R is kept dense (c × c, the band's column order); d follows that order too."""
        band, c = self.band, G.shape[-1]
        # gathers by index_select (a copy): advanced indexing with the two index vectors took 2.5x as
        # long (200 points of 99 × 97: 55 against 22 ms on one thread)
        W = G.index_select(-2, band.rows).index_select(-1, band.cols)
        self.d = self.d.index_select(-1, band.cols)
        self.blocks, self._qt = [], None
        for j0, j1, nr, reach in band.blocks:
            refl, tau = torch.geqrf(W[..., j0:nr, j0:j1])
            if reach > j1:
                W[..., j0:nr, j1:reach] = torch.ormqr(refl, tau, W[..., j0:nr, j1:reach], left=True, transpose=True)
            W[..., j0:j1, j0:j1] = refl[..., :j1 - j0, :]          # R's diagonal block (its upper triangle)
            self.blocks.append((refl, tau))
        # below the diagonal: eliminated entries, never written back — solve_triangular reads one
        # triangle only; compact: a solve would copy the view at every call
        self.R = W[..., :c, :].contiguous()

    def _in_band_order(self, X: Tensor) -> Tensor:
        """X (…, nζ, k) with its rows (components of ζ) in the band's column order."""
        return X if self.band is None else X.index_select(-2, self.band.cols)

    def _apply_qt(self, X: Tensor) -> Tensor:
        """Qᵀ X for X (…, r, k) in the original row order (the result in the band's row order)."""
        if self.band is None:
            return torch.ormqr(self.reflectors, self.tau, X, left=True, transpose=True)
        if self._qt is None:
            # the windows' orthogonal factors formed once (~20 × 20 each): Qᵀ is then applied by batched
            # products, where LAPACK's ormqr would loop over the points one by one
            pad = torch.nn.functional.pad
            self._qt = [torch.linalg.householder_product(pad(refl, (0, nr - j0 - refl.shape[-1])),
                                                         pad(tau, (0, nr - j0 - tau.shape[-1]))).transpose(-1, -2)
                        for (j0, _, nr, _), (refl, tau) in zip(self.band.blocks, self.blocks)]
        X = X.index_select(-2, self.band.rows)
        for (j0, _, nr, _), Qt in zip(self.band.blocks, self._qt):
            X[..., j0:nr, :] = Qt @ X[..., j0:nr, :]
        return X

    @classmethod
    def joined(cls, parts: list["NormalEquations"]) -> "NormalEquations | None":
        """The factors of several batches of points (…, leading axis the points), one after another;
        None when they were not factorised alike (another band)."""
        if any(p.diagonal != parts[0].diagonal or p.band is not parts[0].band for p in parts):
            return None
        out = cls.__new__(cls)
        out.diagonal, out.band = parts[0].diagonal, parts[0].band
        names = (("d", "R", "regular") + (("reflectors", "tau") if out.band is None else ())
                 if out.diagonal else ("d", "lu", "piv", "regular"))
        for name in names:
            setattr(out, name, torch.cat([getattr(p, name) for p in parts]))
        if out.band is not None:
            out.blocks = [tuple(torch.cat([p.blocks[i][j] for p in parts]) for j in range(2))
                          for i in range(len(out.band.blocks))]
            out._qt = None
        return out

    def factor_storage(self) -> Tensor:
        """The largest tensor the factorisation keeps (for the size of a cache)."""
        return (self.R if self.band is not None else self.reflectors) if self.diagonal else self.lu

    def solve(self, b: Tensor) -> Tensor:
        """M⁻¹ b for b (…, nζ) or (…, nζ, k)."""
        vec = b.dim() == self.d.dim()
        B = self._in_band_order(b.unsqueeze(-1) if vec else b) * self.d[..., :, None]
        if self.diagonal:
            Rt = self.R.transpose(-1, -2)
            y = torch.linalg.solve_triangular(self.R, torch.linalg.solve_triangular(Rt, B, upper=False), upper=True)
        else:
            y = torch.linalg.lu_solve(self.lu, self.piv, B)
        y = y * self.d[..., :, None]
        if self.band is not None:
            y = torch.empty_like(y).index_copy_(-2, self.band.cols, y)
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
        Qtc = self._apply_qt(V.clamp_min(0).sqrt()[..., None] * C)
        b, g = Qtc[..., :nz, :], Qtc[..., nz:, :]
        k = Tc.shape[-1]
        # ζ in the band's order: U, Y and a alike, their products unchanged
        TB = self._in_band_order(torch.cat([Tc, B.T.expand(*Tc.shape[:-1], -1)], -1))
        sol = torch.linalg.solve_triangular(self.R.transpose(-1, -2), self.d[..., :, None] * TB, upper=False)
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
