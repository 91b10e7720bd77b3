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

from .estimation import EstimationResult


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
    def num(v):
        return v if math.isfinite(v) else None
    sh = res.shooting
    return dict(model=res.problem.model.name, success=res.success, message=res.message,
                parameters={k: num(v) for k, v in res.parameters.items()}, J=num(res.J),
                iterations=sh.iterations, jacobian_evaluations=sh.jacobian_evaluations,
                residual_norm=num(sh.residual_norm), seconds=res.seconds, points=res.points,
                stages=sh.stages)


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


def plot_estimation(res: EstimationResult, out: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model, data = res.problem.model, res.problem.data
    t = res.t.numpy()
    files = []
    # measured vs estimated channels (report figs. 3.7, 4.3)
    rows = [r for r in model.equations if r in model.channels]
    fig, axes = plt.subplots(len(rows), 1, figsize=(7, 2.2 * len(rows)), sharex=True, squeeze=False)
    for ax, row in zip(axes[:, 0], rows):
        ch = model.channels[row]
        meas = np.interp(t, data.t, data.channels[ch])
        ax.plot(t, meas, ".", ms=2, color="0.5", label=f"{ch} measured")
        ax.plot(t, meas - res.xi[row].numpy(), "-", lw=1.2, label=f"{ch} estimated")
        ax.set_ylabel(ch)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("t")
    fig.suptitle(f"{model.name}: measured vs estimated")
    fig.tight_layout()
    fig.savefig(out / "channels.png", dpi=110)
    plt.close(fig)
    files.append("channels.png")
    # residuals per equation (report fig. 4.5)
    names = list(res.xi)
    fig, axes = plt.subplots(len(names), 1, figsize=(7, 1.8 * len(names)), sharex=True, squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        ax.plot(t, res.xi[name].numpy(), lw=1)
        ax.set_ylabel(f"ξ {name}", fontsize=8)
        ax.axhline(0.0, color="0.7", lw=0.5)
    axes[-1, 0].set_xlabel("t")
    fig.suptitle(f"{model.name}: residuals ξ on the equations")
    fig.tight_layout()
    fig.savefig(out / "residuals.png", dpi=110)
    plt.close(fig)
    files.append("residuals.png")
    return files
