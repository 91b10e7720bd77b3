"""Devices: where the tensors of a solve live, and which code paths suit that device.

The engine follows its inputs: a solve runs where ``t`` and the guess are.  The entry points that
build their own tensors (:func:`shootlab.estimate`, :func:`shootlab.estimation.output_error.estimate_output_error`,
:func:`shootlab.diagnosis.diagnose`, the ``--device`` option of the command line) take
``device="cpu" | "cuda" | "auto"`` (:func:`resolve_device`).

Two kinds of code differ between the CPU and an accelerator:

* LAPACK-style kernels that an accelerator runs as a host loop over the matrices of a batch
  (``torch.linalg.eigvals``, ``torch.linalg.qr``, ``torch.ormqr``): on an accelerator the engine
  uses batched matrix products instead (:func:`shootlab.bvp.shooting.spectral_bounds`,
  :func:`shootlab.bvp.linalg.apply_qt`);
* host synchronisation (``bool(tensor)``, ``.item()``, boolean indexing) in the loops over the steps
  of an integration: cheap on the CPU, a stall of the whole device queue on an accelerator, where
  the fixed-step integrators advance every row and mark failures instead of dropping rows.

:func:`accelerator_paths` says which applies to a tensor; :func:`forced_accelerator_paths` runs
the accelerator's paths on the CPU (for tests: they give the CPU's results to rounding).
"""
from __future__ import annotations

import contextlib
from typing import Iterator

import torch
from torch import Tensor

__all__ = ["resolve_device", "accelerator_paths", "forced_accelerator_paths", "DEVICES"]

#: the values of ``device=`` and of the command line's ``--device``
DEVICES = ("cpu", "cuda", "auto")

_FORCED = False


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``"cpu"`` (also None), ``"cuda"`` (``"cuda:1"``, a :class:`torch.device`) or ``"auto"``
    (CUDA where available, else the CPU) as a :class:`torch.device`.  Raises ``ValueError`` with one
    line for an unknown name and for CUDA where torch sees no GPU."""
    if device is None:
        return torch.device("cpu")
    if isinstance(device, str) and device.strip().lower() == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device.strip().lower() if isinstance(device, str) else device)
    except (RuntimeError, TypeError):
        raise ValueError(f"unknown device {device!r}: use one of {', '.join(DEVICES)}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: CUDA is not available (torch {torch.__version__} sees no GPU); "
                         f"use the CPU")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"unknown device {device!r}: use one of {', '.join(DEVICES)}")
    return dev


def accelerator_paths(x: Tensor | torch.device) -> bool:
    """Whether work on ``x`` (a tensor or a device) takes the accelerator's code paths: batched
    products instead of per-matrix LAPACK kernels, no host synchronisation per integration step
    (module docstring).  True off the CPU, and on the CPU inside :func:`forced_accelerator_paths`."""
    dev = x if isinstance(x, torch.device) else x.device
    return _FORCED or dev.type != "cpu"


@contextlib.contextmanager
def forced_accelerator_paths(on: bool = True) -> Iterator[None]:
    """Run the accelerator's code paths on the CPU too (tests compare them with the CPU's)."""
    global _FORCED
    old, _FORCED = _FORCED, bool(on)
    try:
        yield
    finally:
        _FORCED = old
