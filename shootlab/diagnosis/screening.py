"""The screening regression of "Which effect" (docs/design.md §4, step 2; ``docs/diagnosis.md``): a
candidate's term fitted to the residual at the nominal estimate, before any re-estimation.

With the residual ξ of the rows that have a noise floor σ, standardised (y = ξ/σ, stacked over
the measured samples), and the nominal free parameters' sensitivities s_θ = ∂(f + Fζ)/∂θ
standardised the same way as nuisance columns S (:class:`Design`, :func:`regression_design`),
the candidate's parameters p minimise, from a few starts (:func:`starting_values`)::

    ‖P⊥ (y − g(p))‖²,    P⊥ = I − Q Qᵀ,   Q an orthonormal basis of span S

where g(p) is the standardised term on the estimated states, inputs and data (:func:`fit_terms`,
bounded non-linear least squares): what re-estimating the nominal parameters could absorb is
projected out.  :func:`linear_parameters` finds the parameters the term is linear in (the rest are
its *shape*, held at the screened values by the scoring step), and :func:`collinearity` the share
‖P⊥ c‖/‖c‖ of a linear parameter's column c that is new to the model.  :func:`screen` runs the
starts, the fit and the linearity probe for one effect; :mod:`.which` takes it from there (the
collinearity test, then the scoring).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from .composition import Vars, new_parameters, term_rows, term_vars
from shootlab.estimation.fit import EstimationResult
from shootlab.estimation.model import IdentificationModel
from .effects import Effect

__all__ = ["Design", "regression_design", "starting_values", "fit_terms", "linear_parameters", "collinearity",
           "screen"]


@dataclass
class Design:
    """The standardised regression problem at the nominal estimate."""

    model: IdentificationModel
    names: list[str]
    x: Tensor                  # (n, nx) estimated states and parameters
    zeta: Tensor               # (n, nζ)
    t: Tensor
    channel: Any
    rows: list[int]            # rows in the regression
    sigma: np.ndarray          # (len(rows),) floor rms per row
    mask: np.ndarray           # (n, len(rows)) bool
    y: np.ndarray              # stacked standardised residual
    Q: np.ndarray              # orthonormal basis of the nuisance columns
    nuisance: list[str]
    S: np.ndarray              # the nuisance columns (unit norm), one per name in ``nuisance``
    n_eff: float

    def project(self, v: np.ndarray) -> np.ndarray:
        return v - self.Q @ (self.Q.T @ v) if self.Q.size else v

    def stack(self, per_row: Tensor | np.ndarray) -> np.ndarray:
        a = per_row.detach().numpy() if isinstance(per_row, Tensor) else np.asarray(per_row)
        a = a[:, self.rows] / self.sigma
        return a[self.mask]

    def vars(self, effects: Sequence[Effect], values: Mapping[str, float]) -> Vars:
        new = new_parameters(self.model, effects)
        n = self.x.shape[0]
        th = torch.tensor([float(values[p]) for p in new], dtype=torch.float64).expand(n, -1)
        x = torch.cat([self.x, th], -1)
        return term_vars(self.model, self.names + new, x, self.zeta, self.t, self.channel)

    def predict(self, effects: Sequence[Effect], values: Mapping[str, float]) -> np.ndarray:
        with torch.no_grad():
            v = self.vars(effects, values)
            out = term_rows(self.model, effects, v, self.t.shape)
        return self.stack(out)


def regression_design(nominal: EstimationResult, floor_sigma: Mapping[str, float], n_eff: float,
                      channel) -> Design:
    """The standardised residual at the nominal estimate (rows with a floor) and the orthonormal
    basis of the free nominal parameters' sensitivities (nuisance columns)."""
    model = nominal.problem.model
    names = model.names
    t = nominal.t
    x = torch.stack([nominal.x[n] for n in names], -1).detach()
    zeta = torch.stack([nominal.zeta[n] for n in model.inputs], -1).detach()
    with torch.no_grad():
        _, mask = nominal.problem.measurements(t)
    xi = torch.stack([nominal.xi[r] for r in model.equations], -1).numpy()
    rows = [i for i, r in enumerate(model.equations) if floor_sigma.get(r, 0.0) > 0]
    sigma = np.array([floor_sigma[model.equations[i]] for i in rows])
    mk = mask.numpy()[:, rows] > 0
    y = (xi[:, rows] / sigma)[mk]
    # nuisance columns: the sensitivities of the rows to the free nominal parameters
    W_a = nominal.problem.W_a
    free = [p for j, p in enumerate(model.parameters) if float(W_a[len(model.states) + j, len(model.states) + j]) == 0.0]
    cols = []
    with torch.no_grad():
        for p in free:
            j = names.index(p)
            h = 1e-6 * max(abs(float(x[:, j].mean())), 1e-3)
            xp, xm = x.clone(), x.clone()
            xp[:, j] += h
            xm[:, j] -= h
            gp = model.f(xp, t) + (model.F(xp, t) @ zeta.unsqueeze(-1)).squeeze(-1)
            gm = model.f(xm, t) + (model.F(xm, t) @ zeta.unsqueeze(-1)).squeeze(-1)
            col = ((gp - gm) / (2 * h)).numpy()
            cols.append((col[:, rows] / sigma)[mk])
    if cols:
        S = np.column_stack(cols)
        norms = np.linalg.norm(S, axis=0)
        keep = norms > 0
        S = S[:, keep] / norms[keep]
        U, sv, _ = np.linalg.svd(S, full_matrices=False)
        Q = U[:, sv > 1e-10 * (sv.max() if sv.size else 1.0)]
        nuis = [p for p, k in zip(free, keep) if k]
    else:
        S, Q, nuis = np.zeros((y.size, 0)), np.zeros((y.size, 0)), []
    return Design(model=model, names=names, x=x, zeta=zeta, t=t, channel=channel, rows=rows, sigma=sigma,
                   mask=mk, y=y, Q=Q, nuisance=nuis, S=S, n_eff=n_eff)


def starting_values(effect: Effect, v: Vars) -> list[dict]:
    """The grid of the effect's initial values and declared ``starts`` (at most 27 combinations)."""
    s = effect.starts(v) if callable(effect.starts) else effect.starts
    grid = []
    for p, v0 in effect.parameters.items():
        vals = [v0] + [float(a) for a in (s or {}).get(p, [])]
        grid.append(list(dict.fromkeys(vals)))
    combos = [dict(zip(effect.parameters, c)) for c in itertools.product(*grid)]
    return combos[:27]


def fit_terms(design: Design, effects: Sequence[Effect],
              starts: Sequence[Mapping[str, float]]) -> tuple[float, dict[str, float]]:
    """Least squares of the projected standardised residual on the effects' terms."""
    from scipy.optimize import least_squares

    names = [p for e in effects for p in e.parameters]
    lo = np.array([e.bounds.get(p, (-np.inf, np.inf))[0] for e in effects for p in e.parameters], dtype=float)
    hi = np.array([e.bounds.get(p, (-np.inf, np.inf))[1] for e in effects for p in e.parameters], dtype=float)
    scale = np.array([float(e.scale.get(p, abs(v) if v != 0 else 1.0)) for e in effects for p, v in e.parameters.items()])
    scale = np.where(scale > 0, scale, 1.0)
    yp = design.project(design.y)

    def resid(th):
        pred = design.predict(effects, dict(zip(names, th)))
        r = yp - design.project(pred)
        return np.where(np.isfinite(r), r, 1e6)

    best = None
    for s in starts:
        x0 = np.array([float(s[p]) for p in names])
        fin_lo, fin_hi = np.isfinite(lo), np.isfinite(hi)
        inner_lo, inner_hi = lo.copy(), hi.copy()
        inner_lo[fin_lo] = lo[fin_lo] + 1e-9 * np.maximum(np.abs(lo[fin_lo]), scale[fin_lo])
        inner_hi[fin_hi] = hi[fin_hi] - 1e-9 * np.maximum(np.abs(hi[fin_hi]), scale[fin_hi])
        x0 = np.minimum(np.maximum(x0, inner_lo), inner_hi)
        try:
            sol = least_squares(resid, x0, bounds=(lo, hi), x_scale=scale, method="trf", max_nfev=200,
                                diff_step=1e-6)
        except Exception:  # noqa: BLE001 - a start that fails is skipped
            continue
        rss = float(sol.fun @ sol.fun)
        if best is None or rss < best[0]:
            best = (rss, sol.x)
    if best is None:
        return float(yp @ yp), {p: float(v) for p, v in zip(names, [s for s in starts[0].values()])}
    return best[0], {p: float(v) for p, v in zip(names, best[1])}


def linear_parameters(design: Design, effect: Effect, values: Mapping[str, float]) -> list[str]:
    """The parameters the effect's term is linear in (numerical probe on the estimated variables)."""
    out = []
    for p in effect.parameters:
        a = float(effect.scale.get(p, abs(values[p]) or 1.0)) or 1.0
        t0, t1, t2 = (design.predict([effect], dict(values, **{p: c})) for c in (0.0, a, 2.0 * a))
        d1, d2 = t1 - t0, t2 - t0
        if np.all(np.isfinite(d2)) and np.abs(d2 - 2 * d1).max() <= 1e-8 * (1.0 + np.abs(d2).max()):
            out.append(p)
    return out


def collinearity(design: Design, effect: Effect, values: Mapping[str, float], linear: Sequence[str]
                 ) -> tuple[float, str | None, list[str]]:
    """How much of the effect's term is new to the model: for each parameter the term is linear
    in, the share ‖P⊥ c‖ / ‖c‖ of its column c (standardised, at ``values``) outside the span of
    the nominal parameters' sensitivities.  Returns the smallest share, its parameter and the
    nominal parameters that make up the column (least-squares coefficients ≥ 10 % of the
    largest) — a share near 0 means re-estimating those parameters absorbs the effect."""
    worst: tuple[float, str | None, list[str]] = (1.0, None, [])
    for p in linear:
        a = float(effect.scale.get(p, 1.0)) or 1.0
        col = design.predict([effect], dict(values, **{p: a})) - design.predict([effect], dict(values, **{p: 0.0}))
        norm = float(np.linalg.norm(col))
        if not (norm > 0 and np.all(np.isfinite(col))):
            continue
        share = float(np.linalg.norm(design.project(col))) / norm
        if share < worst[0]:
            coef = np.linalg.lstsq(design.S, col, rcond=None)[0] if design.S.size else np.zeros(0)
            big = np.abs(coef) >= 0.1 * np.abs(coef).max() if coef.size else np.zeros(0, bool)
            worst = (share, p, [n for n, b in zip(design.nuisance, big) if b])
    return worst


def screen(design: Design, effect: Effect) -> tuple[list[dict], dict[str, float], list[str]]:
    """The effect's term fitted to the floor-standardised residual with the nominal parameters'
    sensitivities as nuisance columns (cheap; it picks the shape parameters).  Returns the starting
    values tried, the screened parameters and the parameters the term is linear in."""
    starts = starting_values(effect, design.vars([effect], effect.parameters))
    _, screened = fit_terms(design, [effect], starts)
    return starts, screened, linear_parameters(design, effect, screened)
