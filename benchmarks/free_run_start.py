"""The free run's start on the independent rig (:mod:`benchmarks.independent.rig`): how far the
library's ``"rest"`` start moves a free run, and what the diagnosis answers from the true start.

Every free run of the diagnosis on a mechanical record — the output-error fits that weigh
look-alikes, the costs they are weighed by — starts from the library's ``initial_state``;
``"rest"`` is the measured states' mean over the record's first five samples, the others zero
(:func:`shootlab.diagnosis.shrinkage.free_run_start`).  On a noisy record that start is off by about
σ/√5 in each position (σ the channel's noise), and the two encoders' errors preload the spring.

1. **The start's reach**: the rig itself (its own laws, noise-free) integrated from that start
   and from its true one (rest at 0); the largest and the last difference of each encoder over the
   record, in units of the record's noise level, and the cost Σ(Δ/σ)² the start alone adds — to
   be read against the ~1,000 that the noise gives each encoder.  Friction holds what the start
   puts in: the difference does not decay.
2. **The diagnosis from the true start**: the records named (by default the mechanical records
   the benchmark misses) diagnosed as ``benchmarks/diagnosis.py`` does, with the library's start
   replaced by the rig's true one — an oracle no user has, measuring what a start estimated from
   the data could recover at most — beside the cached answer from the ``"rest"`` start
   (``benchmarks/results/diagnosis_cases``).

    python benchmarks/free_run_start.py [--jobs 2] [--cases stribeck_m1:2 ...] [--out ...]

Minutes: part 2 runs a diagnosis per record (1–3 min each).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.independent import rig  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "free_run_start.json"
CASES = ROOT / "benchmarks" / "results" / "diagnosis_cases"

#: part 1's records: the clean rig and every friction effect
REACH_EFFECTS = (None, "coulomb_m1", "stribeck_m1", "viscous_m1", "coulomb_m2", "stribeck_m2", "viscous_m2")
#: part 2's default records: the independent rig's mechanical records the benchmark misses
MISSES = ("coulomb_m1:3", "stribeck_m1:2", "stribeck_m1:3", "stribeck_m1:4", "stribeck_m2:3", "stribeck_m2:4",
          "coulomb_m2:4", "viscous_m2:3")


def reach(effect: str | None, seed: int) -> list[dict]:
    """Part 1 on the records of ``effect`` (moderate, 1 % noise, ``seed``)."""
    from benchmarks.diagnosis import mechanical_setup, independent_mechanical_data
    from shootlab.diagnosis.shrinkage import free_run_start
    from shootlab.estimation.data import noise_level

    model, library, _ = mechanical_setup()
    ident, valid, _ = independent_mechanical_data(effect, "moderate", 0.01, seed)
    eff = {} if effect is None else {effect: rig.effect_parameters(effect, "moderate")}
    order = ("s1", "s2", "v1", "v2")                               # the rig's state vector
    rows = []
    for name, rec in (("identification", ident), ("validation", valid)):
        sigma = noise_level(rec, ["s1", "s2"])
        x0 = dict(zip(model.states, free_run_start(model, rec, library.initial_state)))
        u = rec.channels["u"]
        true = rig.integrate(eff, rec.t, u)
        rest = rig.integrate(eff, rec.t, u, start=[x0.get(s, 0.0) for s in order])
        row = dict(effect=effect or "none", seed=seed, record=name)
        for j, ch in enumerate(("s1", "s2")):
            d = (rest[:, j] - true[:, j]) / sigma[ch]
            row[ch] = dict(start=float(d[0]), largest=float(np.max(np.abs(d))), last=float(d[-1]),
                           cost=float(np.sum(d * d)))
        rows.append(row)
    return rows


def _true_start(model, data):
    """The rig's records start at rest at 0 (:func:`benchmarks.independent.rig.integrate`)."""
    return [0.0] * len(model.states)


def oracle(case: str) -> dict:
    """Part 2 on one record ``effect:seed``."""
    from benchmarks.diagnosis import answer_of, mechanical_setup, independent_mechanical_data
    from shootlab.diagnosis import diagnose

    effect, seed = case.split(":")
    seed = int(seed)
    model, library, _ = mechanical_setup()
    library.initial_state = _true_start
    ident, valid, info = independent_mechanical_data(effect, "moderate", 0.01, seed)
    clock = time.perf_counter()
    d = diagnose(model, ident, library, validation=valid, seed=seed, progress=False)
    inherent = info.get("inherent") or {}
    out = dict(effect=effect, seed=seed, answer=answer_of(list(d.selected), d.status.value, inherent),
               selected=list(d.selected), confidence=d.confidence, status=d.status.value,
               seconds=time.perf_counter() - clock)
    cached = CASES / f"independent__mechanical__{effect}__moderate__0.01__{seed}.json"
    if cached.exists():
        rec = json.loads(cached.read_text())
        out["rest"] = dict(answer=rec["answer"], confidence=rec.get("answer_confidence"))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=list(MISSES), help="part 2's records, effect:seed")
    ap.add_argument("--seeds", nargs="*", type=int, default=[1, 2, 3, 4], help="part 1's noise seeds")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    clock = time.perf_counter()
    rows = [r for e in REACH_EFFECTS for s in a.seeds for r in reach(e, s)]
    for r in rows:
        print(f"reach: {r['effect']:<12} seed {r['seed']} {r['record']:<14} "
              + "  ".join(f"{c}: start {r[c]['start']:+.2f}, largest {r[c]['largest']:.2f}, last {r[c]['last']:+.2f}, "
                          f"cost {r[c]['cost']:.0f}" for c in ("s1", "s2")), flush=True)
    with ProcessPoolExecutor(max_workers=max(a.jobs, 1)) as pool:
        answers = list(pool.map(oracle, a.cases))
    for o in answers:
        was = o.get("rest") or {}
        print(f"oracle: {o['effect']}:{o['seed']} from the true start {o['answer']} ({o['confidence']}), "
              f"from rest {was.get('answer')} ({was.get('confidence')})", flush=True)
    result = dict(reach=rows, oracle=answers, seconds=time.perf_counter() - clock)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {a.out} ({result['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
