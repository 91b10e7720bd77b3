"""``python -m studies {sweep, stiffness, suggest, scaling} …`` — see ``python -m studies -h``.

Problems: ``msd``, ``flexible``, ``confined`` or ``module:object`` / ``file.py:object``, with
``--option key=value`` (see :mod:`studies.problems`); integrators as ``name:steps`` (``rk4:4``:
RK4 with 4 steps per shooting interval).  Every command writes plain files (CSV, JSON with the
settings and the package version, PNG) into ``--out`` and prints a summary.
"""
from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

import numpy as np

from shootlab.cli.arguments import parse_assignments


def _problem_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--problem", default="msd",
                   help="msd | flexible | confined | module:object | path/file.py:object (default msd)")
    p.add_argument("--option", nargs="*", default=[], metavar="KEY=VALUE",
                   help="problem options, e.g. elements=3, W_states=1e-4, V_s=1e6, H0=2.4")


def _exec_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dask", action="store_true", help="run the cases on a Dask LocalCluster")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the cases on the Dask scheduler at ADDRESS (e.g. tcp://host:8786)")
    p.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (default 2)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _points(values: list[str]) -> list[int]:
    """``100 200 400`` or ``log:100:10000:9`` (9 log-spaced values)."""
    out: list[int] = []
    for v in values:
        if v.startswith("log:"):
            _, lo, hi, k = v.split(":")
            out += [int(round(x)) for x in np.geomspace(float(lo), float(hi), int(k))]
        else:
            out.append(int(v))
    return sorted(set(out))


def _executor(args) -> str:
    return "dask" if (args.dask or args.scheduler) else "serial"


def _default_out(kind: str, label: str) -> Path:
    safe = label.replace("/", "_").replace(":", "_").replace("[", "_").replace("]", "").replace(",", "_").replace("=", "")
    return Path("out/studies") / kind / safe


def _replot(args) -> int:
    """``--replot``: the figures of a finished run redrawn from its JSON file, nothing solved."""
    module = importlib.import_module(f"{__package__}.{args.command}")
    print(f"wrote {module.replot(args.replot)} next to {args.replot}")
    return 0


def cmd_sweep(args) -> int:
    from . import problems, sweep

    if args.family:
        return cmd_parameter_sweep(args)
    options = parse_assignments(args.option, "--option")
    settings = sweep.SweepSettings(problem=args.problem, options=options, integrators=args.integrators,
                                   points=_points(args.points), max_iter=args.max_iter, accuracy=args.accuracy,
                                   memory=not args.no_memory)
    label = problems.build(args.problem, options).name
    out = Path(args.out) if args.out else _default_out("sweep", label)
    res = sweep.run(settings, out, executor=_executor(args), scheduler=args.scheduler, workers=args.workers,
                    progress=not args.quiet)
    print(f"{res['problem']}: {res['description']}  (reference: {res['reference_source']})")
    print(f"{'integrator':10s} {'m':>7s} {'kind':>11s} {'iter':>5s} {'jac':>4s} {'error':>9s} {'time [s]':>9s} {'peak MB':>8s}")
    for r in res["rows"]:
        print(f"{r['integrator']:10s} {r['m']:7d} {r['kind']:>11s} {r['iterations']:5d} {r['jacobian_evaluations']:4d} "
              f"{r['error']:9.2e} {r['seconds']:9.2f} {r['peak_mb']:8.1f}")
    print(sweep.format_comparison(sweep.comparison([res])))
    print(f"wrote {out}/sweep.csv, sweep.json, sweep.png ({res['wall_seconds']:.0f} s, {res['executor']})")
    return 0


def cmd_parameter_sweep(args) -> int:
    """``sweep --family NAME --values …``: a parameter sweep, every (integrator, m) one batch."""
    from . import sweep

    if not args.values:
        raise SystemExit("python -m studies sweep: --family needs --values")
    out = Path(args.out) if args.out else _default_out("sweep", f"{args.family}_family")
    res = sweep.parameter_sweep(args.family, args.values, _points(args.points), args.integrators,
                                max_iter=args.max_iter, device=args.device, out=out)
    print(f"{'problem':24s} {'integrator':10s} {'m':>7s} {'kind':>11s} {'iter':>5s} {'slope':>12s} {'error':>9s}")
    for r in res["rows"]:
        print(f"{r['problem']:24s} {r['integrator']:10s} {r['m']:7d} {r['kind']:>11s} {r['iterations']:5d} "
              f"{r['quantities']['slope']:12.6g} {r['error']:9.2e}")
    print(f"wrote {out}/parameter_sweep.csv, parameter_sweep.json ({res['wall_seconds']:.1f} s)")
    return 0


def cmd_stiffness(args) -> int:
    from . import stiffness

    options = parse_assignments(args.option, "--option")
    res = stiffness.analyse(args.problem, options, points=args.points, solve=args.solve,
                            integrators=args.integrators, m_for_h=args.m_for_h)
    out = Path(args.out) if args.out else _default_out("stiffness", res["problem"])
    stiffness.write(res, out)
    print(stiffness.report(res))
    print(f"wrote {out}/stiffness.csv, stiffness_intervals.csv, stiffness.json, stiffness.png")
    return 0


def cmd_suggest(args) -> int:
    from . import problems, sweep

    if args.validate:
        return _validate(args)
    options = parse_assignments(args.option, "--option")
    prob = problems.build(args.problem, options)
    if not args.check:
        preds = sweep.predictions(prob, args.integrators, args.probe_points)
        print(f"{prob.name}: {prob.description}")
        for integ, p in preds.items():
            print(f"  {integ:10s} m = {p['m']:7d}  (stability {p['m_stability']}, growth {p['m_growth']}; "
                  f"limited by {p['limited_by']}); kappa = {p['kappa']:.4g}, kappa+ = {p['kappa_plus']:.4g}, "
                  f"max|lambda| = {p['rho']:.4g}, h = {p['h']:.3g}, kappa*h = {p['kappa_h']:.3g}")
        return 0
    out = Path(args.out) if args.out else _default_out("suggest", prob.name)
    res = sweep.check(args.problem, options, args.integrators, out, executor=_executor(args),
                      scheduler=args.scheduler, workers=args.workers, progress=not args.quiet,
                      max_iter=args.max_iter, accuracy=args.accuracy)
    table = sweep.comparison([res])
    print(sweep.format_comparison(table))
    print(f"wrote {out}/sweep.csv, sweep.json, sweep.png")
    return 0


def _validate(args) -> int:
    from . import problems, sweep

    out = Path(args.out) if args.out else Path("out/studies/suggest_validation")
    cases = [(p, o) for p, o in sweep.VALIDATION if not args.only or p in args.only]
    integrators = args.integrators if args.integrators_given else sweep.VALIDATION_INTEGRATORS
    client = cluster = None
    if _executor(args) == "dask":               # one cluster for all the problems
        from distributed import Client, LocalCluster
        if args.scheduler:
            client = Client(args.scheduler)
        else:
            cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                                   dashboard_address=":0")
            client = Client(cluster)
    results = []
    try:
        for problem, options in cases:
            label = problems.build(problem, options).name
            sub = (Path(args.sweep_dir) if args.sweep_dir else out) / _default_out("", label).name
            if args.resume and (sub / "sweep.json").is_file():
                results.append(sweep.read(sub))
                continue
            res = sweep.check(problem, options, integrators, sub, progress=not args.quiet, max_iter=args.max_iter,
                              accuracy=args.accuracy, client=client)
            results.append(res)
            print(sweep.format_comparison(sweep.comparison([res])), flush=True)
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    table = sweep.comparison(results)
    text = sweep.format_comparison(table)
    print("\npredicted vs observed minimal number of shooting points (observed: smallest tested m from which "
          "every larger tested m converged with a stable integrator / also within "
          f"{args.accuracy:g} of the reference)\n" + text)
    ok = sum(r["within_factor_2"] for r in table)
    ok_a = sum(r["accurate_within_factor_2"] for r in table)
    one = [r for r in table if r["integrator"].endswith(":1")]
    ok1 = sum(r["within_factor_2"] for r in one)
    print(f"within a factor 2: {ok} of {len(table)} (converged and stable); {ok_a} of {len(table)} "
          f"(also accurate within {args.accuracy:g}); one step per interval: {ok1} of {len(one)}")
    out.mkdir(parents=True, exist_ok=True)
    meta = sweep.metadata(dict(cases=[[p, o] for p, o in cases], integrators=list(integrators),
                               accuracy=args.accuracy, max_iter=args.max_iter))
    (out / "validation.json").write_text(json.dumps(dict(kind="suggest_validation", **meta, table=table), indent=2))
    with open(out / "validation.csv", "w") as fh:
        cols = list(table[0]) if table else []
        fh.write(",".join(cols) + "\n")
        for r in table:
            fh.write(",".join(f'"{r[c]}"' if isinstance(r[c], str) and "," in r[c] else str(r[c]) for c in cols) + "\n")
    (out / "validation.txt").write_text(text + f"\nwithin a factor 2: {ok} of {len(table)} (converged and stable), "
                                        f"{ok_a} of {len(table)} (also accurate within {args.accuracy:g})\n")
    sweep.plot_comparison(table, out / "validation.png",
                          f"suggest_shooting_points vs sweeps: {ok} of {len(table)} within a factor 2 "
                          f"({ok1} of {len(one)} with one step per interval)")
    print(f"wrote {out}/validation.csv, validation.json, validation.txt, validation.png")
    return 0


def cmd_scaling(args) -> int:
    from . import scaling

    name, steps = args.integrator.split(":") if ":" in args.integrator else (args.integrator, "1")
    settings = scaling.ScalingSettings(problem=args.problem, options=parse_assignments(args.option, "--option"),
                                       m=tuple(_points(args.m)), elements=tuple(args.elements), n_points=args.n_points,
                                       integrator=name, steps=int(steps), repeat=args.repeat)
    out = Path(args.out) if args.out else Path("out/studies/scaling")
    res = scaling.run(settings, out, progress=not args.quiet)
    print(scaling.report(res))
    print(f"wrote {out}/scaling_m.csv, scaling_n.csv, scaling.json, scaling.png")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m studies", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("sweep", help="solve for a list of shooting-point counts and integrators")
    _problem_args(p)
    p.add_argument("--integrators", nargs="+", default=["euler:1", "rk4:1"], help="name:steps (default euler:1 rk4:1)")
    p.add_argument("--points", nargs="+", default=["log:50:800:5"], help="m values, or log:LO:HI:COUNT")
    p.add_argument("--max-iter", type=int, default=50, help="Newton iterations per case (default 50)")
    p.add_argument("--accuracy", type=float, default=0.05,
                   help="max relative error of the quantities vs the reference for a success (inf: off)")
    p.add_argument("--no-memory", action="store_true", help="skip the per-case memory measurement")
    p.add_argument("--family", default=None, choices=["layer", "troesch", "bratu"],
                   help="sweep a parameter of this family of BVPs instead of --problem (studies.families): all "
                        "--values of one (integrator, m) solved as one batch by shootlab.solve_batch")
    p.add_argument("--values", nargs="+", type=float, default=None, help="with --family: the parameter values")
    p.add_argument("--device", default=None, help="with --family: cpu (default), cuda or auto")
    p.add_argument("--out", default=None, help="output folder (default out/studies/sweep/PROBLEM)")
    p.add_argument("--replot", default=None, metavar="DIR_OR_JSON", help="redraw sweep.png from sweep.json only")
    _exec_args(p)
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("stiffness", help="local-Jacobian eigenvalues, kappa(t), +-pairing, kappa*h")
    _problem_args(p)
    p.add_argument("--points", type=int, default=101, help="shooting points to analyse (default 101)")
    p.add_argument("--solve", action="store_true", help="along the solution (the problem's reference settings)")
    p.add_argument("--m-for-h", type=int, default=None, help="grid for kappa*h (default --points)")
    p.add_argument("--integrators", nargs="+", default=["euler:1", "rk4:1", "rk4:4"],
                   help="name:steps for kappa*h per integrator (default euler:1 rk4:1 rk4:4)")
    p.add_argument("--out", default=None, help="output folder (default out/studies/stiffness/PROBLEM)")
    p.add_argument("--replot", default=None, metavar="DIR_OR_JSON", help="redraw the figures from stiffness.json only")
    p.set_defaults(func=cmd_stiffness)

    p = sub.add_parser("suggest", help="predict the minimal m; --check: verify by a sweep; --validate: all cases")
    _problem_args(p)
    p.add_argument("--integrators", nargs="+", default=None, help="name:steps (default euler:1 rk4:1 rk4:2 rk4:4)")
    p.add_argument("--probe-points", type=int, default=101,
                   help="shooting points at which the local Jacobians are probed (default 101)")
    p.add_argument("--check", action="store_true", help="sweep a ladder of m around the prediction")
    p.add_argument("--validate", action="store_true",
                   help="--check on the built-in validation set (3 problems x 3-4 stiffness levels)")
    p.add_argument("--only", nargs="*", default=None, help="with --validate: only these problems")
    p.add_argument("--resume", action="store_true", help="with --validate: reuse finished sub-sweeps")
    p.add_argument("--sweep-dir", default=None,
                   help="with --validate: where the per-problem sweeps go (default: inside --out)")
    p.add_argument("--max-iter", type=int, default=50, help="with --check/--validate: Newton iterations per case (default 50)")
    p.add_argument("--accuracy", type=float, default=0.05,
                   help="with --check/--validate: max relative error vs the reference for a success (default 0.05)")
    p.add_argument("--out", default=None, help="output folder (default out/studies/suggest/PROBLEM, "
                   "with --validate out/studies/suggest_validation)")
    _exec_args(p)
    p.set_defaults(func=cmd_suggest)

    p = sub.add_parser("scaling", help="time split and memory of one Newton iteration vs m and n")
    _problem_args(p)
    p.add_argument("--m", nargs="+", default=["100", "215", "464", "1000", "2154", "4642", "10000"],
                   help="shooting-point counts of the m scan, or log:LO:HI:COUNT (default 100 ... 10000)")
    p.add_argument("--elements", nargs="*", type=int, default=[1, 3, 8, 18, 48, 98],
                   help="confined-compression elements for the n scan, n = 2(N+2) (default up to n = 200)")
    p.add_argument("--n-points", type=int, default=201, help="shooting points of the n scan")
    p.add_argument("--integrator", default="rk4:1", help="name:steps (default rk4:1)")
    p.add_argument("--repeat", type=int, default=3, help="timed runs per case, the best is kept (default 3)")
    p.add_argument("--out", default=None, help="output folder (default out/studies/scaling)")
    p.add_argument("--replot", default=None, metavar="DIR_OR_JSON", help="redraw scaling.png from scaling.json only")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=cmd_scaling)
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if getattr(args, "command", None) == "suggest":
        args.integrators_given = args.integrators is not None
        if args.integrators is None:
            from .sweep import VALIDATION_INTEGRATORS
            args.integrators = list(VALIDATION_INTEGRATORS)
    try:
        return _replot(args) if getattr(args, "replot", None) else args.func(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
