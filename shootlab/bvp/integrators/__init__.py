"""Batched initial value problem integrators.

Multiple shooting integrates many independent IVPs -- one per shooting
interval, each with its own start time ``t0``, end time ``t1`` and initial
value ``y0`` -- and this package advances all of them together as one tensor::

    integ = get_integrator("ros4", rtol=1e-8, atol=1e-10)
    res = integ.integrate(rhs, t0, t1, y0)      # t0, t1: (B,), y0: (B, n)
    res.y, res.failed, res.reason, res.nfev, res.nsteps

``rhs(t, y)`` receives ``y`` of shape ``(m, n)`` and ``t`` of shape ``(m,)``
and must treat the rows independently: the number of rows ``m`` changes
between calls, because rows that finished (or failed) are dropped from the
active set and implicit schemes stack stage values into one call.

One scheme per module, registered in :data:`INTEGRATORS`; every scheme carries its own facts
as class attributes -- ``order``, ``adaptive``, ``kind``, ``stable``, the stability function
``stability(z)`` and a one-line ``description`` -- which :mod:`shootlab.bvp.suggest` and
:mod:`shootlab.bvp.solver` read (:func:`facts` tabulates them):

=================  =========================================================
``euler``          explicit Euler, ``steps`` equal steps (:mod:`.euler`)
``rk4``            classical Runge--Kutta, ``steps`` equal steps (:mod:`.rk4`)
``rkf45``          Fehlberg 4(5), 4th-order solution, ``steps`` equal steps (:mod:`.rkf45`)
``implicit_euler`` backward Euler + Newton, ``steps`` equal steps (:mod:`.implicit_euler`)
``midpoint``       implicit midpoint rule + Newton, ``steps`` equal steps (:mod:`.midpoint`)
``radau3``         2-stage Radau IIA (order 3, L-stable) + Newton (:mod:`.radau3`)
``dopri5``         Dormand--Prince 5(4), per-element adaptive steps (:mod:`.dopri5`)
``dop853``         Hairer's DOP853, order 8 with a 5(3) error estimate, adaptive (:mod:`.dop853`)
``ros4``           Shampine's Rosenbrock 4(3), per-element adaptive steps (:mod:`.ros4`)
``auto``           ``dop853`` per row, ``ros4`` on the rows whose local Jacobian
                   is stiff over the row's length (:mod:`.auto`)
=================  =========================================================

Failures never raise: a row whose values become non-finite, whose step size
underflows, which exceeds ``max_steps`` or whose implicit stage equations do
not converge is frozen at its last finite state, flagged in
``IntegrationResult.failed`` and dropped from the computation; the other rows
carry on.

Differentiation.  The state updates are ordinary differentiable torch
operations, so ``y0`` may be a forward-mode dual tensor (the shooting code
replicates each interval ``n`` times with identity tangents to obtain
``dy(t1)/dy0``) or may require grad (reverse mode).  Everything used only for
control flow -- error norms, step sizes, convergence tests -- is computed from
detached values, so step sizes carry no tangent.  Implicit stage equations are
solved by Newton's method on detached values; one final Newton correction is
then applied to the non-detached quantities, which by the implicit function
theorem gives the exact derivative of the converged stages.

References:
  [HNW1] E. Hairer, S.P. Norsett, G. Wanner, Solving Ordinary Differential
         Equations I, 2nd ed., Springer 1993.
  [HW2]  E. Hairer, G. Wanner, Solving Ordinary Differential Equations II,
         2nd ed., Springer 1996.
  [NR]   W.H. Press et al., Numerical Recipes in C, 2nd ed., 1992, sec. 16.6.
"""
from __future__ import annotations

from typing import Any

from .adaptive import AdaptiveIntegrator
from .auto import Auto
from .base import MAX_STEPS, NO_CONVERGENCE, NONFINITE, RHS, UNDERFLOW, FixedStepIntegrator, IntegrationResult, Integrator
from shootlab.bvp.tangents import _value_and_jacobian, batch_jacobian
from .dop853 import Dop853
from .dopri5 import Dopri5
from .euler import Euler
from .explicit import ExplicitRK, tableau_polynomial
from .implicit import _simplified_newton
from .implicit_euler import ImplicitEuler
from .midpoint import ImplicitMidpoint
from .radau3 import Radau3
from .rk4 import RK4
from .rkf45 import RKF45
from .ros4 import Ros4

__all__ = ["Integrator", "FixedStepIntegrator", "AdaptiveIntegrator", "IntegrationResult", "INTEGRATORS",
           "get_integrator", "batch_jacobian", "facts", "ExplicitRK", "Euler", "RK4", "RKF45", "ImplicitEuler",
           "ImplicitMidpoint", "Radau3", "Dopri5", "Dop853", "Ros4", "Auto", "tableau_polynomial", "RHS",
           "NONFINITE", "UNDERFLOW", "MAX_STEPS", "NO_CONVERGENCE", "_value_and_jacobian", "_simplified_newton"]

INTEGRATORS: dict[str, type[Integrator]] = {
    cls.name: cls for cls in (Euler, RK4, RKF45, Dopri5, Dop853, ImplicitEuler, ImplicitMidpoint, Radau3, Ros4, Auto)
}


def facts() -> list[dict]:
    """The declared facts of every registered scheme, one dict per scheme (registry order)."""
    return [dict(name=name, order=cls.order, adaptive=cls.adaptive, kind=cls.kind, stable=cls.stable,
                 description=cls.description) for name, cls in INTEGRATORS.items()]


def get_integrator(name: str, **options: Any) -> Integrator:
    """Instantiate the integrator registered as ``name`` (see :data:`INTEGRATORS`).

    ``options`` go to the constructor; all schemes accept ``steps``, ``rtol``
    and ``atol``.  Raises ValueError for an unknown name.
    """
    try:
        cls = INTEGRATORS[name]
    except KeyError:
        raise ValueError(f"unknown integrator {name!r}; available: "
                         f"{', '.join(sorted(INTEGRATORS))}") from None
    return cls(**options)
