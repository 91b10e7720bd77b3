"""Example record of the mixture for ``shootlab simulate confined`` (entry point
``shootlab.records``; :class:`shootlab.registry.Record`, :mod:`manipulators.records`)."""
from __future__ import annotations

import numpy as np

from shootlab.registry import Option, Record


def _confined(seed: int, noise: float, elements: int) -> tuple[dict[str, np.ndarray], list[str], str]:
    from .simulation import MEASUREMENT_COLUMNS, simulated_measurements
    rec = simulated_measurements(elements=elements)
    if noise:
        peaks = [float(np.abs(rec.channels[c]).max()) for c in ("load", "displacement", "pressure")]
        rec = simulated_measurements(elements=elements, noise=[noise * p for p in peaks], seed=seed)
    cols = list(MEASUREMENT_COLUMNS)
    return (dict(rec.channels, t=rec.t), cols,
            f"confined compression, {elements} elements, H = 2, K = 1, noise {noise or 0:g} x peak")


#: confined compression with ``elements`` elements, H = 2, K = 1: ``t,load,displacement,pressure``
confined = Record(_confined, "confined compression of a mixture, H = 2, K = 1: t,load,displacement,pressure",
                  options=(Option("noise", float, 0.0, low=0.0, help="noise std as a fraction of each channel's peak"),
                           Option("elements", int, 3, low=1, help="number of finite elements")))
