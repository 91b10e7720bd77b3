"""The report's chapter-5 table (confined compression, MUSN vs RMUSN) reproduced with shootlab,
plus the local-Jacobian eigenvalues of figs. 5.4/5.5 and finer meshes than the report's.

Data: :func:`mixtures.simulation.simulated_measurements` — true H = 2, K = 1, load ramped to 1 over
t ∈ [0, 0.1] and held, 401 samples on [0, 1], generated with the same number of elements as the
estimating model; "1 % noise" is Gaussian with a standard deviation of 1 % of each channel's
peak value (load, displacement, pressure; seed 1).  Every run starts from the report's
H₀ = K₀ = 4 with its weights W = I, V = I, W_a = 0 (report §5.3) and, for N = 3, the linear
displacement profile.

Rows (N = 3 unless stated; the verdict column: ``ok`` = success and H, K within 0.5 %
(noise-free) / 5 % (1 % noise) of (2, 1); ``WRONG`` = success at other values; ``FAIL`` =
success=False, with the solver's message):

* no continuation, 401 points, explicit integrators — ``appendix_a`` (appendix A) with RK4 × 8 steps
  (the schedule's last stage) and with RKF45 × 4; ``armijo`` with RK4 × 8 (a few iterations:
  it creeps; the table adds whether the full Newton step from the guess overflows, tested by
  integrating it), RKF45 × 4, and explicit Euler × 1 at the tight tolerance;
  the report's MUSN run (RKF45, 1001 points, full study only);
* ``armijo`` and ``appendix_a`` with the tolerance continuation of the model (one explicit Euler step
  per interval to |F| ≤ 1e-4, then RK4 × 2, RK4 × 8 to 1e-10: report §5.4);
* stiff integrators: two grids (:func:`mixtures.identification.estimate_two_grid`: the loose
  Euler stage on 401 points, then the implicit midpoint rule or Radau IIA × 2 on 51 points); the
  Euler stage then Radau IIA × 2 on 201 points; Radau IIA × 1 alone on 401 points;
* N = 10 and N = 20: the explicit continuation on 401 points, and the model's defaults (an
  output-error fit of H, K — :func:`mixtures.prefit.output_error_fit`, a forward simulation
  fitted to the measurements, well under a second — for the initial H, K, a forward simulation
  for the initial states, then the implicit midpoint rule × 2 on 51 / 201 points); and the
  earlier default, a 3-element TPBVP estimate for the initial H, K (``prefit=False``): on the
  noisy 20-element record it settles at K ≈ 0.075 and the 101-point stage then fails (measured:
  2525 s, "step length below the floor"; ``--long`` only).

Report (1993 PC): MUSN, 1001 points: numerical overflow.  RMUSN, 401 points, with tolerance
continuation: 70 iterations, 8.0 min (final residual 7.3e-11).

Figures: eigenvalues of the local Jacobians ∂f/∂X of the TPBVP at the 401 shooting points for the
report's initial approximation (fig. 5.4) and for the solution (fig. 5.5); the stiffness measure
κ = min Re λ (report eq. 5.6) at the shooting points and κ·h per interval.

Run: ``python -m studies.confined_report [--quick | --long] [--out DIR]`` (default
``studies/results/confined``; ``--quick``: no 1001-point MUSN run, no N = 20, N = 10 noise-free
only; ``--long``: also N = 20 with 1 % noise from the 3-element start, about 40 min).  Writes
``confined_report.json``, ``confined_report.txt`` (the printed table), ``eigenvalues.png`` and
``stiffness.png``.
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from mixtures.simulation import simulated_measurements
from mixtures.identification import CONTINUATION, as_data, estimate_two_grid, model
from shootlab.estimation import estimate
from shootlab.estimation.fit import initial_approximation
from shootlab.outputs import json_ready
from shootlab.bvp.shooting import IntegrationFailure
from shootlab.bvp.suggest import local_eigenvalues

TRUE = dict(H=2.0, K=1.0)
START = dict(H=4.0, K=4.0)
NOISE = 0.01
TOLERANCE = {0.0: 5e-3, NOISE: 5e-2}        # the acceptance: 0.5 % noise-free, 5 % with 1 % noise

REPORT = [
    dict(code="MUSN", points=1001, iterations=None, minutes=None, residual=None, outcome="numerical overflow"),
    dict(code="RMUSN", points=401, iterations=70, minutes=8.0, residual=7.3e-11,
         outcome="converged (tolerance continuation)"),
]


def data_for(elements: int, noise: float) -> dict[str, np.ndarray]:
    """Simulated measurements of ``elements`` elements; ``noise``: σ as a fraction of each
    channel's peak (seed 1)."""
    tab = simulated_measurements(elements=elements)
    if noise:
        peaks = [float(np.abs(tab.channels[c]).max()) for c in ("load", "displacement", "pressure")]
        tab = simulated_measurements(elements=elements, noise=[noise * p for p in peaks], seed=1)
    return as_data(tab)


def cases(quick: bool, long: bool = False) -> list[dict]:
    """The rows: label, N, points (None: the model's default), estimate options ``opts``,
    model options ``mopt``, noise levels, ``twogrid`` (integrator of the second grid).
    ``long`` adds N = 20 with 1 % noise from the 3-element start (about 40 min, fails)."""
    none = dict(continuation=None)
    both = (0.0, NOISE)
    out = [
        dict(label="appendix_a, no continuation, RK4 x8", N=3, points=401,
             opts=dict(newton="appendix_a", integrator="rk4", steps=8, **none), probe=True),
        dict(label="appendix_a, no continuation, RKF45 x4 (MUSN's integrator)", N=3, points=401,
             opts=dict(newton="appendix_a", integrator="rkf45", steps=4, **none)),
        dict(label="appendix_a, no continuation, RKF45 x4, 1001 points (the report's MUSN run)", N=3, points=1001,
             opts=dict(newton="appendix_a", integrator="rkf45", steps=4, **none), skip_quick=True),
        dict(label="armijo, no continuation, RK4 x8 (10 iterations)", N=3, points=401,
             opts=dict(newton="armijo", integrator="rk4", steps=8, max_iter=10, **none), probe=True),
        dict(label="armijo, no continuation, RKF45 x4", N=3, points=401,
             opts=dict(newton="armijo", integrator="rkf45", steps=4, **none)),
        dict(label="armijo, no continuation, Euler x1 to tol 1e-10", N=3, points=401,
             opts=dict(newton="armijo", integrator="euler", steps=1, **none)),
        dict(label="armijo + tolerance continuation (model default)", N=3, points=None, opts={}, noise=both,
             spectra=True),
        dict(label="appendix_a + tolerance continuation", N=3, points=None, opts=dict(newton="appendix_a")),
        dict(label="stiff, two grids: Euler (401), then implicit midpoint x2 on 51", N=3, points=51,
             twogrid="midpoint", opts={}, noise=both),
        dict(label="stiff, two grids: Euler (401), then Radau IIA x2 on 51", N=3, points=51,
             twogrid="radau3", opts={}),
        dict(label="stiff: Euler stage, then Radau IIA x2, 201 points", N=3, points=201,
             opts=dict(continuation=[CONTINUATION[0], dict(integrator="radau3", steps=2)], max_growth=None),
             noise=both),
        dict(label="stiff: Radau IIA x1 alone, 401 points", N=3, points=401,
             opts=dict(integrator="radau3", steps=1, max_iter=60, **none)),
        dict(label="N=10, explicit continuation, 401 points", N=10, points=401,
             opts=dict(continuation=CONTINUATION), mopt=dict(coarse=0, prefit=False)),
        dict(label="N=10, model default: output-error start, implicit midpoint x2", N=10, points=None, opts={},
             noise=(0.0,) if quick else both, kappa=True),
        dict(label="N=10, 3-element start, implicit midpoint x2", N=10, points=None, opts={},
             mopt=dict(prefit=False), noise=both, skip_quick=True),
        dict(label="N=20, explicit continuation, 401 points", N=20, points=401,
             opts=dict(continuation=CONTINUATION), mopt=dict(coarse=0, prefit=False), skip_quick=True),
        dict(label="N=20, model default: output-error start, implicit midpoint x2", N=20, points=None, opts={},
             noise=both, skip_quick=True, kappa=True),
        dict(label="N=20, output-error start, implicit midpoint x2, 101 points", N=20, points=101, opts={},
             noise=(NOISE,), skip_quick=True),
        dict(label="N=20, 3-element start, implicit midpoint x2", N=20, points=101, opts={},
             mopt=dict(prefit=False), noise=both if long else (0.0,), skip_quick=True),
    ]
    return [c for c in out if not (quick and c.get("skip_quick"))]


def schedule(m, opts: dict) -> str:
    """The integrator (or continuation schedule) a run uses, e.g. ``euler x1 -> rk4 x2 -> rk4 x8``."""
    solve = {**m.settings.solver, **opts}
    if solve.get("continuation"):
        return " -> ".join(f"{s['integrator']} x{s.get('steps', '')}" for s in solve["continuation"])
    integ = solve.get("integrator", "ros4")
    return f"{integ} x{solve['steps']}" if "steps" in solve else integ


def full_step_overflows(res, m) -> str | None:
    """Integrate the full Newton step from the initial approximation on the run's own shooting
    system: the IntegrationFailure message if it overflows, else None.  Shows *why* a run
    without continuation creeps (armijo shortens overflowing steps) or stops (MUSN)."""
    system = res.shooting._system
    X0 = initial_approximation(m, res.problem.data, res.shooting.t, START)
    step = system.newton_step(system.linearize(X0), system.residual(X0).F)
    try:
        system.residual(X0 + step)
    except IntegrationFailure as exc:
        return str(exc)
    return None


def verdict(success: bool, err: float, noise: float) -> str:
    if not success:
        return "FAIL"
    return "ok" if err <= TOLERANCE[noise] else "WRONG"


def run_case(case: dict, noise: float) -> tuple[dict, object]:
    """One estimate from (H, K) = (4, 4); the row of the table and the EstimationResult (None
    when ``estimate`` rejects the initial approximation with a ValueError)."""
    N = case["N"]
    m = model(elements=N, **case.get("mopt", {}))
    data = data_for(N, noise)
    t0, prefit = time.perf_counter(), None
    if case.get("twogrid"):
        res = estimate_two_grid(m, data, points=case["points"], integrator=case["twogrid"], steps=2,
                                initial=START, **case["opts"])
        first = None if res.loose is None else dict(
            points=res.loose.points, success=res.loose.success, parameters=dict(res.loose.parameters),
            iterations=res.loose.iterations, jacobian_evaluations=res.loose.shooting.jacobian_evaluations)
        integ, cont = f"euler x1 (401) -> {case['twogrid']} x2", "2 grids"
    else:
        solve = {**m.settings.solver, **case["opts"]}
        integ = schedule(m, case["opts"])
        try:
            res = estimate(m, data, n_points=case["points"], initial=START, **case["opts"])
        except ValueError as exc:          # rejected before any Newton iteration (a clear error)
            return dict(case=case["label"], N=N, noise=noise, newton=case["opts"].get("newton", "armijo"),
                        integrator=integ, points=case["points"], continuation="-", iterations=0,
                        jacobian_evaluations=0, first_stage=None, seconds=time.perf_counter() - t0,
                        H=START["H"], K=START["K"], err_H=START["H"] / TRUE["H"] - 1, err_K=START["K"] / TRUE["K"] - 1,
                        success=False, verdict="FAIL", message=f"ValueError before solving: {exc}",
                        residual=math.inf, stages=[]), None
        memo = m.settings.extra["memo"]
        first, prefit = memo.get("coarse"), memo.get("prefit")
        cont = ("mesh" if memo.get("coarse") else "o.e." if memo.get("prefit")
                else "tol." if solve.get("continuation") else "no")
    wall = time.perf_counter() - t0
    sh = res.shooting
    H, K = res.parameters["H"], res.parameters["K"]
    err_H, err_K = abs(H - TRUE["H"]) / TRUE["H"], abs(K - TRUE["K"]) / TRUE["K"]
    row = dict(case=case["label"], N=N, noise=noise, newton=case["opts"].get("newton", "armijo"),
               integrator=integ, points=res.points, continuation=cont,
               iterations=sh.iterations, jacobian_evaluations=sh.jacobian_evaluations,
               first_stage=first, prefit=prefit, seconds=wall, H=H, K=K, err_H=err_H, err_K=err_K,
               success=res.success, verdict=verdict(res.success, max(err_H, err_K), noise),
               message=res.message, residual=sh.residual_norm,
               stages=[dict(settings=s["settings"], iterations=s["iterations"],
                            jacobian_evaluations=s["jacobian_evaluations"], success=s["success"],
                            message=s["message"]) for s in sh.stages])
    if case.get("probe") and not res.success:
        row["full_newton_step"] = full_step_overflows(res, m) or "integrates (no overflow)"
    return row, res


# -- eigenvalues of the local Jacobians --------------------------------------------------------
def local_spectra(res) -> dict:
    """Eigenvalues of ∂f/∂X at the shooting points of ``res`` for the report's initial
    approximation (linear profile, H = K = 4, λ = 0) and for the solution; κ = min Re λ at
    the points and κ·h per interval (the smaller κ of its two ends, report eq. 5.6)."""
    prob, t = res.problem, res.shooting.t
    start = model(elements=len(prob.model.states), coarse=0, prefit=False)       # the report's start, any N
    X0 = initial_approximation(start, prob.data, t, START)
    h = np.diff(t.numpy())
    out = {"t": t.numpy()}
    for key, X in (("initial", X0), ("solution", res.shooting.x)):
        ev = local_eigenvalues(prob.rhs, t, X).numpy()
        kappa = ev.real.min(-1)
        out[key] = dict(eigenvalues=ev, kappa=kappa, kappa_h=np.minimum(kappa[:-1], kappa[1:]) * h,
                        max_abs_real=float(np.abs(ev.real).max()), max_abs_imag=float(np.abs(ev.imag).max()),
                        H=float(X[:, prob.model.nx - 2].mean()), K=float(X[:, prob.model.nx - 1].mean()))
    return out


def kappa_summary(spec: dict) -> dict:
    """κ, max |Re λ| and the most negative κ·h, at the initial approximation and at the solution."""
    return {k: dict(kappa=float(spec[k]["kappa"].min()), max_abs_real=spec[k]["max_abs_real"],
                    kappa_h=float(spec[k]["kappa_h"].min())) for k in ("initial", "solution")}


def plot_spectra(spec: dict, out: Path, N: int) -> list[str]:
    """``eigenvalues.png`` (figs. 5.4/5.5) and ``stiffness.png`` (κ and κ·h)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = len(spec["t"])
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    for ax, key, what, c in zip(axes, ("initial", "solution"), ("initial approximation (report fig. 5.4)",
                                                               "solution (report fig. 5.5)"), ("C0", "C3")):
        s = spec[key]
        ev = s["eigenvalues"].reshape(-1)
        ax.scatter(ev.real, ev.imag, marker="x", s=16, lw=0.7, color=c,
                   label=f"{ev.size} eigenvalues ({m} points × {s['eigenvalues'].shape[1]})")
        lim = 1.15 * max(s["max_abs_real"], 1.0)
        ax.set_xlim(-lim, lim)
        ymax = max(s["max_abs_imag"], 1e-3) * 1.5
        ax.set_ylim(-ymax, ymax)
        ax.axvline(0, color="0.6", lw=0.6)
        ax.axhline(0, color="0.6", lw=0.6)
        ax.set_xlabel("Re λ  [1 / unit of dimensionless time]")
        ax.set_ylabel("Im λ  [1 / unit of dimensionless time]")
        ax.set_title(f"N = {N}, {what}:\nH = {s['H']:.4g}, K = {s['K']:.4g};  max |Re λ| = {s['max_abs_real']:.1f}",
                     fontsize=9)
        ax.legend(fontsize=8, loc="lower left")
        ax.grid(alpha=0.3)
    fig.suptitle("Eigenvalues of the local Jacobians ∂f/∂X of the TPBVP at the shooting points "
                 "(W = V = I, W_a = 0): Hamiltonian pairs ±λ", fontsize=10)
    fig.tight_layout()
    files = [out / "eigenvalues.png"]
    fig.savefig(files[0], dpi=120)
    plt.close(fig)

    t = spec["t"]
    tm = 0.5 * (t[1:] + t[:-1])
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for key, c in (("initial", "C0"), ("solution", "C3")):
        lab = f"{key} (H = {spec[key]['H']:.3g}, K = {spec[key]['K']:.3g})"
        axes[0].plot(t, spec[key]["kappa"], color=c, label=lab)
        axes[1].plot(tm, spec[key]["kappa_h"], color=c, label=lab)
    for lim, ls, name in ((-2.0, "--", "explicit Euler limit κh = −2"), (-2.785, ":", "RK4 limit κh = −2.785")):
        axes[1].axhline(lim, color="k", lw=0.8, ls=ls, label=name)
    axes[0].set_xlabel("time t [dimensionless]")
    axes[0].set_ylabel("κ = min Re λ  [1 / unit time]")
    axes[0].set_title("stiffness measure κ at the shooting points (report eq. 5.6)", fontsize=9)
    axes[1].set_ylim(top=0.0)
    axes[1].set_xlabel("time t [dimensionless] (interval midpoints)")
    axes[1].set_ylabel("κ·h per shooting interval  [–]")
    axes[1].set_title(f"κ·h per interval, h = {t[1] - t[0]:.4g} ({m} points);\none explicit step per "
                      f"interval is unstable below the dashed limits", fontsize=9)
    for ax in axes:
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    files.append(out / "stiffness.png")
    fig.savefig(files[1], dpi=120)
    plt.close(fig)
    return [str(f) for f in files]


# -- printing ----------------------------------------------------------------------------------
HEAD = (f"{'N':>3} {'noise':>5} {'pts':>5} {'newton':>6} {'integrator / schedule':<34} {'cont.':>7} {'iter':>7} "
        f"{'jac':>6} {'time[s]':>8}  {'H':>8} {'K':>8} {'err H':>7} {'err K':>7}  verdict: message")
LEGEND = ("cont.: tol. = tolerance continuation, mesh = 3-element estimate first, o.e. = output-error fit of H, K first, 2 grids = loose Euler stage "
          "on 401 points first;\niter, jac: final run + first stage (mesh, 2 grids); time: wall clock of all "
          "stages, 1 CPU thread")


def fmt_row(r: dict) -> str:
    first = r.get("first_stage")
    it = f"{r['iterations']}+{first['iterations']}" if first else r["iterations"]
    je = f"{r['jacobian_evaluations']}+{first['jacobian_evaluations']}" if first else r["jacobian_evaluations"]
    line = (f"{r['N']:>3} {100 * r['noise']:>4.0f}% {r['points']:>5} {r['newton']:>6} {r['integrator']:<34} "
            f"{r['continuation']:>7} {str(it):>7} {str(je):>6} {r['seconds']:>8.1f}  {r['H']:>8.5f} {r['K']:>8.5f} "
            f"{100 * r['err_H']:>6.2g}% {100 * r['err_K']:>6.2g}%  {r['verdict']}: {r['message'][:120]}")
    if "full_newton_step" in r:
        line += f"\n{'':>45}full Newton step from the guess: {r['full_newton_step']}"
    return line


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="studies/results/confined",
                    help="output folder for the JSON and figures (default studies/results/confined)")
    ap.add_argument("--quick", action="store_true", help="no 1001-point MUSN run, no N = 20, N = 10 noise-free only")
    ap.add_argument("--long", action="store_true", help="also N = 20 with 1 %% noise from the 3-element start (about 40 min)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lines: list[str] = []

    def emit(text: str = "") -> None:
        print(text, flush=True)
        lines.append(text)

    emit("Confined compression (report ch. 5): estimation of H, K from H0 = K0 = 4, truth (2, 1); "
         "weights W = I, V = I, W_a = 0")
    emit("Report (1993 PC):")
    for r in REPORT:
        it = "-" if r["iterations"] is None else r["iterations"]
        mins = "-" if r["minutes"] is None else f"{r['minutes']} min"
        emit(f"  {r['code']:<6} {r['points']:>5} points  iterations {it:>3}  time {mins:>8}  {r['outcome']}")
    emit()
    emit("shootlab (" + LEGEND + "):")
    emit(HEAD)
    rows, figures, kappas = [], [], {}
    for case in cases(args.quick, args.long):
        for noise in case.get("noise", (0.0,)):
            row, res = run_case(case, noise)
            rows.append(row)
            emit(fmt_row(row))
            if res is not None and noise == 0.0 and res.success and (case.get("spectra") or case.get("kappa")):
                spec = local_spectra(res)
                kappas[case["N"]] = dict(points=res.points, **kappa_summary(spec))
                if case.get("spectra"):
                    figures = plot_spectra(spec, out, case["N"])
            (out / "confined_report.json").write_text(json.dumps(json_ready(dict(report=REPORT, rows=rows)), indent=2))
            (out / "confined_report.txt").write_text("\n".join(lines) + "\n")      # partial runs keep a table
    emit()
    emit("Local Jacobians of the TPBVP (κ = min Re λ over the shooting points; κ·h: most negative interval):")
    for N, ks in sorted(kappas.items()):
        for key in ("initial", "solution"):
            k = ks[key]
            emit(f"  N = {N:>2} ({ks['points']:>3} points) {key:<9} κ = {k['kappa']:12.1f}   "
                 f"max|Re λ| = {k['max_abs_real']:12.1f}   κ·h = {k['kappa_h']:10.2f}")
    report = dict(report=REPORT, start=START, truth=TRUE, noise=f"{NOISE:g} x peak of each channel (seed 1)",
                  tolerance={str(k): v for k, v in TOLERANCE.items()}, quick=args.quick, rows=rows,
                  stiffness={str(k): v for k, v in kappas.items()}, figures=figures)
    (out / "confined_report.json").write_text(json.dumps(json_ready(report), indent=2))
    (out / "confined_report.txt").write_text("\n".join(lines) + "\n")
    print(f"\nwrote {out / 'confined_report.json'}, {out / 'confined_report.txt'}"
          + (f", {', '.join(figures)}" if figures else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
