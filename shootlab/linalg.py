"""Structured solve of the multiple-shooting Newton system.

With separated boundary conditions the Newton system J Δ = r of multiple shooting
(report eq. 3.11a) is block-bidiagonal with two boundary blocks::

    B_a Δ_1                     = r_a          (p rows)
    Y_k Δ_k − Δ_{k+1}           = r_k,   k = 1 … m−1   (n rows each)
    B_b Δ_m                     = r_b          (n−p rows)

with Y_k = ∂y_k(t_{k+1})/∂s_k.  Condensation (Δ_{k+1} = Y_k Δ_k + …) multiplies the
Y_k together and is unstable for the dichotomic (Hamiltonian) problems multiple
shooting exists for.  We use *structured orthogonal cyclic reduction* (S. J. Wright,
"Stable parallel algorithms for two-point boundary value problems", SIAM J. Sci.
Stat. Comput. 13, 1992): at each level the chain rows are paired,

    [P_{2j}  Q_{2j}      0      ] [v_{2j}  ]
    [  0     P_{2j+1}  Q_{2j+1} ] [v_{2j+1}]   ,
                                  [v_{2j+2}]

and an orthogonal Q (a QR factorisation of the 2n×n column [Q_{2j}; P_{2j+1}])
eliminates the middle variable from the lower n rows, leaving a chain of half the
length.  All pairs of a level are factorised at once as one batched QR, so the work
is O(m n³) in log₂ m vectorised levels and the memory O(m n²); orthogonal
transformations keep it backward stable.  The last row couples Δ_1 and Δ_m and is
closed with the boundary rows into a 2n×2n system solved by LU with partial pivoting.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


class SingularJacobianError(RuntimeError):
    """The Newton matrix is (numerically) singular; ``interval`` locates it when known."""

    def __init__(self, message: str, interval: int | None = None):
        super().__init__(message)
        self.interval = interval


@dataclass
class _Level:
    reflectors: Tensor   # (P, 2n, n) Householder reflectors of the pairs' orthogonal factors Q (LAPACK geqrf)
    tau: Tensor          # (P, n) their scalar factors
    T12: Tensor      # (P, n, 2n) top rows: [T1 T2] [v_left; v_right] + R v_mid = top rhs
    R: Tensor        # (P, n, n) upper triangular in its upper triangle (a view of the reflectors)
    mid: Tensor      # (P,) original indices of the pairs' middle variables (for error messages)
    odd: bool        # whether the last chain row was carried to the next level unpaired
    scale: Tensor    # (P, n) row equilibration of the reduced rows handed to the next level


@dataclass
class BlockFactorization:
    """Factorised multiple-shooting Newton matrix (reusable for many right-hand sides)."""

    levels: list[_Level]
    scale: Tensor        # (m−1, n) row equilibration of the matching rows
    lu: Tensor
    pivots: Tensor
    row_scale: Tensor
    m: int
    n: int
    p: int

    def solve(self, r_a: Tensor, r_match: Tensor, r_b: Tensor) -> Tensor:
        """Solve J Δ = r; returns Δ with shape (m, n)."""
        n = self.n
        rhs = r_match * self.scale
        tops = []
        for lev in self.levels:
            npair = lev.tau.shape[0]
            stacked = rhs[:2 * npair].reshape(npair, 2 * n)          # [r_2j, r_2j+1] side by side
            rot = torch.ormqr(lev.reflectors, lev.tau, stacked.unsqueeze(-1), left=True, transpose=True).squeeze(-1)
            tops.append(rot[:, :n])
            reduced = rot[:, n:] * lev.scale
            rhs = torch.cat([reduced, rhs[-1:]]) if lev.odd else reduced
        ends = torch.linalg.lu_solve(self.lu, self.pivots,
                                     (torch.cat([r_a, rhs[0], r_b]) / self.row_scale).unsqueeze(-1)).squeeze(-1)
        x = ends.view(2, n)             # the last level's variables, Δ_1 and Δ_m
        for lev, top in zip(reversed(self.levels), reversed(tops)):
            # x holds the next level's variables v_0, v_2, …, v_2P (and the carried last): pair j
            # couples v_2j = x[j] and v_2j+2 = x[j+1] through its middle variable v_2j+1
            npair = top.shape[0]
            outer = torch.cat([x[:npair], x[1:npair + 1]], -1).unsqueeze(-1)
            b = top.unsqueeze(-1) - lev.T12 @ outer                  # T1 v_left + T2 v_right
            mid = torch.linalg.solve_triangular(lev.R, b, upper=True).squeeze(-1)
            x = torch.cat([torch.stack([x[:npair], mid], 1).reshape(2 * npair, n), x[npair:]])
        return x


def factorize(Y: Tensor, B_a: Tensor, B_b: Tensor, rcond: float = 1e-13) -> BlockFactorization:
    """Factorise the Newton matrix from the interval Jacobians Y (m−1, n, n) and the
    boundary-condition Jacobians B_a (p, n), B_b (n−p, n).

    The matching rows are equilibrated (each row of [Y_k, −I], and each reduced row at every
    level, divided by its largest entry) and a pivot is compared with the norm of its own column,
    so the rank test does not depend on the units of the equations or of the unknowns.  Raises
    :class:`SingularJacobianError` when a pivot falls below ``rcond`` relative to that norm.
    """
    Y = Y.detach()
    L, n, _ = Y.shape
    m = L + 1
    scale = _row_scale(Y, floor=1.0)      # rows of [Y_k, −I]: the −I contributes 1
    P = Y * scale[..., None]
    Qc = torch.diag_embed(-scale)
    var = torch.arange(m, device=Y.device)
    levels: list[_Level] = []
    pivots: list[Tensor] = []        # per level, each pair's smallest pivot ratio (the rank test)
    while P.shape[0] > 1:
        L = P.shape[0]
        npair = L // 2
        Pa, Qa = P[0:2 * npair:2], Qc[0:2 * npair:2]
        Pb, Qb = P[1:2 * npair:2], Qc[1:2 * npair:2]
        column = torch.cat([Qa, Pb], dim=-2)
        reflectors, tau = torch.geqrf(column)         # column = Q [R; 0], Q kept as reflectors
        pair = Pa.new_zeros(npair, 2 * n, 2 * n)
        pair[:, :n, :n], pair[:, n:, n:] = Pa, Qb
        rotated = torch.ormqr(reflectors, tau, pair, left=True, transpose=True)     # Qᵀ [Pa 0; 0 Qb]
        R = reflectors[:, :n]                         # upper triangle (the solves read only it)
        # |R_jj| / ‖column j‖ is the sine of the angle between column j and the span of the
        # columns before it: independent of the columns' scales (the units of the unknowns)
        norms = column.square().sum(-2).sqrt().clamp_min(1e-300)
        pivots.append((R.diagonal(dim1=-2, dim2=-1).abs() / norms).amin(-1))
        odd = bool(L % 2)
        reduced = rotated[:, n:]                      # [P' Q'] of the chain of half the length
        lscale = _row_scale(reduced)                  # re-equilibrate its rows
        levels.append(_Level(reflectors, tau, rotated[:, :n], R, var[1:2 * npair:2], odd, lscale))
        reduced = reduced * lscale[..., None]
        if odd:                                       # the last chain row waits for the next level
            P, Qc = torch.cat([reduced[..., :n], P[-1:]]), torch.cat([reduced[..., n:], Qc[-1:]])
        else:
            P, Qc = reduced[..., :n], reduced[..., n:]
        var = torch.cat([var[0:L:2], var[-1:]]) if odd else var[0::2]
    _check_pivots(pivots, levels, rcond)
    p = B_a.shape[0]
    top = torch.cat([B_a.detach(), torch.zeros_like(B_a)], dim=1)
    mid = torch.cat([P[0], Qc[0]], dim=1)
    bot = torch.cat([torch.zeros_like(B_b), B_b.detach()], dim=1)
    E = torch.cat([top, mid, bot], dim=0)
    row_scale = E.abs().amax(dim=1).clamp_min(1e-300)               # row equilibration
    E = E / row_scale[:, None]
    # the rank test on the column-equilibrated matrix: growing and decaying modes differ in scale
    sv = torch.linalg.svdvals(E / E.abs().amax(dim=0).clamp_min(1e-300))
    if not torch.isfinite(sv).all() or sv[-1] <= rcond * sv[0]:
        raise SingularJacobianError(
            "singular Newton matrix: the boundary conditions together with the condensed "
            f"matching conditions are rank deficient (reciprocal condition {float(sv[-1] / sv[0]):.2e})")
    lu, piv = torch.linalg.lu_factor(E)
    return BlockFactorization(levels, scale, lu, piv, row_scale, m, n, p)


def _check_pivots(pivots: list[Tensor], levels: list[_Level], rcond: float) -> None:
    """Raise :class:`SingularJacobianError` at the first pair, level by level, whose pivot ratio
    is at most ``rcond`` (one test after the reduction instead of one per level)."""
    if not pivots or not bool((torch.cat(pivots) <= rcond).any()):
        return
    for ratio, lev in zip(pivots, levels):
        bad = (ratio <= rcond).nonzero()
        if bad.numel():
            k = int(lev.mid[int(bad[0])])
            raise SingularJacobianError(
                f"singular Newton matrix: shooting variable s_{k} is not determined by the matching "
                f"conditions around it", interval=k)


def _row_scale(rows: Tensor, floor: float = 1e-300) -> Tensor:
    """1 / the largest magnitude in each row of a block row (…, k): row equilibration, so that a
    pivot is judged against its own row's size, not against the largest entry of the block (a
    position weighted 1e12 against a force weighted 1 is not singular).  ``floor``: a lower bound
    on that magnitude (an entry of the row not passed in)."""
    return 1.0 / rows.abs().amax(-1).clamp_min(floor)


def dense_matrix(Y: Tensor, B_a: Tensor, B_b: Tensor) -> Tensor:
    """The full (m n × m n) Newton matrix, row order [B_a; matching; B_b].  For tests at small m."""
    L, n, _ = Y.shape
    m = L + 1
    p = B_a.shape[0]
    J = Y.new_zeros(m * n, m * n)
    J[:p, :n] = B_a
    for k in range(L):  # tests only
        J[p + k * n:p + (k + 1) * n, k * n:(k + 1) * n] = Y[k]
        J[p + k * n:p + (k + 1) * n, (k + 1) * n:(k + 2) * n] = -torch.eye(n, dtype=Y.dtype)
    J[p + L * n:, (m - 1) * n:] = B_b
    return J
