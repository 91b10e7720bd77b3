"""The mass–spring–damper estimation TPBVP: ``scipy.integrate.solve_bvp`` vs ``shootlab.estimate``.

The same problem for both: :class:`shootlab.estimation.optimality.EstimationProblem` of
``manipulators.msd.model()`` (report weights) on noise-free data (1001 samples on [0, 10],
m = b = k = 1), the same initial approximation
``shootlab.estimation.fit.initial_approximation(model, data, t, initial)`` on the same 101-point
mesh ``t``, from m = b = k = 10 and from 50.

* scipy: collocation (``solve_bvp``, 4th order Lobatto IIIA) with the torch right-hand side
  wrapped as ``fun(t, y)``, y (2 nx, k) → rhs of (k, 2 nx) with t (k,), ``bc`` from ``bc_a``,
  ``bc_b``; ``tol`` 1e-6, ``max_nodes`` 1e5; Jacobians by scipy's finite differences
  (default) or, with ``--fun-jac``, by torch autograd.
* shootlab: ``estimate`` with the model's solver settings (RK4, 10 steps per interval,
  ``newton="armijo"``).

Reported side by side: success/message, wall time, parameter estimates (time average of the
parameter trajectories on the data times, as ``estimate`` does), final mesh size, the max
deviation between the two solutions' x(t) (states and parameter trajectories) on the data
times, and the time ratio scipy / shootlab.  These are ratios on a shared, loaded machine,
not timed tests.

Run: ``python benchmarks/estimation_vs_scipy.py [--out FILE] [--fun-jac] [--starts 10 50]``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from scipy.integrate import solve_bvp

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from manipulators import msd  # noqa: E402
from manipulators.rig import msd_data  # noqa: E402
from shootlab.estimation.data import Measurements  # noqa: E402
from shootlab.estimation.optimality import EstimationProblem
from shootlab.estimation import estimate
from shootlab.estimation.fit import initial_approximation
from shootlab.outputs import fmt  # noqa: E402

DEFAULT_OUT = ROOT / "benchmarks" / "results" / "estimation_vs_scipy.json"


def scipy_functions(prob: EstimationProblem):
    """fun, bc and (autograd) fun_jac in solve_bvp's layout, counting rhs evaluations."""
    calls = dict(fun=0, jac=0)

    def fun(t, y):
        calls["fun"] += 1
        with torch.no_grad():
            out = prob.rhs(torch.from_numpy(np.ascontiguousarray(t, dtype=np.float64)),
                           torch.from_numpy(np.ascontiguousarray(y.T, dtype=np.float64)))
        return out.detach().numpy().T

    def bc(ya, yb):
        with torch.no_grad():
            return torch.cat([prob.bc_a(torch.from_numpy(ya.copy())).reshape(-1),
                              prob.bc_b(torch.from_numpy(yb.copy())).reshape(-1)]).numpy()

    def fun_jac(t, y):
        calls["jac"] += 1
        tt = torch.from_numpy(np.ascontiguousarray(t, dtype=np.float64))
        Y = torch.from_numpy(np.ascontiguousarray(y.T, dtype=np.float64))
        # the rhs is pointwise in the batch: d(sum_k rhs_k)/dY gives every (n, n) block
        J = torch.autograd.functional.jacobian(lambda Z: prob.rhs(tt, Z).sum(0), Y)   # (n, k, n)
        return J.permute(0, 2, 1).detach().numpy()                                    # (n, n, k)

    return fun, bc, fun_jac, calls


def run_scipy(prob: EstimationProblem, t: torch.Tensor, X0: torch.Tensor, tol: float, max_nodes: int,
              use_jac: bool) -> dict:
    fun, bc, fun_jac, calls = scipy_functions(prob)
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sol = solve_bvp(fun, bc, t.numpy(), X0.numpy().T, fun_jac=fun_jac if use_jac else None,
                            tol=tol, max_nodes=max_nodes, verbose=0)
    except Exception as exc:                                   # noqa: BLE001 — record how it fails
        return dict(success=False, status=None, message=f"{type(exc).__name__}: {exc}",
                    seconds=time.perf_counter() - t0, nodes=None, rhs_calls=calls["fun"],
                    jac_calls=calls["jac"], sol=None, warnings=[])
    return dict(success=bool(sol.success), status=int(sol.status), message=str(sol.message),
                seconds=time.perf_counter() - t0, nodes=int(sol.x.size), iterations=int(sol.niter),
                max_rms_residual=float(np.max(sol.rms_residuals)), rhs_calls=calls["fun"],
                jac_calls=calls["jac"], sol=sol, warnings=sorted({str(w.message)[:200] for w in caught}))


def parameters_from(x_params: np.ndarray, ts: np.ndarray, names) -> dict[str, float]:
    span = ts[-1] - ts[0]
    return {n: float(np.trapezoid(x_params[:, j], ts) / span) for j, n in enumerate(names)}


def run(starts=(10.0, 50.0), tol=1e-6, max_nodes=100_000, points=101, use_jac=False) -> list[dict]:
    model = msd.model()
    raw = msd_data()
    data = Measurements.coerce({k: raw[k] for k in ("t", "u", "s")})
    ts = data.t
    solve_opts = dict(model.settings.solver)
    rows = []
    for start in starts:
        initial = dict(m=start, b=start, k=start)
        prob = EstimationProblem(model, data)
        t = torch.linspace(float(ts[0]), float(ts[-1]), points, dtype=torch.float64)
        X0 = initial_approximation(model, data, t, initial)

        print(f"from {start:g}: scipy solve_bvp (tol {tol:g}, max_nodes {max_nodes}, "
              f"{'autograd' if use_jac else 'finite-difference'} Jacobian) ...", flush=True)
        sp = run_scipy(prob, t, X0, tol, max_nodes, use_jac)
        print(f"   {'OK' if sp['success'] else 'FAIL'} {sp['seconds']:.1f} s: {sp['message']}", flush=True)

        print(f"from {start:g}: shootlab.estimate ({points} points, {solve_opts}) ...", flush=True)
        t0 = time.perf_counter()
        res = estimate(model, data, n_points=points, initial=initial, **solve_opts)
        sl_seconds = time.perf_counter() - t0
        print(f"   {'OK' if res.success else 'FAIL'} {sl_seconds:.1f} s: {res.message}", flush=True)

        x_sl = np.stack([res.x[n].numpy() for n in model.names], -1)          # (K, nx) on the data times
        row = dict(start=start, points=points,
                   scipy=dict((k, v) for k, v in sp.items() if k != "sol"),
                   shootlab=dict(success=res.success, message=res.message, seconds=sl_seconds,
                                 iterations=res.iterations,
                                 jacobian_evaluations=res.shooting.jacobian_evaluations,
                                 residual_norm=res.shooting.residual_norm, parameters=res.parameters,
                                 settings=solve_opts))
        if sp["sol"] is not None:
            x_sp = sp["sol"].sol(ts)[:model.nx].T                                 # (K, nx)
            ns = len(model.states)
            row["scipy"]["parameters"] = parameters_from(x_sp[:, ns:], ts, model.parameters)
            dev = np.abs(x_sp - x_sl).max(0)
            row["max_deviation_x"] = float(dev.max()) if np.isfinite(dev).all() else math.nan
            row["max_deviation_per_component"] = {n: float(d) for n, d in zip(model.names, dev)}
        else:
            row["scipy"]["parameters"] = None
            row["max_deviation_x"] = None
        row["time_ratio_scipy_over_shootlab"] = sp["seconds"] / sl_seconds
        rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    head = (f"{'from':>4} {'solver':<9} {'ok':<4} {'time [s]':>9} {'nodes':>6} {'iter':>5} "
            f"{'m':>12} {'b':>12} {'k':>12}   message")
    lines = [head, "-" * len(head)]
    for r in rows:
        for name, key in (("scipy", "scipy"), ("shootlab", "shootlab")):
            s = r[key]
            p = s.get("parameters") or {}
            nodes = s.get("nodes") if key == "scipy" else r["points"]
            it = s.get("iterations")
            lines.append(f"{r['start']:>4g} {name:<9} {'yes' if s['success'] else 'NO':<4} {s['seconds']:>9.2f} "
                         f"{fmt(nodes, '>6d')} {fmt(it, '>5d')} {fmt(p.get('m'), '12.9f')} {fmt(p.get('b'), '12.9f')} "
                         f"{fmt(p.get('k'), '12.9f')}   {s['message'][:90]}")
        lines.append(f"{'':>4} max |x_scipy - x_shootlab| on the data times: {fmt(r['max_deviation_x'], '.2e')}; "
                     f"time ratio scipy/shootlab: {r['time_ratio_scipy_over_shootlab']:.2f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"JSON output (default {DEFAULT_OUT})")
    ap.add_argument("--starts", type=float, nargs="+", default=[10.0, 50.0])
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--max-nodes", type=int, default=100_000)
    ap.add_argument("--points", type=int, default=101)
    ap.add_argument("--fun-jac", action="store_true", help="give solve_bvp the autograd Jacobian of the rhs")
    args = ap.parse_args(argv)
    rows = run(tuple(args.starts), args.tol, args.max_nodes, args.points, args.fun_jac)
    print()
    print(table(rows))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(torch=torch.__version__, threads=torch.get_num_threads(), tol=args.tol, max_nodes=args.max_nodes,
                points=args.points, scipy_jacobian="autograd" if args.fun_jac else "finite differences",
                data="manipulators.rig.msd_data(): 1001 samples on [0, 10], m = b = k = 1, noise-free")
    args.out.write_text(json.dumps(dict(meta=meta, rows=rows), indent=2, default=float))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
