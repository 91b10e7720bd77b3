"""The two-stage Radau IIA method ([HW2] sec. IV.5)::

    Z_i = h Σ_j a_ij f(t + c_j h, y + Z_j),   y+ = y + Z_2,
    c = (1/3, 1),   A = [[5/12, −1/12], [3/4, 1/4]],   b = (3/4, 1/4),

order 3, L-stable and stiffly accurate; R(z) = (1 + z/3) / (1 − 2z/3 + z²/6).
"""
from __future__ import annotations

import torch
from torch import Tensor

from shootlab.bvp.tangents import rhs_jacobian
from shootlab.bvp.tangents import _const
from .implicit import HeldNewton, _differentiable, _ImplicitFixedStep, _lu_solve


class Radau3(_ImplicitFixedStep):
    """Two-stage Radau IIA method, order 3, L-stable, stiffly accurate
    ([HW2] sec. IV.5):

        c = (1/3, 1),   A = [[5/12, -1/12], [3/4, 1/4]],   b = (3/4, 1/4).

    Unknowns are the stage increments ``Z_i = h sum_j a_ij f(t + c_j h, y + Z_j)``
    (2n per row), found by simplified Newton from ``Z = 0`` with the 2n x 2n matrix
    ``I - h (A ⊗ J(t, y))``; both stages are evaluated in one rhs call.  ``y+ = y + Z_2``.
    Sensitivity (implicit function theorem, ``J_j`` at the converged stages):
    ``(I − h [a_ij J_j]) ∂Z/∂y = h [Σ_j a_ij J_j] S``,  ``S+ = S + ∂Z_2/∂y``.
    """

    name = "radau3"
    order = 3
    stable = "L-stable, stiffly accurate"
    description = "2-stage Radau IIA + simplified Newton, steps equal steps"

    @classmethod
    def stability(cls, z):
        """R(z) = (1 + z/3) / (1 − 2z/3 + z²/6)."""
        return (1.0 + z / 3.0) / (1.0 - 2.0 * z / 3.0 + z * z / 6.0)
    c = (1 / 3, 1.0)
    A = ((5 / 12, -1 / 12), (3 / 4, 1 / 4))

    @classmethod
    def stability_matrix(cls, Z: Tensor) -> Tensor:
        """R(Z) = (I − 2Z/3 + Z²/6)⁻¹ (I + Z/3)."""
        eye = torch.eye(Z.shape[-1], dtype=Z.dtype, device=Z.device)
        return torch.linalg.solve(eye - 2.0 * Z / 3.0 + Z @ Z / 6.0, eye + Z / 3.0)

    def _blocks(self, a: Tensor, J: Tensor, h: Tensor) -> Tensor:
        """``I − h [a_ij J_j]`` (r, 2n, 2n) from the stage Jacobians J (r, 2, n, n)."""
        r, _, n, _ = J.shape
        blocks = a[None, :, :, None, None] * J[:, None]  # [r, i, j] = a_ij J_j
        eye = torch.eye(2 * n, dtype=J.dtype, device=J.device)
        return eye - h[:, None, None] * blocks.permute(0, 1, 3, 2, 4).reshape(r, 2 * n, 2 * n)

    def _stages(self, rhs, t, y, h, exact: bool = True, held: HeldNewton | None = None):
        """Converged stage increments Z (m, 2, n) and, if ``exact``, the stage Jacobians
        J_j = J(t + c_j h, y + Z_j) (m, 2, n, n) (else None); ``held``: the Newton state held over the
        interval (:class:`~.implicit.HeldNewton`), else the Newton matrix from J(t, y) of the step."""
        m, n = y.shape
        a = torch.tensor(self.A, dtype=y.dtype, device=y.device)
        c = torch.tensor(self.c, dtype=y.dtype, device=y.device)
        t_st = t[:, None] + h[:, None] * c  # (m, 2) stage times
        hc, yd = h[:, None, None], y.detach()

        def G(rows, z):
            r = rows.numel()
            zz = z.view(r, 2, n)
            f = rhs(t_st[rows].reshape(-1), (yd[rows, None] + zz).reshape(-1, n)).view(r, 2, n)
            return (zz - hc[rows] * torch.einsum("ij,rjk->rik", a, f)).reshape(r, 2 * n)

        jacobian = self._held(held, lambda rows, z: rhs_jacobian(rhs, t[rows], yd[rows])[1])

        def matrix(rows, z):
            J = jacobian(rows, z)
            return self._blocks(a, J[:, None].expand(-1, 2, n, n), h[rows])

        z, ok, nfev = self._solve(G, matrix, y.new_zeros(m, 2 * n), self._newton_scale(y).repeat(1, 2), held)
        z, J = z.view(m, 2, n), None
        if exact:
            J = rhs_jacobian(rhs, t_st.reshape(-1), (yd[:, None] + z).reshape(-1, n))[1].view(m, 2, n, n)
            nfev += 1
        return z, ok, nfev, a, t_st, J

    def _step(self, rhs, t, y, h, held=None):
        m, n = y.shape
        z, ok, nfev, a, t_st, J = self._stages(rhs, t, y, h, exact=_differentiable(y), held=held)
        if J is None:
            return y + z[:, 1], ok, nfev
        # the differentiable Newton correction with the exact matrix (carries the tangents / graph)
        zz = _const(z, y)
        f = rhs(t_st.reshape(-1), (y[:, None] + zz).reshape(-1, n)).view(m, 2, n)
        g = zz - _const(h[:, None, None], y) * torch.einsum("ij,rjk->rik", _const(a, y), f)
        zz = zz - _lu_solve(self._blocks(a, J, h), g.reshape(m, 2 * n)).view(m, 2, n)
        return y + zz[:, 1], ok, nfev + 1

    def _step_sensitivity(self, rhs, t, y, S, h):
        z, ok, nfev, a, _, J = self._stages(rhs, t, y, h)
        m, n = y.shape
        if S is None:                                                         # an interval's first step: S = I
            JS, S = J, torch.eye(n, dtype=y.dtype, device=y.device)
        else:
            JS = J @ S[:, None]                                               # (m, 2, n, n): J_j S
        R = h[:, None, None, None] * torch.einsum("ij,rjkl->rikl", a, JS)     # h Σ_j a_ij J_j S
        dZ = _lu_solve(self._blocks(a, J, h), R.reshape(m, 2 * n, n)).view(m, 2, n, n)
        return y + z[:, 1], S + dZ[:, 1], ok, nfev

