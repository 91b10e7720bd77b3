"""The diagnosis benchmark's scoring (benchmarks/diagnosis.py): answers, effects a simulator puts
in every record, the reliability table."""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks import diagnosis as bd  # noqa: E402

HOLD = {"input_delay": {"input_delay": 0.0005}}


def _rec(effect, answer, confidence=None, delay=None, success=True, inherent=HOLD):
    return dict(effect=effect, answer=answer, answer_confidence=confidence, inherent=inherent,
                extended_success=success, extended_parameters=None if delay is None else {"input_delay": delay})


def test_answers_name_numerical_and_inconclusive():
    assert bd.answer_of(["coulomb_m2", "input_delay"], "confirmed") == "coulomb_m2"
    assert bd.answer_of([], "numerical") == "numerical" and bd.answer_of([], "inconclusive") == "inconclusive"
    assert bd.answer_of([], "unexplained") == "none" and bd.answer_of([], "no_structural_error") == "none"


def test_a_pair_with_the_simulators_own_effect_answers_the_other_member():
    """The independent rig's half-sample hold is in every record: input_delay + viscous_m2 answers
    viscous_m2; the hold alone answers input_delay (then judged by names_inherent)."""
    inherent = {"input_delay": {"input_delay": 0.0005}}
    assert bd.answer_of(["input_delay", "viscous_m2"], "confirmed", inherent) == "viscous_m2"
    assert bd.answer_of(["input_delay"], "confirmed", inherent) == "input_delay"
    assert bd.answer_of(["input_delay", "viscous_m2"], "confirmed") == "input_delay"


def test_an_effect_in_every_record_is_right_only_near_its_true_size():
    assert bd.names_inherent(_rec("none", "input_delay", 1.0, delay=0.00046))
    assert not bd.names_inherent(_rec("none", "input_delay", 1.0, delay=0.0012))        # > 2x the hold
    assert not bd.names_inherent(_rec("none", "input_delay", 1.0, delay=0.00046, success=False))
    assert not bd.names_inherent(_rec("none", "coulomb_m1", 1.0, delay=0.00046))
    assert not bd.names_inherent(_rec("none", "input_delay", 1.0, delay=0.00046, inherent={}))


def test_reliability_bins_verdicts_by_confidence():
    recs = [_rec("coulomb_m1", "coulomb_m1", 0.99), _rec("coulomb_m1", "stribeck_m1", 1.0),
            _rec("none", "input_delay", 0.95, delay=0.00045), _rec("viscous_m2", "viscous_m2", 0.8),
            _rec("backlash", "none"), _rec("none", "cubic_spring", 0.3),
            _rec("load_offset", "load_offset", 1.0000000000000002)]      # normalised weights' rounding
    rows = {r["confidence"]: (r["verdicts"], r["right"]) for r in bd.reliability(recs)}
    assert rows == {"[0.9, 1.0]": (4, 3), "[0.7, 0.9)": (1, 1), "[0.5, 0.7)": (0, 0), "[0.0, 0.5)": (1, 0)}


def test_a_run_into_a_new_folder_is_ordered_by_the_shipped_cases_times(tmp_path):
    """--jobs runs the longest expected case first; with nothing cached in the new folder the times
    come from the cases shipped in benchmarks/results, and a case cached in the folder wins."""
    cases = bd.plan(True, ["mechanical"], {"stribeck_m2", "input_gain"})
    shipped = [bd.cached(bd.case_file(bd.RESULTS / "diagnosis_cases", c))["seconds"] for c in cases]
    assert bd._expected_seconds(cases, tmp_path) == shipped
    bd.case_file(tmp_path, cases[0]).write_text('{"seconds": 1234.5, "answer": "error"}')
    assert bd._expected_seconds(cases, tmp_path) == [1234.5] + shipped[1:]


def test_held_out_seeds_are_summarised_apart_and_in_the_criteria():
    """Records of another noise seed (``--seed 2``) get their own rows, and the criteria say their
    figures alone beside those over every record; the default plan's seeds are not held out."""
    base = dict(magnitude="moderate", noise=0.01, family="mechanical", top1_ranking="coulomb_m1",
                validation_shrink=0.5, validation_shrink_above_noise=0.6, significant=True)
    recs = [dict(base, **_rec("coulomb_m1", "coulomb_m1", 1.0), seed=1),
            dict(base, **_rec("coulomb_m1", "stribeck_m1", 0.5), seed=2),
            dict(base, **_rec("none", "none"), magnitude="-", seed=110)]
    out = bd.summarize(recs)
    assert set(out["mechanical"]) == {"moderate @ noise 0.01", "moderate @ noise 0.01, held-out seeds",
                                      "clean @ noise 0.01, held-out seeds"}
    crit = out["criteria"]
    assert crit["top1_moderate_1pct"] == 0.5 and crit["cases_moderate_1pct"] == 2
    assert crit["held_out"] == dict(top1_moderate_1pct=0.0, cases_moderate_1pct=1, clean_cases=1, false_alarms=0,
                                  seeds=[2])
    assert [c[-1] for c in bd.plan(True, ["mechanical"], None, ["independent"])] == [1] * 12 + [100, 101, 102]
    assert [c[-1] for c in bd.plan(True, ["mechanical"], None, ["independent"], seed=2)][-3:] == [110, 111, 112]
