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

from shootlab.estimation.declarative import model as declare
from shootlab.estimation.settings import EstimationSettings
from shootlab.estimation import IdentificationModel

REPORT_W = (1e10, 1e10, 1.0, 1.0, 1.0)
REPORT_V = (1.0, 1.0, 1.0)
UNITS = dict(t="s", s="m", v="m/s", a="m/s²", u="N", m="kg", b="N s/m", k="N/m", motion="N")


def model(W=REPORT_W, V=REPORT_V, prior: dict | None = None) -> IdentificationModel:
    """The report's mass–spring–damper identification model (module docstring)."""
    return declare(
        name="msd", states={"s": "v", "v": "a"}, inputs=["u", "a"],
        parameters=dict({"m": 10.0, "b": 10.0, "k": 10.0}, **(prior or {})),
        equations={"motion": lambda x: x.m * x.a + x.b * x.v + x.k * x.s - x.u,
                   "u": lambda x: x.u, "s": lambda x: x.s},
        channels=["u", "s"], W=W if callable(W) else list(W), V=V if callable(V) else list(V),
        bounds={p: (0.0, math.inf) for p in ("m", "b", "k")},          # as the CasADi user's m, b, k ≥ 0
        units=dict(UNITS),
        # 101 points on [0, 10] with data every 0.01: RK4 steps land on the samples; the response
        # is slow (ω ≈ 1 rad/s) next to the 100 Hz sampling: v differentiated over 0.5 s; on a
        # longer record the points follow its length (span, shootlab.estimation.fit.default_points)
        settings=EstimationSettings(points=101, span=10.0, solver=dict(integrator="rk4", steps=10), smoothing=51))
