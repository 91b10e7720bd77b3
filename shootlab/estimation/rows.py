"""The rows of a declared model (:func:`shootlab.model`) as the engine evaluates them: the
namespace a row expression — and an added effect's term — sees (:class:`Variables`), and f and F
of the augmented state form (docs/design.md §1, report eq. 2.5) from the expressions::

    f(x, t) = rows(x, ζ = 0, t),      F(x, t) = ∂rows/∂ζ

F is exact for rows affine in ζ: the rows at ζ = S e_j (S a power of two large enough to swamp the
ζ-free part) less the rows at 0, divided by S; a model with blocks (a mesh) probes the inputs in
groups that share no row (Curtis, Powell & Reid 1974).
"""
from __future__ import annotations

import copy
from typing import Callable, Mapping, Sequence

import torch
from torch import Tensor

__all__ = ["Row", "Rows", "Variables", "UnknownName", "not_affine"]


Row = Callable[["Variables"], "Tensor | float"]


class UnknownName(AttributeError, KeyError):
    """A row or a term asked :class:`Variables` for a name it does not hold (an AttributeError for
    ``x.name``, a KeyError for ``x["name"]``)."""

    def __init__(self, name: str, known: Sequence[str]):
        super().__init__(f"no variable named {name!r}; known names: {', '.join(known)}")
        self.name, self.known = name, list(known)


class Variables:
    """What a model's row (``lambda x: …``) and an effect's term (``lambda v: …``) see: ``x.name`` is
    a state, a parameter or an input as a tensor of the batch shape, ``x.t`` the time (same shape),
    and ``x["name"]`` the same for a name held in a string.  An effect's term also reads
    ``x.channel(name, at=None)``, a measured channel of the bound data at ``x.t`` (or at the times
    ``at``, differentiably in ``at``), ``x.input(name)`` for an input whose name is also a state's
    or a parameter's (a name resolves to the states and parameters first) and ``x.zeros()``.  The
    values are the instance's attributes (a row reads several per evaluation: plain attribute
    lookups); an unknown name raises :class:`UnknownName` naming the known ones."""

    def __init__(self, values: Mapping[str, Tensor], inputs: Mapping[str, Tensor] | None = None,
                 channel: Callable[[str, Tensor], Tensor] | None = None):
        own = self.__dict__
        own.update(inputs or {})
        own.update(values)
        own["_inputs"], own["_channel"] = dict(inputs or {}), channel

    def _known(self) -> list[str]:
        return [n for n in self.__dict__ if not n.startswith("_")]

    def __getattr__(self, name: str) -> Tensor:      # only for names that are not values
        if name.startswith("__"):                    # copy, pickle, … probe dunders
            raise AttributeError(name)
        raise UnknownName(name, self._known())

    def __getitem__(self, name: str) -> Tensor:
        if name.startswith("_") or name not in self.__dict__:
            raise UnknownName(name, self._known())
        return self.__dict__[name]

    def __contains__(self, name: str) -> bool:
        return not name.startswith("_") and name in self.__dict__

    def __setattr__(self, name, value):
        raise AttributeError("Variables are read-only")

    def input(self, name: str) -> Tensor:
        """The input ζ named ``name`` (also where a state or a parameter has that name)."""
        if name not in self._inputs:
            raise UnknownName(name, list(self._inputs))
        return self._inputs[name]

    def channel(self, name: str, at: Tensor | None = None) -> Tensor:
        """The measured channel ``name`` at ``x.t``, or at the times ``at`` (differentiably in them)."""
        if self._channel is None:
            raise KeyError(f"channel {name!r}: no measured channels are bound to these variables")
        return self._channel(name, self.t if at is None else at)

    def zeros(self) -> Tensor:
        """Zeros of the batch shape."""
        return torch.zeros_like(self.t)


def not_affine(value: Callable[[Tensor], Tensor], f: Tensor, F: Tensor, zs: Sequence[Tensor],
               rtol: float = 1e-9) -> list[int]:
    """The rows that are not affine in the inputs ζ: where ``value(ζ)`` (…, r) — a model's rows or
    an effect's terms on fixed states — is not f + F ζ at one of the sample inputs ``zs`` (each
    (…, nζ)), f (…, r) and F (…, r, nζ) the value at ζ = 0 and the derivative in ζ the caller
    uses, to ``rtol`` of the sizes involved: |value − f − F ζ| ≤ rtol (1 + |value| + |f| + |F||ζ|)
    (rounding leaves a few ε of them; a non-finite value decides nothing).  The indices along r,
    in order (empty: affine at the samples)."""
    bad = torch.zeros(f.shape[-1], dtype=torch.bool, device=f.device)
    with torch.no_grad():
        for z in zs:
            got, lin = value(z), f + (F @ z.unsqueeze(-1)).squeeze(-1)
            size = 1 + got.abs() + f.abs() + (F.abs() @ z.abs().unsqueeze(-1)).squeeze(-1)
            ok = ~torch.isfinite(got) | ((got - lin).abs() <= rtol * size)
            bad |= (~ok).reshape(-1, f.shape[-1]).any(0)
    return bad.nonzero().flatten().tolist()


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


class Rows:
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
        self._constants: dict = {}      # (dtype, device, …) → _probes

    def variables(self, x: Tensor, zeta: Tensor, t) -> Variables:
        """The namespace of the rows: x's and ζ's columns (and blocks) by name, and t, all of the
        batch shape x.shape[:-1] (a block's components last)."""
        batch = x.shape[:-1]
        values = _columns_by_name(x, self.x_at)
        values.update(_columns_by_name(zeta, self.z_at))
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

    def single(self, name: str) -> "Rows":
        """The row (or block) ``name`` alone, over the same variables."""
        out = copy.copy(self)
        out.equations = {name: self.equations[name]}
        out._constants = {}
        return out

    #: the size of the probing inputs of :meth:`F`: a power of two (scaling by it is exact)
    SCALE = 2.0 ** 300

    def F(self, x: Tensor, t: Tensor) -> Tensor:
        """∂rows/∂ζ: (…, r, nζ) of rows affine in ζ, as (row(S e_j) − row(0)) / S for every input
        j in one batched evaluation, S = :attr:`SCALE`.  Exact where a difference with unit
        inputs would cancel digits: S F_j swamps the ζ-free part of the row (it is absorbed in
        the rounding unless |f| > 2^247 |F_j|), and multiplying or dividing by a power of two is
        exact — the values equal the hand-written F's bit for bit (tests: msd), at a
        tenth of the cost of a forward-mode derivative per input.

        With a sparsity :meth:`pattern`, inputs whose columns share no row are probed together
        (one probe per group, Curtis, Powell & Reid 1974): each row then sees one input of the
        group, so the entries are as exact as one probe per input, at a fraction of the probes
        (the confined mixture model of N elements: at most 6 probes instead of 2N + 2)."""
        return self.f_and_F(x, t, with_f=False)[1]

    def f_and_F(self, x: Tensor, t: Tensor, with_f: bool = True) -> tuple[Tensor | None, Tensor]:
        """:meth:`f` and :meth:`F` from one evaluation: f is :meth:`F`'s probe at ζ = 0, with the
        rows of :attr:`zero_f` set to zero as :meth:`f` leaves them."""
        batch = x.shape[:-1]
        tb = torch.broadcast_to(torch.as_tensor(t, dtype=x.dtype, device=x.device), batch).unsqueeze(-1)
        Z, zero = self._probes(x)
        out = self(x.unsqueeze(-2).expand(*batch, len(Z), x.shape[-1]), Z.expand(*batch, *Z.shape), tb)
        f = None
        if with_f:
            f = out[..., 0, :].clone()          # not a view: it would keep all probes alive
            if zero is not None:
                f = f.masked_fill(zero, 0.0)
        probes = ((out[..., 1:, :] - out[..., :1, :]) / self.SCALE).transpose(-1, -2)     # (…, r, groups)
        if self.colors is None:
            return f, probes
        # entry (i, j) is row i's response to input j's group where the pattern has it, else the
        # appended zero: one gather writes F
        probes = torch.cat([probes, probes.new_zeros(*probes.shape[:-1], 1)], -1)
        return f, torch.gather(probes, -1, self.entries.to(x.device).expand(*probes.shape[:-1], len(self.inputs)))

    def _probes(self, x: Tensor) -> tuple[Tensor, Tensor | None]:
        """The probing inputs [0; S·I] (or [0; S·groups]) and the mask of :attr:`zero_f`'s columns
        (None without such rows), made once per dtype and device (and per pattern: a copy may
        drop the grouping, ``colors = None``)."""
        key = (x.dtype, x.device, self.colors is None, self.zero_f)
        if key not in self._constants:
            nz, like = len(self.inputs), dict(dtype=x.dtype, device=x.device)     # plain tensors, also under a transform
            Z = torch.eye(nz, **like) if self.colors is None else self.groups.to(**like)
            Z = torch.cat([torch.zeros(1, nz, **like), self.SCALE * Z], 0)
            zero = None
            if self.zero_f:
                zero = torch.zeros(sum(self.sizes.get(r, 1) for r in self.equations), dtype=torch.bool, device=x.device)
                zero[[j for r in self.zero_f for j in _columns(self.row_at[r])]] = True
            self._constants[key] = (Z, zero)
        return self._constants[key]

    #: with a :meth:`pattern`: each input's group, the groups as 0/1 rows (groups, nζ), and per
    #: entry of F its group's probe or the appended zero (r, nζ)
    colors: Tensor | None = None
    groups: Tensor | None = None
    entries: Tensor | None = None

    def pattern(self, f: Tensor, F: Tensor) -> None:
        """Group the inputs for :meth:`F` by the nonzeros of F at samples (…, r, nζ): a greedy
        colouring of the columns in which no two columns of a colour share a row.  A non-finite
        entry counts as a nonzero.  The rows (blocks) whose f (…, r) is zero at every sample are
        not evaluated by :meth:`f` (a mesh's mass balance, a measured input)."""
        moves = ((f != 0) | ~torch.isfinite(f)).reshape(-1, f.shape[-1]).any(0)
        self.zero_f = frozenset(r for r in self.equations if not moves[_columns(self.row_at[r])].any())
        self._constants = {}            # the probes and the mask change with the pattern
        nonzero = ((F != 0) | ~torch.isfinite(F)).reshape(-1, *F.shape[-2:]).any(0)
        share = (nonzero.T.double() @ nonzero.double()) > 0             # columns j, k share a row
        colors = torch.full((F.shape[-1],), -1, dtype=torch.long)
        for j in torch.argsort(share.sum(1), descending=True, stable=True).tolist():
            used = set(colors[share[j]].tolist())
            colors[j] = next(c for c in range(F.shape[-1]) if c not in used)
        groups = int(colors.max()) + 1
        if groups < F.shape[-1]:
            self.colors = colors
            self.groups = (colors == torch.arange(groups)[:, None]).double()
            self.entries = torch.where(nonzero, colors, groups)


def _columns_by_name(x: Tensor, at: Mapping[str, int | slice]) -> dict[str, Tensor]:
    """x's columns (…) and blocks (…, k) by name, as views from one ``split``: its derivative is
    one concatenation, where a column selected by indexing would add a zero tensor of x's whole
    size per name in a reverse sweep (half the time of the eq. 2.7 Jacobian of a rig model).
    ``at`` lists the names in the order of x's columns."""
    sizes = [len(_columns(j)) for j in at.values()]
    pieces = x.split(sizes, -1) if sum(sizes) == x.shape[-1] else [x[..., _slice(j)] for j in at.values()]
    return {n: (p if isinstance(j, slice) else p.squeeze(-1)) for (n, j), p in zip(at.items(), pieces)}


def _slice(at: int | slice) -> slice:
    return at if isinstance(at, slice) else slice(at, at + 1)


def _columns(at: int | slice) -> list[int]:
    return list(range(at.start, at.stop)) if isinstance(at, slice) else [at]
