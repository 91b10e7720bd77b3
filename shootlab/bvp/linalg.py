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

from .device import accelerator_paths


class SingularJacobianError(RuntimeError):
    """The Newton matrix is (numerically) singular; ``interval`` locates it when known."""

    def __init__(self, message: str, interval: int | None = None):
        super().__init__(message)
        self.interval = interval


@dataclass
class _Level:
    reflectors: Tensor   # (…, P, 2n, n) Householder reflectors of the pairs' orthogonal factors Q (LAPACK geqrf)
    tau: Tensor          # (…, P, n) their scalar factors
    T12: Tensor      # (…, P, n, 2n) top rows: [T1 T2] [v_left; v_right] + R v_mid = top rhs
    R: Tensor        # (…, P, n, n) upper triangular in its upper triangle (a view of the reflectors)
    mid: Tensor      # (P,) original indices of the pairs' middle variables (for error messages)
    odd: bool        # whether the last chain row was carried to the next level unpaired
    scale: Tensor    # (…, P, n) row equilibration of the reduced rows handed to the next level
    wy: tuple[Tensor, Tensor] | None = None   # accelerator: (V, T) of Q = I − V T Vᵀ (:func:`apply_qt`)


@dataclass
class BlockFactorization:
    """Factorised multiple-shooting Newton matrix (reusable for many right-hand sides); with
    leading batch dimensions (…) where it factorises several systems of one shape at once
    (:func:`factorize_batch`)."""

    levels: list[_Level]
    scale: Tensor        # (…, m−1, n) row equilibration of the matching rows
    lu: Tensor
    pivots: Tensor
    row_scale: Tensor
    m: int
    n: int
    p: int

    def solve(self, r_a: Tensor, r_match: Tensor, r_b: Tensor) -> Tensor:
        """Solve J Δ = r (r_a (…, p), r_match (…, m−1, n), r_b (…, n−p)); returns Δ (…, m, n)."""
        n = self.n
        batch = r_match.shape[:-2]
        rhs = r_match * self.scale
        tops = []
        for lev in self.levels:
            npair = lev.tau.shape[-2]
            stacked = rhs[..., :2 * npair, :].reshape(*batch, npair, 2 * n)     # [r_2j, r_2j+1] side by side
            rot = apply_qt(lev.reflectors, lev.tau, stacked.unsqueeze(-1), lev.wy).squeeze(-1)
            tops.append(rot[..., :n])
            reduced = rot[..., n:] * lev.scale
            rhs = torch.cat([reduced, rhs[..., -1:, :]], -2) if lev.odd else reduced
        ends = torch.linalg.lu_solve(self.lu, self.pivots,
                                     (torch.cat([r_a, rhs[..., 0, :], r_b], -1) / self.row_scale).unsqueeze(-1)
                                     ).squeeze(-1)
        x = ends.view(*batch, 2, n)             # the last level's variables, Δ_1 and Δ_m
        for lev, top in zip(reversed(self.levels), reversed(tops)):
            # x holds the next level's variables v_0, v_2, …, v_2P (and the carried last): pair j
            # couples v_2j = x[j] and v_2j+2 = x[j+1] through its middle variable v_2j+1
            npair = top.shape[-2]
            outer = torch.cat([x[..., :npair, :], x[..., 1:npair + 1, :]], -1).unsqueeze(-1)
            b = top.unsqueeze(-1) - lev.T12 @ outer                  # T1 v_left + T2 v_right
            mid = torch.linalg.solve_triangular(lev.R, b, upper=True).squeeze(-1)
            x = torch.cat([torch.stack([x[..., :npair, :], mid], -2).reshape(*batch, 2 * npair, n),
                           x[..., npair:, :]], -2)
        return x


def apply_qt(reflectors: Tensor, tau: Tensor, C: Tensor, wy: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Qᵀ C for the orthogonal factor Q = H_1 ⋯ H_k of ``torch.geqrf`` (reflectors (…, M, k),
    tau (…, k)) and C (…, M, N).  On the CPU LAPACK's ``ormqr``; on an accelerator, whose
    ``ormqr`` loops over the matrices of a batch (:func:`shootlab.bvp.device.accelerator_paths`), the
    compact WY form Q = I − V T Vᵀ (:func:`wy_form`, or ``wy`` when already formed): three
    batched products, Qᵀ C = C − V (Tᵀ (Vᵀ C)).  Equal to rounding."""
    if not accelerator_paths(C):
        return torch.ormqr(reflectors, tau, C, left=True, transpose=True)
    V, T = wy if wy is not None else wy_form(reflectors, tau)
    return C - V @ (T.mT @ (V.mT @ C))


def wy_form(reflectors: Tensor, tau: Tensor) -> tuple[Tensor, Tensor]:
    """(V, T) of the compact WY form Q = H_1 ⋯ H_k = I − V T Vᵀ (Schreiber & Van Loan 1989; LAPACK
    ``larft``, forward, columnwise) of ``torch.geqrf``'s reflectors (…, M, k): V unit lower
    trapezoidal (the reflectors' vectors), T (…, k, k) upper triangular with T_jj = τ_j and
    T[:j, j] = −τ_j T[:j, :j] V[:, :j]ᵀ v_j — k batched steps, no loop over the batch."""
    M, k = reflectors.shape[-2:]
    V = reflectors.tril(-1) + torch.eye(M, k, dtype=reflectors.dtype, device=reflectors.device)
    G = V.mT @ V
    T = torch.zeros(*tau.shape, k, dtype=tau.dtype, device=tau.device)
    for j in range(k):          # over the columns of one block (n), not over the batch
        if j:
            T[..., :j, j] = -tau[..., j, None] * (T[..., :j, :j] @ G[..., :j, j, None]).squeeze(-1)
        T[..., j, j] = tau[..., j]
    return V, T


def householder_qr(A: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(reflectors, tau, R) of the Householder QR factorisation A = Q [R; 0] of each matrix of A
    (…, M, k), M ≥ k, by ``torch.geqrf`` (batched on an accelerator, unlike ``torch.linalg.qr``);
    Qᵀ b by :func:`apply_qt`."""
    reflectors, tau = torch.geqrf(A)
    k = A.shape[-1]
    return reflectors, tau, reflectors[..., :k, :k].triu()


def factorize(Y: Tensor, B_a: Tensor, B_b: Tensor, rcond: float = 1e-13) -> BlockFactorization:
    """Factorise the Newton matrix from the interval Jacobians Y (m−1, n, n) and the
    boundary-condition Jacobians B_a (p, n), B_b (n−p, n).

    The matching rows are equilibrated (each row of [Y_k, −I], and each reduced row at every
    level, divided by its largest entry) and a pivot is compared with the norm of its own column,
    so the rank test does not depend on the units of the equations or of the unknowns.  Raises
    :class:`SingularJacobianError` when a pivot falls below ``rcond`` relative to that norm.
    """
    fac, pivots, E = _reduce(Y.detach(), B_a.detach(), B_b.detach())
    _check_pivots(pivots, fac.levels, rcond)
    # the rank test on the column-equilibrated matrix: growing and decaying modes differ in scale
    sv = torch.linalg.svdvals(E / E.abs().amax(dim=0).clamp_min(1e-300))
    if not torch.isfinite(sv).all() or sv[-1] <= rcond * sv[0]:
        raise SingularJacobianError(
            "singular Newton matrix: the boundary conditions together with the condensed "
            f"matching conditions are rank deficient (reciprocal condition {float(sv[-1] / sv[0]):.2e})")
    fac.lu, fac.pivots = torch.linalg.lu_factor(E)
    return fac


def factorize_batch(Y: Tensor, B_a: Tensor, B_b: Tensor, rcond: float = 1e-13
                    ) -> tuple[BlockFactorization, Tensor]:
    """:func:`factorize` for B systems of one shape at once — Y (B, m−1, n, n), B_a (B, p, n),
    B_b (B, n−p, n) — as one batch at every level.  Returns the factorisation and a bool (B,)
    marking the singular systems (the same two rank tests as :func:`factorize`, or non-finite
    entries), whose solutions are meaningless; nothing is raised and no host synchronisation."""
    Y, B_a, B_b = Y.detach(), B_a.detach(), B_b.detach()
    finite = torch.isfinite(Y).flatten(-3).all(-1) & torch.isfinite(B_a).flatten(-2).all(-1) \
        & torch.isfinite(B_b).flatten(-2).all(-1)
    Y = torch.where(finite[:, None, None, None], Y, torch.zeros_like(Y))
    fac, pivots, E = _reduce(Y, B_a, B_b)
    singular = ~finite
    for ratio in pivots:
        singular = singular | ~(ratio > rcond).all(-1)
    ok = torch.isfinite(E).flatten(-2).all(-1)
    eye = torch.eye(E.shape[-1], dtype=E.dtype, device=E.device)
    E = torch.where(ok[:, None, None], E, eye)
    sv = torch.linalg.svdvals(E / E.abs().amax(dim=-2, keepdim=True).clamp_min(1e-300))
    singular = singular | ~ok | ~torch.isfinite(sv).all(-1) | ~(sv[..., -1] > rcond * sv[..., 0])
    E = torch.where(singular[:, None, None], eye, E)
    fac.lu, fac.pivots, _ = torch.linalg.lu_factor_ex(E)
    return fac, singular


def solve_initial_value(Y: Tensor, B_a: Tensor, r_a: Tensor, r_match: Tensor) -> tuple[Tensor, Tensor]:
    """Δ (…, m, n) of the Newton system with all n conditions at a — B_a (…, n, n), no rows at b —
    for systems of one shape at once: B_a Δ_1 = r_a, Y_k Δ_k − Δ_{k+1} = r_k, by forward
    substitution Δ_{k+1} = Y_k Δ_k − r_k, summed for all k at once as an inclusive scan of the
    affine maps x ↦ Y_k x − r_k (Hillis–Steele: log₂ m batched compositions (Y', d') ∘ (Y, d) =
    (Y'Y, Y'd + d') instead of m − 1 sequential steps).  Condensation is as stable as the
    initial-value problem itself here: its instability needs conditions at b that pin down growing
    modes.  Returns Δ and a bool (…) marking the systems whose B_a is singular (their Δ meaningless)."""
    lu, pivots, info = torch.linalg.lu_factor_ex(B_a)
    first = torch.linalg.lu_solve(lu, pivots, r_a.unsqueeze(-1))                   # Δ_1 (…, n, 1)
    Y, d = Y.clone(), -r_match.clone()
    d[..., 0, :] += (Y[..., 0, :, :] @ first).squeeze(-1)         # x_1 = Y_1 Δ_1 − r_1, then x_0 = 0
    L, shift = d.shape[-2], 1
    while shift < L:
        d[..., shift:, :] = d[..., shift:, :] + (Y[..., shift:, :, :] @ d[..., :-shift, :, None]).squeeze(-1)
        if 2 * shift < L:                       # the products the next level composes with
            Y[..., shift:, :, :] = Y[..., shift:, :, :] @ Y[..., :-shift, :, :]
        shift *= 2
    return torch.cat([first.transpose(-1, -2), d], -2), info != 0


def _reduce(Y: Tensor, B_a: Tensor, B_b: Tensor) -> tuple[BlockFactorization, list[Tensor], Tensor]:
    """The cyclic reduction of :func:`factorize` (module docstring) on Y (…, m−1, n, n): the
    factorisation without its last block (``lu``, ``pivots`` None), each level's pivot ratios
    (…, P) and the row-equilibrated last block E (…, 2n, 2n) of Δ_1, Δ_m."""
    L, n, _ = Y.shape[-3:]
    batch = Y.shape[:-3]
    m = L + 1
    scale = _row_scale(Y, floor=1.0)      # rows of [Y_k, −I]: the −I contributes 1
    P = Y * scale[..., None]
    Qc = torch.diag_embed(-scale)
    var = torch.arange(m, device=Y.device)
    levels: list[_Level] = []
    pivots: list[Tensor] = []        # per level, each pair's smallest pivot ratio (the rank test)
    fast = accelerator_paths(Y)
    while P.shape[-3] > 1:
        L = P.shape[-3]
        npair = L // 2
        Pa, Qa = P[..., 0:2 * npair:2, :, :], Qc[..., 0:2 * npair:2, :, :]
        Pb, Qb = P[..., 1:2 * npair:2, :, :], Qc[..., 1:2 * npair:2, :, :]
        column = torch.cat([Qa, Pb], dim=-2)
        reflectors, tau = torch.geqrf(column)         # column = Q [R; 0], Q kept as reflectors
        pair = Pa.new_zeros(*batch, npair, 2 * n, 2 * n)
        pair[..., :n, :n], pair[..., n:, n:] = Pa, Qb
        wy = wy_form(reflectors, tau) if fast else None
        rotated = apply_qt(reflectors, tau, pair, wy)     # Qᵀ [Pa 0; 0 Qb]
        R = reflectors[..., :n, :]                    # upper triangle (the solves read only it)
        # |R_jj| / ‖column j‖ is the sine of the angle between column j and the span of the
        # columns before it: independent of the columns' scales (the units of the unknowns)
        norms = column.square().sum(-2).sqrt().clamp_min(1e-300)
        pivots.append((R.diagonal(dim1=-2, dim2=-1).abs() / norms).amin(-1))
        odd = bool(L % 2)
        reduced = rotated[..., n:, :]                 # [P' Q'] of the chain of half the length
        lscale = _row_scale(reduced)                  # re-equilibrate its rows
        levels.append(_Level(reflectors, tau, rotated[..., :n, :], R, var[1:2 * npair:2], odd, lscale, wy))
        reduced = reduced * lscale[..., None]
        if odd:                                       # the last chain row waits for the next level
            P = torch.cat([reduced[..., :n], P[..., -1:, :, :]], -3)
            Qc = torch.cat([reduced[..., n:], Qc[..., -1:, :, :]], -3)
        else:
            P, Qc = reduced[..., :n], reduced[..., n:]
        var = torch.cat([var[0:L:2], var[-1:]]) if odd else var[0::2]
    p = B_a.shape[-2]
    top = torch.cat([B_a, torch.zeros_like(B_a)], dim=-1)
    mid = torch.cat([P[..., 0, :, :], Qc[..., 0, :, :]], dim=-1)
    bot = torch.cat([torch.zeros_like(B_b), B_b], dim=-1)
    E = torch.cat([top, mid, bot], dim=-2)
    row_scale = E.abs().amax(dim=-1).clamp_min(1e-300)               # row equilibration
    E = E / row_scale[..., None]
    return BlockFactorization(levels, scale, None, None, row_scale, m, n, p), pivots, E


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
        J[p + k * n:p + (k + 1) * n, (k + 1) * n:(k + 2) * n] = -torch.eye(n, dtype=Y.dtype, device=Y.device)
    J[p + L * n:, (m - 1) * n:] = B_b
    return J
