"""Model composition: an identification model with added terms (the diagnosis's candidate effects,
docs/design.md §4; ``docs/diagnosis.md``, "Adding an effect").

A term enters some rows of the model side of ``E z_m = f(x) + F(x) ζ + ξ`` (report eq. 2.5): the
extended model has ``f + Σ term(ζ = 0)`` and ``F + ∂term/∂ζ`` (the terms must be affine in ζ,
checked by :func:`probe_terms`), and the terms' new constant parameters are appended to x with
``θ' = ε_θ`` like the model's own (report eq. 2.4).  :func:`extend` builds that model; a term is
written with torch on the namespace of the model's rows (:class:`~shootlab.estimation.rows.Variables`:
``v.name`` for a state, parameter or input, ``v.t``, ``v.channel(name)`` for a measured channel).

Anything with the attributes of :class:`Term` can be composed; the diagnosis's
:class:`shootlab.diagnosis.Effect` is one.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable, Mapping, Protocol, Sequence

import numpy as np
import torch
from torch import Tensor

from shootlab.estimation.data import Interpolant, Measurements
from shootlab.estimation.model import IdentificationModel
from shootlab.estimation.rows import Variables, not_affine

__all__ = ["Vars", "Term", "extend", "new_parameters", "term_rows", "term_vars", "channel_reader",
           "probe_terms", "term_inputs", "extend_weight", "parameter_weight"]


#: the namespace of an effect's term: the model rows' own (``v.name``; ``v["name"]`` for a name
#: held in a string)
Vars = Variables


class Term(Protocol):
    """What :func:`extend` needs of an added term (:class:`shootlab.diagnosis.Effect` has it)."""

    name: str
    equations: Sequence[str]
    parameters: Mapping[str, float]
    term: Callable[[Vars], Mapping[str, Tensor]]
    scale: Mapping[str, float]
    channels: Sequence[str]


def new_parameters(model: IdentificationModel, effects: Sequence[Term]) -> list[str]:
    """The terms' parameter names in order (ValueError for a name the model or another term uses)."""
    names: list[str] = []
    for e in effects:
        for p in e.parameters:
            if p in model.names or p in model.inputs or p in names:
                raise ValueError(f"effect {e.name!r}: parameter name {p!r} is already used")
            names.append(p)
    return names


def term_rows(model: IdentificationModel, effects: Sequence[Term], v: Vars, shape) -> Tensor:
    """The terms summed per row of the model, shape ``(*shape, rows)`` (zero where none enters)."""
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


def term_vars(model: IdentificationModel, names: Sequence[str], x: Tensor, zeta: Tensor, t: Tensor,
              channel=None) -> Variables:
    """The :class:`~shootlab.estimation.rows.Variables` of states and parameters ``x`` (named
    ``names``), inputs ``zeta`` and the time ``t``, reading the measured channels through ``channel``."""
    values = {n: x[..., i] for i, n in enumerate(names)}
    values["t"] = t
    inputs = {n: zeta[..., j] for j, n in enumerate(model.inputs)}
    return Variables(values, inputs, channel)


def channel_reader(data: Measurements | None,
                   names: Sequence[str]) -> Callable[[str, Tensor], Tensor] | None:
    """``channel(name, at)``: the measured channels ``names`` of ``data`` interpolated at the times
    ``at`` (differentiably); None without data or channels."""
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


def probe_terms(model: IdentificationModel, effects: Sequence[Term]) -> tuple[bool, bool]:
    """Evaluate the terms on random states: (depends on ζ, affine in ζ).  KeyError for unknown names."""
    used, affine = term_inputs(model, effects)
    return bool(used), affine


def term_inputs(model: IdentificationModel, effects: Sequence[Term]) -> tuple[list[int], bool]:
    """Evaluate the terms on random states: the inputs ζ_j they depend on (indices into
    ``model.inputs``: the columns of ∂term/∂ζ = term(e_j) − term(0), as :func:`extend` forms it,
    above 1e-9 of the terms' size) and whether they are affine in ζ — term(ζ) = term(0) + ∂term/∂ζ ζ
    at two random ζ (:func:`shootlab.estimation.rows.not_affine`, the check of a declared model's
    rows).  KeyError for unknown names."""
    gen = torch.Generator().manual_seed(12345)
    names = model.names + new_parameters(model, effects)
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
    z1, z2 = (torch.randn(n, nz, generator=gen, dtype=torch.float64) for _ in range(2))

    def rows(z: Tensor) -> Tensor:
        with torch.no_grad():
            return term_rows(model, effects, term_vars(model, names, x, z, t, channel), t.shape)
    f = rows(torch.zeros_like(z1))
    eye = torch.eye(nz, dtype=torch.float64)
    F = torch.stack([rows(eye[j].expand(n, nz)) - f for j in range(nz)], -1)
    size = 1e-9 * (1.0 + float(f.abs().max()) + float(F.abs().max()))
    used = [j for j in range(nz) if float(F[..., j].abs().max()) > size]
    return used, not not_affine(rows, f, F, (z1, z2))


def extend_weight(w, n_old: int, n_new: int, fill: float):
    """A weight (vector, matrix or function of t) of ``n_old`` entries with ``n_new`` diagonal entries
    ``fill`` appended."""
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


def parameter_weight(model: IdentificationModel) -> float:
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


class _Extended:
    """f and F of a model with added terms (:func:`extend`): the model's f + Σ term and
    F + ∂term/∂ζ, and both from one evaluation of each (:meth:`IdentificationModel.f_and_F`).
    f evaluates the terms at ζ = 0 alone; F probes only the inputs they depend on."""

    def __init__(self, model: IdentificationModel, added: Callable, nx0: int, depends: bool):
        self.model, self.added, self.nx0, self.depends = model, added, nx0, depends

    def f(self, x: Tensor, t: Tensor) -> Tensor:
        return self.model.f(x[..., :self.nx0], t) + self.added(x, t, False)[0]

    def F(self, x: Tensor, t: Tensor) -> Tensor:
        base = self.model.F(x[..., :self.nx0], t)
        return base + self.added(x, t)[1] if self.depends else base

    def f_and_F(self, x: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        f, F = self.model.f_and_F(x[..., :self.nx0], t)
        term, dF = self.added(x, t)
        return f + term, (F + dF if self.depends else F)


def extend(model: IdentificationModel, effects: Sequence[Term], data=None,
           initial: Mapping[str, float] | None = None, name: str | None = None) -> IdentificationModel:
    """The model with the effects' terms added: ``f + Σ term`` and ``F + ∂term/∂ζ``, the effects'
    parameters appended to x (θ' = ε_θ like the others; weight W = the median of the model's W on
    its parameters, no prior: W_a = 0; a model whose default weights are still to be scaled by the
    data, :mod:`shootlab.estimation.weights`, gets the new ones scaled too), their initial values from
    ``initial`` or the effects, their units from the effects' ``units`` where they declare them.
    ``data`` binds the channels the effects read (needed for estimation and simulation on that
    record: bind again for another record)."""
    effects = list(effects)
    if not effects:
        return model
    new = new_parameters(model, effects)
    for e in effects:
        missing = [r for r in e.equations if r not in model.equations]
        if missing:
            raise ValueError(f"effect {e.name!r} enters rows {missing} that model {model.name!r} lacks")
    used, affine = term_inputs(model, effects)
    depends = bool(used)
    if not affine:
        raise ValueError(f"the terms of {[e.name for e in effects]} are not affine in the inputs ζ "
                         f"{model.inputs}; write them with the measured channels (v.channel) instead")
    data = Measurements.coerce(data) if data is not None else None
    chans = sorted({c for e in effects for c in e.channels})
    channel = channel_reader(data, chans)
    if chans and channel is None:
        def channel(nm, at):        # unbound: a clear error on use, not at construction
            raise ValueError(f"effects {[e.name for e in effects if e.channels]} read channel(s) {chans}: "
                             f"bind data with extend(..., data=...)")
    nx0, n_new, nz = model.nx, len(new), len(model.inputs)
    names = model.names + new
    init = {p: float(v) for e in effects for p, v in e.parameters.items()}
    init.update({k: float(v) for k, v in (initial or {}).items() if k in init})
    # the terms' F by probing the inputs they depend on: (term(e_j) − term(0)) for j in ``used``,
    # written into those columns of F
    place, columns = torch.eye(nz, dtype=torch.float64)[used], torch.tensor(used, dtype=torch.long)

    def added(x: Tensor, t: Tensor, with_F: bool = True) -> tuple[Tensor, Tensor | None]:
        t = torch.broadcast_to(t, x.shape[:-1])
        if not depends or not with_F:
            z = x.new_zeros(*x.shape[:-1], nz)
            return term_rows(model, effects, term_vars(model, names, x, z, t, channel), t.shape), None
        k = len(used)
        xb = x.unsqueeze(-2).expand(*x.shape[:-1], k + 1, x.shape[-1])
        tb = t.unsqueeze(-1).expand(*t.shape, k + 1)
        Z = torch.cat([x.new_zeros(1, nz), place.to(x)], 0).expand(*x.shape[:-1], k + 1, nz)
        out = term_rows(model, effects, term_vars(model, names, xb, Z, tb, channel), tb.shape)
        dF = (out[..., 1:, :] - out[..., :1, :]).transpose(-1, -2)
        return out[..., 0, :], (dF if k == nz else
                                dF.new_zeros(*dF.shape[:-1], nz).index_copy(-1, columns.to(x.device), dF))

    extended = _Extended(model, added, nx0, depends)

    A = torch.zeros(nx0 + n_new, nx0 + n_new, dtype=torch.float64)
    A[:nx0, :nx0] = torch.as_tensor(model.A, dtype=torch.float64)
    B = torch.zeros(nx0 + n_new, nz, dtype=torch.float64)
    B[:nx0] = torch.as_tensor(model.B, dtype=torch.float64)
    q_a = torch.cat([torch.as_tensor(model.q_a, dtype=torch.float64), torch.tensor([init[p] for p in new], dtype=torch.float64)])
    settings = model.settings.replace(refine=None, simulate=None,      # they lack the terms
                                      effects=model.settings.effects + tuple(e.name for e in effects),
                                      nominal_model=model.settings.nominal_model or model.name)
    marks = settings.weights_from_data
    if marks:           # weights still to be scaled by the data: the new parameters' as the others'
        theirs = marks["W"][len(model.states):]
        new_mark = float(np.median(theirs)) if theirs and None not in theirs else None
        settings = settings.replace(weights_from_data=dict(marks, W=list(marks["W"]) + [new_mark] * n_new))
    units = dict(model.units, **{p: u for e in effects for p, u in (getattr(e, "units", None) or {}).items()})
    return replace(model, name=name or f"{model.name}+{'+'.join(e.name for e in effects)}", units=units,
                   parameters=list(model.parameters) + new, A=A, B=B, f=extended.f, F=extended.F,
                   W=extend_weight(model.W, nx0, n_new, parameter_weight(model)),
                   W_a=extend_weight(model.W_a, nx0, n_new, 0.0), q_a=q_a,
                   prior=dict(model.prior, **{p: init[p] for p in new}), settings=settings)
