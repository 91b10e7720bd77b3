"""Time and memory of one Newton iteration vs the number of shooting points m and of ODEs n
(the report's figs. 3.5 and 3.8, redone).

One ``press`` Newton iteration with a fresh Jacobian is split, as in ``benchmarks/engine.py``
(whose ``newton_split`` is this measurement for one fixed problem; :func:`newton_iteration_split`
is the general form), into

    F build            the residual: all m − 1 intervals integrated as one batch
    Jacobian build     the interval Jacobians Y_k by reverse mode through the integrator, and B_a, B_b
    factorisation      structured orthogonal cyclic reduction (shootlab.bvp.linalg)
    back-substitution  the Newton step from the factorisation

each the best of ``repeat`` runs.  Memory: the peak of the live tensor storage during one
iteration (:class:`TensorMemory`: every storage an aten op creates is counted until it is
freed — deterministic, independent of the allocator's caching), and the storage the
factorisation keeps.  Fitted growth exponents p of time ∝ m^p are printed, over the whole
range and over its upper decade (where fixed per-call overheads no longer dominate).

    python -m studies scaling [--problem msd] [--m 100 ... 10000] [--elements 1 3 8 18 48] [--out DIR]
"""
from __future__ import annotations

import json
import math
import time
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

import shootlab
from shootlab.bvp.integrators import get_integrator
from shootlab.bvp.linalg import SingularJacobianError, factorize
from shootlab.bvp.shooting import ShootingSystem

from . import problems

PARTS = ("F_build", "jacobian_build", "factorisation", "back_substitution")
LABELS = dict(F_build="F build", jacobian_build="Jacobian build", factorisation="factorisation",
              back_substitution="back-substitution")


# -- memory ------------------------------------------------------------------------------------
class TensorMemory(TorchDispatchMode):
    """Peak bytes of live tensor storage created inside the ``with`` block (CPU, any dtype).

    Every output of an aten op is counted once per storage until the last tensor viewing it
    is freed (a weakref finalizer), so views and in-place results are not double counted and
    the autograd graph's saved tensors are included.  Storage allocated before the block
    is not counted.  ``peak`` and ``current`` are in bytes."""

    def __init__(self):
        super().__init__()
        self._live: dict[int, list] = {}
        self.current = 0
        self.peak = 0

    def _release(self, key: int) -> None:
        entry = self._live.get(key)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] <= 0:
            del self._live[key]
            self.current -= entry[0]

    def _track(self, t: torch.Tensor) -> None:
        st = t.untyped_storage()
        key = st.data_ptr()
        if key == 0:
            return
        entry = self._live.get(key)
        if entry is None:
            entry = self._live[key] = [st.nbytes(), 0]
            self.current += entry[0]
            self.peak = max(self.peak, self.current)
        entry[1] += 1
        weakref.finalize(t, self._release, key)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in tree_flatten(out)[0]:
            if isinstance(t, torch.Tensor) and t.device.type == "cpu":
                try:
                    self._track(t)
                except (RuntimeError, NotImplementedError):      # e.g. sparse / no storage
                    pass
        return out


def factorisation_bytes(fac) -> int:
    """Bytes the structured factorisation keeps (its O(m n²) storage)."""
    total = sum(x.numel() * x.element_size() for x in (fac.lu, fac.pivots, fac.row_scale))
    for lev in fac.levels:
        total += sum(x.numel() * x.element_size() for x in (lev.reflectors, lev.tau, lev.T12, lev.mid, lev.scale))
    return int(total)


def iteration_peak_bytes(system: ShootingSystem, s: torch.Tensor, rcond: float | None = None) -> int:
    """Peak live tensor bytes of one Newton iteration (F, fresh Jacobian, factorisation, step);
    ``rcond`` for :func:`shootlab.bvp.linalg.factorize` (None: its default; 0: no rank test failure)."""
    s = s.detach().clone()
    with TensorMemory() as mem:
        F = system.residual(s).F
        if rcond is None:
            fac = system.linearize(s)
        else:
            fac = factorize(system.interval_jacobians(s), *system.bc_jacobians(s), rcond=rcond)
        system.newton_step(fac, F)
        del F, fac
    return int(mem.peak)


# -- time --------------------------------------------------------------------------------------
def best_of(fn, repeat: int = 3, budget: float = 5.0) -> float:
    """Best wall time of up to ``repeat`` calls (fewer once ``budget`` seconds are spent)."""
    best, spent = math.inf, 0.0
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        fn()
        dt = time.perf_counter() - t0
        best, spent = min(best, dt), spent + dt
        if spent > budget:
            break
    return best


def _forget(system: ShootingSystem) -> None:
    """Drop what the right-hand side keeps of earlier evaluations (the estimation TPBVP keeps
    its factorised normal equations per stage point, :class:`shootlab.estimation.optimality.EstimationProblem`),
    so that every timed residual is that of a new iterate."""
    rhs = getattr(system.prob.rhs, "fun", system.prob.rhs)               # a VectorField's function
    forget = getattr(getattr(rhs, "__self__", None), "forget", None)
    if forget is not None:
        forget()


def newton_iteration_split(system: ShootingSystem, s: torch.Tensor, repeat: int = 3) -> dict:
    """Seconds of the four parts of one Newton iteration at s (module docstring), best of ``repeat``.

    F and the Jacobian are timed as a Newton iteration meets them: F at a new iterate (nothing
    kept from earlier evaluations), then the Jacobian at the same iterate (which may reuse what
    F computed); the best of ``repeat`` such pairs.  The work of an iteration does not depend on
    whether the Newton matrix passes the rank test,
    so the factorisation is timed with ``rcond=0`` (no SingularJacobianError); ``rank_deficient``
    records whether the default test would have failed (a problem of the start values, not of
    the timing — the mixture with N ≥ 18 elements at its linear start profile)."""
    F = system.residual(s).F
    Y = system.interval_jacobians(s)
    Ba, Bb = system.bc_jacobians(s)
    try:
        factorize(Y, Ba, Bb)
        deficient = False
    except SingularJacobianError:
        deficient = True
    fac = factorize(Y, Ba, Bb, rcond=0.0)

    def residual_then_jacobian() -> tuple[float, float]:
        _forget(system)
        t0 = time.perf_counter()
        system.residual(s)
        t1 = time.perf_counter()
        system.interval_jacobians(s), system.bc_jacobians(s)
        return t1 - t0, time.perf_counter() - t1

    pairs = [residual_then_jacobian() for _ in range(max(1, repeat))]
    F_build, jacobian_build = min(pairs, key=sum)
    seconds = dict(
        F_build=F_build, jacobian_build=jacobian_build,
        factorisation=best_of(lambda: factorize(Y, Ba, Bb, rcond=0.0), repeat),
        back_substitution=best_of(lambda: system.newton_step(fac, F), repeat))
    return dict(seconds=seconds, total=sum(seconds.values()), factorisation_bytes=factorisation_bytes(fac),
                rank_deficient=deficient)


def dense_floor(system: ShootingSystem, s: torch.Tensor, repeat: int = 3) -> dict:
    """The floating-point work a Jacobian build cannot avoid with a dense right-hand-side
    Jacobian: one batched product J·S (m − 1 blocks of n × n times n × n, 2 m n³ flops) per
    rhs-Jacobian evaluation of the build (counted), timed on this machine as one ``bmm``."""
    from shootlab.bvp.tangents import count_jacobians

    with count_jacobians() as count:
        system.interval_jacobians(s)
    calls = count.evaluations
    m1, n = s.shape[0] - 1, s.shape[1]
    a = torch.randn(m1, n, n, dtype=s.dtype)
    bmm = best_of(lambda: torch.bmm(a, a), repeat)
    return dict(rhs_jacobians=calls, flops=2.0 * calls * m1 * n ** 3, seconds=calls * bmm)


def measure(problem: problems.StudyProblem, m: int, integrator: str = "rk4", steps: int = 1,
            repeat: int = 3) -> dict:
    t = problem.grid(m)
    s = problem.guess(t)
    system = ShootingSystem(problem.bvp, t, get_integrator(integrator, steps=steps))
    row = newton_iteration_split(system, s, repeat)
    row.update(m=int(m), n=int(s.shape[1]), problem=problem.name, integrator=f"{integrator}:{steps}",
               peak_bytes=iteration_peak_bytes(system, s, rcond=0.0), dense_floor=dense_floor(system, s, repeat))
    return row


# -- fits ---------------------------------------------------------------------------------------
def fit_exponent(x, y) -> float:
    """Slope p of log y = p log x + c (least squares)."""
    x, y = np.log(np.asarray(x, float)), np.log(np.asarray(y, float))
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(x[ok], y[ok], 1)[0])


def exponents(rows: list[dict], var: str) -> dict:
    """Fitted exponents of every time part, the total, and the memories vs ``var`` (m or n):
    over all rows and over the rows in the upper decade of ``var``."""
    xs = np.array([r[var] for r in rows], float)
    series = {k: [r["seconds"][k] for r in rows] for k in PARTS}
    series["total"] = [r["total"] for r in rows]
    series["peak_memory"] = [r["peak_bytes"] for r in rows]
    series["factorisation_memory"] = [r["factorisation_bytes"] for r in rows]
    top = xs >= xs.max() / 10.0
    out = {}
    for k, v in series.items():
        v = np.asarray(v, float)
        out[k] = dict(all=fit_exponent(xs, v), upper_decade=fit_exponent(xs[top], v[top]) if top.sum() >= 2 else float("nan"))
    return out


# -- the study ------------------------------------------------------------------------------------
@dataclass
class ScalingSettings:
    problem: str = "msd"
    options: dict | None = None
    m: tuple = (100, 215, 464, 1000, 2154, 4642, 10000)
    n_problem: str = "confined"
    elements: tuple = (1, 3, 8, 18, 48, 98)   # n = 2 (N + 2): 6, 10, 20, 40, 100, 200
    #: options of the n scan; coarse=0: no refinement of the start by a 3-element estimate.  The start
    #: values H0 = K0 are chosen per N (:func:`n_scan_problem`) so that κ·h = ``n_kappa_h`` on the
    #: n scan's grid: the cost of an iteration does not depend on them, but the stiffness does
    #: (κ ∝ H·K, growing like N⁴), and a fixed H = K makes the Newton matrix numerically singular
    #: for N ≥ 8 (the growing modes swamp it for large H·K; for tiny H·K the pressures decouple)
    n_options: tuple = (("coarse", 0),)
    n_kappa_h: float = -1.0
    n_points: int = 201
    integrator: str = "rk4"
    steps: int = 1
    repeat: int = 3


def n_scan_problem(settings: ScalingSettings, N: int) -> problems.StudyProblem:
    """The n scan's problem with N elements, H0 = K0 = c scaled so that κ h = settings.n_kappa_h
    on ``n_points`` points (κ ∝ H·K: measured at c = 1 on 11 points of the guess, then scaled)."""
    from shootlab.bvp.suggest import local_eigenvalues

    opts = dict(settings.n_options, elements=int(N))
    if settings.n_kappa_h is None or settings.n_problem != "confined":
        return problems.build(settings.n_problem, opts)
    p1 = problems.build(settings.n_problem, dict(opts, H0=1.0, K0=1.0))
    t = p1.grid(11)
    kappa1 = float(local_eigenvalues(p1.bvp.rhs, t, p1.guess(t)).real.min())
    h = (p1.interval[1] - p1.interval[0]) / (settings.n_points - 1)
    c = math.sqrt(abs(settings.n_kappa_h / h) / abs(kappa1))
    return problems.build(settings.n_problem, dict(opts, H0=float(f"{c:.3g}"), K0=float(f"{c:.3g}")))


def run(settings: ScalingSettings, out: str | Path | None = None, progress: bool = True) -> dict:
    from tqdm import tqdm

    prob = problems.build(settings.problem, settings.options or {})
    rows_m = []
    for m in tqdm(settings.m, desc=f"scaling in m ({prob.name})", disable=not progress):
        rows_m.append(measure(prob, m, settings.integrator, settings.steps, settings.repeat))
    rows_n = []
    for N in tqdm(settings.elements, desc=f"scaling in n ({settings.n_problem})", disable=not progress):
        pn = n_scan_problem(settings, int(N))
        rows_n.append(dict(measure(pn, settings.n_points, settings.integrator, settings.steps, settings.repeat),
                           elements=int(N)))
    res = dict(kind="scaling", version=shootlab.__version__, torch=torch.__version__,
               threads=torch.get_num_threads(), settings=_jsonable(settings.__dict__),
               m_rows=rows_m, n_rows=rows_n, exponents_m=exponents(rows_m, "m"), exponents_n=exponents(rows_n, "n"))
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "scaling.json").write_text(json.dumps(res, indent=2))
        _csv(out / "scaling_m.csv", rows_m)
        _csv(out / "scaling_n.csv", rows_n)
        res["figures"] = plot(res, out)
    return res


def _jsonable(d: dict) -> dict:
    return {k: (dict(v) if k == "n_options" else list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def _csv(path: Path, rows: list[dict]) -> None:
    cols = ["problem", "integrator", "m", "n", *PARTS, "total", "peak_bytes", "factorisation_bytes"]
    lines = [",".join(cols)]
    for r in rows:
        vals = [r["problem"], r["integrator"], r["m"], r["n"], *(r["seconds"][k] for k in PARTS), r["total"],
                r["peak_bytes"], r["factorisation_bytes"]]
        lines.append(",".join(f'"{v}"' if isinstance(v, str) and "," in v else str(v) for v in vals))
    path.write_text("\n".join(lines) + "\n")


def report(res: dict) -> str:
    lines = []
    for var, rows, ex in (("m", res["m_rows"], res["exponents_m"]), ("n", res["n_rows"], res["exponents_n"])):
        if not rows:
            continue
        fixed = f"n = {rows[0]['n']}" if var == "m" else f"m = {rows[0]['m']}"
        lines.append(f"one Newton iteration vs {var} ({rows[0]['problem'].split('[')[0]}, {rows[0]['integrator']}, {fixed}):")
        lines.append(f"  {var:>6} " + " ".join(f"{LABELS[k]:>17}" for k in PARTS) + f" {'total':>9} {'peak MB':>9} {'fact. MB':>9}")
        for r in rows:
            lines.append(f"  {r[var]:6d} " + " ".join(f"{r['seconds'][k] * 1e3:14.1f} ms" for k in PARTS)
                         + f" {r['total']:8.3f}s {r['peak_bytes'] / 1e6:9.2f} {r['factorisation_bytes'] / 1e6:9.2f}")
        if var == "n":
            lines.append("  the Jacobian build beside the work a dense rhs Jacobian forces (one J·S product of "
                         "2 m n³ flops per rhs-Jacobian evaluation, timed as a batched matmul here):")
            for r in rows:
                fl = r.get("dense_floor")
                if fl:
                    lines.append(f"  {r['n']:6d}  {fl['rhs_jacobians']:3d} rhs Jacobians, {fl['flops'] / 1e9:7.2f} GFLOP, "
                                 f"floor {fl['seconds'] * 1e3:9.1f} ms; build {r['seconds']['jacobian_build'] * 1e3:9.1f} ms "
                                 f"({r['seconds']['jacobian_build'] / max(fl['seconds'], 1e-12):.1f}x the floor)")
        lines.append(f"  fitted exponent p ({var}^p), all points / upper decade:")
        for k in (*PARTS, "total", "peak_memory", "factorisation_memory"):
            e = ex[k]
            lines.append(f"    {k:22s} {e['all']:6.2f} / {e['upper_decade']:6.2f}")
    return "\n".join(lines)


def plot(res: dict, out: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    colors = dict(F_build="C0", jacobian_build="C1", factorisation="C2", back_substitution="C3", total="k")
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    for ax, var, rows, ex in ((axes[0], "m", res["m_rows"], res["exponents_m"]),
                              (axes[1], "n", res["n_rows"], res["exponents_n"])):
        if not rows:
            ax.set_visible(False)
            continue
        x = np.array([r[var] for r in rows])
        for k in (*PARTS, "total"):
            y = np.array([r["total"] if k == "total" else r["seconds"][k] for r in rows])
            lab = "total" if k == "total" else LABELS[k]
            ax.loglog(x, y, "o-", color=colors[k], lw=2 if k == "total" else 1.2,
                      label=f"{lab} (p = {ex[k]['all']:.2f}, upper decade {ex[k]['upper_decade']:.2f})")
        ax.set_xlabel("shooting points m" if var == "m" else "number of ODEs n")
        ax.set_ylabel("time per Newton iteration [s]")
        fixed = f"n = {rows[0]['n']}" if var == "m" else f"m = {rows[0]['m']}, confined compression, N = 1…{rows[-1].get('elements', '')} elements"
        ax.set_title(f"time vs {var} ({rows[0]['integrator']}, {fixed})", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    ax = axes[2]
    for var, rows, ex, mk in (("m", res["m_rows"], res["exponents_m"], "o"),):
        x = np.array([r[var] for r in rows])
        ax.loglog(x, [r["peak_bytes"] / 1e6 for r in rows], mk + "-", color="C4",
                  label=f"peak tensor memory of one iteration (p = {ex['peak_memory']['all']:.2f})")
        ax.loglog(x, [r["factorisation_bytes"] / 1e6 for r in rows], mk + "--", color="C2",
                  label=f"storage of the factorisation (p = {ex['factorisation_memory']['all']:.2f})")
        ref = x / x[0] * rows[0]["peak_bytes"] / 1e6
        ax.loglog(x, ref, ":", color="0.5", label="∝ m (reference)")
    ax.set_xlabel("shooting points m")
    ax.set_ylabel("memory [MB]")
    ax.set_title(f"memory vs m (n = {res['m_rows'][0]['n']})", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"one Newton iteration (fresh Jacobian): time split and memory — shootlab {res['version']}, "
                 f"{res['threads']} thread(s)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "scaling.png", dpi=110)
    plt.close(fig)
    files.append("scaling.png")
    return files


def replot(path: str | Path) -> list[str]:
    path = Path(path)
    if path.is_dir():
        path = path / "scaling.json"
    res = json.loads(path.read_text())
    return plot(res, path.parent)
