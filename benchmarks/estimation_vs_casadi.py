"""Mass–spring–damper parameter estimation: CasADi + IPOPT direct multiple shooting vs ``shootlab.estimate``.

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
  ``press`` Newton), and the same with ``newton="musn"`` (the time ratio is against ``press``).

The two solve different optimality conditions (output error vs optimal estimation with process
noise); on noise-free data both must return m = b = k = 1.  Reported side by side: success,
wall time (build + solve; CasADi's symbolic build separately), iterations, estimates, and the
time ratio CasADi / shootlab.  Ratios on a shared machine, not absolute seconds.

Needs the extra ``casadi`` (``pip install casadi``).

Run: ``python benchmarks/estimation_vs_casadi.py [--out FILE] [--starts 10 50]``.
"""
from __future__ import annotations

import argparse
import json
import sys
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


def run_shootlab(data: dict, start: float, newton: str = "press") -> dict:
    t0 = time.perf_counter()
    res = estimate(msd.model(), {c: data[c] for c in ("t", "u", "s")}, n_points=POINTS,
                   initial=dict(m=start, b=start, k=start), newton=newton, max_iter=100)
    return dict(solver="shootlab" if newton == "press" else f"shootlab {newton}", success=bool(res.success),
                message=res.message, iterations=int(res.iterations),
                seconds=time.perf_counter() - t0, parameters={k: float(v) for k, v in res.parameters.items()})


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(DEFAULT_OUT))
    ap.add_argument("--starts", nargs="*", type=float, default=[10.0, 50.0])
    args = ap.parse_args(argv)
    rows = []
    print("ok: converged (IPOPT: Solve_Succeeded) and m, b, k within 5 % of the truth 1")
    print(f"{'data':<11} {'from':>4} {'solver':<13} {'ok':>3} {'time [s]':>9} {'iter':>5} {'m':>10} {'b':>10} {'k':>10}  message")
    for label, data in records().items():
        for start in args.starts:
            pair = [run_casadi(data, start), run_shootlab(data, start), run_shootlab(data, start, "musn")]
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
            rows.append(dict(data=label, start=start, casadi=pair[0], shootlab=pair[1], shootlab_musn=pair[2],
                             time_ratio=ratio, max_parameter_difference=dev))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(points=POINTS, steps=STEPS, rows=rows), indent=2))
    print(f"wrote {out}")
    return rows


if __name__ == "__main__":
    main()
