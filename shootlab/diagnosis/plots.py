"""The diagnosis's figures (``docs/diagnosis.md``): ``residuals.png`` (residuals per row, the floor
band, the flagged windows), ``signatures.png`` (partial residuals against the top candidates'
terms) and ``validation.png`` (free run before/after).  A model that was not estimated is not drawn.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from .composition import channel_reader, term_rows, term_vars
from .outcome import Diagnosis, fmt

__all__ = ["figures"]


def figures(diag: Diagnosis, out: Path) -> list[str]:
    """Draw the figures into the folder ``out``; their file names."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from shootlab.outputs import plot_samples, residual_label, save_figure, time_label

    files = []
    res, model = diag.nominal, diag.model
    if not res.success:                      # an unestimated model is not drawn
        return files
    t = res.t.numpy()
    # 1. residuals over time with the flagged windows and the floor band
    rows = [w for w in diag.where if w["kind"] != "dynamics"]
    fig, axes = plt.subplots(len(rows), 1, figsize=(8, 1.7 * len(rows) + 0.6), sharex=True, squeeze=False)
    for ax, w in zip(axes[:, 0], rows):
        xi = res.xi[w["equation"]].numpy()
        ax.plot(t, xi, lw=0.8, color="tab:red" if w["significant"] else "0.4", label="nominal")
        if diag.extended is not None and diag.extended.success:
            ax.plot(diag.extended.t.numpy(), diag.extended.xi[w["equation"]].numpy(), lw=0.7, color="tab:blue",
                    alpha=0.8, label="extended")
        fr = w.get("floor_rms")
        if fr:
            ax.axhspan(-2 * fr, 2 * fr, color="tab:green", alpha=0.15, label="±2 floor rms")
        for a, b in w["windows"]:
            ax.axvspan(a, b, color="gold", alpha=0.3)
        ax.set_ylabel(residual_label(model, w['equation']), fontsize=8)
        ax.set_title(f"{w['equation']}: {100 * w['share']:.1f} % of J, rms/floor {fmt(math.sqrt(w['ratio']) if w.get('ratio') else None)}"
                     + (" — significant" if w["significant"] else ""), fontsize=8)
    axes[0, 0].legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel(time_label(model))
    files.append(save_figure(fig, out / "residuals.png", f"{model.name}: residuals per row (shaded: flagged windows)",
                             fontsize=10))
    # 2. residual vs the top signatures: partial residuals (the residual the candidate leaves after its
    #    re-estimation, plus the candidate's own term) against the candidate's variable
    which = diag.which
    top = which.get("ranking", [])[:3]
    if top:
        fig, axes = plt.subplots(1, len(top), figsize=(4.3 * len(top), 3.7), squeeze=False)
        for ax, r in zip(axes[0], top):
            e = diag.library[r["effect"]]
            row = e.equations[0]
            m = next((mm for mm in which.get("models", []) if mm.effects == [e.name]), None)
            res_e = m.result if m else None
            if res_e is None:
                ax.set_axis_off()
                continue
            em = res_e.problem.model
            x = torch.stack([res_e.x[n] for n in em.names], -1)
            z = torch.stack([res_e.zeta[n] for n in model.inputs], -1)
            with torch.no_grad():
                v = term_vars(model, em.names, x, z, res_e.t, channel_reader(diag.data, list(e.channels)))
                contrib = term_rows(model, [e], v, res_e.t.shape)[:, model.equations.index(row)].numpy()
                xv = e.variable[1](v).numpy() if e.variable else contrib
            partial = res_e.xi[row].numpy() + contrib
            ax.plot(xv, partial, ".", ms=2, color="0.45", alpha=0.6, label=f"partial residual {row}")
            if np.all(np.diff(xv) >= 0):        # a variable that only grows (t): the term as a line
                ax.plot(xv, contrib, "-", color="tab:red", lw=1.4, label=f"{e.name} term")
            else:       # against a variable that goes back and forth (a velocity, du/dt) the term need not
                ax.plot(xv, contrib, ".", ms=1.5, color="tab:red", label=f"{e.name} term")  # be its function
            ax.axhline(0.0, color="0.7", lw=0.5)
            xname, xunit = (e.variable[0] if e.variable else f"{e.name} term"), _variable_unit(model, e, row)
            ax.set_xlabel(xname + (f" [{xunit}]" if xunit else ""), fontsize=8)
            ax.set_ylabel(f"{residual_label(model, row)} + term (re-estimated)", fontsize=8)
            chosen = " (selected)" if r["effect"] in diag.selected else ""
            ax.set_title(f"{r['effect']}{chosen}: alone explains {100 * r['score']:.0f} % of J, confidence "
                         f"{r.get('confidence_nested', r['confidence']):.2f}", fontsize=8)
            ax.legend(fontsize=7)
        files.append(save_figure(fig, out / "signatures.png", "residual vs the top candidate signatures (partial "
                                 "residuals after each candidate's linearised re-estimation)"))
    # 3. validation before/after
    val = (diag.shrink or {}).get("validation")
    if val is not None and diag.validation is not None:
        preds = val.get("predictions", {})
        chans = [c for c in model.measured if c not in model.given]
        how = (f"simulations restarted every {fmt(val.get('window'))} (state fitted on each window's first quarter)"
               if val.get("measure") == "windows" else "free run")
        fig, axes = plt.subplots(len(chans), 1, figsize=(8, 2.2 * len(chans) + 0.6), sharex=True, squeeze=False)
        for ax, ch in zip(axes[:, 0], chans):
            for key, col, lab in (("before", "tab:red", "nominal"), ("after", "tab:blue", "extended")):
                p = preds.get(key)
                if p is not None and ch in p:
                    ax.plot(p["t"], p[ch], color=col, lw=0.9, label=f"{lab} model")
            plot_samples(ax, np.asarray(diag.validation.t), np.asarray(diag.validation.channels[ch]), f"{ch} measured")
            ax.set_ylabel(_channel_label(model, ch))
            d = val["per_channel"][ch]
            ax.set_title(f"{ch}: RMS error {fmt(d['before'])} → {fmt(d['after'])} (shrink {fmt(d['shrink'], '.2f')})", fontsize=8)
            ax.legend(fontsize=7, loc="best")
        axes[-1, 0].set_xlabel(time_label(model))
        files.append(save_figure(fig, out / "validation.png", f"validation record: {how}, before / after", fontsize=10))
    return files


def _channel_label(model, channel: str) -> str:
    """'channel [unit]': the channel's declared unit, else that of its measurement row."""
    row = next((r for r, c in model.channels.items() if c == channel), channel)
    unit = model.units.get(channel) or model.units.get(row)
    return f"{channel} [{unit}]" if unit else channel


def _variable_unit(model, effect, row: str) -> str | None:
    """The unit of an effect's signature variable: its declared one (``variable[2]``), else the
    model's unit of the label's first word ('v2 (estimated)' → v2's); without a variable (the x-axis
    is the term itself) the unit of the row it enters."""
    if not effect.variable:
        return model.units.get(row) or model.units.get(model.channels.get(row, ""))
    if len(effect.variable) > 2:
        return effect.variable[2]
    return model.units.get(effect.variable[0].split(" ")[0])
