"""The diagnosis's verdict on both records (``docs/diagnosis.md``: "Evidence on the validation
record", "Leading candidates re-estimated in full"; shootlab.diagnosis.floor.validation_evidence,
shootlab.diagnosis.confirmation, the status enum).

On the mass–spring–damper (``m s'' + s' + s + k3 s³ = u``, records by DOP853, 1 % noise on s):

* a cubic spring invisible on a small identification record (the cubic force 0.3 % of the
  linear one) but not on a large validation record: the identification residual is at its
  floor, the validation free run misses by 62 times the noise — never "no significant structural
  error"; the same records without the spring stay at the noise (0.98 times it);
* a strong cubic spring (k3 = 8 at 1.3 times the input) whose one undamped step from the nominal
  solution explains 26 % of J, its full re-estimate all of it: selected, with k3 recovered;
* with backlash among the candidates the steps select it, but it leaves the validation misfit 9
  times the noise: the validation record decides for the spring (slow: 25 s);
* Stribeck friction that cannot be estimated (the library's estimator fails on it) gives way to
  the Coulomb friction it nests, and the verdict says what failed.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from manipulators.friction import smooth_sign
from manipulators.msd import model as msd_model
from shootlab import diagnosis as dg
from shootlab.diagnosis import confirmation
from shootlab.diagnosis.floor import validation_evidence
from shootlab.diagnosis.outcome import Diagnosis, Status
from shootlab.diagnosis.shrinkage import free_run_error, free_run_start, misfit
from shootlab.estimation.data import Measurements


def _record(u, seed: int, cubic: float = 0.0, friction=None, noise: float = 0.01) -> dict:
    """m = b = k = 1 with + cubic s³ and ``friction(v)``, from rest, 10 s at 100 Hz; Gaussian noise
    of ``noise`` × std on s, u exact."""
    t = np.linspace(0.0, 10.0, 1001)
    fr = friction or (lambda v: 0.0)

    def rhs(tt, x):
        return [x[1], float(u(tt)) - x[1] - x[0] - cubic * x[0] ** 3 - fr(x[1])]
    sol = solve_ivp(rhs, (t[0], t[-1]), [0.0, 0.0], t_eval=t, method="DOP853", rtol=1e-10, atol=1e-12, max_step=0.01)
    s = sol.y[0]
    rng = np.random.default_rng(seed)
    return {"t": t, "u": np.array([float(u(tt)) for tt in t]), "s": s + rng.normal(0, noise * s.std(), t.size)}


def _u_id(t, a: float = 1.0):
    return a * (np.sin(0.5 * t) + 0.6 * np.sin(1.3 * t + 1.0) + 0.3 * np.sin(2.9 * t + 2.0))


def _u_val(t, a: float = 1.0):
    return a * (0.8 * np.sign(np.sin(0.4 * t)) * (1 - np.exp(-3 * (t % (np.pi / 0.4)))) + 0.3 * np.sin(2.1 * t))


# -- the status ------------------------------------------------------------------------------------------------
def test_the_status_is_an_enum_whose_json_is_its_string():
    """Each status says what it means and whether the command exits 0; it compares equal to its
    string value, formats as it and is written as it; a Diagnosis takes a string for it and
    refuses an unknown one."""
    assert {s.value for s in Status} == {"confirmed", "selected", "no_structural_error", "unexplained", "numerical",
                                        "not_confirmed", "inconclusive"}
    assert [s.value for s in Status if not s.definite] == ["not_confirmed", "inconclusive"]
    assert all(s.meaning for s in Status)
    assert Status.CONFIRMED == "confirmed" and f"{Status.INCONCLUSIVE}" == "inconclusive"
    assert json.dumps({"status": Status.NO_STRUCTURAL_ERROR}) == '{"status": "no_structural_error"}'
    d = Diagnosis(model=None, library=None, data=None, validation=None, nominal=None, floor=None, noise={}, where=[],
                  significant=False, which={}, selected=[], verdict="", extended=None, shrink=None, skipped={},
                  seconds={}, status="not_confirmed")
    assert d.status is Status.NOT_CONFIRMED and not d.success
    with pytest.raises(ValueError, match="'maybe' is not a valid Status"):
        Diagnosis(model=None, library=None, data=None, validation=None, nominal=None, floor=None, noise={},
                  where=[], significant=False, which={}, selected=[], verdict="", extended=None, shrink=None,
                  skipped={}, seconds={}, status="maybe")


# -- A: the validation record's evidence -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def quiet_identification():
    """A cubic spring k3 = 0.5: identified at 0.08 times the input (the cubic force 0.3 % of the
    linear one), validated at 1.5 times it; and the same records without the spring."""
    out = {}
    for k3 in (0.5, 0.0):
        ident = _record(lambda t: _u_id(t, 0.08), seed=1, cubic=k3)
        valid = _record(lambda t: _u_val(t, 1.5), seed=2, cubic=k3)
        out[k3] = dg.diagnose(msd_model(), ident, validation=valid, effects=["cubic_spring", "input_offset"], seed=0)
    return out


def test_a_validation_free_run_beyond_the_noise_is_a_structural_error_though_the_identification_is_at_its_floor(
        quiet_identification):
    """The identification residual is at its floor on every row, but the nominal model's free run
    misses the validation record by far more than 3 times its noise (the floor's estimates, run
    on surrogate validation records, by about 1): significant on the validation record, never
    "no significant structural error"; the verdict says which record carried the evidence, and
    the cubic spring explains it."""
    d = quiet_identification[0.5]
    assert not any(w["significant"] for w in d.where)
    ev = d.evidence
    # the evidence's misfit is the free run's RMS error in units of the record's noise (one channel),
    # over the whole record, from the initial state fitted to it
    assert ev["measure"] == "fitted_start"
    val = Measurements.coerce(d.validation)
    run = misfit(d.model, val, d.nominal.parameters, "fitted_start", sigma=ev["noise"])["prediction"]
    np.testing.assert_array_equal(run["t"], val.t)
    assert ev["samples"] == val.t.size
    x0 = free_run_start(d.model, val, "fitted", d.nominal.parameters)
    assert run["s"][0] == pytest.approx(x0[d.model.states.index("s")], rel=1e-12)
    z = (run["s"] - val.channels["s"]) / ev["noise"]["s"]
    assert ev["misfit"] == pytest.approx(math.sqrt(np.mean(z * z)), rel=1e-12)
    free = free_run_error(d.model, val, d.nominal.parameters, d.library.initial_state, sigma=ev["noise"])
    assert free["per_channel"]["s"]["rms"] / ev["noise"]["s"] > 30        # from the library's start alike
    assert ev["misfit"] > 30 and 0.8 < ev["floor_misfit"] < 1.3 and ev["significant"]
    assert d.significant and d.status is not Status.NO_STRUCTURAL_ERROR, d.verdict
    assert "significant on the validation record: the validation free-run misfit (from a fitted start)" in d.verdict
    assert d.status is Status.CONFIRMED and d.selected == ["cubic_spring"], d.verdict
    assert d.extended.parameters["cubic_k3"] == pytest.approx(0.5, rel=0.25)
    assert d.shrink["validation"]["shrink"] > 0.9
    info = d.to_dict()
    assert info["status"] == "confirmed" and info["evidence"]["significant"] is True
    json.dumps(info)


def test_without_the_spring_both_records_are_at_their_floors(quiet_identification):
    """The same records without the cubic spring: the validation free run misses by the noise
    (its mean square within 30 % of the floor's), no structural error — and the verdict says so
    for both records."""
    d = quiet_identification[0.0]
    ev = d.evidence
    assert not ev["significant"] and 0.8 < ev["misfit"] < 1.3 and 0.7 < ev["ratio"] < 1.3
    assert d.status is Status.NO_STRUCTURAL_ERROR and d.success and d.selected == []
    assert "the validation free-run misfit (from a fitted start) within what the noise explains" in d.verdict


def test_without_a_noise_floor_the_validation_reference_is_the_noise_alone():
    """Without a noise floor (none could be made) the validation misfit is compared with the noise
    alone: a mean square of 1 in units of the record's noise level."""
    ident = Measurements.coerce(_record(lambda t: _u_id(t, 0.08), seed=1))
    valid = Measurements.coerce(_record(lambda t: _u_val(t, 1.5), seed=2))
    nominal = dg.default_estimator(msd_model(), ident)
    alone = validation_evidence(nominal, None, valid)
    assert alone["floor_misfit"] == 1.0 and alone["floor_costs"] == []
    assert 0.8 < alone["misfit"] < 1.3 and not alone["significant"]


# -- B: leading candidates re-estimated in full ------------------------------------------------------------------
def test_scan_starts_are_log_spaced_with_the_signs_the_bounds_allow():
    effect = dg.Effect("stiff", ["motion"], {"k3": 0.0, "c": 1.0}, lambda v: {"motion": v["k3"] * v["s"] ** 3},
                       nonlinear={"k3": (1e-3, 1.0)})
    starts = confirmation.scan_starts(effect, None, {"k3": 0.0, "c": 2.0})
    mags = sorted({abs(s["k3"]) for s in starts})
    assert mags == pytest.approx(np.geomspace(1e-3, 1.0, 7)) and len(starts) == 14
    assert all(s["c"] == 2.0 for s in starts)
    hard = dg.Effect("stiff", ["motion"], {"k3": 0.0}, effect.term, bounds={"k3": (0.0, 10.0)},
                     nonlinear=lambda v: {"k3": (0.01, 1.0)})
    assert sorted(s["k3"] for s in confirmation.scan_starts(hard, None, {"k3": 0.0})) == \
        pytest.approx([0.01, 0.1 ** 1.5, 0.1, 0.1 ** 0.5, 1.0])
    with pytest.raises(ValueError, match="nonlinear for unknown parameters"):
        dg.Effect("bad", ["motion"], {"k3": 0.0}, effect.term, nonlinear={"k4": (1.0, 2.0)})


@pytest.fixture(scope="module")
def strong_spring():
    """k3 = 8 at 1.3 times the input: the cubic force exceeds the linear one."""
    return _record(lambda t: _u_id(t, 1.3), seed=1, cubic=8.0), _record(lambda t: _u_val(t, 1.3), seed=2, cubic=8.0)


def test_a_spring_whose_one_step_explains_little_is_selected_by_its_full_re_estimate(strong_spring, monkeypatch):
    """One undamped step from k3 = 0 — where ∂(k3 s³)/∂s = 0 — sees none of the stiffening: it
    explains 26 % of J, less than the half a selection needs, and no candidate is selected by the
    steps.  (The ranking's further steps for its three leading models would reach the spring's
    minimum here, with two candidates; they are left out, as for a candidate outside the three —
    on a rig record with twelve candidates the spring was scored 6 % and not among them.)
    Re-estimated in full (the leading candidates, and the spring for its declared nonlinear k3), it
    explains all of the excess over the floor and is selected, k3 recovered."""
    from shootlab.diagnosis import which
    monkeypatch.setattr(which, "polish_leaders", lambda *args, **kw: None)
    ident, _ = strong_spring
    d = dg.diagnose(msd_model(), ident, effects=["cubic_spring", "coulomb_m1"], seed=0)
    cubic = next(m for m in d.which["models"] if m.effects == ["cubic_spring"])
    J0 = d.nominal.J
    assert cubic.full and cubic.linearised is not None
    assert (J0 - cubic.linearised) / J0 < 0.5 and cubic.explained_excess > 0.99
    assert d.status is Status.SELECTED and d.selected == ["cubic_spring"], d.verdict
    assert d.extended.parameters["cubic_k3"] == pytest.approx(8.0, rel=0.02)


@pytest.mark.slow
def test_the_validation_record_decides_between_a_selection_and_a_leading_candidate(strong_spring):
    """With backlash among the candidates the steps select it (85 % of J's excess), and it shrinks
    the validation misfit — but leaves it 9 times the noise: the validation record decides between
    it and the leading candidates re-estimated in full, and the cubic spring brings it to the noise."""
    ident, valid = strong_spring
    d = dg.diagnose(msd_model(), ident, validation=valid,
                    effects=["backlash", "cubic_spring", "input_offset", "coulomb_m1"], seed=0)
    assert d.status is Status.CONFIRMED and d.selected == ["cubic_spring"], d.verdict
    rows = {r["effect"]: r for r in d.free_run["candidates"]}
    assert d.free_run["method"] == "re-estimates"
    assert rows["backlash"]["validation_explained"] < 0.9 < 0.99 < rows["cubic_spring"]["validation_explained"]
    assert any(n.startswith("the TPBVP's selection backlash was confirmed, but it removes ") and
               "of the validation misfit's excess over the noise floor and leaves a misfit" in n for n in d.notes)
    assert d.shrink["validation"]["after_above_noise"] < 0.3 * d.shrink["validation"]["before_above_noise"]


def test_a_leading_candidate_that_cannot_be_estimated_gives_way_to_its_nested_form():
    """Stribeck friction (f_c 0.15, f_s 0.45, v_st 0.25) ranks first, but the library's estimator
    cannot estimate any model with it (max_iter = 1) — from its own start nor from Coulomb
    friction's solution: Coulomb friction, which it nests, is estimated and selected, and the
    verdict says that the Stribeck model could not be estimated.  (No validation record: there the
    ranking's own converged re-estimate of the Stribeck model would be compared, and win.)"""
    fc, fs, vst, vs = 0.15, 0.45, 0.25, 0.1

    def law(v):         # the library's law: the hump's sign ramped over v_h = v_st v_s/(v_st + v_s)
        return fc * float(smooth_sign(v, vs)) + (fs - fc) * math.exp(-(v / vst) ** 2) * float(
            smooth_sign(v, vst * vs / (vst + vs)))

    def failing(model, data, **kw):
        if "stribeck_m1" in model.settings.effects:
            kw = dict(kw, max_iter=1)
        return dg.default_estimator(model, data, **kw)
    ident = _record(_u_id, seed=1, friction=law)
    lib = dg.Library("msd, Stribeck fails", dg.library_for(msd_model()).effects, estimator=failing)
    d = dg.diagnose(msd_model(), ident, lib, effects=["stribeck_m1", "coulomb_m1"], seed=0)
    assert d.which["ranking"][0]["effect"] == "stribeck_m1"
    assert d.status is Status.SELECTED and d.selected == ["coulomb_m1"], d.verdict
    assert "could not be estimated: msd+stribeck_m1 (" in d.verdict
    assert any("coulomb_m1 taken for stribeck_m1, which contains it and could not be estimated" in n for n in d.notes)
    assert d.extended.success and d.extended.parameters["coulomb1_f"] > fc


def test_the_validation_z_of_a_richer_model_counts_its_better_prediction_in_standard_errors():
    """reestimation.validation_z, the nested test's question to the validation record: with a cubic
    spring (k3 = 2) in both records, the model with the spring predicts the large validation record
    better than the linear one by more standard errors of the cost difference than the test at
    α = 0.01 asks (2.33; the difference is a slow, strongly correlated one, so its standard error
    is large: z about 3); asked the other way round, z is as far below zero; and the same model on
    both sides has no difference to test."""
    from types import SimpleNamespace

    from shootlab.diagnosis.reestimation import validation_z

    ident = _record(_u_id, seed=5, cubic=2.0)
    valid = Measurements.coerce(_record(lambda t: _u_val(t, 1.5), seed=6, cubic=2.0))
    nominal = dg.default_estimator(msd_model(), ident)
    lib = dg.library_for(msd_model())
    evidence = validation_evidence(nominal, None, valid, initial_state=lib.initial_state)
    rich = SimpleNamespace(parameters=dict(m=1.0, b=1.0, k=1.0, cubic_k3=2.0))
    plain = SimpleNamespace(parameters=dict(nominal.parameters))
    z = validation_z(nominal, lib, ["cubic_spring"], rich, [], plain, valid, evidence)
    assert z > 2.6, z
    assert validation_z(nominal, lib, [], plain, ["cubic_spring"], rich, valid, evidence) == pytest.approx(-z)
    assert validation_z(nominal, lib, [], plain, [], plain, valid, evidence) is None


def test_a_selection_that_predicts_the_validation_record_worse_by_the_evidence_s_measure_is_not_confirmed(
        strong_spring, monkeypatch):
    """A selection confirmed by its free run from the validation record's start, whose free run by
    the measure that carries the validation evidence (from a fitted start) misses that record by
    more than the nominal model's, is not confirmed (exit status 1), and the verdict gives both
    misfits in units of the noise.  (The strong spring's records, with the selection's measured
    validation cost made four times the nominal model's: no record of the benchmark or the rigs
    shows this since that measure is taken over the whole record.)"""
    from shootlab.diagnosis import pipeline

    measured = pipeline.selection_on_validation

    def worse(nominal, library, selected, extended, validation, evidence, say):
        c = measured(nominal, library, selected, extended, validation, evidence, say)
        c.validation_cost, c.why = 4.0 * evidence["cost"], None
        return c
    monkeypatch.setattr(pipeline, "selection_on_validation", worse)
    ident, valid = strong_spring
    d = dg.diagnose(msd_model(), ident, validation=valid, effects=["cubic_spring", "input_offset"], seed=0)
    assert d.status is Status.NOT_CONFIRMED and not d.success and d.selected == [], d.verdict
    ev = d.evidence
    assert d.verdict.startswith(
        f"not confirmed: cubic_spring explains the identification record but predicts the validation record "
        f"worse than the nominal model by the free-run misfit (from a fitted start): "
        f"{math.sqrt(4.0 * ev['cost'] / ev['samples']):.3g}× the noise against {ev['misfit']:.3g}×"), d.verdict
    assert any(n.startswith("cubic_spring was confirmed by the free run from the record's start: structural error "
                            "explained by cubic_spring") for n in d.notes), d.notes


@pytest.mark.slow
@pytest.mark.parametrize("truth", ["stribeck_m1", "coulomb_m2"])
def test_coulomb_and_stribeck_friction_the_records_do_not_settle_are_not_answered_with_confidence(truth):
    """The independent rig's moderate friction records with the noise of seed 2 (the benchmark's
    records use seed 1), where the verdicts had been wrong with confidence 1.00:

    * Stribeck friction on the motor: input_delay + coulomb_m1 is selected, and input_delay +
      stribeck_m1, which contains it, converges from no start (the one-step score had left it
      above the selection's J) — the records have not weighed it: it is named beside the selection
      and the confidence is at most even odds.
    * Coulomb friction on the load: Stribeck + delay passes the identification record's likelihood
      ratio against Coulomb + delay (15.8 against 9.21, J 0.8 % lower) but predicts the validation
      record worse (free-run cost 11116 against 6239), and with both records weighed Coulomb + delay
      is taken — the records disagree, so Stribeck is named beside it, at most even odds."""
    from benchmarks.diagnosis import mechanical_setup
    from benchmarks.independent import rig
    from shootlab.diagnosis.lookalike_words import UNRESOLVED

    model, library, _ = mechanical_setup()
    ident, valid, _ = rig.data(truth, "moderate", 0.01, 2)
    d = dg.diagnose(model, ident, library, validation=valid, seed=2)
    other = {"stribeck_m1": "stribeck_m1", "coulomb_m2": "stribeck_m2"}[truth]
    assert d.status is Status.CONFIRMED and "input_delay" in d.selected, d.verdict
    if truth == "coulomb_m2":
        assert "coulomb_m2" in d.selected, d.verdict
    assert other in d.lookalikes and d.confidence <= UNRESOLVED, d.verdict


def test_a_richer_model_with_an_effect_the_nested_one_lacks_is_not_started_from_its_solution():
    """reestimation.from_nested starts a richer model from the solution of the one it nests only
    where the richer one's other effects are all in the nested one (their estimates are the start):
    Stribeck friction + an input offset is not started from Coulomb friction's solution, which has
    no offset (the one-axis drive's look-alike stribeck + input_delay against the selection coulomb
    had raised a KeyError here)."""
    from types import SimpleNamespace

    from shootlab.diagnosis.reestimation import from_nested

    lib = dg.library_for(msd_model())
    coulomb = SimpleNamespace(parameters=dict(m=1.0, b=1.0, k=1.0, coulomb1_f=0.1))
    assert from_nested(None, lib, None, ["stribeck_m1", "input_offset"], ["coulomb_m1"], coulomb, None, None,
                       print) is None


def test_a_re_estimate_whose_warm_start_does_not_converge_is_made_from_the_data_s_states():
    """reestimation.reestimate: where the estimate from the candidate's solution does not converge —
    that solution's smoothed states carry the misfit the effect is to explain (on the independent
    tanks with a leak of the lower tank, the leak's re-estimate stopped at its damping floor from
    there, and a pair with a negative upper leak was taken for it) — the model is estimated from the
    data's states, its parameters started at the warm estimate's, before more shooting points are
    tried.  Here the library's estimator fails every warm start: the cubic spring's re-estimate
    converges from the data's states to the estimate made that way directly, k3 recovered, and the
    failed warm start is in the notes."""
    from dataclasses import replace as _replace
    from types import SimpleNamespace

    from shootlab.diagnosis.reestimation import reestimate

    ident = _record(_u_id, seed=5, cubic=2.0)
    nominal = dg.default_estimator(msd_model(), ident)
    calls = []

    def no_warm_start(model, data, start=None, **kw):
        calls.append((start is not None, dict(kw.get("initial") or {})))
        res = dg.default_estimator(model, data, start=start, **kw)
        return _replace(res, success=False, message="stopped (a warm start)") if start is not None else res

    lib = dg.library_for(msd_model())
    cand = SimpleNamespace(parameters={"cubic_k3": 1.0}, result=None)
    res, sh, tried = reestimate(nominal, lib, no_warm_start, ["cubic_spring"], cand, Measurements.coerce(ident), None,
                                lambda s: None)
    assert res.success and sh is not None
    assert calls[0][0] and not calls[1][0] and len(calls) == 2
    assert {p: calls[1][1][p] for p in ("m", "b", "k")} == nominal.parameters and calls[1][1]["cubic_k3"] == 1.0
    direct = dg.default_estimator(dg.extend(msd_model(), [lib["cubic_spring"]], data=ident), ident,
                                  initial=dict(nominal.parameters, cubic_k3=1.0))
    assert res.J == pytest.approx(direct.J, rel=1e-8)
    assert res.parameters["cubic_k3"] == pytest.approx(2.0, abs=4 * res.standard_errors["cubic_k3"])
    assert tried and tried[0].startswith("msd+cubic_spring from its linearised solution did not converge: stopped")


@pytest.mark.slow
def test_the_independent_tanks_small_lower_leak_is_named_alone():
    """The independent tanks (Torricelli outflows, RK45, 12-bit ADC) with a small leak of the lower
    tank: the leak's re-estimate from its linearised solution stops at the damping floor, and the
    pair with the upper leak (estimated negative: a source) had been selected for want of it.  From
    the data's states it converges, the nested test prefers it to the pair, and it is named alone,
    confirmed, with the simulator's k1 = 0.037 recovered (the nominal fit puts k1 at 0.030)."""
    from benchmarks.diagnosis import independent_tanks_setup
    from benchmarks.independent import tanks

    model, library, _ = independent_tanks_setup()
    ident, valid, size = tanks.data("leak_lower", "small", 0.01, 1)
    d = dg.diagnose(model, ident, library, validation=valid, seed=1)
    assert d.status is Status.CONFIRMED and d.selected == ["leak_lower"], d.verdict
    assert d.extended.parameters["leak_lower"] > 0
    assert d.extended.parameters["k1"] == pytest.approx(size["model_parameters"]["k1"], rel=0.03)
    assert any(n.startswith("tanks+leak_lower from its linearised solution did not converge") for n in d.notes)
