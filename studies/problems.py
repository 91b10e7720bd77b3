"""Named problems for the studies: a TPBVP, its interval, a guess builder and checkable quantities.

    prob = studies.problems.build("confined", {"elements": 3})
    t = prob.grid(401); x0 = prob.guess(t); shootlab.solve(prob.bvp, t, x0, ...)

Built-in names (options in brackets, defaults first; registered as entry points
``shootlab.problems``, where other packages add theirs):

``msd``        mass–spring–damper (report §3.4) from noise-free data, 1001 samples on [0, 10]
               [``W_states`` 1e10: weight of the s, v state equations — the stiffness knob,
               κ ≈ −(1/W_states)^{1/2} for W_states ≤ 1e-2; ``start`` 10: initial m = b = k]
``flexible``   flexible rotation manipulator (report ch. 4), plain model on the virtual rig
               [``rig`` "ideal" (linear two-mass rig, no friction or sensor effects: the plain
               model is exact) or "full" (``RigSettings()``); ``W`` 1.0; ``V_s`` 1e6: weight of
               the encoder rows — κ ≈ −(V_s/W)^{1/2}; ``V_u`` 1; ``friction`` False: the
               extended model instead]
``confined``   confined compression with N elements (report ch. 5) from noise-free data
               [``elements`` 3; ``H0``, ``K0`` 4, 4: the initial parameters (the report's);
               ``coarse`` −1: the model's default, for N > 3 the start is refined by a 3-element
               estimate on the same data (and the states simulated with it), 0: no refinement;
               ``prefit`` False: True starts from the output-error fit instead (the model's
               own default for N > 3; the stored sweeps used the 3-element start);
               κ grows with N and with H·K: ±4896 for N = 3 at 4, 4]
``module:object`` or ``path/file.py:object``: a :class:`StudyProblem`, a callable returning one
               (called with the options), a tuple ``(bvp, (a, b), guess)`` with ``guess(t)``,
               or an :class:`~shootlab.estimation.IdentificationModel` (option ``data``: CSV path)

Quantities and reference.  A sweep calls a converged run a success only if its quantities
(the estimated parameters; for a plain BVP x(a) and x(b)) agree with the reference within the
sweep's ``accuracy``: a converged solution of an *unstable* discretisation is spurious.  The
reference is known for the built-in simulated, noise-free data (the data-generating parameters
solve the TPBVP exactly, with λ = 0); otherwise the sweep computes it with ``reference_solve``.
"""
from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
import torch
from torch import Tensor

import shootlab
from shootlab.estimation.data import Measurements
from shootlab.estimation.optimality import EstimationProblem
from shootlab.estimation import IdentificationModel
from shootlab.estimation.fit import initial_approximation
from shootlab import registry
from shootlab.estimation.lookup import load_object

f64 = torch.float64


@dataclass
class StudyProblem:
    """What a study needs of a problem (module docstring)."""

    name: str
    bvp: shootlab.BVP
    interval: tuple[float, float]
    guess: Callable[[Tensor], Tensor]                      # t (m,) -> x0 (m, n)
    quantities: Callable[[Tensor, Tensor], dict] | None = None   # (t, x) -> {name: float}
    reference: dict | None = None                          # known values of the quantities
    reference_solve: dict = field(default_factory=lambda: dict(points=101))   # solve() settings
    options: dict = field(default_factory=dict)
    description: str = ""
    estimation: EstimationProblem | None = None
    time_unit: str = ""                                    # for axis labels ("s"; "" = dimensionless)

    def grid(self, m: int) -> Tensor:
        if int(m) < 2:
            raise ValueError(f"need at least 2 shooting points, got {m}")
        return torch.linspace(self.interval[0], self.interval[1], int(m), dtype=f64)

    def measure(self, t: Tensor, x: Tensor) -> dict:
        """The quantities checked against the reference."""
        if self.quantities is not None:
            return {k: float(v) for k, v in self.quantities(t, x).items()}
        return {**{f"x{j}(a)": float(v) for j, v in enumerate(x[0])},
                **{f"x{j}(b)": float(v) for j, v in enumerate(x[-1])}}

    @property
    def n(self) -> int:
        return int(self.guess(self.grid(2)).shape[1])


def parameter_means(model: IdentificationModel):
    """Quantities of an estimation problem: the parameters, averaged over [a, b] (trapezoid)."""
    ns = len(model.states)

    def q(t: Tensor, x: Tensor) -> dict:
        theta = x[:, ns:model.nx]
        span = float(t[-1] - t[0])
        return {p: float(torch.trapezoid(theta[:, j], t)) / span for j, p in enumerate(model.parameters)}
    return q


def relative_error(q: Mapping[str, float], ref: Mapping[str, float]) -> float:
    """max over the quantities of |q − ref| / |ref| (with a floor 1e-6·max|ref|); inf if any is
    missing or not finite."""
    if not ref:
        return float("nan")
    scale = max(abs(v) for v in ref.values())
    floor = 1e-6 * scale + 1e-300
    err = 0.0
    for k, r in ref.items():
        v = q.get(k)
        if v is None or not np.isfinite(v):
            return float("inf")
        err = max(err, abs(v - r) / max(abs(r), floor))
    return err


def _estimation(name: str, model: IdentificationModel, data, initial: dict, truth: dict | None,
                options: dict, description: str, time_unit: str = "") -> StudyProblem:
    data = Measurements.coerce(data)
    prob = EstimationProblem(model, data)
    a, b = float(data.t[0]), float(data.t[-1])

    def guess(t: Tensor) -> Tensor:
        return initial_approximation(model, data, t, initial)
    return StudyProblem(name=name, bvp=prob.bvp(), interval=(a, b), guess=guess,
                        quantities=parameter_means(model), reference=truth,
                        reference_solve=dict(points=model.settings.points,
                                             **model.settings.solver),
                        options=dict(options), description=description, estimation=prob, time_unit=time_unit)


def _label(base: str, options: Mapping) -> str:
    return base if not options else base + "[" + ",".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                                                            for k, v in sorted(options.items())) + "]"


# -- built-in problems ---------------------------------------------------------------------
def msd(W_states: float = 1e10, start: float = 10.0, **rest) -> StudyProblem:
    from manipulators import msd as msd_mod
    from manipulators.rig import msd_data
    _no_more(rest, "msd")
    d = msd_data()
    data = {k: d[k] for k in ("t", "u", "s")}
    model = msd_mod.model(W=[float(W_states)] * 2 + [1.0] * 3)
    opts = dict(W_states=float(W_states), start=float(start))
    return _estimation(_label("msd", _nondefault(opts, msd)), model, data,
                       dict(m=float(start), b=float(start), k=float(start)),
                       dict(m=1.0, b=1.0, k=1.0), opts,
                       f"mass-spring-damper, noise-free data, W = [{W_states:g}]*2 + [1]*3, start {start:g}", "s")


def flexible(rig: str = "ideal", W: float = 1.0, V_s: float = 1e6, V_u: float = 1.0,
             friction: bool = False, **rest) -> StudyProblem:
    from manipulators import flexible as flex
    from manipulators.rig import RigSettings
    _no_more(rest, "flexible")
    if rig not in ("ideal", "full", "friction_only"):
        raise ValueError(f"flexible: rig must be 'ideal', 'full' or 'friction_only', got {rig!r}")
    settings = dict(ideal=RigSettings.ideal, full=RigSettings, friction_only=RigSettings.friction_only)[rig]()
    data = _rig_data(rig)
    V = (1.0, 1.0, float(V_u), float(V_s), float(V_s))
    model = (flex.friction_model(W=float(W), V=V) if friction else flex.plain_model(W=float(W), V=V))
    exact = rig == "ideal" and not friction or rig == "friction_only" and friction
    truth = {p: float(getattr(settings, p)) for p in model.parameters} if exact else None
    opts = dict(rig=rig, W=float(W), V_s=float(V_s), V_u=float(V_u), friction=bool(friction))
    return _estimation(_label("flexible", _nondefault(opts, flexible)), model, data, {}, truth, opts,
                       f"flexible manipulator ({'extended' if friction else 'plain'} model), rig {rig}, "
                       f"W = {W:g}, V = {list(V)}, start from the report's prior", "s")


@functools.lru_cache(maxsize=4)
def _rig_data(rig: str) -> Measurements:
    from manipulators.rig import RigSettings, simulate_rig
    settings = dict(ideal=RigSettings.ideal, full=RigSettings, friction_only=RigSettings.friction_only)[rig]()
    return Measurements.coerce(simulate_rig(settings, input="sweep").measured())


def confined(elements: int = 3, H0: float = 4.0, K0: float = 4.0, coarse: int = -1, prefit: bool = False,
             **rest) -> StudyProblem:
    from mixtures import identification as mid
    _no_more(rest, "confined")
    N = int(elements)
    model = mid.model(elements=N, coarse=int(coarse), prefit=prefit)
    data = mid.as_data(_confined_data(N))
    opts = dict(elements=N, H0=float(H0), K0=float(K0), coarse=int(coarse), prefit=bool(prefit))
    return _estimation(_label("confined", _nondefault(opts, confined)), model, data,
                       dict(H=float(H0), K=float(K0)), dict(H=2.0, K=1.0), opts,
                       f"confined compression, {N} elements, noise-free data (H = 2, K = 1), "
                       f"start H = {H0:g}, K = {K0:g}"
                       + (" refined by an output-error fit" if prefit else "")
                       + (f" refined by a {3 if coarse == -1 else coarse}-element estimate"
                          if (coarse == -1 and N > 3 and not prefit) or coarse > 0 else ""))


@functools.lru_cache(maxsize=8)
def _confined_data(N: int):
    from mixtures.simulation import simulated_measurements
    return simulated_measurements(elements=N)


def _no_more(rest: dict, name: str) -> None:
    if rest:
        raise ValueError(f"problem {name!r} has no option(s) {sorted(rest)}")


def _nondefault(opts: dict, fn) -> dict:
    import inspect
    sig = inspect.signature(fn).parameters
    return {k: v for k, v in opts.items() if k in sig and sig[k].default != v}


# -- user problems ---------------------------------------------------------------------------
def _load(spec: str):
    """The object named by ``module:object`` / ``file.py:object`` (:func:`shootlab.estimation.lookup.load_object`)."""
    target, sep, attr = spec.rpartition(":")
    if not sep or not target or not attr:
        raise ValueError(f"unknown problem {spec!r}: installed problems are {', '.join(registry.names('problems'))}; "
                         f"or give 'module:object' / 'file.py:object'")
    return load_object(spec)


def _from_object(spec: str, obj, options: dict) -> StudyProblem:
    opts = dict(options)
    if isinstance(obj, IdentificationModel) or (callable(obj) and not isinstance(obj, (StudyProblem, shootlab.BVP))
                                                 and "data" in opts):
        data = opts.pop("data", None)
        if data is None:
            raise ValueError(f"problem {spec!r} is an IdentificationModel: give its data with --option data=FILE.csv")
        model = obj if isinstance(obj, IdentificationModel) else obj(**opts)
        if not isinstance(model, IdentificationModel):
            raise ValueError(f"problem {spec!r} with data= must give an IdentificationModel")
        return _estimation(_label(spec, options), model, data, {}, None, options, f"user model {spec}")
    if callable(obj) and not isinstance(obj, (StudyProblem, shootlab.BVP)):
        obj = obj(**opts)
    elif opts:
        raise ValueError(f"problem {spec!r} is not callable: it takes no options {sorted(opts)}")
    if isinstance(obj, StudyProblem):
        obj.options = dict(options, **obj.options)
        return obj
    if isinstance(obj, (tuple, list)) and len(obj) == 3 and isinstance(obj[0], shootlab.BVP):
        bvp, interval, guess = obj
        return StudyProblem(name=_label(spec, options), bvp=bvp, interval=(float(interval[0]), float(interval[1])),
                            guess=guess, options=dict(options), description=f"user problem {spec}")
    raise ValueError(f"problem {spec!r} gave {type(obj).__name__}: expected a StudyProblem, "
                     f"(BVP, (a, b), guess) or an IdentificationModel")


def build(spec: str, options: Mapping | None = None) -> StudyProblem:
    """A problem from an installed name (entry points ``shootlab.problems``) or ``module:object``
    (module docstring) and its options."""
    options = dict(options or {})
    if registry.find("problems", spec):
        return registry.load("problems", spec)(**options)
    return _from_object(spec, _load(spec), options)


@functools.lru_cache(maxsize=16)
def _cached(spec: str, options_json: str) -> StudyProblem:
    return build(spec, json.loads(options_json))


def cached(spec: str, options: Mapping | None = None) -> StudyProblem:
    """:func:`build`, memoised per process (the sweep's workers build each problem once)."""
    return _cached(spec, json.dumps(dict(options or {}), sort_keys=True))
