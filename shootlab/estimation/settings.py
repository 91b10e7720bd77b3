"""The settings an identification model carries (``model.settings``): one frozen dataclass,
:class:`EstimationSettings`, with the estimation defaults that :func:`shootlab.estimation.estimate`
and the CLI read, what :func:`shootlab.model` compiles into a model, and the hooks of the
output-error fit and the diagnosis."""
from __future__ import annotations

import dataclasses
import inspect
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

__all__ = ["EstimationSettings"]


@dataclass(frozen=True)
class EstimationSettings:
    """The settings of an :class:`~shootlab.estimation.IdentificationModel` (``model.settings``).
    Frozen: a changed copy is ``settings.replace(points=201)``.

    Estimation defaults (``estimate`` and the CLI; ``--points`` and the solver flags override them)

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
                         or raise ValueError for bad ones)
    weight_continuation  levels at which the diagonal V is capped in easier stages estimated
                         first, each warm-starting the next (report §4.2)
    fallback             where the Newton iteration stalls, try ``armijo`` and then
                         ``trust_region`` from the same start
                         (:func:`shootlab.estimation.fit.solve_falling_back`); default True
    smoothing            Savitzky–Golay window (samples) that differentiates a measured state for
                         the initial approximation of its derivative state (read when
                         :func:`shootlab.model` compiles the model)

    Compiled by :func:`shootlab.model`

    weights_from_data    the weight entries left to the defaults, ``{"W": [w_j or None per state
                         and parameter], "V": [v_i or None per row]}`` (None: given by the user),
                         scaled by the data when estimated (:func:`shootlab.estimation.weights.from_data`)
    mechanics            the :class:`~shootlab.estimation.mechanics.Mechanics` a model declares
                         (the diagnosis's mechanical library)

    Output error and diagnosis

    simulate             the model's exact free run ``(model, data, params, s0) -> channels``, the
                         output-error fit's simulator (default: :class:`~shootlab.estimation.free_run.FreeRun`)
    refine               ``() -> IdentificationModel | None``: the same model on a finer
                         discretisation (the diagnosis's check for a discretisation error,
                         :mod:`shootlab.diagnosis.numerics`)
    resolution           that discretisation in words (``"3 elements"``)
    diagnosis_library    the model's own candidate library (:func:`shootlab.diagnosis.libraries.library_for`)
    effects              the effects added to a nominal model (:func:`shootlab.diagnosis.composition.extend`)
    nominal_model        the name of the model they were added to (whose library is used)

    extra                further model-specific entries, kept as they are
    """

    points: int = 101
    span: float | None = None
    solver: Mapping[str, Any] = field(default_factory=lambda: dict(integrator="rk4", steps=10))
    prefit: Callable | None = None
    weight_continuation: Sequence[float] | None = None
    fallback: bool = True
    smoothing: int = 11
    weights_from_data: Mapping[str, list] | None = None
    mechanics: Any = None
    simulate: Callable | None = None
    refine: Callable | None = None
    resolution: str | None = None
    diagnosis_library: Any = None
    effects: tuple[str, ...] = ()
    nominal_model: str | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        from shootlab.bvp.solver import solve
        if not isinstance(self.solver, Mapping):
            raise ValueError(f"solver must be a mapping of options of shootlab.solve, got {type(self.solver).__name__}")
        known = [p for p in inspect.signature(solve).parameters if p not in ("prob", "t", "x_guess")]
        bad = sorted(set(self.solver) - set(known))
        if bad:
            raise ValueError(f"solver options {bad} are not options of shootlab.solve ({', '.join(known)})")
        if isinstance(self.points, bool) or int(self.points) != self.points or int(self.points) < 2:
            raise ValueError(f"points must be an integer of at least 2, got {self.points!r}")
        if self.span is not None and not float(self.span) > 0:
            raise ValueError(f"span must be a positive record length, got {self.span}")
        object.__setattr__(self, "points", int(self.points))
        object.__setattr__(self, "span", None if self.span is None else float(self.span))
        if int(self.smoothing) < 5 or int(self.smoothing) % 2 == 0:
            raise ValueError(f"smoothing must be an odd window of at least 5 samples, got {self.smoothing}")
        for name in ("prefit", "simulate", "refine"):
            if getattr(self, name) is not None and not callable(getattr(self, name)):
                raise ValueError(f"{name} must be a callable or None, got {type(getattr(self, name)).__name__}")
        if isinstance(self.effects, str):
            raise ValueError(f"effects must be a sequence of effect names, got the string {self.effects!r}")
        object.__setattr__(self, "effects", tuple(self.effects))
        if self.weight_continuation is not None:
            object.__setattr__(self, "weight_continuation", tuple(float(v) for v in self.weight_continuation))

    def replace(self, **changes) -> EstimationSettings:
        """A copy with ``changes`` (field names; checked as at construction)."""
        return dataclasses.replace(self, **changes)
