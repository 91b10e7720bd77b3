"""Files an estimation leaves behind: ``estimate.json``, residual CSV, and figures."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .estimation import EstimationResult


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
