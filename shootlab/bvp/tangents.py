"""Forward-mode derivatives of a batched right-hand side, by ``torch.func`` transforms.

The forward sensitivities of the integrators (internal numerical differentiation, Bock) need,
at every stage point Y of every row, either the product J V of the rhs Jacobian J = ∂f/∂y with
a matrix of tangents V (explicit schemes: V = ∂Y/∂s) or J itself (implicit schemes, simplified
Newton).  Both are one ``torch.func.jvp`` vectorised by ``torch.func.vmap`` over the k tangent
columns: column j of J V is the directional derivative of f along V[..., j] for all rows at
once (the rows are independent).  ``rhs(t, y)`` is called with its usual batch (m, n); only the
tangent dimension is vmapped.

A right-hand side that brings its own Jacobian (:class:`VectorField`, e.g. the estimation
TPBVP, which assembles it from the model's derivatives) is not transformed: ``J`` is its own and
``J V`` one batched product.

A right-hand side that ``torch.func`` cannot transform (an in-place write of a traced value
into a plain tensor, ``.item()``, numpy) raises :class:`NotTransformable`; the caller then
falls back to reverse sweeps (:func:`shootlab.bvp.integrators.batch_jacobian`), and
:func:`untransformable` tells the user once per right-hand side.
"""
from __future__ import annotations

import contextlib
import warnings
import weakref
from typing import Any, Callable, Iterator

import torch
import torch.autograd.forward_ad as fwAD
from torch import Tensor
from torch.func import jvp, vmap

__all__ = ["VectorField", "NotTransformable", "outside_transforms", "jacobian_product", "batched_stages", "rhs_jacobian", "time_derivative", "second_product", "FORWARD_MIN_N", "untransformable", "known_untransformable",
           "TANGENT_BUDGET", "count_jacobians", "JacobianCount"]

RHS = Callable[[Tensor, Tensor], Tensor]

#: at most about this many tangent entries (m · chunk · n) · n per vmapped call: the tangents of
#: a dense (n, n) intermediate per row (e.g. F of eq. 2.7) are the memory that matters
TANGENT_BUDGET = 2 ** 24


class NotTransformable(RuntimeError):
    """The right-hand side cannot be differentiated by ``torch.func`` (see module docstring)."""


class VectorField:
    """A right-hand side ``f(t, y)`` with its Jacobian: ``jacobian(t, y) -> (f, ∂f/∂y)`` for a
    batch y (m, n), giving (m, n) and (m, n, n) on plain values (scipy's ``fun_jac``).  Calls
    go to ``fun``; the integrators' forward sensitivities use ``jacobian`` instead of
    transforming ``fun``.  ``jacobian`` may raise :class:`NotTransformable`: the caller then
    falls back to transforming ``fun``."""

    def __init__(self, fun: RHS, jacobian: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]):
        self.fun, self._jacobian = fun, jacobian

    def __call__(self, t: Tensor, y: Tensor) -> Tensor:
        return self.fun(t, y)

    def jacobian(self, t: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        return self._jacobian(t, y)

    def __repr__(self) -> str:
        return f"VectorField({getattr(self.fun, '__qualname__', self.fun)!r})"


def _own_jacobian(rhs: RHS, t: Tensor, y: Tensor) -> tuple[Tensor, Tensor] | None:
    """(f, J) from the right-hand side's own Jacobian, or None when it has none (or cannot give
    it for this rhs: :class:`NotTransformable`, remembered and told once)."""
    own = getattr(rhs, "jacobian", None)
    if own is None or known_untransformable(own):
        return None
    try:
        f, J = own(t.detach(), y.detach())
    except NotTransformable as exc:
        untransformable(own, exc.__cause__ or exc, "forward-mode differentiation of the right-hand side")
        return None
    return f.detach(), J.detach()


_flagged: "weakref.WeakKeyDictionary[object, set[str]]" = weakref.WeakKeyDictionary()


def outside_transforms():
    """Context in which tensors are made outside any active torch.func transform: for constants
    and caches made during a transformed call and used after it (made inside, they would be
    that transform's wrapped tensors and escape it)."""
    return getattr(torch._C, "_DisableFuncTorch", contextlib.nullcontext)()


def _key(rhs: RHS) -> tuple[object, str]:
    owner = getattr(rhs, "__self__", None)
    func = getattr(rhs, "__func__", rhs)
    return (owner, func.__qualname__) if owner is not None else (func, "")


def known_untransformable(rhs: RHS) -> bool:
    """True once :func:`untransformable` has been called for this right-hand side."""
    owner, name = _key(rhs)
    try:
        return name in _flagged.get(owner, ())
    except TypeError:           # not weak-referenceable: never remembered
        return False


def untransformable(rhs: RHS, exc: BaseException, fallback: str) -> None:
    """Remember that ``rhs`` defeats torch.func and warn the user (once per rhs)."""
    owner, name = _key(rhs)
    if known_untransformable(rhs):
        return
    try:
        _flagged.setdefault(owner, set()).add(name)
    except TypeError:
        pass
    warnings.warn(f"the right-hand side cannot be differentiated by torch.func ({type(exc).__name__}: "
                  f"{str(exc).splitlines()[0] if str(exc) else ''}); using {fallback} instead, which is slower. "
                  "Write it with out-of-place torch operations (no in-place writes into new tensors, "
                  "no .item(), no numpy) for the fast forward-mode Jacobians.", RuntimeWarning, stacklevel=3)


#: below this many equations J comes from one batched reverse sweep (``is_grads_batched``) and
#: J V from a product: on small problems the per-operation overhead of the torch.func
#: transforms dominates, on large ones the sweeps' count (``benchmarks/engine.py`` times both)
FORWARD_MIN_N = 32


def reverse_jacobian(rhs: RHS, t: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """``f = rhs(t, y)`` (m, n) and ``J = ∂f/∂y`` (m, n, n) by reverse sweeps through rhs (one per
    output component, batched over the rows).  Raises :class:`NotTransformable`."""
    try:
        f, J, _ = _value_and_jacobian(rhs, t, y.detach())
    except RuntimeError as exc:
        raise NotTransformable(str(exc)) from exc
    return f.detach(), J.detach()


def _chunk(m: int, n: int, k: int) -> int | None:
    c = max(1, TANGENT_BUDGET // max(1, m * n * n))
    return None if c >= k else c


class JacobianCount:
    """The rhs-Jacobian evaluations (calls of :func:`jacobian_product` and :func:`rhs_jacobian`,
    each one batched evaluation over the rows) inside a :func:`count_jacobians` block."""

    def __init__(self) -> None:
        self.evaluations = 0


_counts: list[JacobianCount] = []


@contextlib.contextmanager
def count_jacobians() -> Iterator[JacobianCount]:
    """Count the rhs-Jacobian evaluations of the block (a measurement of a computation's Jacobian cost)::

        with count_jacobians() as count:
            system.interval_jacobians(s)
        count.evaluations
    """
    count = JacobianCount()
    _counts.append(count)
    try:
        yield count
    finally:
        _counts.remove(count)


def _counted() -> None:
    for count in _counts:
        count.evaluations += 1


def batched_stages(n: int) -> bool:
    """Whether the Jacobians at several points are best had from one batched call over all of
    them: below :data:`FORWARD_MIN_N` equations, where a call's fixed cost dominates — a reverse
    sweep, or a right-hand side's own Jacobian (the estimation TPBVP of a rig model, n = 16: its
    assembled Jacobian at 76 and 400 rows 2.6 and 4.4 ms; twelve undamped re-estimation steps of
    the diagnosis with the four RK4 stages in one call 7.9 s, with one call per stage 10.5 s; since
    then the one call joins the TPBVP's normal equations kept from the stages' own evaluations,
    :meth:`~shootlab.estimation.optimality.EstimationProblem._joined`, instead of solving them again: 0.90 of
    that time)."""
    return n < FORWARD_MIN_N


def jacobian_product(rhs: RHS, t: Tensor, y: Tensor, V: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``f = rhs(t, y)`` (m, n) and ``J V`` (m, n, k) with ``J = ∂f/∂y`` row by row; ``V`` (m, n, k),
    None for the identity (then ``J V = J``).  Raises :class:`NotTransformable`."""
    _counted()
    return _product(rhs, t, y, V)


def _product(rhs: RHS, t: Tensor, y: Tensor, V: Tensor | None = None) -> tuple[Tensor, Tensor]:
    own = _own_jacobian(rhs, t, y)
    if own is not None:
        return own[0], (own[1] if V is None else own[1] @ V)
    m, n = y.shape
    if n < FORWARD_MIN_N:
        f, J = reverse_jacobian(rhs, t, y)
        return f, (J if V is None else J @ V)
    if V is None:
        tangents = torch.eye(n, dtype=y.dtype, device=y.device)[:, None, :].expand(n, m, n)
    else:
        tangents = V.movedim(-1, 0)
    y = y.detach().contiguous()          # a view would give every tangent its whole base storage

    def along(v: Tensor) -> tuple[Tensor, Tensor]:
        return jvp(lambda yy: rhs(t, yy), (y,), (v,))

    k = tangents.shape[0]
    chunk = _chunk(m, n, k) or k
    parts = [_transform(lambda: vmap(along, out_dims=(None, 0))(tangents[i:i + chunk])) for i in range(0, k, chunk)]
    f = parts[0][0]
    JV = parts[0][1] if len(parts) == 1 else torch.cat([p[1] for p in parts])
    return f, JV.movedim(0, -1)


def _transform(fn: Callable[[], Tensor]) -> Tensor:
    try:
        return fn()
    except (RuntimeError, NotImplementedError, TypeError, ValueError, AttributeError) as exc:
        raise NotTransformable(str(exc)) from exc


def time_derivative(rhs: RHS, t: Tensor, y: Tensor) -> Tensor:
    """``∂f/∂t`` (m, n) at every row, by one forward-mode call."""
    y = y.detach().contiguous()
    return _transform(lambda: jvp(lambda tt: rhs(tt, y), (t.detach(),), (torch.ones_like(t),))[1])


def second_product(rhs: RHS, t: Tensor, y: Tensor, u: Tensor, tu: Tensor, V: Tensor) -> Tensor:
    """``D_y[J(t, y) u + ∂f/∂t(t, y) tu] V`` (m, n, k): the derivative along the columns of V
    (m, n, k) of the directional derivative of f along (tu, u) — second derivatives of the rhs,
    as forward over forward mode (the sensitivity of a Rosenbrock stage, whose matrix holds J)."""
    y, u, t = y.detach().contiguous(), u.detach(), t.detach()

    def phi(yy: Tensor) -> Tensor:
        return jvp(lambda tt, y2: rhs(tt, y2), (t, yy), (tu.detach(), u))[1]

    m, n = y.shape
    tangents = V.movedim(-1, 0)
    k = tangents.shape[0]
    chunk = _chunk(m, n, k) or k
    along = vmap(lambda v: jvp(phi, (y,), (v,))[1])
    return torch.cat([_transform(lambda: along(tangents[i:i + chunk])) for i in range(0, k, chunk)]).movedim(0, -1)


def rhs_jacobian(rhs: RHS, t: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """``f = rhs(t, y)`` and ``J = ∂f/∂y`` (m, n, n) by forward mode, falling back to one batched
    reverse sweep (:func:`shootlab.bvp.integrators.batch_jacobian`) for a right-hand side that
    torch.func cannot transform (the user is told once)."""
    _counted()
    own = _own_jacobian(rhs, t, y)
    if own is not None:
        return own
    # inside a forward-AD dual level (dual tensors through the integrator) torch.func cannot
    # nest its own forward mode: reverse sweep, and nothing to tell the user
    if not known_untransformable(rhs) and fwAD._current_level < 0:
        try:
            return _product(rhs, t, y)
        except NotTransformable as exc:
            untransformable(rhs, exc.__cause__ or exc, "reverse-mode autograd")
    f, J, _ = _value_and_jacobian(rhs, t, y.detach())
    return f.detach(), J.detach()


def _is_dual(x: Tensor) -> bool:
    return fwAD.unpack_dual(x).tangent is not None


def _drop_graph(x: Tensor) -> Tensor:
    """Detach ``x`` from the reverse-mode graph but keep its forward tangent."""
    primal, tangent = fwAD.unpack_dual(x)
    if tangent is None:
        return x.detach()
    return fwAD.make_dual(primal.detach(), tangent.detach())


def _const(x: Any, like: Tensor) -> Tensor:
    """``x`` as a constant operand for arithmetic with ``like``.

    When ``like`` is a dual tensor the constant gets an explicit zero tangent:
    forward AD treats an operand *without* tangent through a slow generic path
    (about 0.3 ms per operation in torch 2.13 on CPU, versus a few us), so the
    integrators keep all operands of their own arithmetic dual.
    """
    x = torch.as_tensor(x, dtype=like.dtype, device=like.device)
    return fwAD.make_dual(x, torch.zeros_like(x)) if _is_dual(like) else x


class _TrackedJacobian(torch.autograd.Function):
    """(f, J, df/dt) at a y that requires grad, without recording the sweep on y's graph.

    ``torch.autograd.grad`` walks the whole graph behind its outputs, so calling it at every
    step of an integration whose state carries a graph costs O(steps²).  Here the forward pass
    works on a detached copy and the backward pass recomputes f, J, df/dt on a fresh leaf and
    returns their vector–Jacobian product.
    """

    @staticmethod
    def forward(ctx, y, rhs, t, with_time):
        ctx.rhs, ctx.t, ctx.with_time = rhs, t, with_time
        ctx.save_for_backward(y)
        out, jac, dfdt = _value_and_jacobian(rhs, t, y.detach(), with_time)
        return out, jac, (dfdt if with_time else torch.zeros_like(out))

    @staticmethod
    def backward(ctx, g_out, g_jac, g_dfdt):
        y, = ctx.saved_tensors
        with torch.enable_grad():
            leaf = y.detach().requires_grad_(True)
            out, jac, dfdt = _value_and_jacobian(ctx.rhs, ctx.t, leaf, ctx.with_time, _direct=True)
            total = (out * g_out).sum() + (jac * g_jac).sum()
            if ctx.with_time:
                total = total + (dfdt * g_dfdt).sum()
            g_y, = torch.autograd.grad(total, leaf, allow_unused=True)
        return (torch.zeros_like(y) if g_y is None else g_y), None, None, None


def _value_and_jacobian(rhs: RHS, t: Tensor, y: Tensor, with_time: bool = False, _direct: bool = False
                        ) -> tuple[Tensor, Tensor, Tensor | None]:
    """``f = rhs(t, y)``, ``J = df/dy`` of shape (..., n, n) and, if asked, ``df/dt``.

    One rhs call plus one reverse sweep vectorised over the n output
    components (``is_grads_batched``).  If ``y`` is a dual tensor the sweep is
    recorded (``create_graph``), so that ``J`` carries forward tangents
    (forward-over-reverse); if ``y`` requires grad, f, J and df/dt are
    differentiable through :class:`_TrackedJacobian`.
    """
    dual, track = _is_dual(y), y.requires_grad
    if track and not dual and not _direct:
        out, jac, dfdt = _TrackedJacobian.apply(y, rhs, t, with_time)
        return out, jac, (dfdt if with_time else None)
    with torch.enable_grad():
        yr = y.clone()
        if not yr.requires_grad:
            yr.requires_grad_(True)
        tr = t.detach().clone().requires_grad_(with_time)
        out = rhs(tr, yr)
        n_out = out.shape[-1]
        if not out.requires_grad:  # rhs does not depend on (t, y)
            jac = _const(out.new_zeros(*out.shape, y.shape[-1]), y)
            return out, jac, (_const(torch.zeros_like(out), y) if with_time else None)
        basis = torch.eye(n_out, dtype=out.dtype, device=out.device)
        basis = basis.reshape(n_out, *([1] * (out.dim() - 1)), n_out).expand(n_out, *out.shape)
        if dual:
            basis = _const(basis.contiguous(), y)
        inputs = (yr, tr) if with_time else (yr,)
        grads = torch.autograd.grad(out, inputs, grad_outputs=basis, is_grads_batched=True,
                                    create_graph=dual or track, allow_unused=True)
    # unused inputs give None: the derivative is zero
    jac = (_const(out.new_zeros(*out.shape, y.shape[-1]), y) if grads[0] is None
           else grads[0].movedim(0, -2))
    dfdt = None
    if with_time:
        dfdt = (_const(out.new_zeros(out.shape), y) if grads[1] is None
                else grads[1].movedim(0, -1))
    if not track:  # forward mode only: keep the tangents, free the reverse graph
        out, jac = _drop_graph(out), _drop_graph(jac)
        dfdt = _drop_graph(dfdt) if dfdt is not None else None
    return out, jac, dfdt


def batch_jacobian(rhs: RHS, t: Tensor, y: Tensor) -> Tensor:
    """Jacobian ``d rhs(t, y) / d y`` at every batch element, shape (..., n, n).

    Computed by reverse-mode autograd (one rhs call, one batched backward
    sweep).  Works when ``y`` is a forward-mode dual tensor (the Jacobian then
    carries tangents) or requires grad (the Jacobian is then differentiable).
    """
    return _value_and_jacobian(rhs, t, y)[1]
