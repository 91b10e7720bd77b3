"""shootlab: multiple shooting for stiff parameter estimation (command line).

Every error ends the command with one line ``shootlab <command>: error: <message>`` on stderr and
exit status 2 (1 when an estimation or diagnosis ran but did not converge); Ctrl-C ends it with
``interrupted after iteration k; nothing written`` and status 130.  An output folder holds one
run: results are written to a new folder next to ``--out`` that replaces it whole when complete;
a non-empty ``--out`` that shootlab did not write is refused unless ``--force``
(:func:`shootlab.outputs.check_output_folder`).  Set SHOOTLAB_TRACEBACK=1 to see the traceback of
an error.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import warnings
from pathlib import Path
from types import TracebackType
from typing import NoReturn

from shootlab.bvp.device import DEVICES
from shootlab.outputs import version
from .arguments import (FORCE_HELP, OUT_HELP, SOLVER_FLAGS, add_option, add_solver_flags, load_data, number,
                        solver_flags)

EPILOG = "Errors: one line on stderr, exit 2; Ctrl-C: exit 130, nothing written; SHOOTLAB_TRACEBACK=1 shows tracebacks."
MODEL_HELP = "show this help and exit; after --model NAME, also NAME's options (--option)"


class _Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors (``prog: error: message (see prog --help)``, exit 2)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class _RecordParser(_Parser):
    """The parser of ``shootlab simulate NAME``: a flag the record does not declare is its own error,
    named with the flags it has (not the top parser's ``unrecognized arguments``)."""

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            flags = [f for a in self._actions for f in a.option_strings if f.startswith("--") and f != "--help"]
            self.error(f"{' '.join(extras)}: not an option of this record; its options are {', '.join(flags)}")
        return namespace, extras


class _ModelHelp(argparse.Action):
    """``-h/--help`` of a command that takes ``--model``: the help, then the options (``--option
    KEY=VALUE``) of the model named before it, e.g. ``shootlab estimate --model confined --help``."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from shootlab.estimation.lookup import describe_options, find_model
        parser.print_help()
        spec = getattr(namespace, "model", None)
        if spec is None:
            print("\n--option KEY=VALUE sets a keyword argument of the model's factory: "
                  f"{parser.prog} --model NAME --help lists NAME's")
        else:
            try:
                print(f"\noptions of the model {spec} (--option KEY=VALUE): {describe_options(find_model(spec))}")
            except ValueError as exc:
                print(f"\nmodel {spec}: {_one_line(exc)}")
        parser.exit()


# ----------------------------------------------------------------------------- commands
def dispatch(argv: list[str]) -> int:
    """Run a ``shootlab`` command inside another (``shootlab demo`` runs ``estimate``): parsed and
    run without :func:`main`'s handler, so errors and Ctrl-C are reported by the outer command."""
    args = build_parser().parse_args(argv)
    return args.func(args)


def _estimate(args: argparse.Namespace) -> int:
    """shootlab estimate --model MODEL --data DATA.csv --out DIR: optimal estimation by multiple shooting."""
    from shootlab.bvp.device import resolve_device
    from shootlab.estimation.fit import default_points, estimate, phase, progress_line
    from shootlab.cli.arguments import parse_assignments, parse_initial
    from shootlab.estimation.lookup import resolve_model
    from shootlab.outputs import check_output_folder, correlation_lines, parameter_lines, staged_folder, write_estimation

    out = check_output_folder(args.out, force=args.force, inputs={"--data": args.data})
    device = resolve_device(args.device)
    model = resolve_model(args.model, parse_assignments(args.option, "--option"))
    initial = parse_initial(args.initial, model)
    log = None if args.quiet else progress_line
    with phase(f"reading {args.data}", log):
        data = load_data(args.data, needed=model.measured, inputs=model.given)
    solve_options = solver_flags(args, model)
    if args.method == "output-error":
        return _estimate_output_error(args, model, data, initial, out, device)
    points = args.points or default_points(model, data, initial=initial)
    print(f"estimating {model.name}: parameters {model.parameters}, {points} shooting points", flush=True)
    res = estimate(model, data, n_points=points, initial=initial, verbose=not args.quiet, device=device,
                   fallback=not args.no_fallback, **solve_options)
    if res.success:
        res.uncertainty                 # the covariance, with its own progress line
    with phase(f"writing {out}", log), staged_folder(out, "estimate") as tmp:
        write_estimation(res, tmp, plots=not args.no_plots)
        files = sorted(p.name for p in tmp.iterdir())
    print(res.message)
    print("parameters (± standard error):\n  " + "\n  ".join(parameter_lines(res) + correlation_lines(res)))
    print(f"J = {res.J:.6g}, {res.seconds:.1f} s; wrote {out}/: {', '.join(files)}")
    return 0 if res.success else 1


def _estimate_output_error(args: argparse.Namespace, model, data, initial, out: Path, device=None) -> int:
    """``estimate --method output-error``: the parameters of the model's free run fitted to the
    record (:mod:`shootlab.estimation.output_error`); the shooting options do not apply."""
    from shootlab.estimation.output_error import estimate_output_error
    from shootlab.outputs import estimate_lines, staged_folder, write_output_error

    ignored = [f"--{k.replace('_', '-')}" for k in ("points",) + SOLVER_FLAGS if getattr(args, k) is not None]
    ignored += ["--no-fallback"] if args.no_fallback else []
    if ignored:
        raise ValueError(f"{', '.join(ignored)} set the multiple-shooting solve; --method output-error has none")
    print(f"estimating {model.name} by output error: parameters {model.parameters}", flush=True)
    res = estimate_output_error(model, data, initial=initial, log=None if args.quiet else print, device=device)
    with staged_folder(out, "estimate --method output-error") as tmp:
        write_output_error(res, data, tmp, plots=not args.no_plots)
        files = sorted(p.name for p in tmp.iterdir())
    print(res.message)
    print("parameters (± standard error):\n  " + "\n  ".join(estimate_lines(model, res.parameters,
                                                                            res.standard_errors)))
    print("RMS misfit / noise level: " + ", ".join(f"{c} {v:.3g}" for c, v in res.rms.items())
          + f"; {res.evaluations} free runs, {res.seconds:.1f} s; wrote {out}/: {', '.join(files)}")
    return 0 if res.success else 1


def _diagnose(args: argparse.Namespace) -> int:
    """shootlab diagnose: where / which effect / how far it shrinks (shootlab.diagnosis)."""
    from .diagnose import run_cli
    return run_cli(args)


def _simulate(args: argparse.Namespace) -> int:
    """shootlab simulate RECORD: write an example record (entry points ``shootlab.records``) as CSV,
    with the options the record declares (:class:`shootlab.registry.Record`)."""
    from shootlab.estimation.data import write_table
    from shootlab.outputs import check_output_file

    out = Path(args.out or f"{args.record}.csv")
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder; give a file name such as {out / (args.record + '.csv')}")
    check_output_file(out)
    record = args.record_entry
    table, columns, what = record(seed=args.seed, **{o.name: getattr(args, o.name) for o in record.options})
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.partial")
    try:
        write_table(tmp, table, columns)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    print(f"wrote {out}: {what}; {len(table['t'])} samples, columns {','.join(columns)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from shootlab import registry

    models = ", ".join(registry.names("models"))
    p = _Parser(prog="shootlab", description=__doc__.splitlines()[0], epilog=EPILOG)
    p.add_argument("--version", action="version", version=f"shootlab {version()}")
    sub = p.add_subparsers(dest="command", required=True)
    for name in registry.names("commands"):             # installed packages' commands: shootlab demo
        registry.load("commands", name)(sub)

    e = sub.add_parser("estimate", help="estimate states, inputs and parameters of a model from measured data",
                       epilog=EPILOG, add_help=False)
    e.add_argument("-h", "--help", action=_ModelHelp, help=MODEL_HELP)
    e.add_argument("--model", required=True, help=f"built-in name ({models}) "
                   "or path/to/file.py:object or package.module:object")
    e.add_argument("--data", required=True, help="CSV with a header row: t and the model's measured channels "
                   "(separator , ; or TAB; units in the header like 't [s]' are allowed; text columns are ignored)")
    e.add_argument("--method", choices=["shooting", "output-error"], default="shooting",
                   help="shooting: the report's optimal estimation, a TPBVP solved by multiple shooting "
                        "(default); output-error: the free run's parameters fitted to the record (no model "
                        "errors; where the TPBVP is too stiff to solve, e.g. confined with 50 elements)")
    e.add_argument("--points", type=number(int, 2), default=None,
                   help="number of shooting points (default: the model's, more on a record longer than the one "
                        "they were chosen for: shootlab.estimation.fit.default_points)")
    e.add_argument("--initial", nargs="*", metavar="NAME=VALUE", help="initial parameter values")
    e.add_argument("--option", nargs="*", metavar="KEY=VALUE", help="keyword arguments of the model's "
                   "factory, e.g. elements=20 (--model NAME --help lists them)")
    add_solver_flags(e)
    e.add_argument("--out", required=True, help=OUT_HELP)
    e.add_argument("--force", action="store_true", help=FORCE_HELP)
    e.add_argument("--device", choices=DEVICES, default="cpu",
                   help="where to solve: cpu (default), cuda (a GPU; an error where torch sees none) or auto "
                        "(cuda where available)")
    e.add_argument("--quiet", action="store_true", help="no per-iteration progress lines")
    e.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    e.set_defaults(func=_estimate)

    g = sub.add_parser("diagnose", help="find the structural error of a model from its residuals, rank candidate "
                       "effects, re-estimate with the best and report how far the misfit shrinks", epilog=EPILOG,
                       add_help=False)
    g.add_argument("-h", "--help", action=_ModelHelp, help=MODEL_HELP)
    g.add_argument("--model", required=True, help=f"built-in name ({models}; each with its library of candidate "
                   "effects) or path/to/file.py:object or package.module:object (the module may define "
                   "diagnosis_library; otherwise the generic library: sensor offsets)")
    g.add_argument("--data", required=True, help="identification CSV: t and the model's measured channels")
    g.add_argument("--validate", default=None, help="validation CSV with another input (free-run comparison)")
    g.add_argument("--design", default=None, metavar="CSV",
                   help="write the input of an experiment that tells the selected effect from its look-alike (or "
                        "its nearest rival) to this CSV: t and the given channels; run it on the rig and diagnose "
                        "again with its record as --validate")
    g.add_argument("--out", required=True, help="output folder: diagnosis.json, report.md, figures; " + OUT_HELP)
    g.add_argument("--force", action="store_true", help=FORCE_HELP)
    g.add_argument("--option", nargs="*", metavar="KEY=VALUE", help="keyword arguments of the model's factory "
                   "(--model NAME --help lists them)")
    g.add_argument("--points", type=number(int, 2), default=None, help="number of shooting points (model default)")
    g.add_argument("--initial", nargs="*", metavar="NAME=VALUE", help="initial parameter values of the nominal model")
    g.add_argument("--library", default=None, help="candidate library: path/to/file.py:object or package.module:object")
    g.add_argument("--effects", default=None, help="comma-separated subset of the library's effects")
    g.add_argument("--seed", type=number(int, 0), default=0, help="seed of the noise-floor surrogate (default 0)")
    g.add_argument("--device", choices=DEVICES, default="cpu",
                   help="where the estimates are solved: cpu (default), cuda or auto (cuda where available)")
    add_solver_flags(g)
    g.add_argument("--quiet", action="store_true", help="no progress lines")
    g.add_argument("--verbose", action="store_true", help="also a line per Newton iteration of every estimate")
    g.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    g.set_defaults(func=_diagnose)

    s = sub.add_parser("simulate", help="write an example record (CSV) used in the README and docs",
                       description="Write an example record as CSV (the installed records: entry points "
                       "shootlab.records); shootlab simulate RECORD --help lists the record's options.",
                       epilog=EPILOG)
    records = s.add_subparsers(dest="record", required=True, metavar="RECORD", help="which record",
                               parser_class=_RecordParser)
    for name in registry.names("records"):
        _add_record(records, name)
    return p


def _add_record(records, name: str) -> None:
    """The parser of ``shootlab simulate NAME``: ``--out``, ``--seed`` and the options the record
    declares; a record that does not load is listed, and running it reports why."""
    from shootlab import registry
    from shootlab.registry import Record
    try:
        record = registry.load("records", name)
        if not isinstance(record, Record):
            raise ValueError(f"record {name!r} is a {type(record).__name__}, not a shootlab.registry.Record")
    except ValueError as exc:
        r = records.add_parser(name, help=f"(does not load: {_one_line(exc)})")
        r.set_defaults(func=lambda args, exc=exc: _raise(exc))
        return
    r = records.add_parser(name, help=record.description, description=record.description, epilog=EPILOG)
    r.add_argument("--out", default=None, help=f"CSV file to write (default {name}.csv)")
    r.add_argument("--seed", type=number(int, 0), default=0, help="noise seed (default 0)")
    for option in record.options:
        add_option(r, option)
    r.set_defaults(func=_simulate, record_entry=record, prog=r.prog)


def _raise(exc: Exception) -> int:
    raise exc


# ----------------------------------------------------------------------------- one handler
def _iterations_done(tb: TracebackType | None) -> int | None:
    """Newton iterations completed by the solve that a Ctrl-C interrupted (all its continuation
    stages), read from the interrupted frames; None when no solve was running."""
    from shootlab.bvp.newton import NewtonOutcome

    before, done, found = 0, 0, False
    while tb is not None:
        frame = tb.tb_frame
        local = frame.f_locals
        if frame.f_code.co_name == "solve" and isinstance(local.get("iters"), int):
            before, done, found = local["iters"], 0, True          # earlier stages of this (innermost) solve
        else:
            for v in list(local.values()):
                if isinstance(v, NewtonOutcome):
                    done, found = (v.history[-1]["iteration"] if v.history else 0), True
        tb = tb.tb_next
    return before + done if found else None


@contextlib.contextmanager
def _one_line_warnings(prog: str):
    """Warnings as ``prog: warning: message`` lines on stderr."""
    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{prog}: warning: {' '.join(str(message).split())}", file=sys.stderr)
    with warnings.catch_warnings():
        warnings.showwarning = show
        yield


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    """The ``shootlab`` command; returns the exit status."""
    from shootlab import _interrupted_while_starting
    if signal.getsignal(signal.SIGINT) is _interrupted_while_starting:
        signal.signal(signal.SIGINT, signal.default_int_handler)       # from here on: KeyboardInterrupt
    prog, args = "shootlab", None
    debug = bool(os.environ.get("SHOOTLAB_TRACEBACK"))
    with _one_line_warnings(prog):
        try:
            args = build_parser().parse_args(argv)
            prog = getattr(args, "prog", None) or f"shootlab {args.command}"
            return args.func(args)
        except KeyboardInterrupt as exc:
            k = _iterations_done(exc.__traceback__)
            done = "interrupted" if k is None else (
                f"interrupted after iteration {k}" if k else "interrupted before the first Newton iteration")
            wrote = getattr(args, "wrote", None)
            print(f"{prog}: {done}; " + (f"only {wrote} was written" if wrote else "nothing written"),
                  file=sys.stderr)
            return 130
        except Exception as exc:  # noqa: BLE001 - the one handler: every error is one line
            if debug:
                raise
            if isinstance(exc, (ValueError, OSError)):
                print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
                return 2
            if isinstance(exc, RuntimeError):      # a numerical failure (no convergence)
                print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
                return 1
            print(f"{prog}: error: {type(exc).__name__}: {_one_line(exc)} (SHOOTLAB_TRACEBACK=1 shows where)",
                  file=sys.stderr)
            return 2


def run() -> NoReturn:
    """The console script ``shootlab`` (and ``python -m shootlab``): :func:`main` in a process set up
    for one command and ended as soon as it is done (:mod:`shootlab.cli.process`)."""
    from .process import run as in_own_process
    in_own_process(main)


if __name__ == "__main__":
    run()
