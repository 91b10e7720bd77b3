"""Prescribed histories of the confined-compression experiment (report ch. 5): the load on the
filter (creep, load control) or the prescribed compression of the sample (stress relaxation,
displacement control).

Every history has ``value(t, left=False)``, ``rate(t, left=False)`` (``left``: the left limit, used
at the end of an integration segment), ``breakpoints`` (where :func:`mixtures.simulation.simulate`
restarts the integrator) and ``check_covers(t0, t1)``.  Loads are compression positive.
:data:`DEFAULT_EXPERIMENT` is the identification experiment (ramp to 1 over 0.1, then held).
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from shootlab.estimation.data import Measurements

__all__ = ["StepLoad", "RampHoldLoad", "SampledHistory", "CallableHistory", "as_history", "DEFAULT_EXPERIMENT"]


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
        return SampledHistory(obj.t, obj.channels["load"])
    if isinstance(obj, dict) and {"t", "load"} <= set(obj):
        return SampledHistory(obj["t"], obj["load"])
    if hasattr(obj, "value") and hasattr(obj, "breakpoints"):
        return obj
    if callable(obj):
        return CallableHistory(obj)
    raise ValueError(f"cannot interpret {obj!r} as a load/displacement history")


#: Default experiment on dimensionless time [0, 1]: load ramped linearly to 1 over t ∈ [0, 0.1],
#: then held (creep).  With H = 2, K = 1 the slowest consolidation time constant is
#: 4L²/(π² H K) ≈ 0.20, so the ramp is faster than the drainage (pore pressure builds up,
#: sensitive to K and H·K) and the hold reaches ≈ 99 % of the drained compression P·L/H by t = 1
#: (sensitive to H).  The report's own load curve (fig. 5.3) is not legible in the OCR text.
DEFAULT_EXPERIMENT = RampHoldLoad(magnitude=1.0, t_ramp=0.1)
