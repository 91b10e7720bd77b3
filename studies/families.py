"""Families of TPBVPs with one parameter, as :class:`shootlab.ParametricBVP` for
:func:`shootlab.solve_batch` (a parameter sweep solved as one batch: ``python -m studies sweep
--family``, ``benchmarks/gpu.py``), each with its guess and, where known, its exact solution.

``layer``    ε y″ = y, y(0) = y(1) = 1: y = cosh((t − ½)/√ε)/cosh(1/(2√ε)) (boundary layers of
             width √ε at both ends); parameter ε
``troesch``  y″ = μ sinh(μ y), y(0) = 0, y(1) = 1 (Troesch 1976; a layer at t = 1); parameter μ
``bratu``    y″ + λ e^y = 0, y(0) = y(1) = 0 (two solutions for λ < 3.5138, none above; the
             guess 0 leads to the lower branch); parameter λ

The state is x = [y, y′]; every family's quantity is y′(0) (:func:`slope`).
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import torch
from torch import Tensor

from shootlab.bvp.batch import ParametricBVP

__all__ = ["FAMILIES", "family", "guess", "layer_exact", "slope"]

f64 = torch.float64


def _layer_rhs(t: Tensor, x: Tensor, theta: Tensor) -> Tensor:
    return torch.stack([x[..., 1], x[..., 0] / theta[..., 0]], -1)


def _troesch_rhs(t: Tensor, x: Tensor, theta: Tensor) -> Tensor:
    mu = theta[..., 0]
    return torch.stack([x[..., 1], mu * torch.sinh(mu * x[..., 0])], -1)


def _bratu_rhs(t: Tensor, x: Tensor, theta: Tensor) -> Tensor:
    return torch.stack([x[..., 1], -theta[..., 0] * torch.exp(x[..., 0])], -1)


#: name → (rhs, y(0), y(1), parameter name, guess of (y, y′) at t)
FAMILIES: dict[str, tuple[Callable, float, float, str, Callable[[Tensor], Tensor]]] = {
    "layer": (_layer_rhs, 1.0, 1.0, "eps", lambda t: torch.stack([torch.ones_like(t), torch.zeros_like(t)], -1)),
    "troesch": (_troesch_rhs, 0.0, 1.0, "mu", lambda t: torch.stack([t, torch.ones_like(t)], -1)),
    "bratu": (_bratu_rhs, 0.0, 0.0, "lambda", lambda t: torch.stack([torch.zeros_like(t), torch.zeros_like(t)], -1)),
}


def _check(name: str) -> None:
    if name not in FAMILIES:
        raise ValueError(f"unknown family {name!r}; choose one of {', '.join(FAMILIES)}")


def family(name: str, values: Sequence[float] | Tensor) -> ParametricBVP:
    """The family ``name`` (module docstring) with one problem per parameter value."""
    _check(name)
    rhs, ya, yb, _, _ = FAMILIES[name]
    return ParametricBVP(rhs, lambda xa, th: xa[:, :1] - ya, lambda xb, th: xb[:, :1] - yb,
                         torch.as_tensor(values, dtype=f64), name=name)


def guess(name: str, t: Tensor) -> Tensor:
    """The family's initial approximation (m, 2) at t: the straight line between the boundary
    values (y′ its slope), for the layer y = 1."""
    _check(name)
    return FAMILIES[name][4](t)


def parameter_name(name: str) -> str:
    _check(name)
    return FAMILIES[name][3]


def layer_exact(t: Tensor, eps: float) -> Tensor:
    """y(t) of ε y″ = y, y(0) = y(1) = 1."""
    r = 1.0 / math.sqrt(eps)
    return torch.cosh((t - 0.5) * r) / math.cosh(0.5 * r)


def slope(x: Tensor) -> float:
    """y′(0) of a solution x (m, 2) at its shooting points."""
    return float(x[0, 1])
