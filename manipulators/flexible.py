"""The flexible rotation manipulator of the report ch. 4 as identification models.

Everything per unit motor constant c.  x = [s1, s2, v1, v2, m1, m2, k, b] (+ [f1, f2] for the
extended model), ζ = [u, a1, a2] (motor torque/c, accelerations)::

    s1' = v1,  s2' = v2,  v1' = a1,  v2' = a2,  θ' = 0                 (A, B; plus ε)
    mass1:  0    = m1 a1 − k (s2 − s1) − b (v2 − v1) [+ f1 σ(v1)]     (eq. 4.1 / 4.4a)
    mass2:  0    = m2 a2 + k (s2 − s1) + b (v2 − v1) [+ f2 σ(v2)] − u  (eq. 4.1 / 4.4b)
    u:      u_m  = u          (the command is not exactly the applied torque: a residual)
    s1:     s1_m = s1
    s2:     s2_m = s2

declared with :func:`shootlab.model` (A, B from the derivatives, F = ∂rows/∂ζ derived; the
compiled f, F and their derivatives equal the former hand-written ones bit for bit).

σ is the C¹ smooth sign of :mod:`manipulators.friction` with half-widths v_s1, v_s2 (the
report: 0.1 and 1.0 rad/s).  Sign conventions as in :mod:`manipulators.rig`.

Weights.  Plain model (report §4.2): q_a = [0 0 0 0 4.7 .39 978 2.7], diag(W_a) = [1e5 ×4, 0 ×4],
diag(V) = [1, 1, 1e4, 1e9, 1e9]: the equations of motion carry the residual so that a
structural error shows there; W (illegible in the OCR) is taken high, 1e4 on every component.
Extended model (report §4.3): W_a = [1 ×4, 0 ×6], W = I, V = I, v_s1 = 0.1, v_s2 = 1.0.
All are settings.  From the prior, the plain model's V = 1e9 on the encoder rows makes Newton
crawl; :func:`manipulators.chapter4.identify_plain` reaches it by weight continuation.

Initial approximation (report §4.2): s1, s2 from the encoders, v1, v2 by central differences.
On quantised encoder data (one count in one sample period is 0.79 rad/s at 8000 counts/rev and
1 kHz) these velocities are rough: good enough to start the estimation, not to start a free-run
simulation from (see :func:`manipulators.chapter4.initial_state`).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from shootlab.estimation.data import Interpolant, Measurements, linear_fill
from shootlab.estimation.declarative import model as declare
from shootlab.estimation.settings import EstimationSettings
from shootlab.estimation import IdentificationModel
from shootlab.estimation.model import central_difference

from .friction import smooth_sign

REPORT_PRIOR = dict(m1=4.7, m2=0.39, k=978.0, b=2.7)
STATES = ["s1", "s2", "v1", "v2"]
#: units per unit motor constant c (report ch. 4): the motor command u and the torques/c are
#: counted in command units [-], so m/c [s²/rad], k/c [1/rad], b/c [s/rad], f/c [-]
UNITS = dict(t="s", s1="rad", s2="rad", v1="rad/s", v2="rad/s", a1="rad/s²", a2="rad/s²", u="-",
             m1="s²/rad", m2="s²/rad", k="1/rad", b="s/rad", f1="-", f2="-", mass1="-", mass2="-")


def _initial_states(data: Measurements, t: Tensor) -> Tensor:
    """s1, s2 from the encoders, v1, v2 by central differences (report §4.2); across a missing
    sample by linear interpolation."""
    ts = torch.as_tensor(data.t, dtype=t.dtype)
    s = torch.stack([torch.as_tensor(linear_fill(data.t, data.channels[c]), dtype=t.dtype) for c in ("s1", "s2")], -1)
    v = central_difference(s, ts)
    cols = {"s1": s[:, 0], "s2": s[:, 1], "v1": v[:, 0], "v2": v[:, 1]}
    ip = Interpolant(Measurements(data.t, {k: c.numpy() for k, c in cols.items()}), STATES, t.dtype, t.device)
    return ip.values(t)


def _build(friction: bool, W, V, W_a, q_a, v_s1: float, v_s2: float, prior: dict) -> IdentificationModel:
    """The rows of the module docstring declared with :func:`shootlab.model` (the spring torque
    written once; the friction terms only in the extended model)."""
    def spring(x):
        return x.k * (x.s2 - x.s1) + x.b * (x.v2 - x.v1)

    def mass1(x):                                        # eq. 4.1 / 4.4a
        r = x.m1 * x.a1 - spring(x)
        return r + x.f1 * smooth_sign(x.v1, v_s1) if friction else r

    def mass2(x):                                        # eq. 4.1 / 4.4b
        r = spring(x) + x.f2 * smooth_sign(x.v2, v_s2) if friction else spring(x)
        return x.m2 * x.a2 + r - x.u

    params = {p: prior[p] for p in ("m1", "m2", "k", "b") + (("f1", "f2") if friction else ())}
    return declare(
        name="flexible_friction" if friction else "flexible",
        states={"s1": "v1", "s2": "v2", "v1": "a1", "v2": "a2"}, inputs=["u", "a1", "a2"], parameters=params,
        equations={"mass1": mass1, "mass2": mass2, "u": lambda x: x.u, "s1": lambda x: x.s1, "s2": lambda x: x.s2},
        channels=["u", "s1", "s2"], given=["u"], W=W, V=V, W_a=W_a, q_a=q_a, units=dict(UNITS),
        initial_states=_initial_states,
        settings=EstimationSettings(points=101, span=1.0, solver=dict(integrator="rk4", steps=10),
                                    extra=dict(v_s1=v_s1, v_s2=v_s2)))


#: measurement-weight levels of the plain model's weight continuation (report §4.2)
WEIGHT_LEVELS: tuple[float, ...] = (1.0, 1e2, 1e4, 1e6, 1e7, 1e8, 1e9)


def plain_model(W: float | list = 1e4, V=(1.0, 1.0, 1e4, 1e9, 1e9), W_a=None, prior: dict | None = None,
                prior_weight: float = 0.0, continuation: bool = True) -> IdentificationModel:
    """The report's model of §4.2 (no friction); weights per the module docstring.

    ``prior_weight`` w ≥ 0 adds w·((θ − θ_a)/θ_a)² for each parameter to the cost (W_a on the
    parameters = w/θ_a²): 0 is the report's W_a (free parameters); a large w holds the
    parameters at values identified independently (the report's prior comes from an impulse
    response, Kerssemakers 1993), so that a structural error stays in the residuals instead of
    being absorbed into the parameters (see :func:`manipulators.chapter4.residual_velocity_correlation`).
    Ignored when ``W_a`` is given.

    ``continuation``: the model reaches its weights by weight continuation (report §4.2): it is
    estimated first with every weight of V capped at the levels :data:`WEIGHT_LEVELS` below its
    largest, each stage warm-starting the next (measured on the default rig sweep: from the prior
    with the full weights at once the Newton iteration drifts to m1 ≈ 2.9 and stalls, with the
    continuation it converges in about 50 iterations over the 7 stages)."""
    nx = 8
    prior = dict(REPORT_PRIOR, **(prior or {}))
    q_a = [0, 0, 0, 0] + [prior[p] for p in ("m1", "m2", "k", "b")]
    W = [float(W)] * nx if isinstance(W, (int, float)) else list(W)
    if not (math.isfinite(prior_weight) and prior_weight >= 0):
        raise ValueError(f"prior_weight must be finite and ≥ 0, got {prior_weight!r}")
    W_a = [1e5] * 4 + [prior_weight / q ** 2 for q in q_a[4:]] if W_a is None else list(W_a)
    model = _build(False, W, list(V), W_a, q_a, 0.1, 1.0, prior)
    if continuation:
        model.settings = model.settings.replace(weight_continuation=WEIGHT_LEVELS)
    return model


def friction_model(W: float | list = 1.0, V=(1.0, 1.0, 1.0, 1.0, 1.0), W_a=None, v_s1: float = 0.1,
                   v_s2: float = 1.0, prior: dict | None = None) -> IdentificationModel:
    """The extended model of §4.3: smooth Coulomb friction f1 σ(v1), f2 σ(v2)."""
    nx = 10
    prior = dict(REPORT_PRIOR, f1=0.0, f2=0.0, **(prior or {}))
    q_a = [0, 0, 0, 0] + [prior[p] for p in ("m1", "m2", "k", "b", "f1", "f2")]
    W = [float(W)] * nx if isinstance(W, (int, float)) else list(W)
    W_a = [1.0] * 4 + [0.0] * 6 if W_a is None else list(W_a)
    return _build(True, W, list(V), W_a, q_a, float(v_s1), float(v_s2), prior)
