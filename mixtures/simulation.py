"""Forward simulation of the confined-compression experiment (report ch. 5) with the finite-element
model of :mod:`mixtures.confined`, and the simulated measurements (the report's data set-up).

:func:`simulate` integrates the balance equations ``R* v + K(s,θ) p = 0``,
``S(s,θ) s − R*ᵀ p − F(s,θ) − H_u u = 0`` as the ODE ``s' = v(s, u)`` with
``scipy.integrate.solve_ivp`` (Radau by default) and the exact Jacobian; it supports load control
(creep: step, ramp-and-hold, user history; :func:`creep`) and displacement control (stress
relaxation: the filter displacement is prescribed and the load is the output;
:func:`stress_relaxation`).  :func:`simulated_measurements` gives the record (channels ``load``,
``displacement``, ``pressure``) as a :class:`shootlab.estimation.data.Measurements`; its CSV path is
:meth:`shootlab.estimation.data.Measurements.to_csv` / :meth:`~shootlab.estimation.data.Measurements.from_csv`.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy.integrate import solve_ivp

from shootlab.estimation.data import Measurements

from .confined import ConfinedCompression, _check_positive
from .loads import DEFAULT_EXPERIMENT, RampHoldLoad, SampledHistory, as_history

__all__ = ["Simulation", "simulate", "creep", "stress_relaxation", "MEASUREMENT_COLUMNS",
           "simulated_measurements"]

#: the record's CSV columns: time and the three measured channels
MEASUREMENT_COLUMNS = ("t", "load", "displacement", "pressure")


# ----------------------------------------------------------------------------------------------
# forward simulation
# ----------------------------------------------------------------------------------------------
@dataclasses.dataclass
class Simulation:
    """Time series of a forward simulation (numpy arrays).

    ``displacement`` is the compression ``−s_{N+1}`` (positive under load), ``pressure`` the bottom
    pore pressure ``p_1``; ``s``/``p`` the nodal values (``(T, N)``, nodes 2…N+1 / 1…N).
    """

    t: np.ndarray
    load: np.ndarray
    displacement: np.ndarray
    pressure: np.ndarray
    s: np.ndarray
    p: np.ndarray
    H: float
    K: float
    control: str
    nfev: int = 0
    info: dict = dataclasses.field(default_factory=dict)

    def measurements(self) -> Measurements:
        """The record: channels ``load``, ``displacement``, ``pressure`` (copies)."""
        return Measurements(self.t.copy(), {"load": self.load.copy(), "displacement": self.displacement.copy(),
                                            "pressure": self.pressure.copy()})


def _check_times(t_eval) -> np.ndarray:
    t = np.asarray(t_eval, dtype=float)
    if t.ndim != 1 or t.size < 1:
        raise ValueError("t_eval must be a non-empty 1-D array")
    if not np.all(np.isfinite(t)):
        raise ValueError("t_eval contains non-finite values")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        raise ValueError("t_eval must be strictly increasing")
    return t


def _segments(t0: float, t1: float, breakpoints) -> list[tuple[float, float]]:
    inner = sorted({float(b) for b in breakpoints if t0 < float(b) < t1})
    edges = [t0] + inner + [t1]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def simulate(model: ConfinedCompression, t_eval, load=None, H: float = 2.0, K: float = 1.0, *,
             displacement=None, s0=None, rtol: float = 1e-10, atol: float = 1e-12,
             method: str = "Radau", max_step: float = np.inf) -> Simulation:
    """Forward simulation of the confined-compression experiment.

    Exactly one of

    * ``load`` – load control (creep): a number (step at ``t = 0``), :class:`StepLoad`,
      :class:`RampHoldLoad`, ``(t_samples, u_samples)`` or a callable ``u(t)``; compression
      positive.
    * ``displacement`` – displacement control (stress relaxation): the prescribed compression
      ``d(t) = −s_{N+1}(t)`` of the sample, same kinds of spec.  It must be continuous (an
      instantaneous compression of an incompressible mixture needs an infinite load) and
      ``d(t_eval[0]) = 0`` unless ``s0`` is given.  The load is then an output.

    The state starts at ``s0`` (default: unloaded, ``s = 0``) at ``t_eval[0]``.  The stiff system
    is integrated with ``scipy.integrate.solve_ivp`` (``method`` Radau/BDF/LSODA), split at the
    breakpoints of the prescribed history, with the exact Jacobian:

    * linear laws: the system is affine, ``y' = J y + g(t)`` with constant ``J`` (``J = M``,
      ``g = b u`` under load control).  It is integrated in the eigenbasis of ``J`` (real,
      negative eigenvalues; ``M = −R*⁻¹KR*⁻ᵀS`` is similar to a symmetric matrix), where the
      Jacobian is diagonal.  This matters: the stiffest eigenvalue grows like ``N⁴`` (≈ −7e7 for
      ``N = 48``), and in nodal coordinates rounding in ``M s`` stalls the step control at tight
      tolerances.
    * non-linear laws: nodal coordinates, Jacobian by autograd; ``rtol`` is raised to at least
      ``4·eps·|λ_max/λ_min|`` of the initial Jacobian (the rounding floor), reported in
      ``Simulation.info``.

    Returns a :class:`Simulation` with the load, the compression, the bottom pressure and the
    nodal ``s`` and ``p`` at ``t_eval``.
    """
    _check_positive("H", H)
    _check_positive("K", K)
    H, K = float(H), float(K)
    if not isinstance(model, ConfinedCompression):
        raise ValueError("model must be a ConfinedCompression")
    t = _check_times(t_eval)
    if (load is None) == (displacement is None):
        raise ValueError("give exactly one of load= (creep) or displacement= (relaxation)")
    if not (rtol > 0 and atol > 0):
        raise ValueError("rtol and atol must be > 0")
    N = model.N
    if s0 is None:
        s_init = np.zeros(N)
    else:
        s_init = np.asarray(s0, dtype=float).reshape(-1)
        if s_init.size != N or not np.all(np.isfinite(s_init)):
            raise ValueError(f"s0 must be {N} finite numbers")
        s_init = s_init.copy()

    def Tt(x):
        return torch.as_tensor(x, dtype=torch.float64)

    hist = as_history(load if load is not None else displacement)
    hist.check_covers(t[0], t[-1])
    breakpoints = tuple(hist.breakpoints)
    if load is not None and isinstance(hist, SampledHistory):
        breakpoints = ()  # a piecewise-linear load is continuous: no need to restart at kinks

    if load is not None:
        control = "load"
        y0 = s_init

        H_t, K_t = Tt(H), Tt(K)

        def vel(y, tt, left):
            u = Tt(float(hist.value(tt, left=left)))
            return model._velocity(y, u, H_t, K_t)
    else:
        control = "displacement"
        d0 = float(hist.value(t[0]))
        if s0 is None and d0 != 0.0:
            raise ValueError("the prescribed compression must start at 0 unless s0 is given "
                             f"(d(t0) = {d0})")
        s_init[-1] = -d0
        y0 = s_init[:-1]

        def interior(y, top, vtop):
            s_full = torch.cat([y, top.reshape(1)])
            u = model.relaxation_load(s_full, vtop, H, K)
            return model.velocity(s_full, u, H, K)[:-1]

        def vel(y, tt, left):
            top = Tt(-float(hist.value(tt, left=left)))
            vtop = Tt(-float(hist.rate(tt, left=left)))
            return interior(y, top, vtop)

    def f_factory(a, b):
        def f(tt, y):
            return vel(Tt(y), tt, tt >= b).numpy()
        return f

    def jac_at(tt, y, left=False):
        return torch.func.jacrev(lambda x: vel(x, tt, left))(Tt(y)).numpy()

    info = {"method": method, "rtol": rtol, "atol": atol}
    n = y0.size
    basis = None
    if model.is_linear and n > 0:
        if control == "load":
            J, bvec = model.linear_system(H, K)

            def g_factory(a, b):
                return lambda tt: bvec * float(hist.value(tt, left=tt >= b))
        else:
            # affine in (y, top, vtop): y' = J y + g_top·top(t) + g_rate·vtop(t)
            zero, one, nil = Tt(np.zeros(n)), Tt(1.0), Tt(0.0)
            J = torch.func.jacrev(lambda x: interior(x, nil, nil))(zero).numpy()
            g_top = interior(zero, one, nil).numpy()
            g_rate = interior(zero, nil, one).numpy()

            def g_factory(a, b):
                def g(tt):
                    left = tt >= b
                    return (g_top * -float(hist.value(tt, left=left))
                            + g_rate * -float(hist.rate(tt, left=left)))
                return g
        basis = _real_eigenbasis(J)
    if basis is not None:
        lam, V, Vi = basis
        info["coordinates"] = "modal"
        info["stiffness_ratio"] = float(np.abs(lam).max() / np.abs(lam).min())
        jac_modal = np.diag(lam)

        def fm_factory(a, b):
            g = g_factory(a, b)
            return lambda tt, z: lam * z + Vi @ g(tt)

        Z, nfev = _integrate(fm_factory, lambda a, b: jac_modal, Vi @ y0, t, breakpoints,
                             rtol, atol, method, max_step)
        Y = Z @ V.T
        Y[0] = y0
    else:
        info["coordinates"] = "nodal"
        if model.is_linear:
            def jac_factory(a, b):
                return J if n > 0 else None
        else:
            def jac_factory(a, b):
                return lambda tt, y: jac_at(tt, y, tt >= b)
        if n > 0:
            ev = np.abs(np.linalg.eigvals(jac_at(t[0], y0)))
            if ev.min() > 0:
                info["stiffness_ratio"] = float(ev.max() / ev.min())
                rtol = float(max(rtol, 4 * np.finfo(float).eps * info["stiffness_ratio"]))
                info["rtol"] = rtol
        Y, nfev = _integrate(f_factory, jac_factory, y0, t, breakpoints, rtol, atol,
                             method, max_step)
    info["nfev"] = int(nfev)

    if control == "load":
        S = Y
        u_out = np.asarray(hist.value(t), dtype=float) * np.ones_like(t)
    else:
        top = -np.asarray(hist.value(t), dtype=float) * np.ones_like(t)
        S = np.concatenate([Y, top[:, None]], axis=1)
        vtop = -np.asarray(hist.rate(t), dtype=float) * np.ones_like(t)
        u_out = model.relaxation_load(Tt(S), Tt(vtop), H, K).numpy()
    P = model.pressure(Tt(S), Tt(u_out), H).numpy()
    return Simulation(t=t, load=u_out, displacement=-S[:, -1].copy(), pressure=P[:, 0].copy(),
                      s=S, p=P, H=H, K=K, control=control, nfev=int(nfev), info=info)


def _real_eigenbasis(J: np.ndarray):
    """``(λ, V, V⁻¹)`` with ``J = V diag(λ) V⁻¹``, or ``None`` if ``J`` is not safely
    diagonalisable over the reals (then the caller integrates in nodal coordinates)."""
    try:
        lam, V = np.linalg.eig(J)
    except np.linalg.LinAlgError:
        return None
    scale = max(np.abs(lam).max(), 1e-300)
    if np.abs(lam.imag).max() > 1e-10 * scale or np.abs(V.imag).max() > 1e-10:
        return None
    lam, V = lam.real, V.real
    if np.linalg.cond(V) > 1e8:
        return None
    Vi = np.linalg.inv(V)
    if np.abs(V @ (lam[:, None] * Vi) - J).max() > 1e-10 * np.abs(J).max():
        return None
    return lam, V, Vi


def _integrate(f_factory, jac_factory, y0, t, breakpoints, rtol, atol, method, max_step):
    """Integrate ``y' = f(t, y)`` from ``y0`` at ``t[0]``; output at ``t``; split at breakpoints.

    ``f_factory(a, b)`` gives the rhs for the segment ``[a, b]`` (prescribed histories evaluated
    with the left limit at ``b``), so discontinuities of the input are never stepped over.
    """
    n = y0.size
    Y = np.empty((t.size, n))
    Y[0] = y0
    if t.size == 1 or n == 0:
        Y[:] = y0
        return Y, 0
    y = y0.astype(float).copy()
    nfev = 0
    for a, b in _segments(t[0], t[-1], breakpoints):
        mask = (t > a) & (t <= b)
        t_out = np.append(t[mask], b) if (not mask.any() or t[mask][-1] < b) else t[mask]
        sol = solve_ivp(f_factory(a, b), (a, b), y, method=method, t_eval=t_out, rtol=rtol,
                        atol=atol, jac=jac_factory(a, b), max_step=max_step)
        if not sol.success:
            raise RuntimeError(f"integration failed on [{a}, {b}]: {sol.message}")
        nfev += sol.nfev
        Y[mask] = sol.y.T[: int(mask.sum())]
        y = sol.y[:, -1].copy()
    return Y, nfev


def creep(model: ConfinedCompression, t_eval, P: float = 1.0, t_ramp: float = 0.0,
          H: float = 2.0, K: float = 1.0, **kw) -> Simulation:
    """Creep test: load ramped to ``P`` over ``t_ramp`` (0: step) from ``t_eval[0]``, then held."""
    t = _check_times(t_eval)
    return simulate(model, t, load=RampHoldLoad(P, t_ramp, t_start=float(t[0])), H=H, K=K, **kw)


def stress_relaxation(model: ConfinedCompression, t_eval, d: float = 0.1, t_ramp: float = 0.1,
                      H: float = 2.0, K: float = 1.0, **kw) -> Simulation:
    """Stress relaxation: the compression is ramped to ``d`` over ``t_ramp > 0`` and held; the
    load (output) peaks at the end of the ramp and relaxes to ``H d / L``."""
    if not t_ramp > 0:
        raise ValueError("stress relaxation needs t_ramp > 0 (a displacement step is "
                         "incompatible with an incompressible mixture)")
    t = _check_times(t_eval)
    return simulate(model, t, displacement=RampHoldLoad(d, t_ramp, t_start=float(t[0])), H=H,
                    K=K, **kw)


def simulated_measurements(t=None, H: float = 2.0, K: float = 1.0, elements: int = 3,
                           load=DEFAULT_EXPERIMENT, noise=0.0, seed: int = 0,
                           length: float = 1.0) -> Measurements:
    """Simulated experiment (the report's set-up: true H = 2, K = 1, 3 elements, t ∈ [0, 1]).

    A :class:`shootlab.estimation.data.Measurements` with channels ``load``, ``displacement``, ``pressure``.
    ``t`` defaults to 401 points on [0, 1]; ``load`` defaults to :data:`DEFAULT_EXPERIMENT`.
    ``noise`` is the standard deviation of independent Gaussian noise added to the measured
    channels: a scalar (all three of load, displacement, pressure) or a 3-sequence
    ``(σ_load, σ_displacement, σ_pressure)``.  ``t`` is noise-free.
    """
    if t is None:
        t = np.linspace(0.0, 1.0, 401)
    model = ConfinedCompression(elements=elements, length=length)
    sim = simulate(model, t, load=load, H=H, K=K)
    sig = np.broadcast_to(np.asarray(noise, dtype=float), (3,))
    if np.any(sig < 0) or not np.all(np.isfinite(sig)):
        raise ValueError("noise must be finite and ≥ 0")
    rng = np.random.default_rng(seed)
    cols = [sim.load, sim.displacement, sim.pressure]
    noisy = [c + (s * rng.standard_normal(c.shape) if s > 0 else 0.0) for c, s in zip(cols, sig)]
    return Measurements(sim.t.copy(), dict(zip(MEASUREMENT_COLUMNS[1:], noisy)))
