"""Where the residual is (docs/design.md §4, step 1; ``docs/diagnosis.md``, "Where").

The nominal estimate leaves residuals ξ on every row (model equations and measurement rows) and ε
on the dynamics (report eqs. 2.4–2.6).  Per row: the weighted energy ½∫ξᵀVξ dt and its share of J,
compared with the noise floor (:mod:`shootlab.diagnosis.floor`).  A row is significant when the
mean-square ratio data/floor is large by an F test and in size (``ratio_min``, ``share_min``).
The floor's mean square is the mean over its surrogate records (:class:`shootlab.diagnosis.floor.NoiseFloor`);
the degrees of freedom are the smaller of the effective sample size from the floor's
autocorrelation (:func:`effective_samples`) and what the mean square's spread over the surrogate
records shows (:func:`replicate_dof`) — the autocorrelation alone counted 150–401 where the spread
showed 7–60 for a 6-element confined model (``floor`` module docstring) — on the data's side, and
as many times that as there are records on the floor's.  Windows: where the standardised local energy exceeds the floor's own extremes.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from shootlab.estimation.fit import EstimationResult

if TYPE_CHECKING:
    from .floor import NoiseFloor

__all__ = ["locate", "residual_components", "row_energy", "effective_samples", "hot_windows",
           "lag1_autocorrelation", "replicate_dof", "row_mean_square"]


def residual_components(res: EstimationResult) -> list[dict]:
    """Every residual component with its weighted energy density (J units): ξ rows and ε entries."""
    prob, model = res.problem, res.problem.model
    t = res.t
    xi = torch.stack([res.xi[r] for r in model.equations], -1)
    eps = torch.stack([res.eps[n] for n in model.names], -1)
    with torch.no_grad():
        _, mask = prob.measurements(t)
        W, V = prob.weights(t, xi)          # of t alone: no states needed (re-integrating them cost 0.19 s)
        V = V * mask.unsqueeze(-1) * mask.unsqueeze(-2)
    dens_xi = xi * (V @ xi.unsqueeze(-1)).squeeze(-1)
    dens_eps = eps * (W @ eps.unsqueeze(-1)).squeeze(-1)
    out = []
    for i, r in enumerate(model.equations):
        kind = "measurement" if r in model.channels else "equation"
        out.append(dict(name=r, kind=kind, channel=model.channels.get(r), values=xi[:, i].numpy(),
                        density=dens_xi[:, i].numpy(), mask=mask[:, i].numpy() > 0))
    for j, n in enumerate(model.names):
        out.append(dict(name=f"ε:{n}", kind="dynamics", channel=None, values=eps[:, j].numpy(),
                        density=dens_eps[:, j].numpy(), mask=np.ones(t.numel(), dtype=bool)))
    return out


def effective_samples(z: np.ndarray) -> float:
    """n / (1 + 2 Σ ρ_k): the autocorrelation sum truncated at the first non-positive pair (Geyer)."""
    z = np.asarray(z, dtype=float)
    z = z - z.mean()
    n = z.size
    if n < 4 or not np.any(z):
        return float(max(n, 1))
    f = np.fft.rfft(z, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:n]
    ac = ac / ac[0]
    s = 0.0
    for k in range(1, n - 1, 2):
        pair = ac[k] + ac[k + 1]
        if pair <= 0:
            break
        s += pair
    return float(min(n, max(1.0, n / (1.0 + 2.0 * s))))


def hot_windows(t: np.ndarray, z2: np.ndarray, floor_z2: np.ndarray | None, width: int,
                max_windows: int = 12) -> tuple[list[dict], float]:
    """Time windows where the local mean of z² (standardised residual squared) exceeds the floor's
    own extremes (its 99.9 % local level, at least 2)."""
    n = t.size
    width = max(3, min(width, n))
    kern = np.ones(width) / width
    local = np.convolve(z2, kern, mode="same")
    thr = 2.0
    if floor_z2 is not None and floor_z2.size == n:
        thr = max(thr, float(np.quantile(np.convolve(floor_z2, kern, mode="same"), 0.999)))
    hot = local > thr
    if not hot.any():
        return [], thr
    # merge gaps shorter than a window
    idx = np.flatnonzero(hot)
    spans, s0, prev = [], idx[0], idx[0]
    for i in idx[1:]:
        if i - prev > width:
            spans.append((s0, prev))
            s0 = i
        prev = i
    spans.append((s0, prev))
    excess = np.clip(z2 - 1.0, 0.0, None)
    total = float(excess.sum()) or 1.0
    wins = []
    for a, b in spans:
        share = float(excess[a:b + 1].sum()) / total
        if share >= 0.02 or len(spans) == 1:
            wins.append(dict(t0=float(t[a]), t1=float(t[b]), share=share))
    wins.sort(key=lambda w: -w["share"])
    wins = sorted(wins[:max_windows], key=lambda w: w["t0"])
    return wins, thr


def locate(nominal: EstimationResult, floor: NoiseFloor | None, alpha: float = 0.01, ratio_min: float = 1.5,
           share_min: float = 0.005, window: float = 0.02) -> list[dict]:
    """Where (module docstring): one entry per residual component (ξ rows, then ε entries), with its
    share of J, its rms against the floor's, the F test and the flagged windows."""
    from scipy import stats

    t = nominal.t.numpy()
    comps = residual_components(nominal)
    reps = [{c["name"]: c for c in residual_components(r)} for r in (floor.draws if floor is not None else [])]
    fl = reps[0] if reps else {}
    total = sum(0.5 * float(np.trapezoid(c["density"], t)) for c in comps)
    d0 = nominal.shooting.sol(nominal.t[:1])[0, :nominal.problem.model.nx] - nominal.problem.q_a
    total += 0.5 * float(d0 @ nominal.problem.W_a @ d0)
    total = total if total > 0 else 1.0
    R = len(comps)
    width = max(5, int(round(window * t.size)))
    out = []
    for c in comps:
        m = c["mask"]
        E = 0.5 * float(np.trapezoid(c["density"], t))
        ms = float(np.mean(c["values"][m] ** 2)) if m.any() else 0.0
        entry = dict(equation=c["name"], kind=c["kind"], share=E / total, energy=E, rms=math.sqrt(ms),
                     significant=False, windows=[])
        if c["channel"]:
            entry["channel"] = c["channel"]
        f = fl.get(c["name"])
        if f is not None and m.any():
            fv = row_values(f, m)
            ms_draws = [row_mean_square(r[c["name"]], m) for r in reps if c["name"] in r]
            ms_f = float(np.mean(ms_draws)) if ms_draws else 0.0
            scale = max(ms_f, 1e-300)
            n_eff = effective_samples(fv / math.sqrt(max(float(np.mean(fv ** 2)), 1e-300))) if fv.size else 1.0
            n_rep = replicate_dof(ms_draws)
            n_eff = min(n_eff, n_rep)
            ratio = ms / scale if ms_f > 0 else (math.inf if ms > 0 else 1.0)
            p = float(stats.f.sf(ratio, n_eff, n_eff * len(ms_draws))) if math.isfinite(ratio) else 0.0
            e_f = [0.5 * float(np.trapezoid(r[c["name"]]["density"], t)) for r in reps
                   if c["name"] in r and r[c["name"]]["density"].size == t.size]
            excess = max(E - float(np.mean(e_f)) if e_f else 0.0, 0.0)
            entry["excess_share"] = excess / total
            sig = bool(p < alpha / R and ratio >= ratio_min and entry["excess_share"] >= share_min)
            z = c["values"] / math.sqrt(scale)
            zf = f["values"] / math.sqrt(scale) if f["values"].size == t.size else None
            entry.update(floor_rms=math.sqrt(ms_f), ratio=ratio, p_value=p, n_eff=n_eff, n_replicate=n_rep,
                         significant=sig,
                         autocorrelation=dict(data=lag1_autocorrelation(c["values"][m]), floor=lag1_autocorrelation(fv)))
            if sig:
                z2 = np.where(m, z * z, 0.0)
                wins, thr = hot_windows(t, z2, None if zf is None else zf * zf, width)
                entry["windows"] = [[w["t0"], w["t1"]] for w in wins]
                entry["window_shares"] = [w["share"] for w in wins]
                entry["window_threshold"] = thr
        out.append(entry)
    return out


def row_values(comp: dict, mask: np.ndarray) -> np.ndarray:
    """A residual component's values at the samples both it and ``mask`` have."""
    m = comp["mask"] & mask if comp["mask"].size == mask.size else comp["mask"]
    return comp["values"][m] if comp["values"].size == m.size else comp["values"]


def row_mean_square(comp: dict, mask: np.ndarray) -> float:
    """The mean square of a residual component over the samples both it and ``mask`` have."""
    v = row_values(comp, mask)
    return float(np.mean(v ** 2)) if v.size else 0.0


def replicate_dof(ms: Sequence[float]) -> float:
    """Degrees of freedom of a mean square measured from its spread over independent noise draws:
    a χ²_ν/ν variable has variance 2/ν, so ν = 2 mean² / var (unbiased variance; ∞ with fewer than
    three draws or no spread, when the autocorrelation's effective samples decide alone)."""
    ms = np.asarray(ms, dtype=float)
    if ms.size < 3:
        return math.inf
    var = float(np.var(ms, ddof=1))
    mean = float(np.mean(ms))
    return 2.0 * mean * mean / var if var > 0 else math.inf


def lag1_autocorrelation(v: np.ndarray) -> float:
    v = np.asarray(v, dtype=float)
    if v.size < 3:
        return 0.0
    v = v - v.mean()
    d = float(v @ v)
    return float(v[1:] @ v[:-1]) / d if d > 0 else 0.0


def row_energy(res: EstimationResult) -> dict[str, float]:
    """½∫ξᵀVξ dt of each row (model equations and measurements; not the dynamics ε)."""
    t = res.t.numpy()
    return {c["name"]: 0.5 * float(np.trapezoid(c["density"], t)) for c in residual_components(res) if c["kind"] != "dynamics"}
