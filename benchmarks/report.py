"""Write ``docs/benchmarks.md`` from the stored results: every figure beside the command that makes it.

    python benchmarks/report.py            # (re)writes docs/benchmarks.md
    python benchmarks/report.py --check    # exit status 1 when docs/benchmarks.md differs

The page is generated, never edited by hand: a benchmark run rewrites its JSON under
``benchmarks/results/`` (or ``studies/results/``), this script rewrites the page, and
``tests/test_docs.py`` checks that the page in the repository is the one the JSON gives.  A section
whose JSON is missing is left out.  Only the standard library is used (no torch, no numpy), so
the page can be rebuilt anywhere.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
import textwrap
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
STUDIES = ROOT / "studies" / "results"
PAGE = ROOT / "docs" / "benchmarks.md"

# names the stored studies used for the Newton strategies, and the names they have in shootlab
NEWTON_NAMES = {"press": "armijo", "musn": "appendix_a"}


# ---- formatting ---------------------------------------------------------------------------------

def newton_names(text: str) -> str:
    """``text`` with the stored studies' names of the Newton strategies replaced by shootlab's."""
    return re.sub(r"\b(press|musn)\b", lambda m: NEWTON_NAMES[m.group(1)], text)


def sec(x: float | None) -> str:
    """Seconds to three significant digits (ms below 0.1 s)."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    if x < 0.1:
        return f"{x * 1e3:.3g} ms"
    return f"{x:.3g} s"


def ratio(x: float | None, digits: int = 2) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def sci(x: float | None) -> str:
    return "–" if x is None else f"{x:.1e}"


def pct(x: float | None, digits: int = 0) -> str:
    return "–" if x is None else f"{100 * x:.{digits}f} %"


def yes(flag) -> str:
    return "yes" if flag else "no"


def geomean(xs) -> float:
    xs = [x for x in xs if x is not None and x > 0]
    return math.exp(sum(math.log(x) for x in xs) / len(xs)) if xs else float("nan")


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return out + [""]


def command(*lines: str) -> list[str]:
    return ["```bash", *lines, "```", ""]


def load(path: Path):
    return json.loads(path.read_text(encoding="utf-8")) if path.exists() else None


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


# ---- sections -----------------------------------------------------------------------------------

def engine() -> list[str]:
    path = RESULTS / "engine.json"
    d = load(path)
    if d is None:
        return []
    m = d["machine"]
    out = ["## The shooting engine", "",
           f"{d['problem']}; torch {m['torch']}, {m['threads']} thread. Source: `{rel(path)}`.", ""]
    out += command("python benchmarks/engine.py")
    out += ["Batched integration of all intervals against a Python loop over the intervals (residual F, "
            "the same integrator):", ""]
    out += table(["m", "integrator", "batched", "loop", "speed-up", "max deviation"],
                 [[r["m"], r["integrator"], sec(r["batched_s"]), sec(r["loop_s"]), f"{r['speedup']:.0f}x",
                   sci(r["max_deviation"])] for r in d["batched_vs_loop"]])
    out += ["Interval Jacobians by automatic differentiation through the integrator against the report's "
            "finite differences (eq. 3.7):", ""]
    out += table(["m", "integrator", "autograd", "finite differences", "time ratio", "max relative deviation"],
                 [[r["m"], r["integrator"], sec(r["autograd_s"]), sec(r["fd_s"]),
                   ratio(r["time_ratio_autograd_over_fd"], 1), sci(r["max_rel_deviation"])]
                  for r in d["autograd_vs_fd"]])
    parts = ["F_build", "jacobian_build", "factorisation", "back_substitution"]
    out += ["One Newton iteration, split (report fig. 3.8):", ""]
    out += table(["m", "integrator", "F", "Jacobian", "factorisation", "back-substitution"],
                 [[r["m"], r["integrator"], *(f"{sec(r['seconds'][k])} ({pct(r['share'][k])})" for k in parts)]
                  for r in d["newton_iteration"]])
    out += ["Interval Jacobians by batched reverse sweeps (several unit cotangents per sweep) against one "
            "sweep per row:", ""]
    out += table(["problem", "m", "n", "batched", "one per row", "speed-up", "max deviation"],
                 [[r["problem"], r["m"], r["n"], sec(r["batched_s"]), sec(r["single_s"]),
                   f"{r['speedup']:.1f}x", sci(r["max_abs_deviation"])] for r in d["jacobian_sweeps"]])
    pairs = defaultdict(dict)
    for r in d.get("newton_vs_n", []):
        pairs[(r["problem"], r["n"], r["m"], r["integrator"])][r["path"]] = r
    if pairs:
        out += ["One Newton iteration of an estimation TPBVP against its size n: the Jacobian of eq. 2.7 "
                "assembled from the model's derivatives (`autograd`) against reverse sweeps through the "
                "whole right-hand side (`reverse`):", ""]
        rows = []
        for (problem, n, mm, integ), p in pairs.items():
            a, r = p.get("autograd"), p.get("reverse")
            rows.append([problem, n, mm, integ,
                         sec(a["seconds"]["jacobian_build"]) if a else "–",
                         sec(r["seconds"]["jacobian_build"]) if r else "–",
                         sec(a["total"]) if a else "–", sec(r["total"]) if r else "–"])
        out += table(["problem", "n", "m", "integrator", "Jacobian, assembled", "Jacobian, reverse",
                      "iteration, assembled", "iteration, reverse"], rows)
    return out


def bvp_testset() -> list[str]:
    runs = [(RESULTS / "bvp_testset.json", "python benchmarks/bvp_testset.py --timeout 60"),
            (RESULTS / "bvp_testset_rtol1e-10.json",
             "python benchmarks/bvp_testset.py --timeout 60 --rtol 1e-10 "
             "--out benchmarks/results/bvp_testset_rtol1e-10.json")]
    runs = [(p, c, load(p)) for p, c in runs if p.exists()]
    if not runs:
        return []
    first = runs[0][2]
    s = first["meta"]["settings"]
    out = ["## Boundary value problems against scipy's `solve_bvp`", "",
           f"The Cash/Mazzia singularly perturbed test set and classics ({first['summary']['cases']} cases), from a "
           f"straight-line guess. `solve_bvp(tol={s['scipy_tol']:g})` from {s['scipy_nodes']} nodes against "
           "`shootlab.solve` with its defaults (integrator `auto`, `refine`, Newton `deuflhard`) on "
           + " → ".join(str(p) for p in s["points"]) + " points; each time the best of up to "
           f"{s['repeat']} runs after one untimed warm-up. A case is solved when its relative error is below "
           f"{s['err_tol']:g}. Time ratio: {first['meta']['time_ratio']}. "
           f"torch {first['meta']['torch']}, scipy {first['meta']['scipy']}, {first['meta']['torch_threads']} thread.",
           ""]
    out += command(*(c for _, c, _ in runs))
    rows = []
    for path, _, d in runs:
        m, sm = d["meta"], d["summary"]
        rows.append([f"rtol {m['settings']['rtol']:g}, atol {m['settings']['atol']:g}", sm["cases"],
                     sm["scipy_solved"], sm["shootlab_solved"],
                     f"{ratio(sm['geomean_ratio_both_solved'])} over {sm['n_both_solved']}",
                     f"{ratio(sm['min_ratio_both_solved'])}–{ratio(sm['max_ratio_both_solved'])}",
                     ", ".join(sm["shootlab_only"]) or "–", ", ".join(sm["scipy_only"]) or "–", f"`{rel(path)}`"])
    out += table(["shootlab's tolerance", "cases", "solve_bvp solves", "shootlab solves",
                  "geometric-mean time ratio shootlab / solve_bvp, both solved", "range",
                  "only shootlab", "only solve_bvp", "source"], rows)
    by = defaultdict(list)
    for c in first["cases"]:
        by[c["problem"]].append(c)
    rows = []
    for problem, cases in by.items():
        both = [c["time_ratio"] for c in cases if c["scipy"]["solved"] and c["shootlab"]["solved"]]
        rows.append([problem, ", ".join(c["param"] for c in cases),
                     sum(bool(c["scipy"]["solved"]) for c in cases), sum(bool(c["shootlab"]["solved"]) for c in cases),
                     ratio(geomean(both)) if both else "–"])
    out += [f"Per problem, rtol {first['meta']['settings']['rtol']:g}:", ""]
    out += table(["problem", "parameters", "solve_bvp solves", "shootlab solves",
                  "geometric-mean time ratio, both solved"], rows)
    path = RESULTS / "bvp_outside_set.json"
    d = load(path)
    if d is not None:
        out += ["Nine problems outside the test set, which the defaults were not tuned on (the same settings, "
                "101 points; the reference is `solve_bvp` at tol 1e-11). Source: "
                f"`{rel(path)}`.", ""]
        out += command("python benchmarks/bvp_outside_set.py")
        out += table(["problem", "solve_bvp error", "solve_bvp time", "shootlab error", "shootlab time",
                      "Newton iterations", "time ratio"],
                     [[c["problem"], sci(c["scipy_error"]), sec(c["scipy_time"]), sci(c["shootlab_error"]),
                       sec(c["shootlab_time"]), c["shootlab_iterations"], ratio(c["time_ratio"])]
                      for c in d["cases"]])
        out += [f"Geometric-mean time ratio shootlab / solve_bvp: {ratio(d['geometric_mean_ratio'])}.", ""]
    return out


def compile_fast_path() -> list[str]:
    path = RESULTS / "compile_fast_path.json"
    d = load(path)
    if d is None:
        return []
    out = ["## A compiled fixed-step path", "",
           f"`torch.compile` of the batched RK4 interval integration against eager mode: {d['problem']}, "
           f"m = {d['m']}, {d['steps']} steps; torch {d['torch']}. Source: `{rel(path)}`.", ""]
    out += command("python benchmarks/compile_fast_path.py")
    out += table(["inductor cache", "compile time", "compiled call", "eager call", "calls to break even"],
                 [[r["cache"], sec(r["compile_s"]), sec(r["compiled_call_s"]), sec(d["eager_call_s"]),
                   f"{r['break_even_calls']:,.0f}"] for r in d["runs"]])
    out += table(["one `shootlab.solve` of the same problem", "kernel calls", "seconds"],
                 [[name, ratio(r["kernel_calls"], 1), sec(r["seconds"])] for name, r in d["solve"].items()])
    out += [f"Pays within one solve: {yes(d['pays_within_one_solve'])}; shootlab has no compiled path.", ""]
    return out


def estimation_peers() -> list[str]:
    out = ["## Estimation against CasADi + IPOPT and `solve_bvp`", "",
           "CasADi + IPOPT direct multiple shooting fits the free run (output error, no model errors); "
           "shootlab solves the report's TPBVP (eq. 2.7), and with `--method output-error` the same "
           "output-error problem. CasADi comes with the extra `bench` (`pip install -e \".[bench]\"`).", ""]
    found = False
    path = RESULTS / "estimation_vs_casadi.json"
    d = load(path)
    if d is not None:
        found = True
        out += [f"**Mass–spring–damper** (report §3.4), {d['points']} points, RK4 ×{d['steps']}, "
                f"from m = b = k = 10 and 50. Source: `{rel(path)}`.", ""]
        out += command("python benchmarks/estimation_vs_casadi.py --problem msd")
        rows = []
        for r in d["rows"]:
            c, s = r["casadi"], r["shootlab"]
            others = "; ".join(f"{NEWTON_NAMES.get(k.split('_', 1)[1], k)}: "
                               + (f"{r[k]['iterations']} iterations" if r[k]["success"] else "fails")
                               for k in ("shootlab_press", "shootlab_musn") if k in r)
            rows.append([r["data"], f"{r['start']:g}",
                         f"{yes(c['within_5_percent'])}, {c['iterations']} iterations, {sec(c['seconds'])}",
                         f"{yes(s['within_5_percent'])}, {s['iterations']} iterations, {sec(s['seconds'])}",
                         ratio(r["time_ratio"]), others])
        out += table(["data", "start", "CasADi: within 5 %, iterations, time",
                      "shootlab (default Newton): within 5 %, iterations, time", "time ratio CasADi / shootlab",
                      "other Newton strategies"], rows)
    path = RESULTS / "mixture_vs_casadi.json"
    d = load(path)
    if d is not None:
        found = True
        out += [f"**Confined compression** (report ch. 5), N elements, records of a {d['fine_elements']}-element "
                f"simulation (H = {d['truth']['H']:g}, K = {d['truth']['K']:g}), {d['points']} points, from H = K = 4; "
                "CasADi integrates by implicit Euler ×2. Ratios are shootlab / CasADi, for the whole command and "
                f"for the solve alone, side by side in one run. Source: `{rel(path)}`.", ""]
        out += command("python benchmarks/estimation_vs_casadi.py --problem mixture --elements 20 50 --no-lifted")
        rows = []
        for r in d["rows"]:
            c, s, oe = r["casadi"], r["shootlab"], r["shootlab_output_error"]
            tpbvp = (f"{ratio(r['ratio_command'])} / {ratio(r['ratio_solve'], 3)}, {pct(s['max_relative_error'], 2)}"
                     if s["success"] else "fails: " + s["message"].split(":")[1].strip())
            rows.append([r["data"], r["elements"], f"{sec(c['command_s'])} / {sec(c['solve_s'])}",
                         pct(c["max_relative_error"], 2), tpbvp,
                         f"{ratio(r['ratio_command_output_error'])} / {ratio(r['ratio_solve_output_error'], 3)}, "
                         f"{pct(oe['max_relative_error'], 2)}"])
        out += table(["data", "N", "CasADi command / solve", "CasADi: error in H, K",
                      "TPBVP: ratio command / solve, error", "output error: ratio command / solve, error"], rows)
        out += ["The TPBVP of the 50-element model is singular at its first iteration on 201 points: the "
                "fastest modes are so fast per step that the implicit midpoint rule maps the growing and the "
                "decaying one alike to |R| ≈ 1 and the boundary conditions no longer pin them "
                "(`mixtures/identification.py`); output error is the estimate there.", ""]
    path = RESULTS / "mixture_vs_casadi_N3_loaded.json"
    d = load(path)
    if d is not None:
        rows = [r for r in d["rows"] if r["elements"] == 3]
        if rows:
            found = True
            out += ["The report's 3-element mesh on the same records (a run with CasADi's lifted variant too, on "
                    f"a loaded machine). Source: `{rel(path)}`.", ""]
            out += command("python benchmarks/estimation_vs_casadi.py --problem mixture --elements 3 "
                           f"--out {rel(path)}")
            out += table(["data", "solver", "converged", "iterations", "error in H, K", "command", "solve"],
                         [[r["data"], x["solver"], yes(x["success"]), x["iterations"],
                           pct(x["max_relative_error"], 1), sec(x["command_s"]), sec(x["solve_s"])]
                          for r in rows for x in (r["casadi"], r.get("casadi_lifted"), r["shootlab"]) if x])
    path = RESULTS / "command_vs_casadi.json"
    d = load(path)
    if d is not None:
        found = True
        out += [f"**Whole commands**, {d['elements']} elements, {d['record']}: `shootlab estimate` (with its figures, "
                "without, and by output error) beside the peer's own script (`benchmarks/casadi_confined.py`: numpy "
                "and CasADi, no torch), and the floors `import torch`, torch's first forward-mode product and "
                f"`import casadi`; each a fresh process, medians over {d['repeats']} rounds in alternating order on "
                f"{d['cpus']} cores. Source: `{rel(path)}`.", ""]
        out += command(f"python benchmarks/estimation_vs_casadi.py --problem command --repeats {d['repeats']}")
        med, rat = d["median"], d["median_ratio_to_casadi"]
        out += table(["command", "wall", "CPU", "ratio to the peer, wall", "ratio to the peer, CPU"],
                     [[name, sec(med["seconds"][name]), sec(med["cpu_seconds"][name]),
                       ratio(rat["seconds"].get(name)) if name in rat["seconds"] else "1",
                       ratio(rat["cpu_seconds"].get(name)) if name in rat["cpu_seconds"] else "1"]
                      for name in med["seconds"]])
    path = RESULTS / "estimation_vs_scipy.json"
    d = load(path)
    if d is not None:
        found = True
        m = d["meta"]
        out += [f"**The same TPBVP by `solve_bvp`** (mass–spring–damper, {m['data']}; solve_bvp with "
                f"{m['scipy_jacobian']}, tol {m['tol']:g}, at most {m['max_nodes']:,} nodes). "
                f"Source: `{rel(path)}`.", ""]
        out += command("python benchmarks/estimation_vs_scipy.py")
        rows = []
        for r in d["rows"]:
            sp, sl = r["scipy"], r["shootlab"]
            rows.append([f"{r['start']:g}", f"{yes(sp['success'])}, {sec(sp['seconds'])}, {sp['nodes']} nodes"
                         + ("" if sp["success"] else f" ({sp['message']})"),
                         f"{yes(sl['success'])}, {sec(sl['seconds'])}, {sl['iterations']} iterations",
                         sci(r.get("max_deviation_x")) if sp["success"] and sl["success"] else "–"])
        out += table(["start", "solve_bvp: converged, time", "shootlab: converged, time",
                      "largest difference of the solutions"], rows)
    return out if found else []


def long_records() -> list[str]:
    path = RESULTS / "long_records.json"
    d = load(path)
    if d is None:
        return []
    out = ["## Records of any length", "",
           "The mass–spring–damper with 20,000 and 200,000 samples (`shootlab simulate msd --noise 0.01 "
           "--duration 199.99` / `1999.99`), `shootlab estimate --initial m=10 b=10 k=10` with every other "
           f"default (figures included), each in its own process. Source: `{rel(path)}`.", ""]
    out += command("python benchmarks/long_records.py")
    out += table(["samples", "default shooting points", "Newton iterations", "wall time", "peak memory",
                  "errors of m, b, k in standard errors"],
                 [[f"{r['samples']:,}", r["points"], r["iterations"], f"{r['wall_s']:.1f} s", f"{r['max_rss_mb']} MB",
                   ", ".join(f"{v:g}" for v in r["errors_in_se"].values())] for r in d["rows"]])
    out += [f"Time ratio long / short: {d['time_ratio']:g} (10x the samples).", ""]
    return out


def figures() -> list[str]:
    path = RESULTS / "figures.json"
    d = load(path)
    if d is None:
        return []
    out = ["## Figures", "",
           "Each figure writer (every line drawn through each window's smallest and largest sample, "
           f"`shootlab.outputs.minmax_decimate`) beside the writers of commit {d['against']}, which draw every "
           f"sample; medians of {d['repeats']} runs. Source: `{rel(path)}`.", ""]
    out += command(f"python benchmarks/figures.py --repeats {d['repeats']} --against {d['against']}")
    out += table(["figures", "wall", f"wall, {d['against']}", "CPU", f"CPU, {d['against']}"],
                 [[name, sec(v["this"]), sec(v[d["against"]]), sec(d["median_cpu"][name]["this"]),
                   sec(d["median_cpu"][name][d["against"]])] for name, v in d["median"].items()])
    return out


def gpu() -> list[str]:
    path = RESULTS / "gpu.json"
    d = load(path)
    if d is None:
        return []
    out = ["## On a GPU", "",
           f"{d['gpu']} against one CPU thread of the same machine; torch {d['torch']}, Python {d['python']}. "
           f"Source: `{rel(path)}` (and `gpu.png`, `gpu_profile.txt` beside it).", ""]
    out += command("python benchmarks/gpu.py")
    sc = d.get("scaling")
    if sc:
        out += [f"Scaling in m: `{sc['settings']}`.", ""]
        out += table(["problem", "m", "CPU", "GPU", "speed-up", "Newton iterations", "CPU − GPU"],
                     [[r["problem"], f"{r['m']:,}", sec(r["cpu_seconds"]), sec(r["cuda_seconds"]),
                       f"{r['cuda_speedup']:.2f}x", r["cuda_iterations"], sci(r["max_difference"])]
                      for r in sc["rows"]])
    b = d.get("batch")
    if b:
        out += [f"{b['problems']:,} problems of one structure (Troesch and Bratu families, m = {b['m']:,}; "
                f"{b['settings']}):", ""]
        out += table(["how", "time", "converged"],
                     [["`solve_batch` on the GPU", sec(b["solve_batch_cuda_seconds"]), b["solve_batch_cuda_converged"]],
                      ["`solve_batch` on the CPU", sec(b["solve_batch_cpu_seconds"]), b["solve_batch_cpu_converged"]],
                      [f"`solve` one after another on the CPU ({b['alone_cpu_solved']} solved, the rest extrapolated)",
                       sec(b["alone_cpu_seconds_all_estimated"]), f"{b['alone_cpu_converged']} of {b['alone_cpu_solved']}"]])
        out += [f"`solve_batch` on the GPU against `solve` one after another on the CPU: "
                f"{b['speedup_solve_batch_cuda_vs_alone_cpu']:.0f}x; the CPU and GPU batches agree to "
                f"{sci(b['solve_batch_max_difference_cpu_cuda'])}.", ""]
    k = d.get("kernels")
    if k:
        c, g = k["cpu"], k["cuda"]
        out += [f"Batched kernels on {c['matrices']:,} matrices of {c['n']}×{c['n']}:", ""]
        names = [("eigvals_seconds", "eigenvalues (`torch.linalg.eigvals`)"),
                 ("spectral_bounds_seconds", "spectral bounds by matrix products (`spectral=\"bound\"`)"),
                 ("geqrf_seconds", "Householder QR (`geqrf`)"), ("ormqr_seconds", "Qᵀ applied by `ormqr`"),
                 ("wy_apply_seconds", "Qᵀ applied in compact WY form"), ("bmm_seconds", "batched matrix product")]
        out += table(["kernel", "CPU", "GPU"], [[label, sec(c[key]), sec(g[key])] for key, label in names])
    cf = d.get("confined")
    if cf:
        out += ["The confined-compression estimates:", ""]
        out += table(["estimate", "CPU", "GPU"],
                     [["20-element TPBVP", sec(cf["tpbvp_N20_cpu"]["seconds"]), sec(cf["tpbvp_N20_cuda"]["seconds"])],
                      ["50-element output error", sec(cf["output_error_N50_cpu"]["seconds"]),
                       sec(cf["output_error_N50_cuda"]["seconds"])]])
        out += [f"({cf['note']}.)", ""]
    return out


def diagnosis() -> list[str]:
    path = RESULTS / "diagnosis.json"
    d = load(path)
    if d is None:
        return []
    crit = d["meta"]["criteria"]
    out = ["## Diagnosis: withheld effects", "",
           "Records generated with one effect of a library withheld from the nominal model (the manipulator rig: "
           "a 1 s sine sweep to identify, a PD controller's command to validate; the mixture: ramp-and-hold "
           "creep, then load–unload–reload), and records with no effect. `ours`: the packages' own simulators; "
           "`independent`: the simulators of `benchmarks/independent/`, written apart from them (LSODA per DAC "
           "segment, other friction widths, quantised encoders, coloured noise, other inputs; the mixture by "
           "finite volumes on 120 cells; a Duffing oscillator with a small input offset in every record; "
           "cascaded tanks with Torricelli outflows and overflow, by events). Right means the withheld effect is "
           "named (top 1); a clean record is right when no effect is named, or only an effect the simulator puts "
           "in every record. In the reliability table a verdict is right when it names the withheld effect or "
           "only such an effect. Look-alike pairs (`--lookalikes`) are diagnosed again with the record the "
           "simulator makes under the experiment the first diagnosis proposed as validation record. Targets: top 1 at least "
           f"{pct(crit['top1'])}, clean records right at least {pct(crit['clean'])}, mean validation shrink at least "
           f"{pct(crit['shrink'])}. Source: `{rel(path)}` ({d['meta']['cases']} cases; every case cached in "
           "`benchmarks/results/diagnosis_cases/`), confusion matrices in `diagnosis_confusion*.png`.", ""]
    held = [(sim, k) for sim, v in d["per_simulator"].items()
            for k in (v["criteria"].get("held_out") or {}).get("seeds", [])]
    families = {"ours": "mechanical mixture", "independent": "mechanical mixture duffing tanks"}
    out += command("python benchmarks/diagnosis.py --quick --simulators ours independent "
                   "--families mechanical mixture duffing tanks --jobs 2",
                   *(f"python benchmarks/diagnosis.py --quick --simulators {sim} --families {families.get(sim, '')} "
                     f"--seed {k}" + (" --experiment proposed" if sim == "independent" else "") + " --jobs 2"
                     + ("" if i else "     # held-out seeds") for i, (sim, k) in enumerate(held)),
                   "python benchmarks/diagnosis.py --lookalikes --simulators independent --families mechanical mixture "
                   "--experiment proposed --jobs 2",
                   "python benchmarks/diagnosis.py --cached            # the summary of every cached case")
    rows = []
    for sim, v in d["per_simulator"].items():
        c = v["criteria"]
        rows.append([sim, f"{pct(c['top1_moderate_1pct'])} of {c['cases_moderate_1pct']}",
                     pct(c["top1_ranking_moderate_1pct"]), f"{pct(c['clean_accuracy'])} of {c['clean_cases']}",
                     c["false_alarms"], pct(c["mean_validation_shrink_moderate_1pct"]),
                     pct(c["verdicts_whose_validation_shrinks"])])
    out += table(["simulator", "moderate effects at 1 % noise named", "named first by the ranking alone",
                  "clean records right", "false alarms", "mean validation shrink", "verdicts whose validation shrinks"],
                 rows)
    for sim, v in d["per_simulator"].items():
        h = v["criteria"].get("held_out")
        if h:
            seeds = ", ".join(f"`--seed {k}`" for k in h.get("seeds", []))
            out += [f"On the held-out noise seeds alone ({seeds}: records the diagnosis was not developed on), "
                    f"{sim}: {pct(h['top1_moderate_1pct'])} of {h['cases_moderate_1pct']} moderate effects named, "
                    f"{h['false_alarms']} false alarms in {h['clean_cases']} clean records.", ""]
    rows = []
    for sim, v in d["per_simulator"].items():
        for family, groups in v.items():
            if family == "criteria":
                continue
            for group, g in groups.items():
                if "clean_accuracy" in g:
                    answers = defaultdict(int)
                    for a in g["answers"]:
                        answers[a] += 1
                    rows.append([sim, family, group, g["cases"], "–", pct(g["clean_accuracy"]),
                                 ", ".join(f"{a} ×{n}" for a, n in sorted(answers.items())), "–"])
                else:
                    missed = [f"{e} → {p['answer']}" for e, p in g["per_effect"].items() if p["answer"] != e]
                    rows.append([sim, family, group, g["cases"], pct(g["top1"]), "–",
                                 "; ".join(missed) or "all named", pct(g["mean_validation_shrink"])])
    out += ["Per family, magnitude and noise level:", ""]
    out += table(["simulator", "family", "records", "cases", "named (top 1)", "clean right", "answers that differ",
                  "mean validation shrink"], rows)
    out += ["Reliability of the confidence a verdict is given:", ""]
    out += table(["confidence", "verdicts", "right", "fraction right"],
                 [[r["confidence"], r["verdicts"], r["right"],
                   "–" if r["fraction_right"] is None else pct(r["fraction_right"])] for r in d["reliability"]])
    tried = [r for r in d["records"] if r.get("experiment") and (r.get("experiment_input") or {}).get("lookalikes")]
    if tried:
        right = [r for r in tried if r["experiment"]["right"]]
        sure = sum((r["experiment"].get("confidence") or 0.0) >= 0.9 for r in right)
        out += [f"Records answered with a look-alike and a proposed experiment, diagnosed again with the record the "
                f"simulator makes under that input as the validation record (`--experiment proposed`; the cases of "
                f"any command above, rerun with it and `--resume`): the withheld effect named in {len(right)} of "
                f"{len(tried)}, {sure} of them with confidence at least 0.9 (the others with the look-alike named "
                f"beside it again).", ""]
        out += table(["simulator", "family", "effect", "records", "first answer", "beside it", "proposed input",
                      "answer under it"],
                     [[r["simulator"], r["family"], r["effect"], f"{r['magnitude']}, seed {r['seed']}",
                       f"{r['answer']} ({ratio(r.get('answer_confidence'))})", ", ".join(r.get("lookalikes") or []),
                       r["experiment_input"]["label"],
                       f"{r['experiment']['answer']} ({ratio(r['experiment'].get('confidence'))})"
                       + ("" if r["experiment"]["right"] else " ✗")] for r in tried])
    path = RESULTS / "mixture_misfit.json"
    m = load(path)
    if m is not None:
        out += ["**The mixture's TPBVP objective J against the free-run misfit** (confined model, "
                f"{m['points']} points, {pct(m['noise'])} white + AR(1) noise, records of the independent simulator): "
                "J relative to the clean record with the same noise draw, and the output-error free run's RMS "
                "misfit over the record's noise level on the identification record. J moves with the estimated "
                "parameters, down as often as up; the free run separates the effects, which is why the mixture "
                f"library's verdict is judged by the free run. Source: `{rel(path)}`.", ""]
        out += command("python benchmarks/mixture_misfit.py")
        out += table(["elements", "effect", "magnitude", "converged", "J / J of the clean record",
                      "free-run misfit: displacement", "pressure"],
                     [[r["elements"], r["effect"], r["magnitude"], yes(r["success"]),
                       ratio(r.get("J_over_clean")) if r["success"] else "–",
                       ratio(r["free_run_identification"]["displacement"]) if r.get("free_run_identification") else "–",
                       ratio(r["free_run_identification"]["pressure"]) if r.get("free_run_identification") else "–"]
                      for r in m["rows"]])
    return out


def report_reproductions() -> list[str]:
    out = ["## The report's experiments reproduced", "",
           "The report's tables rerun with shootlab (`python -m studies.<name>`; each writes its JSON and "
           "figures to `out/<name>/`, a copy of which is kept in `studies/results/`).", ""]
    found = False
    path = STUDIES / "msd" / "msd_report.json"
    d = load(path)
    if d is not None:
        found = True
        out += [f"**Mass–spring–damper** (report §3.4): {d['meta']['data']}, {d['meta']['points']} points, "
                f"{d['meta']['integrator']} ×{d['meta']['steps']}. Source: `{rel(path)}`.", ""]
        out += command("python -m studies.msd_report")
        rows = []
        for r in d["rows"]:
            rep = r.get("report")
            rows.append([r["case"], NEWTON_NAMES.get(r["newton"], r["newton"]), f"{r['start']:g}",
                         f"{r['iterations']}" if r["success"] else f"fails at iteration {r['iterations']}",
                         sec(r["seconds"]),
                         "–" if not r["success"] else f"{max(abs(r[p] - 1) for p in 'mbk'):.1e}",
                         "–" if not rep else f"{rep['code']}: " + (f"{rep['iterations']} iterations, "
                                                                  if rep["iterations"] else "")
                         + f"{rep['minutes']} min, {rep['outcome']}"])
        out += table(["data", "Newton", "start m = b = k", "iterations", "time",
                      "largest error of m, b, k", "report (1993 PC)"], rows)
    path = STUDIES / "flexible" / "flexible_report.json"
    d = load(path)
    if d is not None:
        found = True
        out += ["**Flexible manipulator** (report ch. 4) on the virtual rig (`manipulators/rig.py`): a 1 s sine "
                "sweep to identify, a PD controller's command to validate; `friction_only`: a rig whose only "
                "effect is the report's friction, `full`: every effect of the rig (friction varying, gain "
                f"error, delay, hold, quantisation, noise), whose friction varies over the record, so that its "
                "parameters have no single true value (the error is against the mean, scaled by the gain error). "
                f"Source: `{rel(path)}`.", ""]
        out += command("python -m studies.flexible_report")
        rows = []
        for case, v in d["cases"].items():
            e = v["extended"]
            rel_err = max(abs(x) for x in v["extended_rel_error"].values())
            rows.append([case, f"{v['plain']['iterations']}", f"{e['iterations']}, {sec(e['seconds'])}",
                         pct(rel_err, 1), ratio(v["validation_ratio"]["rms_s1"], 1),
                         ratio(v["validation_ratio"]["rms_s2"], 1)])
        out += table(["rig", "plain model: iterations (weight continuation)", "extended model: iterations, time",
                      "largest parameter error of the extended model", "validation RMS plain / extended, s1",
                      "s2"], rows)
    path = STUDIES / "confined" / "confined_report.json"
    d = load(path)
    if d is not None:
        found = True
        rep = "; ".join(f"{r['code']} {r['points']} points: {r['outcome']}"
                        + (f", {r['iterations']} iterations, {r['minutes']:g} min" if r["iterations"] else "")
                        for r in d["report"])
        out += [f"**Confined compression** (report ch. 5) from H = {d['start']['H']:g}, K = {d['start']['K']:g} "
                f"(truth {d['truth']['H']:g}, {d['truth']['K']:g}); noise: {d['noise']}. Report (1993 PC): {rep}. "
                f"Source: `{rel(path)}`.", ""]
        out += command("python -m studies.confined_report")
        rows = [[r["N"], f"{r['noise']:g}", newton_names(r["case"]), NEWTON_NAMES.get(r["newton"], r["newton"]), r["integrator"],
                 r["points"], r["iterations"], sec(r["seconds"]),
                 f"{sci(r['err_H'])} / {sci(r['err_K'])}", r["verdict"]] for r in d["rows"]]
        out += table(["N", "noise", "case", "Newton", "integrator", "points", "iterations", "time",
                      "relative error H / K", "verdict"], rows)
    path = STUDIES / "suggest" / "validation.json"
    d = load(path)
    if d is not None:
        found = True
        rows = d["table"]
        per = defaultdict(lambda: [0, 0])
        for r in rows:
            key = "one step per interval" if r["integrator"].endswith(":1") else "2–4 steps per interval"
            per[key][0] += bool(r["within_factor_2"])
            per[key][1] += 1
        out += ["**Shooting points from the local eigenvalues** (`suggest_shooting_points`, report eq. 5.6) "
                "against sweeps of the number of points: the prediction within a factor 2 of the smallest "
                "number on which the solve is stable. Source: "
                f"`{rel(path)}` (the table in `validation.txt` beside it).", ""]
        out += command("python -m studies suggest --validate")
        out += table(["integrator", "predictions within 2x"], [[k, f"{a} of {n}"] for k, (a, n) in per.items()])
    for path in (STUDIES / "scaling" / "scaling.json", STUDIES / "scaling_n" / "scaling.json"):
        d = load(path)
        if d is None:
            continue
        found = True
        s = d["settings"]
        scan_m = len(s["m"]) > 1
        out += [f"**Time and memory of one Newton iteration** ({s['integrator']} ×{s['steps']}, best of "
                f"{s['repeat']}): " + (f"against m on the {s['problem']} (n = {d['m_rows'][0]['n']}), " if scan_m else "")
                + f"against n on the {s['n_problem']} model with more elements (m = {s['n_points']}). "
                f"Source: `{rel(path)}`.", ""]
        out += command(f"python -m studies scaling --m {' '.join(str(m) for m in s['m'])} "
                       f"--elements {' '.join(str(e) for e in s['elements'])} --repeat {s['repeat']} "
                       f"--out {rel(path.parent)}")
        keys = ["F_build", "jacobian_build", "factorisation", "total", "peak_memory"]
        out += table(["fitted exponent in", "F", "Jacobian", "factorisation", "iteration", "peak memory"],
                     [[axis, *(ratio(d[f"exponents_{axis}"][k]["all"]) for k in keys)]
                      for axis in (("m", "n") if scan_m else ("n",))])
        out += table(["n", "m", "F", "Jacobian", "factorisation", "iteration", "peak memory"],
                     [[r["n"], r["m"], sec(r["seconds"]["F_build"]), sec(r["seconds"]["jacobian_build"]),
                       sec(r["seconds"]["factorisation"]), sec(r["total"]), f"{r['peak_bytes'] / 2**20:.0f} MiB"]
                      for r in d["n_rows"]])
    return out if found else []


def friction_laws() -> list[str]:
    path = RESULTS / "friction_laws.json"
    d = load(path)
    if d is None:
        return []
    out = ["## Diagnosis: Coulomb against Stribeck friction on the independent rig", "",
           "What the rig's records can tell apart, what the library's laws can represent, and what the "
           "diagnosis's TPBVP estimates (moderate size, 1 % noise). First the rig's own laws: each record "
           "refitted, noise-free, by the other law with every parameter free (and m2, k, b); ΔJ in units of the "
           "records' noise, on the identification record and on the validation record's free run. Then the "
           "library's laws fitted by output error to the noisy records of one seed, as the diagnosis weighs them "
           "(`shootlab/diagnosis/nested.py`: its free run from rest; Stribeck from each of its embeddings of the "
           "Coulomb fit, constrained to its bounds, until one converges at or below the Coulomb fit's cost): "
           "free-run costs Σ((y − z)/σ)² on the identification / validation record, z the Coulomb − Stribeck "
           "difference summed over both, less the extra parameters, over its standard error (the residuals' "
           f"autocorrelation counted), and the TPBVP started from the Stribeck fit. Source: `{rel(path)}`.", ""]
    out += command("python benchmarks/friction_laws.py")
    out += table(["record", "refitted by", "ΔJ identification", "ΔJ validation"],
                 [[r["effect"], r["twin"] or "the nominal rig", f"{r['dJ_identification']:.3g}",
                   f"{r['dJ_validation']:.3g}"] for r in d["rig_laws"]])
    rows = []
    for rec in d["library_laws"]:
        name, w = f"{rec['effect']} (seed {rec['seed']})", rec.get("weighed")
        rows.append([name, "nominal", " / ".join(f"{c:.4g}" for c in rec["nominal"]), ""])
        rows.append([name, "coulomb + input_delay",
                     "–" if w is None else f"{w['identification_cost_simple']:.4g} / {w['cost_simple']:.4g}",
                     "" if rec["coulomb"]["success"] else "not converged"])
        for t in rec["tries"]:
            start = ", ".join(f"{p.split('_')[-1]} {v:.3g}" for p, v in t["start"].items())
            note = ("not converged" if not t["success"] else "above the Coulomb fit" if t["above"] else
                    "on its bound: " + ", ".join(t["on_bound"]) if t["on_bound"] else "")
            rows.append([name, f"stribeck + input_delay from {start}",
                         f"{w['identification_cost_richer']:.4g} / {w['cost_richer']:.4g}"
                         if w is not None and t is rec["tries"][-1] and t["success"] and not t["above"] else "–",
                         f"{t['evaluations']} free runs, {t['seconds']:.0f} s" + (f"; {note}" if note else "")])
        tp = rec.get("tpbvp_from_output_error")
        rows.append([name, "z = (ΔC − Δk)/se, Coulomb − Stribeck", "–" if w is None else f"{w['z']:.2f}",
                     "" if tp is None else ("TPBVP from the Stribeck fit: " + (
                         f"J {tp['J']:.5g}" if tp["success"] else "not converged (" + tp["message"].split(":")[0] + ")"))])
    out += table(["record", "model", "output-error costs", ""], rows)
    return out


def free_run_start() -> list[str]:
    path = RESULTS / "free_run_start.json"
    d = load(path)
    if d is None:
        return []
    out = ["## Diagnosis: where the free run starts, on the independent rig", "",
           "Every free run of the diagnosis on a mechanical record starts from the library's `initial_state`; "
           "`\"rest\"` takes the measured positions' mean over the first five samples, the velocities 0. First the "
           "rig itself (its own laws, noise-free) run from that start and from its true one (rest at 0): the "
           "largest difference of an encoder over the record in units of its noise level, and the cost "
           "Σ(Δ/σ)² the start alone adds over both encoders (the noise gives each about 1,000), least and most "
           "over the seeds. Then the records the benchmark misses, diagnosed from the true start — an oracle no "
           "user has, the most a start estimated from the data could recover — beside the answer from rest "
           f"(moderate size, 1 % noise). Source: `{rel(path)}`.", ""]
    out += command("python benchmarks/free_run_start.py --jobs 2")
    groups: dict = {}
    for r in d["reach"]:
        g = groups.setdefault((r["effect"], r["record"]), dict(largest=[], cost=[]))
        g["largest"].append(max(r["s1"]["largest"], r["s2"]["largest"]))
        g["cost"].append(r["s1"]["cost"] + r["s2"]["cost"])
    seeds = sorted({r["seed"] for r in d["reach"]})
    out += table(["record", "run", "largest difference / σ", "cost the start adds"],
                 [[e, rec, f"{min(g['largest']):.2f}–{max(g['largest']):.2f}", f"{min(g['cost']):.0f}–{max(g['cost']):.0f}"]
                  for (e, rec), g in groups.items()])
    out += [f"Seeds {', '.join(str(s) for s in seeds)}.", ""]

    def answer(a, c):
        return a if c is None else f"{a} ({c:.2f})"
    out += table(["record", "seed", "from rest", "from the true start"],
                 [[o["effect"], o["seed"], answer(o["rest"]["answer"], o["rest"]["confidence"]) if o.get("rest") else "–",
                   answer(o["answer"], o["confidence"])] for o in d["oracle"]])
    return out


def free_run_windows() -> list[str]:
    path = RESULTS / "free_run_windows.json"
    d = load(path)
    if d is None:
        return []
    names = {"pendulum": "the pendulum at the Coulomb fit's non-physical f = −0.54 (Radau IIA)",
             "van_der_pol": "van der Pol's oscillator from near rest, a bare torch right-hand side (RK4)",
             "coulomb_fit": "the pendulum's output-error fit of Coulomb friction (86 free runs)"}
    out = ["## Free runs whose sweeps fail over the whole record", "",
           "A free run is shot with all its sample intervals at once; where those Newton sweeps fail over the "
           "whole record (a run that is unstable or strongly non-linear), it is run in windows that shorten where "
           "they fail (`free_run._in_windows`), where it had gone sample by sample. Both ways side by side in one "
           "process, alternating, the median of the repeats; the largest difference of the two runs' states (of "
           "the fit: its parameters) beside their scale. Windows pay where a call of the right-hand side carries "
           "overhead, as a model's does (its least squares for ζ); on a bare right-hand side of a few "
           f"operations the run sample by sample is faster. torch {d['torch']}, {d['threads']} thread. "
           f"Source: `{rel(path)}`.", ""]
    out += command("python benchmarks/free_run_windows.py")
    out += table(["case", "in windows", "sample by sample", "sample by sample / in windows", "largest difference (scale)"],
                 [[names.get(r["case"], r["case"]), sec(r["windows_s"]), sec(r["sample_by_sample_s"]),
                   f"{r['speedup']:.1f}×", f"{r['max_difference']:.2g} ({r['scale']:.3g})"] for r in d["cases"]])
    return out


SECTIONS = [engine, bvp_testset, compile_fast_path, estimation_peers, long_records, figures, gpu, diagnosis,
            friction_laws, free_run_start, free_run_windows, report_reproductions]


def render() -> str:
    """The page: a header and every section whose results exist."""
    lines = ["# Benchmarks", "",
             "<!-- generated by `python benchmarks/report.py` from benchmarks/results/ and studies/results/: "
             "edit the script, not this page -->", "",
             "Every figure here is read from the JSON a benchmark wrote; the command above each table makes it "
             "again (from the repository root, in the project's virtual environment). Speed is compared side by "
             "side in one run, as ratios: absolute seconds depend on the machine (a 2-core machine shared with "
             "other work unless a section says otherwise). `python benchmarks/report.py` rewrites this page "
             "from the results.", ""]
    for section in SECTIONS:
        lines += section()
    while lines and lines[-1] == "":
        lines.pop()
    return "\n".join(wrap(lines)) + "\n"


def wrap(lines: list[str], width: int = 100) -> list[str]:
    """Prose lines wrapped at ``width``; tables, headings, comments and code blocks as they are."""
    out, code = [], False
    for line in lines:
        if line.startswith("```"):
            code = not code
        if code or not line or line.startswith(("```", "|", "#", "<!--")):
            out.append(line)
        else:
            out += textwrap.wrap(line, width, break_long_words=False, break_on_hyphens=False)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="do not write: exit 1 when the page differs")
    ap.add_argument("--out", type=Path, default=PAGE, help=f"the page (default {rel(PAGE)})")
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        same = args.out.exists() and args.out.read_text(encoding="utf-8") == text
        print(f"{args.out}: {'up to date' if same else 'out of date: run python benchmarks/report.py'}")
        return 0 if same else 1
    args.out.write_text(text, encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
