"""Default weights from the data's scales, so that a model estimates the same in any consistent units.

The cost of eq. 2.6, J = ∫ ε'Wε + ξ'Vξ dt, compares quantities of different units: ε_j has the
unit of state (or parameter) j per time, ξ_i the unit of row i.  Weights given as plain numbers
(the report's W = 1e10 on the states, 1 on the parameters, V = 1 on every row, §3.4) fit one
choice of units: the same model written in millimetres instead of metres weights its position
residual 10⁶ times more and estimates something else, or does not converge.  The entries a
declared model leaves to the defaults (:func:`shootlab.model`) are therefore read as
dimensionless and divided by the square of a scale taken from the data::

    W_j = w_j / S_j²        w = 1e10 on a state, 1 on a parameter
    V_i = 1 / R_i²

    S_j   the spread (standard deviation over the record) of state j's initial approximation
          from the data; |prior value| for a parameter
    R_i   the size of row i at that approximation: the RMS over the record of
          ( Σ_j (∂row_i/∂x_j · S_j)² + Σ_k (F_ik Z_k)² )^½,
          Z_k the spread of input k (a measured input's channel, or the derivative of the state
          whose derivative it is)

A variable whose scale is zero (an unmeasured state, a parameter with prior 0, e.g. an offset) is
given the scale at which it would matter in the rows it enters, min_i R_i / RMS|∂row_i/∂x_j|.
Changing the unit of any state, channel, parameter or row multiplies its scale by the same factor,
so every weighted term, hence the estimate, is unchanged.  The unit of time is taken as it is.
The drive of docs/your_own_model.md in mm gives the SI estimate to 1e-9 (tests/engine/test_declarative.py).
The Newton iterates are not exactly invariant (the stopping test on |F|_inf and the scale floor of
:func:`shootlab.bvp.newton._typical_magnitude` are absolute or relative to the largest component),
so a damped re-estimation may stop at a slightly different point in other units.

Weights from each channel's *noise level* (V = 1/σ̂², maximum likelihood) make the TPBVP very
stiff (on an SI axis record with σ̂ = 5e-7 m weight continuation stalls), so the scales here are
the signals' spreads, not their noise.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from .data import Measurements

__all__ = ["scales", "from_data"]

GRID = 501      # points over the record at which the scales are measured


def _spread(v: Tensor) -> float:
    s = float(v.std()) if v.numel() > 1 else 0.0
    return s if np.isfinite(s) else 0.0


def scales(model, data: Measurements) -> tuple[Tensor, Tensor]:
    """(S, R): the scale of every state and parameter and of every row of ``model`` on ``data``
    (module docstring)."""
    from .model import measured_states

    t = torch.linspace(float(data.t[0]), float(data.t[-1]), GRID, dtype=torch.float64)
    ns, nx = len(model.states), model.nx
    states = model.initial_states(data, t) if model.initial_states else measured_states(model, data, t)
    prior = torch.tensor([float(model.prior.get(p, 0.0)) for p in model.parameters], dtype=torch.float64)
    x = torch.cat([states, prior.expand(GRID, -1)], -1)
    S = torch.tensor([_spread(states[:, j]) for j in range(ns)] + prior.abs().tolist(), dtype=torch.float64)
    # inputs: a measured one (a row that is that input alone) by its channel, a state's derivative by
    # the derivative of the state's approximation
    F = model.F(x, t)                                                   # (m, r, nζ)
    Z = torch.zeros(len(model.inputs), dtype=torch.float64)
    B = torch.as_tensor(model.B)
    for k in range(len(model.inputs)):
        for j in range(ns):
            if B[j, k] != 0 and S[j] > 0:
                Z[k] = _spread(torch.gradient(states[:, j], spacing=(t,))[0])
    f0 = model.f(x, t)
    for i, row in enumerate(model.equations):
        alone = (F[:, i] != 0).sum(-1) == 1
        if row in model.channels and bool(alone.all()) and float(f0[:, i].abs().max()) == 0.0:
            k = int((F[0, i] != 0).nonzero()[0])
            ch = np.asarray(data.channels[model.channels[row]], dtype=np.float64)
            Z[k] = float(np.nanstd(ch)) / float(F[:, i, k].abs().mean())
    # ∂row/∂x_j along each variable (forward mode), its RMS over the record
    def along(j: int) -> Tensor:
        e = torch.zeros_like(x)
        e[:, j] = 1.0
        return torch.func.jvp(lambda xx: model.f(xx, t), (x,), (e,))[1]
    dfdx = torch.stack([along(j) for j in range(nx)], -1)             # (m, r, nx)
    sens = dfdx.pow(2).mean(0).sqrt()                                   # (r, nx)
    inputs = (F * Z).pow(2).sum(-1).mean(0)                             # (r,)

    def sizes(S: Tensor) -> Tensor:
        return ((sens * S).pow(2).sum(-1) + inputs).sqrt()
    R = sizes(S)
    unknown = S == 0
    for j in unknown.nonzero().flatten().tolist():                      # the scale at which x_j matters
        rows = (sens[:, j] > 0) & (R > 0)
        if rows.any():
            S[j] = float((R[rows] / sens[rows, j]).min())
    if unknown.any():                                                   # the rows again, with those scales
        R = sizes(S)
    S = torch.where(S > 0, S, torch.ones_like(S))
    R = torch.where(R > 0, R, torch.ones_like(R))
    return S, R


def from_data(model, data):
    """``model`` with the weight entries it left to the defaults (``settings.weights_from_data``:
    {"W": [w_j or None per state/parameter], "V": [v_i or None per row]}, None: given by the user)
    scaled by the data (module docstring); a model without that mark is returned as it is."""
    marks = model.settings.weights_from_data
    if not marks:
        return model
    S, R = scales(model, Measurements.coerce(data))
    W = torch.tensor([float(model.W[j]) if w is None else w / float(S[j]) ** 2 for j, w in enumerate(marks["W"])],
                     dtype=torch.float64)
    V = torch.tensor([float(model.V[i]) if v is None else v / float(R[i]) ** 2 for i, v in enumerate(marks["V"])],
                     dtype=torch.float64)
    return replace(model, W=W, V=V, settings=model.settings.replace(weights_from_data=None))
