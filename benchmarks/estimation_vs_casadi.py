"""Parameter estimation: CasADi + IPOPT direct multiple shooting vs ``shootlab.estimate``, side by side.

Two problems: the mass–spring–damper (``--problem msd``) and the confined compression of a
mixture with N = 3, 20 and 50 elements (``--problem mixture``, section at the end).

Mass–spring–damper.

What a user would otherwise write with CasADi (the peer for the speed of parameter estimation):
``m a + b v + k s = u`` on the same data (``manipulators.rig.msd_data``: 1001 samples on
[0, 10], m = b = k = 1; noise-free and with 1 % noise on s and u as in ``studies/msd_report``),
the same 101 shooting points and the same integrator (RK4, 10 steps per interval, so that the
steps land on the samples), from m = b = k = 10 and from 50, states started from the measured s
and its central differences (as shootlab's initial approximation).

* CasADi: decision variables x_k = (s, v) at the shooting points and θ = (m, b, k); continuity
  constraints x_{k+1} = Φ(x_k, θ) (RK4 with the measured u at the stage times, linearly
  interpolated); bounds m, b, k ≥ 0 (without them IPOPT went to m = −4e8 on the noisy record);
  objective Σ (s(t_i) − s_m(t_i))² over all samples (output error); IPOPT with the exact
  Hessian from CasADi's AD, tol 1e-10, MUMPS.
* shootlab: ``estimate(manipulators.msd.model(), ...)`` with the model's settings (the report's
  optimal estimation, eq. 2.7: process noise weighted by W, measurement residuals by V;
  default Newton), and the same with ``newton="armijo"`` and ``newton="appendix_a"`` (the time ratio is
  against the default).

The two solve different optimality conditions (output error vs optimal estimation with process
noise); on noise-free data both must return m = b = k = 1.  Reported side by side: success,
wall time (build + solve; CasADi's symbolic build separately), iterations, estimates, and the
time ratio CasADi / shootlab.  Ratios on a shared machine, not absolute seconds.

Needs the extra ``casadi`` (``pip install casadi``).

Mixture.  One record per noise level from an independent fine-grid simulator
(:func:`mixtures.simulation.simulate`: 200 elements, Radau in the eigenbasis, the report's
ramp-and-hold load, H = 2, K = 1, 401 samples on [0, 1]; noise-free and 1 % of each channel's RMS),
written to CSV; each tool estimates H, K of its N-element linear model from H = K = 4 on the same
CSV and the same 201 shooting points, as a user would run it — a whole command (a fresh Python
process: imports, reading, building, solving) — and the solve alone:

* CasADi: ``benchmarks/casadi_confined.py`` (numpy and CasADi only, no torch: the script a user
  would write): the N-element model s' = H K A₁ s + K b₁ u (its own assembly, equal to
  ``mixtures.prefit.filter_system``), implicit Euler with 2 steps per interval (the steps land on
  the samples), decision variables s at the shooting points and H, K ≥ 1e-6; continuity
  constraints; output error Σ (d − d_m)²/σ_d² + (p_1 − p_m)²/σ_p² over all samples (σ: the
  channel's spread); IPOPT, exact Hessian, tol 1e-8; states started from the report's linear
  profile of the measured displacement.  A second, *lifted* variant makes every implicit Euler
  step's state a decision variable (sparse bilinear constraints, no solves).  The peer's time is
  that of its faster variant among those that found H, K within 1 %.
* shootlab: ``shootlab estimate --model confined --option elements=N`` with the model's defaults
  (the report's optimal estimation: the TPBVP by multiple shooting), and the same command with
  ``--method output-error`` (:mod:`shootlab.estimation.output_error`: what CasADi solves, the free run of the
  N-element model — exact for the piecewise-linear load — fitted by Gauss–Newton; no shooting
  points).  At N = 50 the TPBVP cannot be solved on 201 points (its Newton matrix is singular: the
  implicit midpoint rule no longer separates the fastest growing and decaying modes, README), so
  there the output-error command is shootlab's answer.

Whole commands (``--problem command``): the user's comparison — ``shootlab estimate --model
confined --option elements=N`` on the 1 %-noise record, *with its figures*, against the peer's
script (``benchmarks/casadi_confined.py``, direct multiple shooting) on the same CSV, each a fresh
process timed from start to exit, in ``--repeats`` rounds whose order alternates (peer first,
then shootlab first, …), with ``--no-plots`` and ``--method output-error`` beside them, and the
floors: ``import torch``, torch's first forward-mode product (what the engine's first Jacobian
pays once: the jvp decompositions and torch._dynamo imported) and ``import casadi``.  Wall and CPU
seconds (user + system of the process, steadier on a shared machine); the medians, every round's
times and the estimates go to ``benchmarks/results/command_vs_casadi.json``.

Run: ``python benchmarks/estimation_vs_casadi.py [--problem msd|mixture|command|all] [--out FILE]
[--starts 10 50] [--elements 3 20 50] [--no-lifted] [--repeats 5] [--record CSV]``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from manipulators import msd  # noqa: E402
from manipulators.rig import msd_data, msd_noisy_data  # noqa: E402
from shootlab.estimation import estimate  # noqa: E402

DEFAULT_OUT = ROOT / "benchmarks" / "results" / "estimation_vs_casadi.json"
MIXTURE_OUT = ROOT / "benchmarks" / "results" / "mixture_vs_casadi.json"
POINTS, STEPS = 101, 10


def records() -> dict[str, dict]:
    return {"noise-free": msd_data(), "1% noise": msd_noisy_data(0.01, seed=0)}


def run_casadi(data: dict, start: float) -> dict:
    """Direct multiple shooting with IPOPT (module docstring)."""
    import casadi as ca

    t_build = time.perf_counter()
    t, u, s_m = data["t"], data["u"], data["s"]
    nodes = np.linspace(t[0], t[-1], POINTS)
    h = (nodes[1] - nodes[0]) / STEPS
    x, th, uu = ca.SX.sym("x", 2), ca.SX.sym("theta", 3), ca.SX.sym("u", 3)   # u at t, t + h/2, t + h

    def f(xx, ui):
        m, b, k = th[0], th[1], th[2]
        return ca.vertcat(xx[1], (ui - b * xx[1] - k * xx[0]) / m)
    k1 = f(x, uu[0])
    k2 = f(x + h / 2 * k1, uu[1])
    k3 = f(x + h / 2 * k2, uu[1])
    k4 = f(x + h * k3, uu[2])
    step = ca.Function("step", [x, th, uu], [x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])
    # the measured u at every RK4 stage time of every interval (linear interpolation)
    fine = np.linspace(t[0], t[-1], (POINTS - 1) * STEPS * 2 + 1)
    u_fine = np.interp(fine, t, u)
    X = ca.MX.sym("X", 2, POINTS)
    TH = ca.MX.sym("TH", 3)
    cost, g = 0, []
    sample = np.interp(nodes[0], t, s_m)
    cost += (X[0, 0] - sample) ** 2
    for kk in range(POINTS - 1):             # building the NLP graph (not the hot loop)
        xk = X[:, kk]
        for j in range(STEPS):
            i = (kk * STEPS + j) * 2
            xk = step(xk, TH, ca.DM(u_fine[i:i + 3]))
            tj = nodes[kk] + (j + 1) * h
            cost += (xk[0] - np.interp(tj, t, s_m)) ** 2
        g.append(xk - X[:, kk + 1])
    nlp = dict(x=ca.vertcat(ca.vec(X), TH), f=cost, g=ca.vertcat(*g))
    solver = ca.nlpsol("dms", "ipopt", nlp, {"ipopt.tol": 1e-10, "ipopt.print_level": 0, "print_time": False,
                                              "ipopt.max_iter": 500})
    build = time.perf_counter() - t_build
    s0 = np.interp(nodes, t, s_m)
    v0 = np.gradient(s0, nodes)
    x0 = np.concatenate([np.column_stack([s0, v0]).reshape(-1), [start] * 3])
    t0 = time.perf_counter()
    lbx = np.concatenate([np.full(2 * POINTS, -np.inf), np.zeros(3)])          # m, b, k ≥ 0
    sol = solver(x0=x0, lbg=0, ubg=0, lbx=lbx)
    solve = time.perf_counter() - t0
    stats = solver.stats()
    p = np.asarray(sol["x"][-3:]).ravel()
    return dict(solver="casadi+ipopt", success=stats["return_status"] == "Solve_Succeeded",
                message=f"{stats['return_status']}, objective {float(sol['f']):.4g}",
                iterations=int(stats["iter_count"]), build_s=build, solve_s=solve, seconds=build + solve,
                parameters=dict(m=float(p[0]), b=float(p[1]), k=float(p[2])))


def run_shootlab(data: dict, start: float, newton: str | None = None) -> dict:
    t0 = time.perf_counter()
    res = estimate(msd.model(), {c: data[c] for c in ("t", "u", "s")}, n_points=POINTS,
                   initial=dict(m=start, b=start, k=start), max_iter=100, **({"newton": newton} if newton else {}))
    return dict(solver="shootlab" if newton is None else f"shootlab {newton}", success=bool(res.success),
                message=res.message, iterations=int(res.iterations),
                seconds=time.perf_counter() - t0, parameters={k: float(v) for k, v in res.parameters.items()})


def run_msd(args) -> list[dict]:
    rows = []
    print("ok: converged (IPOPT: Solve_Succeeded) and m, b, k within 5 % of the truth 1")
    print(f"{'data':<11} {'from':>4} {'solver':<13} {'ok':>3} {'time [s]':>9} {'iter':>5} {'m':>10} {'b':>10} {'k':>10}  message")
    for label, data in records().items():
        for start in args.starts:
            pair = [run_casadi(data, start), run_shootlab(data, start), run_shootlab(data, start, "armijo"),
                    run_shootlab(data, start, "appendix_a")]
            for r in pair:
                p = r["parameters"]
                r["within_5_percent"] = bool(r["success"] and max(abs(v - 1.0) for v in p.values()) < 0.05)
                print(f"{label:<11} {start:4g} {r['solver']:<13} {'yes' if r['within_5_percent'] else 'NO':>3} "
                      f"{r['seconds']:9.2f} {r['iterations']:5d} {p['m']:10.6f} {p['b']:10.6f} {p['k']:10.6f}  "
                      f"{r['message'][:60]}")
            ratio = pair[0]["seconds"] / pair[1]["seconds"]
            dev = max(abs(pair[0]["parameters"][k] - pair[1]["parameters"][k]) for k in "mbk")
            print(f"{'':<17} time ratio casadi/shootlab {ratio:.2f} (casadi build {pair[0]['build_s']:.2f} s + "
                  f"solve {pair[0]['solve_s']:.2f} s); max |θ_casadi − θ_shootlab| = {dev:.2e}")
            rows.append(dict(data=label, start=start, casadi=pair[0], shootlab=pair[1], shootlab_press=pair[2],
                             shootlab_musn=pair[3], time_ratio=ratio, max_parameter_difference=dev))
    out = Path(args.out or DEFAULT_OUT)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(points=POINTS, steps=STEPS, rows=rows), indent=2))
    print(f"wrote {out}")
    return rows


# -- the mixture (confined compression) -----------------------------------------------------------
TRUE_HK = dict(H=2.0, K=1.0)
FINE_ELEMENTS, MIX_POINTS = 200, 201
PEER = ROOT / "benchmarks" / "casadi_confined.py"      # the peer's whole command: numpy + CasADi, no torch
COMMAND_OUT = ROOT / "benchmarks" / "results" / "command_vs_casadi.json"
#: torch's one-off costs of forward mode: its first jvp scripts the jvp decompositions, and its first
#: elementwise product with a constant runs a Python reference wrapped to import torch._dynamo
FORWARD_MODE = ("import torch; x = torch.ones(4, dtype=torch.float64); "
                "torch.func.jvp(lambda y: 2.0 * torch.sin(y), (x,), (x,))")


def mixture_records(folder: Path) -> dict[str, Path]:
    """The fine-grid records (module docstring), written as CSV into ``folder``."""
    from mixtures.confined import ConfinedCompression
    from mixtures.loads import DEFAULT_EXPERIMENT
    from mixtures.simulation import simulate
    from shootlab.estimation.data import Measurements

    t = np.linspace(0.0, 1.0, 401)
    sim = simulate(ConfinedCompression(elements=FINE_ELEMENTS), t, load=DEFAULT_EXPERIMENT, **TRUE_HK)
    clean = dict(t=t, load=sim.load, displacement=sim.displacement, pressure=sim.pressure)
    rng = np.random.default_rng(1)
    noisy = dict(clean, **{c: clean[c] + 0.01 * np.sqrt(np.mean(clean[c] ** 2)) * rng.standard_normal(t.size)
                           for c in ("load", "displacement", "pressure")})
    out = {}
    for label, table in (("noise-free", clean), ("1% noise", noisy)):
        out[label] = folder / f"confined_{label.replace('%', 'pct').replace(' ', '_')}.csv"
        Measurements(table["t"], {c: table[c] for c in ("load", "displacement", "pressure")}).to_csv(out[label])
    return out


def _timed(cmd: list[str]) -> tuple[float, subprocess.CompletedProcess]:
    wall, proc, _ = _timed_cpu(cmd)
    return wall, proc


def _timed_cpu(cmd: list[str]) -> tuple[float, subprocess.CompletedProcess, float]:
    """(wall seconds, the finished process, its CPU seconds: user + system, from the children's
    resource usage — steadier than the wall time on a shared machine)."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, proc, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def run_shootlab_mixture(csv: Path, N: int, tmp: Path, method: str) -> dict:
    """``shootlab estimate --model confined --option elements=N [--method output-error]`` on ``csv``,
    timed as a whole command; its ``estimate.json`` read back."""
    out_dir = tmp / f"shootlab_{N}_{method}_{csv.stem}"
    wall, proc = _timed([sys.executable, "-m", "shootlab", "estimate", "--model", "confined", "--option",
                         f"elements={N}", "--method", method, "--data", str(csv), "--out", str(out_dir),
                         "--quiet", "--no-plots"])
    est = json.loads((out_dir / "estimate.json").read_text()) if (out_dir / "estimate.json").exists() else {}
    return dict(solver="shootlab" if method == "shooting" else "shootlab OE",
                success=bool(est.get("success", False)) and proc.returncode == 0,
                message=(est.get("message") or proc.stderr.strip()[-200:]),
                iterations=int(est.get("iterations", est.get("evaluations", 0))),
                solve_s=float(est.get("seconds", float("nan"))), command_s=wall,
                parameters={k: float(est.get("parameters", {}).get(k, float("nan"))) for k in ("H", "K")})


def run_mixture(args) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        csvs = mixture_records(Path(tmp))
        print(f"records: {FINE_ELEMENTS}-element simulation, H = 2, K = 1; both start from H = K = 4, "
              f"{MIX_POINTS} shooting points")
        print(f"{'data':<11} {'N':>3} {'solver':<13} {'ok':>3} {'command [s]':>11} {'solve [s]':>9} {'iter':>5} "
              f"{'H':>9} {'K':>9}  message")
        for label, csv in csvs.items():
            for N in args.elements:
                variants = []
                for lifted in (False, True)[:1 + (not args.no_lifted)]:
                    cmd = [sys.executable, str(PEER), str(csv), str(N)]
                    wall_c, proc = _timed(cmd + (["--lifted"] if lifted else []))
                    cas = json.loads(proc.stdout.strip().splitlines()[-1]) if proc.returncode == 0 else dict(
                        solver="casadi lifted" if lifted else "casadi+ipopt", success=False,
                        message=proc.stderr.strip()[-200:], iterations=0, solve_s=float("nan"),
                        parameters=dict(H=float("nan"), K=float("nan")))
                    cas["command_s"] = wall_c
                    variants.append(cas)
                ours = [run_shootlab_mixture(csv, N, Path(tmp), method) for method in ("shooting", "output-error")]
                for r in variants + ours:
                    err = max(abs(r["parameters"][k] / TRUE_HK[k] - 1.0) for k in TRUE_HK)
                    r["max_relative_error"] = err
                    r["within_1_percent"] = bool(r["success"] and err < 0.01)
                    print(f"{label:<11} {N:3d} {r['solver']:<13} {'yes' if r['within_1_percent'] else 'no':>3} "
                          f"{r['command_s']:11.2f} {r['solve_s']:9.2f} {r['iterations']:5d} {r['parameters']['H']:9.5f} "
                          f"{r['parameters']['K']:9.5f}  {r['message'][:60]}", flush=True)
                # the peer's time: its fastest variant among those that got H, K right (else the fastest)
                good = [r for r in variants if r["within_1_percent"]] or variants
                cas = min(good, key=lambda r: r["command_s"])
                ratios = {}
                for sl in ours:
                    key = "" if sl["solver"] == "shootlab" else "_output_error"
                    ratios[f"ratio_command{key}"] = sl["command_s"] / cas["command_s"]
                    ratios[f"ratio_solve{key}"] = sl["solve_s"] / cas["solve_s"]
                    print(f"{'':<15} {sl['solver']} / {cas['solver']}: whole command "
                          f"{ratios[f'ratio_command{key}']:.3f}, solve alone {ratios[f'ratio_solve{key}']:.3f}",
                          flush=True)
                rows.append(dict(data=label, elements=N, casadi=variants[0], casadi_lifted=variants[1] if len(variants) > 1 else None,
                                 shootlab=ours[0], shootlab_output_error=ours[1], peer=cas["solver"], **ratios))
    out = Path(args.out or MIXTURE_OUT)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(points=MIX_POINTS, fine_elements=FINE_ELEMENTS, truth=TRUE_HK, rows=rows), indent=2))
    print(f"wrote {out}")
    return rows


def _estimate_json(folder: Path) -> dict:
    path = folder / "estimate.json"
    return json.loads(path.read_text()) if path.exists() else {}


def run_commands(args) -> dict:
    """Whole commands side by side (module docstring, ``--problem command``)."""
    N = args.elements[0] if len(args.elements) == 1 else 20
    rounds = []
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(args.record) if args.record else mixture_records(Path(tmp))["1% noise"]
        shoot = [sys.executable, "-m", "shootlab", "estimate", "--model", "confined", "--option", f"elements={N}",
                 "--data", str(csv), "--quiet"]
        variants = {"casadi": ([sys.executable, str(PEER), str(csv), str(N)], None),
                    "shootlab": (shoot, "figures"),
                    "shootlab --no-plots": (shoot + ["--no-plots"], "no_plots"),
                    "shootlab output-error": (shoot + ["--method", "output-error"], "output_error"),
                    # the floors: what any torch program pays before its first result, and the peer's import
                    "python: import torch": ([sys.executable, "-c", "import torch"], None),
                    "python: torch + first forward-mode product": ([sys.executable, "-c", FORWARD_MODE], None),
                    "python: import casadi": ([sys.executable, "-c", "import casadi"], None)}
        names = list(variants)
        print(f"record {csv}; N = {N}; {args.repeats} rounds, the order alternating")
        for r in range(args.repeats):
            order = names if r % 2 == 0 else names[::-1]
            row = {}
            for name in order:
                cmd, folder = variants[name]
                out = Path(tmp) / f"out_{folder}"
                wall, proc, cpu = _timed_cpu(cmd + (["--out", str(out)] if folder else []))
                if name == "casadi":
                    got = json.loads(proc.stdout.strip().splitlines()[-1]) if proc.returncode == 0 else {}
                elif folder:
                    got = _estimate_json(out) if proc.returncode == 0 else {}
                else:
                    got = dict(success=proc.returncode == 0, message=proc.stderr[-200:])
                row[name] = dict(seconds=wall, cpu_seconds=cpu, returncode=proc.returncode, success=bool(got.get("success")),
                                 parameters=got.get("parameters"), message=got.get("message", proc.stderr[-200:]),
                                 solve_s=got.get("solve_s", got.get("seconds")))
            rounds.append(row)
            print(f"round {r + 1}: " + ", ".join(f"{n} {row[n]['seconds']:.2f} s ({row[n]['cpu_seconds']:.2f} s CPU)"
                                                for n in names), flush=True)
    median, ratios = {}, {}
    for key in ("seconds", "cpu_seconds"):
        median[key] = {n: float(np.median([row[n][key] for row in rounds])) for n in names}
        ratios[key] = {n: float(np.median([row[n][key] / row["casadi"][key] for row in rounds]))
                       for n in names if n != "casadi"}
    for n in names:
        last = rounds[-1][n]
        found = (f"; H, K within {100 * max(abs(last['parameters'][k] / TRUE_HK[k] - 1.0) for k in TRUE_HK):.2f} % "
                 f"of 2, 1; {last['message'][:60]}" if last["success"] and last["parameters"] else "")
        print(f"{n:<44} median {median['seconds'][n]:6.2f} s wall, {median['cpu_seconds'][n]:6.2f} s CPU"
              + (f"; / casadi {ratios['seconds'][n]:.2f} wall, {ratios['cpu_seconds'][n]:.2f} CPU" if n != "casadi" else "")
              + found)
    result = dict(elements=N, record=str(csv) if args.record else "1% noise, 200-element simulation (mixture_records)",
                  repeats=args.repeats, median=median, median_ratio_to_casadi=ratios, rounds=rounds,
                  load_average=os.getloadavg(), cpus=os.cpu_count(), python=sys.version.split()[0])
    out = Path(args.out or COMMAND_OUT)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")
    return result


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", choices=["msd", "mixture", "command", "all"], default="all",
                    help="which section to run (all: msd and mixture)")
    ap.add_argument("--repeats", type=int, default=5, help="command: rounds of the whole commands")
    ap.add_argument("--record", default=None, help="command: the CSV (default: the 1 %% noise mixture record)")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/<section>.json)")
    ap.add_argument("--starts", nargs="*", type=float, default=[10.0, 50.0], help="msd: initial m = b = k")
    ap.add_argument("--elements", nargs="*", type=int, default=[3, 20, 50], help="mixture: numbers of elements")
    ap.add_argument("--no-lifted", action="store_true", help="mixture: skip CasADi's lifted variant (670 s at N = 50, "
                    "and not within 1 %% at N = 20 or 50)")
    args = ap.parse_args(argv)
    rows = []
    if args.problem in ("msd", "all"):
        rows += run_msd(args)
    if args.problem in ("mixture", "all"):
        rows += run_mixture(args)
    if args.problem == "command":
        rows.append(run_commands(args))
    return rows


if __name__ == "__main__":
    main()
