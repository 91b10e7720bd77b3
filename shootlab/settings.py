"""Typed estimation settings of a model (:func:`shootlab.model`): the shooting points, the
solver's options and the stages run before the estimate — the compiled model carries them as its
``settings`` dict (:meth:`EstimationSettings.as_dict`), which :func:`shootlab.estimation.estimate`
and the CLI read."""
from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

__all__ = ["EstimationSettings", "shorter_intervals", "MAX_INTERVALS", "OWN_GRID"]


@dataclass(frozen=True)
class EstimationSettings:
    """Typed defaults for :func:`shootlab.estimation.estimate` and the CLI (the model's
    ``settings`` dict, :meth:`as_dict`).

    points               shooting points (``--points`` overrides)
    solver               options of :func:`shootlab.solve` (``integrator``, ``steps``, ``newton``,
                         ``tol``, ``continuation``, …; checked against its signature); default
                         RK4 with 10 steps per interval, as the built-in models: with the default
                         W = 1e10 the TPBVP is stiff enough that the solver's own default (an
                         adaptive Rosenbrock method) takes tiny steps (measured on the drive of
                         docs/your_own_model.md: 2 minutes per Newton iteration with a fresh
                         Jacobian, against 0.4 s)
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
    solver: Mapping[str, object] = field(default_factory=lambda: dict(integrator="rk4", steps=10))
    prefit: Callable | None = None
    weight_continuation: Sequence[float] | None = None
    smoothing: int = 11
    extra: Mapping[str, object] = field(default_factory=dict)

    def __post_init__(self):
        from .solver import solve
        known = [p for p in inspect.signature(solve).parameters if p not in ("prob", "t", "x_guess")]
        bad = sorted(set(self.solver) - set(known))
        if bad:
            raise ValueError(f"solver options {bad} are not options of shootlab.solve ({', '.join(known)})")
        if int(self.points) < 2:
            raise ValueError(f"points must be at least 2, got {self.points}")
        if int(self.smoothing) < 5 or int(self.smoothing) % 2 == 0:
            raise ValueError(f"smoothing must be an odd window of at least 5 samples, got {self.smoothing}")

    def as_dict(self) -> dict:
        """The ``settings`` dict that :class:`~shootlab.estimation.IdentificationModel` carries."""
        out = dict(self.extra, points=int(self.points), solve=dict(self.solver))
        if self.prefit is not None:
            out["initial_parameters"] = self.prefit
        if self.weight_continuation:
            out["weight_continuation"] = tuple(self.weight_continuation)
        return out


#: the most shooting intervals :func:`shorter_intervals` makes.  Every interval runs as a row of one
#: batch and a fixed-step scheme's steps run one after another, so k steps on m − 1 intervals cost
#: k calls of the right-hand side on m − 1 rows, and a call's fixed cost weighs most on few rows
#: (measured, eq. 2.7, one thread: the rig with friction 1.2 ms on 100 rows, 5.5 ms on 1,000; the
#: 3-element mixture 1.3 / 4.2 / 14.4 ms on 100 / 1,000 / 3,200 rows), while the Jacobian and its
#: factorisation grow with the intervals.  The rig record's nominal estimate: 100 intervals × 10
#: RK4 steps 2.5 s, 1,000 × 1 1.1 s; the 3-element mixture's, 400 × 8 RK4 steps 0.66 s, 800 × 4
#: 0.59 s, 1,600 × 2 0.69 s, 3,200 × 1 0.96 s
MAX_INTERVALS = 1000

#: the settings key under which :func:`shorter_intervals` keeps the model's own grid
OWN_GRID = "own_grid"


def shorter_intervals(settings: Mapping, max_intervals: int = MAX_INTERVALS) -> tuple[dict, int]:
    """The same discrete equations on more, shorter shooting intervals: where the solver's (last
    continuation stage's) scheme takes k fixed steps per interval on m points, k / f steps on
    (m − 1) f + 1 points, f the largest divisor of k with (m − 1) f ≤ ``max_intervals``.  The
    solution of the TPBVP is the same (every step starts where the last one ended, whether or not
    a shooting point lies between them); what changes is that f times fewer steps run one after
    another, each on f times as many rows (:data:`MAX_INTERVALS`), and a Newton iteration's
    linearisation is that of the finer grid.  Earlier continuation stages take ⌈k_i / f⌉ steps
    (no longer than before); adaptive schemes keep theirs.  Returns the settings (a new dict; the
    input unchanged where f = 1; else with the model's own ``points`` and ``solve`` under
    :data:`OWN_GRID`, where :func:`shootlab.estimators.estimate_retrying` goes back to when an
    estimate fails on the shorter intervals) and f."""
    from .integrators import INTEGRATORS
    from .solver import _steps

    solve = dict(settings.get("solve", {}))
    stages = list(solve.get("continuation") or ())

    def fixed_steps(st: dict) -> int | None:         # a stage's steps per interval, None if adaptive
        merged = {**solve, **st}
        name = merged.get("integrator")
        if name not in INTEGRATORS or INTEGRATORS[name].adaptive:
            return None
        return _steps(name, dict(steps=merged.get("steps")))

    m, k = int(settings.get("points", 101)), fixed_steps(stages[-1] if stages else {})
    if k is None or (m - 1) * 2 > max_intervals:
        return dict(settings), 1
    f = max(d for d in range(1, k + 1) if k % d == 0 and (m - 1) * d <= max_intervals)
    if f == 1:
        return dict(settings), 1

    def shorter(st: dict) -> dict:
        k_i = fixed_steps(st)
        return st if k_i is None else dict(st, steps=-(-k_i // f))

    if stages:
        solve["continuation"] = [shorter(dict(st)) for st in stages]
    else:
        solve = shorter(solve)
    own = {"points": m, "solve": settings.get("solve", {})}
    return dict(settings, points=(m - 1) * f + 1, solve=solve, **{OWN_GRID: own}), f
