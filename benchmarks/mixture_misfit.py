"""Which misfit tells a structural effect from noise on mixture records made another way?

The diagnosis (``shootlab diagnose``) decides whether a record has a structural error from the
objective J of the TPBVP estimate (report eq. 2.6) against the noise floor J_floor of surrogate
records.  On the independent mixture records (``benchmarks/independent/mixture.py``: finite
volumes on 120 cells, white + AR(1) noise) it answered "no significant structural error" on every
effect, moderate and large.  This script sets two measures side by side, per record,
for the confined model with N elements estimated on 201 shooting points:

* ``J`` of the TPBVP estimate, and its ratio to J of the clean record with the same noise draw;
* the output-error free run: the N-element model simulated under the measured load with the
  estimated H, K (:func:`mixtures.identification.simulated_profile`), its RMS misfit per channel
  divided by the channel's noise level read from the record (:func:`shootlab.estimation.data.noise_level`),
  on the identification record and on the validation record (another load, another noise draw).

A free-run ratio near 1 is noise; the clean records show what the N-element discretisation adds.
Prints the table and saves ``benchmarks/results/mixture_misfit.json``.

    python benchmarks/mixture_misfit.py [--elements 6 12] [--magnitudes moderate large]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.independent import mixture as independent  # noqa: E402
from mixtures.confined import ConfinedCompression  # noqa: E402
from mixtures.identification import model, simulated_profile  # noqa: E402
from shootlab.estimation import estimate  # noqa: E402
from shootlab.estimation.data import noise_level  # noqa: E402
from shootlab.outputs import json_ready  # noqa: E402

EFFECTS = ["filter_permeability", "load_offset", "machine_compliance", "nonlinear_solid",
           "strain_dependent_permeability"]
CHANNELS = ("displacement", "pressure")
POINTS = 201


def free_run_ratios(cc: ConfinedCompression, record, H: float, K: float) -> dict[str, float]:
    """RMS of (measured − free run) / the record's noise level, per channel."""
    t = torch.as_tensor(record.t)
    s = simulated_profile(cc, record, t, H, K)
    u = torch.as_tensor(record.channels["load"])
    sim = {"displacement": -s[:, -1].numpy(),
           "pressure": cc.pressure(s, u, torch.tensor(H, dtype=torch.float64))[..., 0].numpy()}
    sigma = noise_level(record, list(CHANNELS))
    return {ch: float(np.sqrt(np.mean((record.channels[ch] - sim[ch]) ** 2)) / sigma[ch]) for ch in CHANNELS}


def one(elements: int, effect: str | None, magnitude: str, seed: int) -> dict:
    ident, valid, info = independent.data(effect, magnitude, 0.01, seed)
    t0 = time.perf_counter()
    res = estimate(model(elements=elements), ident, n_points=POINTS)
    if not res.success:
        return dict(elements=elements, effect=effect or "none", magnitude=magnitude, seed=seed, success=False,
                    message=res.message)
    H, K = res.parameters["H"], res.parameters["K"]
    cc = ConfinedCompression(elements)
    return dict(elements=elements, effect=effect or "none", magnitude=magnitude, seed=seed, success=True,
                H=H, K=K, J=float(res.J), relative_change=info["relative_change"],
                free_run_identification=free_run_ratios(cc, ident, H, K),
                free_run_validation=free_run_ratios(cc, valid, H, K), seconds=time.perf_counter() - t0)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--elements", type=int, nargs="+", default=[6, 12])
    ap.add_argument("--magnitudes", nargs="+", default=["moderate", "large"])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "mixture_misfit.json"))
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    rows = []
    print(f"{'N':>3} {'effect':<30} {'size':<9} {'seed':>4} {'J':>9} {'J/J_clean':>9}   free run / noise: "
          f"ident (disp, pres)   valid (disp, pres)")
    for N in args.elements:
        clean = {}
        cases = [(None, "-", seed) for seed in (1, 100, 101)] + [(e, m, 1) for m in args.magnitudes for e in EFFECTS]
        for effect, magnitude, seed in cases:
            row = one(N, effect, magnitude, seed)
            rows.append(row)
            if not row["success"]:
                print(f"{N:>3} {row['effect']:<30} {magnitude:<9} {seed:>4}  estimate failed: {row['message']}")
                continue
            if effect is None:
                clean[seed] = row["J"]
            row["J_over_clean"] = row["J"] / clean[seed] if seed in clean else None
            fi, fv = row["free_run_identification"], row["free_run_validation"]
            ratio = "" if row["J_over_clean"] is None else f"{row['J_over_clean']:9.2f}"
            print(f"{N:>3} {row['effect']:<30} {magnitude:<9} {seed:>4} {row['J']:9.2e} {ratio:>9}   "
                  f"{fi['displacement']:5.2f} {fi['pressure']:5.2f}            {fv['displacement']:5.2f} "
                  f"{fv['pressure']:5.2f}", flush=True)
    out = dict(points=POINTS, noise=0.01, rows=rows,
               note="free run: RMS misfit / the record's noise level (4th differences); J: the TPBVP objective")
    Path(args.out).write_text(json.dumps(json_ready(out), indent=1))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
