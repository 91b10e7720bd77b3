"""Example record of the mixture for ``shootlab simulate confined`` (entry point
``shootlab.records``; :mod:`shootlab.registry`, :mod:`manipulators.records`)."""
from __future__ import annotations

import numpy as np


def confined(noise: float | None = None, seed: int = 0, elements: int = 3, **_
             ) -> tuple[dict[str, np.ndarray], list[str], str]:
    """Confined compression with ``elements`` elements, H = 2, K = 1: ``t,load,displacement,pressure``,
    noise std ``noise`` × the peak of each channel."""
    from .simulation import MEASUREMENT_COLUMNS, simulated_measurements
    rec = simulated_measurements(elements=elements)
    if noise:
        peaks = [float(np.abs(rec.channels[c]).max()) for c in ("load", "displacement", "pressure")]
        rec = simulated_measurements(elements=elements, noise=[noise * p for p in peaks], seed=seed)
    cols = list(MEASUREMENT_COLUMNS)
    return (dict(rec.channels, t=rec.t), cols,
            f"confined compression, {elements} elements, H = 2, K = 1, noise {noise or 0:g} x peak")
