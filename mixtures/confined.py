"""Confined compression of a biphasic (solid/fluid) mixture: a 1-D mixed finite-element model.

The experiment (report ch. 5, docs/design.md §3): a sample of height ``L`` sits in a rigid, tight
ring on a rigid, impermeable bottom and is loaded through a free-draining filter on top.

Discretisation
--------------
``z`` runs from the bottom (``z = 0``) to the top (``z = L``); ``N`` linear elements of length
``h = L/N``; nodes ``1 … N+1`` at ``z_i = (i-1) h``.  Displacement and pore pressure are both
linear per element.  Boundary conditions: ``s_1 = 0`` (rigid bottom), ``p_{N+1} = 0``
(free-draining filter).  Unknowns: displacements ``s = (s_2 … s_{N+1})`` and pressures
``p = (p_1 … p_N)``.  Both arrays have length ``N`` and are stored in node order, so
``s[..., -1]`` is the filter (top) displacement and ``p[..., 0]`` the bottom pressure.

Balance equations (small strain, intrinsically incompressible constituents)::

    R* v + K(s,θ) p = 0                         mass balance, v = ds/dt
    S(s,θ) s − R*ᵀ p − F(s,θ) − H_u u = 0       momentum

They are the Galerkin weak forms of ``∂v/∂z − ∂/∂z(k ∂p/∂z) = 0`` (tested with pressure shape
functions; impermeable bottom ⇒ no flux term) and ``∂/∂z(σᵉ − p) = 0`` (tested with displacement
shape functions; total stress ``σᵉ − p = −u`` at the filter).  Element matrices::

    ∫ N_a N_b' dz  = ½ [[−1, 1], [−1, 1]]      (rows: pressure test functions)  → R*
    ∫ N_a' N_b' dz = (1/h) [[1, −1], [−1, 1]]                                 → K, S

``R*`` keeps pressure rows ``1 … N`` and displacement columns ``2 … N+1``; ``K`` keeps pressure
nodes ``1 … N``; ``S`` keeps displacement nodes ``2 … N+1``.  For ``N = 3``
``R* = ½[[1,0,0],[0,1,0],[−1,0,1]]``.  In general ``R* = ½ (I − J²)`` with ``J`` the lower shift
matrix: lower triangular with ½ on the diagonal, hence always invertible, and constant (it depends
neither on ``s`` nor on the parameters).

Sign conventions
----------------
* ``s`` – nodal displacement in the **+z (upward)** direction; under a compressive load it is
  **negative**.  ``v = ds/dt`` likewise.
* ``p`` – pore (gauge) pressure, **positive under a compressive load**.
* ``u`` – applied load per unit area on the filter, **compression positive**.  It therefore enters
  with ``H_u = −e_N`` (minus the unit vector of the top displacement node):
  ``S s − R*ᵀ p − F + e_N u = 0``.
* Element strain ``e = (s_{i+1} − s_i)/h`` (extension positive, negative in compression);
  solid stress ``σᵉ(e)`` tension positive.
* Measured channels: ``filter_displacement(s) = −s_{N+1}`` is the **compression** of the sample
  (positive under load) and ``bottom_pressure = p_1`` (positive under load).  In the linear model
  with a steady load ``P`` the compression tends to ``P·L/H``.

Units are the report's dimensionless ones: ``H`` the confined compression (aggregate) modulus,
``K`` the permeability (Darcy: relative fluid flux ``= −K ∂p/∂z``), consolidation coefficient
``c = H·K`` (see :mod:`mixtures.terzaghi`).

Material laws are pluggable small classes of the element strain (see :class:`LinearSolid`,
:class:`ExponentialSolid`, :class:`ConstantPermeability`, :class:`ExponentialPermeability`).  A
non-linear solid stress is split as ``S(s,θ) s − F(s,θ)`` with ``S = H·(assembled ∫N'N')`` the
linear part at the reference state and ``F = −(assembled (σᵉ(e) − H e))`` the non-linear
remainder; ``F ≡ 0`` for the linear solid.

Everything in the model is torch, vectorised over elements (no Python loop over elements) and
batched over leading dimensions: ``s`` has shape ``(..., N)``; ``H``, ``K`` and ``u`` are floats
or tensors of shape ``(...)`` that broadcast against ``s.shape[:-1]`` and may carry autograd.

Forward simulation (:func:`simulate`) uses ``scipy.integrate.solve_ivp`` (Radau by default) with
the exact Jacobian; it supports load control (creep: step, ramp-and-hold, user history) and
displacement control (stress relaxation: the filter displacement is prescribed and the load is
the output).
"""
from __future__ import annotations

import csv
import dataclasses
import math
import os
from typing import Callable, NamedTuple, Sequence

import numpy as np
import torch
from scipy.integrate import solve_ivp

from shootlab.tangents import outside_transforms

__all__ = [
    "LinearSolid",
    "ExponentialSolid",
    "ConstantPermeability",
    "ExponentialPermeability",
    "ConfinedCompression",
    "Matrices",
    "StepLoad",
    "RampHoldLoad",
    "SampledHistory",
    "CallableHistory",
    "as_history",
    "Simulation",
    "simulate",
    "creep",
    "stress_relaxation",
    "Measurements",
    "MEASUREMENT_COLUMNS",
    "DEFAULT_EXPERIMENT",
    "simulated_measurements",
    "write_measurements_csv",
    "read_measurements_csv",
]

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


# ----------------------------------------------------------------------------------------------
# the finite-element model
# ----------------------------------------------------------------------------------------------
class Matrices(NamedTuple):
    """System matrices at a state, batched: shapes ``(..., N, N)`` / ``(..., N)``."""

    Rstar: torch.Tensor
    Kmat: torch.Tensor
    Smat: torch.Tensor
    Fvec: torch.Tensor
    Hu: torch.Tensor


def _check_positive(name: str, value) -> None:
    """Raise ValueError unless every entry of ``value`` is finite and > 0 (detached check)."""
    if isinstance(value, torch.Tensor):
        v = value.detach()
        if v.numel() == 0:
            raise ValueError(f"{name} is empty")
        if not bool(torch.all(torch.isfinite(v))) or not bool(torch.all(v > 0)):
            raise ValueError(f"{name} must be finite and > 0, got {value}")
    else:
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a positive number, got {value!r}") from exc
        if arr.size == 0 or not np.all(np.isfinite(arr)) or not np.all(arr > 0):
            raise ValueError(f"{name} must be finite and > 0, got {value!r}")


class ConfinedCompression:
    """1-D mixed (linear/linear) FE model of confined compression; see the module docstring.

    Parameters
    ----------
    elements : number of elements ``N ≥ 1`` (the report used 3).
    length : sample height ``L > 0``.
    solid : solid law with ``stress(e, H)`` / ``tangent(e, H)`` (default :class:`LinearSolid`).
    permeability : permeability law ``k(e, K)`` (default :class:`ConstantPermeability`).

    The torch functions (:meth:`matrices`, :meth:`pressure`, :meth:`velocity`, ...) do not
    validate the values of ``H`` and ``K`` (an estimator may probe any value and they must stay
    cheap and differentiable); :func:`simulate` and :meth:`linear_system` raise ``ValueError``
    for ``H ≤ 0`` or ``K ≤ 0``.
    """

    def __init__(self, elements: int = 3, length: float = 1.0, solid=None, permeability=None):
        if isinstance(elements, bool) or int(elements) != elements:
            raise ValueError(f"elements must be an integer, got {elements!r}")
        elements = int(elements)
        if elements < 1:
            raise ValueError(f"need at least one element, got N = {elements}")
        _check_positive("length", length)
        self.N = elements
        self.L = float(length)
        self.h = self.L / self.N
        self.solid = LinearSolid() if solid is None else solid
        self.permeability = ConstantPermeability() if permeability is None else permeability
        N = self.N
        # Constant matrices, built once (float64 numpy; torch copies cached per dtype/device).
        R_full = np.zeros((N + 1, N + 1))
        # element e (nodes e, e+1): rows e and e+1 each receive ½[−1, 1] in columns e, e+1
        el = np.arange(N)
        rows = np.concatenate([el, el, el + 1, el + 1])
        cols = np.concatenate([el, el + 1, el, el + 1])
        vals = np.concatenate([-0.5 * np.ones(N), 0.5 * np.ones(N)] * 2)
        np.add.at(R_full, (rows, cols), vals)
        self._Rstar = R_full[:N, 1:].copy()
        self._Rstar_inv = np.linalg.inv(self._Rstar)  # exact: entries are 0 and 2
        self._unit_K = self._tridiag_numpy(np.ones(N))[:N, :N]
        self._unit_S = self._tridiag_numpy(np.ones(N))[1:, 1:]
        self._Hu = np.zeros(N)
        self._Hu[-1] = -1.0
        self._cache: dict = {}

    # -- small helpers ------------------------------------------------------------------------
    def __repr__(self) -> str:
        return (f"ConfinedCompression(elements={self.N}, length={self.L}, solid={self.solid!r}, "
                f"permeability={self.permeability!r})")

    @property
    def is_linear(self) -> bool:
        """True when both material laws are linear (then ``s' = M s + b u`` exactly)."""
        return bool(getattr(self.solid, "linear", False)) and bool(
            getattr(self.permeability, "linear", False))

    @property
    def nodes(self) -> np.ndarray:
        """Node positions ``z_1 … z_{N+1}`` (from the bottom)."""
        return np.linspace(0.0, self.L, self.N + 1)

    def _tridiag_numpy(self, c: np.ndarray) -> np.ndarray:
        N, h = self.N, self.h
        A = np.zeros((N + 1, N + 1))
        d = np.zeros(N + 1)
        d[:-1] += c
        d[1:] += c
        A[np.arange(N + 1), np.arange(N + 1)] = d / h
        A[np.arange(N), np.arange(1, N + 1)] = -c / h
        A[np.arange(1, N + 1), np.arange(N)] = -c / h
        return A

    def _const(self, name: str, dtype, device) -> torch.Tensor:
        key = (name, dtype, device)
        if key not in self._cache:
            # a tensor made inside a torch.func transform would be that transform's (and escape
            # it through the cache): the constant is made outside them
            with outside_transforms():
                self._cache[key] = torch.as_tensor(getattr(self, name), dtype=dtype, device=device)
        return self._cache[key]

    @staticmethod
    def _dtype_of(*xs) -> torch.dtype:
        for x in xs:
            if isinstance(x, torch.Tensor) and x.is_floating_point():
                return x.dtype
        return torch.float64

    def _prepare(self, s, *params):
        """Cast ``s`` and parameters to tensors of a common dtype; check the trailing size."""
        dtype = self._dtype_of(s, *params)
        device = s.device if isinstance(s, torch.Tensor) else None
        s = torch.as_tensor(s, dtype=dtype, device=device)
        if s.ndim < 1 or s.shape[-1] != self.N:
            raise ValueError(f"s must have shape (..., {self.N}), got {tuple(s.shape)}")
        out = [torch.as_tensor(q, dtype=dtype, device=s.device) for q in params]
        return s, out

    # -- kinematics / laws ---------------------------------------------------------------------
    def full_displacement(self, s: torch.Tensor) -> torch.Tensor:
        """Prepend the fixed bottom displacement ``s_1 = 0``: shape ``(..., N+1)``."""
        return torch.nn.functional.pad(s, (1, 0))

    def element_strain(self, s) -> torch.Tensor:
        """Element strains ``e_i = (s_{i+1} − s_i)/h``, shape ``(..., N)`` (tension positive)."""
        s, _ = self._prepare(s)
        return self._strain(s)

    def _element_coefficients(self, s, H, K):
        e = self.element_strain(s)
        He, Ke = H.unsqueeze(-1), K.unsqueeze(-1)
        k = self.permeability(e, Ke)
        sigma = self.solid.stress(e, He)
        return e, He, k, sigma

    def _assemble_tridiag(self, c: torch.Tensor) -> torch.Tensor:
        """Assemble ``Σ_e c_e (1/h)[[1,−1],[−1,1]]`` over all nodes: ``(..., N+1, N+1)``."""
        pad = torch.nn.functional.pad
        diag = (pad(c, (1, 0)) + pad(c, (0, 1))) / self.h
        off = -c / self.h
        return torch.diag_embed(diag) + torch.diag_embed(off, 1) + torch.diag_embed(off, -1)

    @staticmethod
    def _assemble_element_force(f: torch.Tensor) -> torch.Tensor:
        """Nodal vector ``Σ_e f_e [−1, +1]`` on nodes 1 … N+1: ``(..., N+1)``."""
        pad = torch.nn.functional.pad
        return pad(f, (1, 0)) - pad(f, (0, 1))

    # -- public model functions ----------------------------------------------------------------
    def matrices(self, s, H, K) -> Matrices:
        """``(Rstar, Kmat, Smat, Fvec, Hu)`` at the state ``s`` (batched, differentiable).

        ``Rstar``: ``R*`` (constant); ``Kmat``: ``K(s,θ)``, assembled with the element
        permeability ``k(e)``; ``Smat``: ``S(s,θ) = H ·(assembled ∫N'N')`` (linear part);
        ``Fvec``: ``F(s,θ) = −assembled(σᵉ(e) − H e)`` (zero for the linear solid); ``Hu``:
        ``−e_N``.  All are expanded to the broadcast batch shape of ``s``, ``H`` and ``K``.
        """
        s, (H, K) = self._prepare(s, H, K)
        batch = torch.broadcast_shapes(s.shape[:-1], H.shape, K.shape)
        N, dt, dev = self.N, s.dtype, s.device
        e, He, k, sigma = self._element_coefficients(s, H, K)
        Kfull = self._assemble_tridiag(k.expand(batch + (N,)))
        Kmat = Kfull[..., :N, :N]
        Smat = He.unsqueeze(-1) * self._const("_unit_S", dt, dev)
        Smat = Smat.expand(batch + (N, N))
        if getattr(self.solid, "linear", False):
            Fvec = torch.zeros(batch + (N,), dtype=dt, device=dev)
        else:
            Fvec = -self._assemble_element_force(sigma - He * e)[..., 1:]
            Fvec = Fvec.expand(batch + (N,))
        Rstar = self._const("_Rstar", dt, dev).expand(batch + (N, N))
        Hu = self._const("_Hu", dt, dev).expand(batch + (N,))
        return Matrices(Rstar, Kmat, Smat, Fvec, Hu)

    # internal kernels: tensors already prepared, strain computed once
    def _strain(self, s: torch.Tensor) -> torch.Tensor:
        sf = torch.nn.functional.pad(s, (1, 0))
        return (sf[..., 1:] - sf[..., :-1]) / self.h

    def _internal_force(self, e, H):
        sigma = self.solid.stress(e, H.unsqueeze(-1))
        return self._assemble_element_force(sigma)[..., 1:]

    def _K_times(self, e, K, p):
        k = self.permeability(e, K.unsqueeze(-1))
        pf = torch.nn.functional.pad(p, (0, 1))  # p_{N+1} = 0
        g = k * (pf[..., :-1] - pf[..., 1:]) / self.h  # element term, node e − node e+1
        return self._assemble_element_force(-g)[..., :-1]

    def _pressure(self, e, u, H):
        rhs = self._internal_force(e, H)
        rhs = rhs + torch.nn.functional.pad(u.unsqueeze(-1), (self.N - 1, 0))  # − H_u u
        # p = R*⁻ᵀ rhs  ⇔  pᵀ = rhsᵀ R*⁻¹
        return rhs @ self._const("_Rstar_inv", e.dtype, e.device)

    def internal_force(self, s, H) -> torch.Tensor:
        """``S(s,θ) s − F(s,θ)`` = assembled solid stress on nodes 2 … N+1 (matrix-free)."""
        s, (H,) = self._prepare(s, H)
        return self._internal_force(self._strain(s), H)

    def permeability_product(self, s, K, p) -> torch.Tensor:
        """``K(s,θ) p`` (matrix-free, tridiagonal), shape ``(..., N)``."""
        s, (K, p) = self._prepare(s, K, p)
        return self._K_times(self._strain(s), K, p)

    def pressure(self, s, u, H, K=None) -> torch.Tensor:
        """Pore pressures ``p_1 … p_N`` from the momentum balance.

        ``p = R*⁻ᵀ (S s − F − H_u u)``; ``K`` is accepted for a uniform signature but unused.
        """
        s, (u, H) = self._prepare(s, u, H)
        return self._pressure(self._strain(s), u, H)

    def velocity(self, s, u, H, K) -> torch.Tensor:
        """``v = ds/dt = −R*⁻¹ K(s,θ) p`` with ``p`` from :meth:`pressure`."""
        s, (u, H, K) = self._prepare(s, u, H, K)
        return self._velocity(s, u, H, K)

    def _velocity(self, s, u, H, K):
        e = self._strain(s)
        Kp = self._K_times(e, K, self._pressure(e, u, H))
        return -Kp @ self._const("_Rstar_inv", s.dtype, s.device).transpose(-1, -2)

    def rhs(self, t, s, H, K, load_fn: Callable) -> torch.Tensor:
        """Right-hand side of the forward model ``s' = velocity(s, u(t))`` (load control)."""
        return self.velocity(s, load_fn(t), H, K)

    def residuals(self, s, v, p, u, H, K):
        """Residuals of the two balances ``(R* v + K p, S s − R*ᵀ p − F − H_u u)``."""
        s, (v, p, u, H, K) = self._prepare(s, v, p, u, H, K)
        R = self._const("_Rstar", s.dtype, s.device)
        mass = v @ R.transpose(-1, -2) + self.permeability_product(s, K, p)
        mom = (self.internal_force(s, H) - p @ R
               + torch.nn.functional.pad(u.unsqueeze(-1), (self.N - 1, 0)))
        return mass, mom

    def filter_displacement(self, s) -> torch.Tensor:
        """Measured displacement channel: compression of the sample ``−s_{N+1}`` (≥ 0 in creep)."""
        s, _ = self._prepare(s)
        return -s[..., -1]

    def bottom_pressure(self, s, u, H, K=None) -> torch.Tensor:
        """Measured pressure channel: pore pressure at the bottom ``p_1``."""
        return self.pressure(s, u, H)[..., 0]

    def equilibrium(self, u, H) -> torch.Tensor:
        """Drained steady state for a constant load ``u`` (``p = 0``): solves ``S s − F = −H_u u``.

        Linear solid: ``s_i = −u z_i / H`` (uniform strain ``−u/H``).  For a non-linear solid the
        uniform strain ``e`` solves ``σᵉ(e) = −u`` (scalar Newton, batched).
        """
        H = torch.as_tensor(H, dtype=self._dtype_of(H, u))
        u = torch.as_tensor(u, dtype=H.dtype)
        z = torch.as_tensor(self.nodes[1:], dtype=H.dtype)
        e = -u / H
        if not getattr(self.solid, "linear", False):
            for _ in range(100):
                r = self.solid.stress(e, H) + u
                e_new = e - r / self.solid.tangent(e, H)
                if bool(torch.all((e_new - e).abs() <= 1e-15 * (1 + e.abs()))):
                    e = e_new
                    break
                e = e_new
        return e.unsqueeze(-1) * z

    # -- linear system form (numpy; used by the stiff integrator) ------------------------------
    def linear_system(self, H: float, K: float) -> tuple[np.ndarray, np.ndarray]:
        """``(M, b)`` with ``s' = M s + b u`` (linear laws only): ``M = −R*⁻¹ K R*⁻ᵀ S``."""
        if not self.is_linear:
            raise ValueError("linear_system() needs linear material laws")
        _check_positive("H", H)
        _check_positive("K", K)
        Ri = self._Rstar_inv
        G = Ri @ (float(K) * self._unit_K) @ Ri.T
        return -G @ (float(H) * self._unit_S), G @ self._Hu

    def relaxation_load(self, s, v_top, H, K) -> torch.Tensor:
        """Load ``u`` for which the top velocity equals ``v_top`` (displacement control).

        ``v(s, u)`` is affine in ``u``; its top component has a strictly negative slope
        ``−e_Nᵀ R*⁻¹ K R*⁻ᵀ e_N`` (``K`` positive definite), so ``u`` is unique.
        """
        s, (v_top, H, K) = self._prepare(s, v_top, H, K)
        v0 = self.velocity(s, torch.zeros_like(v_top), H, K)[..., -1]
        v1 = self.velocity(s, torch.ones_like(v_top), H, K)[..., -1]
        return (v_top - v0) / (v1 - v0)


# ----------------------------------------------------------------------------------------------
# prescribed histories (loads or displacements)
# ----------------------------------------------------------------------------------------------
class StepLoad:
    """``u(t) = P`` for ``t ≥ t0`` and 0 before (right-continuous)."""

    def __init__(self, magnitude: float = 1.0, t0: float = 0.0):
        self.magnitude, self.t0 = float(magnitude), float(t0)
        if not (math.isfinite(self.magnitude) and math.isfinite(self.t0)):
            raise ValueError("StepLoad needs finite magnitude and t0")

    @property
    def breakpoints(self) -> tuple:
        return (self.t0,)

    def value(self, t, left: bool = False):
        t = np.asarray(t, dtype=float)
        on = (t > self.t0) if left else (t >= self.t0)
        return np.where(on, self.magnitude, 0.0)

    def rate(self, t, left: bool = False):
        return np.zeros_like(np.asarray(t, dtype=float))

    def check_covers(self, t0, t1):
        pass

    __call__ = value

    def __repr__(self):
        return f"StepLoad(magnitude={self.magnitude}, t0={self.t0})"


class RampHoldLoad:
    """Linear ramp from 0 at ``t_start`` to ``P`` at ``t_start + t_ramp``, then held.

    ``t_ramp = 0`` is a step.  Used for loads (creep) and for prescribed compressions
    (stress relaxation).
    """

    def __init__(self, magnitude: float = 1.0, t_ramp: float = 0.1, t_start: float = 0.0):
        self.magnitude, self.t_ramp, self.t_start = float(magnitude), float(t_ramp), float(t_start)
        if not all(map(math.isfinite, (self.magnitude, self.t_ramp, self.t_start))):
            raise ValueError("RampHoldLoad needs finite arguments")
        if self.t_ramp < 0:
            raise ValueError(f"t_ramp must be ≥ 0, got {t_ramp}")

    @property
    def breakpoints(self) -> tuple:
        return (self.t_start, self.t_start + self.t_ramp)

    def value(self, t, left: bool = False):
        t = np.asarray(t, dtype=float)
        if self.t_ramp == 0.0:
            return StepLoad(self.magnitude, self.t_start).value(t, left)
        return self.magnitude * np.clip((t - self.t_start) / self.t_ramp, 0.0, 1.0)

    def rate(self, t, left: bool = False):
        t = np.asarray(t, dtype=float)
        if self.t_ramp == 0.0:
            return np.zeros_like(t)
        a, b = self.t_start, self.t_start + self.t_ramp
        inside = ((t > a) & (t <= b)) if left else ((t >= a) & (t < b))
        return np.where(inside, self.magnitude / self.t_ramp, 0.0)

    def check_covers(self, t0, t1):
        pass

    __call__ = value

    def __repr__(self):
        return (f"RampHoldLoad(magnitude={self.magnitude}, t_ramp={self.t_ramp}, "
                f"t_start={self.t_start})")


class SampledHistory:
    """Piecewise-linear interpolation of samples ``(t_k, y_k)``; must cover the simulated time."""

    def __init__(self, t, y):
        t = np.asarray(t, dtype=float)
        y = np.asarray(y, dtype=float)
        if t.ndim != 1 or y.shape != t.shape or t.size < 2:
            raise ValueError("a sampled history needs 1-D arrays t, y of equal length ≥ 2")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
            raise ValueError("sampled history contains non-finite values")
        if np.any(np.diff(t) <= 0):
            raise ValueError("sample times of a history must be strictly increasing")
        self.t, self.y = t, y
        self._slopes = np.diff(y) / np.diff(t)

    @property
    def breakpoints(self) -> tuple:
        return tuple(self.t[1:-1])

    def check_covers(self, t0, t1):
        span = self.t[-1] - self.t[0]
        tol = 1e-12 * max(1.0, abs(span))
        if t0 < self.t[0] - tol or t1 > self.t[-1] + tol:
            raise ValueError(f"the history covers [{self.t[0]}, {self.t[-1]}] but the simulation "
                             f"needs [{t0}, {t1}]")

    def value(self, t, left: bool = False):
        return np.interp(t, self.t, self.y)

    def rate(self, t, left: bool = False):
        t = np.asarray(t, dtype=float)
        side = "left" if left else "right"
        k = np.searchsorted(self.t, t, side=side) - 1
        k = np.clip(k, 0, self._slopes.size - 1)
        return self._slopes[k]

    __call__ = value

    def __repr__(self):
        return f"SampledHistory({self.t.size} samples on [{self.t[0]}, {self.t[-1]}])"


class CallableHistory:
    """A user function ``f(t)`` (assumed smooth between the given ``breakpoints``).

    ``rate`` uses ``derivative`` if given, else a central finite difference (one-sided at the
    breakpoints on the requested side).
    """

    def __init__(self, fn: Callable, derivative: Callable | None = None,
                 breakpoints: Sequence[float] = ()):
        if not callable(fn):
            raise ValueError("history must be callable")
        self.fn, self.derivative = fn, derivative
        self._breaks = tuple(float(b) for b in breakpoints)

    @property
    def breakpoints(self) -> tuple:
        return self._breaks

    def check_covers(self, t0, t1):
        for tt in (t0, t1):
            val = np.asarray(self.fn(tt), dtype=float)
            if val.size != 1 or not np.isfinite(val).all():
                raise ValueError(f"history does not give a finite scalar at t = {tt}")

    @staticmethod
    def _map(fn, t):
        t = np.asarray(t, dtype=float)
        if t.ndim == 0:
            return float(fn(float(t)))
        return np.vectorize(lambda x: float(fn(float(x))), otypes=[float])(t)

    def value(self, t, left: bool = False):
        return self._map(self.fn, t)

    def rate(self, t, left: bool = False):
        t = np.asarray(t, dtype=float)
        if self.derivative is not None:
            return self._map(self.derivative, t)
        d = 1e-6 * np.maximum(1.0, np.abs(t))
        if left:
            return (self.value(t) - self.value(t - d)) / d
        return (self.value(t + d) - self.value(t - d)) / (2 * d)

    __call__ = value


def as_history(obj):
    """Coerce a history spec: a number (step at t = 0), ``(t, y)`` samples, a callable, or a
    history object (:class:`StepLoad`, :class:`RampHoldLoad`, :class:`SampledHistory`, ...)."""
    if isinstance(obj, (StepLoad, RampHoldLoad, SampledHistory, CallableHistory)):
        return obj
    if isinstance(obj, (int, float, np.floating, np.integer)) and not isinstance(obj, bool):
        return StepLoad(float(obj))
    if isinstance(obj, (tuple, list)) and len(obj) == 2:
        return SampledHistory(*obj)
    if isinstance(obj, Measurements):
        return SampledHistory(obj.t, obj.load)
    if isinstance(obj, dict) and {"t", "load"} <= set(obj):
        return SampledHistory(obj["t"], obj["load"])
    if hasattr(obj, "value") and hasattr(obj, "breakpoints"):
        return obj
    if callable(obj):
        return CallableHistory(obj)
    raise ValueError(f"cannot interpret {obj!r} as a load/displacement history")


# ----------------------------------------------------------------------------------------------
# forward simulation
# ----------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Simulation:
    """Time series of a forward simulation (numpy arrays).

    ``displacement`` is the compression ``−s_{N+1}`` (positive under load), ``pressure`` the bottom
    pore pressure ``p_1``; ``s``/``p`` the nodal values (``(T, N)``, nodes 2…N+1 / 1…N).
    """

    t: np.ndarray
    load: np.ndarray
    displacement: np.ndarray
    pressure: np.ndarray
    s: np.ndarray
    p: np.ndarray
    H: float
    K: float
    control: str
    nfev: int = 0
    info: dict = dataclasses.field(default_factory=dict)

    def measurements(self) -> "Measurements":
        return Measurements(self.t.copy(), self.load.copy(), self.displacement.copy(),
                            self.pressure.copy())


def _check_times(t_eval) -> np.ndarray:
    t = np.asarray(t_eval, dtype=float)
    if t.ndim != 1 or t.size < 1:
        raise ValueError("t_eval must be a non-empty 1-D array")
    if not np.all(np.isfinite(t)):
        raise ValueError("t_eval contains non-finite values")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        raise ValueError("t_eval must be strictly increasing")
    return t


def _segments(t0: float, t1: float, breakpoints) -> list[tuple[float, float]]:
    inner = sorted({float(b) for b in breakpoints if t0 < float(b) < t1})
    edges = [t0] + inner + [t1]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def simulate(model: ConfinedCompression, t_eval, load=None, H: float = 2.0, K: float = 1.0, *,
             displacement=None, s0=None, rtol: float = 1e-10, atol: float = 1e-12,
             method: str = "Radau", max_step: float = np.inf) -> Simulation:
    """Forward simulation of the confined-compression experiment.

    Exactly one of

    * ``load`` – load control (creep): a number (step at ``t = 0``), :class:`StepLoad`,
      :class:`RampHoldLoad`, ``(t_samples, u_samples)`` or a callable ``u(t)``; compression
      positive.
    * ``displacement`` – displacement control (stress relaxation): the prescribed compression
      ``d(t) = −s_{N+1}(t)`` of the sample, same kinds of spec.  It must be continuous (an
      instantaneous compression of an incompressible mixture needs an infinite load) and
      ``d(t_eval[0]) = 0`` unless ``s0`` is given.  The load is then an output.

    The state starts at ``s0`` (default: unloaded, ``s = 0``) at ``t_eval[0]``.  The stiff system
    is integrated with ``scipy.integrate.solve_ivp`` (``method`` Radau/BDF/LSODA), split at the
    breakpoints of the prescribed history, with the exact Jacobian:

    * linear laws: the system is affine, ``y' = J y + g(t)`` with constant ``J`` (``J = M``,
      ``g = b u`` under load control).  It is integrated in the eigenbasis of ``J`` (real,
      negative eigenvalues; ``M = −R*⁻¹KR*⁻ᵀS`` is similar to a symmetric matrix), where the
      Jacobian is diagonal.  This matters: the stiffest eigenvalue grows like ``N⁴`` (≈ −7e7 for
      ``N = 48``), and in nodal coordinates rounding in ``M s`` stalls the step control at tight
      tolerances.
    * non-linear laws: nodal coordinates, Jacobian by autograd; ``rtol`` is raised to at least
      ``4·eps·|λ_max/λ_min|`` of the initial Jacobian (the rounding floor), reported in
      ``Simulation.info``.

    Returns a :class:`Simulation` with the load, the compression, the bottom pressure and the
    nodal ``s`` and ``p`` at ``t_eval``.
    """
    _check_positive("H", H)
    _check_positive("K", K)
    H, K = float(H), float(K)
    if not isinstance(model, ConfinedCompression):
        raise ValueError("model must be a ConfinedCompression")
    t = _check_times(t_eval)
    if (load is None) == (displacement is None):
        raise ValueError("give exactly one of load= (creep) or displacement= (relaxation)")
    if not (rtol > 0 and atol > 0):
        raise ValueError("rtol and atol must be > 0")
    N = model.N
    if s0 is None:
        s_init = np.zeros(N)
    else:
        s_init = np.asarray(s0, dtype=float).reshape(-1)
        if s_init.size != N or not np.all(np.isfinite(s_init)):
            raise ValueError(f"s0 must be {N} finite numbers")
        s_init = s_init.copy()

    def Tt(x):
        return torch.as_tensor(x, dtype=torch.float64)

    hist = as_history(load if load is not None else displacement)
    hist.check_covers(t[0], t[-1])
    breakpoints = tuple(hist.breakpoints)
    if load is not None and isinstance(hist, SampledHistory):
        breakpoints = ()  # a piecewise-linear load is continuous: no need to restart at kinks

    if load is not None:
        control = "load"
        y0 = s_init

        H_t, K_t = Tt(H), Tt(K)

        def vel(y, tt, left):
            u = Tt(float(hist.value(tt, left=left)))
            return model._velocity(y, u, H_t, K_t)
    else:
        control = "displacement"
        d0 = float(hist.value(t[0]))
        if s0 is None and d0 != 0.0:
            raise ValueError("the prescribed compression must start at 0 unless s0 is given "
                             f"(d(t0) = {d0})")
        s_init[-1] = -d0
        y0 = s_init[:-1]

        def interior(y, top, vtop):
            s_full = torch.cat([y, top.reshape(1)])
            u = model.relaxation_load(s_full, vtop, H, K)
            return model.velocity(s_full, u, H, K)[:-1]

        def vel(y, tt, left):
            top = Tt(-float(hist.value(tt, left=left)))
            vtop = Tt(-float(hist.rate(tt, left=left)))
            return interior(y, top, vtop)

    def f_factory(a, b):
        def f(tt, y):
            return vel(Tt(y), tt, tt >= b).numpy()
        return f

    def jac_at(tt, y, left=False):
        return torch.func.jacrev(lambda x: vel(x, tt, left))(Tt(y)).numpy()

    info = {"method": method, "rtol": rtol, "atol": atol}
    n = y0.size
    basis = None
    if model.is_linear and n > 0:
        if control == "load":
            J, bvec = model.linear_system(H, K)

            def g_factory(a, b):
                return lambda tt: bvec * float(hist.value(tt, left=tt >= b))
        else:
            # affine in (y, top, vtop): y' = J y + g_top·top(t) + g_rate·vtop(t)
            zero, one, nil = Tt(np.zeros(n)), Tt(1.0), Tt(0.0)
            J = torch.func.jacrev(lambda x: interior(x, nil, nil))(zero).numpy()
            g_top = interior(zero, one, nil).numpy()
            g_rate = interior(zero, nil, one).numpy()

            def g_factory(a, b):
                def g(tt):
                    left = tt >= b
                    return (g_top * -float(hist.value(tt, left=left))
                            + g_rate * -float(hist.rate(tt, left=left)))
                return g
        basis = _real_eigenbasis(J)
    if basis is not None:
        lam, V, Vi = basis
        info["coordinates"] = "modal"
        info["stiffness_ratio"] = float(np.abs(lam).max() / np.abs(lam).min())
        jac_modal = np.diag(lam)

        def fm_factory(a, b):
            g = g_factory(a, b)
            return lambda tt, z: lam * z + Vi @ g(tt)

        Z, nfev = _integrate(fm_factory, lambda a, b: jac_modal, Vi @ y0, t, breakpoints,
                             rtol, atol, method, max_step)
        Y = Z @ V.T
        Y[0] = y0
    else:
        info["coordinates"] = "nodal"
        if model.is_linear:
            def jac_factory(a, b):
                return J if n > 0 else None
        else:
            def jac_factory(a, b):
                return lambda tt, y: jac_at(tt, y, tt >= b)
        if n > 0:
            ev = np.abs(np.linalg.eigvals(jac_at(t[0], y0)))
            if ev.min() > 0:
                info["stiffness_ratio"] = float(ev.max() / ev.min())
                rtol = float(max(rtol, 4 * np.finfo(float).eps * info["stiffness_ratio"]))
                info["rtol"] = rtol
        Y, nfev = _integrate(f_factory, jac_factory, y0, t, breakpoints, rtol, atol,
                             method, max_step)
    info["nfev"] = int(nfev)

    if control == "load":
        S = Y
        u_out = np.asarray(hist.value(t), dtype=float) * np.ones_like(t)
    else:
        top = -np.asarray(hist.value(t), dtype=float) * np.ones_like(t)
        S = np.concatenate([Y, top[:, None]], axis=1)
        vtop = -np.asarray(hist.rate(t), dtype=float) * np.ones_like(t)
        u_out = model.relaxation_load(Tt(S), Tt(vtop), H, K).numpy()
    P = model.pressure(Tt(S), Tt(u_out), H).numpy()
    return Simulation(t=t, load=u_out, displacement=-S[:, -1].copy(), pressure=P[:, 0].copy(),
                      s=S, p=P, H=H, K=K, control=control, nfev=int(nfev), info=info)


def _real_eigenbasis(J: np.ndarray):
    """``(λ, V, V⁻¹)`` with ``J = V diag(λ) V⁻¹``, or ``None`` if ``J`` is not safely
    diagonalisable over the reals (then the caller integrates in nodal coordinates)."""
    try:
        lam, V = np.linalg.eig(J)
    except np.linalg.LinAlgError:
        return None
    scale = max(np.abs(lam).max(), 1e-300)
    if np.abs(lam.imag).max() > 1e-10 * scale or np.abs(V.imag).max() > 1e-10:
        return None
    lam, V = lam.real, V.real
    if np.linalg.cond(V) > 1e8:
        return None
    Vi = np.linalg.inv(V)
    if np.abs(V @ (lam[:, None] * Vi) - J).max() > 1e-10 * np.abs(J).max():
        return None
    return lam, V, Vi


def _integrate(f_factory, jac_factory, y0, t, breakpoints, rtol, atol, method, max_step):
    """Integrate ``y' = f(t, y)`` from ``y0`` at ``t[0]``; output at ``t``; split at breakpoints.

    ``f_factory(a, b)`` gives the rhs for the segment ``[a, b]`` (prescribed histories evaluated
    with the left limit at ``b``), so discontinuities of the input are never stepped over.
    """
    n = y0.size
    Y = np.empty((t.size, n))
    Y[0] = y0
    if t.size == 1 or n == 0:
        Y[:] = y0
        return Y, 0
    y = y0.astype(float).copy()
    nfev = 0
    for a, b in _segments(t[0], t[-1], breakpoints):
        mask = (t > a) & (t <= b)
        t_out = np.append(t[mask], b) if (not mask.any() or t[mask][-1] < b) else t[mask]
        sol = solve_ivp(f_factory(a, b), (a, b), y, method=method, t_eval=t_out, rtol=rtol,
                        atol=atol, jac=jac_factory(a, b), max_step=max_step)
        if not sol.success:
            raise RuntimeError(f"integration failed on [{a}, {b}]: {sol.message}")
        nfev += sol.nfev
        Y[mask] = sol.y.T[: int(mask.sum())]
        y = sol.y[:, -1].copy()
    return Y, nfev


def creep(model: ConfinedCompression, t_eval, P: float = 1.0, t_ramp: float = 0.0,
          H: float = 2.0, K: float = 1.0, **kw) -> Simulation:
    """Creep test: load ramped to ``P`` over ``t_ramp`` (0: step) from ``t_eval[0]``, then held."""
    t = _check_times(t_eval)
    return simulate(model, t, load=RampHoldLoad(P, t_ramp, t_start=float(t[0])), H=H, K=K, **kw)


def stress_relaxation(model: ConfinedCompression, t_eval, d: float = 0.1, t_ramp: float = 0.1,
                      H: float = 2.0, K: float = 1.0, **kw) -> Simulation:
    """Stress relaxation: the compression is ramped to ``d`` over ``t_ramp > 0`` and held; the
    load (output) peaks at the end of the ramp and relaxes to ``H d / L``."""
    if not t_ramp > 0:
        raise ValueError("stress relaxation needs t_ramp > 0 (a displacement step is "
                         "incompatible with an incompressible mixture)")
    t = _check_times(t_eval)
    return simulate(model, t, displacement=RampHoldLoad(d, t_ramp, t_start=float(t[0])), H=H,
                    K=K, **kw)


# ----------------------------------------------------------------------------------------------
# simulated measurements and CSV
# ----------------------------------------------------------------------------------------------
MEASUREMENT_COLUMNS = ("t", "load", "displacement", "pressure")

#: Default experiment on dimensionless time [0, 1]: load ramped linearly to 1 over t ∈ [0, 0.1],
#: then held (creep).  With H = 2, K = 1 the slowest consolidation time constant is
#: 4L²/(π² H K) ≈ 0.20, so the ramp is faster than the drainage (pore pressure builds up,
#: sensitive to K and H·K) and the hold reaches ≈ 99 % of the drained compression P·L/H by t = 1
#: (sensitive to H).  The report's own load curve (fig. 5.3) is not legible in the OCR text.
DEFAULT_EXPERIMENT = RampHoldLoad(magnitude=1.0, t_ramp=0.1)


@dataclasses.dataclass
class Measurements:
    """Table with columns ``t, load, displacement, pressure`` (numpy arrays of equal length)."""

    t: np.ndarray
    load: np.ndarray
    displacement: np.ndarray
    pressure: np.ndarray

    columns = MEASUREMENT_COLUMNS

    def __post_init__(self):
        arrs = [np.asarray(getattr(self, c), dtype=float) for c in MEASUREMENT_COLUMNS]
        if any(a.ndim != 1 or a.shape != arrs[0].shape for a in arrs):
            raise ValueError("measurement columns must be 1-D arrays of equal length")
        for c, a in zip(MEASUREMENT_COLUMNS, arrs):
            setattr(self, c, a)

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in MEASUREMENT_COLUMNS:
            raise KeyError(name)
        return getattr(self, name)

    def __len__(self) -> int:
        return self.t.size

    def to_array(self) -> np.ndarray:
        """``(T, 4)`` array in column order ``t, load, displacement, pressure``."""
        return np.stack([getattr(self, c) for c in MEASUREMENT_COLUMNS], axis=1)

    def to_csv(self, path) -> None:
        write_measurements_csv(path, self)

    @classmethod
    def from_csv(cls, path) -> "Measurements":
        return read_measurements_csv(path)


def simulated_measurements(t=None, H: float = 2.0, K: float = 1.0, elements: int = 3,
                           load=DEFAULT_EXPERIMENT, noise=0.0, seed: int = 0,
                           length: float = 1.0) -> Measurements:
    """Simulated experiment (the report's set-up: true H = 2, K = 1, 3 elements, t ∈ [0, 1]).

    ``t`` defaults to 401 points on [0, 1]; ``load`` defaults to :data:`DEFAULT_EXPERIMENT`.
    ``noise`` is the standard deviation of independent Gaussian noise added to the measured
    channels: a scalar (all three of load, displacement, pressure) or a 3-sequence
    ``(σ_load, σ_displacement, σ_pressure)``.  ``t`` is noise-free.
    """
    if t is None:
        t = np.linspace(0.0, 1.0, 401)
    model = ConfinedCompression(elements=elements, length=length)
    sim = simulate(model, t, load=load, H=H, K=K)
    sig = np.broadcast_to(np.asarray(noise, dtype=float), (3,))
    if np.any(sig < 0) or not np.all(np.isfinite(sig)):
        raise ValueError("noise must be finite and ≥ 0")
    rng = np.random.default_rng(seed)
    cols = [sim.load, sim.displacement, sim.pressure]
    noisy = [c + (s * rng.standard_normal(c.shape) if s > 0 else 0.0) for c, s in zip(cols, sig)]
    return Measurements(sim.t.copy(), *noisy)


def write_measurements_csv(path, table) -> None:
    """Write ``t,load,displacement,pressure`` (header row, full float precision)."""
    if isinstance(table, Measurements):
        cols = [table[c] for c in MEASUREMENT_COLUMNS]
    else:
        cols = [np.asarray(table[c], dtype=float) for c in MEASUREMENT_COLUMNS]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(MEASUREMENT_COLUMNS)
        for row in zip(*cols):
            w.writerow([repr(float(x)) for x in row])


def read_measurements_csv(path) -> Measurements:
    """Read a CSV with header ``t,load,displacement,pressure`` (column order free)."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise ValueError(f"{path}: empty file")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in MEASUREMENT_COLUMNS if c not in header]
    if missing:
        raise ValueError(f"{path}: missing columns {missing}; header is {header}")
    data = np.array([[float(x) for x in r] for r in rows[1:] if r], dtype=float)
    if data.size == 0:
        data = data.reshape(0, len(header))
    return Measurements(*[data[:, header.index(c)] for c in MEASUREMENT_COLUMNS])
