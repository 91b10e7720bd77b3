"""Does a compiled fixed-step fast path pay?  ``torch.compile`` of the RK4 interval integration vs
eager mode, side by side in one run, with the compile time set against the calls a solve makes
(adopted only where a benchmark shows it pays after compile time).

The kernel is what a fixed-step solve repeats: ``steps`` classical RK4 steps on every interval of
an m-point grid at once (one batched tensor), for a right-hand side of the BVP test set (bvpT1,
ε y'' = y, the smallest problems, where per-operation overhead dominates and fusion could help
most).  Measured:

* the eager and the compiled kernel's time per call (the median of ``--calls`` calls);
* the compile time, cold (a fresh inductor cache, in this process) and warm (a second process
  with the cache the first one left: what a user's second run pays);
* break-even = compile time / (eager − compiled): calls before compiling has paid;
* the kernel calls one ``shootlab.solve`` of the same problem makes (its integrations with the
  fixed-step RK4 and with the default integrator counted as right-hand-side batches / 4).

    python benchmarks/compile_fast_path.py [--m 100] [--steps 4] [--eps 1e-2] [--out FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
OUT = ROOT / "benchmarks" / "results" / "compile_fast_path.json"


def kernel(rhs, t: torch.Tensor, y: torch.Tensor, h: torch.Tensor, steps: int) -> torch.Tensor:
    """``steps`` RK4 steps of length h (m,) on every row of y (m, n) from t (m,)."""
    hc = h[:, None]
    for _ in range(steps):
        k1 = rhs(t, y)
        k2 = rhs(t + h / 2, y + hc / 2 * k1)
        k3 = rhs(t + h / 2, y + hc / 2 * k2)
        k4 = rhs(t + h, y + hc * k3)
        y = y + hc / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t = t + h
    return y


def setting(m: int, steps: int, eps: float):
    from studies.bvp_testset import bvpT1
    p = bvpT1(eps)
    t = torch.linspace(p.a, p.b, m, dtype=torch.float64)
    h = (t[1:] - t[:-1]) / steps
    y = torch.as_tensor(p.straight_line_guess(t[:-1].numpy()))
    return p, t, h, y


def per_call(fn, calls: int) -> float:
    fn()
    times = []
    for _ in range(calls):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def compiled_seconds(m: int, steps: int, eps: float, calls: int) -> dict:
    """Compile the kernel in this process (cache dir from the environment) and time it."""
    p, t, h, y = setting(m, steps, eps)
    fn = torch.compile(lambda tt, yy, hh: kernel(p.rhs_torch, tt, yy, hh, steps), dynamic=False)
    t0 = time.perf_counter()
    out = fn(t[:-1], y, h)
    compile_s = time.perf_counter() - t0
    assert torch.allclose(out, kernel(p.rhs_torch, t[:-1], y, h, steps), rtol=1e-12, atol=1e-12)
    return dict(compile_s=compile_s, compiled_call_s=per_call(lambda: fn(t[:-1], y, h), calls))


def solve_calls(m: int, eps: float) -> dict:
    """Right-hand-side batches of one shootlab.solve of the problem, by integrator."""
    import shootlab
    p, t, _, _ = setting(m, 1, eps)
    out = {}
    for name in ("rk4", None):
        count = [0]

        def rhs(tt, x, _f=p.rhs_torch):
            count[0] += 1
            return _f(tt, x)
        bvp = shootlab.BVP(rhs, p.bc_a_torch, p.bc_b_torch)
        t0 = time.perf_counter()
        res = shootlab.solve(bvp, t, torch.as_tensor(p.straight_line_guess(t.numpy())),
                             **(dict(integrator="rk4", steps=4, refine=False) if name else {}))
        out[name or "default"] = dict(success=bool(res.success), rhs_batches=count[0],
                                      kernel_calls=count[0] / 4, seconds=time.perf_counter() - t0)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--m", type=int, default=100, help="grid points (default 100)")
    ap.add_argument("--steps", type=int, default=4, help="RK4 steps per interval (default 4)")
    ap.add_argument("--eps", type=float, default=1e-2, help="bvpT1's ε (default 1e-2)")
    ap.add_argument("--calls", type=int, default=200, help="timed calls per kernel (median)")
    ap.add_argument("--out", default=str(OUT), help=f"JSON file (default {OUT.relative_to(ROOT)})")
    ap.add_argument("--compiled-only", action="store_true", help="internal: print the compiled timing as JSON")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.compiled_only:
        print(json.dumps(compiled_seconds(args.m, args.steps, args.eps, args.calls)))
        return {}
    p, t, h, y = setting(args.m, args.steps, args.eps)
    eager = per_call(lambda: kernel(p.rhs_torch, t[:-1], y, h, args.steps), args.calls)
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=cache)
        cmd = [sys.executable, __file__, "--compiled-only", "--m", str(args.m), "--steps", str(args.steps),
               "--eps", str(args.eps), "--calls", str(args.calls)]
        runs = []
        for label in ("cold", "warm"):
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            runs.append(dict(json.loads(proc.stdout.strip().splitlines()[-1]), cache=label))
    calls = solve_calls(args.m, args.eps)
    res = dict(problem=f"bvpT1 eps={args.eps:g}", m=args.m, steps=args.steps, torch=torch.__version__,
               eager_call_s=eager, runs=runs, solve=calls)
    print(f"RK4 kernel, {res['problem']}, m = {args.m}, {args.steps} steps per interval, one thread")
    print(f"  eager     {eager * 1e3:8.3f} ms per call")
    for r in runs:
        gain = eager - r["compiled_call_s"]
        r["break_even_calls"] = r["compile_s"] / gain if gain > 0 else float("inf")
        print(f"  compiled  {r['compiled_call_s'] * 1e3:8.3f} ms per call ({eager / r['compiled_call_s']:.1f}x), "
              f"compile {r['compile_s']:.1f} s with a {r['cache']} cache: pays after {r['break_even_calls']:,.0f} calls")
    for name, c in calls.items():
        print(f"  one shootlab.solve ({name} integrator): {c['kernel_calls']:,.0f} kernel calls, {c['seconds']:.2f} s")
    most = max(c["kernel_calls"] for c in calls.values())
    res["pays_within_one_solve"] = any(r["break_even_calls"] <= most for r in runs)
    print(f"  compiling pays within one solve: {'yes' if res['pays_within_one_solve'] else 'no'}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2))
    print(f"wrote {out}")
    return res


if __name__ == "__main__":
    main()
