"""What the diagnosis says (shootlab.diagnosis.progress, .which's ranking, the effects' units):
messages summarised at a sentence boundary, a failed fit said in words, units composed as products
of powers, the Which table's confidence the one the verdict adds up.  Fast: no estimation."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
from shootlab import diagnosis as dg
from shootlab.diagnosis.mechanical import unit_product
from shootlab.diagnosis.progress import LineWriter, brief, fit_line, progress_sink
from shootlab.diagnosis.selection import Candidate, ranking_table

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


def test_the_evidence_section_says_the_noise_shape_the_floor_was_drawn_with():
    """report.md's Evidence section: a channel whose noise is not white Gaussian is named with its
    shape (the colour, the tails, what the 4th differences read), as ``diagnosis.json`` keeps it."""
    from shootlab.diagnosis.noise import NoiseShape
    from shootlab.diagnosis.report import _evidence_section

    shape = NoiseShape(0.7, 0.5, 1.2)
    info = dict(evidence=dict(misfit=3.0, floor_misfit=1.1, significant=True, ratio=7.4, p_value=1e-4),
                nominal=dict(J=2.0), where=[dict(significant=True)],
                floor=dict(J=1.0, noise_shapes={"angle": dict(white=0.5, pole=0.7, tails=1.2, reads=shape.reads)}))
    text = "\n".join(_evidence_section(info))
    assert "The noise on angle is not white Gaussian: white 50 % + AR(1) pole 0.70, heavy tails (1.20×" in text
    assert f"4th differences read {shape.reads:.2f} of it" in text
    assert shape.reads == pytest.approx(NoiseShape(0.7, 0.5).reads / 1.2)
