"""Files an estimation leaves behind: ``estimate.json``, residual CSV, and figures."""
from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from .data import Measurements
from .estimation import EstimationResult


def fmt(v, spec: str = ".3g", missing: str = "-") -> str:
    """A number as text for a table or report: ``missing`` for None and non-finite floats."""
    return missing if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def json_ready(o):
    """``o`` as plain JSON: numpy scalars, arrays and torch tensors as Python numbers and lists,
    non-finite floats as None, mapping keys as strings; anything else is returned unchanged."""
    if isinstance(o, dict):
        return {str(k): json_ready(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_ready(v) for v in o]
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, (np.ndarray, torch.Tensor)):
        return json_ready(o.tolist())
    return o


@contextmanager
def staged_folder(out: str | Path) -> Iterator[Path]:
    """A temporary folder next to ``out`` to write results into; when the block completes its
    files are moved into ``out`` (created if needed; a new ``out`` is renamed into place in one
    step), and on any error or Ctrl-C it is removed: an interrupted run leaves nothing that looks
    like a result."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        yield tmp
        if not out.exists():
            tmp.rename(out)
            return
        for f in sorted(tmp.iterdir()):
            target = out / f.name
            if target.is_dir() and not f.is_dir():
                raise ValueError(f"cannot write {target}: it is a folder")
            os.replace(f, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def check_output_folder(out: str | Path) -> Path:
    """ValueError (naming ``out``) unless results can be written to the folder ``out``: it must be
    a folder or not exist yet, and its nearest existing parent must be a folder we can create
    files in (tried, so it holds for root and read-only file systems too).  Nothing is left behind."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is an existing file; give a folder")
    parent = out if out.exists() else out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"--out {out}: cannot create a folder under {parent}, which is a file")
    try:
        Path(tempfile.mkdtemp(prefix=".shootlab-check-", dir=parent)).rmdir()
    except OSError as exc:
        raise ValueError(f"--out {out}: cannot create files in {parent} ({exc.strerror or exc})") from None
    return out


def summary(res: EstimationResult) -> dict:
    """The content of ``estimate.json``: parameters with standard errors, their correlation
    matrix and covariance (order ``parameter_order``; :mod:`shootlab.uncertainty`), the noise
    level σ̂ per channel they are scaled by, the units, the diagonal weights W and V used, and the
    solver's record, with the Newton strategies tried (``attempts``: the default's and its fallbacks,
    :func:`shootlab.estimation.solve_falling_back`) (non-finite
    numbers as None: :func:`json_ready`)."""
    sh = res.shooting
    model = res.problem.model
    unc = res.uncertainty
    names = list(res.parameters)
    info = dict(model=model.name, success=res.success, message=res.message,
                parameters=dict(res.parameters),
                standard_errors=dict(res.standard_errors),
                parameter_order=names,
                correlation=[[float(v) for v in row] for row in res.correlation],
                covariance=[[float(v) for v in row] for row in res.covariance],
                noise_levels=dict(unc.noise) if unc is not None else {},
                units=dict(model.units), J=res.J,
                iterations=sh.iterations, jacobian_evaluations=sh.jacobian_evaluations,
                residual_norm=sh.residual_norm, seconds=res.seconds, points=res.points,
                stages=sh.stages, attempts=res.attempts, weights=_weights(model))
    if unc is None and res.success:
        info["uncertainty_note"] = "not available: the Newton matrix at the solution is singular"
    elif unc is not None and unc.warnings:
        info["uncertainty_note"] = unc.warnings
    return json_ready(info)


def _weights(model) -> dict:
    """The diagonal weights used, by name (as estimated: a declared model's defaults scaled by the
    data, :mod:`shootlab.weights`); a weight given as a matrix or a function of t is not listed."""
    out = {}
    for key, names in (("W", model.names), ("V", model.equations)):
        w = getattr(model, key)
        if not callable(w):
            w = torch.as_tensor(w, dtype=torch.float64)
            if w.ndim == 1:
                out[key] = {n: float(v) for n, v in zip(names, w)}
    return out


def parameter_lines(res: EstimationResult) -> list[str]:
    """'m = 1.0012 ± 0.0021 kg' per parameter (the value to the standard error's 2nd digit)."""
    return estimate_lines(res.problem.model, res.parameters, res.standard_errors)


def estimate_lines(model, parameters: dict[str, float], standard_errors: dict[str, float]) -> list[str]:
    """:func:`parameter_lines` for any estimate: values, standard errors and the model's units."""
    from .uncertainty import format_estimate
    unit = {p: u for p, u in model.units.items() if u != "-"}          # dimensionless: no unit after the value
    return [f"{p} = {format_estimate(v, standard_errors.get(p), unit.get(p, ''))}" for p, v in parameters.items()]


def correlation_lines(res: EstimationResult, threshold: float = 0.9) -> list[str]:
    """Pairs of parameters whose estimates are correlated beyond ``threshold`` (nearly unidentifiable
    separately), and the misfit warnings of :attr:`shootlab.uncertainty.Uncertainty.warnings`."""
    names, rho = list(res.parameters), res.correlation
    unc = res.uncertainty
    return [f"corr({names[i]}, {names[j]}) = {rho[i, j]:+.3f}" for i in range(len(names))
            for j in range(i + 1, len(names)) if math.isfinite(rho[i, j]) and abs(rho[i, j]) >= threshold] \
        + ([f"note: {w}" for w in unc.warnings] if unc is not None else [])


def write_estimation(res: EstimationResult, out: str | Path, plots: bool = True) -> dict:
    """Write ``estimate.json``, ``residuals.csv`` and (optionally) PNG figures into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    info = summary(res)
    cols = {"t": res.t.numpy()}
    cols.update({f"xi:{k}": v.numpy() for k, v in res.xi.items()})
    cols.update({f"eps:{k}": v.numpy() for k, v in res.eps.items()})
    cols.update({f"x:{k}": v.numpy() for k, v in res.x.items()})
    cols.update({f"zeta:{k}": v.numpy() for k, v in res.zeta.items()})
    np.savetxt(out / "residuals.csv", np.column_stack(list(cols.values())), delimiter=",",
               header=",".join(cols), comments="", fmt="%.10g")
    if plots:
        info["figures"] = plot_estimation(res, out)
    (out / "estimate.json").write_text(json.dumps(info, indent=2))
    return info


def _every(n: int, target: int = 120) -> int:
    """Stride that leaves about ``target`` markers of ``n`` samples."""
    return max(1, int(math.ceil(n / target)))


def time_label(model) -> str:
    """x-axis label of a time axis, with the model's unit of t."""
    return f"time {model.label('t')}" if model.units.get("t") else "time t"


def residual_label(model, row: str) -> str:
    """'ξ row [unit]': the residual of an equation row, in the row's unit (else its channel's)."""
    unit = model.units.get(row) or model.units.get(model.channels.get(row, ""), "")
    return f"ξ {row}" + (f" [{unit}]" if unit else "")


def plot_samples(ax, t: np.ndarray, values: np.ndarray, label: str, target: int = 120) -> None:
    """Measured samples as small hollow markers, every k-th (about ``target``), drawn on top of
    the lines of the axes, so that they stay visible where the model fits them exactly."""
    k = _every(len(t), target)
    ax.plot(t[::k], values[::k], "o", ms=3.2, mfc="none", mec="0.15", mew=0.7, zorder=3,
            label=label + (f" (every {k}{_ordinal(k)} sample)" if k > 1 else ""))


def _ordinal(k: int) -> str:
    """The English ordinal suffix: 2nd, 3rd, 4th, 11th, 21st."""
    return "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")


def plot_channel(ax, model, channel: str, t: np.ndarray, fitted: np.ndarray, what: str, t_measured: np.ndarray,
                 measured: np.ndarray) -> None:
    """One measured channel: the model's line (``what``: "estimated", "free run") under the samples
    (:func:`plot_samples`), the channel's unit on the axis, legend and grid."""
    ax.plot(t, fitted, "-", lw=0.9, color="tab:blue", zorder=2, label=f"{channel} {what}")
    plot_samples(ax, t_measured, measured, f"{channel} measured")
    ax.set_ylabel(model.label(channel))
    ax.legend(loc="best", fontsize=7, framealpha=0.8)
    ax.grid(alpha=0.25, lw=0.5)


def save_figure(fig, path: Path, title: str, fontsize: float = 9, dpi: int = 100) -> str:
    """Give ``fig`` its title, lay it out, write it to ``path`` and close it; the file name."""
    import matplotlib.pyplot as plt

    fig.suptitle(title, fontsize=fontsize)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path.name


def plot_estimation(res: EstimationResult, out: Path) -> list[str]:
    """``channels.png``: every measured channel, samples as small hollow markers (every k-th, on
    top) over the thinner estimated line, axes with the model's units, the parameters ± standard
    errors in the title; ``residuals.png``: ξ per equation row with its unit."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model, data = res.problem.model, res.problem.data
    t = res.t.numpy()
    tlabel = time_label(model)
    lines, title = parameter_lines(res), f"{model.name}:"
    for i in range(0, len(lines), 3):                 # the parameter table, three to a line
        title += ("  " if i == 0 else "\n") + ",  ".join(lines[i:i + 3])
    files = []
    # measured vs estimated channels (report figs. 3.7, 4.3)
    rows = [r for r in model.equations if r in model.channels]
    fig, axes = plt.subplots(len(rows), 1, figsize=(8, 1.2 + 2.1 * len(rows)), sharex=True, squeeze=False)
    td = np.asarray(data.t, dtype=float)
    inside = (td >= t[0]) & (td <= t[-1])
    for ax, row in zip(axes[:, 0], rows):
        ch = model.channels[row]
        meas = np.asarray(data.channels[ch], dtype=float)[inside]
        tm = td[inside]
        fit = np.interp(tm, t, (np.interp(t, tm, meas) - res.xi[row].numpy()))
        plot_channel(ax, model, ch, tm, fit, "estimated", tm, meas)
    axes[-1, 0].set_xlabel(tlabel)
    files.append(save_figure(fig, out / "channels.png", title, dpi=130))
    # residuals per equation (report fig. 4.5)
    names = list(res.xi)
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 1.0 + 1.7 * len(names)), sharex=True, squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        ax.plot(t, res.xi[name].numpy(), lw=0.8, color="tab:red")
        ax.set_ylabel(residual_label(model, name), fontsize=8)
        ax.axhline(0.0, color="0.6", lw=0.5)
        ax.grid(alpha=0.25, lw=0.5)
    axes[-1, 0].set_xlabel(tlabel)
    files.append(save_figure(fig, out / "residuals.png", f"{model.name}: residuals ξ on the equations", dpi=130))
    return files


def write_output_error(res, data, out: str | Path, plots: bool = True) -> dict:
    """Write an output-error estimate (:class:`shootlab.output_error.OutputErrorResult`) into
    ``out``: ``estimate.json`` (parameters, standard errors, correlation, the misfit per channel),
    ``free_run.csv`` (t, the measured and the simulated channels) and ``channels.png``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model, names = res.model, list(res.parameters)
    data = Measurements.coerce(data).fill_inputs(model.given)[0]      # the record as the estimate used it
    info = json_ready(dict(model=model.name, method="output-error", success=res.success, status=res.status,
                           message=res.message, parameters=res.parameters, standard_errors=res.standard_errors,
                           parameter_order=names,
                           correlation=None if res.correlation is None else res.correlation.tolist(),
                           cost=res.cost, samples=res.samples, misfit_ratio=res.misfit_ratio,
                           rms_over_noise=res.rms, noise_levels=res.noise, evaluations=res.evaluations,
                           seconds=res.seconds, units=dict(model.units)))
    cols = {"t": np.asarray(data.t)}
    for c, y in res.predicted.items():
        cols[f"measured:{c}"], cols[f"simulated:{c}"] = np.asarray(data.channels[c]), y
    np.savetxt(out / "free_run.csv", np.column_stack(list(cols.values())), delimiter=",", header=",".join(cols),
               comments="", fmt="%.10g")
    if plots and res.predicted:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(len(res.predicted), 1, figsize=(8, 1.2 + 2.1 * len(res.predicted)), sharex=True,
                                 squeeze=False)
        t = np.asarray(data.t)
        for ax, (c, y) in zip(axes[:, 0], res.predicted.items()):
            plot_channel(ax, model, c, t, y, "free run", t, np.asarray(data.channels[c]))
        axes[-1, 0].set_xlabel(time_label(model))
        title = f"{model.name}, output error: " + ",  ".join(estimate_lines(model, res.parameters,
                                                                             res.standard_errors))
        info["figures"] = [save_figure(fig, out / "channels.png", title, dpi=130)]
    (out / "estimate.json").write_text(json.dumps(info, indent=2))
    return info
