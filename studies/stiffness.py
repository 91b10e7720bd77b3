"""Stiffness along a solution or an initial approximation: eigenvalues of the local Jacobian ∂f/∂x
of the TPBVP at the shooting points (the report's fig. 5.4 and eq. 5.6).

    python -m studies stiffness --problem confined --option elements=3 [--points 101] [--solve] [--out DIR]

For every point t_k: the eigenvalues λ of ∂f/∂x (scatter in the complex plane), κ(t) = min Re λ
and κ₊(t) = max Re λ, the largest |λ|, and the *Hamiltonian pairing* check — the optimal-
estimation TPBVP is Hamiltonian, so its eigenvalues come in pairs ±λ; the pairing error is
max_i min_j |λ_i + λ_j| / max|λ| at each point.  Per interval the report's stiffness measure
κ·h (the smaller κ of its two ends times its length h); |κ h| beyond the explicit schemes'
real stability limits (2 for Euler, 2.785 for RK4 per step) is marked in the figure.
Writes ``stiffness.csv`` (per point), ``stiffness.json`` (settings, version, summary,
predictions of :func:`shootlab.suggest_shooting_points`) and ``stiffness.png``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

import shootlab
from shootlab.bvp.suggest import local_eigenvalues, real_stability_limit, suggest_shooting_points

from . import problems
from .sweep import integrator_label, metadata, parse_integrator

#: real stability limits −hλ of one step, from the schemes' own stability functions
LIMITS = {name: round(real_stability_limit(name), 3) for name in ("euler", "rk4")}


def pairing_error(ev: np.ndarray) -> np.ndarray:
    """max_i min_j |λ_i + λ_j| / max|λ| per row of ev (k, n): 0 for exact ±λ pairs."""
    d = np.abs(ev[:, :, None] + ev[:, None, :]).min(-1).max(-1)
    return d / np.maximum(np.abs(ev).max(-1), 1e-300)


def analyse(problem: str, options: dict | None = None, points: int = 101, solve: bool = False,
            solve_options: dict | None = None, integrators: Sequence[str] = ("euler:1", "rk4:1", "rk4:4"),
            m_for_h: int | None = None) -> dict:
    """Eigenvalue analysis at ``points`` shooting points along the guess (or, with ``solve``,
    along the solution of ``shootlab.solve`` with ``solve_options``; the problem's reference
    settings by default).  ``m_for_h``: the grid whose κ·h is reported (default ``points``)."""
    prob = problems.build(problem, options or {})
    t = prob.grid(points)
    x = prob.guess(t)
    source, message = "initial approximation", ""
    if solve:
        opts = dict(prob.reference_solve) if solve_options is None else dict(solve_options)
        m_solve = int(opts.pop("points", points))
        ts = prob.grid(m_solve)
        res = shootlab.solve(prob.bvp, ts, prob.guess(ts), **opts)
        message = res.message
        if res.success:
            x = res.sol(t) if m_solve != points else res.x
            source = f"solution ({m_solve} points, {opts or 'default settings'})"
        else:
            source = f"initial approximation (the solve failed: {res.message})"
    ev = local_eigenvalues(prob.bvp.rhs, t, x).numpy()
    kappa, kappa_plus, rho = ev.real.min(-1), ev.real.max(-1), np.abs(ev).max(-1)
    pe = pairing_error(ev)
    mh = int(m_for_h or points)
    th = prob.grid(mh).numpy()
    k_h = np.interp(th, t.numpy(), kappa)
    kappa_h = np.minimum(k_h[:-1], k_h[1:]) * np.diff(th)
    preds = {}
    for spec in integrators:
        name, steps = parse_integrator(spec)
        preds[integrator_label(name, steps)] = suggest_shooting_points(
            prob.bvp, (t, x), name, steps=steps, interval=prob.interval).as_dict()
    return dict(kind="stiffness", **metadata(dict(problem=problem, options=options or {}, points=points,
                                                  solve=solve, solve_options=solve_options, m_for_h=mh,
                                                  integrators=list(integrators))),
                problem=prob.name, description=prob.description, n=int(x.shape[1]), source=source,
                time_unit=prob.time_unit,
                solve_message=message, t=t.tolist(), eig_real=ev.real.tolist(), eig_imag=ev.imag.tolist(),
                kappa=kappa.tolist(), kappa_plus=kappa_plus.tolist(), rho=rho.tolist(), pairing_error=pe.tolist(),
                t_h=th.tolist(), kappa_h=kappa_h.tolist(),
                summary=dict(kappa_min=float(kappa.min()), kappa_plus_max=float(kappa_plus.max()),
                             rho_max=float(rho.max()), pairing_error_max=float(pe.max()),
                             hamiltonian_pairs=bool(pe.max() < 1e-6), kappa_h_min=float(kappa_h.min()),
                             m_for_h=mh),
                predictions=preds)


def report(res: dict) -> str:
    s = res["summary"]
    lines = [f"{res['problem']} (n = {res['n']}): local Jacobian along the {res['source']}, {len(res['t'])} points",
             f"  kappa = min Re lambda: {s['kappa_min']:.6g}   max Re lambda: {s['kappa_plus_max']:.6g}   "
             f"max |lambda|: {s['rho_max']:.6g}",
             f"  Hamiltonian pairing (+-lambda): max relative error {s['pairing_error_max']:.2e} "
             f"({'paired' if s['hamiltonian_pairs'] else 'NOT paired'})",
             f"  kappa*h on {s['m_for_h']} points: min {s['kappa_h_min']:.4g}"]
    for integ, p in res["predictions"].items():
        lines.append(f"  suggest {integ:10s} m = {p['m']:7d} (limited by {p['limited_by']}, kappa*h = {p['kappa_h']:.3g})")
    return "\n".join(lines)


def write(res: dict, out: str | Path) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "stiffness.json").write_text(json.dumps(res, indent=2))
    t = np.asarray(res["t"])
    cols = np.column_stack([t, res["kappa"], res["kappa_plus"], res["rho"], res["pairing_error"]])
    np.savetxt(out / "stiffness.csv", cols, delimiter=",", header="t,kappa,kappa_plus,max_abs_lambda,pairing_error",
               comments="", fmt="%.10g")
    np.savetxt(out / "stiffness_intervals.csv",
               np.column_stack([res["t_h"][:-1], res["t_h"][1:], res["kappa_h"]]), delimiter=",",
               header="t_start,t_end,kappa_h", comments="", fmt="%.10g")
    plot(res, out / "stiffness.png")
    return out


def replot(path: str | Path) -> str:
    path = Path(path)
    file = path / "stiffness.json" if path.is_dir() else path
    return plot(json.loads(file.read_text()), file.with_suffix(".png"))


def plot(res: dict, path: str | Path) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(res["t"])
    er, ei = np.asarray(res["eig_real"]), np.asarray(res["eig_imag"])
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    ax = axes[0]
    sc = ax.scatter(er.ravel(), ei.ravel(), c=np.repeat(t, er.shape[1]), s=10, cmap="viridis")
    fig.colorbar(sc, ax=ax, label="time t of the shooting point")
    unit = res.get("time_unit") or ""
    rate = f"1/{unit}" if unit else "dimensionless"
    lin = max(1.0, float(np.abs(er).max()) * 1e-3)
    ax.set_xscale("asinh", linear_width=lin)
    ax.set_xlabel(f"Re λ [{rate}] (asinh scale, linear within ±{lin:.3g})")
    ax.set_ylabel(f"Im λ [{rate}]")
    ax.axvline(0.0, color="0.6", lw=0.6)
    ax.set_title("eigenvalues of the local Jacobian ∂f/∂x (cf. report fig. 5.4)", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax = axes[1]
    ax.plot(t, -np.asarray(res["kappa"]), "-", lw=2, label="−κ(t) = −min Re λ")
    ax.plot(t, res["kappa_plus"], "--", lw=1.5, label="κ₊(t) = max Re λ (Hamiltonian partner)")
    ax.plot(t, res["rho"], ":", lw=1.5, label="max |λ|")
    vals = np.concatenate([-np.asarray(res["kappa"]), np.asarray(res["rho"])])
    if vals.min() > 0 and vals.max() / vals.min() > 10:
        ax.set_yscale("log")
    else:
        ax.ticklabel_format(axis="y", useOffset=False)
    tlabel = f"t [{unit}]" if unit else "t (dimensionless)"
    ax.set_xlabel(tlabel)
    ax.set_ylabel(f"rate [{rate}]")
    pe = res["summary"]["pairing_error_max"]
    ax.set_title(f"stiffness along the {res['source'].split(' (')[0]}; ±λ pairing error {pe:.1e}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax = axes[2]
    th = np.asarray(res["t_h"])
    mid = 0.5 * (th[1:] + th[:-1])
    ax.plot(mid, -np.asarray(res["kappa_h"]), "-", color="k", label=f"−κ·h per interval (m = {res['summary']['m_for_h']})")
    for name, lim in LIMITS.items():
        ax.axhline(lim, ls="--", lw=1, color="C3" if name == "euler" else "C2",
                   label=f"{name}: one step per interval stable below {lim}")
    ax.set_yscale("log")
    ax.set_xlabel(tlabel)
    ax.set_ylabel("−κ·h (dimensionless)")
    ax.set_title("stiffness measure per shooting interval (report eq. 5.6)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.suptitle(f"{res['problem']}: {res['description']} (n = {res['n']}; shootlab {res['version']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(Path(path).name)
