"""A model declared by names and equations, compiled to :class:`~shootlab.estimation.IdentificationModel`.

The augmented state form of docs/design.md §1 (report eqs. 2.4–2.5), x = states and
parameters, ζ = inputs::

    x' = A x + B ζ + ε                    (A, B from the map state → its derivative)
    E z_m = f(x, t) + F(x, t) ζ + ξ       (one row per equation, affine in ζ)

is written as a map ``states`` (each state's derivative: another state → an entry of A, an
input → an entry of B; parameters have θ' = ε_θ) and one torch expression per row over named
variables (:class:`Variables`)::

    model = shootlab.model(
        name="drive", states={"s": "v", "v": "a"}, inputs=["a", "u"],
        parameters={"m": 1.0, "b": 1.0, "c": 0.0},
        equations={"motion": lambda x: x.m * x.a + x.b * x.v + x.c - x.u,    # model row: 0 = …
                   "position": lambda x: x.s, "force": lambda x: x.u},      # measurement rows
        channels={"position": "s", "force": "u"})                          # row → CSV column

A row named in ``channels`` is a measurement equation (its channel's samples are E z_m), every
other row a model equation (a zero pseudo-measurement).  The compiled rows are

    f(x, t) = row(x, ζ = 0, t),      F(x, t) = ∂row/∂ζ   (exact: rows at ζ = 2^300 e_j, Rows.F)

checked at compile time to be affine in ζ (the rows at two random ζ against f + F ζ).  f and F
are batched, float64 and compose with ``torch.func`` (the engine differentiates them by forward
mode), provided the expressions use out-of-place torch operations.
"""
from __future__ import annotations

import math
import numbers
import warnings
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

from .data import Interpolant, Measurements, linear_fill
from .rows import Row, Rows, UnknownName, _columns, not_affine
from .model import IdentificationModel, smoothed
from .mechanics import declared_mechanics
from .settings import EstimationSettings

#: default weights (report §3.4, as the built-in mass–spring–damper): W on the states — their
#: equations x' = A x + B ζ are kinematic identities, held nearly exact — W on the parameters
#: (free to drift only as the data demand) and V on every row
DEFAULT_W_STATE, DEFAULT_W_PARAMETER, DEFAULT_V = 1e10, 1.0, 1.0

def _sample(states: Sequence[str], parameters: Mapping[str, float], nz: int, n: int = 5, spread: bool = False):
    """Random x (n, nx), two random ζ (n, nζ) and t (n,) for the compile-time checks: states of
    either sign, parameters moved from their defaults (a term often vanishes at a default of 0);
    ``spread``: the states' sizes spread over 1e-4 … 10."""
    gen = torch.Generator().manual_seed(20261130)

    def rand(*shape):
        return torch.rand(*shape, generator=gen, dtype=torch.float64)
    xs = (0.2 + rand(n, len(states))) * torch.where(rand(n, len(states)) < 0.5, -1.0, 1.0)
    if spread:
        xs = xs * 10.0 ** (5 * rand(n, len(states)) - 4)
    p = torch.tensor([float(v) for v in parameters.values()], dtype=torch.float64)
    xp = p + (0.3 + 0.4 * rand(n, len(p))) * torch.where(p == 0, torch.ones_like(p), p.abs())
    return torch.cat([xs, xp], -1), (rand(n, nz) - 0.5) * 4, (rand(n, nz) - 0.5) * 4, rand(n)


def _check_derivative(name: str, single: Rows, x: Tensor, t: Tensor) -> None:
    """The forward-mode derivative of the row's f + F·1 along a random direction of x against a
    central difference: an expression that leaves torch (``float()``, ``.item()``, numpy,
    ``.detach()``) evaluates but loses its derivative, which the engine needs."""
    d = torch.randn(x.shape, generator=torch.Generator().manual_seed(7), dtype=x.dtype)

    def g(xx: Tensor) -> Tensor:
        return single.f(xx, t) + single.F(xx, t).sum(-1)
    h = 1e-6 * (1 + x.abs())
    dual = torch.func.jvp(g, (x,), (d * h,))[1]
    central = (g(x + d * h) - g(x - d * h)) / 2
    ok = ~torch.isfinite(central) | ((dual - central).abs() <= 1e-4 * (central.abs() + dual.abs()) + 1e-12 * (1 + g(x).abs()))
    if not ok.all():
        raise ValueError(f"row {name!r} loses its derivative in the states and parameters (float(), .item(), "
                         f"numpy or .detach() in the expression?): write it with torch operations")


def _check_rows(rows: Rows, x: Tensor, z1: Tensor, z2: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
    """f and F at the sample, each row checked on its own: known names, one value per sample
    (k for a block), torch.func-composable, affine in ζ.  ValueError naming the row otherwise."""
    known = list(rows.x_at) + list(rows.z_at) + ["t"]
    shape = x.shape[:-1]
    with warnings.catch_warnings():     # torch's first forward-mode use scripts its decompositions
        warnings.filterwarnings("ignore", message=".*torch.jit.script.*", category=DeprecationWarning)
        torch.func.jvp(torch.sin, (x,), (x,))
    for name in rows.equations:
        single = rows.single(name)
        want = (*shape, rows.sizes[name]) if name in rows.sizes else shape
        try:
            out = rows.equations[name](rows.variables(x, z1, t))
            out = torch.as_tensor(out, dtype=torch.float64)
            if out.dim() > len(want) or any(a not in (1, b) for a, b in zip(out.shape[::-1], want[::-1])):
                what = f"{want[-1]} values per sample (the block's size)" if name in rows.sizes else \
                    f"one value per sample (the batch shape {tuple(shape)})"
                raise ValueError(f"row {name!r} returns shape {tuple(out.shape)}: {what} is needed; write it elementwise")
            _check_derivative(name, single, x, t)
        except UnknownName as exc:
            raise ValueError(f"row {name!r}: unknown name {exc.name!r}; known names: {', '.join(known)}") from None
        except ValueError:
            raise
        except Exception as exc:        # noqa: BLE001 - any failure of the user's expression
            raise ValueError(f"row {name!r} fails on batched tensors under torch.func "
                             f"(use out-of-place torch operations): {type(exc).__name__}: {exc}") from None
    with torch.no_grad():
        f, F = rows.f(x, t), rows.F(x, t)
    for i in not_affine(lambda z: rows(x, z, t), f, F, (z1, z2)):
        raise ValueError(f"row {rows.rows[i]!r} is not affine in the inputs "
                         f"{rows.inputs}: its derivative in them changes with their values")
    return f, F


# -- weights and the initial approximation ------------------------------------------------------
def _diagonal(value, names: Sequence[str], default: Sequence[float], what: str):
    """A weight (or q_a) as the model takes it: a mapping name → value over ``default`` (the
    diagonal), else the value itself (a vector, a matrix or a function of t)."""
    if not isinstance(value, Mapping):
        return default if value is None else value
    bad = sorted(set(value) - set(names))
    if bad:
        raise ValueError(f"{what} names {bad}, which are not among {list(names)}")
    return [float(value.get(n, d)) for n, d in zip(names, default)]


def _left_to_defaults(value, names: Sequence[str], default: Sequence[float]) -> list[float | None]:
    """Per entry, its dimensionless default where the weight ``value`` leaves it to the default
    (None, or a mapping that does not name it), else None (given by the user)."""
    if value is None:
        return list(default)
    if isinstance(value, Mapping):
        return [None if n in value else d for n, d in zip(names, default)]
    return [None] * len(names)


def _initial_states(states: Mapping[str, str], x_at: Mapping[str, int | slice], measured: Mapping[str, str],
                    window: int) -> Callable[[Measurements, Tensor], Tensor]:
    """Initial approximation of the states (module :func:`model`): a state that a measurement row
    equals from its channel, a state that is the derivative of an approximated one by
    Savitzky–Golay differentiation (:func:`~shootlab.estimation.smoothed`), the rest zero; across
    a missing sample of a channel by linear interpolation (:func:`~shootlab.estimation.data.linear_fill`)."""

    def initial(data: Measurements, t: Tensor) -> Tensor:
        ts = torch.as_tensor(data.t, dtype=t.dtype)
        cols = {s: torch.as_tensor(linear_fill(data.t, data.channels[c]), dtype=t.dtype) for s, c in measured.items()}
        grown = True
        while grown:
            grown = False
            for s, d in states.items():
                if s in cols and d in states and d not in cols:
                    cols[d] = smoothed(cols[s], ts, deriv=1, window=window)
                    grown = True
        out = t.new_zeros(t.numel(), sum(len(_columns(x_at[s])) for s in states))
        if cols:
            names = [s for s in states if s in cols]
            ip = Interpolant(Measurements(data.t, {s: cols[s].numpy() for s in names}), names, t.dtype, t.device)
            vals = ip.values(t)
            for j, s in enumerate(names):
                out[:, x_at[s]] = vals[:, j]
        return out
    return initial


# -- the declaration ----------------------------------------------------------------------------
def model(name: str, states: Mapping[str, str], inputs: Sequence[str], parameters: Mapping[str, float],
          equations: Mapping[str, Row], channels: Mapping[str, str] | Sequence[str], *,
          W=None, V=None, W_a=None, q_a=None, given: Sequence[str] | None = None,
          units: Mapping[str, str] | None = None, bounds: Mapping[str, tuple[float, float]] | None = None,
          settings: EstimationSettings | None = None, blocks: Mapping[str, int | Sequence] | None = None,
          initial_states: Callable[[Measurements, Tensor], Tensor] | None = None,
          mechanics: Mapping[str, object] | None = None,
          F: Callable[[Tensor, Tensor], Tensor] | None = None) -> IdentificationModel:
    """Compile a declared model (module docstring) to an :class:`IdentificationModel`.

    The model x' = A x + B ζ + ε, E z_m = f(x, t) + F(x, t) ζ + ξ (report eqs. 2.4–2.5): A and B
    from ``states``, f the rows at ζ = 0 and F = ∂rows/∂ζ, exact for rows affine in ζ.

    Parameters
    ----------
    name : str
        The model's name (summaries, file names).
    states : mapping of str to str
        State → its derivative: the name of another state (an entry 1 of A) or of an input (an
        entry 1 of B).  x is the states in this order, then the parameters.
    inputs : sequence of str
        The names of ζ, in order.
    parameters : mapping of str to float
        Parameter → default initial value (the model's ``prior``); θ' = ε_θ.
    equations : mapping of str to callable
        Row → ``lambda x: …``, a torch expression over :class:`Variables` (states, parameters,
        inputs and ``t`` by name), affine in the inputs.
    channels : mapping of str to str, or sequence of str
        Measurement row → data column (a list: rows named as their columns); the other rows are
        model equations, zero pseudo-measurements.
    W, V : mapping, tensor or callable, optional
        Weights of eq. 2.6: a mapping name → weight over the defaults, or the full vector, matrix
        or function of t that :class:`IdentificationModel` takes.  The defaults are the report's
        (§3.4: W 1e10 on every state, 1 on every parameter, V 1 on every row) read as
        dimensionless: divided by the square of each variable's and row's scale on the data when
        estimated (:mod:`shootlab.estimation.weights`), so that the model estimates the same in
        any consistent units.
    W_a, q_a : mapping or tensor, optional
        Prior on x(a) (default none: W_a = 0).
    given : sequence of str, optional
        Channels known when the model is simulated; default those whose row is free of the
        states and depends on an input (e.g. a measured motor force).
    units : mapping of str to str, optional
        Unit per name (``"t"``, variables, rows, channels) for labels and summaries; a
        measurement row that reads one state or input (``lambda x: x.s``) and its channel take
        that variable's unit unless given.
    bounds : mapping of str to (float, float), optional
        (low, high) per state or parameter that the Newton iterates keep strictly inside.
    settings : EstimationSettings, optional
        Default: 101 points, RK4 ×10.
    blocks : mapping of str to int or sequence, optional
        Name → number of components (labels 1 … k) or their labels, for a state, input or model
        row that is a vector (the nodes of a finite-element mesh): ``x.s`` is then a (…, k)
        tensor, a block row returns (…, k), and the components are named ``s1 … sk``
        (``s{label}``).  A state and its derivative are blocks of the same labels; a single
        variable next to a block broadcasts as ``x.m[..., None]``.  F is then probed in groups
        of inputs that share no row, found from f and F at 64 random samples
        (:meth:`Rows.pattern`): an input coefficient or a row nonzero only in a small region of
        the states would be missed, so such a model is declared without blocks.
    initial_states : callable, optional
        ``(data, t) -> (m, n_states)``; default: a state that a measurement row equals from its
        channel, a state that is its derivative by Savitzky–Golay differentiation
        (``settings.smoothing``), every other state 0.
    mechanics : mapping, optional
        For the diagnosis's mechanical library (:mod:`shootlab.diagnosis.mechanical`):
        ``motion`` (the equation-of-motion row), ``velocity`` (its velocity state, whose
        derivative is an input), ``command`` (the measured channel of the driving force),
        optionally ``deflection`` and ``stiffness`` (a spring's state and parameter) and
        ``friction_width`` (the smooth sign's half-width; default from the record).
    F : callable, optional
        ``(x, t) -> (…, r, nζ)``: ∂rows/∂ζ written out (a mesh's assembled matrices cost fewer
        torch operations than probing its rows); checked against the rows' own F at random
        samples (to 1e-12), which stay the model's definition.

    Returns
    -------
    IdentificationModel
        The compiled model, for :func:`shootlab.estimate`, :func:`shootlab.diagnose` and the
        command line (``--model file.py:object``).

    Raises
    ------
    ValueError
        Every mistake in the declaration, in one line naming what is wrong: an unknown name, a
        derivative that is neither a state nor an input, a row not affine in the inputs or one
        that loses its derivative, an input that enters no row, a block of the wrong size.
    """
    F_given = F
    states, inputs, parameters = dict(states), list(inputs), dict(parameters)
    names = list(states) + list(parameters)
    _check_names(states, inputs, parameters)
    if not equations:
        raise ValueError("a model needs at least one equation row")
    if not inputs:
        raise ValueError("a model needs at least one input ζ (e.g. the acceleration its equation of motion determines)")
    channels = {c: c for c in channels} if not isinstance(channels, Mapping) else dict(channels)
    for row, column in channels.items():
        if row not in equations:
            raise ValueError(f"channel {column!r} is given for row {row!r}, which is not an equation "
                             f"row ({', '.join(equations)})")
    blocks = _blocks(blocks, states, inputs, parameters, equations, channels)
    rows = Rows(equations, names, inputs, blocks)
    nx, nz = len(rows.names), len(rows.inputs)
    A, B = torch.zeros(nx, nx, dtype=torch.float64), torch.zeros(nx, nz, dtype=torch.float64)
    for s, d in states.items():
        if d not in states and d not in inputs:
            raise ValueError(f"state {s!r}: its derivative {d!r} is neither a state ({', '.join(states)}) "
                             f"nor an input ({', '.join(inputs)})")
        if (s in blocks or d in blocks) and list(blocks.get(s, [])) != list(blocks.get(d, [])):
            raise ValueError(f"state {s!r} and its derivative {d!r} must be blocks of the same components")
        i, j = _columns(rows.x_at[s]), _columns((rows.x_at if d in states else rows.z_at)[d])
        (A if d in states else B)[i, j] = 1.0
    x, z1, z2, t = _sample(rows.names[:nx - len(parameters)], parameters, nz)
    f, F = _check_rows(rows, x, z1, z2, t)
    if blocks:              # a mesh's rows: probe the inputs in groups (Rows.F, Rows.pattern)
        xs, _, _, ts = _sample(rows.names[:nx - len(parameters)], parameters, nz, n=64, spread=True)
        with torch.no_grad():
            rows.pattern(torch.cat([f, rows.f(xs, ts)]), torch.cat([F, rows.F(xs, ts)]))
    F_of = rows.F if F_given is None else _checked_F(F_given, rows, x, t, spread=(rows.names[:nx - len(parameters)], parameters))
    unused = [u for j, u in enumerate(rows.inputs) if not (F[..., j] != 0).any()]
    if unused:
        raise ValueError(f"input(s) {unused} enter no equation row: every input needs a row that determines it")
    measured, units = {}, dict(units or {})
    for row, column in channels.items():
        i = rows.row_at[row]
        read = None                     # the variable the row reads, if it is one state or one input
        if not F[:, i].any():
            same = [s for s in states if s not in blocks and torch.equal(f[:, i], x[:, rows.x_at[s]])]
            if same:
                measured.setdefault(same[0], column)
                read = same[0]
        elif not f[:, i].any():
            ones = [u for j, u in enumerate(rows.inputs) if bool((F[:, i, j] == 1).all())]
            if len(ones) == 1 and int((F[:, i] != 0).sum()) == F.shape[0]:
                read = ones[0]
        if read is not None and units.get(read) and column not in units:    # a channel and its row in the
            # unit of what they read, unless the channel declares its own
            units.setdefault(row, units[read])
            units.setdefault(column, units[row])
    if given is None:
        given = [c for r, c in channels.items() if F[:, rows.row_at[r]].any() and not f[:, rows.row_at[r]].any()]
    settings = settings if settings is not None else EstimationSettings()
    if not isinstance(settings, EstimationSettings):
        raise ValueError(f"settings must be an EstimationSettings, got {type(settings).__name__}")
    names, equations_ = rows.names, rows.rows
    w_defaults = [DEFAULT_W_STATE] * (nx - len(parameters)) + [DEFAULT_W_PARAMETER] * len(parameters)
    v_defaults = [DEFAULT_V] * len(equations_)
    marks = {"W": _left_to_defaults(W, names, w_defaults), "V": _left_to_defaults(V, equations_, v_defaults)}
    compiled = settings.replace(
        # the entries left to the defaults are scaled by the data when estimated (shootlab.estimation.weights)
        weights_from_data=marks if any(m is not None for m in marks["W"] + marks["V"]) else None)
    if mechanics is not None:
        x0, _, _, t0 = _sample(names[:nx - len(parameters)], {}, nz)
        x0 = torch.cat([x0, torch.tensor([float(v) for v in parameters.values()], dtype=x0.dtype).expand(x0.shape[0], -1)], -1)
        with torch.no_grad():
            F0 = rows.F(x0, torch.zeros_like(t0))     # at the default parameters: the signs
        compiled = compiled.replace(mechanics=declared_mechanics(dict(mechanics), states, rows, channels, F0))
    return IdentificationModel(
        name=name, states=names[:nx - len(parameters)], parameters=list(parameters), inputs=rows.inputs,
        equations=equations_, channels=channels, A=A, B=B, f=rows.f, F=F_of,
        W=_diagonal(W, names, w_defaults, "W"),
        V=_diagonal(V, equations_, v_defaults, "V"),
        W_a=_diagonal(W_a, names, [0.0] * nx, "W_a") if W_a is not None else None,
        q_a=_diagonal(q_a, names, [0.0] * nx, "q_a") if q_a is not None else None,
        prior={p: float(v) for p, v in parameters.items()}, given=list(given),
        initial_states=initial_states or _initial_states(states, rows.x_at, measured, int(settings.smoothing)),
        settings=compiled, units=units, bounds=dict(bounds or {}))


def _checked_F(given: Callable[[Tensor, Tensor], Tensor], rows: Rows, x: Tensor, t: Tensor, spread) -> Callable:
    """``given`` (:func:`model`'s ``F``) after checking it against the rows' own F at the
    compile-time samples and 64 more with spread states: ValueError naming the first entry off."""
    xs, _, _, ts = _sample(*spread, len(rows.inputs), n=64, spread=True)
    for xx, tt in ((x, t), (xs, ts)):
        with torch.no_grad():
            want, got = rows.F(xx, tt), torch.as_tensor(given(xx, tt))
        if got.shape != want.shape:
            raise ValueError(f"F returns shape {tuple(got.shape)}; the rows' F has {tuple(want.shape)}")
        ok = ((got - want).abs() <= 1e-12 * (1 + want.abs())) | (~torch.isfinite(want) & ~torch.isfinite(got))
        if not ok.all():
            k, i, j = (~ok).nonzero()[0].tolist()
            raise ValueError(f"F differs from the rows' derivative in the inputs: ∂{rows.rows[i]}/∂{rows.inputs[j]} "
                             f"is {float(got[k, i, j]):.6g}, the rows give {float(want[k, i, j]):.6g}")
    return given


def _blocks(blocks, states: Mapping[str, str], inputs: Sequence[str], parameters: Mapping[str, float],
            equations: Mapping[str, Row], channels: Mapping[str, str]) -> dict[str, list[str]]:
    """``blocks`` (name → size or component labels) checked: states, inputs or model rows only,
    each component name new."""
    out = {}
    for n, spec in dict(blocks or {}).items():
        if n not in states and n not in inputs and n not in equations:
            raise ValueError(f"block {n!r} is not a state, input or equation row (parameters are single numbers)")
        if n in channels:
            raise ValueError(f"block {n!r} is a measurement row: a channel is one row")
        labels = list(range(1, int(spec) + 1)) if isinstance(spec, numbers.Integral) and not isinstance(spec, bool) \
            else list(spec)
        if not labels:
            raise ValueError(f"block {n!r} has no components")
        out[n] = [str(label) for label in labels]
    seen = set(states) | set(inputs) | set(parameters) | set(equations)
    for n, labels in out.items():
        clash = sorted(({f"{n}{label}" for label in labels} & (seen - {n})) | ({"t"} & {f"{n}{label}" for label in labels}))
        if clash or len(set(labels)) < len(labels):
            raise ValueError(f"block {n!r}: its components {clash or 'repeat a label'} clash with other names")
    return out


def _check_names(states: Mapping[str, str], inputs: Sequence[str], parameters: Mapping[str, float]) -> None:
    seen: dict[str, str] = {}
    for kind, group in (("state", states), ("input", inputs), ("parameter", parameters)):
        for n in group:
            if not isinstance(n, str) or not n:
                raise ValueError(f"{kind} names must be non-empty strings, got {n!r}")
            if n == "t":
                raise ValueError(f"{kind} {n!r}: the name t is the time")
            if n in seen:
                raise ValueError(f"{n!r} is declared twice (as a {seen[n]} and as a {kind})")
            seen[n] = kind
    for p, v in parameters.items():
        if not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise ValueError(f"parameter {p!r}: its default must be a finite number, got {v!r}")
