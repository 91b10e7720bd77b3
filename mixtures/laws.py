"""Material laws of the confined-compression mixture (report ch. 5): small pluggable classes of the
element strain ``e`` (tension positive, negative in compression) used by
:class:`mixtures.confined.ConfinedCompression`.

The solid law gives the effective stress ``σᵉ(e, H)`` and its tangent; a non-linear law enters the
momentum balance through ``F(s,θ) = −assembled(σᵉ(e) − H e)`` (``F ≡ 0`` for
:class:`LinearSolid`).  The permeability law gives the element permeability ``k(e, K)`` of the
mass balance ``R* v + K(s,θ) p = 0`` (:class:`ConstantPermeability`; Lai & Mow's
:class:`ExponentialPermeability`).  All are torch, vectorised over elements and batched; the
parameters (``H``, ``K``, ``β``, ``M``) broadcast against ``e`` of shape ``(..., N)``.
"""
from __future__ import annotations

import math

import torch

__all__ = ["LinearSolid", "ExponentialSolid", "ConstantPermeability", "ExponentialPermeability", "Tensorish"]

Tensorish = float | torch.Tensor


# ----------------------------------------------------------------------------------------------
# material laws (functions of the element strain e; e has shape (..., N), parameters broadcast)
# ----------------------------------------------------------------------------------------------
class LinearSolid:
    """Linear elastic solid: ``σᵉ(e) = H e`` (tangent modulus ``H``); gives ``F ≡ 0``."""

    linear = True

    def stress(self, e: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
        return H * e

    def tangent(self, e: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
        return H * torch.ones_like(e)

    def __repr__(self) -> str:
        return "LinearSolid()"


class ExponentialSolid:
    """Strain-stiffening solid in the spirit of Holmes & Mow (1990) (not their exact law).

    With the compressive strain ``ε_c = −e ≥ 0`` the compressive stress is
    ``σ_c = (H/β)(exp(β ε_c) − 1)``, i.e. in the tension-positive convention ::

        σᵉ(e) = −(H/β) · expm1(−β e),      dσᵉ/de = H · exp(−β e).

    The tangent modulus equals ``H`` at ``e = 0`` and grows exponentially with compression
    (``β > 0``); ``β = 0`` is the linear solid.  ``β`` may be a float or a tensor broadcastable
    to the element-strain shape ``(..., N)`` (e.g. shape ``(..., 1)`` for a batch).
    """

    linear = False

    def __init__(self, beta: Tensorish = 1.0):
        if not isinstance(beta, torch.Tensor) and not math.isfinite(float(beta)):
            raise ValueError("beta must be finite")
        self.beta = beta

    def stress(self, e: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
        beta = torch.as_tensor(self.beta, dtype=e.dtype, device=e.device)
        x = -beta * e
        # (H/β)·(−expm1(−βe)), written so that β → 0 is exact: expm1(x)/x → 1.
        small = x.abs() < 1e-8
        safe_x = torch.where(small, torch.ones_like(x), x)
        ratio = torch.where(small, 1.0 + 0.5 * x, torch.expm1(safe_x) / safe_x)
        return H * e * ratio

    def tangent(self, e: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
        beta = torch.as_tensor(self.beta, dtype=e.dtype, device=e.device)
        return H * torch.exp(-beta * e)

    def __repr__(self) -> str:
        return f"ExponentialSolid(beta={self.beta!r})"


class ConstantPermeability:
    """Strain-independent permeability ``k(e) = K``."""

    linear = True

    def __call__(self, e: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
        return K * torch.ones_like(e)

    def __repr__(self) -> str:
        return "ConstantPermeability()"


class ExponentialPermeability:
    """Strain-dependent permeability of Lai & Mow (1980): ``k(e) = K · exp(M e)``.

    ``e`` is the element strain (volumetric in confined compression; negative in compression),
    so ``M > 0`` lowers the permeability of a compressed sample.  ``M = 0`` is the constant law.
    ``M`` may be a float or a tensor broadcastable to ``(..., N)``.
    """

    def __init__(self, M: Tensorish = 1.0):
        if not isinstance(M, torch.Tensor) and not math.isfinite(float(M)):
            raise ValueError("M must be finite")
        self.M = M

    @property
    def linear(self) -> bool:
        return (not isinstance(self.M, torch.Tensor)) and float(self.M) == 0.0

    def __call__(self, e: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
        M = torch.as_tensor(self.M, dtype=e.dtype, device=e.device)
        return K * torch.exp(M * e)

    def __repr__(self) -> str:
        return f"ExponentialPermeability(M={self.M!r})"
