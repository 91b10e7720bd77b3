"""shootlab: multiple shooting for stiff parameter-estimation problems, in PyTorch.

    prob = shootlab.BVP(rhs, bc_a, bc_b)
    res = shootlab.solve(prob, t, x_guess)

    model = shootlab.model(name=..., states=..., inputs=..., parameters=..., equations=..., channels=...)
    res = shootlab.estimate(model, "data.csv")          # a declared model (docs/your_own_model.md)
"""
import os as _os
import signal as _signal
import sys as _sys


def _interrupted_while_starting(signum, frame):
    print("shootlab: interrupted; nothing written", file=_sys.stderr)
    raise SystemExit(130)


# the shootlab command (`shootlab ...`, `python -m shootlab ...`) is starting: a Ctrl-C during the
# imports below ends it with one line instead of torch's import traceback (shootlab.cli.main restores
# the default handler)
if (_sys.argv[:1] == ["-m"] or _os.path.basename(_sys.argv[0] if _sys.argv else "") == "shootlab") \
        and _signal.getsignal(_signal.SIGINT) is _signal.default_int_handler:
    _signal.signal(_signal.SIGINT, _interrupted_while_starting)

import torch as _torch

# The tensors here are many small blocks: intra-op threads buy little and, on a loaded
# machine, cost far more than they give.  One thread unless SHOOTLAB_NUM_THREADS says otherwise.
_torch.set_num_threads(int(_os.environ.get("SHOOTLAB_NUM_THREADS", "1")))

from shootlab.bvp.allocator import tune as _tune_allocator

_tune_allocator()       # large tensors reused from the heap instead of fresh pages (shootlab.bvp.allocator)

from .bvp import (BVP, INTEGRATORS, NEWTON, ParametricBVP, ShootingResult, SingularJacobianError, Status,
                  get_integrator, get_newton, solve, solve_batch, suggest_shooting_points)

__version__ = "0.1.0"

# the estimation and diagnosis tiers on first use: they import scipy (about 1 s), which a BVP user
# does not need.  name -> module that defines it
_LAZY = {"model": "shootlab.estimation.declarative", "EstimationSettings": "shootlab.estimation.settings",
         "Variables": "shootlab.estimation.rows", "estimate": "shootlab.estimation.fit",
         "IdentificationModel": "shootlab.estimation.model", "EstimationResult": "shootlab.estimation.fit",
         "Measurements": "shootlab.estimation.data", "estimate_output_error": "shootlab.estimation.output_error",
         "diagnose": "shootlab.diagnosis.pipeline", "Effect": "shootlab.diagnosis.effects",
         "Library": "shootlab.diagnosis.effects"}

__all__ = ["BVP", "solve", "solve_batch", "ParametricBVP", "ShootingResult", "Status", "INTEGRATORS", "get_integrator", "NEWTON", "get_newton",
           "SingularJacobianError", "suggest_shooting_points", "__version__", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'shootlab' has no attribute {name!r}")
