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

Material laws are pluggable small classes of the element strain (:mod:`mixtures.laws`:
:class:`~mixtures.laws.LinearSolid`, :class:`~mixtures.laws.ExponentialSolid`,
:class:`~mixtures.laws.ConstantPermeability`, :class:`~mixtures.laws.ExponentialPermeability`).  A
non-linear solid stress is split as ``S(s,θ) s − F(s,θ)`` with ``S = H·(assembled ∫N'N')`` the
linear part at the reference state and ``F = −(assembled (σᵉ(e) − H e))`` the non-linear
remainder; ``F ≡ 0`` for the linear solid.

Everything in the model is torch, vectorised over elements (no Python loop over elements) and
batched over leading dimensions: ``s`` has shape ``(..., N)``; ``H``, ``K`` and ``u`` are floats
or tensors of shape ``(...)`` that broadcast against ``s.shape[:-1]`` and may carry autograd.

This module is the model and its assembly (:class:`ConfinedCompression`, :class:`Matrices`).
Forward simulation (:func:`mixtures.simulation.simulate`) uses ``scipy.integrate.solve_ivp``
(Radau by default) with the exact Jacobian; it supports load control (creep: step, ramp-and-hold,
user history, :mod:`mixtures.loads`) and displacement control (stress relaxation: the filter
displacement is prescribed and the load is the output).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import torch

from shootlab.bvp.tangents import outside_transforms

from .laws import ConstantPermeability, LinearSolid

__all__ = ["ConfinedCompression", "Matrices"]


# ----------------------------------------------------------------------------------------------
# the finite-element model
# ----------------------------------------------------------------------------------------------
def _shifted(w: torch.Tensor, k: int) -> torch.Tensor:
    """``w`` moved by ``k`` places along its last axis, zeros shifted in: ``w_{i−k}``."""
    n = w.shape[-1]
    j = min(abs(k), n)
    zero = w.new_zeros(*w.shape[:-1], j)
    if k >= 0:
        return torch.cat([zero, w[..., :n - j]], -1)
    return torch.cat([w[..., j:], zero], -1)


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
        batch = torch.Size(np.broadcast_shapes(s.shape[:-1], H.shape, K.shape))   # torch's imports sympy
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
        """Residuals of the two balances ``(R* v + K p, S s − R*ᵀ p − F − H_u u)``, matrix-free
        (:meth:`mass_balance`, :meth:`momentum_balance`)."""
        s, (v, p, u, H, K) = self._prepare(s, v, p, u, H, K)
        return self.mass_balance(s, K, v, p), self.momentum_balance(s, H, p, u)

    # The balances as the identification model's rows (mixtures.identification): tensors already
    # prepared, O(N) each.  Every product multiplies p, v, u by the very entries that
    # :meth:`matrices` assembles (R* = ½(I − J²), K tridiagonal with diagonal (k_{i−1} + k_i)/h
    # and off-diagonal −k_i/h), so that the rows' derivatives in v, p, u — taken by
    # shootlab.model with one-hot inputs — equal those matrices bit for bit.
    def mass_balance(self, s, K, v, p) -> torch.Tensor:
        """``R* v + K(s,θ) p``, shape ``(..., N)``."""
        k = self.permeability(self._strain(s), K.unsqueeze(-1))
        diag = (_shifted(k, 1) + k) / self.h
        off = -k / self.h                                     # K_{i,i+1} = K_{i+1,i} = off_i
        Kp = diag * p + off * _shifted(p, -1) + _shifted(off * p, 1)
        return 0.5 * v - 0.5 * _shifted(v, 2) + Kp           # R* v = ½ v_i − ½ v_{i−2}

    def momentum_balance(self, s, H, p, u) -> torch.Tensor:
        """``S(s,θ) s − F(s,θ) − R*ᵀ p − H_u u``, shape ``(..., N)`` (H_u = −e_N)."""
        m = self._internal_force(self._strain(s), H) - (0.5 * p - 0.5 * _shifted(p, -2))
        return torch.cat([m[..., :-1], m[..., -1:] + u.unsqueeze(-1)], -1)

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
