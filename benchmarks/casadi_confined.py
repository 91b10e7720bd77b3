"""The peer's whole command: H, K of the N-element confined-compression model from a CSV record by
CasADi + IPOPT direct multiple shooting, as a user would write it — numpy and CasADi only (no
torch, no shootlab), so that its wall time as a fresh process is the peer's own.

    python benchmarks/casadi_confined.py RECORD.csv N [--lifted]    # prints one line of JSON

The model is the linear N-element model s' = H K A₁ s + K b₁ u (free-draining filter on top,
impermeable bottom; :func:`linear_system`, the report's mixed elements of docs/design.md §3, as
``mixtures.prefit.filter_system`` with ρ = 0), measured: the filter displacement d = −s_N and the
bottom pressure p₁ = H (P₁ s)₁ + q₁ u.  Implicit Euler with 2 steps per interval of 201 shooting
points (the steps land on the 401 samples); decision variables s at the shooting points and H, K
≥ 1e-6; continuity constraints; output error Σ (d − d_m)²/σ_d² + (p₁ − p_m)²/σ_p² over all
samples (σ: the channel's spread); IPOPT with the exact Hessian, tol 1e-8; states started from the
report's linear profile of the measured displacement, H = K = 4.  ``--lifted``: every implicit
Euler step's state is a decision variable too (sparse bilinear constraints, no solves).
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

POINTS, STEPS = 201, 2
LINSOL = "lapacklu"       # CasADi's dense LU for the implicit steps (its default symbolic QR: 2-3x slower)


def read_record(path: str) -> dict[str, np.ndarray]:
    """The CSV's columns by header name (a plain comma-separated table with one header row)."""
    with open(path) as fh:
        names = fh.readline().strip().split(",")
    table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {n: table[:, j] for j, n in enumerate(names)}


def linear_system(elements: int, length: float = 1.0):
    """(A₁, b₁, P₁, q₁) of s' = H K A₁ s + K b₁ u and the pressures p = H P₁ s + q₁ u on nodes
    1 … N+1: linear elements, element matrices ∫N_a N_b' = ½[[−1, 1], [−1, 1]] (R) and
    ∫N_a' N_b' = (1/h)[[1, −1], [−1, 1]] (K L, H L); mass balance R s' + K L p = 0 with
    p_{N+1} = 0 (filter), momentum Rᵀ p = H L s + e_N u, the bottom displacement s₁ = 0."""
    N, h = int(elements), float(length) / int(elements)
    R, L = np.zeros((N + 1, N + 1)), np.zeros((N + 1, N + 1))
    for e in range(N):
        i = np.array([e, e + 1])
        R[np.ix_(i, i)] += 0.5 * np.array([[-1.0, 1.0], [-1.0, 1.0]])
        L[np.ix_(i, i)] += np.array([[1.0, -1.0], [-1.0, 1.0]]) / h
    R, S = R[:, 1:], L[1:, 1:]
    n = 2 * N + 1                                    # unknowns [s' (N), p (N+1)]
    M = np.zeros((n, n))
    M[:N + 1, :N], M[:N + 1, N:] = R, L
    M[N, :] = 0.0
    M[N, 2 * N] = 1.0                                # the mass row of node N+1 replaced by p_{N+1} = 0
    M[N + 1:, N:] = R.T
    rhs_s, rhs_u = np.zeros((n, N)), np.zeros(n)
    rhs_s[N + 1:, :] = S
    rhs_u[2 * N] = 1.0
    sol_s, sol_u = np.linalg.solve(M, rhs_s), np.linalg.solve(M, rhs_u)
    return sol_s[:N], sol_u[:N], sol_s[N:], sol_u[N:]


def estimate(csv: str, elements: int, start: float = 4.0, lifted: bool = False) -> dict:
    """Direct multiple shooting of the N-element model with IPOPT (module docstring); the record
    is read here, so that a caller times the whole job."""
    import casadi as ca

    t_all = time.perf_counter()
    d = read_record(csv)
    t, u, dm, pm = d["t"], d["load"], d["displacement"], d["pressure"]
    N = int(elements)
    A1, b1, P1, q1 = linear_system(N)
    nodes = np.linspace(t[0], t[-1], POINTS)
    h = (nodes[1] - nodes[0]) / STEPS
    fine = nodes[0] + h * np.arange(1, (POINTS - 1) * STEPS + 1)
    sd, sp = max(float(np.std(dm)), 1e-12), max(float(np.std(pm)), 1e-12)
    TH = ca.MX.sym("TH", 2)
    H, K = TH[0], TH[1]
    M = ca.DM.eye(N) - h * H * K * ca.DM(A1)                 # implicit Euler: M s_{j+1} = s_j + h K b1 u_{j+1}
    z = (np.arange(1, N + 1) / N)[:, None]                  # the report's linear profile s_j = −d_m z_j / L
    if lifted:
        S = ca.MX.sym("S", N, fine.size + 1)                 # every step end (every sample)
        Uf = ca.DM(np.interp(fine, t, u)).T
        g = ca.vec(ca.mtimes(M, S[:, 1:]) - S[:, :-1] - h * K * ca.mtimes(ca.DM(b1), Uf))
        Y_d = -S[N - 1, 1:]
        Y_p = H * ca.mtimes(ca.DM(P1[0:1, :]), S[:, 1:]) + q1[0] * Uf
        grid = np.concatenate([[nodes[0]], fine])
    else:
        s, uu = ca.MX.sym("s", N), ca.MX.sym("u", STEPS)
        outs, x = [], s
        for j in range(STEPS):
            x = ca.solve(M, x + h * K * ca.DM(b1) * uu[j], LINSOL)
            outs += [-x[N - 1], H * ca.mtimes(ca.DM(P1[0:1, :]), x) + q1[0] * uu[j]]
        interval = ca.Function("interval", [s, TH, uu], [x, ca.vertcat(*outs)]).map(POINTS - 1)
        S = ca.MX.sym("S", N, POINTS)
        U = np.interp(fine, t, u).reshape(POINTS - 1, STEPS).T
        ends, Y = interval(S[:, :-1], ca.repmat(TH, 1, POINTS - 1), ca.DM(U))
        g = ca.vec(ends - S[:, 1:])
        Y_d, Y_p = ca.vec(Y[0::2, :]).T, ca.vec(Y[1::2, :]).T     # column-major: sample order
        grid = nodes
    cost = ca.sumsqr((Y_d - ca.DM(np.interp(fine, t, dm)).T) / sd) \
        + ca.sumsqr((Y_p - ca.DM(np.interp(fine, t, pm)).T) / sp) + ((-S[N - 1, 0] - float(dm[0])) / sd) ** 2
    nlp = dict(x=ca.vertcat(ca.vec(S), TH), f=cost, g=g)
    solver = ca.nlpsol("dms", "ipopt", nlp, {"ipopt.tol": 1e-8, "ipopt.print_level": 0, "print_time": False,
                                              "ipopt.max_iter": 500, "ipopt.sb": "yes"})
    s0 = -z * np.interp(grid, t, dm)[None, :]
    x0 = np.concatenate([s0.T.reshape(-1), [start, start]])
    lbx = np.concatenate([np.full(s0.size, -np.inf), [1e-6, 1e-6]])
    t0 = time.perf_counter()
    sol = solver(x0=x0, lbg=0, ubg=0, lbx=lbx)
    solve = time.perf_counter() - t0
    stats = solver.stats()
    p = np.asarray(sol["x"][-2:]).ravel()
    return dict(solver="casadi lifted" if lifted else "casadi+ipopt",
                success=stats["return_status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level"),
                message=f"{stats['return_status']}, objective {float(sol['f']):.4g}",
                iterations=int(stats["iter_count"]), solve_s=solve, in_process_s=time.perf_counter() - t_all,
                parameters=dict(H=float(p[0]), K=float(p[1])))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", help="record: t,load,displacement,pressure")
    ap.add_argument("elements", type=int, help="N, the model's number of elements")
    ap.add_argument("--lifted", action="store_true", help="every implicit Euler step's state a decision variable")
    args = ap.parse_args()
    print(json.dumps(estimate(args.csv, args.elements, lifted=args.lifted)))
