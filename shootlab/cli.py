"""shootlab: multiple shooting for stiff parameter estimation (command line)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path



def _demo(args: argparse.Namespace) -> int:
    """The main job on a built-in example: the report's mass–spring–damper (§3.4) — simulated
    data are written to DIR/msd.csv and m, b, k estimated from the report's worse start (50)."""
    from manipulators.rig import msd_data, save_csv

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    d = msd_data(noise=args.noise, u_noise=args.noise, seed=0)
    csv_path = out / "msd.csv"
    save_csv(csv_path, {k: d[k] for k in ("t", "u", "s")}, columns=["t", "u", "s"])
    print(f"wrote {csv_path} (m = b = k = 1, noise {args.noise:g}); now, as a user would type it:")
    argv = ["estimate", "--model", "msd", "--data", str(csv_path), "--initial", "m=50", "b=50", "k=50",
            "--out", str(out)]
    print("  shootlab " + " ".join(argv), flush=True)
    return main(argv)


def _estimate(args: argparse.Namespace) -> int:
    """shootlab estimate --model MODEL --data DATA.csv --out DIR: optimal estimation by multiple shooting."""
    from .estimation import estimate
    from .models import parse_assignments, resolve_model
    from .outputs import correlation_lines, parameter_lines, write_estimation

    model = resolve_model(args.model, parse_assignments(args.option, "--option"))
    initial = parse_assignments(args.initial, "--initial")
    solve_options = dict(model.settings.get("solve", {}))
    for key in ("integrator", "steps", "newton", "max_iter", "tol"):
        if getattr(args, key) is not None:
            solve_options[key] = getattr(args, key)
    points = args.points or model.settings.get("points", 101)
    print(f"estimating {model.name}: parameters {model.parameters}, {points} shooting points", flush=True)
    res = estimate(model, args.data, n_points=points, initial=initial, verbose=not args.quiet, **solve_options)
    info = write_estimation(res, args.out, plots=not args.no_plots)
    print(res.message)
    print("parameters (± standard error):\n  " + "\n  ".join(parameter_lines(res) + correlation_lines(res)))
    print(f"J = {res.J:.6g}, {info['iterations']} iterations, {res.seconds:.1f} s; wrote {args.out}/estimate.json")
    return 0 if res.success else 1


def _diagnose(args: argparse.Namespace) -> int:
    """shootlab diagnose: where / which effect / how far it shrinks (shootlab.diagnosis)."""
    from .diagnosis import run_cli
    return run_cli(args)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="shootlab", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="the main job on a built-in example: estimate the report's "
                       "mass-spring-damper from simulated data, with progress output")
    d.add_argument("--noise", type=float, default=0.0, help="measurement noise std (default 0)")
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    d.set_defaults(func=_demo)

    e = sub.add_parser("estimate", help="estimate states, inputs and parameters of a model from measured data")
    e.add_argument("--model", required=True, help="built-in name (msd, flexible, flexible_friction, confined) "
                   "or path/to/file.py:object or package.module:object")
    e.add_argument("--data", required=True, help="CSV with a header row: t and the model's measured channels")
    e.add_argument("--points", type=int, default=None, help="number of shooting points (model default, else 101)")
    e.add_argument("--initial", nargs="*", metavar="NAME=VALUE", help="initial parameter values")
    e.add_argument("--option", nargs="*", metavar="KEY=VALUE", help="model settings, e.g. elements=20")
    e.add_argument("--integrator", default=None, help="integrator name (model default)")
    e.add_argument("--steps", type=int, default=None, help="steps per interval for fixed-step integrators")
    e.add_argument("--newton", default=None, choices=["press", "musn"], help="Newton strategy (default press)")
    e.add_argument("--max-iter", dest="max_iter", type=int, default=None, help="maximum Newton iterations")
    e.add_argument("--tol", type=float, default=None, help="Newton tolerance")
    e.add_argument("--out", required=True, help="output folder")
    e.add_argument("--quiet", action="store_true", help="no per-iteration progress lines")
    e.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    e.set_defaults(func=_estimate)

    g = sub.add_parser("diagnose", help="find the structural error of a model from its residuals, rank candidate "
                       "effects, re-estimate with the best and report how far the misfit shrinks")
    g.add_argument("--model", required=True, help="built-in name (flexible, msd, confined) or path/to/file.py:object "
                   "or package.module:object (the module may define diagnosis_library)")
    g.add_argument("--data", required=True, help="identification CSV: t and the model's measured channels")
    g.add_argument("--validate", default=None, help="validation CSV with another input (free-run comparison)")
    g.add_argument("--out", required=True, help="output folder: diagnosis.json, report.md, figures")
    g.add_argument("--option", nargs="*", metavar="KEY=VALUE", help="model settings")
    g.add_argument("--library", default=None, help="candidate library: path/to/file.py:object or package.module:object")
    g.add_argument("--effects", default=None, help="comma-separated subset of the library's effects")
    g.add_argument("--seed", type=int, default=0, help="seed of the noise-floor surrogate (default 0)")
    g.add_argument("--quiet", action="store_true", help="no progress lines")
    g.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    g.set_defaults(func=_diagnose)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValueError as exc:
        print(f"shootlab {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
