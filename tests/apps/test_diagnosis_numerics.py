"""Numerical causes before physical ones (shootlab.diagnosis.numerics, issue 15 item 3).

Fast: on the mass–spring–damper with Coulomb friction withheld (a physical misfit) neither twice the
shooting points nor a declared "refinement" is taken for the answer, and a bad refinement hook is a
clear error.  Slow (about 2 minutes each on the shared 2-core machine): a record of a 200-element
confined-compression simulation diagnosed with the default 3-element model is answered
``numerical`` naming 6 elements, and with the 6 elements it names gets no significant structural
error.

The mixture record has noise on the measured outputs (displacement, pressure) and an exact load:
with noise on the given load the noise floor's surrogate, driven by the noisy load, is too low (a
12-element model on 401 points still shows its momentum and load rows at 6 times the floor) — a
limitation of the floor, not of the numerical check.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from manipulators.msd import model as msd_model
from mixtures.confined import ConfinedCompression
from mixtures.loads import DEFAULT_EXPERIMENT
from mixtures.simulation import simulate
from mixtures.identification import model as confined_model
from shootlab import diagnosis as dg
from shootlab.estimation.data import Measurements
from shootlab.diagnosis.numerics import AT_NOISE, NUMERICAL_MIN, numerical_check, refinement_check
from shootlab.diagnosis.estimators import default_estimator
from test_diagnosis import _msd_record, _u_id


# -- a physical misfit is not numerical ------------------------------------------------------------------
@pytest.fixture(scope="module")
def coulomb_record():
    return Measurements.coerce(_msd_record(0.15, _u_id, 0.01, seed=1))


def test_twice_the_points_do_not_move_a_physical_misfit(coulomb_record):
    nominal = default_estimator(msd_model(), coulomb_record)
    sigma, floor, _ = dg.floor.noise_floor(nominal, coulomb_record, default_estimator)
    out, verdict = numerical_check(nominal, floor, coulomb_record, default_estimator)
    assert verdict is None and "refinement" not in out          # the msd declares no refinement
    pc = out["points"]
    assert pc["after"]["points"] == 2 * (nominal.points - 1) + 1 and pc["after"]["success"]
    assert abs(pc["change"]) < 0.05, pc                          # J does not move with the grid
    assert not pc["numerical"]


def test_a_refinement_that_does_not_remove_the_misfit_is_not_the_answer(coulomb_record):
    # a model whose declared "refinement" is itself: the Coulomb misfit stays, nothing is numerical
    def refine():
        return msd_model()
    m = msd_model()
    m = replace(m, settings=m.settings.replace(refine=refine, resolution="the msd"))
    nominal = default_estimator(m, coulomb_record)
    out = refinement_check(nominal, coulomb_record, default_estimator)
    before = out["before"]["misfit"]["overall"]
    assert before > 2.0, out["before"]                          # friction: a free-run misfit well above the noise
    assert not out["numerical"] and out["use"] is None
    step = out["steps"][0]
    assert abs(step["removed"]) < 0.05 and step["misfit"]["overall"] == pytest.approx(before, rel=0.05)


def test_a_bad_refinement_hook_is_a_clear_error(coulomb_record):
    m = msd_model()
    nominal = default_estimator(m, coulomb_record)
    with pytest.raises(ValueError, match="refine must be a callable or None, got str"):
        m.settings.replace(refine="more")
    nominal.problem.model = replace(m, settings=m.settings.replace(refine=lambda: "finer"))
    with pytest.raises(ValueError, match="not an IdentificationModel"):
        refinement_check(nominal, coulomb_record, default_estimator)


# -- the 3-element confined model on a record of a continuum ---------------------------------------------------
def fine_grid_record(samples: int = 401, noise: float = 0.01, seed: int = 1) -> Measurements:
    """A 200-element simulation (H = 2, K = 1) of the ramp-and-hold creep test, as
    ``benchmarks/estimation_vs_casadi.py: mixture_records``, with ``noise`` (relative to the
    channel's rms) on displacement and pressure; the load exact."""
    t = np.linspace(0.0, 1.0, samples)
    sim = simulate(ConfinedCompression(elements=200), t, load=DEFAULT_EXPERIMENT, H=2.0, K=1.0)
    rng = np.random.default_rng(seed)
    out = dict(t=t, load=sim.load)
    for c in ("displacement", "pressure"):
        y = getattr(sim, c)
        out[c] = y + noise * np.sqrt(np.mean(y ** 2)) * rng.standard_normal(t.size)
    return Measurements.coerce(out)


@pytest.mark.slow
def test_three_elements_on_a_fine_grid_record_is_numerical_use_six(tmp_path):
    d = dg.diagnose(confined_model(), fine_grid_record(), seed=0)
    assert d.status == "numerical" and d.success, d.verdict
    assert d.verdict.startswith("the misfit is numerical: use 6 elements"), d.verdict
    assert d.selected == [] and d.which == {}                    # the effect library was not consulted
    rc = d.numerical["refinement"]
    before, use = rc["before"]["misfit"]["overall"], rc["use"]["misfit"]["overall"]
    assert before > 1.5 and use < AT_NOISE and rc["use"]["removed"] > NUMERICAL_MIN, rc
    assert rc["use"]["model"] == "confined[N=6]" and rc["use"]["resolution"] == "6 elements"
    assert abs(rc["use"]["parameters"]["H"] / 2.0 - 1) < 0.015 and abs(rc["use"]["parameters"]["K"] - 1) < 0.015
    assert not d.numerical["points"]["numerical"]                # the 3-element grid itself is resolved
    info = dg.write_report(d, tmp_path / "out", plots=False)
    assert info["status"] == "numerical" and info["numerical"]["refinement"]["use"]["resolution"] == "6 elements"
    assert "## Numerical checks" in (tmp_path / "out" / "report.md").read_text()


@pytest.mark.slow
def test_with_the_elements_it_names_the_same_record_is_at_the_noise_floor():
    d = dg.diagnose(confined_model(elements=6), fine_grid_record(), seed=0)
    assert d.status == "no_structural_error" and not d.significant, d.verdict
    assert "no significant structural error" in d.verdict
