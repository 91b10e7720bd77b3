"""Files an estimation leaves behind: ``estimate.json``, residual CSV, and figures."""
from __future__ import annotations

import json
import math
import os
import secrets
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from shootlab.estimation.data import Measurements
from shootlab.estimation.fit import EstimationResult
from shootlab.bvp.newton import Status


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


#: the file by which shootlab knows an output folder as its own: a folder that holds it is replaced
#: whole by the next run that writes there; a non-empty folder without it is refused (``--force``)
MARKER = ".shootlab"


def _new_folder(parent: Path, prefix: str) -> Path:
    """A new, empty folder ``parent/prefix<random>`` created with mode 0o777 less the umask (755
    under the usual 022, as ``mkdir`` makes it; ``tempfile.mkdtemp`` would make it 700)."""
    for _ in range(100):
        path = parent / f"{prefix}{secrets.token_hex(4)}"
        try:
            path.mkdir(mode=0o777)
            return path
        except FileExistsError:
            continue
    raise FileExistsError(f"cannot create a new folder {prefix}... in {parent}")


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the
    system or its file system cannot."""
    import ctypes

    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


def _replace_folder(new: Path, out: Path) -> None:
    """Put the folder ``new`` in the place of ``out`` and remove what was there: one rename for a
    new ``out``, one exchange of the two folders for an existing one (two renames where the system
    has no exchange: ``out`` is then missing for the instant between them)."""
    if not out.exists():
        new.rename(out)
        return
    if _exchange(new, out):
        shutil.rmtree(new)                  # now the previous results
        return
    old = out.with_name(f".{out.name}.old-{secrets.token_hex(4)}")
    out.rename(old)
    new.rename(out)
    shutil.rmtree(old, ignore_errors=True)


def _foreign(out: Path) -> list[str]:
    """The entries of the existing folder ``out`` when shootlab did not write it (no :data:`MARKER`),
    else none."""
    if (out / MARKER).is_file():
        return []
    return sorted(p.name for p in out.iterdir())


@contextmanager
def staged_folder(out: str | Path, command: str | None = None) -> Iterator[Path]:
    """A new folder next to ``out`` to write one run's results into.  When the block completes it
    receives :data:`MARKER` (naming ``command``) and replaces ``out`` whole — no file of an earlier
    run stays beside the new ones; on any error or Ctrl-C it is removed and ``out`` is left as it
    was.  ValueError when ``out`` is a non-empty folder that shootlab did not write (see
    :func:`check_output_folder`, which decides that before any work, with ``force``)."""
    out = Path(os.path.realpath(out))
    if out.is_dir() and _foreign(out):
        raise ValueError(f"--out {out} holds files that shootlab did not write; give a new or empty folder "
                         f"(or --force)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = _new_folder(out.parent, f".{out.name}.partial-")
    try:
        yield tmp
        (tmp / MARKER).write_text(json.dumps({"written_by": f"shootlab {command}" if command else "shootlab",
                                              "version": version()}) + "\n")
        _replace_folder(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _check_writable(out: Path) -> None:
    """ValueError unless a file or folder ``out`` can be created next to where it goes: its nearest
    existing parent must be a folder we can create files in (tried, so it holds for root and
    read-only file systems too)."""
    parent = Path(os.path.realpath(out)).parent          # where the results are staged and renamed
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"--out {out}: cannot create a folder under {parent}, which is a file")
    try:
        Path(tempfile.mkdtemp(prefix=".shootlab-check-", dir=parent)).rmdir()
    except OSError as exc:
        raise ValueError(f"--out {out}: cannot create files in {parent} ({exc.strerror or exc})") from None


def check_output_file(out: str | Path) -> Path:
    """``out`` as a file that one command writes whole (``shootlab simulate``'s CSV, replaced in one
    step): ValueError (naming ``out``) if it is a folder or cannot be created."""
    out = Path(out)
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder; give a file name such as {out / 'record.csv'}")
    _check_writable(out)
    return out


def check_output_folder(out: str | Path, force: bool = False, inputs: dict[str, str | Path | None] | None = None
                        ) -> Path:
    """``out`` as a folder that one run's results can replace, checked before any work; ValueError
    (naming ``out``) otherwise.

    It must be a folder or not exist yet, its nearest existing parent a folder we can create files
    in (tried, so it holds for root and read-only file systems too).  An existing non-empty folder
    is replaced whole by the results (:func:`staged_folder`), so it must be one shootlab wrote
    (:data:`MARKER`) — or ``force``, which marks it as shootlab's here — and an existing folder
    must hold neither the working directory nor the home folder, nor any of ``inputs`` (option →
    file read by the run, e.g. ``{"--data": "out/data.csv"}``).  Nothing else is left behind."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is an existing file; give a folder")
    if out.is_dir():
        full = Path(os.path.realpath(out))
        foreign = _foreign(full)
        if foreign and not force:
            shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
            raise ValueError(f"--out {out} is a folder that shootlab did not write ({shown}); the results replace "
                             f"the whole folder: give a new or empty one, or --force to replace it")
        held = [("the working directory", Path.cwd()), ("your home folder", Path.home())] + \
            [(f"{k} {v}", Path(v)) for k, v in (inputs or {}).items() if v]
        for what, path in held:
            if Path(os.path.realpath(path)).is_relative_to(full):
                raise ValueError(f"--out {out} holds {what}, and the results replace the whole folder: "
                                 f"give another folder")
    _check_writable(out)
    if out.is_dir() and _foreign(Path(os.path.realpath(out))):       # force: shootlab's from now on
        (out / MARKER).write_text(json.dumps({"written_by": "shootlab (--force)"}) + "\n")
    return out


def summary(res: EstimationResult) -> dict:
    """The content of ``estimate.json``: ``success`` and ``status`` (a
    :class:`~shootlab.bvp.newton.Status` number, ``success`` exactly when it is 0, and its meaning),
    parameters with standard errors, their correlation matrix and covariance (order
    ``parameter_order``; :mod:`shootlab.estimation.uncertainty`), the noise level σ̂ per channel they are
    scaled by, the units, the diagonal weights W and V used, and the solver's record, with the
    Newton strategies tried (``attempts``: the default's and its fallbacks,
    :func:`shootlab.estimation.fit.solve_falling_back`) (non-finite
    numbers as None: :func:`json_ready`)."""
    sh = res.shooting
    model = res.problem.model
    unc = res.uncertainty
    names = list(res.parameters)
    status = Status(sh.status)
    info = dict(model=model.name, method="shooting", success=res.success, status=int(status),
                status_meaning=status.meaning, message=res.message,
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
    data, :mod:`shootlab.estimation.weights`); a weight given as a matrix or a function of t is not listed."""
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
    from shootlab.estimation.uncertainty import format_estimate
    unit = {p: u for p, u in model.units.items() if u != "-"}          # dimensionless: no unit after the value
    return [f"{p} = {format_estimate(v, standard_errors.get(p), unit.get(p, ''))}" for p, v in parameters.items()]


def correlation_lines(res: EstimationResult, threshold: float = 0.9) -> list[str]:
    """Pairs of parameters whose estimates are correlated beyond ``threshold`` (nearly unidentifiable
    separately), and the misfit warnings of :attr:`shootlab.estimation.uncertainty.Uncertainty.warnings`."""
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


#: the most points a drawn line keeps (:func:`minmax_decimate`): a min/max pair for each of about as
#: many windows as a figure has pixel columns across its axes
DISPLAY_POINTS = 2000


def minmax_decimate(t, y, points: int = DISPLAY_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """The samples of a line to draw: all of them when there are at most ``points``; otherwise
    the first and the last, and in each of ⌈n/k⌉ consecutive windows of k = ⌈n / (points/2)⌉
    samples its smallest and its largest value, in time order (NaN ignored; a window of NaN
    only keeps a NaN, a gap in the line).  The line drawn through them reaches every window's
    extremes, so peaks and noise bands stay as wide as in the full record, with at most
    ``points + 2`` vertices."""
    t, y = np.asarray(t, dtype=float), np.asarray(y, dtype=float)
    n = y.size
    if n <= points:
        return t, y
    k = -(-n // max(points // 2, 1))                 # samples per window
    w = -(-n // k)                                   # windows; the last one padded
    pad = w * k - n
    low = np.concatenate([np.where(np.isnan(y), np.inf, y), np.full(pad, np.inf)]).reshape(w, k)
    high = np.concatenate([np.where(np.isnan(y), -np.inf, y), np.full(pad, -np.inf)]).reshape(w, k)
    start = np.arange(w) * k
    keep = np.concatenate([[0, n - 1], start + low.argmin(1), start + high.argmax(1)])
    keep = np.unique(np.minimum(keep, n - 1))
    return t[keep], y[keep]


def unit_of(model, name: str) -> str:
    """The declared unit of a variable, row or channel (a channel's is its row's, a row's its
    channel's); "" when none is declared."""
    units = model.units
    if units.get(name):
        return units[name]
    row = next((r for r, c in model.channels.items() if c == name), None)
    if row is not None and units.get(row):
        return units[row]
    return units.get(model.channels.get(name, ""), "") or ""


def time_label(model) -> str:
    """x-axis label of a time axis, with the model's unit of t."""
    return f"time {model.label('t')}" if model.units.get("t") else "time t"


def channel_label(model, channel: str) -> str:
    """'channel [unit]' (:func:`unit_of`), 'channel' when no unit is declared."""
    unit = unit_of(model, channel)
    return f"{channel} [{unit}]" if unit else channel


def residual_label(model, row: str) -> str:
    """'ξ row [unit]': the residual of an equation row, in the row's unit (else its channel's)."""
    unit = unit_of(model, row)
    return f"ξ {row}" + (f" [{unit}]" if unit else "")


def plot_samples(ax, t: np.ndarray, values: np.ndarray, label: str, target: int = 120, sep: str = " ") -> None:
    """Measured samples as small hollow markers, every k-th (about ``target``), drawn on top of
    the lines of the axes, so that they stay visible where the model fits them exactly; the
    label says which (after ``sep``)."""
    k = _every(len(t), target)
    ax.plot(t[::k], values[::k], "o", ms=3.2, mfc="none", mec="0.15", mew=0.7, zorder=3,
            label=label + (f"{sep}(every {k}{_ordinal(k)} sample)" if k > 1 else ""))


def _ordinal(k: int) -> str:
    """The English ordinal suffix: 2nd, 3rd, 4th, 11th, 21st."""
    return "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")


def legend_outside(ax, **kw) -> None:
    """The axes' legend right of it, in the figure's margin (:func:`stacked_axes`), off the data."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=7, frameon=False, **kw)


def plot_channel(ax, model, channel: str, t: np.ndarray, fitted: np.ndarray, what: str, t_measured: np.ndarray,
                 measured: np.ndarray) -> None:
    """One measured channel: the model's line (``what``: "estimated", "free run"; min/max
    decimated for display, :func:`minmax_decimate`) under the samples (:func:`plot_samples`),
    the channel's unit on the axis (:func:`channel_label`), the legend outside, a grid."""
    ax.plot(*minmax_decimate(t, fitted), "-", lw=0.9, color="tab:blue", zorder=2, label=what)
    plot_samples(ax, t_measured, measured, "measured", sep="\n")
    ax.set_ylabel(channel_label(model, channel), fontsize=9)
    legend_outside(ax)
    ax.grid(alpha=0.25, lw=0.5)


def stacked_axes(rows: int, title_lines: int = 1, height: float = 1.8, width: float = 9.0):
    """A figure (no pyplot: :class:`matplotlib.figure.Figure` on the Agg canvas) of ``rows`` axes
    one above the other sharing t, with fixed margins in inches — room for the title's lines
    above, the tick labels and y label left, a legend right (:func:`legend_outside`) — so that
    no layout pass is needed; (figure, axes)."""
    from matplotlib.figure import Figure

    top, bottom, left, right, gap = 0.3 + 0.19 * title_lines, 0.55, 0.95, 1.75, 0.22
    tall = top + bottom + rows * height + (rows - 1) * gap
    fig = Figure(figsize=(width, tall))
    axes = fig.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    fig.subplots_adjust(left=left / width, right=1 - right / width, bottom=bottom / tall, top=1 - top / tall,
                        hspace=gap / height)
    for ax in axes:
        ax.tick_params(labelsize=8)
    return fig, axes


def save_figure(fig, path: Path, title: str, fontsize: float = 9, dpi: int = 100, layout: bool = True) -> str:
    """Give ``fig`` its title, lay it out (``layout``: ``tight_layout``; a figure of
    :func:`stacked_axes` has its layout already), write it to ``path`` (Agg) and close it; the
    file name."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig.suptitle(title, fontsize=fontsize, y=1 - 0.12 / fig.get_figheight() if not layout else 0.98)
    if layout:
        fig.tight_layout()
    fast = {"pil_kwargs": {"compress_level": 3}}       # zlib's fast levels: about half the encoding time
    if fig.canvas.manager is not None:              # a pyplot figure: drawn by Agg, then released
        import matplotlib.pyplot as plt
        fig.savefig(path, dpi=dpi, **fast)
        plt.close(fig)
    else:
        FigureCanvasAgg(fig)
        fig.savefig(path, dpi=dpi, **fast)
    return path.name


def _row_groups(model, rows: list[str]) -> list[list[str]]:
    """The rows of a residual figure, one list per axes: the rows of a block (three or more named
    ``name1 … nameN`` with one unit, e.g. a mesh's mass balance) share one axes, every other row
    has its own."""
    import re

    groups: dict[str, list[str]] = {}
    for r in rows:
        m = re.fullmatch(r"(.*?\D)(\d+)", r)
        groups.setdefault(f"block:{m.group(1)}" if m else f"row:{r}", []).append(r)
    out = []
    for key, members in groups.items():
        if key.startswith("block:") and (len(members) < 3 or len({unit_of(model, r) for r in members}) > 1):
            out += [[r] for r in members]
        else:
            out.append(members)
    return out


def plot_estimation(res: EstimationResult, out: Path) -> list[str]:
    """``channels.png``: every measured channel, samples as small hollow markers (every k-th, on
    top) over the thinner estimated line, axes with the model's units, the parameters ± standard
    errors in the title; ``residuals.png``: ξ per equation row with its unit, the rows of a block
    on one axes (:func:`_row_groups`).  Lines are min/max decimated for display
    (:func:`minmax_decimate`), legends right of the axes."""
    model, data = res.problem.model, res.problem.data
    t = res.t.numpy()
    tlabel = time_label(model)
    lines, title = parameter_lines(res), f"{model.name}:"
    for i in range(0, len(lines), 3):                 # the parameter table, three to a line
        title += ("  " if i == 0 else "\n") + ",  ".join(lines[i:i + 3])
    files = []
    # measured vs estimated channels (report figs. 3.7, 4.3)
    rows = [r for r in model.equations if r in model.channels]
    fig, axes = stacked_axes(len(rows), title_lines=1 + (len(lines) - 1) // 3)
    td = np.asarray(data.t, dtype=float)
    inside = (td >= t[0]) & (td <= t[-1])
    for ax, row in zip(axes, rows):
        ch = model.channels[row]
        meas = np.asarray(data.channels[ch], dtype=float)[inside]
        tm = td[inside]
        fit = np.interp(tm, t, (np.interp(t, tm, meas) - res.xi[row].numpy()))
        plot_channel(ax, model, ch, tm, fit, "estimated", tm, meas)
    axes[-1].set_xlabel(tlabel, fontsize=9)
    files.append(save_figure(fig, out / "channels.png", title, dpi=110, layout=False))
    # residuals per equation (report fig. 4.5)
    groups = _row_groups(model, list(res.xi))
    fig, axes = stacked_axes(len(groups), height=1.5)
    for ax, group in zip(axes, groups):
        if len(group) == 1:
            ax.plot(*minmax_decimate(t, res.xi[group[0]].numpy()), lw=0.8, color="tab:red")
            ax.set_ylabel(residual_label(model, group[0]), fontsize=8)
        else:
            from matplotlib import colormaps
            colours = colormaps["viridis"](np.linspace(0.0, 0.9, len(group)))
            for j, (row, c) in enumerate(zip(group, colours)):
                ax.plot(*minmax_decimate(t, res.xi[row].numpy()), lw=0.6, color=c,
                        label=row if j in (0, len(group) - 1) else None)
            legend_outside(ax, title=f"{len(group)} rows", title_fontsize=7)
            ax.set_ylabel(residual_label(model, group[0]).replace(group[0], f"{group[0]}…{group[-1]}"), fontsize=8)
        ax.axhline(0.0, color="0.6", lw=0.5)
        ax.grid(alpha=0.25, lw=0.5)
    axes[-1].set_xlabel(tlabel, fontsize=9)
    files.append(save_figure(fig, out / "residuals.png", f"{model.name}: residuals ξ on the equations", dpi=110,
                             layout=False))
    return files


def write_output_error(res, data, out: str | Path, plots: bool = True) -> dict:
    """Write an output-error estimate (:class:`shootlab.estimation.output_error.OutputErrorResult`) into
    ``out``: ``estimate.json`` (parameters, standard errors, correlation, the misfit per channel),
    ``free_run.csv`` (t, the measured and the simulated channels) and ``channels.png``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model, names = res.model, list(res.parameters)
    data = Measurements.coerce(data).fill_inputs(model.given)[0]      # the record as the estimate used it
    status = Status(res.status)
    info = json_ready(dict(model=model.name, method="output-error", success=res.success, status=int(status),
                           status_meaning=status.meaning, message=res.message, parameters=res.parameters, standard_errors=res.standard_errors,
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
        fig, axes = stacked_axes(len(res.predicted))
        t = np.asarray(data.t)
        for ax, (c, y) in zip(axes, res.predicted.items()):
            plot_channel(ax, model, c, t, y, "free run", t, np.asarray(data.channels[c]))
        axes[-1].set_xlabel(time_label(model), fontsize=9)
        title = f"{model.name}, output error: " + ",  ".join(estimate_lines(model, res.parameters,
                                                                             res.standard_errors))
        info["figures"] = [save_figure(fig, out / "channels.png", title, dpi=110, layout=False)]
    (out / "estimate.json").write_text(json.dumps(info, indent=2))
    return info


def version() -> str:
    """The installed distribution's version, else the package's ``__version__``."""
    try:
        from importlib.metadata import PackageNotFoundError, version as dist_version
        return dist_version("shootlab")
    except PackageNotFoundError:
        from . import __version__
        return __version__
