"""Coulomb against Stribeck friction on the independent rig (:mod:`benchmarks.independent.rig`):
what the records can tell, what the library's laws can represent, and what the TPBVP estimates.

1. **The rig's own laws** (:func:`benchmarks.independent.rig.law_twin`): each friction record
   (moderate size) refitted, noise-free, by the other law with every parameter free (and m2, k,
   b): ΔJ in units of the records' 1 % noise on the identification record and on the validation
   record's free run — the records' power to tell the two laws apart.
2. **The library's laws, by output error**, as the diagnosis weighs them
   (:func:`shootlab.diagnosis.nested.nested_fits` and :func:`~shootlab.diagnosis.nested.weigh_fits`):
   on the noisy records of one seed, the nominal model, ``coulomb_mi + input_delay`` and
   ``stribeck_mi + input_delay`` (from each of Stribeck's embeddings of the Coulomb fit in turn,
   constrained to its bounds, until one converges at or below the Coulomb fit's cost) fitted to
   the identification record; their free-run costs Σ((y − z)/σ)² on both records (σ each
   record's noise level) and z = (ΔC − Δk)/se, the costs' difference summed over the records less
   the extra parameters, over its standard error (the residuals' autocorrelation counted).
3. **The TPBVP from the output-error solution**: ``stribeck_mi + input_delay`` estimated as the
   diagnosis does (the library's weight-continuation estimator, its give-up limits), started
   from the output-error fit's parameters.

    python benchmarks/friction_laws.py [--seed 1] [--out benchmarks/results/friction_laws.json]

Minutes: the Stribeck law's free runs on the load are stiff (a hump 0.02 rad/s wide).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.independent import rig  # noqa: E402
from shootlab.diagnosis.composition import extend  # noqa: E402
from shootlab.diagnosis.design import free_run_cost  # noqa: E402
from shootlab.diagnosis.estimators import giving_up  # noqa: E402
from shootlab.diagnosis.free_run_screen import output_error_fit  # noqa: E402
from shootlab.diagnosis.nested import nested_fits, weigh_fits  # noqa: E402
from shootlab.estimation.data import noise_level  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "friction_laws.json"


def laws_of_the_rig() -> list[dict]:
    """Part 1: each friction record refitted by the other law, and by the nominal rig."""
    rows = []
    for mass in (1, 2):
        c, s = f"coulomb_m{mass}", f"stribeck_m{mass}"
        for effect, twin in ((s, c), (c, s), (s, None), (c, None)):
            rows.append(rig.law_twin(effect, twin))
            print(f"rig laws: {effect} refitted by {twin or 'the nominal rig'}: ΔJ {rows[-1]['dJ_identification']:.4g} "
                  f"(identification), {rows[-1]['dJ_validation']:.4g} (validation)", flush=True)
    return rows


def laws_of_the_library(effect: str, seed: int) -> dict:
    """Parts 2 and 3 on the records of ``effect`` (moderate, 1 % noise, ``seed``)."""
    from benchmarks.diagnosis import mechanical_setup

    model, library, _ = mechanical_setup()
    data, validation, _ = rig.data(effect, "moderate", 0.01, seed)
    how = library.initial_state
    chans = [c for c in model.measured if c not in model.given]
    sigma = [noise_level(data, chans), noise_level(validation, chans)]
    mass = effect[-1]
    simple, rich = [f"coulomb_m{mass}", "input_delay"], [f"stribeck_m{mass}", "input_delay"]

    def say(line: str) -> None:
        print(f"library laws, {effect} seed {seed}:{line}", flush=True)
    nominal = output_error_fit(model, data, dict(model.prior), how)
    costs = [free_run_cost(model, [], rec, nominal.parameters, how, sg)[0] for rec, sg in zip((data, validation), sigma)]
    say(f"  the nominal model by output error: costs {costs[0]:.5g} / {costs[1]:.5g}")
    fits = nested_fits(model, library, simple, dict(nominal.parameters, **{f"coulomb{mass}_f": 1.0, "input_delay": 1e-3}),
                       rich, None, data, say)
    weighed = weigh_fits(model, library, simple, rich, fits, data, validation, *sigma, say)
    out = dict(effect=effect, seed=seed, nominal=costs, coulomb=dict(success=bool(fits["simple"].success),
                                                                     parameters=dict(fits["simple"].parameters)),
               tries=fits["tries"], weighed=None if weighed is None else {k: v for k, v in weighed.items()
                                                                            if k != "tries"})
    if weighed is None:
        return out
    effects = [library[e] for e in rich]
    ext = extend(model, effects, data=data)
    clock = time.perf_counter()
    res = library.estimator(ext, data, initial=dict(weighed["parameters"]), **giving_up(ext, library.estimator))
    out["tpbvp_from_output_error"] = dict(success=bool(res.success), message=res.message, J=float(res.J),
                                          seconds=time.perf_counter() - clock)
    say("  the TPBVP from the output-error solution: " + (f"J = {res.J:.5g}" if res.success else res.message))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    clock = time.perf_counter()
    result = dict(rig_laws=laws_of_the_rig(),
                  library_laws=[laws_of_the_library(e, a.seed) for e in ("stribeck_m1", "coulomb_m1",
                                                                          "stribeck_m2", "coulomb_m2")])
    result["seconds"] = time.perf_counter() - clock
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1, default=lambda v: float(v) if isinstance(v, np.floating) else str(v)))
    print(f"wrote {a.out} ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
