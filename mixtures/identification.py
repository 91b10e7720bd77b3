"""The confined-compression experiment as an identification model (report §5.2, docs/design.md §3).

Augmented state form (report eqs. 5.2–5.4), ``N`` elements (:mod:`mixtures.confined`)::

    x = [s_2 … s_{N+1}, H, K]          node displacements and the two parameters
    ζ = [v_2 … v_{N+1}, p_1 … p_N, u]  velocities, pore pressures, load

    s' = v + ε_s,   H' = ε_H,   K' = ε_K          (A = 0, B = [I 0 0; 0 0 0])
    rows of E z_m = f(x) + F(x) ζ + ξ:
        mass_i      (N rows)  0   = R* v + K(s, K) p
        momentum_j  (N rows)  0   = S(s, H) s − F(s, H) − R*ᵀ p − H_u u
        load                  u_m = u
        displacement          d_m = −s_{N+1}       (compression of the sample, positive)
        pressure              p_m = p_1            (pore pressure at the bottom)

Declared with :func:`shootlab.model`: s, v, p and the two balances are blocks of N components,
the balances written matrix-free (:meth:`~mixtures.confined.ConfinedCompression.mass_balance`,
:meth:`~mixtures.confined.ConfinedCompression.momentum_balance`); the compiled f and F equal the
assembled matrices bit for bit.

Units: none — the report's experiment is dimensionless (time on [0, 1]); ``model.units``
declares every quantity "-".

Data: channels ``load``, ``displacement``, ``pressure`` (CSV columns ``t,load,displacement,
pressure``, as written by :func:`mixtures.simulation.simulated_measurements`).

Weights (report §5.3: "weighting matrices W_a = 0, W = I, V = I"): ``W = I`` (N + 2),
``V = I`` (2N + 3), ``W_a = 0``.  With these weights, ``H = K = 4`` and the linear initial
profile the local Jacobian of the TPBVP has the eigenvalues ±4896 of the report's fig. 5.4;
they scale like H·K (±613 at the solution H = 2, K = 1) and roughly like N⁴ (N = 10: ±8.8e5,
N = 20: ±1.3e7 at the initial approximation).

Initial approximation (report §5.3): node displacements linear in the node height from the
measured displacement, ``s_j(t) = −d_m(t) z_j / L``; ``H = K = 4`` unless given; costates 0.

Solver settings (``model.settings``, measured in ``studies/confined_report.py``):

* ``N = 3`` (the report's mesh): 401 shooting points and the report's tolerance continuation
  (:data:`CONTINUATION`: one explicit Euler step per interval, then RK4).  Without it the
  explicit runs fail (overflow / singular Newton matrix), as MUSN did.
* ``N ≥ 4``: the TPBVP is far too stiff for explicit schemes (κ ≈ −1e6 … −1e7) and an
  L-stable scheme (radau3, implicit Euler) damps the *growing* fast modes as well, which
  destroys the dichotomy of the Hamiltonian system: the Newton matrix becomes singular.  A
  symmetric A-stable scheme keeps it: the implicit midpoint rule (integrator
  ``"midpoint"`` of :mod:`shootlab.bvp.integrators`), with 51 shooting points (201 for N > 10).  It
  converges only from close by, so the initial parameter values are first refined by an
  output-error fit (``prefit``: a forward simulation of the N-element model fitted to the
  measurements) and the initial states are a forward simulation with those values
  (``states="simulated"``).  The alternative, a 3-element TPBVP estimate first (``coarse=3``:
  continuation in the mesh, the analogue of the report's tolerance continuation), works on
  noise-free data but on a noisy 20-element record settles at K ≈ 0.075.  N = 20 with 1 % noise
  needs 201 points: on 101 the Newton iteration stalls at |F| ≈ 2e-2 even from the fit
  (noise-free, 101 points suffice).
"""
from __future__ import annotations

import math
import time
import warnings
from typing import Mapping

import numpy as np
import torch
from torch import Tensor

import shootlab
from shootlab.estimation.data import Interpolant, Measurements
from shootlab.estimation.settings import EstimationSettings
from shootlab.estimation import IdentificationModel

from .confined import ConfinedCompression
from .prefit import filter_system, linear_outputs, linear_response, output_error_fit
from .simulation import MEASUREMENT_COLUMNS, simulate

__all__ = ["model", "as_data", "initial_profile", "simulated_profile", "CONTINUATION",
           "LOOSE", "FINE", "check_parameters", "estimate_two_grid"]


# -- settings -----------------------------------------------------------------------------------
#: The report's strategy (§5.4): one explicit Euler step per shooting interval first, then
#: tighter.  RK4 with 8 steps per interval (step 3.1e-4 on 401 points) keeps |κ h| ≈ 1.5 inside
#: RK4's stability interval even at the initial κ ≈ −4896 — the report's "2500 points" rule of
#: thumb applied to internal steps instead of shooting points.
CONTINUATION = [dict(integrator="euler", steps=1, tol=1e-4),
                dict(integrator="rk4", steps=2),
                dict(integrator="rk4", steps=8)]

#: Defaults of the report's 3-element mesh (and N < 3).
SETTINGS_N3 = dict(points=401, solve=dict(continuation=CONTINUATION))

#: The loose first stage of :func:`estimate_two_grid`: one explicit Euler step per interval on
#: 401 points, Newton stopped at |F| ≤ 1e-4 (tighter is not reachable with 1 % noise).
LOOSE = dict(points=401, solve=dict(continuation=[dict(CONTINUATION[0])]))

#: Finer meshes (N ≥ 4): implicit midpoint, after the output-error fit, on 51 shooting points
#: up to N = 10 and 201 beyond (N = 20 on 51 points: singular Newton matrix; on 101 with 1 %
#: noise: stalls).
#: ``max_growth=None``: the growth guard of shootlab.solve measures e^{κ h} of the exact flow,
#: which a symmetric A-stable step does not reproduce (|R| stays near 1).
#: ``newton="armijo"``: on these meshes the Newton matrix is very ill-conditioned (κh up to 4e3 at
#: N = 20) and the error-oriented test of the default ``deuflhard`` compares Newton corrections
#: that carry its rounding error — on a 20-element record with 1 % noise it crawled to λ = 1e-8
#: and stopped at |F| = 8e-4, while the Armijo test on ‖F‖ converges in 7 iterations (noise-free:
#: 3 iterations either way).  The output-error prefit starts it close by, where the Armijo test's
#: weakness (a step that lowers ‖F‖ but throws the parameters off) does not arise.
FINE = dict(points=51, solve=dict(integrator="midpoint", steps=2, max_growth=None, max_iter=40, newton="armijo"))


#: the diagnosis's refinement (``settings.refine``): N -> REFINE_FACTOR·N elements
REFINE_FACTOR = 2


def as_data(table) -> dict[str, np.ndarray]:
    """A :class:`shootlab.estimation.data.Measurements` record with channels ``load, displacement, pressure``
    (:func:`mixtures.simulation.simulated_measurements`), or a mapping with the keys ``t, load,
    displacement, pressure``, as the mapping :func:`shootlab.estimate` takes."""
    if isinstance(table, Measurements):
        table = dict(table.channels, t=table.t)
    return {c: np.asarray(table[c], dtype=np.float64) for c in MEASUREMENT_COLUMNS}


# -- checks and initial approximation -------------------------------------------------------
def _check_parameter(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"initial {name} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        what = "confined compression modulus" if name == "H" else "permeability"
        raise ValueError(f"initial {name} ({what}) must be finite and > 0, got {value!r}")
    return v


def check_parameters(params: Mapping[str, float]) -> dict[str, float]:
    """The initial H and K as floats; ValueError unless both are finite and positive."""
    return {k: (_check_parameter(k, v) if k in ("H", "K") else float(v)) for k, v in params.items()}


def _check_covers(data: Measurements, channel: str, a: float, b: float) -> None:
    """ValueError unless ``channel`` has a valid sample at or beyond both ends of [a, b] and no
    missing sample in between (the model needs the load at every time)."""
    t, v = data.t, data.channels[channel]
    tol = 1e-12 * max(1.0, abs(a), abs(b))
    lo = int(np.searchsorted(t, a + tol, side="right")) - 1
    hi = int(np.searchsorted(t, b - tol, side="left"))
    if lo < 0 or hi >= t.size:
        raise ValueError(f"the {channel} history covers [{t[0]:g}, {t[-1]:g}], not the time "
                         f"interval [{a:g}, {b:g}]")
    gap = np.isnan(v[lo:hi + 1])
    if gap.any():
        bad = t[lo:hi + 1][gap]
        raise ValueError(f"the {channel} history does not cover the time interval [{a:g}, {b:g}]: "
                         f"{bad.size} missing sample(s) from t = {bad[0]:g} to {bad[-1]:g}")


def initial_profile(cc: ConfinedCompression, data: Measurements, t: Tensor) -> Tensor:
    """(m, N) node displacements linear in the node height from the measured compression:
    ``s_j(t) = −d_m(t) z_j / L`` (report §5.3)."""
    d = Interpolant(data, ["displacement"], t.dtype, t.device).values(t)[..., 0]
    z = torch.as_tensor(cc.nodes[1:] / cc.L, dtype=t.dtype, device=t.device)
    return -d.unsqueeze(-1) * z


def simulated_profile(cc: ConfinedCompression, data: Measurements, t: Tensor, H: float, K: float) -> Tensor:
    """(m, N) node displacements of a forward simulation with H, K under the measured load
    (piecewise linear through the samples), starting unloaded at t[0].  Linear material laws:
    the exact first-order-hold solution of s' = A s + b u on the samples (one matrix exponential
    per step length; :func:`mixtures.prefit.linear_response`), interpolated linearly to t —
    the general simulation restarts its implicit integrator at every sample of a noisy load
    (12.9 s for 20 elements and 401 samples, against well under a second)."""
    ok = ~np.isnan(data.channels["load"])
    tn = t.detach().cpu().numpy()
    if cc.is_linear:
        ts = data.t[ok]
        ts = np.concatenate([[tn[0]], ts[(ts >= tn[0]) & (ts <= tn[-1])], [tn[-1]]])
        us = np.interp(ts, data.t[ok], data.channels["load"][ok])
        A, b, _, _ = filter_system(H, K, 0.0, cc.N, cc.L)
        states = linear_response(A, b, np.eye(cc.N), np.zeros(cc.N), us, ts)
        s = np.stack([np.interp(tn, ts, states[:, j]) for j in range(cc.N)], -1)
        return torch.as_tensor(s, dtype=t.dtype, device=t.device)
    sim = simulate(cc, tn, load=(data.t[ok], data.channels["load"][ok]), H=H, K=K)
    return torch.as_tensor(sim.s, dtype=t.dtype, device=t.device)


# -- the model --------------------------------------------------------------------------------
def model(elements: int = 3, length: float = 1.0, W=None, V=None, W_a=None, H: float = 4.0,
          K: float = 4.0, solid=None, permeability=None, points: int | None = None,
          integrator: str | None = None, steps: int | None = None, coarse: int | None = -1,
          states: str | None = None, prefit: bool | None = None) -> IdentificationModel:
    """The confined-compression identification model with ``elements`` linear elements.

    W, V, W_a    weights (default: the report's I, I, 0); a vector is a diagonal
    H, K         default initial parameter values (the report's 4, 4)
    solid, permeability   material laws of :class:`~mixtures.confined.ConfinedCompression`
    points       default number of shooting points (N ≤ 3: 401; N ≤ 10: 51; else 201)
    integrator, steps     one integrator instead of the default schedule (e.g. ``radau3``)
    prefit       refine the initial H, K first by an output-error fit of the linear
                 N-element model (:func:`mixtures.prefit.output_error_fit`: a forward
                 simulation fitted to the displacement and pressure, well under a second);
                 default True for N > 3, False for N ≤ 3 (the report's start).  On a noisy
                 20-element record the 3-element start below settled in a spurious minimum
                 (K = 0.075); the simulation fit does not have that basin near (4, 4).
    coarse       refine the initial H, K by a ``coarse``-element estimate (mesh continuation,
                 the report's weights and settings), after ``prefit``; default 3 for N > 3
                 without ``prefit``, else none; 0 or None: never
    states       initial states: ``"linear"`` (the report's profile from the measured
                 displacement) or ``"simulated"`` (forward simulation with the initial H, K);
                 default ``"simulated"`` when ``prefit`` or ``coarse`` is used, else ``"linear"``

    The initial H, K are checked (ValueError unless finite and > 0) and refined by ``prefit``
    and ``coarse`` through ``settings.prefit``; ``settings.refine()`` is the model on
    :data:`REFINE_FACTOR` times the elements (the diagnosis's check for a discretisation error,
    :mod:`shootlab.diagnosis.numerics`) and ``settings.resolution`` says "N elements";
    ``settings.extra["memo"]["prefit"]`` and ``settings.extra["memo"]["coarse"]`` summarise those
    stages of the last estimate, ``settings.extra["prefits_output_error"]`` says whether ``prefit``
    fits H, K by output error.  The states are named by node number
    (``s2 … s{N+1}``), so a warm start (``estimate(..., start=)``) is meaningful only between
    models with the same number of elements; across meshes use ``coarse``.
    """
    if isinstance(elements, bool) or not (isinstance(elements, (int, np.integer))
                                          or (isinstance(elements, float) and elements.is_integer())):
        raise ValueError(f"elements must be an integer, got {elements!r}")
    if int(elements) < 1:
        raise ValueError(f"elements must be at least 1 (N ≥ 1), got {elements}")
    cc = ConfinedCompression(int(elements), length=length, solid=solid, permeability=permeability)
    N = cc.N
    prior = check_parameters(dict(H=H, K=K))
    if prefit not in (None, True, False):          # 0 and 1 compare equal to False and True
        raise ValueError(f"prefit must be true or false, got {prefit!r}")
    prefit = N > 3 if prefit is None else bool(prefit)
    if coarse == -1:
        coarse = 3 if N > 3 and not prefit else None
    if coarse is not None and coarse != 0:
        if isinstance(coarse, bool) or int(coarse) != coarse or not 1 <= int(coarse) < N:
            raise ValueError(f"coarse must be a number of elements between 1 and {N - 1}, got {coarse!r}")
        coarse = int(coarse)
    else:
        coarse = None
    states = states or ("simulated" if coarse or prefit else "linear")
    if states not in ("linear", "simulated"):
        raise ValueError(f"states must be 'linear' or 'simulated', got {states!r}")
    memo: dict = {}            # the initial values of the current estimate (for "simulated")

    def initial_parameters(data: Measurements, params: dict, t: Tensor, log=None) -> dict:
        params = check_parameters(params)
        a, b = float(t[0]), float(t[-1])
        _check_covers(data, "load", a, b)
        memo.pop("coarse", None)
        memo.pop("prefit", None)
        if prefit:
            t0 = time.perf_counter()
            if log is not None:
                log(f"prefit: output-error fit of H, K from H = {params['H']:.6g}, K = {params['K']:.6g}")
            fit = output_error_fit(this, data, params, log=log)
            memo["prefit"] = dict(start=dict(params), parameters=fit, seconds=time.perf_counter() - t0)
            params.update(fit)
        if coarse:
            from shootlab.estimation import estimate
            res = estimate(model(elements=coarse, length=length, solid=solid, permeability=permeability),
                           data, initial=dict(H=params["H"], K=params["K"]), interval=(a, b),
                           verbose=log is not None)
            memo["coarse"] = dict(elements=coarse, success=res.success, message=res.message,
                                  parameters=dict(res.parameters), iterations=res.iterations,
                                  jacobian_evaluations=res.shooting.jacobian_evaluations,
                                  seconds=res.seconds, points=res.points)
            if res.success and all(math.isfinite(v) and v > 0 for v in res.parameters.values()):
                params.update(res.parameters)
            else:
                warnings.warn(f"the {coarse}-element estimate for the initial values failed "
                              f"({res.message}); starting from H = {params['H']:g}, K = {params['K']:g}")
        memo["params"] = dict(params)
        return params

    def initial_states(data: Measurements, t: Tensor) -> Tensor:
        p = memo.get("params", prior)
        if states == "simulated" and t.numel() > 1:
            return simulated_profile(cc, data, t, p["H"], p["K"])
        return initial_profile(cc, data, t)

    base = dict(points=SETTINGS_N3["points"], solve=dict(continuation=[dict(c) for c in CONTINUATION]))
    if N > 3:
        base = dict(points=FINE["points"] if N <= 10 else 201, solve=dict(FINE["solve"]))
    if integrator is not None:
        solve = dict(integrator=integrator, max_growth=None)
        if steps is not None:
            solve["steps"] = int(steps)
        base["solve"] = solve
    elif steps is not None:
        raise ValueError("steps needs an integrator (the default is a schedule)")
    if points is not None:
        if isinstance(points, bool) or int(points) != points or int(points) < 2:
            raise ValueError(f"points must be an integer ≥ 2, got {points!r}")
        base["points"] = int(points)

    def refine() -> IdentificationModel | None:
        """The same experiment on twice the elements, each with its own default settings and prefit
        (the diagnosis's numerical check, :mod:`shootlab.diagnosis.numerics`); None when the
        weights were given (they are sized for N elements)."""
        if W is not None or V is not None or W_a is not None:
            return None
        return model(elements=REFINE_FACTOR * N, length=length, H=prior["H"], K=prior["K"], solid=solid,
                     permeability=permeability)

    def free_run(m: IdentificationModel, data: Measurements, params: Mapping[str, float], s0=None) -> dict:
        """The measured channels of the free run with H, K from the unloaded sample (``s0`` None or
        zero): exact for the linear laws (:func:`mixtures.prefit.linear_outputs`; the output-error
        estimate's simulator)."""
        if s0 is not None and np.any(np.asarray(s0) != 0):
            raise ValueError("the confined model's free run starts from the unloaded sample (initial state 0)")
        load = data.channels["load"]
        ok = np.isfinite(load)
        return linear_outputs(data.t, np.interp(data.t, data.t[ok], load[ok]), params["H"], params["K"], N, length)

    nodes, elements_ = range(2, N + 2), range(1, N + 1)

    def domain_K(x):
        # outside the physical domain (an iterate with H ≤ 0 or K ≤ 0) the rows are made
        # non-finite through K: the integrator reports it and the line search steps back
        # instead of wandering off (masked_fill, not torch.where: the first forward-mode
        # torch.where of a process costs 2.5 s)
        return x.K.masked_fill((x.H <= 0) | (x.K <= 0), math.nan)

    def assembled_F(x: Tensor, t: Tensor) -> Tensor:
        """The rows' F from the assembled matrices (:meth:`ConfinedCompression.matrices`), the
        domain guard as in the rows: fewer torch operations than probing the rows (at N = 3 the
        estimate took 1.5x as long with the probed F)."""
        s, Hp, Kp = x[..., :N], x[..., N], x[..., N + 1]
        Kp = Kp.masked_fill((Hp <= 0) | (Kp <= 0), math.nan)
        R, Km, _, _, Hu = cc.matrices(s, Hp, Kp)
        batch, nz = Km.shape[:-2], 2 * N + 1
        mass = torch.cat([R, Km, Km.new_zeros(*batch, N, 1)], -1)
        mom = torch.cat([Km.new_zeros(*batch, N, N), -R.transpose(-1, -2), -Hu.unsqueeze(-1)], -1)
        e = torch.eye(nz, dtype=Km.dtype, device=Km.device)
        rows = torch.stack([e[-1], torch.zeros_like(e[0]), e[N]], 0).expand(*batch, 3, nz)
        return torch.cat([mass, mom, rows], -2)

    this = shootlab.model(
        name="confined" if N == 3 else f"confined[N={N}]",
        states={"s": "v"}, inputs=["v", "p", "u"], parameters=dict(prior),
        blocks={"s": nodes, "v": nodes, "p": elements_, "mass": elements_, "momentum": nodes},
        equations={"mass": lambda x: cc.mass_balance(x.s, domain_K(x), x.v, x.p),        # eq. 5.2
                   "momentum": lambda x: cc.momentum_balance(x.s, x.H, x.p, x.u),           # eq. 5.3
                   "load": lambda x: x.u,
                   "displacement": lambda x: -x.s[..., -1],      # compression of the sample
                   "pressure": lambda x: x.p[..., 0]},           # pore pressure at the bottom
        channels=["load", "displacement", "pressure"], given=["load"],
        W=torch.ones(N + 2, dtype=torch.float64) if W is None else W,
        V=torch.ones(2 * N + 3, dtype=torch.float64) if V is None else V, W_a=W_a,
        bounds=dict(H=(0.0, math.inf), K=(0.0, math.inf)), initial_states=initial_states, F=assembled_F,
        settings=EstimationSettings(points=base["points"], solver=base["solve"], prefit=initial_parameters,
                                    refine=refine, resolution=f"{N} element{'s' if N != 1 else ''}",
                                    simulate=free_run if cc.is_linear else None,
                                    extra=dict(memo=memo, prefits_output_error=prefit)))
    # the report's experiment is dimensionless (time on [0, 1], load, displacement, pressure,
    # H and K scaled): every quantity is declared "-"
    this.units = {name: "-" for name in ["t", *this.names, *this.inputs, *this.equations, *this.measured]}
    return this


def estimate_two_grid(m: IdentificationModel, data, points: int = 51, integrator: str = "midpoint",
                      steps: int = 2, initial: Mapping[str, float] | None = None, **options):
    """The stiff path on few shooting points: the loose explicit-Euler stage (:data:`LOOSE`) on
    401 points, then ``integrator`` × ``steps`` on ``points`` points, warm-started from it
    (states, parameters and costates re-integrated onto the coarse grid).  Returns the final
    :class:`~shootlab.estimation.EstimationResult` with the first one as ``.loose``; its
    ``seconds`` and iteration counts are those of the second stage only."""
    from shootlab.estimation import estimate

    loose = estimate(m, data, n_points=LOOSE["points"], initial=initial, **LOOSE["solve"])
    if not loose.success:
        loose.loose = None
        return loose
    res = estimate(m, data, n_points=points, start=loose, integrator=integrator, steps=steps,
                   continuation=None, max_growth=None, **options)
    res.loose = loose
    return res
