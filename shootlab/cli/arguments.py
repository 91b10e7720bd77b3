"""What the command line reads: data files, numbers in range, ``key=value`` assignments and
initial values, and the help texts the commands share."""
from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from shootlab.estimation.model import IdentificationModel

#: what ``--out`` and ``--force`` do (:func:`shootlab.outputs.check_output_folder`)
OUT_HELP = ("output folder, holding one run: a rerun replaces it whole; a non-empty folder that shootlab "
            "did not write is refused")
FORCE_HELP = ("replace --out even if shootlab did not write it: its files are deleted when the run completes, "
              "and it counts as shootlab's from now on")


def load_data(path: str, what: str = "--data", needed: list[str] | None = None, inputs: list[str] | None = None):
    """Measurements from a CSV; ValueError if a ``needed`` channel is missing or not numeric, else
    the reader's notes are printed (one line each).  The missing samples of the ``inputs`` (the
    model's given channels) are made good (:meth:`~shootlab.estimation.data.Measurements.fill_inputs`), each
    thing done printed as a note."""
    from shootlab.estimation.data import Measurements
    try:
        data = Measurements.from_csv(path)
    except OSError as exc:
        raise ValueError(f"{what} {path}: cannot read it ({exc.strerror or exc})") from None
    if needed:
        data.require(needed, float(data.t[0]), float(data.t[-1]))
    data, filled = data.fill_inputs(inputs or [])
    for note in data.notes + filled:
        print(f"note: {note}")
    return data


# ----------------------------------------------------------------------------- parser
def number(kind: type, low: float, strict: bool = False):
    """An argparse ``type``: a finite ``kind`` (int or float) at least ``low`` (above it where
    ``strict``); otherwise a usage error ``argument --x: must be …, got …`` (exit 2)."""
    bound = f"{'> ' if strict else '≥ '}{low:g}"

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'an integer' if kind is int else 'a number'}") from None
        if not (math.isfinite(value) and (value > low if strict else value >= low)):
            raise argparse.ArgumentTypeError(f"must be a finite number {bound}, got {text}" if kind is float
                                             else f"must be an integer {bound}, got {text}")
        return value
    return parse


def parse_initial(items: list[str] | None, model: IdentificationModel, what: str = "--initial") -> dict[str, float]:
    """``['m=10', 'b=2']`` -> ``{'m': 10.0, 'b': 2.0}``; ValueError naming the flag and the key for an
    unknown parameter (with the model's parameters) or a value that is not a number."""
    out: dict[str, float] = {}
    for key, value in parse_assignments(items, what, numbers=False).items():
        if key not in model.parameters:
            raise ValueError(f"{what} {key}: model {model.name!r} has no parameter {key!r}; "
                             f"its parameters are {', '.join(model.parameters)}")
        try:
            out[key] = float(value)
        except ValueError:
            raise ValueError(f"{what} {key}={value}: {value!r} is not a number") from None
    return out


def parse_assignments(items: list[str] | None, what: str, numbers: bool = True) -> dict:
    """['a=1', 'b=x'] -> {'a': 1, 'b': 'x'} (with ``numbers``: numbers where they parse, ints stay
    ints, true/false are booleans; else the strings)."""
    out: dict = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"{what} {item!r}: expected name=value")
        value = value.strip()
        if key.strip() in out:
            raise ValueError(f"{what} {key.strip()}: given twice")
        if not numbers:
            out[key.strip()] = value
            continue
        for conv in (int, float):
            try:
                out[key.strip()] = conv(value)
                break
            except ValueError:
                continue
        else:
            out[key.strip()] = {"true": True, "false": False}.get(value.lower(), value)
    return out


def add_option(p: argparse.ArgumentParser, option) -> None:
    """The flag ``--name`` of a declared :class:`~shootlab.registry.Option`: a number checked by
    :func:`number` where it has a lower bound, its choices, ``--name`` / ``--no-name`` for a
    bool; the help ends with the default."""
    flag = "--" + option.name.replace("_", "-")
    text = option.help + (f" (default {option.default})" if option.default is not None else "")
    kw = dict(dest=option.name, default=option.default, help=text.replace("%", "%%"))
    if option.kind is bool:
        p.add_argument(flag, action=argparse.BooleanOptionalAction, **kw)
        return
    kind = option.kind
    if kind is float or (kind is int and option.low is not None):      # a float is finite, bounded or not
        kind = number(option.kind, -math.inf if option.low is None else option.low, option.strict)
    p.add_argument(flag, type=kind, choices=option.choices, **kw)


#: the options of shootlab.solve that ``estimate`` and ``diagnose`` take as flags (:func:`add_solver_flags`)
SOLVER_FLAGS = ("integrator", "steps", "newton", "max_iter", "tol")


def solver_flags(args: argparse.Namespace, model) -> dict:
    """The model's solver settings (``settings.solver``) with the flags of :data:`SOLVER_FLAGS` given over them."""
    options = dict(model.settings.solver)
    options.update({key: getattr(args, key) for key in SOLVER_FLAGS if getattr(args, key) is not None})
    return options


def add_solver_flags(p: argparse.ArgumentParser) -> None:
    """--integrator, --steps, --newton, --max-iter, --tol and --no-fallback (``estimate``, ``diagnose``)."""
    from shootlab.bvp.newton import NEWTON
    p.add_argument("--integrator", default=None, help="integrator name (model default)")
    p.add_argument("--steps", type=number(int, 1), default=None, help="steps per interval for fixed-step integrators")
    p.add_argument("--newton", default=None, choices=sorted(NEWTON),
                   help="Newton strategy (default: the model's, else shootlab.solve's)")
    p.add_argument("--max-iter", dest="max_iter", type=number(int, 1), default=None, help="maximum Newton iterations")
    p.add_argument("--tol", type=number(float, 0.0, strict=True), default=None, help="Newton tolerance")
    p.add_argument("--no-fallback", action="store_true",
                   help="where the Newton iteration stalls, stop there; by default (with --newton too) "
                        "armijo and then trust_region are tried from the same start")
