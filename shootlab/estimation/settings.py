"""Typed estimation settings of a model (:func:`shootlab.model`): the shooting points, the
solver's options and the stages run before the estimate — the compiled model carries them as its
``settings`` dict (:meth:`EstimationSettings.as_dict`), which :func:`shootlab.estimation.estimate`
and the CLI read."""
from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

__all__ = ["EstimationSettings"]


@dataclass(frozen=True)
class EstimationSettings:
    """Typed defaults for :func:`shootlab.estimation.estimate` and the CLI (the model's
    ``settings`` dict, :meth:`as_dict`).

    points               shooting points (``--points`` overrides); on a record longer than ``span``
                         a lower bound (:func:`shootlab.estimation.fit.default_points`)
    span                 the record length (in the unit of t) that ``points`` were chosen for: on a
                         longer record the default keeps that grid's |λ|max·h (the local
                         Jacobian's fastest time scale), no finer than |λ|max·h = 0.5; None: the
                         declared count on any record (raised only where the integrator needs it)
    solver               options of :func:`shootlab.solve` (``integrator``, ``steps``, ``newton``,
                         ``tol``, ``continuation``, …; checked against its signature); default
                         RK4 with 10 steps per interval, as the built-in models: with the default
                         W = 1e10 the TPBVP is stiff enough that the solver's own default (an
                         adaptive Rosenbrock method) takes tiny steps (minutes per Newton
                         iteration on the drive of docs/your_own_model.md)
    prefit               ``(data, params, t) -> params | None``: a stage run on the initial
                         parameter values before the initial approximation is built (refine them,
                         or raise ValueError for bad ones) — ``settings["initial_parameters"]``
    weight_continuation  levels at which the diagonal V is capped in easier stages estimated
                         first, each warm-starting the next (report §4.2)
    smoothing            Savitzky–Golay window (samples) that differentiates a measured state for
                         the initial approximation of its derivative state (:func:`model`)
    extra                further model-specific keys, kept as they are
    """

    points: int = 101
    span: float | None = None
    solver: Mapping[str, object] = field(default_factory=lambda: dict(integrator="rk4", steps=10))
    prefit: Callable | None = None
    weight_continuation: Sequence[float] | None = None
    smoothing: int = 11
    extra: Mapping[str, object] = field(default_factory=dict)

    def __post_init__(self):
        from shootlab.bvp.solver import solve
        known = [p for p in inspect.signature(solve).parameters if p not in ("prob", "t", "x_guess")]
        bad = sorted(set(self.solver) - set(known))
        if bad:
            raise ValueError(f"solver options {bad} are not options of shootlab.solve ({', '.join(known)})")
        if int(self.points) < 2:
            raise ValueError(f"points must be at least 2, got {self.points}")
        if self.span is not None and not float(self.span) > 0:
            raise ValueError(f"span must be a positive record length, got {self.span}")
        if int(self.smoothing) < 5 or int(self.smoothing) % 2 == 0:
            raise ValueError(f"smoothing must be an odd window of at least 5 samples, got {self.smoothing}")

    def as_dict(self) -> dict:
        """The ``settings`` dict that :class:`~shootlab.estimation.IdentificationModel` carries."""
        out = dict(self.extra, points=int(self.points), solve=dict(self.solver))
        if self.span is not None:
            out["span"] = float(self.span)
        if self.prefit is not None:
            out["initial_parameters"] = self.prefit
        if self.weight_continuation:
            out["weight_continuation"] = tuple(self.weight_continuation)
        return out
