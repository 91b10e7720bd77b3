"""The free-run screen (shootlab/diagnosis/free_run_screen.py) on a first-order plant whose records
are made by scipy's LSODA (not shootlab's free run): a withheld input offset is named and confirmed
on the validation record, a clean record gets no verdict, a refinement that helps is taken first."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import shootlab
from shootlab.estimation.data import Measurements
from shootlab.diagnosis import Effect, Library
from shootlab.diagnosis.free_run_screen import SHRINK_MIN, screen

A_TRUE = 2.0


def _model(prior_a: float = 1.0):
    """x' = −a x + u (a > 0), x and u measured, u given."""
    return shootlab.model(name="lag", states={"x": "d"}, inputs=["d", "u"], parameters={"a": prior_a},
                          equations={"motion": lambda v: v.d + v.a * v.x - v.u, "position": lambda v: v.x,
                                     "input": lambda v: v.u},
                          channels={"position": "x", "input": "u"}, given=["u"], bounds={"a": (0.0, float("inf"))})


def _library() -> Library:
    offset = Effect(name="input_offset", equations=["motion"], parameters={"u0": 0.0},
                    term=lambda v: {"motion": -v["u0"]})
    cubic = Effect(name="cubic_damping", equations=["motion"], parameters={"c3": 0.0},
                   term=lambda v: {"motion": v["c3"] * v["x"] ** 3})
    return Library(name="lag", effects=[offset, cubic], initial_state="rest", free_run_screen=True)


def _record(u, offset: float, seed: int) -> Measurements:
    """x' = −a x + u(t) + offset by LSODA on a fine grid, 201 samples on [0, 4], 1 % noise on x."""
    t = np.linspace(0.0, 4.0, 201)
    sol = solve_ivp(lambda tt, x: -A_TRUE * x + u(tt) + offset, (0, 4), [0.0], t_eval=t, rtol=1e-10, atol=1e-12)
    x = sol.y[0]
    rng = np.random.default_rng(seed)
    return Measurements(t, {"x": x + 0.01 * np.std(x) * rng.standard_normal(t.size), "u": u(t)})


def _pair(offset: float, seed: int = 0):
    ident = _record(lambda t: np.sin(2 * t) + 0.5 * np.sin(5 * t), offset, seed)
    valid = _record(lambda t: 0.8 * np.tanh(3 * np.sin(1.3 * t)), offset, seed + 1000)   # smooth: between
    return ident, valid                                 # samples the free run's input is linear


def test_a_withheld_offset_is_named_and_confirmed_on_the_validation_record():
    ident, valid = _pair(offset=0.1)
    lib = _library()
    out = screen(_model(), lib, lib.effects, ident, valid)
    assert out["selected"] == ["input_offset"], out["verdict"]
    row = {r["effect"]: r for r in out["candidates"]}
    assert row["input_offset"]["parameters"]["u0"] == pytest.approx(0.1, rel=0.05)
    assert row["input_offset"]["parameters"]["a"] == pytest.approx(A_TRUE, rel=0.02)
    assert row["input_offset"]["validation_shrink"] > 0.9
    assert out["confidence"] > 0.9
    assert out["shrink"]["validation"]["shrink"] > 0.5


def test_a_clean_record_gets_no_verdict():
    ident, valid = _pair(offset=0.0, seed=3)
    lib = _library()
    out = screen(_model(), lib, lib.effects, ident, valid)
    assert out["selected"] == []
    assert all(r["validation_shrink"] < SHRINK_MIN for r in out["candidates"])
    assert out["nominal"]["parameters"]["a"] == pytest.approx(A_TRUE, rel=0.02)


def test_a_refinement_that_helps_is_taken_before_the_effects():
    """A coarse model (a fixed wrong time constant in a 'discretised' version) declares its refinement:
    the screen moves to it and, on a clean record, answers 'numerical'."""
    ident, valid = _pair(offset=0.0, seed=5)
    lib = _library()
    coarse = shootlab.model(name="lag[coarse]", states={"x": "d"}, inputs=["d", "u"], parameters={"a": 1.0},
                            equations={"motion": lambda v: v.d + v.a * v.x - 0.8 * v.u, "position": lambda v: v.x,
                                       "input": lambda v: v.u},
                            channels={"position": "x", "input": "u"}, given=["u"], bounds={"a": (0.0, float("inf"))})
    fine = _model()
    coarse.settings = coarse.settings.replace(refine=lambda: fine)
    fine.settings = fine.settings.replace(resolution="the fine model")
    out = screen(coarse, lib, lib.effects, ident, valid)
    assert out["model"] == "lag"
    assert out["refinements"][0]["shrink"] > 0.5
    assert out["selected"] == [] and out["verdict"].startswith("numerical: use the fine model")


def test_diagnose_consults_the_screen_when_the_tpbvp_finds_nothing():
    """The whole diagnosis with a library that opts in: on a clean record the TPBVP's verdict is 'no
    significant structural error', the screen runs, finds nothing, and is reported."""
    from shootlab.diagnosis import diagnose

    ident, valid = _pair(offset=0.0, seed=7)
    d = diagnose(_model(), ident, _library(), validation=valid, numerics=False)
    assert d.status == "no_structural_error" and d.selected == []
    assert d.free_run is not None and d.free_run["selected"] == []
    info = d.to_dict()
    assert info["free_run"]["nominal"]["success"] and "shrink" not in info["free_run"]


def test_a_screen_verdict_is_reported_with_its_output_error_fit(tmp_path, monkeypatch):
    """When the TPBVP's ranking selects nothing (here: blinded), the screen's selection becomes the
    verdict; diagnosis.json's extended model is its output-error fit and report.md shows the screen."""
    import json

    from shootlab.diagnosis import diagnose, pipeline, write_report

    real = pipeline.rank

    def blind(*args, **kwargs):
        return dict(real(*args, **kwargs), selected=[], verdict="no candidate explains it")
    monkeypatch.setattr(pipeline, "rank", blind)
    ident, valid = _pair(offset=0.1, seed=7)
    d = diagnose(_model(), ident, _library(), validation=valid, numerics=False)
    assert d.status == "confirmed" and d.selected == ["input_offset"] and d.success
    info = write_report(d, tmp_path / "out", plots=True)
    assert info["extended"]["method"] == "output-error"
    assert info["extended"]["parameters"]["u0"] == pytest.approx(0.1, rel=0.05)
    assert "validation.png" in info["figures"]
    md = (tmp_path / "out" / "report.md").read_text()
    assert "The free run on the validation record" in md and "output error, cost" in md
    assert json.loads((tmp_path / "out" / "diagnosis.json").read_text())["free_run"]["selected"] == ["input_offset"]
