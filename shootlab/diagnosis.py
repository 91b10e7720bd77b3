"""Sim-to-real gap diagnosis (DESIGN §4): where the residual is, which effect explains it, and how far
adding that effect shrinks the misfit.  Generic over any :class:`~shootlab.estimation.IdentificationModel`.

1. **Where** (:func:`locate`).  The nominal estimate leaves residuals ξ on every row (model equations
   and measurement rows) and ε on the dynamics.  Per row: the weighted energy ½∫ξᵀVξ dt and its
   share of J, compared with a *noise floor*: the same model estimated, the same way, on a
   surrogate record — the nominal model's own free-run response to the same given inputs, plus
   Gaussian noise at the level estimated from the data (:func:`noise_level`).  The surrogate is
   well specified by construction, so its residuals are what noise alone leaves through this
   model, these weights and this estimator (smoother residuals are coloured, so a whiteness test
   alone cannot tell).  A row is significant when the mean-square ratio data/floor is large by an
   F test (degrees of freedom = the effective sample size from the floor's autocorrelation) and
   in size (``ratio_min``, ``share_min``).  Windows: where the standardised local energy exceeds
   the floor's own extremes.
2. **Which** (:func:`rank`).  A candidate :class:`Effect` adds a term to some rows of the model
   (``f + term``); its *signature* is that term evaluated on the estimated states, inputs and
   data.  Every candidate (and every pair of compatible candidates) is fitted to the residual —
   rows standardised by the floor, the nominal parameters' sensitivities ∂(f + Fζ)/∂θ as free
   nuisance columns (what re-estimating them could absorb), the effect's parameters by bounded
   non-linear least squares from a few starts — and scored by a Bayesian information criterion
   on the effective sample size.  Confidence = posterior inclusion probability (BIC weights over
   {no effect, singles, pairs}).  Nothing is selected when the residual is not significant, or
   when the best model explains less than ``explained_min`` of the residual's excess over the
   floor ("no candidate explains the residual").
3. **How far it shrinks** (:func:`shrink`).  The model extended with the selected effects
   (:func:`extend`) is re-estimated warm-started from the nominal estimate (states, parameters and
   costates by name; new parameters from the fit), and the weighted residual J, the per-row
   residual energies and — on validation data with another input — the free-run simulation error
   of the measured channels are reported before and after, with ``shrink = 1 − after/before``.

:func:`diagnose` runs all three; :func:`write_report` writes ``diagnosis.json``, the figures and
``report.md``.  Candidate libraries: :mod:`manipulators.effects`, :mod:`mixtures.effects`, or the
user's own (``docs/diagnosis.md``).
"""
from __future__ import annotations

import inspect
import itertools
import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .data import Interpolant, Measurements
from .estimation import EstimationResult, IdentificationModel, continue_in_weights, estimate, simulate

__all__ = ["Effect", "Library", "Vars", "extend", "noise_level", "surrogate_data", "locate", "rank",
           "shrink", "diagnose", "Diagnosis", "write_report", "generic_library", "library_for",
           "default_estimator", "weight_continuation_estimator", "resolve_library", "free_run_error"]


# =============================================================================== effects
class Vars:
    """What an effect's ``term`` sees: ``v["name"]`` is a state, a parameter (the model's or the
    effect's new ones) or an input ζ (states and parameters first; :meth:`input` for an input whose
    name is also a state's), ``v.t`` the time, ``v.channel(name, at=None)`` a measured channel of
    the bound data at ``v.t`` (or at the times ``at``, differentiably in ``at``).  Every value is a
    tensor of the batch shape of ``v.t``."""

    def __init__(self, values: Mapping[str, Tensor], inputs: Mapping[str, Tensor], t: Tensor,
                 channel: Callable[[str, Tensor], Tensor] | None = None):
        self._values, self._inputs, self.t, self._channel = values, inputs, t, channel

    def __getitem__(self, name: str) -> Tensor:
        if name in self._values:
            return self._values[name]
        if name in self._inputs:
            return self._inputs[name]
        raise KeyError(f"no state, parameter or input named {name!r} (have {sorted(self._values)} "
                       f"and inputs {sorted(self._inputs)})")

    def __contains__(self, name: str) -> bool:
        return name in self._values or name in self._inputs

    def input(self, name: str) -> Tensor:
        return self._inputs[name]

    def channel(self, name: str, at: Tensor | None = None) -> Tensor:
        if self._channel is None:
            raise KeyError(f"channel {name!r}: no data bound to this model (extend(..., data=...))")
        return self._channel(name, self.t if at is None else at)

    def zeros(self) -> Tensor:
        return torch.zeros_like(self.t)


@dataclass
class Effect:
    """A candidate unmodelled effect.

    name        stable identifier (``coulomb_m2``)
    equations   the rows of the model it enters
    parameters  its new parameters → initial value (also the value its signature is drawn with)
    term        ``term(v) -> {row: tensor}``: what it adds to the model side ``f + Fζ`` of those rows,
                written with torch on ``v`` (:class:`Vars`); it must be C¹ in the states and
                parameters and affine in the inputs ζ (checked)
    description one line for reports
    bounds      parameter → (low, high) for the fit (default unbounded)
    scale       parameter → typical size (fit scaling; default |initial| or 1)
    starts      parameter → extra starting values for the fit, or ``starts(v) -> dict`` computed
                from the estimated variables (e.g. from the command's range)
    channels    measured channels the term reads through ``v.channel`` (bound at :func:`extend`)
    group       effects of the same group are alternatives and are not combined in pairs
    variable    optional ``(label, fn(v) -> tensor)``: the x-axis of the signature figure
    nests       names of simpler effects this one contains as a special case (Stribeck friction
                contains Coulomb friction): the richer one is kept only when a likelihood-ratio
                test on the converged re-estimates says its extra parameters are needed
    """

    name: str
    equations: Sequence[str]
    parameters: Mapping[str, float]
    term: Callable[[Vars], Mapping[str, Tensor]]
    description: str = ""
    bounds: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    scale: Mapping[str, float] = field(default_factory=dict)
    starts: Mapping[str, Sequence[float]] | Callable[[Vars], Mapping[str, Sequence[float]]] = field(default_factory=dict)
    channels: Sequence[str] = ()
    group: str | None = None
    variable: tuple[str, Callable[[Vars], Tensor]] | None = None
    nests: Sequence[str] = ()

    def __post_init__(self):
        if not self.name or not isinstance(self.name, str):
            raise ValueError("an effect needs a name")
        self.equations = list(self.equations)
        self.parameters = {str(k): float(v) for k, v in self.parameters.items()}
        if not self.parameters:
            raise ValueError(f"effect {self.name!r} has no parameters")
        if not callable(self.term):
            raise ValueError(f"effect {self.name!r}: term must be callable")
        bad = set(self.bounds) - set(self.parameters)
        if bad:
            raise ValueError(f"effect {self.name!r}: bounds for unknown parameters {sorted(bad)}")

    def applies_to(self, model: IdentificationModel) -> str | None:
        """None if the effect fits the model, else why not."""
        missing = [r for r in self.equations if r not in model.equations]
        if missing:
            return f"rows {missing} not in the model"
        clash = [p for p in self.parameters if p in model.names or p in model.inputs]
        if clash:
            return f"parameter names {clash} already used by the model"
        try:
            _probe(model, [self])
        except KeyError as exc:
            return f"needs {exc.args[0] if exc.args else exc}"
        return None


@dataclass
class Library:
    """Candidate effects for a family of models, and how that family is estimated.

    estimator       ``estimator(model, data, initial=None, start=None) -> EstimationResult``:
                    the nominal estimation strategy (default: :func:`default_estimator`); also
                    used for the noise-floor surrogate and, with ``start``, for the extended model
    initial_state   free-run start on validation data: ``"rest"`` (measured states from the first
                    samples, others zero), ``"data"`` (the model's initial approximation) or
                    ``fn(model, data) -> sequence``
    """

    name: str
    effects: list[Effect]
    estimator: Callable[..., EstimationResult] | None = None
    initial_state: str | Callable = "rest"
    description: str = ""

    def __post_init__(self):
        names = [e.name for e in self.effects]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"library {self.name!r}: duplicate effect names {dup}")

    def __getitem__(self, name: str) -> Effect:
        for e in self.effects:
            if e.name == name:
                return e
        raise KeyError(f"library {self.name!r} has no effect {name!r}; it has {self.names}")

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.effects]

    def add(self, effect: Effect) -> "Library":
        """A copy with ``effect`` added (or replacing the one of the same name)."""
        return replace(self, effects=[e for e in self.effects if e.name != effect.name] + [effect])

    def applicable(self, model: IdentificationModel) -> tuple[list[Effect], dict[str, str]]:
        ok, skipped = [], {}
        for e in self.effects:
            why = e.applies_to(model)
            if why is None:
                ok.append(e)
            else:
                skipped[e.name] = why
        return ok, skipped


# =============================================================================== extension
def _new_parameters(model: IdentificationModel, effects: Sequence[Effect]) -> list[str]:
    names: list[str] = []
    for e in effects:
        for p in e.parameters:
            if p in model.names or p in model.inputs or p in names:
                raise ValueError(f"effect {e.name!r}: parameter name {p!r} is already used")
            names.append(p)
    return names


def _rows_sum(model: IdentificationModel, effects: Sequence[Effect], v: Vars, shape) -> Tensor:
    index = {r: i for i, r in enumerate(model.equations)}
    parts: list[Any] = [None] * len(model.equations)
    for e in effects:
        out = e.term(v)
        for row, val in out.items():
            if row not in index:
                raise ValueError(f"effect {e.name!r} adds a term to {row!r}, which is not a row of the model "
                                 f"{model.equations}")
            val = torch.broadcast_to(torch.as_tensor(val, dtype=v.t.dtype), shape)
            parts[index[row]] = val if parts[index[row]] is None else parts[index[row]] + val
    zero = torch.zeros(shape, dtype=v.t.dtype)
    return torch.stack([p if p is not None else zero for p in parts], -1)


def _vars(model: IdentificationModel, names: Sequence[str], x: Tensor, zeta: Tensor, t: Tensor,
          channel=None) -> Vars:
    values = {n: x[..., i] for i, n in enumerate(names)}
    inputs = {n: zeta[..., j] for j, n in enumerate(model.inputs)}
    return Vars(values, inputs, t, channel)


def _channel_fn(data: Measurements | None, names: Sequence[str]):
    if data is None or not names:
        return None
    missing = [c for c in names if c not in data.channels]
    if missing:
        raise ValueError(f"the effects read channel(s) {missing} that the data lack (have {sorted(data.channels)})")
    ip = Interpolant(data, list(names))
    col = {n: i for i, n in enumerate(names)}

    def channel(name: str, at: Tensor) -> Tensor:
        if name not in col:
            raise KeyError(f"channel {name!r} (declare it in Effect.channels)")
        return ip.values(at)[..., col[name]]
    return channel


def _probe(model: IdentificationModel, effects: Sequence[Effect]) -> tuple[bool, bool]:
    """Evaluate the terms on random states: (depends on ζ, affine in ζ).  KeyError for unknown names."""
    gen = torch.Generator().manual_seed(12345)
    names = model.names + _new_parameters(model, effects)
    n = 4
    base = [float(model.prior.get(p, 1.0)) for p in model.parameters]
    # the effects' parameters away from their initial values (a term often vanishes there, e.g. an
    # amplitude 0, which would hide its dependence on ζ)
    base += [float(v) + (0.3 + 0.4 * float(torch.rand((), generator=gen))) * float(e.scale.get(p, abs(v) or 1.0) or 1.0)
             for e in effects for p, v in e.parameters.items()]
    x = torch.cat([0.1 * torch.randn(n, len(model.states), generator=gen, dtype=torch.float64),
                   torch.tensor(base, dtype=torch.float64).expand(n, -1)], -1)
    t = torch.linspace(0.1, 0.2, n, dtype=torch.float64)
    chans = sorted({c for e in effects for c in e.channels})

    def channel(name, at):
        if name not in chans:
            raise KeyError(f"channel {name!r} (declare it in Effect.channels)")
        return torch.sin(at + len(name))
    nz = len(model.inputs)
    z1 = torch.randn(n, nz, generator=gen, dtype=torch.float64)
    outs = []
    with torch.no_grad():
        for z in (torch.zeros_like(z1), z1, 2 * z1):
            outs.append(_rows_sum(model, effects, _vars(model, names, x, z, t, channel), t.shape))
    d1, d2 = outs[1] - outs[0], outs[2] - outs[0]
    scale = 1e-9 * (1.0 + float(outs[0].abs().max()) + float(d1.abs().max()))
    depends = bool(d1.abs().max() > scale)
    affine = bool((d2 - 2 * d1).abs().max() <= 1e-7 * (1.0 + float(d2.abs().max())))
    return depends, affine


def _extend_weight(w, n_old: int, n_new: int, fill: float):
    if n_new == 0:
        return w
    if callable(w):
        def wf(t, _w=w):
            base = torch.as_tensor(_w(t), dtype=torch.float64)
            if base.ndim >= 1 and base.shape[-1] == n_old and (base.ndim == t.ndim + 1 or base.ndim == 1):
                return torch.cat([base, torch.full((*base.shape[:-1], n_new), fill, dtype=base.dtype)], -1)
            out = torch.zeros(*base.shape[:-2], n_old + n_new, n_old + n_new, dtype=base.dtype)
            out[..., :n_old, :n_old] = base
            out[..., range(n_old, n_old + n_new), range(n_old, n_old + n_new)] = fill
            return out
        return wf
    w = torch.as_tensor(np.asarray(w, dtype=np.float64) if not isinstance(w, Tensor) else w, dtype=torch.float64)
    if w.ndim == 1:
        return torch.cat([w, torch.full((n_new,), fill, dtype=torch.float64)])
    out = torch.zeros(n_old + n_new, n_old + n_new, dtype=torch.float64)
    out[:n_old, :n_old] = w
    out[range(n_old, n_old + n_new), range(n_old, n_old + n_new)] = fill
    return out


def _parameter_weight(model: IdentificationModel) -> float:
    """The weight W of a new parameter: the median of the model's W on its parameters."""
    w = model.W
    try:
        if callable(w):
            w = w(torch.zeros((), dtype=torch.float64))
        w = torch.as_tensor(np.asarray(w, dtype=np.float64) if not isinstance(w, Tensor) else w)
        d = w if w.ndim == 1 else torch.diagonal(w, dim1=-2, dim2=-1)
        d = d.reshape(-1, model.nx)[0]
        vals = d[len(model.states):]
        return float(vals.median()) if vals.numel() else float(d.median())
    except Exception:  # noqa: BLE001 - a weight we cannot read: a neutral value
        return 1.0


def extend(model: IdentificationModel, effects: Sequence[Effect], data=None,
           initial: Mapping[str, float] | None = None, name: str | None = None) -> IdentificationModel:
    """The model with the effects' terms added: ``f + Σ term`` and ``F + ∂term/∂ζ``, the effects'
    parameters appended to x (θ' = ε_θ like the others; weight W = the median of the model's W on
    its parameters, no prior: W_a = 0), their initial values from ``initial`` or the effects.
    ``data`` binds the channels the effects read (needed for estimation and simulation on that
    record: bind again for another record)."""
    effects = list(effects)
    if not effects:
        return model
    new = _new_parameters(model, effects)
    for e in effects:
        missing = [r for r in e.equations if r not in model.equations]
        if missing:
            raise ValueError(f"effect {e.name!r} enters rows {missing} that model {model.name!r} lacks")
    depends, affine = _probe(model, effects)
    if not affine:
        raise ValueError(f"the terms of {[e.name for e in effects]} are not affine in the inputs ζ "
                         f"{model.inputs}; write them with the measured channels (v.channel) instead")
    data = Measurements.coerce(data) if data is not None else None
    chans = sorted({c for e in effects for c in e.channels})
    channel = _channel_fn(data, chans)
    if chans and channel is None:
        def channel(nm, at):        # unbound: a clear error on use, not at construction
            raise ValueError(f"effects {[e.name for e in effects if e.channels]} read channel(s) {chans}: "
                             f"bind data with extend(..., data=...)")
    nx0, n_new, nz = model.nx, len(new), len(model.inputs)
    names = model.names + new
    init = {p: float(v) for e in effects for p, v in e.parameters.items()}
    init.update({k: float(v) for k, v in (initial or {}).items() if k in init})

    def added(x: Tensor, t: Tensor) -> tuple[Tensor, Tensor | None]:
        t = torch.broadcast_to(t, x.shape[:-1])
        if not depends:
            z = x.new_zeros(*x.shape[:-1], nz)
            return _rows_sum(model, effects, _vars(model, names, x, z, t, channel), t.shape), None
        xb = x.unsqueeze(-2).expand(*x.shape[:-1], nz + 1, x.shape[-1])
        tb = t.unsqueeze(-1).expand(*t.shape, nz + 1)
        Z = torch.cat([x.new_zeros(1, nz), torch.eye(nz, dtype=x.dtype, device=x.device)], 0)
        Z = Z.expand(*x.shape[:-1], nz + 1, nz)
        out = _rows_sum(model, effects, _vars(model, names, xb, Z, tb, channel), tb.shape)
        return out[..., 0, :], (out[..., 1:, :] - out[..., :1, :]).transpose(-1, -2)

    def f(x: Tensor, t: Tensor) -> Tensor:
        return model.f(x[..., :nx0], t) + added(x, t)[0]

    def F(x: Tensor, t: Tensor) -> Tensor:
        base = model.F(x[..., :nx0], t)
        if not depends:
            return base
        return base + added(x, t)[1]

    A = torch.zeros(nx0 + n_new, nx0 + n_new, dtype=torch.float64)
    A[:nx0, :nx0] = torch.as_tensor(model.A, dtype=torch.float64)
    B = torch.zeros(nx0 + n_new, nz, dtype=torch.float64)
    B[:nx0] = torch.as_tensor(model.B, dtype=torch.float64)
    q_a = torch.cat([torch.as_tensor(model.q_a, dtype=torch.float64), torch.tensor([init[p] for p in new], dtype=torch.float64)])
    settings = dict(model.settings)
    settings["effects"] = list(model.settings.get("effects", [])) + [e.name for e in effects]
    settings["nominal_model"] = model.settings.get("nominal_model", model.name)
    return replace(model, name=name or f"{model.name}+{'+'.join(e.name for e in effects)}",
                   parameters=list(model.parameters) + new, A=A, B=B, f=f, F=F,
                   W=_extend_weight(model.W, nx0, n_new, _parameter_weight(model)),
                   W_a=_extend_weight(model.W_a, nx0, n_new, 0.0), q_a=q_a,
                   prior=dict(model.prior, **{p: init[p] for p in new}), settings=settings)


# =============================================================================== estimation strategies
def default_estimator(model: IdentificationModel, data, initial=None, start=None, **options) -> EstimationResult:
    """:func:`shootlab.estimation.estimate` with the model's settings."""
    return estimate(model, data, initial=initial, start=start, **options)


def weight_continuation_estimator(factor: float = 100.0, noise_weights: bool = False, reference: float = 1.0,
                                  cap: Mapping[str, float] | None = None):
    """An estimator that reaches the model's measurement weights by continuation (the report's
    remedy, §4.2; :mod:`manipulators.chapter4` does it for the flexible manipulator): the
    measurement rows' diagonal V starts at the level of the model-equation rows and is raised by
    ``factor`` per stage, each stage warm-started from the previous one.  With ``start`` (a warm
    start) it goes straight to the final weights, and falls back to the continuation if that fails.

    ``noise_weights``: cap each non-given measurement row's weight at ``reference / σ̂²`` (σ̂ the
    channel's noise level, :func:`noise_level`): weights that trust the encoders far beyond their
    noise make the smoother chase it and the Newton iteration crawl.  ``cap``: fixed caps per row.
    Only for models whose V is a constant vector."""
    def estimator(model: IdentificationModel, data, initial=None, start=None, **options) -> EstimationResult:
        data = Measurements.coerce(data)
        V = model.V
        if callable(V) or torch.as_tensor(np.asarray(V, dtype=np.float64) if not isinstance(V, Tensor) else V).ndim != 1:
            return estimate(model, data, initial=initial, start=start, **options)
        V = torch.as_tensor(np.asarray(V, dtype=np.float64) if not isinstance(V, Tensor) else V, dtype=torch.float64).clone()
        meas = [i for i, r in enumerate(model.equations) if r in model.channels]
        eqs = [i for i in range(len(model.equations)) if i not in meas]
        if noise_weights:
            sig = noise_level(data, [model.channels[model.equations[i]] for i in meas])
            for i in meas:
                ch = model.channels[model.equations[i]]
                if ch not in model.given and sig[ch] > 0:
                    V[i] = min(float(V[i]), reference / sig[ch] ** 2)
        for row, c in (cap or {}).items():
            if row in model.equations:
                i = model.equations.index(row)
                V[i] = min(float(V[i]), float(c))
        target = replace(model, V=V)
        if start is not None:
            res = estimate(target, data, initial=initial, start=start, **options)
            if res.success:
                return res
        base = float(V[eqs].min()) if eqs else 1.0
        top = float(V[meas].max()) if meas else base
        levels, lv = [], base
        while lv < top:
            levels.append(lv)
            lv *= factor
        stages = []
        for lv in levels:
            Vs = V.clone()
            Vs[meas] = Vs[meas].clamp_max(lv)
            stages.append(replace(model, V=Vs))
        opts = dict(options)
        n_points, interval = opts.pop("n_points", None), opts.pop("interval", None)
        return continue_in_weights(stages + [target], data, n_points, initial, interval, opts)
    return estimator


# =============================================================================== noise floor
def noise_level(data, channels: Sequence[str] | None = None) -> dict[str, float]:
    """Noise standard deviation per channel from the data alone: the spread of the 4th differences
    (robust: median absolute deviation; a smooth signal sampled densely has tiny 4th differences,
    white noise of std σ gives std √70 σ).  At least 1e-6 of the channel's std."""
    data = Measurements.coerce(data)
    out = {}
    for ch in channels if channels is not None else list(data.channels):
        y = data.channels[ch]
        y = y[~np.isnan(y)]
        if y.size < 8:
            out[ch] = 0.0
            continue
        d = np.diff(y, n=4)
        mad = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(70.0)
        rms = float(np.sqrt(np.mean(d * d)) / math.sqrt(70.0))
        s = mad if mad > 0 else rms
        out[ch] = max(s, 1e-6 * float(np.std(y)))
    return out


def _initial_state(model: IdentificationModel, data: Measurements, how) -> list[float] | None:
    if callable(how):
        return [float(v) for v in how(model, data)]
    if how == "data":
        return None
    if how != "rest":
        raise ValueError(f"initial_state must be 'rest', 'data' or a function, got {how!r}")
    out = []
    for s in model.states:
        if s in data.channels:
            v = data.channels[s][:5]
            v = v[~np.isnan(v)]
            out.append(float(np.mean(v)) if v.size else 0.0)
        else:
            out.append(0.0)
    return out


def surrogate_data(model: IdentificationModel, data, parameters: Mapping[str, float], sigma: Mapping[str, float],
                   initial_state=None, seed: int = 0) -> Measurements:
    """A record on which ``model`` is exactly right: its free-run response (with ``parameters``,
    from ``initial_state``) to the given channels of ``data``, plus Gaussian noise of std
    ``sigma[channel]`` on the other measured channels; missing samples stay missing."""
    data = Measurements.coerce(data)
    pred = simulate(model, data, parameters, initial_state)
    n = pred["t"].size
    if n != data.t.size:
        raise RuntimeError(f"the free-run simulation of {model.name} stopped at t = {pred['t'][-1]:.6g}")
    rng = np.random.default_rng(seed)
    chans = {}
    for ch, v in data.channels.items():
        if ch in model.measured and ch not in model.given:
            y = pred[ch] + rng.normal(0.0, float(sigma.get(ch, 0.0)), size=n)
            y[np.isnan(v)] = np.nan
            chans[ch] = y
        else:
            chans[ch] = v.copy()
    return Measurements(data.t.copy(), chans)


# =============================================================================== where
def _components(res: EstimationResult) -> list[dict]:
    """Every residual component with its weighted energy density (J units): ξ rows and ε entries."""
    prob, model = res.problem, res.problem.model
    t = res.t
    X = res.shooting.sol(t)
    with torch.no_grad():
        _, mask = prob.measurements(t)
        W, V = prob.weights(t, X)
        V = V * mask.unsqueeze(-1) * mask.unsqueeze(-2)
    xi = torch.stack([res.xi[r] for r in model.equations], -1)
    eps = torch.stack([res.eps[n] for n in model.names], -1)
    dens_xi = xi * (V @ xi.unsqueeze(-1)).squeeze(-1)
    dens_eps = eps * (W @ eps.unsqueeze(-1)).squeeze(-1)
    out = []
    for i, r in enumerate(model.equations):
        kind = "measurement" if r in model.channels else "equation"
        out.append(dict(name=r, kind=kind, channel=model.channels.get(r), values=xi[:, i].numpy(),
                        density=dens_xi[:, i].numpy(), mask=mask[:, i].numpy() > 0))
    for j, n in enumerate(model.names):
        out.append(dict(name=f"ε:{n}", kind="dynamics", channel=None, values=eps[:, j].numpy(),
                        density=dens_eps[:, j].numpy(), mask=np.ones(t.numel(), dtype=bool)))
    return out


def effective_samples(z: np.ndarray) -> float:
    """n / (1 + 2 Σ ρ_k): the autocorrelation sum truncated at the first non-positive pair (Geyer)."""
    z = np.asarray(z, dtype=float)
    z = z - z.mean()
    n = z.size
    if n < 4 or not np.any(z):
        return float(max(n, 1))
    f = np.fft.rfft(z, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:n]
    ac = ac / ac[0]
    s = 0.0
    for k in range(1, n - 1, 2):
        pair = ac[k] + ac[k + 1]
        if pair <= 0:
            break
        s += pair
    return float(min(n, max(1.0, n / (1.0 + 2.0 * s))))


def _windows(t: np.ndarray, z2: np.ndarray, floor_z2: np.ndarray | None, width: int, max_windows: int = 12):
    """Time windows where the local mean of z² (standardised residual squared) exceeds the floor's
    own extremes (its 99.9 % local level, at least 2)."""
    n = t.size
    width = max(3, min(width, n))
    kern = np.ones(width) / width
    local = np.convolve(z2, kern, mode="same")
    thr = 2.0
    if floor_z2 is not None and floor_z2.size == n:
        thr = max(thr, float(np.quantile(np.convolve(floor_z2, kern, mode="same"), 0.999)))
    hot = local > thr
    if not hot.any():
        return [], thr
    # merge gaps shorter than a window
    idx = np.flatnonzero(hot)
    spans, s0, prev = [], idx[0], idx[0]
    for i in idx[1:]:
        if i - prev > width:
            spans.append((s0, prev))
            s0 = i
        prev = i
    spans.append((s0, prev))
    excess = np.clip(z2 - 1.0, 0.0, None)
    total = float(excess.sum()) or 1.0
    wins = []
    for a, b in spans:
        share = float(excess[a:b + 1].sum()) / total
        if share >= 0.02 or len(spans) == 1:
            wins.append(dict(t0=float(t[a]), t1=float(t[b]), share=share))
    wins.sort(key=lambda w: -w["share"])
    wins = sorted(wins[:max_windows], key=lambda w: w["t0"])
    return wins, thr


def locate(nominal: EstimationResult, floor: EstimationResult | None, alpha: float = 0.01, ratio_min: float = 1.5,
           share_min: float = 0.005, window: float = 0.02) -> list[dict]:
    """Where (module docstring, 1.): one entry per residual component (ξ rows, then ε entries)."""
    from scipy import stats

    t = nominal.t.numpy()
    comps = _components(nominal)
    fl = {c["name"]: c for c in _components(floor)} if floor is not None else {}
    total = sum(0.5 * float(np.trapezoid(c["density"], t)) for c in comps)
    d0 = nominal.shooting.sol(nominal.t[:1])[0, :nominal.problem.model.nx] - nominal.problem.q_a
    total += 0.5 * float(d0 @ nominal.problem.W_a @ d0)
    total = total if total > 0 else 1.0
    R = len(comps)
    width = max(5, int(round(window * t.size)))
    out = []
    for c in comps:
        m = c["mask"]
        E = 0.5 * float(np.trapezoid(c["density"], t))
        ms = float(np.mean(c["values"][m] ** 2)) if m.any() else 0.0
        entry = dict(equation=c["name"], kind=c["kind"], share=E / total, energy=E, rms=math.sqrt(ms),
                     significant=False, windows=[])
        if c["channel"]:
            entry["channel"] = c["channel"]
        f = fl.get(c["name"])
        if f is not None and m.any():
            fm = f["mask"] & m if f["mask"].size == m.size else f["mask"]
            fv = f["values"][fm] if f["values"].size == m.size else f["values"]
            ms_f = float(np.mean(fv ** 2)) if fv.size else 0.0
            scale = max(ms_f, 1e-300)
            n_eff = effective_samples(fv / math.sqrt(scale)) if fv.size else 1.0
            ratio = ms / scale if ms_f > 0 else (math.inf if ms > 0 else 1.0)
            p = float(stats.f.sf(ratio, n_eff, n_eff)) if math.isfinite(ratio) else 0.0
            excess = max(E - 0.5 * float(np.trapezoid(f["density"], t)) if f["density"].size == t.size else 0.0, 0.0)
            entry["excess_share"] = excess / total
            sig = bool(p < alpha / R and ratio >= ratio_min and entry["excess_share"] >= share_min)
            z = c["values"] / math.sqrt(scale)
            zf = f["values"] / math.sqrt(scale) if f["values"].size == t.size else None
            entry.update(floor_rms=math.sqrt(ms_f), ratio=ratio, p_value=p, n_eff=n_eff, significant=sig,
                         autocorrelation=dict(data=_lag1(c["values"][m]), floor=_lag1(fv)))
            if sig:
                z2 = np.where(m, z * z, 0.0)
                wins, thr = _windows(t, z2, None if zf is None else zf * zf, width)
                entry["windows"] = [[w["t0"], w["t1"]] for w in wins]
                entry["window_shares"] = [w["share"] for w in wins]
                entry["window_threshold"] = thr
        out.append(entry)
    return out


def _lag1(v: np.ndarray) -> float:
    v = np.asarray(v, dtype=float)
    if v.size < 3:
        return 0.0
    v = v - v.mean()
    d = float(v @ v)
    return float(v[1:] @ v[:-1]) / d if d > 0 else 0.0


# =============================================================================== which
@dataclass
class _Design:
    """The standardised regression problem at the nominal estimate."""

    model: IdentificationModel
    names: list[str]
    x: Tensor                  # (n, nx) estimated states and parameters
    zeta: Tensor               # (n, nζ)
    t: Tensor
    channel: Any
    rows: list[int]            # rows in the regression
    sigma: np.ndarray          # (len(rows),) floor rms per row
    mask: np.ndarray           # (n, len(rows)) bool
    y: np.ndarray              # stacked standardised residual
    Q: np.ndarray              # orthonormal basis of the nuisance columns
    nuisance: list[str]
    n_eff: float

    def project(self, v: np.ndarray) -> np.ndarray:
        return v - self.Q @ (self.Q.T @ v) if self.Q.size else v

    def stack(self, per_row: Tensor | np.ndarray) -> np.ndarray:
        a = per_row.detach().numpy() if isinstance(per_row, Tensor) else np.asarray(per_row)
        a = a[:, self.rows] / self.sigma
        return a[self.mask]

    def vars(self, effects: Sequence[Effect], values: Mapping[str, float]) -> Vars:
        new = _new_parameters(self.model, effects)
        n = self.x.shape[0]
        th = torch.tensor([float(values[p]) for p in new], dtype=torch.float64).expand(n, -1)
        x = torch.cat([self.x, th], -1)
        return _vars(self.model, self.names + new, x, self.zeta, self.t, self.channel)

    def predict(self, effects: Sequence[Effect], values: Mapping[str, float]) -> np.ndarray:
        with torch.no_grad():
            v = self.vars(effects, values)
            out = _rows_sum(self.model, effects, v, self.t.shape)
        return self.stack(out)


def _design(nominal: EstimationResult, floor_sigma: Mapping[str, float], n_eff: float,
            channel) -> _Design:
    model = nominal.problem.model
    names = model.names
    t = nominal.t
    x = torch.stack([nominal.x[n] for n in names], -1).detach()
    zeta = torch.stack([nominal.zeta[n] for n in model.inputs], -1).detach()
    with torch.no_grad():
        _, mask = nominal.problem.measurements(t)
    xi = torch.stack([nominal.xi[r] for r in model.equations], -1).numpy()
    rows = [i for i, r in enumerate(model.equations) if floor_sigma.get(r, 0.0) > 0]
    sigma = np.array([floor_sigma[model.equations[i]] for i in rows])
    mk = mask.numpy()[:, rows] > 0
    y = (xi[:, rows] / sigma)[mk]
    # nuisance columns: the sensitivities of the rows to the free nominal parameters
    W_a = nominal.problem.W_a
    free = [p for j, p in enumerate(model.parameters) if float(W_a[len(model.states) + j, len(model.states) + j]) == 0.0]
    cols = []
    with torch.no_grad():
        for p in free:
            j = names.index(p)
            h = 1e-6 * max(abs(float(x[:, j].mean())), 1e-3)
            xp, xm = x.clone(), x.clone()
            xp[:, j] += h
            xm[:, j] -= h
            gp = model.f(xp, t) + (model.F(xp, t) @ zeta.unsqueeze(-1)).squeeze(-1)
            gm = model.f(xm, t) + (model.F(xm, t) @ zeta.unsqueeze(-1)).squeeze(-1)
            col = ((gp - gm) / (2 * h)).numpy()
            cols.append((col[:, rows] / sigma)[mk])
    if cols:
        S = np.column_stack(cols)
        norms = np.linalg.norm(S, axis=0)
        keep = norms > 0
        S = S[:, keep] / norms[keep]
        U, sv, _ = np.linalg.svd(S, full_matrices=False)
        Q = U[:, sv > 1e-10 * (sv.max() if sv.size else 1.0)]
        nuis = [p for p, k in zip(free, keep) if k]
    else:
        Q, nuis = np.zeros((y.size, 0)), []
    return _Design(model=model, names=names, x=x, zeta=zeta, t=t, channel=channel, rows=rows, sigma=sigma,
                   mask=mk, y=y, Q=Q, nuisance=nuis, n_eff=n_eff)


def _starts(effect: Effect, v: Vars) -> list[dict]:
    s = effect.starts(v) if callable(effect.starts) else effect.starts
    grid = []
    for p, v0 in effect.parameters.items():
        vals = [v0] + [float(a) for a in (s or {}).get(p, [])]
        grid.append(list(dict.fromkeys(vals)))
    combos = [dict(zip(effect.parameters, c)) for c in itertools.product(*grid)]
    return combos[:27]


def _fit(design: _Design, effects: Sequence[Effect], starts: Sequence[Mapping[str, float]]):
    """Least squares of the projected standardised residual on the effects' terms."""
    from scipy.optimize import least_squares

    names = [p for e in effects for p in e.parameters]
    lo = np.array([e.bounds.get(p, (-np.inf, np.inf))[0] for e in effects for p in e.parameters], dtype=float)
    hi = np.array([e.bounds.get(p, (-np.inf, np.inf))[1] for e in effects for p in e.parameters], dtype=float)
    scale = np.array([float(e.scale.get(p, abs(v) if v != 0 else 1.0)) for e in effects for p, v in e.parameters.items()])
    scale = np.where(scale > 0, scale, 1.0)
    yp = design.project(design.y)

    def resid(th):
        pred = design.predict(effects, dict(zip(names, th)))
        r = yp - design.project(pred)
        return np.where(np.isfinite(r), r, 1e6)

    best = None
    for s in starts:
        x0 = np.array([float(s[p]) for p in names])
        fin_lo, fin_hi = np.isfinite(lo), np.isfinite(hi)
        inner_lo, inner_hi = lo.copy(), hi.copy()
        inner_lo[fin_lo] = lo[fin_lo] + 1e-9 * np.maximum(np.abs(lo[fin_lo]), scale[fin_lo])
        inner_hi[fin_hi] = hi[fin_hi] - 1e-9 * np.maximum(np.abs(hi[fin_hi]), scale[fin_hi])
        x0 = np.minimum(np.maximum(x0, inner_lo), inner_hi)
        try:
            sol = least_squares(resid, x0, bounds=(lo, hi), x_scale=scale, method="trf", max_nfev=200,
                                diff_step=1e-6)
        except Exception:  # noqa: BLE001 - a start that fails is skipped
            continue
        rss = float(sol.fun @ sol.fun)
        if best is None or rss < best[0]:
            best = (rss, sol.x)
    if best is None:
        return float(yp @ yp), {p: float(v) for p, v in zip(names, [s for s in starts[0].values()])}
    return best[0], {p: float(v) for p, v in zip(names, best[1])}


def _solve_final(model: IdentificationModel) -> dict:
    """The model's solver settings with a continuation schedule reduced to its last stage."""
    opts = dict(model.settings.get("solve", {}))
    cont = opts.pop("continuation", None)
    if cont:
        opts.update(cont[-1])
    return opts


def _linear_parameters(design: _Design, effect: Effect, values: Mapping[str, float]) -> list[str]:
    """The parameters the effect's term is linear in (numerical probe on the estimated variables)."""
    out = []
    for p in effect.parameters:
        a = float(effect.scale.get(p, abs(values[p]) or 1.0)) or 1.0
        t0, t1, t2 = (design.predict([effect], dict(values, **{p: c})) for c in (0.0, a, 2.0 * a))
        d1, d2 = t1 - t0, t2 - t0
        if np.all(np.isfinite(d2)) and np.abs(d2 - 2 * d1).max() <= 1e-8 * (1.0 + np.abs(d2).max()):
            out.append(p)
    return out


def one_step(nominal: EstimationResult, effects: Sequence[Effect], data, values: Mapping[str, float],
             pinned: Sequence[str] = (), start: EstimationResult | None = None) -> EstimationResult:
    """The linearised re-estimation of the model extended with ``effects``: one undamped Newton
    step of the extended TPBVP from the nominal solution (new parameters at ``values``; those in
    ``pinned`` held there by a strong prior).  For a term linear in its free parameters this step
    *is* the re-estimation, up to the curvature of the rest of the model: it accounts for how the
    states, inputs and nominal parameters re-adjust (what a regression on the residual alone
    misses when the weights let the smoother absorb part of a structural error).  ``start``: warm
    start from another (extended) estimate instead of the nominal one, for a second step."""
    nm = nominal.problem.model
    ext = extend(nm, effects, data=data, initial=values)
    if pinned:
        Wa = torch.as_tensor(_extend_weight(ext.W_a, ext.nx, 0, 0.0)).clone() if not callable(ext.W_a) else None
        if Wa is not None:
            Wa = torch.diag(Wa) if Wa.ndim == 1 else Wa
            for p in pinned:
                j = ext.names.index(p)
                sc = float(next(e.scale.get(p, abs(values[p]) or 1.0) for e in effects if p in e.parameters)) or 1.0
                Wa[j, j] = 1e8 / sc ** 2
            ext = replace(ext, W_a=Wa)
    opts = _solve_final(nm)
    opts.update(max_iter=1, newton="undamped", newton_options={}, max_growth=None, continuation=None)
    return estimate(ext, data, n_points=nominal.points, initial=dict(values), start=start or nominal, **opts)


def rank(nominal: EstimationResult, effects: Sequence[Effect], data=None, *, floor_sigma: Mapping[str, float],
         n_eff: float, nu: float, J_floor: float | None = None, significant: bool = True,
         explained_min: float = 0.5, pair_gain: float = 0.3, pairs: int = 3, shape_trials: int = 4, refine: int = 2,
         polish: int = 3, polish_steps: int = 3,
         log: Callable[[str], None] | None = None) -> dict:
    """Which (module docstring, 2.): the ranking of the single effects, the table of models, the
    selection and a plain-words verdict.

    Screening: every candidate's term is fitted to the floor-standardised residual with the nominal
    parameters' sensitivities as nuisance columns (cheap; it picks the shape parameters — the ones
    the term is not linear in).  Scoring: :func:`one_step` per candidate, shape parameters held at
    the screened values — J after the step is what re-estimating with that effect leaves.  The
    information criterion ``ν log J + k log ν`` (ν: effective number of measured samples, k: the
    effect's parameters) ranks them; the ``pairs`` best compatible singles are combined in pairs, and
    the ``polish`` leading models get up to ``polish_steps`` further steps before the selection."""
    say = log or (lambda s: None)
    data = Measurements.coerce(data) if data is not None else nominal.problem.data
    chans = sorted({c for e in effects for c in e.channels})
    design = _design(nominal, floor_sigma, n_eff, _channel_fn(data, chans))
    J0 = nominal.J
    nu = max(float(nu), 2.0)

    def crit(J, k):
        return nu * math.log(max(J, 1e-300)) + k * math.log(nu) if math.isfinite(J) else math.inf

    by_name = {e.name: e for e in effects}
    models = [dict(effects=[], k=0, J=J0, parameters={}, criterion=crit(J0, 0), result=nominal)]
    singles: dict[str, dict] = {}
    for e in effects:
        v0 = design.vars([e], e.parameters)
        starts = _starts(e, v0)
        rss, screened = _fit(design, [e], starts)
        linear = _linear_parameters(design, e, screened)
        shape = [p for p in e.parameters if p not in linear]
        # one-step trials: the screened shape, and other starting shapes (the screening sees the
        # residual after the smoother has absorbed part of the error, its shape can be off)
        trials = [{p: (0.0 if p in linear else screened[p]) for p in e.parameters}]
        for st in starts:
            cand = {p: (0.0 if p in linear else float(st[p])) for p in e.parameters}
            if shape and all(cand != tr for tr in trials):
                trials.append(cand)
        trials = trials[:shape_trials] if shape else trials[:1]
        done = []
        for start in trials:
            try:
                res = one_step(nominal, [e], data, start, pinned=shape if linear else ())
                J = res.J if math.isfinite(res.J) else math.inf
                par = {p: res.parameters[p] for p in e.parameters}
            except Exception as exc:  # noqa: BLE001 - a candidate that cannot be evaluated is reported
                res, J, par = None, math.inf, dict(start)
                say(f"  {e.name}: start {start} not evaluated ({type(exc).__name__}: {str(exc)[:120]})")
            done.append((J, par, res))
        done.sort(key=lambda d: d[0])
        J, par, res = done[0]
        if shape:
            # a second undamped step with every parameter free refines the shape, from the two best
            # starts (a step from a start far from the optimum overshoots where the term is steep)
            for J1, par1, res1 in done[:refine]:
                if res1 is None or not math.isfinite(J1):
                    continue
                try:
                    res2 = one_step(nominal, [e], data, par1, start=res1)
                except Exception:  # noqa: BLE001 - keep the first step
                    continue
                par2 = {p: res2.parameters[p] for p in e.parameters}
                inside = all(e.bounds.get(p, (-math.inf, math.inf))[0] <= par2[p] <= e.bounds.get(p, (-math.inf, math.inf))[1]
                             for p in e.parameters)
                if math.isfinite(res2.J) and res2.J < J and inside:
                    J, par, res = res2.J, par2, res2
        k = len(e.parameters)
        singles[e.name] = dict(effects=[e.name], k=k, J=J, parameters=par, criterion=crit(J, k), result=res,
                               screened=screened, shape=shape if linear else [])
        models.append(singles[e.name])
        say(f"  {e.name:<22} J {J:.5g} ({100 * (J0 - J) / J0 if math.isfinite(J) else float('nan'):5.1f} % less)"
            + (f" [{len(trials)} starts]" if len(trials) > 1 else ""))
    order = sorted(singles.values(), key=lambda m: m["criterion"])
    top = [m for m in order if math.isfinite(m["criterion"]) and m["J"] < J0][:max(pairs, 0)]
    for ma, mb in itertools.combinations(top, 2):
        a, b = by_name[ma["effects"][0]], by_name[mb["effects"][0]]
        if a.group is not None and a.group == b.group:
            continue
        vals = dict(ma["parameters"], **mb["parameters"])
        try:
            res = one_step(nominal, [a, b], data, vals, pinned=ma["shape"] + mb["shape"])
            J = res.J if math.isfinite(res.J) else math.inf
            par = {p: res.parameters[p] for p in vals}
        except Exception:  # noqa: BLE001
            res, J, par = None, math.inf, vals
        k = ma["k"] + mb["k"]
        models.append(dict(effects=[a.name, b.name], k=k, J=J, parameters=par, criterion=crit(J, k), result=res,
                           shape=ma["shape"] + mb["shape"]))
        say(f"  {a.name} + {b.name}: J {J:.5g}")
    # polish the leading models: the undamped step is exact only for a model linear in everything,
    # so the few that compete for selection get further steps until J settles (a single effect's
    # first step can leave part of the error a pair then seems to explain)
    lead = sorted((m for m in models if m["effects"] and m["result"] is not None and math.isfinite(m["J"])),
                  key=lambda m: m["criterion"])[:max(polish, 0)]
    for m in lead:
        for _ in range(polish_steps):
            try:
                res = one_step(nominal, [by_name[n] for n in m["effects"]], data, m["parameters"], start=m["result"])
            except Exception:  # noqa: BLE001 - keep the last step
                break
            if not (math.isfinite(res.J) and res.J < m["J"]):
                break
            gain = (m["J"] - res.J) / m["J"]
            m.update(J=res.J, result=res, parameters={p: res.parameters[p] for p in m["parameters"]},
                     criterion=crit(res.J, m["k"]))
            if gain < 1e-3:
                break
        say(f"  polished {' + '.join(m['effects'])}: J {m['J']:.5g}")
    finite = [m for m in models if math.isfinite(m["criterion"])]
    cmin = min(m["criterion"] for m in finite)
    wsum = sum(math.exp(-0.5 * (m["criterion"] - cmin)) for m in finite)
    for m in models:
        m["weight"] = math.exp(-0.5 * (m["criterion"] - cmin)) / wsum if math.isfinite(m["criterion"]) else 0.0
        m["explained"] = (J0 - m["J"]) / J0 if math.isfinite(m["J"]) and J0 > 0 else 0.0
    excess = J0 - (J_floor if J_floor is not None else 0.0)
    excess = excess if excess > 0 else 1e-12 * max(J0, 1e-300)
    for m in models:
        m["explained_excess"] = (J0 - m["J"]) / excess if math.isfinite(m["J"]) else 0.0
    ranking = []
    for e in effects:
        sg = singles[e.name]
        conf = sum(m["weight"] for m in models if e.name in m["effects"])
        ranking.append(dict(effect=e.name, score=sg["explained"], confidence=conf, explained_excess=sg["explained_excess"],
                            criterion=sg["criterion"] - models[0]["criterion"], J=sg["J"], parameters=sg["parameters"],
                            screened=sg["screened"], equations=list(e.equations), description=e.description))
    ranking.sort(key=lambda r: (r["criterion"], -r["score"]))
    best = min(models, key=lambda m: m["criterion"])
    if len(best["effects"]) == 2:
        # a pair only if its second effect removes a real part of what the better member leaves
        better = min((singles[n] for n in best["effects"]), key=lambda m: m["J"])
        left = max(better["J"] - (J_floor or 0.0), 1e-300)
        if (better["J"] - best["J"]) < pair_gain * left:
            best = better
    if not significant:
        selected, verdict = [], "no significant structural error: the residual is at the noise floor"
    elif not best["effects"]:
        selected = []
        tp = ranking[0] if ranking else None
        verdict = ("the residual is significantly above the noise floor but no candidate explains it"
                   + (f" (best: {tp['effect']}, {100 * max(tp['explained_excess'], 0):.0f} % of the excess)" if tp else ""))
    elif best["explained_excess"] < explained_min:
        selected = []
        verdict = (f"the residual is significantly above the noise floor but no candidate explains it: the best, "
                   f"{' + '.join(best['effects'])}, explains only {100 * max(best['explained_excess'], 0):.0f} % of "
                   f"its excess over the floor")
    else:
        selected = list(best["effects"])
        verdict = (f"structural error explained by {' + '.join(selected)} "
                   f"({100 * min(best['explained_excess'], 1.0):.0f} % of the residual's excess over the noise floor)")
    models.sort(key=lambda m: m["criterion"])
    return dict(ranking=ranking, models=models, selected=selected, verdict=verdict, best=best,
                selected_parameters=dict(best["parameters"]) if selected else {},
                explained_excess=best["explained_excess"] if selected else None, n=int(design.y.size), nu=nu,
                J_floor=J_floor, nuisance=design.nuisance, design=design)


# =============================================================================== shrink
def _row_energy(res: EstimationResult) -> dict[str, float]:
    t = res.t.numpy()
    return {c["name"]: 0.5 * float(np.trapezoid(c["density"], t)) for c in _components(res) if c["kind"] != "dynamics"}


def free_run_error(model: IdentificationModel, data: Measurements, parameters: Mapping[str, float],
                   initial_state="rest", sigma: Mapping[str, float] | None = None) -> dict:
    """Free-run simulation of the measured (non-given) channels on ``data``: RMS error per channel,
    relative to the channel's standard deviation, and overall (quadratic mean of the relative
    errors); infinite when the simulation does not reach the end of the record.  With ``sigma``
    (the channels' noise levels) also the error *above the noise*, √max(MSE − σ², 0): what the
    model gets wrong, without the measurement noise no model can predict."""
    chans = [c for c in model.measured if c not in model.given]
    x0 = _initial_state(model, data, initial_state)
    try:
        pred = simulate(model, data, parameters, x0)
        ok = pred["t"].size == data.t.size
    except Exception as exc:  # noqa: BLE001 - a diverging model is a result, not a crash
        pred, ok = {"t": data.t[:0], "error": f"{type(exc).__name__}: {exc}"}, False
    per, rel, rel_n = {}, [], []
    for ch in chans:
        y = data.channels[ch]
        if ok and np.all(np.isfinite(pred[ch])):
            m = ~np.isnan(y)
            e = pred[ch][m] - y[m]
            mse = float(np.mean(e * e))
        else:
            mse = math.inf
        sd = float(np.nanstd(y)) or 1.0
        rms = math.sqrt(mse)
        per[ch] = dict(rms=rms, relative=rms / sd)
        rel.append(rms / sd)
        if sigma is not None:
            above = math.sqrt(max(mse - float(sigma.get(ch, 0.0)) ** 2, 0.0)) if math.isfinite(mse) else math.inf
            per[ch]["above_noise"] = above
            rel_n.append(above / sd)
    overall = float(np.sqrt(np.mean(np.square(rel)))) if rel else math.nan
    out = dict(per_channel=per, overall=overall, prediction=pred if ok else None, complete=ok)
    if sigma is not None:
        out["overall_above_noise"] = float(np.sqrt(np.mean(np.square(rel_n)))) if rel_n else math.nan
    return out


def _shrink(before: float, after: float) -> float | None:
    if before is None or after is None or not math.isfinite(before):
        return None
    if before <= 0:
        return 0.0
    return 1.0 - after / before if math.isfinite(after) else -math.inf


def shrink(nominal: EstimationResult, extended: EstimationResult, validation=None, initial_state="rest",
           nominal_model: IdentificationModel | None = None, effects: Sequence[Effect] = ()) -> dict:
    """How far it shrinks (module docstring, 3.)."""
    nm = nominal_model or nominal.problem.model
    e0, e1 = _row_energy(nominal), _row_energy(extended)
    ident = dict(before=nominal.J, after=extended.J, shrink=_shrink(nominal.J, extended.J),
                 per_channel={r: dict(before=e0[r], after=e1.get(r), shrink=_shrink(e0[r], e1.get(r))) for r in e0})
    out = dict(identification=ident)
    if validation is not None:
        val = Measurements.coerce(validation)
        ext_model = extend(nm, effects, data=val) if effects else nm
        out["validation"] = _validation_summary(nm, ext_model, val, nominal.parameters, extended.parameters,
                                                initial_state)
    return out


def _validation_summary(before_model, after_model, val: Measurements, before_params, after_params,
                        initial_state) -> dict:
    chans = [c for c in before_model.measured if c not in before_model.given]
    sigma = noise_level(val, chans)
    b = free_run_error(before_model, val, before_params, initial_state, sigma)
    a = free_run_error(after_model, val, after_params, initial_state, sigma) if after_model is not None else b
    per = {}
    for ch in b["per_channel"]:
        B, A = b["per_channel"][ch], a["per_channel"][ch]
        per[ch] = dict(before=B["rms"], after=A["rms"], shrink=_shrink(B["rms"], A["rms"]),
                       before_above_noise=B["above_noise"], after_above_noise=A["above_noise"],
                       shrink_above_noise=_shrink(B["above_noise"], A["above_noise"]))
    return dict(before=b["overall"], after=a["overall"], shrink=_shrink(b["overall"], a["overall"]),
                before_above_noise=b["overall_above_noise"], after_above_noise=a["overall_above_noise"],
                shrink_above_noise=_shrink(b["overall_above_noise"], a["overall_above_noise"]),
                per_channel=per, noise=sigma,
                measure="free-run RMS error per channel; overall: quadratic mean over the channels of RMS error / "
                        "channel std; *_above_noise: sqrt(max(MSE - noise^2, 0)), the noise estimated from the "
                        "validation record",
                predictions=dict(before=b["prediction"], after=a["prediction"] if after_model is not None else None))


# =============================================================================== the whole diagnosis
@dataclass
class Diagnosis:
    """Outcome of :func:`diagnose` (``to_dict()`` is the JSON of ``diagnosis.json``)."""

    model: IdentificationModel
    library: Library
    data: Measurements
    validation: Measurements | None
    nominal: EstimationResult
    floor: EstimationResult | None
    noise: dict[str, float]
    where: list[dict]
    significant: bool
    which: dict
    selected: list[str]
    verdict: str
    extended: EstimationResult | None
    shrink: dict | None
    skipped: dict[str, str]
    seconds: dict[str, float]
    notes: list[str] = field(default_factory=list)
    #: ``confirmed`` (the selected effects shrink the validation misfit), ``selected`` (no
    #: validation record to confirm it), ``no_structural_error``, ``unexplained`` (significant,
    #: no candidate explains it), ``not_confirmed`` (the candidates explain the identification
    #: record but none shrinks the validation misfit) or ``inconclusive`` (an estimate failed)
    status: str = "selected"

    @property
    def success(self) -> bool:
        """False when the diagnosis could not reach a verdict it can stand by (``inconclusive``,
        ``not_confirmed``): the command line then exits non-zero."""
        return self.status not in ("inconclusive", "not_confirmed")

    def to_dict(self) -> dict:
        def est(r: EstimationResult | None, effects=None):
            if r is None:
                return None
            out = dict(model=r.problem.model.name, parameters=dict(r.parameters), J=r.J, success=bool(r.success),
                       iterations=int(r.iterations), points=int(r.points), message=r.message)
            if effects is not None:
                out["effects"] = list(effects)
            return out
        ranking = [{k: v for k, v in r.items()} for r in self.which.get("ranking", [])]
        models = [dict(effects=m["effects"], criterion=m["criterion"], weight=m["weight"], explained=m["explained"],
                       parameters=m["parameters"]) for m in self.which.get("models", [])[:20]]
        sh = None
        if self.shrink is not None:
            sh = {k: ({kk: vv for kk, vv in v.items() if kk != "predictions"} if v is not None else None)
                  for k, v in self.shrink.items()}
        return _clean(dict(
            model=self.model.name, library=self.library.name, verdict=self.verdict, status=self.status,
            significant=self.significant, nominal=est(self.nominal),
            extended=(est(self.extended, self.selected) if self.extended is not None
                      else est(self.nominal, []) if self.status != "inconclusive" else None),
            noise=self.noise, floor=est(self.floor), where=self.where, ranking=ranking, models=models,
            selected=self.selected, selected_parameters=self.which.get("selected_parameters", {}),
            regression=dict(samples=self.which.get("n"), effective_samples=self.which.get("n_eff"),
                            nuisance_parameters=self.which.get("nuisance")),
            shrink=sh, skipped_effects=self.skipped, seconds=self.seconds, notes=self.notes))


def _clean(o):
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    return o


def diagnose(model: IdentificationModel | str, data, library: Library | None = None, validation=None,
             nominal: EstimationResult | None = None, effects: Sequence[str] | None = None, seed: int = 0,
             alpha: float = 0.01, ratio_min: float = 1.5, share_min: float = 0.005, explained_min: float = 0.5,
             pairs: int = 3, alternatives: int = 2, log: Callable[[str], None] | None = None) -> Diagnosis:
    """Where / which / how far (module docstring) for ``model`` on ``data``.

    ``library``: the candidates and the family's estimation strategy (default :func:`library_for`);
    ``model``: or a built-in name (``"flexible"``); ``effects``: restrict to these names; ``validation``: a record with another input for the
    free-run comparison; ``nominal``: an estimate of ``model`` on ``data`` to start from (else the
    library's estimator runs).  ``log``: progress lines (then also one per Newton iteration).

    Honest failure: an estimate that does not converge is retried on 2, 4 and 8 times the shooting points; if it
    still fails the status is ``inconclusive`` and no shrink is reported.  With a validation record a
    selection counts only when it makes the free-run misfit there shrink; otherwise up to
    ``alternatives`` next-best models are tried, and without one that shrinks it the status is
    ``not_confirmed`` (:attr:`Diagnosis.status`)."""
    say = log or (lambda s: None)
    if isinstance(model, str):
        from .models import resolve_model
        model = resolve_model(model)
    data = Measurements.coerce(data)
    data.require(model.measured, float(data.t[0]), float(data.t[-1]))
    if validation is not None:
        validation = Measurements.coerce(validation)
        validation.require(model.measured, float(validation.t[0]), float(validation.t[-1]))
    library = library or library_for(model)
    estimator = _verbose(library.estimator or default_estimator, log is not None)
    cands, skipped = library.applicable(model)
    if effects is not None:
        unknown = [e for e in effects if e not in library.names]
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; the library {library.name!r} has {library.names}")
        cands = [e for e in cands if e.name in effects]
    seconds = {}
    notes = []
    t0 = time.perf_counter()
    if nominal is None:
        say(f"estimating the nominal model {model.name} ...")
        nominal, tried = _estimate_retrying(estimator, model, data, say)
        notes += tried
    seconds["nominal"] = time.perf_counter() - t0
    nm = nominal.problem.model
    if not nominal.success:
        return Diagnosis(model=nm, library=library, data=data, validation=validation, nominal=nominal, floor=None,
                         noise={}, where=[], significant=False, which={}, selected=[],
                         verdict=f"inconclusive: the nominal model {model.name} could not be estimated "
                                 f"({nominal.message})", extended=None, shrink=None, skipped=skipped,
                         seconds=seconds, notes=notes, status="inconclusive")
    say(f"  J = {nominal.J:.6g}, parameters " + ", ".join(f"{k} = {v:.5g}" for k, v in nominal.parameters.items()))
    # noise floor
    t0 = time.perf_counter()
    sigma = noise_level(data, [c for c in nm.measured if c not in nm.given])
    say("noise floor: surrogate record (the nominal model's free run + noise " +
        ", ".join(f"{k} {v:.3g}" for k, v in sigma.items()) + ") ...")
    floor = None
    try:
        x0 = [float(nominal.x[s][0]) for s in nm.states]
        sur = surrogate_data(nm, data, nominal.parameters, sigma, x0, seed=seed)
        floor = estimator(nm, sur, initial=dict(nominal.parameters))
        if not floor.success:
            notes.append(f"the noise-floor estimate did not converge ({floor.message}); its residuals are used anyway")
    except Exception as exc:  # noqa: BLE001 - reported, the diagnosis goes on without a floor
        notes.append(f"no noise floor: {type(exc).__name__}: {exc}")
        floor = None
    seconds["floor"] = time.perf_counter() - t0
    where = locate(nominal, floor, alpha=alpha, ratio_min=ratio_min, share_min=share_min)
    significant = any(w["significant"] for w in where)
    if floor is None:
        significant = True
        notes.append("without a noise floor every residual is treated as significant")
    say("where: " + ", ".join(f"{w['equation']} {100 * w['share']:.1f} %" + (" *" if w["significant"] else "")
                              for w in where if w["share"] >= 0.005))
    # which
    t0 = time.perf_counter()
    floor_sigma = {w["equation"]: w.get("floor_rms", 0.0) for w in where if w["kind"] != "dynamics"}
    if floor is None:
        floor_sigma = {w["equation"]: w["rms"] for w in where if w["kind"] != "dynamics"}
    n_eff = sum(w.get("n_eff", 0.0) for w in where if w["kind"] != "dynamics" and floor_sigma.get(w["equation"], 0) > 0)
    meas = [w for w in where if w["kind"] == "measurement" and w.get("channel") not in nm.given]
    nu = sum(w.get("n_eff", 0.0) for w in meas) if floor is not None else len(meas) * nominal.t.numel()
    say(f"which: {len(cands)} candidates, linearised re-estimation of each ...")
    which = rank(nominal, cands, data, floor_sigma=floor_sigma, n_eff=n_eff or nominal.t.numel(),
                 nu=nu or nominal.t.numel(), J_floor=floor.J if floor is not None else None,
                 significant=significant, explained_min=explained_min, pairs=pairs, log=say)
    seconds["rank"] = time.perf_counter() - t0
    selected, verdict = which["selected"], which["verdict"]
    say("which: " + ", ".join(f"{r['effect']} {100 * r['score']:.0f} % ({r['confidence']:.2f})" for r in which["ranking"][:4]))
    say(verdict)
    extended_res, sh = None, None
    status = "no_structural_error" if not significant else ("unexplained" if not selected else "selected")
    if selected:
        t0 = time.perf_counter()
        # the first choice, then (with a validation record) the next-best models as long as the
        # validation misfit does not shrink
        choices = [list(selected)] + ([m["effects"] for m in which["models"] if m["effects"]
                                       and set(m["effects"]) != set(selected)
                                       and m.get("explained_excess", 0.0) >= explained_min][:alternatives]
                                      if validation is not None else [])
        rejected = []
        for k, effs in enumerate(choices):
            model_k = which["best"] if k == 0 else next(m for m in which["models"] if m["effects"] == effs)
            extended_res, sh, tried = _reestimate(nominal, nm, library, estimator, effs, model_k, data, validation, say)
            notes += tried
            if k == 0 and extended_res.success:     # parsimony: a nested simpler model that does as well
                effs, extended_res, sh, model_k = _prefer_nested(nominal, nm, library, estimator, which, effs,
                                                                 extended_res, sh, model_k, data, validation, nu,
                                                                 notes, say)
            if k == 0:
                first = (extended_res, sh)
            if not extended_res.success and k > 0:          # an alternative that fails is passed over
                notes.append(f"the alternative {' + '.join(effs)} could not be estimated: {extended_res.message}")
                continue
            if not extended_res.success:
                status, selected, sh = "inconclusive", [], None
                verdict = (f"inconclusive: the extended model {nm.name}+{'+'.join(effs)} could not be estimated "
                           f"({extended_res.message})")
                break
            val = sh.get("validation")
            say(f"  J {nominal.J:.4g} -> {extended_res.J:.4g}" + (
                f"; validation misfit {val['before']:.4g} -> {val['after']:.4g}" if val else ""))
            if val is None:
                selected, status = list(effs), "selected"
                verdict += "; not confirmed on validation data (none given)"
                break
            if val["shrink"] is not None and val["shrink"] > 0:
                selected, status = list(effs), "confirmed"
                verdict = (f"structural error explained by {' + '.join(effs)} "
                           f"({100 * min(max(model_k['explained_excess'], 0.0), 1.0):.0f} % of the residual's excess "
                           f"over the noise floor), confirmed on the validation record: the free-run misfit shrinks "
                           f"{val['before']:.3g} -> {val['after']:.3g}")
                if rejected:
                    verdict += (f"; {', '.join(rejected)} explained the identification record but not the "
                                f"validation record")
                break
            rejected.append(" + ".join(effs))
            say(f"  {' + '.join(effs)} does not shrink the validation misfit: not confirmed")
        else:                                  # report the first choice's figures
            (extended_res, sh), status, selected = first, "not_confirmed", []
            verdict = (f"not confirmed: {', '.join(rejected)} explain(s) the identification record but not the "
                       f"validation record (the free-run misfit does not shrink)")
        seconds["extended"] = time.perf_counter() - t0
        say(verdict)
    else:
        # nothing added: the "extended" model is the nominal one and nothing shrinks
        e0 = _row_energy(nominal)
        sh = dict(identification=dict(before=nominal.J, after=nominal.J, shrink=0.0,
                                      per_channel={r: dict(before=v, after=v, shrink=0.0) for r, v in e0.items()}),
                  validation=None)
        if validation is not None:
            sh["validation"] = _validation_summary(nm, None, validation, nominal.parameters, None,
                                                   library.initial_state)
    return Diagnosis(model=nm, library=library, data=data, validation=validation, nominal=nominal, floor=floor,
                     noise=sigma, where=where, significant=significant, which=which, selected=selected,
                     verdict=verdict, extended=extended_res, shrink=sh, skipped=skipped, seconds=seconds, notes=notes,
                     status=status)


#: significance of the likelihood-ratio test between nested models (:func:`_prefer_nested`)
NESTED_ALPHA = 0.01


def _prefer_nested(nominal, nm, library, estimator, which, effs, res, sh, cand, data, validation, nu, notes, say):
    """Between nested models the simpler one unless the data need the richer one's extra
    parameters: each model nested in ``effs`` (a single effect's ``nests``, a pair's members) is
    re-estimated in full, and the richer is kept only if the likelihood ratio ν log(J_simple/J_rich)
    exceeds the χ² quantile (1 − ``NESTED_ALPHA``) with the difference in parameters as degrees of
    freedom (ν: the effective number of measured samples).  Returns the chosen (effects, result,
    shrink, candidate)."""
    from scipy.stats import chi2

    simpler = [[n] for e in effs for n in library[e].nests] + ([[e] for e in effs] if len(effs) > 1 else [])
    k_rich = sum(len(library[e].parameters) for e in effs)
    cands = [(s, next((m for m in which["models"] if m["effects"] == s), None)) for s in simpler]
    for s_effs, s_cand in sorted((c for c in cands if c[1] is not None), key=lambda c: c[1]["J"]):
        s_res, s_sh, tried = _reestimate(nominal, nm, library, estimator, s_effs, s_cand, data, validation, say)
        notes += tried
        if not s_res.success or not (s_res.J > 0 and res.J > 0):
            continue
        dk = k_rich - sum(len(library[e].parameters) for e in s_effs)
        lr, limit = nu * math.log(s_res.J / res.J), float(chi2.ppf(1.0 - NESTED_ALPHA, max(dk, 1)))
        say(f"  nested test {' + '.join(s_effs)} within {' + '.join(effs)}: LR {lr:.3g} vs χ²({max(dk, 1)}) {limit:.3g}")
        if lr < limit:
            notes.append(f"{' + '.join(s_effs)} preferred to {' + '.join(effs)}, which contains it: likelihood "
                         f"ratio {lr:.3g} < {limit:.3g} (χ², {max(dk, 1)} degrees of freedom, α = {NESTED_ALPHA})")
            return list(s_effs), s_res, s_sh, s_cand
    return effs, res, sh, cand


#: shooting-point multiples tried when an estimate of the diagnosis does not converge
RETRY_POINTS = (2, 4, 8)


def _estimate_retrying(estimator, model: IdentificationModel, data, say, **kw) -> tuple[EstimationResult, list[str]]:
    """``estimator(model, data, **kw)``; when it does not converge, again on 2, 4 and 8 times as many
    shooting points (intervals too long for the problem's growth, or a Newton iteration that a finer
    grid makes more linear).  The last result and a note per failed attempt."""
    res = estimator(model, data, **kw)
    notes = []
    base = res.points
    for factor in RETRY_POINTS:
        if res.success:
            break
        notes.append(f"{model.name} on {res.points} shooting points did not converge: {res.message}")
        say(f"  {notes[-1]}; retrying on {factor * base} points ...")
        res = estimator(model, data, n_points=factor * base, **kw)
    return res, notes


def _reestimate(nominal: EstimationResult, nm: IdentificationModel, library: "Library", estimator,
                effects: Sequence[str], candidate: dict, data, validation, say):
    """The model extended with ``effects`` re-estimated from the candidate's linearised solution
    (parameters clipped to the effects' bounds), retried on more shooting points when it does not
    converge, and how far the misfit shrinks (None when it did not converge)."""
    sel = [library[n] for n in effects]
    ext = extend(nm, sel, data=data)
    init = {p: candidate["parameters"][p] for p in candidate["parameters"]}
    for e in sel:
        for p, (lo, hi) in e.bounds.items():
            if p in init:
                init[p] = min(max(init[p], lo), hi)
    say(f"re-estimating {ext.name} (warm start) ...")
    warm = candidate.get("result") or nominal
    res, tried = _estimate_retrying(estimator, ext, data, say, initial=init, start=warm)
    if not res.success:
        return res, None, tried
    sh = shrink(nominal, res, validation, library.initial_state, nm, sel)
    sh.setdefault("validation", None)
    return res, sh, tried


def _verbose(estimator: Callable, on: bool) -> Callable:
    """``estimator`` with ``verbose=True`` (a progress line per Newton iteration) when ``on`` and it
    takes that option (the built-in ones pass ``**options`` to :func:`estimate`)."""
    params = inspect.signature(estimator).parameters.values()
    if not on or not any(p.kind is inspect.Parameter.VAR_KEYWORD or p.name == "verbose" for p in params):
        return estimator
    return lambda *args, **kw: estimator(*args, verbose=True, **kw)


# =============================================================================== libraries
def generic_library(model: IdentificationModel) -> Library:
    """Effects any model has: a constant offset on each measured channel (``offset_<channel>``)."""
    effects = []
    for row, ch in model.channels.items():
        p = f"offset_{ch}"
        if p in model.names or p in model.inputs:
            continue

        def term(v, _row=row, _p=p):
            return {_row: v[_p]}
        effects.append(Effect(name=f"offset_{ch}", equations=[row], parameters={p: 0.0}, term=term,
                              description=f"constant offset of the {ch} sensor", scale={p: 1.0}))
    return Library(name="generic", effects=effects)


#: model name (or prefix before '[') → "module:factory(model) -> Library"
BUILTIN_LIBRARIES = {
    "flexible": "manipulators.effects:library",
    "flexible_friction": "manipulators.effects:library",
    "msd": "manipulators.effects:library",
    "confined": "mixtures.effects:library",
}


def _as_library(obj, model: IdentificationModel, name: str) -> Library:
    if isinstance(obj, Library):
        return obj
    if isinstance(obj, Effect):
        return Library(name=name, effects=[obj])
    if isinstance(obj, (list, tuple)) and all(isinstance(e, Effect) for e in obj):
        return Library(name=name, effects=list(obj))
    if callable(obj):
        return _as_library(obj(model), model, name)
    raise ValueError(f"{name}: not a Library, a list of Effects or a function returning one")


def library_for(model: IdentificationModel) -> Library:
    """The candidate library of a model: ``model.settings["diagnosis_library"]`` if set, else the
    built-in one for its name (:data:`BUILTIN_LIBRARIES`), else :func:`generic_library`."""
    own = model.settings.get("diagnosis_library")
    if own is not None:
        return _as_library(own, model, f"{model.name} (model settings)")
    base = model.settings.get("nominal_model", model.name).split("[")[0]
    spec = BUILTIN_LIBRARIES.get(base)
    if spec is not None:
        return resolve_library(spec, model)
    return generic_library(model)


def resolve_library(spec: str, model: IdentificationModel) -> Library:
    """A library from ``path/to/file.py:object`` / ``package.module:object`` (a Library, a list of
    Effects, or a function of the model returning one)."""
    from .models import load_object
    return _as_library(load_object(spec), model, spec)


# =============================================================================== command line
def _module_of(spec: str):
    """The module an import spec's object lives in (already imported by :func:`resolve_model`)."""
    import importlib
    import sys as _sys

    from .models import BUILTIN
    target, sep, _ = BUILTIN.get(spec, spec).rpartition(":")
    if not sep:
        return None
    if target.endswith(".py") or "/" in target or "\\" in target:
        path = Path(target).resolve()
        for mod in list(_sys.modules.values()):
            f = getattr(mod, "__file__", None)
            if f and Path(f).resolve() == path:
                return mod
        return None
    try:
        return importlib.import_module(target)
    except Exception:  # noqa: BLE001
        return None


def run_cli(args) -> int:
    """``shootlab diagnose``: every input is checked before any work; the output folder receives
    the results only when the diagnosis is complete (:func:`write_report`)."""
    from .cli import _load_data
    from .models import parse_assignments, parse_initial, resolve_model
    from .outputs import check_output_folder

    say = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    check_output_folder(args.out)
    model = resolve_model(args.model, parse_assignments(args.option, "--option"))
    initial = parse_initial(getattr(args, "initial", None), model)
    points = getattr(args, "points", None)
    if initial or points:
        if points is not None and points < 2:
            raise ValueError(f"--points {points}: need at least 2 shooting points")
        model = replace(model, prior=dict(model.prior, **initial),
                        settings=dict(model.settings, **({"points": points} if points else {})))
    data = _load_data(args.data, needed=model.measured)
    validation = None
    if args.validate:
        try:
            validation = _load_data(args.validate, "--validate", needed=model.measured)
        except ValueError as exc:
            raise ValueError(f"validation data {args.validate}: {exc}") from None
    if args.library:
        library = resolve_library(args.library, model)
    else:
        mod = _module_of(args.model)
        own = getattr(mod, "diagnosis_library", None) if mod is not None else None
        library = _as_library(own, model, f"{args.model} (diagnosis_library)") if own is not None else library_for(model)
    effects = [e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else None
    say(f"diagnosing {model.name} on {args.data} ({data.t.size} samples) with the library {library.name!r}: "
        + ", ".join(library.names))
    diag = diagnose(model, data, library, validation=validation, effects=effects, seed=args.seed,
                    log=None if args.quiet else say)
    info = write_report(diag, args.out, plots=not args.no_plots)
    print(diag.verdict)
    print(f"status: {diag.status}; selected: {', '.join(diag.selected) or 'none'}; wrote "
          f"{Path(args.out) / 'diagnosis.json'}, report.md"
          + (", " + ", ".join(info.get("figures", [])) if info.get("figures") else ""))
    return 0 if diag.success else 1


# =============================================================================== report
def write_report(diag: Diagnosis, out: str | Path, plots: bool = True) -> dict:
    """``diagnosis.json``, ``report.md`` and the figures, written to a temporary folder next to
    ``out`` and moved into ``out`` only when all are complete (an interrupted run leaves nothing
    that looks like a result)."""
    from .outputs import staged_folder

    with staged_folder(out) as tmp:
        info = diag.to_dict()
        figures = _figures(diag, tmp) if plots else []
        info["figures"] = figures
        (tmp / "report.md").write_text(_markdown(info))
        (tmp / "diagnosis.json").write_text(json.dumps(info, indent=2))
    return info


def _fmt(v, spec=".3g"):
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def _markdown(info: dict) -> str:
    L = [f"# Diagnosis of `{info['model']}`", "", f"**{info['verdict']}**", ""]
    nom, ext = info["nominal"], info["extended"]
    L.append(f"Nominal estimate: J = {_fmt(nom['J'], '.5g')}, " + ", ".join(f"{k} = {_fmt(v, '.5g')}" for k, v in nom["parameters"].items()))
    if ext and ext.get("effects"):
        L.append(f"\nExtended ({ext['model']}): J = {_fmt(ext['J'], '.5g')}, " + ", ".join(f"{k} = {_fmt(v, '.5g')}" for k, v in ext["parameters"].items()))
    L += ["", "## Where", "", "| residual | share of J | rms / floor rms | p | significant | windows |", "|---|---|---|---|---|---|"]
    for w in info["where"]:
        if w["share"] is not None and w["share"] < 0.001 and not w["significant"]:
            continue
        wins = ", ".join(f"[{a:.3g}, {b:.3g}]" for a, b in w["windows"][:4]) + (" …" if len(w["windows"]) > 4 else "")
        ratio = w.get("ratio")
        L.append(f"| {w['equation']} | {100 * w['share']:.1f} % | {_fmt(math.sqrt(ratio) if ratio else None)} | "
                 f"{_fmt(w.get('p_value'), '.2g')} | {'yes' if w['significant'] else 'no'} | {wins} |")
    L += ["", "## Which", "", "| effect | explains | confidence | parameters |", "|---|---|---|---|"]
    for r in info["ranking"][:8]:
        L.append(f"| {r['effect']} | {100 * r['score']:.1f} % | {r['confidence']:.2f} | "
                 + ", ".join(f"{k} = {_fmt(v, '.4g')}" for k, v in r["parameters"].items()) + " |")
    L.append(f"\nSelected: {', '.join(info['selected']) or 'none'}")
    sh = info.get("shrink")
    if sh:
        L += ["", "## How far it shrinks", "", "| measure | before | after | shrink |", "|---|---|---|---|"]
        idn = sh.get("identification")
        if idn:
            L.append(f"| J (identification) | {_fmt(idn['before'])} | {_fmt(idn['after'])} | {_fmt(idn['shrink'], '.2f')} |")
            for r, d in idn["per_channel"].items():
                L.append(f"| residual energy {r} | {_fmt(d['before'])} | {_fmt(d['after'])} | {_fmt(d['shrink'], '.2f')} |")
        val = sh.get("validation")
        if val:
            L.append(f"| validation free-run misfit (relative RMS) | {_fmt(val['before'])} | {_fmt(val['after'])} | "
                     f"{_fmt(val['shrink'], '.2f')} |")
            L.append(f"| — above the noise | {_fmt(val.get('before_above_noise'))} | {_fmt(val.get('after_above_noise'))} | "
                     f"{_fmt(val.get('shrink_above_noise'), '.2f')} |")
            for ch, d in val["per_channel"].items():
                L.append(f"| validation RMS {ch} | {_fmt(d['before'])} | {_fmt(d['after'])} | {_fmt(d['shrink'], '.2f')} |")
    if info.get("notes"):
        L += ["", "## Notes", ""] + [f"- {n}" for n in info["notes"]]
    if info.get("figures"):
        L += ["", "## Figures", ""] + [f"![{f}]({f})" for f in info["figures"]]
    return "\n".join(L) + "\n"


def _figures(diag: Diagnosis, out: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .outputs import plot_samples, residual_label, time_label

    files = []
    res, model = diag.nominal, diag.model
    if not res.success:                      # an unestimated model is not drawn
        return files
    t = res.t.numpy()
    # 1. residuals over time with the flagged windows and the floor band
    rows = [w for w in diag.where if w["kind"] != "dynamics"]
    fig, axes = plt.subplots(len(rows), 1, figsize=(8, 1.7 * len(rows) + 0.6), sharex=True, squeeze=False)
    for ax, w in zip(axes[:, 0], rows):
        xi = res.xi[w["equation"]].numpy()
        ax.plot(t, xi, lw=0.8, color="tab:red" if w["significant"] else "0.4", label="nominal")
        if diag.extended is not None and diag.extended.success:
            ax.plot(diag.extended.t.numpy(), diag.extended.xi[w["equation"]].numpy(), lw=0.7, color="tab:blue",
                    alpha=0.8, label="extended")
        fr = w.get("floor_rms")
        if fr:
            ax.axhspan(-2 * fr, 2 * fr, color="tab:green", alpha=0.15, label="±2 floor rms")
        for a, b in w["windows"]:
            ax.axvspan(a, b, color="gold", alpha=0.3)
        ax.set_ylabel(residual_label(model, w['equation']), fontsize=8)
        ax.set_title(f"{w['equation']}: {100 * w['share']:.1f} % of J, rms/floor {_fmt(math.sqrt(w['ratio']) if w.get('ratio') else None)}"
                     + (" — significant" if w["significant"] else ""), fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel(time_label(model))
    fig.suptitle(f"{model.name}: residuals per row (shaded: flagged windows)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "residuals.png", dpi=100)
    plt.close(fig)
    files.append("residuals.png")
    # 2. residual vs the top signatures: partial residuals (the residual the candidate leaves after its
    #    re-estimation, plus the candidate's own term) against the candidate's variable
    which = diag.which
    top = which.get("ranking", [])[:3]
    if top:
        fig, axes = plt.subplots(1, len(top), figsize=(4.3 * len(top), 3.7), squeeze=False)
        for ax, r in zip(axes[0], top):
            e = diag.library[r["effect"]]
            row = e.equations[0]
            m = next((mm for mm in which.get("models", []) if mm["effects"] == [e.name]), None)
            res_e = m.get("result") if m else None
            if res_e is None:
                ax.set_axis_off()
                continue
            em = res_e.problem.model
            x = torch.stack([res_e.x[n] for n in em.names], -1)
            z = torch.stack([res_e.zeta[n] for n in model.inputs], -1)
            with torch.no_grad():
                v = _vars(model, em.names, x, z, res_e.t, _channel_fn(diag.data, list(e.channels)))
                contrib = _rows_sum(model, [e], v, res_e.t.shape)[:, model.equations.index(row)].numpy()
                xv = e.variable[1](v).numpy() if e.variable else contrib
            partial = res_e.xi[row].numpy() + contrib
            ax.plot(xv, partial, ".", ms=2, color="0.45", alpha=0.6, label=f"partial residual {row}")
            order = np.argsort(xv)
            ax.plot(xv[order], contrib[order], "-", color="tab:red", lw=1.4, label=f"{e.name} term")
            ax.axhline(0.0, color="0.7", lw=0.5)
            xname = e.variable[0] if e.variable else f"{e.name} term"
            xunit = model.units.get(xname.split(" ")[0]) if e.variable else None     # 'v (estimated)' → v's unit
            ax.set_xlabel(xname + (f" [{xunit}]" if xunit else ""), fontsize=8)
            ax.set_ylabel(f"{residual_label(model, row)} + term (re-estimated)", fontsize=8)
            ax.set_title(f"{r['effect']}: explains {100 * r['score']:.0f} % of J, confidence {r['confidence']:.2f}",
                         fontsize=8)
            ax.legend(fontsize=7)
        fig.suptitle("residual vs the top candidate signatures (partial residuals after each candidate's "
                     "linearised re-estimation)", fontsize=9)
        fig.tight_layout()
        fig.savefig(out / "signatures.png", dpi=100)
        plt.close(fig)
        files.append("signatures.png")
    # 3. validation before/after
    val = (diag.shrink or {}).get("validation")
    if val is not None and diag.validation is not None:
        preds = val.get("predictions", {})
        chans = [c for c in model.measured if c not in model.given]
        fig, axes = plt.subplots(len(chans), 1, figsize=(8, 2.2 * len(chans) + 0.6), sharex=True, squeeze=False)
        for ax, ch in zip(axes[:, 0], chans):
            for key, col, lab in (("before", "tab:red", "nominal"), ("after", "tab:blue", "extended")):
                p = preds.get(key)
                if p is not None and ch in p:
                    ax.plot(p["t"], p[ch], color=col, lw=0.9, label=f"{lab} free run")
            plot_samples(ax, np.asarray(diag.validation.t), np.asarray(diag.validation.channels[ch]), f"{ch} measured")
            ax.set_ylabel(model.label(ch))
            d = val["per_channel"][ch]
            ax.set_title(f"{ch}: RMS error {_fmt(d['before'])} → {_fmt(d['after'])} (shrink {_fmt(d['shrink'], '.2f')})", fontsize=8)
            ax.legend(fontsize=7, loc="best")
        axes[-1, 0].set_xlabel(time_label(model))
        fig.suptitle("validation input: free-run simulation before / after", fontsize=10)
        fig.tight_layout()
        fig.savefig(out / "validation.png", dpi=100)
        plt.close(fig)
        files.append("validation.png")
    return files
