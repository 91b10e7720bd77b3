"""The identification model in augmented state form (report eqs. 2.4–2.5) and the helpers for its initial approximation."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from .data import Interpolant, Measurements, linear_fill
from .settings import EstimationSettings
from shootlab.bvp.problem import as_tensor


@dataclass
class IdentificationModel:
    """A model in augmented state form (module docstring).

    states, parameters  names; x = states + parameters (parameters have θ' = ε_θ)
    inputs              names of ζ
    equations           names of the rows of f and F
    channels            row name → data channel for the measurement rows; the other rows are
                        model equations (zero pseudo-measurements)
    A, B                constant (nx, nx), (nx, nζ); parameter rows are zero
    f(x, t), F(x, t)    batched torch functions: x (..., nx), t (...) → (..., r), (..., r, nζ)
    W, V, W_a           weights: a vector (diagonal), a matrix, or a function of t returning either
    q_a                 prior on x(a) (zeros by default; only components with W_a > 0 matter)
    prior               default initial parameter values
    given               the channels known when the model is *simulated* (its inputs, e.g. the
                        motor command); with the model-equation rows they determine ζ
    initial_states      (data, t) → (m, n_states) initial approximation of the states at t
    settings            an :class:`~shootlab.estimation.settings.EstimationSettings`: defaults for
                        estimate and the CLI (points, solver options, prefit, weight
                        continuation, fallback) and the hooks of the output-error fit and the
                        diagnosis; default ``EstimationSettings(solver={})`` (shootlab.solve's
                        own defaults)
    units               optional unit per name — "t", states, parameters, inputs, channels and
                        equation rows (the unit of the row's residual ξ) — for labels and
                        summaries, e.g. {"t": "s", "s": "m", "u": "N", "m": "kg"}; "-" for a
                        dimensionless quantity, no entry for an unknown unit
    bounds              optional (low, high) per state or parameter name that the Newton
                        iterates keep strictly inside, e.g. {"m": (0, inf)} for a positive mass
                        (IPOPT users give the same bounds)
    """

    name: str
    states: list[str]
    parameters: list[str]
    inputs: list[str]
    equations: list[str]
    channels: dict[str, str]
    A: Tensor
    B: Tensor
    f: Callable[[Tensor, Tensor], Tensor]
    F: Callable[[Tensor, Tensor], Tensor]
    W: object
    V: object
    W_a: object = None
    q_a: object = None
    prior: dict[str, float] = field(default_factory=dict)
    given: list[str] = field(default_factory=list)
    initial_states: Callable[[Measurements, Tensor], Tensor] | None = None
    settings: EstimationSettings = field(default_factory=lambda: EstimationSettings(solver={}))
    units: dict[str, str] = field(default_factory=dict)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)

    def f_and_F(self, x: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """f(x, t) and F(x, t); from one evaluation where f and F are methods of one object that
        has ``f_and_F`` (a declared model's rows, :meth:`shootlab.estimation.rows.Rows.f_and_F`; an extended
        model, :func:`shootlab.diagnosis.composition.extend`)."""
        owner = getattr(self.f, "__self__", None)
        if owner is not None and getattr(self.F, "__self__", None) is owner and hasattr(owner, "f_and_F"):
            return owner.f_and_F(x, t)
        return self.f(x, t), self.F(x, t)

    def __post_init__(self):
        if not isinstance(self.settings, EstimationSettings):
            raise ValueError(f"settings must be a shootlab.EstimationSettings, got {type(self.settings).__name__}")
        self.A = as_tensor(self.A, name="A")
        self.B = as_tensor(self.B, name="B")
        nx, nz, r = self.nx, len(self.inputs), len(self.equations)
        if tuple(self.A.shape) != (nx, nx):
            raise ValueError(f"A must be ({nx}, {nx}) for {nx} states + parameters, got {tuple(self.A.shape)}")
        if tuple(self.B.shape) != (nx, nz):
            raise ValueError(f"B must be ({nx}, {nz}), got {tuple(self.B.shape)}")
        unknown = set(self.channels) - set(self.equations)
        if unknown:
            raise ValueError(f"channels name rows {sorted(unknown)} that are not among the equations {self.equations}")
        bad_given = set(self.given) - set(self.channels.values())
        if bad_given:
            raise ValueError(f"given channels {sorted(bad_given)} are not measured channels")
        self.W_a = torch.zeros(nx, dtype=torch.float64) if self.W_a is None else self.W_a
        self.q_a = torch.zeros(nx, dtype=torch.float64) if self.q_a is None else as_tensor(self.q_a, name="q_a")
        for name, lohi in self.bounds.items():
            if name not in self.names:
                raise ValueError(f"bounds for {name!r}, which is not a state or parameter of {self.names}")
            if len(lohi) != 2 or not float(lohi[0]) < float(lohi[1]):
                raise ValueError(f"bounds for {name!r} must be (low, high) with low < high, got {lohi!r}")
        _check_weight(self.W, nx, "W", positive=True)
        _check_weight(self.V, r, "V", positive=False)
        _check_weight(self.W_a, nx, "W_a", positive=False)

    @property
    def names(self) -> list[str]:
        return list(self.states) + list(self.parameters)

    @property
    def nx(self) -> int:
        return len(self.states) + len(self.parameters)

    @property
    def measured(self) -> list[str]:
        return list(dict.fromkeys(self.channels.values()))

    def label(self, name: str) -> str:
        """'name [unit]' from :attr:`units` ('name' when the unit is not declared)."""
        unit = self.units.get(name)
        return f"{name} [{unit}]" if unit else name


# -- initial approximation helpers ---------------------------------------------------------
def central_difference(values: Tensor, t: Tensor) -> Tensor:
    """Derivative of samples (K, …) on a grid t (K,) by central differences (one-sided at the ends)."""
    return torch.gradient(values, spacing=(t,), dim=0, edge_order=2)[0]


def smoothed(values: Tensor, t: Tensor, deriv: int = 1, window: int = 11, order: int = 3) -> Tensor:
    """Noisy samples (K, …) smoothed (deriv=0) or differentiated (deriv=1) by a Savitzky–Golay
    filter (scipy.signal) on a uniform grid; plain values / central differences where the grid
    is irregular or shorter than the window.  Missing samples (NaN) are filled by linear
    interpolation first.  For initial approximations (report §3.4: derivatives from data)."""
    from scipy.signal import savgol_filter

    v = values.detach().cpu().numpy().reshape(values.shape[0], -1).copy()
    tn = t.detach().cpu().numpy()
    for j in range(v.shape[1]):
        v[:, j] = linear_fill(tn, v[:, j])
    dt = np.diff(tn)
    if tn.size < window or np.abs(dt - dt.mean()).max() > 1e-6 * abs(dt.mean()):
        d = np.gradient(v, tn, axis=0, edge_order=2) if deriv else v
    else:
        d = savgol_filter(v, window, order, deriv=deriv, delta=float(dt.mean()), axis=0)
    return torch.as_tensor(d.reshape(values.shape), dtype=values.dtype, device=values.device)


def measured_states(model: IdentificationModel, data: Measurements, t: Tensor) -> Tensor:
    """States that are measured channels taken from the data at t (across a missing sample by
    linear interpolation, :func:`~shootlab.estimation.data.linear_fill`), the rest zero."""
    names = [s for s in model.states if s in data.channels]
    if any(np.isnan(data.channels[s]).any() for s in names):
        data = Measurements(data.t, {s: linear_fill(data.t, data.channels[s]) for s in names})
    ip = Interpolant(data, names, t.dtype, t.device)
    out = t.new_zeros(t.numel(), len(model.states))
    vals = ip.values(t) if ip.names else None
    for j, name in enumerate(ip.names):
        out[:, model.states.index(name)] = vals[:, j]
    return out


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
