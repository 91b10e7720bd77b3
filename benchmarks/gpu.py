"""CPU (one thread) against CUDA, side by side in one run.

1. ``scaling``: ``shootlab.solve(..., integrator="rk4", steps=4, refine=False)`` on ε y″ = y
   (ε = 1e-2, y(0) = y(1) = 1; exact y = cosh((t − ½)/√ε)/cosh(1/(2√ε))) at m = 1e3 … 1e6 and on
   Troesch's problem (μ = 5) at m = 1e3 … 1e5, each device after a warm-up solve; time, Newton
   iterations, the largest difference between the two devices' solutions (and the error against
   the exact solution of the layer problem);
2. ``batch``: 1,000 BVPs (500 Troesch μ ∈ [0.5, 5], 500 Bratu λ ∈ [0.1, 3.4]; m = 1,000 each) by
   :func:`shootlab.solve_batch` on CUDA (and on the CPU) against :func:`shootlab.solve` one after
   another on the CPU (``--alone`` of them, the rest extrapolated from their mean);
3. ``confined``: the confined-compression estimates of H, K — output error with 50 elements and
   the TPBVP with 20 elements — with ``device="cpu"`` and ``device="cuda"``;
4. ``--profile``: torch.profiler's top operations of one Newton iteration on CUDA (ε y″ = y,
   m = 1e5: residual with interval Jacobians, factorisation, Newton step).

Writes ``benchmarks/results/gpu.json`` (after every section, so a run cut short keeps what it
measured) and ``gpu.png`` (time against m).  The project is put on ``sys.path`` here: no install
needed on the GPU machine.

    python benchmarks/gpu.py [--quick] [--sections scaling batch confined] [--profile] [--budget S]
        [--out DIR]

``--quick``: CPU only, small m, 10 batch problems, no confined estimate (runs in a test).
``--budget``: seconds after which no further case is started (the run ends with what it has).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

import shootlab  # noqa: E402
from shootlab.bvp.batch import ParametricBVP, solve_batch  # noqa: E402
from studies import families  # noqa: E402

f64 = torch.float64
EPS = 1e-2


# -- problems -------------------------------------------------------------------------------------
def layer(eps: float = EPS) -> shootlab.BVP:
    """ε y″ = y, y(0) = y(1) = 1 as x = [y, y′]."""
    return shootlab.BVP(lambda t, x: torch.stack([x[..., 1], x[..., 0] / eps], -1),
                        lambda xa: xa[:1] - 1.0, lambda xb: xb[:1] - 1.0, name=f"layer({eps:g})")


def layer_exact(t: torch.Tensor, eps: float = EPS) -> torch.Tensor:
    return families.layer_exact(t, eps)


def layer_guess(t: torch.Tensor) -> torch.Tensor:
    return families.guess("layer", t)


def troesch(mu: float = 5.0) -> shootlab.BVP:
    return troesch_family([mu]).member(0)


def troesch_guess(t: torch.Tensor) -> torch.Tensor:
    return families.guess("troesch", t)


def troesch_family(mus) -> ParametricBVP:
    """Troesch's problems y″ = μ sinh(μ y), y(0) = 0, y(1) = 1, one per μ (:mod:`studies.families`)."""
    return families.family("troesch", mus)


def bratu_family(lams) -> ParametricBVP:
    """Bratu's problems y″ + λ e^y = 0, y(0) = y(1) = 0 (a solution for λ ≤ 3.5138), one per λ."""
    return families.family("bratu", lams)


def bratu_guess(t: torch.Tensor) -> torch.Tensor:
    return families.guess("bratu", t)


# -- helpers --------------------------------------------------------------------------------------
def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn, device: torch.device):
    sync(device)
    t0 = time.perf_counter()
    out = fn()
    sync(device)
    return out, time.perf_counter() - t0


def devices(quick: bool) -> list[torch.device]:
    out = [torch.device("cpu")]
    if not quick and torch.cuda.is_available():
        out.append(torch.device("cuda"))
    return out


def rk4(prob, t, guess):
    return shootlab.solve(prob, t, guess, integrator="rk4", steps=4, refine=False)


class Budget:
    def __init__(self, seconds: float):
        self.end = time.perf_counter() + seconds

    def left(self) -> float:
        return self.end - time.perf_counter()


# -- sections -------------------------------------------------------------------------------------
def scaling(quick: bool, budget: Budget) -> dict:
    cases = {"layer": (layer(), layer_guess, [1000, 2000] if quick else [1000, 10_000, 100_000, 1_000_000]),
             "troesch": (troesch(5.0), troesch_guess, [1000, 2000] if quick else [1000, 10_000, 100_000])}
    rows = []
    for dev in devices(quick):
        for name, (prob, guess, _) in cases.items():          # warm-up (kernels, allocator, first calls)
            t = torch.linspace(0, 1, 200, dtype=f64, device=dev)
            rk4(prob, t, guess(t))
    last: dict[tuple[str, str], tuple[int, float]] = {}
    for name, (prob, guess, ms) in cases.items():
        for m in ms:
            row = dict(problem=name, m=m)
            xs = {}
            for dev in devices(quick):
                prev = last.get((name, dev.type))
                if budget.left() <= 0 or (prev is not None and prev[1] * m / prev[0] > budget.left()):
                    row[f"{dev.type}_skipped"] = "budget"          # (linear in m from the last case)
                    continue
                t = torch.linspace(0, 1, m, dtype=f64, device=dev)
                try:
                    res, sec = timed(lambda: rk4(prob, t, guess(t)), dev)
                except Exception as exc:            # noqa: BLE001 — a benchmark records, it goes on
                    row[f"{dev.type}_error"] = f"{type(exc).__name__}: {exc}"
                    continue
                row[f"{dev.type}_seconds"] = sec
                last[(name, dev.type)] = (m, sec)
                row[f"{dev.type}_iterations"] = res.iterations
                row[f"{dev.type}_status"] = int(res.status)
                xs[dev.type] = res.x.detach().cpu()
                if name == "layer":
                    row[f"{dev.type}_error_vs_exact"] = float((res.x[:, 0].cpu() - layer_exact(t.cpu())).abs().max())
                print(f"scaling {name:8s} m={m:>8d} {dev.type:4s} {sec:9.3f} s  {res.iterations} it  {res.message[:50]}",
                      flush=True)
            if len(xs) == 2:
                row["max_difference"] = float((xs["cpu"] - xs["cuda"]).abs().max())
            if "cpu_seconds" in row and "cuda_seconds" in row:
                row["cuda_speedup"] = row["cpu_seconds"] / row["cuda_seconds"]
            rows.append(row)
    return dict(settings="shootlab.solve(prob, t, guess, integrator='rk4', steps=4, refine=False); "
                         f"layer: eps y'' = y, eps = {EPS:g}; troesch: mu = 5", rows=rows)


def batch(quick: bool, budget: Budget, alone: int) -> dict:
    per = 5 if quick else 500
    m = 200 if quick else 1000
    fams = [(troesch_family(torch.linspace(0.5, 5.0, per)), troesch_guess),
            (bratu_family(torch.linspace(0.1, 3.4, per)), bratu_guess)]
    out = dict(problems=2 * per, m=m, settings="rk4, steps=4; solve: refine=False, max_growth=None")
    for dev in devices(quick):
        t = torch.linspace(0, 1, m, dtype=f64, device=dev)
        fam, guess = fams[0]
        solve_batch(troesch_family([1.0, 2.0]), t, guess(t), device=dev)        # warm-up
        total, conv, iters, xs = 0.0, 0, [], []
        for fam, guess in fams:
            res, sec = timed(lambda: solve_batch(fam, t, guess(t), device=dev), dev)
            total += sec
            conv += sum(r.success for r in res)
            iters += [r.iterations for r in res]
            xs += [r.x.detach().cpu() for r in res]
        out[f"solve_batch_{dev.type}_seconds"] = total
        out[f"solve_batch_{dev.type}_converged"] = conv
        out[f"solve_batch_{dev.type}_mean_iterations"] = sum(iters) / len(iters)
        out.setdefault("_x", {})[dev.type] = xs
        print(f"batch solve_batch {dev.type:4s} {2 * per} problems: {total:8.3f} s, {conv} converged", flush=True)
    xs = out.pop("_x")
    if len(xs) == 2:
        out["solve_batch_max_difference_cpu_cuda"] = max(float((a - b).abs().max()) for a, b in zip(xs["cpu"], xs["cuda"]))
    # one after another on the CPU: `alone` problems of each family, spread over the parameter range
    t = torch.linspace(0, 1, m, dtype=f64)
    k = max(1, min(per, alone // 2))
    secs, conv, diffs = [], 0, []
    for f, (fam, guess) in enumerate(fams):
        for i in torch.linspace(0, per - 1, k).round().long().tolist():
            if budget.left() <= 0:
                break
            res, sec = timed(lambda: shootlab.solve(fam.member(i), t, guess(t), integrator="rk4", steps=4,
                                                    refine=False, max_growth=None), torch.device("cpu"))
            secs.append(sec)
            conv += res.success
            if res.success:
                diffs.append(float((res.x - xs["cpu"][f * per + i]).abs().max()))
    if secs:
        out["alone_cpu_solved"] = len(secs)
        out["alone_cpu_converged"] = conv
        out["alone_cpu_mean_seconds"] = sum(secs) / len(secs)
        out["alone_cpu_seconds_all_estimated"] = sum(secs) / len(secs) * 2 * per
        out["alone_vs_batch_max_difference"] = max(diffs) if diffs else None
        print(f"batch alone cpu: {len(secs)} solved, mean {out['alone_cpu_mean_seconds']:.3f} s -> "
              f"{out['alone_cpu_seconds_all_estimated']:.1f} s for all {2 * per}", flush=True)
        for dev in ("cpu", "cuda"):
            if f"solve_batch_{dev}_seconds" in out:
                out[f"speedup_solve_batch_{dev}_vs_alone_cpu"] = (out["alone_cpu_seconds_all_estimated"]
                                                                  / out[f"solve_batch_{dev}_seconds"])
    return out


def confined(budget: Budget) -> dict:
    from mixtures.identification import as_data, model
    from mixtures.simulation import simulated_measurements
    from shootlab.estimation.output_error import estimate_output_error

    out = {}
    for N, kind in ((50, "output_error"), (20, "tpbvp")):
        data = as_data(simulated_measurements(elements=N))
        for dev in devices(False):
            if budget.left() <= 0:
                out[f"{kind}_N{N}_{dev.type}"] = dict(skipped="budget")
                continue
            mdl = model(elements=N)
            try:
                if kind == "output_error":
                    res, sec = timed(lambda: estimate_output_error(mdl, data, device=dev), dev)
                else:
                    res, sec = timed(lambda: shootlab.estimate(mdl, data, device=dev), dev)
            except Exception as exc:               # noqa: BLE001
                out[f"{kind}_N{N}_{dev.type}"] = dict(error=f"{type(exc).__name__}: {exc}",
                                                      where=traceback.format_exc().splitlines()[-3:])
                continue
            out[f"{kind}_N{N}_{dev.type}"] = dict(seconds=sec, success=bool(res.success),
                                                  H=res.parameters["H"], K=res.parameters["K"],
                                                  message=res.message[:200])
            print(f"confined {kind} N={N} {dev.type}: {sec:.1f} s, H = {res.parameters['H']:.6g}, "
                  f"K = {res.parameters['K']:.6g}, success {res.success}", flush=True)
    out["note"] = ("the 50-element output error runs the model's own free run (the linear system's exact "
                   "response, numpy) on either device; only the TPBVP estimate's solve moves to the GPU")
    return out


def profile(m: int = 100_000, rows: int = 25) -> str:
    """torch.profiler's table of one Newton iteration on CUDA (after one warm-up iteration)."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as prof

    from shootlab.bvp.integrators import get_integrator
    from shootlab.bvp.shooting import ShootingSystem

    dev = torch.device("cuda")
    t = torch.linspace(0, 1, m, dtype=f64, device=dev)
    s = layer_guess(t)
    system = ShootingSystem(layer(), t, get_integrator("rk4", steps=4))

    def iteration():
        F = system.residual(s, jacobian=True).F
        fac = system.linearize(s)
        dx = system.newton_step(fac, F)
        return system.residual(s + dx).F

    iteration()
    sync(dev)
    with prof(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as p:
        iteration()
        sync(dev)
    table = p.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)
    print(table, flush=True)
    return table


def kernels(device: torch.device, k: int = 10_000, n: int = 2) -> dict:
    """Seconds of the batched kernels the engine avoids or uses on an accelerator, k matrices of
    n × n (pairs 2n × n for the QR): eigenvalues against the spectral bounds, ``ormqr`` against the
    compact WY form."""
    from shootlab.bvp.linalg import wy_form
    from shootlab.bvp.spectrum import abscissa_bound, spectral_radius_bound

    g = torch.Generator().manual_seed(0)
    J = torch.randn(k, n, n, generator=g, dtype=f64).to(device)
    A = torch.randn(k, 2 * n, n, generator=g, dtype=f64).to(device)
    C = torch.randn(k, 2 * n, 2 * n, generator=g, dtype=f64).to(device)
    out = dict(matrices=k, n=n)
    for label, fn in (("eigvals", lambda: torch.linalg.eigvals(J)),
                      ("spectral_bounds", lambda: (spectral_radius_bound(J), abscissa_bound(J))),
                      ("geqrf", lambda: torch.geqrf(A)),
                      ("ormqr", lambda: torch.ormqr(*torch.geqrf(A), C, left=True, transpose=True)),
                      ("wy_apply", lambda: (lambda r, tau: C - (lambda V, T: V @ (T.mT @ (V.mT @ C)))(*wy_form(r, tau)))(
                          *torch.geqrf(A))),
                      ("bmm", lambda: C @ C)):
        fn()
        out[f"{label}_seconds"] = timed(fn, device)[1]
    print(f"kernels on {device.type}: " + ", ".join(f"{k_}: {v:.4f}" for k_, v in out.items() if k_.endswith("seconds")),
          flush=True)
    return out


# -- output ---------------------------------------------------------------------------------------
def plot(res: dict, path: Path) -> str | None:
    rows = res.get("scaling", {}).get("rows", [])
    if not rows:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, marker in (("layer", "o"), ("troesch", "s")):
        for dev, color in (("cpu", "tab:blue"), ("cuda", "tab:green")):
            pts = [(r["m"], r[f"{dev}_seconds"]) for r in rows if r["problem"] == name and f"{dev}_seconds" in r]
            if pts:
                ax.plot(*zip(*pts), marker=marker, color=color, ls="-" if name == "layer" else "--",
                        label=f"{name}, {dev}" + (" (1 thread)" if dev == "cpu" else ""))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("shooting points m")
    ax.set_ylabel("solve time [s]")
    ax.set_title("shootlab.solve, rk4 x 4, refine=False", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="CPU only, small m (for a test)")
    ap.add_argument("--sections", nargs="*", default=["scaling", "batch", "confined"],
                    choices=["scaling", "batch", "confined"])
    ap.add_argument("--profile", action="store_true", help="print the top operations of one Newton iteration on CUDA")
    ap.add_argument("--alone", type=int, default=100, help="batch: problems solved one after another on the CPU")
    ap.add_argument("--budget", type=float, default=540.0, help="seconds after which no new case starts")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"), help="output folder")
    args = ap.parse_args(argv)
    budget = Budget(args.budget)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cuda = torch.cuda.is_available()
    res = dict(torch=torch.__version__, python=platform.python_version(), threads=torch.get_num_threads(),
               cpu=platform.processor() or platform.machine(), cuda=cuda,
               gpu=torch.cuda.get_device_name(0) if cuda else None, quick=args.quick,
               created=time.strftime("%Y-%m-%d %H:%M:%S"))
    name = "gpu_quick" if args.quick else "gpu"

    def save() -> None:
        from shootlab.outputs import json_ready
        (out / f"{name}.json").write_text(json.dumps(json_ready(res), indent=2))

    if not args.quick and not cuda:
        print("note: torch sees no GPU; measuring the CPU only", flush=True)
    if args.profile and cuda:
        try:
            res["kernels"] = {dev.type: kernels(dev) for dev in devices(False)}
            res["profile"] = profile()
        except Exception as exc:                   # noqa: BLE001
            res["profile_error"] = f"{type(exc).__name__}: {exc}"
            print(res["profile_error"], flush=True)
        save()
    for section in args.sections:
        if args.quick and section == "confined":
            continue
        try:
            if section == "scaling":
                res["scaling"] = scaling(args.quick, budget)
            elif section == "batch":
                res["batch"] = batch(args.quick, budget, 10 if args.quick else args.alone)
            else:
                res["confined"] = confined(budget)
        except Exception as exc:                   # noqa: BLE001 — keep the other sections
            res[section] = dict(error=f"{type(exc).__name__}: {exc}", where=traceback.format_exc().splitlines()[-6:])
            print(f"{section}: {type(exc).__name__}: {exc}", flush=True)
        save()
    fig = plot(res, out / f"{name}.png")
    if fig:
        res["figure"] = fig
    save()
    print(f"wrote {out / (name + '.json')}" + (f", {fig}" if fig else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
