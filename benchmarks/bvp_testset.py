"""Side-by-side benchmark: scipy.integrate.solve_bvp vs shootlab.solve on the BVP test set.

For every problem of ``studies.bvp_testset`` (Cash/Mazzia problems for each
eps, plus linear_unstable, troesch(5), troesch(10), bratu and
singular_perturbation(eps)):

* scipy: ``solve_bvp(fun, bc, x, y, tol=1e-8, max_nodes=200000)`` from the
  straight-line guess on a uniform mesh of 101 nodes;
* shootlab: ``shootlab.solve(BVP, t, x_guess, rtol=tol, atol=tol/100)`` from the
  same straight-line guess: the integrator tolerance matched to the ``tol`` solve_bvp
  is asked for (``--rtol``/``--atol`` override it; ``--integrator`` picks a scheme),
  everything else shootlab's defaults (the automatic integrator choice, ``refine``,
  Newton ``deuflhard`` with its tolerance following rtol); on 101 -> 401 -> 1601
  uniform shooting points, stopping at the first attempt that reports success
  *and* has a relative max error <= 1e-5.  The options are printed and saved.

Timing: each solver runs once on a small problem before the table (the first
torch.func transform of a process imports torch._dynamo, ~1.5 s, which is not a
cost of any one case); each case is timed as the best of up to ``--repeat`` (3)
runs while the runs so far took under ``--repeat-budget`` (1 s), the same rule for
both solvers.  The summary prints the geometric mean of the time ratios over the
cases both solve.

Errors are ``max |y_num - y_exact| / max |y_exact|`` of the solution component
y, measured on a fine grid (2001 uniform points + geometric clustering at the
layer locations) through ``res.sol`` / scipy's ``sol``.  A case counts as
*solved* when the solver reports success and that error is <= ``--err-tol``.
The shootlab time is the total over all attempts (``time_last`` is the last
attempt alone); ``ratio`` = shootlab total time / scipy time.

Every case is wrapped in try/except and a per-case, per-solver time limit
(SIGALRM, ``--timeout``; for shootlab the budget is shared by the escalation
attempts), so a crash or a hang in one case does not kill the table.
If ``shootlab.solve`` cannot be imported the shootlab column reads ``n/a``.

Usage::

    python benchmarks/bvp_testset.py                 # everything (slow-ish)
    python benchmarks/bvp_testset.py --quick         # small subset
    python benchmarks/bvp_testset.py --eps 1e-2 1e-3 --problems bvpT1 troesch
    python benchmarks/bvp_testset.py --out /tmp/r.json --skip-shootlab
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import platform
import signal
import sys
import time
import traceback
import warnings
from pathlib import Path

import numpy as np
import scipy
import torch
from scipy.integrate import solve_bvp

_REPO = Path(__file__).resolve().parents[1]
# this checkout's shootlab and studies, not whichever one an editable install points to
sys.path.insert(0, str(_REPO))
from shootlab.outputs import json_ready  # noqa: E402
from studies import bvp_testset as ts  # noqa: E402

DEFAULT_OUT = _REPO / "benchmarks" / "results" / "bvp_testset.json"
QUICK_CASH = ("bvpT1", "bvpT2", "bvpT6", "bvpT20", "bvpT21")
QUICK_EPS = (1e-1, 1e-2)


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------
class CaseTimeout(BaseException):
    """Raised by SIGALRM; BaseException so solver-internal ``except Exception`` cannot eat it."""


class _time_limit:
    def __init__(self, seconds: float | None):
        self.seconds = seconds if seconds and seconds > 0 else None

    def _handler(self, signum, frame):
        raise CaseTimeout(f"time limit of {self.seconds:g} s exceeded")

    def __enter__(self):
        if self.seconds is not None and hasattr(signal, "SIGALRM"):
            self._old = signal.signal(signal.SIGALRM, self._handler)
            signal.setitimer(signal.ITIMER_REAL, self.seconds)
        return self

    def __exit__(self, *exc):
        if self.seconds is not None and hasattr(signal, "SIGALRM"):
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self._old)
        return False


class _quiet:
    """Silence (but count) warnings and numpy floating-point messages inside a solver call."""

    def __enter__(self):
        self._w = warnings.catch_warnings(record=True)
        caught = self._w.__enter__()
        warnings.simplefilter("always")
        self._np = np.errstate(all="ignore")
        self._np.__enter__()
        return caught

    def __exit__(self, *exc):
        self._np.__exit__(*exc)
        self._w.__exit__(*exc)
        return False


def _finite_or_none(v):
    if v is None:
        return None
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _to_numpy(a) -> np.ndarray:
    if torch.is_tensor(a):
        return a.detach().cpu().double().numpy()
    return np.asarray(a, dtype=float)


def _exc_str(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}"


def _load_shootlab():
    """Return (module, None) or (None, reason)."""
    try:
        import shootlab
    except Exception as e:  # the solver package may be mid-refactor
        return None, "import shootlab failed: " + _exc_str(e)
    if not hasattr(shootlab, "solve") or not hasattr(shootlab, "BVP"):
        return None, "shootlab.solve / shootlab.BVP not available yet"
    return shootlab, None


def _eval_sol(sol, tq: np.ndarray, n: int) -> np.ndarray:
    """Evaluate ``res.sol`` at ``tq`` -> (k, n) numpy; accepts torch or numpy in/out."""
    try:
        out = sol(torch.as_tensor(tq, dtype=torch.float64))
    except (TypeError, AttributeError):
        out = sol(tq)
    out = _to_numpy(out)
    if out.shape == (n, tq.size) and n != tq.size:
        out = out.T
    return out.reshape(tq.size, n)


# --------------------------------------------------------------------------
# the two solver runs
# --------------------------------------------------------------------------
def run_scipy(p: ts.TestProblem, tq: np.ndarray, args) -> dict:
    rec = {"success": False, "solved": False, "status": None, "message": None, "error": None,
           "error_all": None, "time": None, "nodes": None, "niter": None, "exception": None}
    x0 = np.linspace(p.a, p.b, args.scipy_nodes)
    y0 = p.straight_line_guess(x0).T.copy()
    try:
        times = []
        with _time_limit(args.timeout), _quiet() as caught:
            while True:          # best of up to --repeat runs while they are short (noise)
                t0 = time.perf_counter()
                sol = solve_bvp(p.fun_np, p.bc_np, x0, y0, tol=args.scipy_tol, max_nodes=args.scipy_max_nodes)
                times.append(time.perf_counter() - t0)
                if len(times) >= args.repeat or sum(times) > args.repeat_budget:
                    break
            rec["time"] = min(times)
            rec["runs"] = len(times)
        rec["warnings"] = len(caught)
        rec.update(success=bool(sol.success), status=int(sol.status), message=str(sol.message),
                   nodes=int(sol.x.size), niter=int(sol.niter))
        xq = sol.sol(tq).T
        rec["error"] = ts.relative_max_error(p, tq, xq, component=0)
        rec["error_all"] = ts.relative_max_error(p, tq, xq, component=None)
        rec["solved"] = bool(rec["success"] and rec["error"] is not None and rec["error"] <= args.err_tol)
    except CaseTimeout as e:
        rec["exception"] = "timeout: " + str(e)
        rec["time"] = args.timeout
    except Exception as e:
        rec["exception"] = _exc_str(e)
        rec["traceback"] = traceback.format_exc(limit=6)
    return rec


def solve_options(args) -> dict:
    """The options passed to shootlab.solve (stated in the output): the tolerances matched to
    what solve_bvp is asked for, the rest the defaults."""
    opts = {}
    if args.integrator:
        opts["integrator"] = args.integrator
    if args.rtol is not None:
        opts["rtol"] = args.rtol
    if args.atol is not None:
        opts["atol"] = args.atol
    return opts


def run_shootlab(p: ts.TestProblem, tq: np.ndarray, args, shootlab) -> dict:
    """Best of up to ``--repeat`` runs of the whole ladder (while they are short), as for scipy."""
    best = None
    spent = 0.0
    for k in range(max(1, args.repeat)):
        rec = _run_shootlab_once(p, tq, args, shootlab)
        if rec.get("time_total") is None:
            return rec
        spent += rec["time_total"]
        if best is None or (rec["solved"], -rec["time_total"]) > (best["solved"], -best["time_total"]):
            best = rec
        if spent > args.repeat_budget or not rec["solved"]:
            break
    best["runs"] = k + 1
    return best


def _run_shootlab_once(p: ts.TestProblem, tq: np.ndarray, args, shootlab) -> dict:
    rec = {"available": shootlab is not None, "solved": False, "success": False, "error": None,
           "error_all": None, "time_total": None, "time_last": None, "points": None, "attempts": []}
    if shootlab is None:
        rec["exception"] = args.shootlab_unavailable
        return rec
    total = 0.0
    try:
        bvp = p.bvp()
    except Exception as e:
        rec["exception"] = "building shootlab.BVP failed: " + _exc_str(e)
        return rec
    budget = args.timeout if args.timeout and args.timeout > 0 else None
    ok = False
    for m in args.points:
        att = {"points": int(m), "success": False, "status": None, "message": None, "iterations": None,
               "error": None, "error_all": None, "error_nodes": None, "time": None, "exception": None}
        if budget is not None and total >= budget:
            rec["skipped_points"] = [int(q) for q in args.points if q >= m]
            rec["note"] = f"case budget of {budget:g} s used up; not tried: {rec['skipped_points']}"
            break
        rec["attempts"].append(att)
        t = torch.linspace(p.a, p.b, m, dtype=torch.float64)
        x_guess = torch.as_tensor(p.straight_line_guess(t.numpy()), dtype=torch.float64)
        t0 = time.perf_counter()
        try:
            with _time_limit(None if budget is None else max(budget - total, 1.0)), _quiet() as caught:
                res = shootlab.solve(bvp, t, x_guess, **solve_options(args))
            att["time"] = time.perf_counter() - t0
            integ = getattr(getattr(res, "_system", None), "integrator", None)
            if getattr(integ, "rows", None) is not None:       # the automatic choice: rows per scheme
                att["integrator_rows"] = dict(integ.rows)
            att["jacobian_evaluations"] = _finite_or_none(getattr(res, "jacobian_evaluations", None))
            att["internal_points"] = _finite_or_none(getattr(res, "points", None))   # with refine's
            att["warnings"] = len(caught)
            att.update(success=bool(res.success), status=_finite_or_none(getattr(res, "status", None)),
                       message=str(getattr(res, "message", "")),
                       iterations=_finite_or_none(getattr(res, "iterations", None)))
            try:
                t_nodes = _to_numpy(res.t).reshape(-1)
                att["error_nodes"] = ts.relative_max_error(p, t_nodes, _to_numpy(res.x), component=0)
            except Exception as e:
                att["exception"] = "node error: " + _exc_str(e)
            xq = _eval_sol(res.sol, tq, p.n)
            att["error"] = ts.relative_max_error(p, tq, xq, component=0)
            att["error_all"] = ts.relative_max_error(p, tq, xq, component=None)
        except CaseTimeout as e:
            att["time"] = time.perf_counter() - t0
            att["exception"] = "timeout: " + str(e)
        except Exception as e:
            att["time"] = time.perf_counter() - t0
            att["exception"] = _exc_str(e)
            att["traceback"] = traceback.format_exc(limit=6)
        total += att["time"] or 0.0
        ok = att["success"] and att["error"] is not None and att["error"] <= args.err_tol
        if ok:
            break
    last = rec["attempts"][-1]
    rec.update(solved=bool(ok), success=last["success"], error=last["error"], error_all=last["error_all"],
               time_total=total, time_last=last["time"], points=last["points"],
               iterations=last["iterations"], jacobian_evaluations=last.get("jacobian_evaluations"),
               integrator_rows=last.get("integrator_rows"), internal_points=last.get("internal_points"))
    if last.get("exception"):
        rec["exception"] = last["exception"]
    return rec


# --------------------------------------------------------------------------
# table / summary
# --------------------------------------------------------------------------
def _fmt_e(v):
    return "-" if v is None else f"{v:.1e}"


def _fmt_t(v):
    return "-" if v is None else (f"{v:.3f}" if v < 10 else f"{v:.1f}")


def _ok_str(rec, key="solved"):
    exc = rec.get("exception")
    if exc and exc.startswith("timeout"):
        return "T/O"
    if rec.get("available") is False:
        return "n/a"
    if exc and not rec.get("success"):
        return "EXC"
    if rec.get(key):
        return "yes"
    return "no" if not rec.get("success") else "inacc"


HEADER = (f"{'problem':22s} {'param':>9s} | {'sp':>5s} {'err':>8s} {'time':>7s} {'nodes':>6s} | "
          f"{'sl':>5s} {'err':>8s} {'time':>7s} {'pts(used)':>10s} {'it/J':>6s} {'stiff':>5s} | {'ratio':>6s}")


def _scheme(sl) -> str:
    rows = sl.get("integrator_rows")
    if not rows:
        return "-"
    tot = sum(rows.values())
    return f"{rows.get('ros4', 0) / tot:.0%}" if tot else "-"


def _pts(sl) -> str:
    """The shooting points given (the ladder's last attempt) and, in parentheses, those used
    (``refine`` adds points where the local Jacobian asks for them)."""
    m, used = sl.get("points"), sl.get("internal_points")
    if m is None:
        return "-"
    return str(m) if used is None or int(used) == int(m) else f"{m}({int(used)})"


def _itj(sl) -> str:
    it, j = sl.get("iterations"), sl.get("jacobian_evaluations")
    return "-" if it is None else f"{int(it)}/{int(j) if j is not None else '?'}"


def _row(c) -> str:
    sp, sl = c["scipy"], c["shootlab"]
    ratio = c.get("time_ratio")
    return (f"{c['problem']:22s} {c['param']:>9s} | {_ok_str(sp):>5s} {_fmt_e(sp['error']):>8s} "
            f"{_fmt_t(sp['time']):>7s} {str(sp['nodes'] or '-'):>6s} | {_ok_str(sl):>5s} "
            f"{_fmt_e(sl['error']):>8s} {_fmt_t(sl['time_total']):>7s} {_pts(sl):>10s} "
            f"{_itj(sl):>6s} {_scheme(sl):>5s} | "
            f"{('-' if ratio is None else f'{ratio:.2f}'):>6s}")


def _brief(labels, k=12) -> str:
    if not labels:
        return ""
    more = f", ... +{len(labels) - k} more" if len(labels) > k else ""
    return " [" + ", ".join(labels[:k]) + more + "]"


def summarize(cases: list[dict]) -> dict:
    lab = lambda c: c["label"]
    sp = [lab(c) for c in cases if c["scipy"].get("solved")]
    sl = [lab(c) for c in cases if c["shootlab"].get("solved")]
    both = [c["time_ratio"] for c in cases if c["scipy"].get("solved") and c["shootlab"].get("solved")
            and c.get("time_ratio")]
    timed = [c["time_ratio"] for c in cases if c.get("time_ratio")]
    gm = lambda r: math.exp(sum(math.log(x) for x in r) / len(r)) if r else None
    return {
        "geomean_ratio_both_solved": gm(both), "n_both_solved": len(both),
        "geomean_ratio_all_timed": gm(timed), "n_timed": len(timed),
        "max_ratio_both_solved": max(both) if both else None,
        "min_ratio_both_solved": min(both) if both else None,
        "cases": len(cases),
        "scipy_solved": len(sp),
        "shootlab_solved": len(sl),
        "shootlab_available": any(c["shootlab"].get("available") for c in cases),
        "scipy_only": [x for x in sp if x not in sl],
        "shootlab_only": [x for x in sl if x not in sp],
    }


# --------------------------------------------------------------------------
def select_problems(args) -> list[ts.TestProblem]:
    eps = tuple(args.eps) if args.eps else (QUICK_EPS if args.quick else ts.DEFAULT_EPS)
    names = QUICK_CASH if args.quick else ts.CASH_PROBLEM_NAMES
    probs = ts.cash_problems(eps, names=names) + ts.classic_problems(eps)
    if args.problems:
        wanted = set(args.problems)
        probs = [p for p in probs if p.name in wanted]
    return probs


def warmup(args, shootlab) -> None:
    """One untimed solve per solver (the first torch.func transform imports torch._dynamo, ~1.5 s)."""
    p = ts.cash_problems((0.1,), names=("bvpT1",))[0]
    with _quiet():
        x0 = np.linspace(p.a, p.b, 11)
        solve_bvp(p.fun_np, p.bc_np, x0, p.straight_line_guess(x0).T.copy(), tol=args.scipy_tol)
        if shootlab is not None:
            t = torch.linspace(p.a, p.b, 11, dtype=torch.float64)
            try:
                shootlab.solve(p.bvp(), t, torch.as_tensor(p.straight_line_guess(t.numpy())), **solve_options(args))
            except Exception:
                pass


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help=f"subset: {', '.join(QUICK_CASH)} + classics, eps in {QUICK_EPS}")
    ap.add_argument("--eps", type=float, nargs="+", help="eps values (default 1e-1 1e-2 1e-3 1e-4)")
    ap.add_argument("--problems", nargs="+", metavar="NAME",
                    help="restrict to these problem names (e.g. bvpT1 troesch bratu)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"JSON output (default {DEFAULT_OUT})")
    ap.add_argument("--points", type=int, nargs="+", default=[101, 401, 1601],
                    help="shootlab shooting-point escalation (default 101 401 1601)")
    ap.add_argument("--err-tol", type=float, default=1e-5, help="relative max error for 'solved'")
    ap.add_argument("--scipy-tol", type=float, default=1e-8)
    ap.add_argument("--scipy-max-nodes", type=int, default=200_000)
    ap.add_argument("--scipy-nodes", type=int, default=101, help="initial uniform scipy mesh")
    ap.add_argument("--timeout", type=float, default=600.0,
                    help="time limit per case and solver in s; for shootlab it is shared by all "
                         "escalation attempts (0 = none; default 600)")
    ap.add_argument("--skip-scipy", action="store_true")
    ap.add_argument("--skip-shootlab", action="store_true")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads")
    ap.add_argument("--integrator", default=None, help="shootlab integrator (default: shootlab's default)")
    ap.add_argument("--rtol", type=float, default=None,
                    help="shootlab integrator rtol (default: --scipy-tol, the tolerance solve_bvp is asked for)")
    ap.add_argument("--atol", type=float, default=None, help="shootlab integrator atol (default: rtol / 100)")
    ap.add_argument("--repeat", type=int, default=3,
                    help="time each solver as the best of up to this many runs (default 3) ...")
    ap.add_argument("--repeat-budget", type=float, default=1.0,
                    help="... while the runs so far took less than this many seconds (default 1)")
    ap.add_argument("--no-warmup", action="store_true",
                    help="do not run each solver once on a small problem before the table")
    args = ap.parse_args(argv)

    if args.threads:
        torch.set_num_threads(args.threads)
    if args.skip_shootlab:
        shootlab, reason = None, "skipped (--skip-shootlab)"
    else:
        shootlab, reason = _load_shootlab()
    args.shootlab_unavailable = reason
    if reason:
        print(f"[shootlab] {reason}", file=sys.stderr)

    if args.rtol is None:
        args.rtol = args.scipy_tol
    if args.atol is None:
        args.atol = args.rtol / 100.0
    probs = select_problems(args)
    print(f"solve_bvp(tol={args.scipy_tol:g}, max_nodes={args.scipy_max_nodes}) on {args.scipy_nodes} nodes; "
          f"shootlab.solve(BVP, t, x_guess, **{solve_options(args)}) on {args.points} shooting points; "
          f"times: best of up to {args.repeat} runs while under {args.repeat_budget:g} s"
          + ("" if args.no_warmup else "; each solver run once on a small problem first (import-time costs excluded)"))
    if not args.no_warmup:
        warmup(args, shootlab)
    print(HEADER)
    print("-" * len(HEADER))
    cases = []
    for p in probs:
        tq = ts.fine_grid(p)
        case = {"problem": p.name, "eps": p.eps, "params": p.params, "param": p.param_str,
                "label": p.label, "exact_kind": p.exact_kind, "a": p.a, "b": p.b}
        if args.skip_scipy:
            case["scipy"] = {"solved": False, "success": False, "error": None, "time": None, "nodes": None,
                             "exception": "skipped (--skip-scipy)"}
        else:
            case["scipy"] = run_scipy(p, tq, args)
        case["shootlab"] = run_shootlab(p, tq, args, shootlab)
        ts_, tl_ = case["scipy"].get("time"), case["shootlab"].get("time_total")
        case["time_ratio"] = (tl_ / ts_) if (ts_ and tl_ is not None and case["shootlab"]["attempts"]) else None
        cases.append(case)
        print(_row(case), flush=True)

    summ = summarize(cases)
    print("-" * len(HEADER))
    line = (f"SUMMARY: {summ['cases']} cases; solved (success & rel. err <= {args.err_tol:g}): "
            f"scipy {summ['scipy_solved']}, shootlab {summ['shootlab_solved']}")
    if summ["shootlab_available"]:
        line += (f"; scipy solves but shootlab does not: {len(summ['scipy_only'])}{_brief(summ['scipy_only'])}"
                 f"; shootlab-only: {len(summ['shootlab_only'])}{_brief(summ['shootlab_only'])}")
    else:
        line += f" (shootlab not run: {reason})"
    print(line)
    if summ["geomean_ratio_both_solved"] is not None:
        print(f"GEOMETRIC MEAN time ratio shootlab / solve_bvp: {summ['geomean_ratio_both_solved']:.2f} over the "
              f"{summ['n_both_solved']} cases both solve (range {summ['min_ratio_both_solved']:.2f} - "
              f"{summ['max_ratio_both_solved']:.2f}); {summ['geomean_ratio_all_timed']:.2f} over all "
              f"{summ['n_timed']} timed cases")

    out = {
        "meta": {
            "date": _dt.datetime.now().isoformat(timespec="seconds"),
            "python": platform.python_version(), "platform": platform.platform(),
            "numpy": np.__version__, "scipy": scipy.__version__, "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(),
            "shootlab_available": shootlab is not None, "shootlab_note": reason,
            "shootlab_file": getattr(shootlab, "__file__", None),
            "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
            "error_definition": "max|y_num - y_exact| / max|y_exact| on studies.bvp_testset.fine_grid "
                                "(component y; error_all = worst component, each normalised)",
            "time_ratio": "shootlab total time over all attempts / scipy time (each the best of up to "
                          "--repeat runs while under --repeat-budget s)",
            "shootlab_options": solve_options(args),
        },
        "summary": summ,
        "cases": cases,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(json_ready(out), fh, indent=1, allow_nan=False, default=str)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
