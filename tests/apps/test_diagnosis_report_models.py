"""What the diagnosis shows for the project's models: the effects' units from the model's, carried
into the extended model, a declared channel's unit, and the Which table with the figures of its
verdict."""
from __future__ import annotations
import runpy
from pathlib import Path

import pytest

from manipulators import effects as me
from manipulators.flexible import UNITS as FLEXIBLE_UNITS
from manipulators.flexible import plain_model
from manipulators.msd import model as msd_model
from mixtures import effects as xe
from mixtures.identification import model as confined_model
from shootlab import diagnosis as dg
from shootlab.diagnosis.mechanical import mechanical_library
from shootlab.diagnosis.report import _markdown

ROOT = Path(__file__).resolve().parents[2]


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
