"""What the diagnosis says and shows (shootlab.diagnosis.progress, .report, .which's ranking, the
effects' units): messages summarised at a sentence boundary, a failed fit said in words, units
composed from the model's and carried into the extended model, the Which table's confidence the
one the verdict adds up.  Fast: no estimation.
"""
from __future__ import annotations

import math
import runpy
from pathlib import Path
from types import SimpleNamespace

import pytest

from manipulators import effects as me
from manipulators.flexible import UNITS as FLEXIBLE_UNITS
from manipulators.flexible import plain_model
from manipulators.msd import model as msd_model
from mixtures import effects as xe
from mixtures.identification import model as confined_model
from shootlab import diagnosis as dg
from shootlab.diagnosis.mechanical import mechanical_library, unit_product
from shootlab.diagnosis.progress import LineWriter, brief, fit_line, progress_sink
from shootlab.diagnosis.report import _markdown
from shootlab.diagnosis.which import Candidate, ranking_table

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def examples() -> dict:
    """The declared models of examples/drive.py and examples/tanks.py (and the tanks' library)."""
    return {name: runpy.run_path(str(ROOT / "examples" / f"{name}.py")) for name in ("drive", "tanks")}

#: the message shootlab.bvp.solver.solve gives for intervals too long (three sentences of advice after it)
TOO_LONG = ("weight continuation stage 1/5: shooting intervals too long for the problem: on interval 92 [t = 0.92, "
            "0.93] the local Jacobian at the guess grows like e^375 (κ₊·h > 20); use more shooting points "
            "(shootlab.suggest_shooting_points) or pass max_growth=None to try anyway; in an estimation the fast "
            "modes also come from the weights: a parameter with a small W drifts to follow the data (a larger W on "
            "the parameters, e.g. W={'k': 1e10}, holds it constant), and a large V on a row speeds up its costate")


def test_brief_keeps_the_first_sentence_in_whole_words_and_closes_its_brackets():
    assert brief(TOO_LONG) == ("weight continuation stage 1/5: shooting intervals too long for the problem: on "
                               "interval 92 [t = 0.92, 0.93] the local Jacobian at the guess grows like e^375 (κ₊·h > 20)")
    note = f"input_delay + stribeck_m2 estimated from the solution of input_delay + coulomb_m2 ({TOO_LONG})"
    short = brief(note)
    assert short.endswith("(κ₊·h > 20) …)") and short.count("(") == short.count(")")
    assert note.startswith(short[:-3])                       # a prefix of the note, cut between words
    assert brief("maximum number of iterations (100) reached, |F| = 3.800e+04") == \
        "maximum number of iterations (100) reached, |F| = 3.800e+04"          # one sentence: as it is
    assert brief("a factor 0.5 (e.g. here) is kept. The rest is not") == "a factor 0.5 (e.g. here) is kept"


def test_a_failed_fit_is_said_in_words_not_as_inf_or_nan():
    failed = SimpleNamespace(success=False, J=math.inf, iterations=36, message=(
        "max|F| not halved in 10 iterations at iteration 36 (|F| = 9.689e+02): the iteration makes no progress; "
        "try a better initial guess, more shooting points or tolerance continuation"))
    line = fit_line("  surrogate 1/4", failed, 12.34)
    assert line == ("  surrogate 1/4: not converged: max|F| not halved in 10 iterations at iteration 36 "
                    "(|F| = 9.689e+02): the iteration makes no progress, 12.3 s")
    ok = SimpleNamespace(success=True, J=0.981137, iterations=3, message="converged: |F|_inf = 1e-9 after 3 iterations")
    assert fit_line("  surrogate 2/4", ok, 0.94) == "  surrogate 2/4: J = 0.98114, 3 iterations, 0.9 s"
    fallback = SimpleNamespace(success=True, J=0.5, iterations=3, message=(
        f"the warm start at the final weights stopped ({failed.message}); by weight continuation from the data's "
        f"states: converged: |F|_inf = 1e-9 after 3 iterations"))
    assert fit_line("x", fallback, 1.0).endswith("; the warm start at the final weights stopped (max|F| not halved in "
                                                 "10 iterations at iteration 36 (|F| = 9.689e+02): the iteration "
                                                 "makes no progress …)")
    for line in (fit_line("x", failed, 1.0), fit_line("x", fallback, 1.0)):
        assert "inf" not in line.split() and "nan" not in line


def test_units_compose_as_products_of_powers():
    assert unit_product(("N", 1), ("m/s", -1)) == "N s/m"
    assert unit_product(("-", 1), ("rad/s", -1)) == "s/rad"
    assert unit_product(("-", 1), ("rad", -3)) == "1/rad³"
    assert unit_product(("m/s²", 1), ("s", 2)) == "m"
    assert unit_product(("V^½/s", 2)) == "V/s²"
    assert unit_product(("kg", 1), ("m", 1), ("s", -2)) == "kg m/s²"
    assert unit_product(("rad", 1), ("rad", -1)) == "-"
    assert unit_product((None, 1), ("s", 1)) is None and unit_product(("N/(m/s)", 1)) is None   # unknown, unread


def test_mechanical_effects_take_their_units_from_the_model(examples):
    """The effects' parameters are in the model's units: the flexible manipulator's viscous friction
    in its own damping b's unit (torque per unit c per velocity), Coulomb friction in its rows' and
    the declared drive's viscous b_v in its b's, N s/m."""
    lib = me.library(plain_model())
    units = {p: u for e in lib.effects for p, u in e.units.items()}
    assert set(units) == {p for e in lib.effects for p in e.parameters}             # every parameter has one
    assert units["viscous2_b"] == FLEXIBLE_UNITS["b"] == "s/rad"
    assert units["coulomb2_f"] == units["stribeck2_fs"] == FLEXIBLE_UNITS["f2"] == "-"
    assert (units["stribeck2_vst"], units["backlash_delta"], units["cubic_k3"]) == ("rad/s", "rad", "1/rad³")
    assert (units["input_delay"], units["input_gain_error"]) == ("s", "-")
    assert lib["input_delay"].variable[2] == "1/s"                       # du/dt of a dimensionless command
    msd = {p: u for e in me.library(msd_model()).effects for p, u in e.units.items()}
    assert (msd["coulomb1_f"], msd["cubic_k3"], msd["input_offset"]) == ("N", "N/m³", "N")
    drive = examples["drive"]["model"]
    dl = mechanical_library(drive)
    assert dl["viscous"].units == {"viscous_b": drive.units["b"]} and dl["coulomb"].units == {"coulomb_f": "N"}
    assert dg.generic_library(msd_model())["offset_s"].units == {"offset_s": "m"}
    mix = {p: u for e in xe.library(confined_model()).effects for p, u in e.units.items()}
    assert mix == {p: "-" for p in mix} and len(mix) == 5               # the dimensionless experiment
    tanks = examples["tanks"]["library"]
    assert tanks["leak_upper"].units == {"leak_upper": "1/s"} and tanks["overflow"].units["overflow_level"] == "V"


def test_effect_units_are_checked_and_carried_into_the_extended_model():
    with pytest.raises(ValueError, match="units for unknown parameters"):
        dg.Effect("b", ["mass2"], {"c": 0.0}, term=lambda v: {"mass2": v["c"]}, units={"d": "N"})
    m = plain_model()
    ext = dg.extend(m, [me.library(m)["viscous_m2"], me.library(m)["input_offset"]])
    assert ext.units["viscous2_b"] == "s/rad" and ext.units["input_offset"] == "-" and ext.units["k"] == "1/rad"


def test_a_declared_channel_takes_the_unit_of_the_variable_its_row_reads(examples):
    drive = examples["drive"]["model"]
    assert (drive.units["position"], drive.units["force"]) == ("m", "N")            # rows x.s and x.u
    assert drive.label("position") == "position [m]"
    tanks = examples["tanks"]["model"]
    assert tanks.units["y"] == "V" and "level" not in tanks.units                  # declared: kept as it is


def _effect(name, nests=()):
    return dg.Effect(name, ["motion"], {f"{name}_p": 0.0}, term=lambda v: {}, nests=list(nests))


def test_a_nested_effect_has_the_confidence_of_the_richer_models_that_contain_it():
    """Coulomb friction kept by the nested test gets the weight of the Stribeck models too: the
    table's confidence of an effect is what Diagnosis.confidence adds up when it is selected."""
    effects = [_effect("coulomb"), _effect("stribeck", nests=["coulomb"]), _effect("delay")]
    single = {e.name: Candidate(effects=[e.name], k=1, J=2.0, parameters={}, result=None) for e in effects}
    none = Candidate(effects=[], k=0, J=3.0, parameters={}, result=None)
    pair = Candidate(effects=["delay", "stribeck"], k=2, J=1.0, parameters={}, result=None)
    for m, w in ((none, 0.0), (single["coulomb"], 0.02), (single["stribeck"], 0.08), (single["delay"], 0.1),
                 (pair, 0.8)):
        m.weight = w
    rows = {r["effect"]: r for r in ranking_table(effects, single, [none, *single.values(), pair], none)}
    assert rows["coulomb"]["confidence"] == pytest.approx(0.02)                     # by its name alone
    assert rows["coulomb"]["confidence_nested"] == pytest.approx(0.9)              # and within Stribeck's models
    assert rows["stribeck"]["confidence_nested"] == rows["stribeck"]["confidence"] == pytest.approx(0.88)
    assert rows["delay"]["confidence_nested"] == pytest.approx(0.9)


def _info(**over):
    info = dict(model="flexible", verdict="structural error explained by input_delay + coulomb_m2", selected=[
        "input_delay", "coulomb_m2"], confidence=0.97,
        nominal=dict(J=185.0, parameters={"m1": 6.27, "k": 1148.7}),
        extended=dict(model="flexible+input_delay+coulomb_m2", J=2.134, effects=["input_delay", "coulomb_m2"],
                      parameters={"m1": 5.73, "k": 1058.4, "input_delay": 0.0029168, "coulomb2_f": 41.62}),
        where=[], ranking=[
            dict(effect="input_delay", score=0.765, confidence=0.97, confidence_nested=0.97, J=43.5,
                 parameters={"input_delay": 0.004229}),
            dict(effect="stribeck_m2", score=0.542, confidence=0.97, confidence_nested=0.97, J=84.8,
                 parameters={"stribeck2_fc": 42.67}),
            dict(effect="coulomb_m2", score=0.407, confidence=0.0, confidence_nested=0.97, J=109.8,
                 parameters={"coulomb2_f": 48.39}),
            dict(effect="backlash", score=0.0, confidence=0.0, confidence_nested=0.0, J=None,
                 why=f"the linearised step diverged and no damped re-estimation converged ({TOO_LONG})",
                 parameters={"backlash_delta": 1e-3})],
        units=dict(FLEXIBLE_UNITS, input_delay="s", coulomb2_f="-", stribeck2_fc="-", backlash_delta="rad"),
        shrink=None, notes=[f"input_delay + stribeck_m2 estimated from the solution of input_delay + coulomb_m2 "
                            f"({TOO_LONG})", "a short note; with two clauses"])
    info.update(over)
    return info


def test_the_which_table_marks_the_selection_with_the_figures_of_its_verdict():
    md = _markdown(_info())
    lines = md.splitlines()
    row = next(ln for ln in lines if ln.startswith("| coulomb_m2"))
    assert "**(selected)**" in row and "| 0.97 |" in row and "coulomb2_f = 48.39 [-]" in row
    assert "**(selected)**" not in next(ln for ln in lines if ln.startswith("| stribeck_m2"))
    assert ("Selected: input_delay + coulomb_m2, confidence 0.97; re-estimated in full with them, "
            "J 185 → 2.134 (98.8 % less)") in md
    assert "input_delay = 0.0029168 [s]" in md and "m1 = 6.27 [s²/rad]" in md and "k = 1148.7 [1/rad]" in md
    backlash = next(ln for ln in lines if ln.startswith("| backlash"))
    assert "not converged: the linearised step diverged" in backlash and "κ₊·h > 20) …)" in backlash
    assert " inf " not in md and "nan" not in md
    notes = lines[lines.index("## Notes") + 2:]
    assert notes[0].endswith("(κ₊·h > 20) …) (in full: `notes` in diagnosis.json)") and len(notes[0]) < 400
    assert notes[1] == "- a short note; with two clauses"                           # short notes as they are
    # a selected effect below the first rows of the ranking is still shown, marked
    many = _info(ranking=[dict(_info()["ranking"][0], effect=f"e{i}") for i in range(9)] + _info()["ranking"][2:3])
    assert any(ln.startswith("| coulomb_m2 **(selected)**") for ln in _markdown(many).splitlines())


def test_progress_goes_to_the_log_or_stderr_or_nowhere(capsys):
    said = []
    with progress_sink(said.append, True, True) as say:
        say("a line")
    with progress_sink(None, False, True) as say:
        assert say is None
    with progress_sink(None, True, False) as say:
        say("to stderr")
    with progress_sink(None, True, True) as say:       # verbose: what the estimators print goes there too
        print("iter 1", end="")
        print(" |F| 1e-3")
        print("unfinished", end="")
    out = capsys.readouterr()
    assert said == ["a line"] and out.out == "" and out.err == "to stderr\niter 1 |F| 1e-3\nunfinished\n"
    lines = []
    w = LineWriter(lines.append)
    w.write("a\nb")
    w.write("c\n\n")
    assert lines == ["a", "bc", ""]
