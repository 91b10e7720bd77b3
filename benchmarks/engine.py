"""Engine benchmark, everything measured side by side in one run (ratios, not absolute seconds).

1. batched integration of all intervals vs a Python loop over intervals (same integrator);
2. interval Jacobians by autograd through the integrator vs the report's finite differences (eq. 3.7):
   time and max deviation;
3. one ``press`` Newton iteration split into F build, Jacobian build, factorisation and
   back-substitution (report fig. 3.8);
4. interval Jacobians by batched reverse sweeps (``shootlab.bvp.shooting.JACOBIAN_CHUNK`` unit
   cotangents per sweep) vs one sweep per row, on Troesch and on two estimation TPBVPs: the
   flexible manipulator with friction (n = 20, RK4 x 10) and confined compression with 20
   elements (n = 44, implicit midpoint x 2), 101 shooting points each.

    python benchmarks/engine.py [--out benchmarks/results/engine.json] [--quick]
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

import shootlab
from shootlab.bvp.integrators import get_integrator
from shootlab.bvp.shooting import ShootingSystem

f64 = torch.float64


def troesch(mu: float = 5.0) -> shootlab.BVP:
    return shootlab.BVP(lambda t, x: torch.stack([x[..., 1], mu * torch.sinh(mu * x[..., 0])], -1),
                        lambda xa: xa[:1], lambda xb: xb[:1] - 1.0, name=f"troesch({mu})")


def best_of(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def system(m: int, integrator: str = "rk4", steps: int = 4, jacobian: str = "autograd"):
    t = torch.linspace(0.0, 1.0, m, dtype=f64)
    s = torch.stack([t, torch.ones_like(t)], -1)
    return ShootingSystem(troesch(), t, get_integrator(integrator, steps=steps), jacobian), s


def batched_vs_loop(m: int, integrator: str, repeat: int) -> dict:
    sysm, s = system(m, integrator)
    integ, rhs = sysm.integrator, sysm.prob.rhs
    t0, t1 = sysm.t0, sysm.t1

    def loop():
        return torch.cat([integ.integrate(rhs, t0[i:i + 1], t1[i:i + 1], s[i:i + 1]).y for i in range(m - 1)])

    def batched():
        return integ.integrate(rhs, t0, t1, s[:-1]).y

    dev = float((loop() - batched()).abs().max())
    tb, tl = best_of(batched, repeat), best_of(loop, max(1, repeat - 1))
    return dict(m=m, integrator=integrator, batched_s=tb, loop_s=tl, speedup=tl / tb, max_deviation=dev)


def autograd_vs_fd(m: int, integrator: str, repeat: int) -> dict:
    sa, s = system(m, integrator, jacobian="autograd")       # forward sensitivities
    sf, _ = system(m, integrator, jacobian="fd")
    Ya, Yf = sa.interval_jacobians(s), sf.interval_jacobians(s)
    ta = best_of(lambda: sa.interval_jacobians(s), repeat)
    tf = best_of(lambda: sf.interval_jacobians(s), repeat)
    return dict(m=m, integrator=integrator, autograd_s=ta, fd_s=tf, time_ratio_autograd_over_fd=ta / tf,
                max_abs_deviation=float((Ya - Yf).abs().max()),
                max_rel_deviation=float(((Ya - Yf).abs() / Ya.abs().clamp_min(1e-12)).max()))


def newton_split(m: int, integrator: str, repeat: int) -> dict:
    from studies.scaling import newton_iteration_split
    sysm, s = system(m, integrator)
    parts = newton_iteration_split(sysm, s, repeat)["seconds"]
    total = sum(parts.values())
    return dict(m=m, integrator=integrator, seconds=parts, share={k: v / total for k, v in parts.items()})


def estimation_system(name: str, points: int = 101):
    """(ShootingSystem, s) of an estimation TPBVP at its initial approximation, ``points`` points."""
    from shootlab.estimation.data import Measurements
    from shootlab.estimation.optimality import EstimationProblem
    from shootlab.estimation.fit import initial_approximation
    if name == "flexible_friction":
        from manipulators.flexible import friction_model
        from manipulators.rig import RigSettings, simulate_rig
        model, data = friction_model(), Measurements.coerce(simulate_rig(RigSettings(), input="sweep").measured())
        integ, initial = get_integrator("rk4", steps=10), None
    else:
        from mixtures.simulation import simulated_measurements
        from mixtures.identification import as_data, model as confined
        model = confined(elements=20, prefit=False, coarse=0, states="simulated")
        data = Measurements.coerce(as_data(simulated_measurements(elements=20)))
        integ, initial = get_integrator("midpoint", steps=2), dict(H=2.0, K=1.0)
    t = torch.linspace(0.0, 1.0, points, dtype=f64)
    prob = EstimationProblem(model, data)
    return ShootingSystem(prob.bvp(), t, integ), initial_approximation(model, data, t, initial)


def batched_vs_single_sweeps(name: str, repeat: int) -> dict:
    from shootlab.bvp import shooting
    sysm, s = system(1000, "rk4") if name == "troesch" else estimation_system(name)
    sysm.jacobian = "reverse"
    chunk = shooting.JACOBIAN_CHUNK
    try:
        Yb = sysm.interval_jacobians(s)
        tb = best_of(lambda: sysm.interval_jacobians(s), repeat)
        shooting.JACOBIAN_CHUNK = 1
        Ys = sysm.interval_jacobians(s)
        ts = best_of(lambda: sysm.interval_jacobians(s), repeat)
    finally:
        shooting.JACOBIAN_CHUNK = chunk
    return dict(problem=name, m=int(s.shape[0]), n=int(s.shape[1]), chunk=chunk, batched_s=tb, single_s=ts,
                speedup=ts / tb, max_abs_deviation=float((Yb - Ys).abs().max()))


def newton_vs_n(elements, repeat: int, old_max_n: int, points: int = 201) -> list[dict]:
    """Section 5 of the module docstring: one row per (problem, path)."""
    from studies.scaling import ScalingSettings, n_scan_problem, newton_iteration_split
    cases = []
    for N in elements:
        p = n_scan_problem(ScalingSettings(n_points=points), int(N))
        t = p.grid(points)
        cases.append((f"confined N={N} (scaling)", p.bvp, t, p.guess(t), "rk4", 1))
    sysm, s = estimation_system("confined20", points)
    cases.append(("confined N=20 estimation", sysm.prob, sysm.t, s, "midpoint", 2))
    rows = []
    for label, bvp, t, s, integrator, steps in cases:
        n = int(s.shape[1])
        for path in ("reverse", "autograd"):
            if path == "reverse" and n > old_max_n:
                continue
            system = ShootingSystem(bvp, t, get_integrator(integrator, steps=steps), jacobian=path)
            t0 = time.perf_counter()
            split = newton_iteration_split(system, s, repeat)
            rows.append(dict(problem=label, n=n, m=int(t.numel()), integrator=f"{integrator}:{steps}", path=path,
                             seconds=split["seconds"], total=split["total"], wall=time.perf_counter() - t0))
            print(f"  {label:<26} n = {n:3d} {path:8s} " + ", ".join(
                f"{k} {v:.3f} s" for k, v in split["seconds"].items()) + f", total {split['total']:.3f} s", flush=True)
    return rows


def print_newton_vs_n(rows: list[dict]) -> None:
    print("one Newton iteration, old path (reverse sweeps through the integrator) vs new (forward sensitivities; "
          "for n >= 16 the rhs Jacobian of eq. 2.7 assembled from the model's derivatives), seconds and ratio old/new")
    print(f"  {'problem':<26} {'n':>4} {'':>5} {'F build':>9} {'Jacobian':>9} {'factor.':>9} {'back-sub':>9} {'total':>9}")
    keys = ("F_build", "jacobian_build", "factorisation", "back_substitution")
    for new in (r for r in rows if r["path"] == "autograd"):
        old = next((r for r in rows if r["path"] == "reverse" and r["problem"] == new["problem"]), None)
        for r in ((old,) if old else ()) + (new,):
            print(f"  {r['problem']:<26} {r['n']:4d} {'old' if r is old else 'new':>5} "
                  + " ".join(f"{r['seconds'][k]:9.3f}" for k in keys) + f" {r['total']:9.3f}")
        if old:
            print(f"  {'':<26} {'':>4} {'ratio':>5} " + " ".join(
                f"{old['seconds'][k] / new['seconds'][k]:9.1f}" for k in keys) + f" {old['total'] / new['total']:9.1f}")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results/engine.json")
    ap.add_argument("--quick", action="store_true", help="m = 100 only, fewer repeats")
    ap.add_argument("--only", choices=["newton_vs_n"], default=None, help="only this section")
    ap.add_argument("--elements", type=int, nargs="+", default=[8, 18, 48],
                    help="elements of the n scan (n = 2 (N + 2)): 20, 40, 100 equations")
    ap.add_argument("--old-max-n", type=int, default=100, help="time the old path up to this n")
    args = ap.parse_args(argv)
    if args.only == "newton_vs_n":
        res = dict(machine=dict(python=platform.python_version(), torch=torch.__version__,
                                threads=torch.get_num_threads()),
                   newton_vs_n=newton_vs_n(args.elements, 1 if args.quick else 2, args.old_max_n))
        print_newton_vs_n(res["newton_vs_n"])
        out = Path(args.out).with_name("engine_newton_vs_n.json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=2))
        print(f"wrote {out}")
        return res
    sizes = [100] if args.quick else [100, 1000]
    repeat = 2 if args.quick else 3
    res = dict(machine=dict(python=platform.python_version(), torch=torch.__version__,
                            threads=torch.get_num_threads()),
               problem="Troesch mu = 5, straight-line guess, rk4 with 4 steps per interval")
    res["batched_vs_loop"] = [batched_vs_loop(m, "rk4", repeat) for m in sizes]
    res["batched_vs_loop"] += [batched_vs_loop(m, "ros4", repeat) for m in sizes[:1]]
    res["autograd_vs_fd"] = [autograd_vs_fd(m, name, repeat) for m in sizes for name in ("rk4", "ros4")]
    res["newton_iteration"] = [newton_split(m, "rk4", repeat) for m in sizes]
    res["jacobian_sweeps"] = [batched_vs_single_sweeps(name, repeat) for name in
                              (("troesch", "flexible_friction") if args.quick else
                               ("troesch", "flexible_friction", "confined20"))]
    res["newton_vs_n"] = newton_vs_n(args.elements[:1] if args.quick else args.elements, repeat, args.old_max_n)
    print("batched vs per-interval loop (residual F, same integrator)")
    for r in res["batched_vs_loop"]:
        print(f"  m = {r['m']:5d} {r['integrator']:6s} batched {r['batched_s']:.4f} s, loop {r['loop_s']:.3f} s,"
              f" speed-up {r['speedup']:.0f}x (max deviation {r['max_deviation']:.1e})")
    print("interval Jacobians: autograd (reverse mode through the integrator) vs finite differences (eq. 3.7)")
    for r in res["autograd_vs_fd"]:
        print(f"  m = {r['m']:5d} {r['integrator']:6s} autograd {r['autograd_s']:.4f} s, fd {r['fd_s']:.4f} s, "
              f"ratio {r['time_ratio_autograd_over_fd']:.2f}, max |Y_ad - Y_fd| = {r['max_abs_deviation']:.1e}")
    print("one press Newton iteration with a fresh Jacobian, split (report fig. 3.8)")
    for r in res["newton_iteration"]:
        print(f"  m = {r['m']:5d} " + ", ".join(f"{k} {v * 1e3:.1f} ms ({r['share'][k]:.0%})"
                                               for k, v in r["seconds"].items()))
    print("interval Jacobians: batched reverse sweeps vs one sweep per row")
    for r in res["jacobian_sweeps"]:
        print(f"  {r['problem']:<18} m = {r['m']:4d}, n = {r['n']:2d}: batched ({r['chunk']} per sweep) "
              f"{r['batched_s']:.3f} s, one per row {r['single_s']:.3f} s, speed-up {r['speedup']:.2f}x "
              f"(max deviation {r['max_abs_deviation']:.1e})")
    print_newton_vs_n(res["newton_vs_n"])
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))
    print(f"wrote {out}")
    return res


if __name__ == "__main__":
    main()
