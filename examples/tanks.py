"""Two cascaded water tanks: a real record, estimated and diagnosed.

The cascaded-tanks benchmark (nonlinear system identification benchmarks, Schoukens, Mattsson,
Wigren and Noël 2016): a pump at voltage u fills the upper tank, which drains through a small
opening into the lower tank, which drains into the reservoir (Torricelli: outflow ∝ √level).
Only the lower level y is measured (volts of a capacitive sensor)::

    x1' = k1 u − k2 √x1              upper level
    x2' = k2 √x1 − k3 √x2            lower level
    y   = x2                         measured; the sensor clips at 10 V

    python examples/tanks.py --convert tanque.csv           # → tanks_est.csv, tanks_val.csv
    shootlab estimate --model examples/tanks.py:model --data tanks_est.csv --out out/tanks_estimate
    shootlab diagnose --model examples/tanks.py:model --library examples/tanks.py:library \\
        --data tanks_est.csv --validate tanks_val.csv --out out/tanks
    python examples/tanks.py --overflow tanks_est.csv tanks_val.csv   # the model with overflow

Both levels are in the sensor's volts and both tanks have the same cross-section, so the upper
tank's outflow k2 √x1 is the lower tank's inflow.  (With a separate k3 √x1 there the model is not
identifiable: x1 → c x1, k1 → k1/c, k2 → k2/√c, k3 → k3 √c leave y unchanged.)  √ is smoothed
near 0 (:func:`root`) because a level may touch 0.  The initial levels are states of the TPBVP,
estimated with the rest.  What the model leaves out — the upper tank overflows when full, part of
the overflow runs into the lower tank — is for ``shootlab diagnose`` to find, from :data:`library`.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

try:
    import shootlab
except ModuleNotFoundError:     # run from a checkout that is not installed: its package, from any directory
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import shootlab
from shootlab.estimation.data import Measurements
from shootlab.diagnosis import Effect, Library
from shootlab.estimation import IdentificationModel, smoothed

TS = 4.0                 # sampling period [s]
CLIP = 10.0              # the level sensor's ceiling [V]
DELTA = 0.1              # where the smoothed square root departs from √x [V]
SPILL_WIDTH = 0.5        # the overflow sets in over L ± this [V]
FLOW_WIDTH = 0.01        # smoothing of max(net inflow, 0) [V/s]


def root(x: Tensor, delta: float = DELTA) -> Tensor:
    """Smooth signed square root x (x² + δ²)^(−1/4): √x within 0.4 % for x ≥ 10 δ, C^∞, odd
    (a level pushed below 0 flows back in), slope δ^(−1/2) at 0 instead of ∞."""
    return x * (x * x + delta * delta) ** -0.25


def soft_step(x: Tensor, width: float) -> Tensor:
    """C^∞ step from 0 (x ≪ −width) to 1 (x ≫ width)."""
    return torch.sigmoid(x / width)


def soft_plus(x: Tensor, width: float) -> Tensor:
    """C^∞ max(x, 0), within width·log 2 of it."""
    return width * torch.nn.functional.softplus(x / width)


def initial_levels(data: Measurements, t: Tensor, k: float = 0.05) -> Tensor:
    """Initial approximation of (x1, x2) at t: x2 the measured level (a clipped sample counted as
    10 V), smoothed; x1 from the lower tank's balance k √x1 = x2' + k √x2 with the initial
    k2 = k3 = k.  (Measured on a record simulated by this model: from x1 = x2 the estimate
    converges to another local minimum, J four times the true one; from this start to the truth.)"""
    ts = torch.as_tensor(data.t, dtype=t.dtype)
    y = torch.as_tensor(np.nan_to_num(data.channels["y"], nan=CLIP), dtype=t.dtype)
    x2 = smoothed(y, ts, deriv=0, window=15)
    x1 = ((smoothed(y, ts, deriv=1, window=15) + k * x2.clamp_min(0).sqrt()) / k).clamp_min(0) ** 2
    at = t.numpy()
    return torch.stack([torch.as_tensor(np.interp(at, data.t, v.numpy()), dtype=t.dtype) for v in (x1, x2)], -1)


model = shootlab.model(
    name="tanks",
    states={"x1": "q1", "x2": "q2"},                   # x1' = q1, x2' = q2
    inputs=["q1", "q2", "u"],                          # ζ: the level rates, the pump voltage
    parameters={"k1": 0.05, "k2": 0.05, "k3": 0.05},   # initial values (time constants ~100 s)
    equations={"upper": lambda x: x.k1 * x.u - x.k2 * root(x.x1) - x.q1,               # 0 = in − out − x1'
               "lower": lambda x: x.k2 * root(x.x1) - x.k3 * root(x.x2) - x.q2,        # 0 = in − out − x2'
               "level": lambda x: x.x2,                # measured: lower level
               "pump": lambda x: x.u},                 # measured: pump voltage
    channels={"level": "y", "pump": "u"},
    W={"k1": 1e10, "k2": 1e10, "k3": 1e10},          # constant parameters: with W = 1 they drift with the level
    V={"upper": 1e6, "lower": 1e6, "level": 1.0, "pump": 1e4},
    units={"t": "s", "x1": "V", "x2": "V", "q1": "V/s", "q2": "V/s", "u": "V", "y": "V",
           "k1": "1/s", "k2": "V^½/s", "k3": "V^½/s", "upper": "V/s", "lower": "V/s"},
    bounds={"k1": (0.0, float("inf")), "k2": (0.0, float("inf")), "k3": (0.0, float("inf"))},
    initial_states=initial_levels,
    settings=shootlab.EstimationSettings(points=257, solver={"integrator": "rk4", "steps": 4}))


# -- candidate effects -------------------------------------------------------------------------
def _net_inflow(v) -> Tensor:
    """k1 u − k2 √x1 with the measured pump voltage: the upper tank's net inflow."""
    return v.k1 * v.channel("u") - v.k2 * root(v.x1)


def _overflow(v) -> dict[str, Tensor]:
    """The upper tank is full at L: above it (smoothly, over ±SPILL_WIDTH) its net inflow spills
    over instead of raising the level, and a fraction b of the spill runs into the lower tank."""
    spill = soft_step(v.x1 - v.overflow_level, SPILL_WIDTH) * soft_plus(_net_inflow(v), FLOW_WIDTH)
    return {"upper": -spill, "lower": v.overflow_in * spill}


def _dead_zone(v) -> dict[str, Tensor]:
    """The pump delivers nothing below u0: applied k1 max(u − u0, 0) instead of k1 u."""
    u = v.channel("u")
    return {"upper": v.k1 * (soft_plus(u - v.dead_zone, 0.05) - u)}


def _overflow_starts(v) -> dict[str, list[float]]:
    top = float(v.x1.max())
    return {"overflow_level": [0.8 * top, 0.9 * top, 0.97 * top]}


def _overflow_range(v) -> dict[str, tuple[float, float]]:
    """The level is a threshold: the response to it is not linear, and the estimated upper level
    (never measured) may run far above the true rim — a full re-estimate scans it."""
    top = float(v.x1.max())
    return {"overflow_level": (0.25 * top, top)}


library = Library(
    name="tanks",
    description="examples/tanks.py: overflow, sensor offset, pump dead zone, leaks",
    effects=[
        Effect(name="overflow", equations=["upper", "lower"],
               parameters={"overflow_level": 10.0, "overflow_in": 0.5}, term=_overflow, channels=["u"],
               bounds={"overflow_level": (1.0, 30.0), "overflow_in": (-0.5, 1.5)},
               physical={"overflow_in": (0.0, 1.0)},      # a share of the spill
               scale={"overflow_level": 1.0, "overflow_in": 0.5}, starts=_overflow_starts, nonlinear=_overflow_range,
               variable=("x1 (estimated)", lambda v: v.x1), units={"overflow_level": "V", "overflow_in": "-"},
               description="upper tank overflows at level L, a fraction b of the spill enters the lower tank"),
        Effect(name="sensor_offset", equations=["level"], parameters={"sensor_offset": 0.0},
               term=lambda v: {"level": v.sensor_offset * torch.ones_like(v.t)}, scale={"sensor_offset": 0.5},
               variable=("t", lambda v: v.t), units={"sensor_offset": "V"}, description="level sensor offset: y = x2 + c"),
        Effect(name="pump_dead_zone", equations=["upper"], parameters={"dead_zone": 0.5}, term=_dead_zone,
               channels=["u"], bounds={"dead_zone": (0.0, 3.0)}, scale={"dead_zone": 0.5},
               starts={"dead_zone": [0.25, 1.0]}, variable=("u (measured)", lambda v: v.channel("u")), units={"dead_zone": "V"},
               description="pump dead zone: inflow k1 max(u − u0, 0)"),
        Effect(name="leak_lower", equations=["lower"], parameters={"leak_lower": 0.0},
               term=lambda v: {"lower": -v.leak_lower * v.x2}, scale={"leak_lower": 1e-3},
               physical={"leak_lower": (0.0, math.inf)},        # the water leaves
               variable=("x2 (estimated)", lambda v: v.x2), units={"leak_lower": "1/s"},
               description="linear leak of the lower tank: − c x2"),
        Effect(name="leak_upper", equations=["upper"], parameters={"leak_upper": 0.0},
               term=lambda v: {"upper": -v.leak_upper * v.x1}, scale={"leak_upper": 1e-3},
               physical={"leak_upper": (0.0, math.inf)},        # the water leaves
               variable=("x1 (estimated)", lambda v: v.x1), units={"leak_upper": "1/s"},
               description="linear leak of the upper tank: − c x1"),
    ],
    # a free run starts both levels at the first measured level, less a fitted sensor offset
    initial_state=lambda model, data, p: [float(np.nanmean(data.channels["y"][:5])) - p.get("sensor_offset", 0.0)] * 2)


# -- the nominal model and the overflow, estimated and validated --------------------------------
def free_run_rms(model: IdentificationModel, record: Measurements, parameters: dict[str, float]) -> float:
    """RMS error [V] of the free run on ``record`` over its unclipped samples, both levels starting
    at the first measured level (as the library's ``initial_state``)."""
    from shootlab.estimation.free_run import simulate
    y = record.channels["y"]
    seen = ~np.isnan(y)
    start = [float(np.nanmean(y[:5]))] * 2
    return float(np.sqrt(np.mean((simulate(model, record, parameters, start)["y"][seen] - y[seen]) ** 2)))


def fit_overflow(est_csv: str, val_csv: str, level: float = 8.0, fraction: float = 1.0) -> dict:
    """The nominal model and the model with the library's overflow, each estimated on ``est_csv``
    from the model's own initial approximation, and their free-run RMS error on ``val_csv``.
    The overflow model is started at L = ``level``, b = ``fraction``; from the nominal estimate
    instead, whose upper level never reaches L, L leaves the range of x1 (docs/diagnosis.md)."""
    from shootlab.diagnosis.composition import extend
    from shootlab.estimation import estimate
    est, val = Measurements.coerce(est_csv), Measurements.coerce(val_csv)
    overflow = [library["overflow"]]
    nominal = estimate(model, est)
    extended = estimate(extend(model, overflow, data=est), est, initial={"overflow_level": level, "overflow_in": fraction})
    out = {}
    for name, res, on_val in (("nominal", nominal, model), ("overflow", extended, extend(model, overflow, data=val))):
        out[name] = dict(result=res, validation_rms=free_run_rms(on_val, val, res.parameters) if res.success else None)
        rms = out[name]["validation_rms"]
        print(f"{name:9s} {res.message}; J = {res.J:.2f}, "
              + ", ".join(f"{p} = {v:.4g}" for p, v in res.parameters.items())
              + (f"; free-run RMS on {val_csv}: {rms:.3f} V" if rms is not None else ""))
    return out


# -- the benchmark's file ------------------------------------------------------------------------
def convert(path: str, out_dir: str = ".") -> tuple[Path, Path]:
    """``tanque.csv`` (columns uEst, uVal, yEst, yVal, Ts) → ``tanks_est.csv`` and ``tanks_val.csv``
    with columns t, u, y; a clipped sample (y ≥ 10 V) is written as missing."""
    with open(path, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("uEst", "").strip()]
    written = []
    for record in ("Est", "Val"):
        u = np.array([float(r["u" + record]) for r in rows])
        y = np.array([float(r["y" + record]) for r in rows])
        y[y >= CLIP] = np.nan
        target = Path(out_dir) / f"tanks_{record.lower()}.csv"
        Measurements(TS * np.arange(u.size), {"u": u, "y": y}).to_csv(str(target))
        print(f"wrote {target}: {u.size} samples of t, u, y ({int(np.isnan(y).sum())} clipped samples missing)")
        written.append(target)
    return written[0], written[1]


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--convert", metavar="tanque.csv",
                        help="the benchmark's file: write tanks_est.csv and tanks_val.csv")
    parser.add_argument("--out-dir", default=".", help="where to write them")
    parser.add_argument("--overflow", nargs=2, metavar=("EST.csv", "VAL.csv"),
                        help="estimate the nominal and the overflow model, validate both")
    args = parser.parse_args()
    if not (args.convert or args.overflow):
        parser.error("give --convert or --overflow")
    if args.convert:
        convert(args.convert, args.out_dir)
    if args.overflow:
        fit_overflow(*args.overflow)
