"""Withheld-effect benchmark of :mod:`shootlab.diagnosis` (docs/design.md §4).

For every effect of the two candidate libraries — mechanical (:mod:`manipulators.effects`, data
from :mod:`manipulators.rig_effects`) and mixture (:mod:`mixtures.effects`) — records are generated
*with* that effect at a few magnitudes and noise levels, with one input for identification and a
different one for validation, and diagnosed with the nominal model that withholds it; records
without any effect ("clean") check the "no significant structural error" answer.

Nominal models.  Mechanical: the report's plain flexible model (:func:`manipulators.flexible.plain_model`)
with the end-effector inertia m1 known (prior W_a = 1e6 at the rig's 5.40): without one known
parameter an actuator gain error is absorbed exactly by the per-unit-c parameters and no method
can see it (see :mod:`manipulators.effects`).  Estimated by weight continuation with the encoder
weights capped at 1/σ̂².  Identification input: the 1 s sine sweep 4 → 14 Hz; validation: the
command of a PD controller on the ideal rig, replayed open loop.  Mixture: the report's 3-element
confined-compression model (:func:`mixtures.identification.model`, 401 points, tolerance
continuation); identification: ramp and hold; validation: load, partial unload, higher reload.

Magnitudes: the "moderate" one is about 5 % of the command's RMS for the mechanical effects
(:func:`manipulators.rig_effects.relative_size`, recorded per case); noise: Gaussian,
a fraction of each measured channel's standard deviation (1 % = ``--noise 0.01``).

Scores:
* the *answer* is the first selected effect, or "none" when nothing is selected; top-1 accuracy is
  the fraction of effect cases whose answer is the withheld effect (also reported: the first of
  the ranking, which ignores the significance test and the selection);
* clean accuracy: the fraction of clean cases answered "none";
* validation shrink: 1 − after/before of the free-run misfit on the validation record, averaged
  over the cases where the withheld effect was selected.

Simulators (``--simulators``): ``ours`` (the packages' generators above) and ``independent``
(:mod:`benchmarks.independent`: written separately, with another integrator and discretisation,
noise model, magnitudes and inputs; the mixture diagnosed with the element count its records need).
Every score is reported per simulator, and a reliability table bins every verdict that names an
effect by the confidence it was given, with the fraction right.

Two families have independent records only (``--families duffing tanks``; the independent
simulator is then taken by default).  ``duffing`` (:mod:`benchmarks.independent.duffing`): a
Duffing oscillator shaped like the Silverbox benchmark — odd multisine identification, arrow-head
validation — with a DC offset of the force in every record (counted as inherent, as the rig's DAC
hold), diagnosed with the linear mass–spring–damper :func:`manipulators.msd.model` and its
mechanical library; the withheld effect is the cubic spring.  ``tanks``
(:mod:`benchmarks.independent.tanks`): cascaded tanks in SI units with the real record's sampling
and input spectrum, the sensor clipping at 10 V (clipped samples missing), diagnosed with
``examples/tanks.py``'s model and library; the withheld effects are the overflow, a sensor offset,
a pump dead zone and the two leaks.

Look-alike pairs (``--lookalikes``): the members of the pairs of the independent rig (Coulomb vs
Stribeck friction on the motor) and mixture (nonlinear solid vs strain-dependent permeability,
filter resistance vs machine compliance), each at the magnitude ``lookalike`` where refitting the
other member to its identification record leaves less than what 1 % noise resolves (the modules'
``LOOKALIKES``); the summary reports how often the other member (``partner``) was named.
``--experiment CSV`` re-simulates every case's system under the input in the CSV (``t`` and ``u``,
or ``load`` for the mixture: a discriminating experiment) and diagnoses that record too
(``experiment`` in the case's record: its answer and whether it is the withheld effect).

Writes ``benchmarks/results/diagnosis.json`` and ``diagnosis_confusion[_independent].png`` (true effect × answer);
every case is cached in ``benchmarks/results/diagnosis_cases/`` and reused with ``--resume``.

Run: ``python benchmarks/diagnosis.py --quick`` (moderate magnitude, 1 % noise, 3 clean records per family:
23 cases; ``--jobs 2`` runs them in two processes on a 2-core machine; the machine's speed moves, so
compare timings within one hour) or without
``--quick`` (small / moderate / large at 1 % noise, moderate at 0.3 %, 5 clean records per family and noise
level).  ``--simulators independent`` (or both), ``--magnitude large`` with ``--quick``,
``--families``/``--effects`` for a subset; ``--cached`` runs nothing and summarises every case cached in
``--out``, so that runs of different subsets (in parallel, or at different times) make one report;
``--resume --reverse`` beside a ``--resume`` run of the same plan works from its other end, so that two
processes share it (set ``OMP_NUM_THREADS=1`` for each: two torch processes with two threads each on two
cores thrash).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from shootlab.diagnosis import diagnose  # noqa: E402
from shootlab.diagnosis.outcome import Status  # noqa: E402
from shootlab.diagnosis.design import separable  # noqa: E402
from shootlab.outputs import fmt  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
CRITERIA = dict(top1=0.90, clean=0.90, shrink=0.50)


# -- the two families with records of our own ----------------------------------------------------------------
def mechanical_setup():
    from manipulators import effects as me
    from manipulators.flexible import plain_model
    from manipulators.rig_effects import NOMINAL

    model = plain_model(W_a=[1e5] * 4 + [1e6, 0.0, 0.0, 0.0], prior=dict(m1=NOMINAL["m1"]))
    return model, me.library(model), list(me.MECHANICAL_EFFECTS)


def mechanical_data(effect: str | None, magnitude: str, noise: float, seed: int):
    from manipulators.rig_effects import relative_size, simulate_effect_rig

    eff = {} if effect is None else {effect: magnitude}
    ident, ident_truth = simulate_effect_rig(eff, input="sweep", noise=noise, seed=seed)
    valid, valid_truth = simulate_effect_rig(eff, input="pd", noise=noise, seed=seed + 1000)
    return ident, valid, dict(relative_size=relative_size(ident, ident_truth),
                              relative_size_validation=relative_size(valid, valid_truth))


def mixture_setup():
    from mixtures import effects as xe
    from mixtures.identification import model as confined_model

    model = confined_model()
    return model, xe.library(model), list(xe.MIXTURE_EFFECTS)


def mixture_data(effect: str | None, magnitude: str, noise: float, seed: int):
    from mixtures.effects import simulate_mixture

    eff = {} if effect is None else {effect: magnitude}
    ident, truth = simulate_mixture(eff, load="identification", noise=noise, seed=seed)
    valid, _ = simulate_mixture(eff, load="validation", noise=noise, seed=seed + 1000)
    _, clean = simulate_mixture({}, load="identification", noise=0.0)
    size = {}
    for ch in ("load", "displacement", "pressure"):
        d = truth[f"measured_{ch}"] - clean[f"measured_{ch}"]
        size[ch] = float(np.sqrt(np.mean(d ** 2)) / np.std(clean[f"measured_{ch}"]))
    return ident, valid, dict(relative_change=size)


FAMILIES = {
    "mechanical": (mechanical_setup, mechanical_data),
    "mixture": (mixture_setup, mixture_data),
}


# -- the independently written simulators (benchmarks/independent/) ----------------------------------------
def independent_mechanical_data(effect: str | None, magnitude: str, noise: float, seed: int):
    from benchmarks.independent import rig
    return rig.data(effect, magnitude, noise, seed)


def independent_mixture_setup():
    from benchmarks.independent.mixture import NOMINAL_ELEMENTS
    from mixtures import effects as xe
    from mixtures.identification import model as confined_model

    model = confined_model(elements=NOMINAL_ELEMENTS)
    return model, xe.library(model), list(xe.MIXTURE_EFFECTS)


def independent_mixture_data(effect: str | None, magnitude: str, noise: float, seed: int):
    from benchmarks.independent import mixture
    return mixture.data(effect, magnitude, noise, seed)


def independent_duffing_setup():
    from benchmarks.independent import duffing
    from manipulators import effects as me
    from manipulators.msd import model as msd

    model = msd()
    return model, me.library(model), list(duffing.EFFECTS)


def independent_duffing_data(effect: str | None, magnitude: str, noise: float, seed: int):
    from benchmarks.independent import duffing
    return duffing.data(effect, magnitude, noise, seed)


def tanks_example():
    """``examples/tanks.py`` (not a package): its model and library."""
    import importlib.util

    name = "shootlab_examples_tanks"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / "tanks.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def independent_tanks_setup():
    from benchmarks.independent import tanks

    example = tanks_example()
    return example.model, example.library, list(tanks.EFFECTS)


def independent_tanks_data(effect: str | None, magnitude: str, noise: float, seed: int):
    from benchmarks.independent import tanks
    return tanks.data(effect, magnitude, noise, seed)


#: simulator → family → (setup, data): ours (the packages' own generators) and the independently
#: written ones (another integrator and discretisation, noise model, magnitudes and inputs); the
#: Duffing oscillator and the cascaded tanks have only independent records
SIMULATORS = {
    "ours": FAMILIES,
    "independent": {"mechanical": (mechanical_setup, independent_mechanical_data),
                    "mixture": (independent_mixture_setup, independent_mixture_data),
                    "duffing": (independent_duffing_setup, independent_duffing_data),
                    "tanks": (independent_tanks_setup, independent_tanks_data)},
}

#: every family, in the order of the help text
ALL_FAMILIES = list(dict.fromkeys(f for fams in SIMULATORS.values() for f in fams))

#: family → the module of :mod:`benchmarks.independent` whose ``simulate`` re-runs a case's system
#: under a new input and whose ``LOOKALIKES`` (where it has them) are the look-alike pairs
INDEPENDENT_MODULES = {"mechanical": "rig", "mixture": "mixture", "duffing": "duffing", "tanks": "tanks"}


def independent_module(family: str):
    import importlib
    return importlib.import_module(f"benchmarks.independent.{INDEPENDENT_MODULES[family]}")


# -- a new input for a case's system (a discriminating experiment) ----------------------------------------
def read_input(path: str | Path, family: str) -> tuple[np.ndarray, np.ndarray]:
    """The input of an experiment from a CSV with the columns ``t`` and the family's input channel
    (``u``; ``load`` for the mixture, where ``u`` is read too).  ValueError naming the file and the
    columns it has when the input column is missing."""
    from shootlab.estimation.data import Measurements

    name = independent_module(family).INPUT
    rec = Measurements.from_csv(path)
    for col in dict.fromkeys([name, "u"]):
        if col in rec.channels:
            u = rec.channels[col]
            bad = np.nonzero(np.isnan(u))[0]
            if bad.size:
                raise ValueError(f"{path}: column {col!r} has no value at t = {rec.t[bad[0]]:g} (row {int(bad[0]) + 2})")
            return rec.t, u
    raise ValueError(f"{path}: no input column {name!r} for the {family} family; the file has t, "
                     f"{', '.join(rec.channels) or 'no numeric column'}")


def experiment_record(case: tuple, input_t, input_u):
    """The record of a case's system — the same effect and magnitude, the same noise level, the
    noise seed ``seed + 2000`` — under a new input (``simulate`` of the family's independent
    simulator); only the independent simulator re-simulates."""
    sim, fam, eff, mag, noise, seed = case
    if sim != "independent":
        raise ValueError(f"case {case_id(fam, eff, mag, noise, seed, sim)}: only the independent simulator "
                         f"re-simulates a system under a new input (--simulators independent)")
    return independent_module(fam).simulate(eff, mag, input_t, input_u, noise, seed + 2000)


def run_experiment(case: tuple, path: str | Path, setups: dict, proposed: dict | None = None) -> dict:
    """Diagnose the case's system simulated under the input in ``path`` (:func:`experiment_record`;
    the case's validation record validates): does the record of the proposed experiment select the
    withheld effect — for a look-alike pair, the right member?  With ``proposed`` (the input the
    case's own diagnosis proposed, ``experiment_input`` of its record: ``t`` and ``values``) the
    feed-back of ``shootlab diagnose … --design``: the identification record again, the
    experiment's record as the validation record."""
    sim, fam, eff, mag, noise, seed = case
    model, library, _ = setups[sim, fam]
    ident, valid, _ = SIMULATORS[sim][fam][1](eff, mag, noise, seed)
    if proposed is not None:
        name = independent_module(fam).INPUT
        u = proposed["values"].get(name, proposed["values"].get("u"))
        record = experiment_record(case, np.asarray(proposed["t"]), np.asarray(u))
        data, valid = ident, record
    else:
        data = experiment_record(case, *read_input(path, fam))
    t0 = time.perf_counter()
    out = dict(input=str(path))
    try:
        info = diagnose(model, data, library, validation=valid, seed=seed).to_dict()
    except Exception as exc:  # noqa: BLE001 - a failed case is a result of the benchmark
        out.update(answer="error", error=f"{type(exc).__name__}: {exc}")
    else:
        out.update(answer=answer_of(info["selected"], info.get("status"), independent_inherent(case)),
                   selected=info["selected"], status=info.get("status"), confidence=info["confidence"],
                   verdict=info["verdict"], lookalikes=info.get("lookalikes"),
                   ranking=[dict(effect=r["effect"], confidence=r["confidence"]) for r in info["ranking"][:5]])
    out.update(right=out["answer"] == (eff or "none"), seconds=time.perf_counter() - t0)
    return out


def independent_inherent(case: tuple) -> dict:
    """The effects the case's simulator puts in every record (``inherent`` of its info)."""
    sim, fam, eff, mag, noise, seed = case
    return SIMULATORS[sim][fam][1](eff, mag, noise, seed)[2].get("inherent", {}) if sim == "independent" else {}


# -- one case ---------------------------------------------------------------------------------------------
def case_id(family, effect, magnitude, noise, seed, simulator: str = "ours"):
    prefix = "" if simulator == "ours" else f"{simulator}__"
    return f"{prefix}{family}__{effect or 'none'}__{magnitude}__{noise:g}__{seed}"


def case_file(cache: Path, case: tuple) -> Path:
    """Where a case of the plan, ``(simulator, family, effect, magnitude, noise, seed)``, is cached."""
    sim, *rest = case
    return Path(cache) / f"{case_id(*rest, sim)}.json"


def confidence_of(selected: list, ranking: list[dict]) -> float | None:
    """The confidence the ranking gave the first selected effect (None when nothing is selected)."""
    return next((r["confidence"] for r in ranking if r["effect"] == selected[0]), None) if selected else None


def cached(path: Path) -> dict:
    """A case from the cache, with the fields later versions of this script add filled in."""
    rec = json.loads(path.read_text())
    rec.setdefault("simulator", "ours")
    if rec["answer"] != "error":      # cached before the answer named numerical / inconclusive
        rec["answer"] = answer_of(rec.get("selected") or [], rec.get("status"), rec.get("inherent") or {})
        rec.setdefault("answer_confidence", confidence_of(rec.get("selected") or [], rec.get("ranking") or []))
    return rec


def names_inherent(rec: dict) -> bool:
    """Whether the answer is an effect the simulator puts in every record (``inherent``: the DAC's
    half-sample hold of the independent rig), estimated within a factor 2 of its true value: then
    a "clean" record's answer is right, not a false alarm."""
    true = (rec.get("inherent") or {}).get(rec["answer"])
    est = rec.get("extended_parameters") or {}
    return bool(true) and rec.get("extended_success") is True and all(
        p in est and 0.5 * v <= est[p] <= 2.0 * v for p, v in true.items())


def answer_of(selected: list, status: str | None, inherent=()) -> str:
    """The case's answer: the first selected effect that is not one the simulator puts in every
    record (``inherent``; a pair of the withheld effect and the independent rig's half-sample hold
    answers the withheld effect), else the first selected, else ``numerical`` / ``inconclusive``
    when the diagnosis says so, else ``none`` (no significant structural error, or unexplained)."""
    if selected:
        return next((e for e in selected if e not in inherent), selected[0])
    return Status(status).value if status in (Status.NUMERICAL, Status.INCONCLUSIVE) else "none"


def run_case(family: str, effect: str | None, magnitude: str, noise: float, seed: int, setups: dict,
             simulator: str = "ours") -> dict:
    model, library, _ = setups[simulator, family]
    ident, valid, size = SIMULATORS[simulator][family][1](effect, magnitude, noise, seed)
    t0 = time.perf_counter()
    rec = dict(simulator=simulator, family=family, effect=effect or "none", magnitude=magnitude if effect else "-",
               noise=noise, seed=seed, **{k: v for k, v in size.items() if k in ("relative_size", "relative_change",
                                                                                  "relative_size_validation")})
    rec.update({k: size[k] for k in ("pair", "partner") if k in size})      # a member of a look-alike pair
    rec["simulator_info"] = {k: v for k, v in size.items() if k not in rec}
    rec["inherent"] = size.get("inherent", {})
    try:
        d = diagnose(model, ident, library, validation=valid, seed=seed, progress=False)
    except Exception as exc:  # noqa: BLE001 - a failed case is a result of the benchmark
        rec.update(error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc(limit=3),
                   answer="error", top1_ranking=None, seconds=time.perf_counter() - t0)
        return rec
    info = d.to_dict()
    told = d.discrimination or {}
    ex = told.get("experiment")
    if ex is None and told.get("propose") is not None and rec.get("pair"):
        ex = told["propose"]()           # a look-alike pair's member: the experiment against the nearest rival
    if ex is not None and separable(ex):        # the proposed experiment's input, for --experiment proposed
        rec["experiment_input"] = dict(t=ex["t"].tolist(), values={c: v.tolist() for c, v in ex["values"].items()},
                                       label=ex["input"]["label"], separation=ex["separation"],
                                       separation_identification=ex["separation_identification"],
                                       measure=ex.get("measure"), between=ex["between"],
                                       lookalikes=bool(told.get("experiment")))
    rec["lookalikes"] = info.get("lookalikes")
    ranking = info["ranking"]
    sh = info.get("shrink") or {}
    val = sh.get("validation") or {}
    idn = sh.get("identification") or {}
    fr = info.get("free_run") or {}           # the free-run screen (shootlab/diagnosis/free_run_screen.py)
    rec.update(
        answer=answer_of(info["selected"], info.get("status"), rec["inherent"]), selected=info["selected"],
        significant=info["significant"], verdict=info["verdict"], status=info.get("status"),
        top1_ranking=ranking[0]["effect"] if ranking else None,
        top1_confidence=ranking[0]["confidence"] if ranking else None,
        answer_confidence=info["confidence"],
        free_run=(dict(model=fr.get("model"), verdict=fr.get("verdict"), refinements=fr.get("refinements"),
                       candidates={c["effect"]: c.get("validation_shrink") for c in fr.get("candidates", [])})
                  if fr else None),
        true_rank=next((i + 1 for i, r in enumerate(ranking) if r["effect"] == effect), None),
        true_confidence=next((r["confidence"] for r in ranking if r["effect"] == effect), None),
        true_parameters=next((r["parameters"] for r in ranking if r["effect"] == effect), None),
        ranking=[dict(effect=r["effect"], score=r["score"], confidence=r["confidence"]) for r in ranking[:5]],
        where=[dict(equation=w["equation"], share=w["share"], ratio=w.get("ratio"), significant=w["significant"])
               for w in info["where"] if w["significant"] or w["kind"] != "dynamics"],
        evidence=({k: info["evidence"].get(k) for k in ("measure", "misfit", "floor_misfit", "ratio", "p_value",
                                                         "significant")} if info.get("evidence") else None),
        J_before=info["nominal"]["J"], J_after=(info["extended"] or {}).get("J"),
        J_floor=(info["floor"] or {}).get("J"),
        extended_parameters=(info["extended"] or {}).get("parameters"),
        extended_success=(info["extended"] or {}).get("success"),
        validation_before=val.get("before"), validation_after=val.get("after"), validation_shrink=val.get("shrink"),
        validation_shrink_above_noise=val.get("shrink_above_noise"),
        validation_per_channel=val.get("per_channel"), identification_shrink=idn.get("shrink"),
        seconds=time.perf_counter() - t0, timing=info.get("seconds"), notes=info.get("notes"))
    return rec


# -- summary and figure --------------------------------------------------------------------------------------
def _clean_right(r: dict) -> bool:
    """A clean record is answered right by "none", by "numerical" (no effect; the model's own
    discretisation misses the record: the 6-element model on the independent mixture's 120 cells),
    or by an effect the simulator always contains."""
    return r["answer"] in ("none", "numerical") or names_inherent(r)


def _false_alarms(clean: list[dict]) -> int:
    """Clean records answered with an effect the simulator does not put in every record."""
    return sum(not _clean_right(r) and r["answer"] not in ("inconclusive", "numerical") for r in clean)


def held_out(r: dict) -> bool:
    """A case of records no default run makes (``--seed`` other than 1): the diagnosis was not
    developed on them."""
    return r["seed"] not in (1, *range(100, 105))


def summarize(records: list[dict]) -> dict:
    out = {}
    for fam in sorted({r["family"] for r in records}):
        rs = [r for r in records if r["family"] == fam]
        groups: dict = {}
        for r in rs:
            groups.setdefault((r["magnitude"], r["noise"], held_out(r)), []).append(r)
        fam_out = {}
        for (mag, noise, other), g in sorted(groups.items(), key=lambda kv: (str(kv[0][0]), kv[0][1], kv[0][2])):
            eff = [r for r in g if r["effect"] != "none"]
            key = f"{'clean' if mag == '-' else mag} @ noise {noise:g}" + (", held-out seeds" if other else "")
            if eff:
                shr = [r["validation_shrink"] for r in eff if r["answer"] == r["effect"] and r.get("validation_shrink") is not None]
                fam_out[key] = dict(
                    cases=len(eff), top1=float(np.mean([r["answer"] == r["effect"] for r in eff])),
                    top1_ranking=float(np.mean([r["top1_ranking"] == r["effect"] for r in eff])),
                    detected=float(np.mean([bool(r.get("significant")) or r["answer"] not in ("none", "error")
                                            for r in eff])),       # by the TPBVP's test or the free run
                    mean_validation_shrink=float(np.mean(shr)) if shr else None,
                    per_effect={r["effect"]: dict(answer=r["answer"], confidence=r.get("true_confidence"),
                                                  shrink=r.get("validation_shrink"), rank=r.get("true_rank"))
                                for r in eff})
                paired = [r for r in eff if r.get("partner")]
                if paired:        # look-alike pairs: how often the other member was named
                    fam_out[key]["answered_partner"] = float(np.mean([r["answer"] == r["partner"] for r in paired]))
                tried = [r for r in eff if r.get("experiment")]
                if tried:         # the records simulated under a proposed experiment
                    fam_out[key]["experiment_right"] = float(np.mean([r["experiment"]["right"] for r in tried]))
            else:
                fam_out[key] = dict(cases=len(g), clean_accuracy=float(np.mean([_clean_right(r) for r in g])),
                                    answers=[r["answer"] + (" (inherent)" if names_inherent(r) else "") for r in g])
        out[fam] = fam_out
    # the issue's criteria: moderate magnitude at 1 % noise, over both libraries
    mod = [r for r in records if r["magnitude"] == "moderate" and abs(r["noise"] - 0.01) < 1e-12]
    clean = [r for r in records if r["effect"] == "none"]
    shr = [r["validation_shrink"] for r in mod if r["answer"] == r["effect"] and r.get("validation_shrink") is not None]
    shr_n = [r["validation_shrink_above_noise"] for r in mod
             if r["answer"] == r["effect"] and r.get("validation_shrink_above_noise") is not None]
    crit = dict(
        top1_moderate_1pct=float(np.mean([r["answer"] == r["effect"] for r in mod])) if mod else None,
        top1_ranking_moderate_1pct=float(np.mean([r["top1_ranking"] == r["effect"] for r in mod])) if mod else None,
        clean_accuracy=float(np.mean([_clean_right(r) for r in clean])) if clean else None,
        mean_validation_shrink_moderate_1pct=float(np.mean(shr)) if shr else None,
        mean_validation_shrink_above_noise_moderate_1pct=float(np.mean(shr_n)) if shr_n else None,
        cases_moderate_1pct=len(mod), clean_cases=len(clean))
    verdicts = [r for r in records if r["answer"] not in ("none", "numerical", "inconclusive", "error")]
    crit["false_alarms"] = _false_alarms(clean)
    crit["verdicts_whose_validation_shrinks"] = (float(np.mean([(r.get("validation_shrink") or 0) > 0 for r in verdicts]))
                                                 if verdicts else None)
    mod_h, clean_h = [r for r in mod if held_out(r)], [r for r in clean if held_out(r)]
    if mod_h or clean_h:        # the same figures on the held-out seeds alone
        crit["held_out"] = dict(
            top1_moderate_1pct=float(np.mean([r["answer"] == r["effect"] for r in mod_h])) if mod_h else None,
            cases_moderate_1pct=len(mod_h), clean_cases=len(clean_h),
            false_alarms=_false_alarms(clean_h), seeds=sorted({r["seed"] for r in mod_h}))
    crit["met"] = dict(top1=(crit["top1_moderate_1pct"] or 0) >= CRITERIA["top1"],
                       clean=(crit["clean_accuracy"] or 0) >= CRITERIA["clean"],
                       shrink=(crit["mean_validation_shrink_moderate_1pct"] or 0) >= CRITERIA["shrink"])
    out["criteria"] = crit
    return out


#: confidence bins of the reliability table
CONFIDENCE_BINS = (0.9, 0.7, 0.5, 0.0)


def _shown_confidence(r: dict) -> float | None:
    """The table's confidence: the one the verdict was given with when it names an effect, else the
    TPBVP ranking's for the withheld effect (its top candidate's on a clean record)."""
    if r.get("answer_confidence") is not None:
        return r["answer_confidence"]
    return r.get("true_confidence") if r["effect"] != "none" else r.get("top1_confidence")


def reliability(records: list[dict]) -> list[dict]:
    """Does the confidence mean what it says?  Every verdict that names an effect, binned by the
    confidence it was given, with the fraction of them that are right: they name the withheld
    effect, or only an effect the simulator puts in every record (:func:`names_inherent`); on a clean
    record any other named effect is wrong."""
    rows, upper = [], 1.0
    verdicts = [r for r in records if r.get("answer_confidence") is not None]
    for low in CONFIDENCE_BINS:
        # a confidence from normalised weights may exceed 1 by rounding (1.0000000000000002): the top bin
        inside = [r for r in verdicts if low <= r["answer_confidence"] < upper or upper == 1.0 <= r["answer_confidence"]]
        # a verdict that names only the simulator's own effect (the rig's hold, estimated within a factor 2)
        # names an effect the record has: right here, though the withheld effect is not named
        right = sum(r["answer"] == r["effect"] or names_inherent(r) for r in inside)
        rows.append(dict(confidence=f"[{low:.1f}, {upper:.1f}{']' if upper == 1.0 else ')'}", verdicts=len(inside),
                         right=right, fraction_right=right / len(inside) if inside else None))
        upper = low
    return rows


def reliability_text(rows: list[dict]) -> str:
    L = [f"{'confidence':<12} {'verdicts':>8} {'right':>6} {'fraction':>8}"]
    for r in rows:
        L.append(f"{r['confidence']:<12} {r['verdicts']:>8} {r['right']:>6} {fmt(r['fraction_right'], '.0%'):>8}")
    return "\n".join(L)


def confusion_figure(records: list[dict], path: Path, title: str = "all cases") -> dict:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    truths = list(dict.fromkeys([r["effect"] for r in records if r["effect"] != "none"])) + ["none"]
    answers = list(dict.fromkeys(truths + [r["answer"] for r in records]))
    M = np.zeros((len(truths), len(answers)), dtype=int)
    for r in records:
        M[truths.index(r["effect"]), answers.index(r["answer"])] += 1
    fig, ax = plt.subplots(figsize=(0.45 * len(answers) + 3, 0.4 * len(truths) + 2.5))
    frac = M / np.maximum(M.sum(1, keepdims=True), 1)
    ax.imshow(frac, cmap="Blues", vmin=0, vmax=1)
    for i in range(len(truths)):
        for j in range(len(answers)):
            if M[i, j]:
                ax.text(j, i, str(M[i, j]), ha="center", va="center", fontsize=7,
                        color="white" if frac[i, j] > 0.6 else "black")
    ax.set_xticks(range(len(answers)))
    ax.set_xticklabels(answers, rotation=70, ha="right", fontsize=7)
    ax.set_yticks(range(len(truths)))
    ax.set_yticklabels(truths, fontsize=7)
    ax.set_xlabel("answer (first selected effect; none = no significant structural error / unexplained)")
    ax.set_ylabel("withheld effect in the data")
    ax.set_title(f"diagnosis benchmark: confusion matrix ({title})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return dict(truths=truths, answers=answers, counts=M.tolist())


def table(records: list[dict]) -> str:
    L = [f"{'sim':<5} {'family':<11} {'effect':<30} {'mag':<9} {'noise':>6} {'size':>6} {'answer':<30} {'conf':>5} "
         f"{'val before':>10} {'after':>9} {'shrink':>7} {'>noise':>7} {'sec':>5}"]
    for r in records:
        size = r.get("relative_size")
        if size is None and r.get("relative_change"):
            size = max(r["relative_change"].values())
        L.append(f"{r.get('simulator', 'ours')[:5]:<5} {r['family']:<11} {r['effect']:<30} {r['magnitude']:<9} {r['noise']:>6g} "
                 f"{(format(100 * size, '.1f') + '%') if size is not None else '-':>6} "
                 f"{r['answer'] + ('' if r['answer'] == r['effect'] else ' ✗'):<30} "
                 f"{fmt(_shown_confidence(r), '.2f'):>5} "
                 f"{fmt(r.get('validation_before')):>10} {fmt(r.get('validation_after')):>9} "
                 f"{fmt(r.get('validation_shrink'), '.2f'):>7} {fmt(r.get('validation_shrink_above_noise'), '.2f'):>7} "
                 f"{r.get('seconds', 0):5.0f}")
    return "\n".join(L)


# -- main --------------------------------------------------------------------------------------------------
#: family → where its list of effects is (the withheld effects of its records)
FAMILY_EFFECTS = {"mechanical": "manipulators.effects:MECHANICAL_EFFECTS", "mixture": "mixtures.effects:MIXTURE_EFFECTS",
                  "duffing": "benchmarks.independent.duffing:EFFECTS", "tanks": "benchmarks.independent.tanks:EFFECTS"}


def simulators_for(families, simulators=None) -> list[tuple[str, str]]:
    """The (simulator, family) pairs a run covers: each requested simulator's families among
    ``families``; with ``simulators`` None, each family's own generator ("ours") where it has one,
    else the independent simulator (duffing, tanks).  ValueError for a family no requested
    simulator has."""
    if simulators is None:
        return [("ours" if fam in SIMULATORS["ours"] else "independent", fam) for fam in families]
    pairs = [(sim, fam) for sim in simulators for fam in families if fam in SIMULATORS[sim]]
    for fam in families:
        if not any(f == fam for _, f in pairs):
            have = [sim for sim in SIMULATORS if fam in SIMULATORS[sim]]
            raise ValueError(f"family {fam!r} has no records from simulator(s) {', '.join(simulators)}: "
                             f"it has {', '.join(have)} (--simulators {' '.join(have)})")
    return pairs


def plan(quick: bool, families, effects_filter, simulators=("ours",), magnitude: str = "moderate",
         lookalikes: bool = False, seed: int = 1) -> list[tuple]:
    """The cases ``(simulator, family, effect, magnitude, noise, seed)`` of a run (module docstring);
    with ``lookalikes`` only the members of the look-alike pairs (:func:`lookalike_plan`).  ``seed``:
    the effect records' seed; the clean records' seeds start at ``100 + 10 (seed - 1)``, so that
    another ``seed`` gives records that no default run has seen."""
    if lookalikes:        # the pairs are the independent simulator's
        return lookalike_plan(simulators_for(families, simulators or ["independent"]), effects_filter, seed=seed)
    pairs = simulators_for(families, simulators)
    out = []
    for sim in dict.fromkeys(s for s, _ in pairs):
        fams = [f for s, f in pairs if s == sim]
        out += [(sim, *case) for case in _plan(quick, fams, effects_filter, magnitude, seed)]
    return out


def lookalike_plan(pairs, effects_filter=None, noise: float = 0.01, seed: int = 1) -> list[tuple]:
    """Each member of each look-alike pair of the independent simulator (``LOOKALIKES`` of
    :mod:`benchmarks.independent.rig` and :mod:`benchmarks.independent.mixture`: Coulomb vs
    Stribeck friction, nonlinear solid vs strain-dependent permeability, filter resistance vs
    machine compliance), at the magnitude where the two are look-alikes on the identification input
    ("lookalike"), 1 % noise.  Families without pairs (or other simulators) contribute nothing."""
    cases = []
    for sim, fam in pairs:
        table = getattr(independent_module(fam), "LOOKALIKES", {}) if sim == "independent" else {}
        for members in table.values():
            for e in members:
                if not effects_filter or e in effects_filter:
                    cases.append((sim, fam, e, "lookalike", noise, seed))
    return cases


def _plan(quick: bool, families, effects_filter, magnitude: str = "moderate", seed: int = 1):
    import importlib

    cases = []
    if quick:
        settings, clean = [(magnitude, 0.01)], [(0.01, 3)]
    else:
        settings = [("small", 0.01), ("moderate", 0.01), ("large", 0.01), ("moderate", 0.003)]
        clean = [(0.01, 5), (0.003, 5)]
    for fam in families:
        mod, attr = FAMILY_EFFECTS[fam].split(":")
        effs = list(getattr(importlib.import_module(mod), attr))
        for mag, noise in settings:
            for e in effs:
                if effects_filter and e not in effects_filter:
                    continue
                cases.append((fam, e, mag, noise, seed))
        if not effects_filter or "none" in effects_filter:
            for noise, n in clean:
                for k in range(n):
                    cases.append((fam, None, "-", noise, 100 + 10 * (seed - 1) + k))
    return cases


# -- cases in parallel processes (--jobs) -----------------------------------------------------------------------
_SETUPS: dict = {}


def _run_one(case: tuple, cache: str) -> tuple:
    """One case in a worker process (one thread): run, cache, return it."""
    import torch

    torch.set_num_threads(1)
    sim, fam, eff, mag, noise, seed = case
    if (sim, fam) not in _SETUPS:
        _SETUPS[sim, fam] = SIMULATORS[sim][fam][0]()
    rec = run_case(fam, eff, mag, noise, seed, _SETUPS, sim)
    case_file(cache, case).write_text(json.dumps(rec, indent=1, default=float))
    return case


def _expected_seconds(cases: list[tuple], cache: Path) -> list[float]:
    """Each case's time in the cache (an earlier run) — in ``cache``, else in the cases shipped in
    ``benchmarks/results`` (a run into a new folder is ordered too; it had kept the plan's order) —
    else the mean of its family's cached cases."""
    shipped, seen = RESULTS / "diagnosis_cases", {}
    for c in cases:
        f = next((f for f in (case_file(cache, c), case_file(shipped, c)) if f.is_file()), None)
        if f is not None:
            seen[c] = cached(f).get("seconds")
    by_family: dict = {}
    for c, t in seen.items():
        if t:
            by_family.setdefault(c[1], []).append(t)
    return [seen.get(c) or float(np.mean(by_family.get(c[1], [60.0]))) for c in cases]


def _run_parallel(cases: list[tuple], cache: Path, jobs: int) -> set:
    """Run ``cases`` in ``jobs`` processes, the longest expected first (so that the last to finish
    are short); returns the cases that ran (a failed one is a record of the benchmark, see
    :func:`run_case`; a crashed worker's case is left to the serial loop)."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor, as_completed

    os.environ["OMP_NUM_THREADS"] = "1"         # two torch processes with two threads each thrash
    order = [c for _, c in sorted(zip(_expected_seconds(cases, cache), cases), key=lambda p: -p[0])]
    done = set()
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {pool.submit(_run_one, c, str(cache)): c for c in order}
        for fut in as_completed(futures):
            try:
                done.add(fut.result())
            except Exception as exc:  # noqa: BLE001 - reported; the serial loop runs the case again
                print(f"case {futures[fut]} crashed in its worker: {type(exc).__name__}: {exc}", file=sys.stderr)
            print(f"  {len(done)}/{len(cases)} cases run", file=sys.stderr)
    return done


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="moderate magnitude, 1 %% noise, 3 clean records per family")
    ap.add_argument("--families", nargs="*", default=list(FAMILIES), choices=ALL_FAMILIES,
                    help="default: mechanical mixture; duffing and tanks have independent records only")
    ap.add_argument("--simulators", nargs="*", default=None, choices=list(SIMULATORS),
                    help="whose records: ours (the packages' generators) and/or independent (benchmarks/independent/); "
                         "default: each family's own generator, the independent one for duffing and tanks")
    ap.add_argument("--lookalikes", action="store_true",
                    help="only the members of the look-alike pairs (independent simulator; mechanical: Coulomb vs "
                         "Stribeck, mixture: solid vs permeability, filter vs compliance), at their look-alike magnitude")
    ap.add_argument("--experiment", metavar="CSV", default=None,
                    help="also diagnose each case's system simulated under this input (columns t and the family's "
                         "input: u, or load for the mixture; independent simulator): does it select the right effect? "
                         "'proposed': the experiment each case's diagnosis proposed between look-alikes, its record "
                         "the validation record of a second diagnosis (the feed-back of shootlab diagnose --design)")
    ap.add_argument("--magnitude", default="moderate", choices=["small", "moderate", "large"],
                    help="the effects' magnitude with --quick (default moderate)")
    ap.add_argument("--effects", nargs="*", default=None, help="only these effects ('none' for the clean records)")
    ap.add_argument("--seed", type=int, default=1,
                    help="the records' noise seed (default 1; clean records from 100 + 10 (seed - 1)): another "
                         "seed checks the benchmark's figures on records no default run has seen")
    ap.add_argument("--out", default=str(RESULTS), help="output folder (default benchmarks/results)")
    ap.add_argument("--resume", action="store_true", help="reuse cached cases from a previous run")
    ap.add_argument("--reverse", action="store_true",
                    help="run the plan from its last case: with --resume, a second run from the other end "
                         "shares the work (each case is looked up in the cache when its turn comes)")
    ap.add_argument("--cached", action="store_true",
                    help="run nothing: summarise every case cached in --out (runs of different subsets merged)")
    ap.add_argument("--jobs", type=int, default=1,
                    help="cases run in this many processes at once, one thread each, the longest first (by "
                         "their cached time, else their family's mean): 2 on a 2-core machine")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs must be at least 1, got {args.jobs}")
    from tqdm import tqdm

    out = Path(args.out)
    cache = out / "diagnosis_cases"
    cache.mkdir(parents=True, exist_ok=True)
    if args.cached:         # every case cached in --out, whichever run made it: no new case is run
        cases, records = [], [cached(f) for f in sorted(cache.glob("*.json"))]
        if not records:
            print(f"no cached cases in {cache}: run the benchmark without --cached first", file=sys.stderr)
            return 2
        args.simulators = list(dict.fromkeys(r["simulator"] for r in records))
    else:
        try:
            cases = plan(args.quick, args.families, set(args.effects) if args.effects else None, args.simulators,
                         args.magnitude, args.lookalikes, args.seed)
        except ValueError as exc:
            ap.error(str(exc))
        if not cases:
            ap.error("no case to run: the look-alike pairs are in the mechanical and mixture families, and "
                     "--effects must name their members" if args.lookalikes else "no case to run: check --effects")
        records = []
        args.simulators = list(dict.fromkeys(c[0] for c in cases))
        if args.experiment and any(c[0] != "independent" for c in cases):
            ap.error("--experiment re-simulates a case's system: only with the independent simulator's cases")
        if args.reverse:
            cases = cases[::-1]
    t_start = time.perf_counter()
    todo = [c for c in cases if not (args.resume and case_file(cache, c).is_file())]
    done: set = set()
    if args.jobs > 1 and len(todo) > 1:
        done = _run_parallel(todo, cache, args.jobs)
    setups = {(sim, fam): SIMULATORS[sim][fam][0]() for sim, fam in dict.fromkeys(c[:2] for c in cases)} \
        if any(c not in done for c in todo) or args.experiment else {}
    bar = tqdm(cases, unit="case", dynamic_ncols=True)
    for case in bar:
        sim, fam, eff, mag, noise, seed = case
        f = case_file(cache, case)
        cid = f.stem
        bar.set_description(f"{sim} {fam} {eff or 'clean'} {mag} {noise:g}")
        if case in done or (args.resume and f.is_file()):
            rec = cached(f)
        else:
            rec = run_case(fam, eff, mag, noise, seed, setups, sim)
            f.write_text(json.dumps(rec, indent=1, default=float))
        if args.experiment and (rec.get("experiment") or {}).get("input") != args.experiment:
            proposed = rec.get("experiment_input") if args.experiment == "proposed" else None
            if args.experiment != "proposed" or proposed is not None:
                rec["experiment"] = run_experiment(case, args.experiment, setups, proposed)
                f.write_text(json.dumps(rec, indent=1, default=float))
        records.append(rec)
        bar.write(f"{cid}: answer {rec['answer']}" + ("" if rec["answer"] == (eff or "none") else "  ✗")
                  + (f", validation shrink {rec['validation_shrink']:.2f}" if rec.get("validation_shrink") is not None else "")
                  + (f", confidence {rec['answer_confidence']:.2f}" if rec.get("answer_confidence") is not None else "")
                  + (f", look-alikes {', '.join(rec['lookalikes'])}" if rec.get("lookalikes") else "")
                  + f"  ({rec.get('seconds', 0):.0f} s)"
                  + (f"; under {args.experiment}: answer {rec['experiment']['answer']}"
                     f"{'' if rec['experiment']['right'] else '  ✗'}"
                     + (f", confidence {rec['experiment']['confidence']:.2f}"
                        if rec["experiment"].get("confidence") is not None else "")
                     + f" ({rec['experiment']['seconds']:.0f} s)"
                     if args.experiment and rec.get("experiment") else ""))
    text = table(records)
    print("\n" + text)
    per_sim, confusion = {}, {}
    for sim in args.simulators:
        recs = [r for r in records if r["simulator"] == sim]
        per_sim[sim] = summary = summarize(recs)
        png = out / ("diagnosis_confusion.png" if sim == "ours" else f"diagnosis_confusion_{sim}.png")
        confusion[sim] = confusion_figure(recs, png, title=f"{sim} simulator")
        c = summary["criteria"]
        print(f"\n{sim} simulator — criteria (moderate magnitude, 1 % noise, both libraries): top-1 "
              f"{fmt(c['top1_moderate_1pct'], '.0%')} (ranking alone {fmt(c['top1_ranking_moderate_1pct'], '.0%')}; need ≥ 90 %), "
              f"clean 'none' or 'numerical' {fmt(c['clean_accuracy'], '.0%')} ({c['false_alarms']} false alarms in {c['clean_cases']}), "
              f"mean validation shrink {fmt(c['mean_validation_shrink_moderate_1pct'], '.2f')} (need ≥ 0.50; above the noise "
              f"{fmt(c['mean_validation_shrink_above_noise_moderate_1pct'], '.2f')}), verdicts whose validation misfit "
              f"shrinks {fmt(c['verdicts_whose_validation_shrinks'], '.0%')}")
        for fam, groups in summary.items():
            if fam == "criteria":
                continue
            for key, g in groups.items():
                if "top1" in g:
                    print(f"  {fam:<11} {key:<22} top-1 {g['top1']:.0%} (ranking {g['top1_ranking']:.0%}), detected "
                          f"{g['detected']:.0%}, mean validation shrink {fmt(g['mean_validation_shrink'], '.2f')}"
                          + (f", the look-alike partner named {g['answered_partner']:.0%}" if "answered_partner" in g else "")
                          + (f", right under the experiment {g['experiment_right']:.0%}" if "experiment_right" in g else ""))
                else:
                    print(f"  {fam:<11} {key:<22} right ('none', 'numerical', or an effect in every record) on {g['clean_accuracy']:.0%} of {g['cases']} clean records "
                          f"(answers {', '.join(g['answers'])})")
    rel = reliability(records)
    print("\nreliability over all cases (verdicts naming an effect, by the confidence given):\n" + reliability_text(rel))
    report = dict(meta=dict(quick=args.quick, families=args.families, simulators=args.simulators, cases=len(records),
                            seconds=time.perf_counter() - t_start, criteria=CRITERIA),
                  summary=per_sim.get("ours") or next(iter(per_sim.values())), per_simulator=per_sim,
                  reliability=rel, confusion=confusion.get("ours") or next(iter(confusion.values())),
                  confusion_per_simulator=confusion, table=text.splitlines(), records=records)
    (out / "diagnosis.json").write_text(json.dumps(report, indent=1, default=float))
    print(f"\nwrote {out / 'diagnosis.json'} and the confusion figures ({time.perf_counter() - t_start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
