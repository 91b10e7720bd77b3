"""Nested friction laws weighed by output error (shootlab.diagnosis.nested.by_output_error): the
user's pendulum (tests/shared.py) with dry friction that scipy's Radau integrates — a
switch over tanh(ω/0.01), narrower than the library's smooth sign (5 % of the speed's RMS), and
Stribeck's hump decaying exponentially, not as the library's Gaussian."""
import pytest

from shootlab.diagnosis import library_for
from shootlab.diagnosis.nested import RICHER_Z, by_output_error, nested_in
from shootlab.estimation.data import noise_level
from shared import friction_record, pendulum


def test_nested_forms_are_one_effect_replaced_by_one_it_nests():
    lib = library_for(pendulum())
    assert nested_in(lib, ["coulomb"], ["stribeck"])
    assert nested_in(lib, ["coulomb", "input_delay"], ["input_delay", "stribeck"])
    assert not nested_in(lib, ["stribeck"], ["coulomb"])
    assert not nested_in(lib, ["viscous"], ["stribeck"])
    assert not nested_in(lib, ["coulomb"], ["stribeck", "input_delay"])


def test_a_richer_fit_held_on_its_bound_never_shows_the_simpler_form_suffices():
    """z ≥ RICHER_Z takes the richer form, on its bound or not; z ≤ −1.28 takes the simpler one
    only where the richer fit is at its own minimum, not held on a bound; between, neither."""
    import math
    from types import SimpleNamespace

    from shootlab.diagnosis.nested import _on_edge, decided

    lib = library_for(pendulum())
    edge = _on_edge([lib["stribeck"]], dict(stribeck_vst=lib["stribeck"].bounds["stribeck_vst"][0] * (1 + 1e-5)))
    assert edge and edge[0].startswith("stribeck_vst = ")
    assert not _on_edge([lib["stribeck"]], dict(stribeck_vst=lib["stribeck"].bounds["stribeck_vst"][0] * 1.2))
    half_open = [SimpleNamespace(bounds={"a": (0.0, math.inf)})]
    assert not _on_edge(half_open, dict(a=3.0)) and _on_edge(half_open, dict(a=0.0))
    assert decided(dict(z=RICHER_Z + 0.1, on_bound=edge))
    assert decided(dict(z=-2.0, on_bound=[]))
    assert not decided(dict(z=-2.0, on_bound=edge))
    assert not decided(dict(z=0.5, on_bound=[]))


def test_the_confidence_left_by_a_weighing_is_read_from_the_answers_side():
    """An undecided z = 0.53 (the richer form a little better) leaves a Coulomb answer at most
    Φ(−0.53) = 0.30 and a Stribeck answer at most Φ(0.53) = 0.70: the chance that each predicts the
    records better than the other."""
    from shootlab.diagnosis.lookalikes import _from_selection, _phi

    weighed = dict(z=0.53, effects=["stribeck"], simple=["coulomb"])
    assert _phi(_from_selection(weighed, ["coulomb"])) == pytest.approx(0.298, abs=1e-3)
    assert _phi(_from_selection(weighed, ["stribeck"])) == pytest.approx(0.702, abs=1e-3)


def test_an_answer_by_output_error_reports_its_own_parameters():
    """After a switch to a richer form estimated by output error, diagnosis.json's
    ``selected_parameters`` are the answer's (the free run's estimate), not those of the ranking's
    selection it replaced; with a TPBVP estimate, that estimate's."""
    from types import SimpleNamespace
    from shootlab.diagnosis.outcome import Diagnosis

    model = pendulum()
    lib = library_for(model)
    oe = dict(stribeck_fc=0.08, stribeck_fs=0.4, stribeck_vst=0.1)
    d = Diagnosis(model=model, library=lib, data=None, validation=None, nominal=None, floor=None, noise={},
                  where=[], significant=True, which=dict(selected_parameters=dict(coulomb_f=0.1)),
                  selected=["stribeck"], verdict="", extended=None, shrink=None, skipped={}, seconds={},
                  free_run=dict(extended=dict(parameters=dict(model.prior, **oe))))
    assert d.selected_parameters() == dict(stribeck_fc=0.08, stribeck_fs=0.4, stribeck_vst=0.1)
    d.free_run, d.selected = None, ["coulomb"]
    d.extended = SimpleNamespace(parameters=dict(model.prior, coulomb_f=0.12))
    assert d.selected_parameters() == dict(coulomb_f=0.12)


@pytest.mark.slow
@pytest.mark.parametrize("law", ["coulomb", "stribeck"])
def test_stribeck_by_output_error_is_taken_only_where_the_records_need_it(law):
    """On the Coulomb record the richer Stribeck form, fitted alike, is not taken (z below
    RICHER_Z, whatever it makes of the narrower switch); on the Stribeck record it predicts the
    validation record better than Coulomb's and z is positive."""
    model = pendulum()
    data, validation = friction_record(law, False, 0), friction_record(law, True, 100)
    lib = library_for(model, data)
    sigma, sigma_v = noise_level(data, ["angle"]), noise_level(validation, ["angle"])
    got = by_output_error(model, lib, ["coulomb"], dict(model.prior, coulomb_f=0.05), ["stribeck"], None,
                          data, validation, sigma, sigma_v, lambda s: None)
    assert got is not None
    assert got["effects"] == ["stribeck"] and got["simple"] == ["coulomb"]
    if law == "coulomb":
        assert got["z"] < RICHER_Z, got
    else:
        assert got["cost_richer"] < got["cost_simple"] and got["z"] > 0, got
        assert got["parameters"]["stribeck_fs"] > got["parameters"]["stribeck_fc"] > 0, got["parameters"]


@pytest.mark.slow
@pytest.mark.parametrize("law", ["none", "coulomb"])
def test_an_effect_added_to_a_selection_is_weighed_from_its_own_initial_values(law):
    """A pair set aside beside its better member is weighed by output error as a richer form: the
    added effect starts from its own initial values (Coulomb friction at 0: the simpler fit
    itself), so its fit ends at or below the simpler one's cost; on the Coulomb record it predicts
    both records better by more than RICHER_Z (z = 2.66), with the record's level, on the record
    without friction by less."""
    from shootlab.diagnosis.nested import nested_fits

    model = pendulum()
    data, validation = friction_record(law, False, 0), friction_record(law, True, 100)
    lib = library_for(model, data)
    sigma, sigma_v = noise_level(data, ["angle"]), noise_level(validation, ["angle"])
    fits = nested_fits(model, lib, ["input_offset"], dict(model.prior, input_offset=0.0), ["input_offset", "coulomb"],
                       None, data, lambda s: None)
    assert fits["tries"][0]["start"] == {"coulomb_f": 0.0}
    assert fits["rich"] is not None and fits["rich"].cost <= fits["simple"].cost * (1 + 1e-9)
    got = by_output_error(model, lib, ["input_offset"], dict(model.prior, input_offset=0.0),
                          ["input_offset", "coulomb"], None, data, validation, sigma, sigma_v, lambda s: None)
    assert got["effects"] == ["input_offset", "coulomb"] and got["simple"] == ["input_offset"]
    if law == "coulomb":
        assert got["z"] > RICHER_Z, got
        assert got["parameters"]["coulomb_f"] == pytest.approx(0.1, rel=0.2)
    else:
        assert got["z"] < RICHER_Z, got


def test_the_weighing_is_bounded_in_free_runs_and_skipped_where_they_are_slow(monkeypatch):
    """The fits of a weighing stop at a budget of free runs, not seconds (the same point on every
    machine): with none, the simpler fit stops after its first iteration and the richer one is not
    tried; where the simpler fit's pace, counted in right-hand-side calls (the same on every
    machine), would take the budget past WEIGH_CALLS, the richer fit is not tried and the progress
    line says why."""
    from shootlab.diagnosis import nested
    from shootlab.diagnosis.composition import extend
    from shootlab.estimation import free_run

    model = pendulum()
    data = friction_record("coulomb", False, 0)
    lib = library_for(model, data)

    def fits():
        said = []
        out = nested.nested_fits(model, lib, ["input_offset"], dict(model.prior, input_offset=0.0),
                                 ["input_offset", "coulomb"], None, data, said.append)
        return out, said
    monkeypatch.setattr(nested, "WEIGH_RUNS", 0)
    out, said = fits()
    assert not out["simple"].success and "budget of 0 free runs" in out["simple"].message
    assert out["rich"] is None and out["tries"] == []
    monkeypatch.setattr(nested, "WEIGH_RUNS", 5000)
    monkeypatch.setattr(nested, "WEIGH_CALLS", 1.0)
    out, said = fits()
    assert out["simple"].success and out["rich"] is None and out["tries"] == []
    assert any("not tried" in s and "right-hand-side calls a free run" in s for s in said), said
    assert out["not_tried"].startswith("at ") and "(more than 1; here " in out["not_tried"]
    calls = float(out["not_tried"].split()[1])       # the simpler fit's calls per run, counted anew
    with free_run.counted() as work:
        free_run.simulate(extend(model, [lib["input_offset"]], data=data), data, out["simple"].parameters)
    assert 0.2 * calls < work.calls < 5 * calls
    # the verdict says why the look-alike stands
    from shootlab.diagnosis.lookalike_words import words
    notes, sigma = {}, noise_level(data, [c for c in model.measured if c not in model.given])
    assert by_output_error(model, lib, ["input_offset"], dict(model.prior, input_offset=0.0),
                           ["input_offset", "coulomb"], None, data, data, sigma, sigma, said.append, notes) is None
    note = notes.pop(frozenset(["input_offset", "coulomb"]))
    assert notes == {} and "(more than 1; here " in note
    assert note.startswith("input_offset + coulomb was not weighed against input_offset by output error: at ")
    assert words(dict(rivals=[], not_weighed=[note]), ["input_offset"]) == "; " + note
