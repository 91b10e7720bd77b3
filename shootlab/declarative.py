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

    f(x, t) = row(x, ζ = 0, t),      F(x, t) = ∂row/∂ζ   (exact: rows at ζ = 2^300 e_j, _Rows.F)

checked at compile time to be affine in ζ (the rows at two random ζ against f + F ζ).  f and F
are batched, float64 and compose with ``torch.func`` (the engine differentiates them by forward
mode), provided the expressions use out-of-place torch operations.
"""
from __future__ import annotations

import copy
import math
import numbers
import warnings
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

from .data import Interpolant, Measurements
from .estimation import IdentificationModel, smoothed
from .settings import EstimationSettings
from .weights import FROM_DATA

#: default weights (report §3.4, as the built-in mass–spring–damper): W on the states — their
#: equations x' = A x + B ζ are kinematic identities, held nearly exact — W on the parameters
#: (free to drift only as the data demand) and V on every row
DEFAULT_W_STATE, DEFAULT_W_PARAMETER, DEFAULT_V = 1e10, 1.0, 1.0

Row = Callable[["Variables"], "Tensor | float"]


class UnknownName(AttributeError):
    """A row asked :class:`Variables` for a name the model does not declare."""

    def __init__(self, name: str, known: Sequence[str]):
        super().__init__(f"no variable named {name!r}; known names: {', '.join(known)}")
        self.name, self.known = name, list(known)


class Variables:
    """What a row expression sees: ``x.name`` (or ``x["name"]``) is a state, parameter or input
    as a tensor of the batch shape, ``x.t`` the time (same shape)."""

    __slots__ = ("_values",)

    def __init__(self, values: Mapping[str, Tensor]):
        object.__setattr__(self, "_values", values)

    def __getattr__(self, name: str) -> Tensor:
        if name.startswith("__"):                    # copy, pickle, … probe dunders
            raise AttributeError(name)
        return self[name]

    def __getitem__(self, name: str) -> Tensor:
        try:
            return self._values[name]
        except KeyError:
            raise UnknownName(name, list(self._values)) from None

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def __setattr__(self, name, value):
        raise AttributeError("Variables are read-only")


# -- the rows ----------------------------------------------------------------------------------
def _layout(names: Sequence[str], blocks: Mapping[str, Sequence[str]]) -> tuple[list[str], dict[str, int | slice]]:
    """The components of the declared ``names`` (a block ``s`` of labels 2, 3 → ``s2, s3``) and
    where each name sits among them: a column (int) or a block of columns (slice)."""
    expanded, where = [], {}
    for n in names:
        if n in blocks:
            where[n] = slice(len(expanded), len(expanded) + len(blocks[n]))
            expanded += [f"{n}{label}" for label in blocks[n]]
        else:
            where[n] = len(expanded)
            expanded.append(n)
    return expanded, where


class _Rows:
    """The row expressions evaluated on x (…, nx), ζ (…, nζ), t: f, F (module docstring).  A
    block (``blocks``) is one variable or row of several components: a (…, k) tensor."""

    def __init__(self, equations: Mapping[str, Row], names: Sequence[str], inputs: Sequence[str],
                 blocks: Mapping[str, Sequence[str]] | None = None):
        blocks = dict(blocks or {})
        self.equations = dict(equations)
        self.names, self.x_at = _layout(names, blocks)
        self.inputs, self.z_at = _layout(inputs, blocks)
        self.rows, self.row_at = _layout(list(self.equations), blocks)
        self.sizes = {r: len(blocks[r]) for r in self.equations if r in blocks}

    def variables(self, x: Tensor, zeta: Tensor, t) -> Variables:
        """The namespace of the rows: x's and ζ's columns (and blocks) by name, and t, all of the
        batch shape x.shape[:-1] (a block's components last)."""
        batch = x.shape[:-1]
        values = {n: x[..., j] for n, j in self.x_at.items()}
        values.update((n, zeta[..., j]) for n, j in self.z_at.items())
        t = t if isinstance(t, Tensor) and t.shape == batch else \
            torch.broadcast_to(torch.as_tensor(t, dtype=x.dtype, device=x.device), batch)
        values["t"] = t
        return Variables(values)

    def row(self, name: str, v: Variables, batch) -> Tensor:
        """The row ``name`` as (…, k): k = 1 for a single row, its size for a block."""
        out = self.equations[name](v)
        out = out if isinstance(out, Tensor) else torch.as_tensor(out, dtype=v.t.dtype, device=v.t.device)
        if name not in self.sizes:
            out = out.unsqueeze(-1)
        shape = (*batch, self.sizes.get(name, 1))
        return out if out.shape == shape else torch.broadcast_to(out, shape)

    def __call__(self, x: Tensor, zeta: Tensor, t, skip: frozenset = frozenset()) -> Tensor:
        v, batch = self.variables(x, zeta, t), x.shape[:-1]
        return torch.cat([x.new_zeros(*batch, self.sizes.get(r, 1)) if r in skip else self.row(r, v, batch)
                          for r in self.equations], -1)

    #: rows that vanish at ζ = 0 (found with :meth:`pattern`), which :meth:`f` does not evaluate
    zero_f: frozenset = frozenset()

    def f(self, x: Tensor, t: Tensor) -> Tensor:
        """Rows at ζ = 0: (…, r)."""
        return self(x, x.new_zeros(*x.shape[:-1], len(self.inputs)), t, self.zero_f)

    def single(self, name: str) -> "_Rows":
        """The row (or block) ``name`` alone, over the same variables."""
        out = copy.copy(self)
        out.equations = {name: self.equations[name]}
        return out

    #: the size of the probing inputs of :meth:`F`: a power of two (scaling by it is exact)
    SCALE = 2.0 ** 300

    def F(self, x: Tensor, t: Tensor) -> Tensor:
        """∂rows/∂ζ: (…, r, nζ) of rows affine in ζ, as (row(S e_j) − row(0)) / S for every input
        j in one batched evaluation, S = :attr:`SCALE`.  Exact where a difference with unit
        inputs would cancel digits: S F_j swamps the ζ-free part of the row (it is absorbed in
        the rounding unless |f| > 2^247 |F_j|), and multiplying or dividing by a power of two is
        exact — the values equal the hand-written F's bit for bit (measured: msd, tests), at a
        tenth of the cost of a forward-mode derivative per input.

        With a sparsity :meth:`pattern`, inputs whose columns share no row are probed together
        (one probe per group, Curtis, Powell & Reid 1974): each row then sees one input of the
        group, so the entries are as exact as one probe per input, at a fraction of the probes
        (the confined mixture model of N elements: at most 6 probes instead of 2N + 2)."""
        nz, batch = len(self.inputs), x.shape[:-1]
        tb = torch.broadcast_to(torch.as_tensor(t, dtype=x.dtype, device=x.device), batch).unsqueeze(-1)
        if self.colors is None:
            Z = torch.eye(nz, dtype=x.dtype, device=x.device)
        else:
            colors = self.colors.to(x.device)
            Z = (colors == torch.arange(int(colors.max()) + 1, device=x.device)[:, None]).to(x.dtype)
        Z = torch.cat([x.new_zeros(1, nz), self.SCALE * Z], 0)
        out = self(x.unsqueeze(-2).expand(*batch, len(Z), x.shape[-1]), Z.expand(*batch, *Z.shape), tb)
        probes = ((out[..., 1:, :] - out[..., :1, :]) / self.SCALE).transpose(-1, -2)     # (…, r, groups)
        if self.colors is None:
            return probes
        # entry (i, j) is row i's response to input j's group where the pattern has it, else the
        # appended zero: one gather writes F
        probes = torch.cat([probes, probes.new_zeros(*probes.shape[:-1], 1)], -1)
        return torch.gather(probes, -1, self.entries.to(x.device).expand(*probes.shape[:-1], nz))

    colors: Tensor | None = None
    entries: Tensor | None = None

    def pattern(self, f: Tensor, F: Tensor) -> None:
        """Group the inputs for :meth:`F` by the nonzeros of F at samples (…, r, nζ): a greedy
        colouring of the columns in which no two columns of a colour share a row.  A non-finite
        entry counts as a nonzero.  The rows (blocks) whose f (…, r) is zero at every sample are
        not evaluated by :meth:`f` (a mesh's mass balance, a measured input)."""
        moves = ((f != 0) | ~torch.isfinite(f)).reshape(-1, f.shape[-1]).any(0)
        self.zero_f = frozenset(r for r in self.equations if not moves[_columns(self.row_at[r])].any())
        nonzero = ((F != 0) | ~torch.isfinite(F)).reshape(-1, *F.shape[-2:]).any(0)
        share = (nonzero.T.double() @ nonzero.double()) > 0             # columns j, k share a row
        colors = torch.full((F.shape[-1],), -1, dtype=torch.long)
        for j in torch.argsort(share.sum(1), descending=True, stable=True).tolist():
            used = set(colors[share[j]].tolist())
            colors[j] = next(c for c in range(F.shape[-1]) if c not in used)
        groups = int(colors.max()) + 1
        if groups < F.shape[-1]:
            self.colors = colors
            self.entries = torch.where(nonzero, colors, groups)       # (r, nζ): a group, or the zero


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


def _check_derivative(name: str, single: _Rows, x: Tensor, t: Tensor) -> None:
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


def _check_rows(rows: _Rows, x: Tensor, z1: Tensor, z2: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
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
        for z in (z1, z2):
            got, lin = rows(x, z, t), f + (F @ z.unsqueeze(-1)).squeeze(-1)
            ok = ~torch.isfinite(got) | ((got - lin).abs() <= 1e-9 * (1 + got.abs() + f.abs()
                                                                        + (F.abs() @ z.abs().unsqueeze(-1)).squeeze(-1)))
            for i in (~ok).any(0).nonzero().flatten().tolist():
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
    Savitzky–Golay differentiation (:func:`~shootlab.estimation.smoothed`), the rest zero."""

    def initial(data: Measurements, t: Tensor) -> Tensor:
        ts = torch.as_tensor(data.t, dtype=t.dtype)
        cols = {s: torch.as_tensor(data.channels[c], dtype=t.dtype) for s, c in measured.items()}
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
          mechanics: Mapping[str, object] | None = None) -> IdentificationModel:
    """Compile a declared model (module docstring) to an :class:`IdentificationModel`.

    name        the model's name (summaries, file names)
    states      state → its derivative, the name of another state (an entry 1 of A) or of an
                input (an entry 1 of B); x = states in this order, then the parameters
    inputs      the names of ζ, in order
    parameters  parameter → default initial value (the model's ``prior``); θ' = ε_θ
    equations   row → ``lambda x: …``, a torch expression over :class:`Variables` (states,
                parameters, inputs and ``t`` by name), affine in the inputs
    channels    measurement row → data column (a list: rows named as their columns); the
                other rows are model equations, zero pseudo-measurements
    W, V        weights of eq. 2.6: a mapping name → weight over the defaults, or the full
                vector, matrix or function of t that :class:`IdentificationModel` takes.  The
                defaults are the report's (§3.4: W 1e10 on every state, 1 on every parameter,
                V 1 on every row) read as dimensionless: divided by the square of each
                variable's and row's scale on the data when estimated (:mod:`shootlab.weights`),
                so that the model estimates the same in any consistent units
    W_a, q_a    prior on x(a) (default none: W_a = 0); a mapping or a vector
    given       channels known when the model is simulated (default: those whose row is free of
                the states and depends on an input, e.g. a measured motor force)
    units       unit per name (``"t"``, variables, rows), for labels and summaries
    bounds      (low, high) per state or parameter that the Newton iterates keep strictly inside
    settings    :class:`EstimationSettings` (default: 101 points, RK4 x10)
    blocks      name → number of components (labels 1 … k) or their labels, for a state, input
                or model row that is a vector (the nodes of a finite-element mesh): ``x.s`` is
                then a (…, k) tensor, a block row returns (…, k), and the components are named
                ``s1 … sk`` (``s{label}``) in the compiled model; a state and its derivative are
                blocks of the same labels (an identity block of A or B).  A single variable next
                to a block broadcasts as ``x.m[..., None]``.  F is then probed in groups of
                inputs that share no row and f skips rows that vanish at ζ = 0
                (:meth:`_Rows.pattern`, from f and F at 64 random samples): an input coefficient
                or a row nonzero only in a small region of the states would be missed, so such a
                model is declared without blocks
    initial_states  ``(data, t) -> (m, n_states)``; default: a state that a measurement row
                equals (``lambda x: x.s``) from its channel, a state that is its derivative
                (``{"s": "v"}``) by Savitzky–Golay differentiation (``settings.smoothing``),
                every other state 0
    mechanics   for the diagnosis's mechanical library (:mod:`shootlab.diagnosis.mechanical`):
                ``motion`` (the equation-of-motion row), ``velocity`` (its velocity state, whose
                derivative is an input), ``command`` (the measured channel of the driving force),
                optionally ``deflection`` and ``stiffness`` (a spring's state and parameter) and
                ``friction_width`` (the smooth sign's half-width; default from the record)

    Every mistake in the declaration is a one-line ValueError naming what is wrong."""
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
    rows = _Rows(equations, names, inputs, blocks)
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
    if blocks:              # a mesh's rows: probe the inputs in groups (_Rows.F, _Rows.pattern)
        xs, _, _, ts = _sample(rows.names[:nx - len(parameters)], parameters, nz, n=64, spread=True)
        with torch.no_grad():
            rows.pattern(torch.cat([f, rows.f(xs, ts)]), torch.cat([F, rows.F(xs, ts)]))
    unused = [u for j, u in enumerate(rows.inputs) if not (F[..., j] != 0).any()]
    if unused:
        raise ValueError(f"input(s) {unused} enter no equation row: every input needs a row that determines it")
    measured = {}
    for row, column in channels.items():
        i = rows.row_at[row]
        if not F[:, i].any():
            same = [s for s in states if s not in blocks and torch.equal(f[:, i], x[:, rows.x_at[s]])]
            if same:
                measured.setdefault(same[0], column)
    if given is None:
        given = [c for r, c in channels.items() if F[:, rows.row_at[r]].any() and not f[:, rows.row_at[r]].any()]
    settings = settings if settings is not None else EstimationSettings()
    if not isinstance(settings, EstimationSettings):
        raise ValueError(f"settings must be an EstimationSettings, got {type(settings).__name__}")
    compiled = settings.as_dict()
    names, equations_ = rows.names, rows.rows
    w_defaults = [DEFAULT_W_STATE] * (nx - len(parameters)) + [DEFAULT_W_PARAMETER] * len(parameters)
    v_defaults = [DEFAULT_V] * len(equations_)
    marks = {"W": _left_to_defaults(W, names, w_defaults), "V": _left_to_defaults(V, equations_, v_defaults)}
    if any(m is not None for m in marks["W"] + marks["V"]):
        compiled[FROM_DATA] = marks         # scaled by the data when estimated (shootlab.weights)
    if mechanics is not None:
        from .diagnosis.mechanical import declared_mechanics
        x0, _, _, t0 = _sample(names[:nx - len(parameters)], {}, nz)
        x0 = torch.cat([x0, torch.tensor([float(v) for v in parameters.values()], dtype=x0.dtype).expand(x0.shape[0], -1)], -1)
        with torch.no_grad():
            F0 = rows.F(x0, torch.zeros_like(t0))     # at the default parameters: the signs
        compiled["mechanics"] = declared_mechanics(dict(mechanics), states, rows, channels, F0)
    return IdentificationModel(
        name=name, states=names[:nx - len(parameters)], parameters=list(parameters), inputs=rows.inputs,
        equations=equations_, channels=channels, A=A, B=B, f=rows.f, F=rows.F,
        W=_diagonal(W, names, w_defaults, "W"),
        V=_diagonal(V, equations_, v_defaults, "V"),
        W_a=_diagonal(W_a, names, [0.0] * nx, "W_a") if W_a is not None else None,
        q_a=_diagonal(q_a, names, [0.0] * nx, "q_a") if q_a is not None else None,
        prior={p: float(v) for p, v in parameters.items()}, given=list(given),
        initial_states=initial_states or _initial_states(states, rows.x_at, measured, int(settings.smoothing)),
        settings=compiled, units=dict(units or {}), bounds=dict(bounds or {}))


def _columns(at: int | slice) -> list[int]:
    return list(range(at.start, at.stop)) if isinstance(at, slice) else [at]


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
