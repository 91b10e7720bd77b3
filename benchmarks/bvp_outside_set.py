"""Side-by-side check on BVPs outside the Cash/Mazzia test set: scipy.integrate.solve_bvp vs
shootlab.solve, both with the settings of ``benchmarks/bvp_testset.py`` (solve_bvp tol 1e-8 from
101 nodes; shootlab's defaults with rtol 1e-8, atol 1e-10 on 101 shooting points), on problems
the engine's defaults were not tuned on: LQ optimal control in Hamiltonian form (growing and
decaying modes), a nonlinear pendulum, a beam (4 equations), steady Burgers layers, Bratu at
λ = 3, Falkner–Skan (3 equations).

The reference is solve_bvp at tol 1e-11 with up to 10⁶ nodes; errors are max-norm over all
components on 2001 points, relative to the reference's max.  Times: best of 3 after one untimed
run each, one thread.  Prints the table and the geometric mean of the time ratios; saves JSON.

Run: ``python benchmarks/bvp_outside_set.py [--out FILE]`` (about 20 s).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from scipy.integrate import solve_bvp

_REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(_REPO))
import shootlab  # noqa: E402
from shootlab.outputs import json_ready  # noqa: E402

OUT = _REPO / "benchmarks" / "results" / "bvp_outside_set.json"


def _system(rows):
    """f(t, y) for numpy (components first) and torch (components last) from one rule."""
    def f_np(t, y):
        return np.vstack(rows(np, t, list(y)))

    def f_torch(t, x):
        return torch.stack([r + torch.zeros_like(x[..., 0]) for r in rows(torch, t, list(x.unbind(-1)))], -1)
    return f_np, f_torch


def problems() -> list[dict]:
    """name, interval, rule for f, boundary conditions as (left indices, values), (right ...), guess."""
    out = []
    for a, T in ((1.0, 10.0), (3.0, 5.0)):           # x' = a x − λ, λ' = −x − a λ: modes ±√(a²+1)
        out.append(dict(name=f"LQ Hamiltonian a={a:g}, T={T:g}", span=(0.0, T),
                        rows=lambda xp, t, y, a=a: [a * y[0] - y[1], -y[0] - a * y[1]],
                        left=((0,), (1.0,)), right=((1,), (0.0,)),
                        guess=lambda t, T=T: np.vstack([1 - t / T, 0 * t])))
    out.append(dict(name="pendulum, T = 3", span=(0.0, 3.0),
                    rows=lambda xp, t, y: [y[1], -xp.sin(y[0])],
                    left=((0,), (0.0,)), right=((0,), (1.0,)), guess=lambda t: np.vstack([t / 3, 0 * t + 1 / 3])))
    out.append(dict(name="beam y'''' = 1 + y", span=(0.0, 1.0),
                    rows=lambda xp, t, y: [y[1], y[2], y[3], 1 + y[0]],
                    left=((0, 2), (0.0, 0.0)), right=((0, 2), (0.0, 0.0)), guess=lambda t: np.zeros((4, t.size))))
    for eps in (0.05, 0.01):                          # ε y'' = −y y'
        out.append(dict(name=f"steady Burgers ε={eps:g}", span=(0.0, 1.0),
                        rows=lambda xp, t, y, e=eps: [y[1], -y[0] * y[1] / e],
                        left=((0,), (1.0,)), right=((0,), (-1.0,)), guess=lambda t: np.vstack([1 - 2 * t, -2 + 0 * t])))
    out.append(dict(name="Bratu λ = 3", span=(0.0, 1.0),
                    rows=lambda xp, t, y: [y[1], -3 * xp.exp(y[0])],
                    left=((0,), (0.0,)), right=((0,), (0.0,)), guess=lambda t: np.zeros((2, t.size))))
    for beta in (0.0, 0.5):                           # f''' + f f'' + β(1 − f'²) = 0 on [0, 6]
        out.append(dict(name=f"Falkner–Skan β={beta:g}", span=(0.0, 6.0),
                        rows=lambda xp, t, y, b=beta: [y[1], y[2], -y[0] * y[2] - b * (1 - y[1] ** 2)],
                        left=((0, 1), (0.0, 0.0)), right=((1,), (1.0,)),
                        guess=lambda t: np.vstack([t * t / 12, t / 6, 0 * t + 1 / 6])))
    return out


def _bc(p):
    (li, lv), (ri, rv) = p["left"], p["right"]
    bc_np = lambda ya, yb: np.array([ya[i] - v for i, v in zip(li, lv)] + [yb[i] - v for i, v in zip(ri, rv)])
    bc_a = lambda xa: torch.stack([xa[..., i] - v for i, v in zip(li, lv)], -1)
    bc_b = lambda xb: torch.stack([xb[..., i] - v for i, v in zip(ri, rv)], -1)
    return bc_np, bc_a, bc_b


def _best(run, repeat: int = 3):
    run()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t0)
    return out, min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    print(f"{'problem':28s} {'scipy':>6s} {'err':>8s} {'ms':>7s} | {'shootlab':>8s} {'err':>8s} {'ms':>7s} {'it':>3s} | ratio")
    for p in problems():
        f_np, f_torch = _system(p["rows"])
        bc_np, bc_a, bc_b = _bc(p)
        a, b = p["span"]
        x = np.linspace(a, b, 101)
        ref = solve_bvp(f_np, bc_np, x, p["guess"](x), tol=1e-11, max_nodes=1_000_000)
        sp, t_sp = _best(lambda: solve_bvp(f_np, bc_np, x, p["guess"](x), tol=1e-8, max_nodes=200_000))
        t = torch.linspace(a, b, 101, dtype=torch.float64)
        guess = torch.as_tensor(p["guess"](t.numpy()).T.copy())
        sl, t_sl = _best(lambda: shootlab.solve(shootlab.BVP(f_torch, bc_a, bc_b), t, guess, rtol=1e-8, atol=1e-10))
        tq = np.linspace(a, b, 2001)
        scale = np.abs(ref.sol(tq)).max()
        err_sp = float(np.abs(sp.sol(tq) - ref.sol(tq)).max() / scale) if sp.success else math.nan
        err_sl = float(np.abs(sl.sol(torch.as_tensor(tq)).numpy().T - ref.sol(tq)).max() / scale) if sl.success else math.nan
        row = dict(problem=p["name"], reference_success=bool(ref.success), scipy_success=bool(sp.success),
                   scipy_error=err_sp, scipy_time=t_sp, scipy_nodes=int(sp.x.size), shootlab_success=bool(sl.success),
                   shootlab_error=err_sl, shootlab_time=t_sl, shootlab_iterations=sl.iterations,
                   shootlab_points=sl.points, time_ratio=t_sl / t_sp)
        rows.append(row)
        print(f"{p['name']:28s} {str(sp.success):>6s} {err_sp:8.1e} {t_sp * 1e3:7.1f} | {str(sl.success):>8s} "
              f"{err_sl:8.1e} {t_sl * 1e3:7.1f} {sl.iterations:3d} | {row['time_ratio']:5.2f}", flush=True)
    both = [r["time_ratio"] for r in rows if r["scipy_success"] and r["shootlab_success"] and r["reference_success"]]
    geo = math.exp(sum(map(math.log, both)) / len(both)) if both else math.nan
    print(f"GEOMETRIC MEAN time ratio shootlab / solve_bvp: {geo:.2f} over the {len(both)} problems both solve")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(json_ready(dict(cases=rows, geometric_mean_ratio=geo)), indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
