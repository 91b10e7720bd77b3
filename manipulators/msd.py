"""The mass–spring–damper of the report §3.4 (eq. 3.23) as an identification model.

    m a + b v + k s = u,      x = [s, v, m, b, k],   ζ = [u, a]

    s' = v,  v' = a,  m' = b' = k' = 0          (A, B; plus ε)
    rows of E z_m = f + F ζ + ξ:
        motion:  0   = b v + k s + (−u + m a)
        u:       u_m = u
        s:       s_m = s

Weights (report §3.4; the exponents are partly illegible in the OCR): diag(W) = [1e10, 1e10,
1, 1, 1] — state equations nearly exact, parameters free to drift only as the data demand —
diag(V) = [1, 1, 1], W_a = 0.  Initial approximation: s from the measurement, v by (Savitzky–Golay
smoothed) differences, parameters from ``initial`` (the report: 10, then 50), λ = 0.

Units (the report's example is unitless; we read it in SI): s [m], v [m/s], a [m/s²], u [N],
t [s], m [kg], b [N s/m], k [N/m]; the residual of the motion row is a force [N].
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from shootlab.data import Interpolant, Measurements
from shootlab.estimation import IdentificationModel, smoothed

REPORT_W = (1e10, 1e10, 1.0, 1.0, 1.0)
REPORT_V = (1.0, 1.0, 1.0)
UNITS = dict(t="s", s="m", v="m/s", a="m/s²", u="N", m="kg", b="N s/m", k="N/m", motion="N")


def _f(x: Tensor, t: Tensor) -> Tensor:
    s, v, m, b, k = x.unbind(-1)
    return torch.stack([b * v + k * s, torch.zeros_like(s), s], -1)


def _F(x: Tensor, t: Tensor) -> Tensor:
    s, v, m, b, k = x.unbind(-1)
    one, zero = torch.ones_like(s), torch.zeros_like(s)
    return torch.stack([torch.stack([-one, m], -1),
                        torch.stack([one, zero], -1),
                        torch.stack([zero, zero], -1)], -2)


def _initial_states(data: Measurements, t: Tensor) -> Tensor:
    ts = torch.as_tensor(data.t, dtype=t.dtype)
    s = torch.as_tensor(data.channels["s"], dtype=t.dtype)
    # the response is slow (ω ≈ 1 rad/s) next to the 100 Hz sampling: differentiate over 0.5 s
    v = smoothed(s, ts, deriv=1, window=51)
    ip = Interpolant(Measurements(data.t, {"s": s.numpy(), "v": v.numpy()}), ["s", "v"], t.dtype, t.device)
    return ip.values(t)


def model(W=REPORT_W, V=REPORT_V, prior: dict | None = None) -> IdentificationModel:
    """The report's mass–spring–damper identification model (module docstring)."""
    A = torch.zeros(5, 5, dtype=torch.float64)
    A[0, 1] = 1.0
    B = torch.zeros(5, 2, dtype=torch.float64)
    B[1, 1] = 1.0
    return IdentificationModel(
        name="msd", states=["s", "v"], parameters=["m", "b", "k"], inputs=["u", "a"],
        equations=["motion", "u", "s"], channels={"u": "u", "s": "s"},
        A=A, B=B, f=_f, F=_F, W=W if callable(W) else list(W), V=V if callable(V) else list(V),
        prior=dict(prior or {"m": 10.0, "b": 10.0, "k": 10.0}), given=["u"], initial_states=_initial_states,
        bounds={p: (0.0, math.inf) for p in ("m", "b", "k")},          # as the CasADi user's m, b, k ≥ 0
        # 101 points on [0, 10] with data every 0.01: RK4 steps land on the samples
        settings=dict(points=101, solve=dict(integrator="rk4", steps=10)), units=dict(UNITS))
