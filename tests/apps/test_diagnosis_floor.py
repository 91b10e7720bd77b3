"""The noise floor on records nobody here simulated (shootlab.diagnosis.floor, issue 15).

Records of the independently written confined-compression simulator
(:mod:`benchmarks.independent.mixture`: 120 finite volumes, Radau, 80 % white + 20 % AR(1) noise,
noisy load), diagnosed with the 6-element model the benchmark uses (implicit midpoint on 51
shooting points).  Each estimate takes 2–10 s; the replicated-floor test (six estimates) is ``slow``.

* The surrogate's free run starts where the diagnosis's free runs start (the library's "rest"),
  so that the surrogate *without noise* leaves nothing: from the nominal estimate's first-sample
  state (the old start) the noise-free surrogate left J = 0.030, 59 % of the nominal's 0.051
  (seed 100), from rest 4.6e-5.
* The floor is the mean over several surrogates and the rows' degrees of freedom come from their
  spread: on the clean record seed 211 one surrogate gave J/J_floor 2.31 and the autocorrelation's
  150–401 effective samples made every row significant.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.independent import mixture as im  # noqa: E402
from mixtures import effects as xe  # noqa: E402
from mixtures.identification import model as confined_model  # noqa: E402
from shootlab.diagnosis import floor as floor_mod  # noqa: E402
from shootlab.diagnosis.where import locate, replicate_dof  # noqa: E402
from shootlab.estimation.weights import from_data  # noqa: E402


def _nominal(seed: int):
    model = confined_model(elements=im.NOMINAL_ELEMENTS)
    lib = xe.library(model)
    ident, _, _ = im.data(None, "moderate", 0.01, seed)
    m = from_data(model, ident)
    return m, lib, ident, lib.estimator(m, ident)


def test_replicate_dof_reads_the_degrees_of_freedom_of_chi2_mean_squares():
    rng = np.random.default_rng(0)
    for nu in (10.0, 30.0, 300.0):
        ms = rng.chisquare(nu, size=400) / nu
        assert replicate_dof(ms) == pytest.approx(nu, rel=0.2)
    assert replicate_dof([1.0, 1.1]) == math.inf            # too few draws: the autocorrelation decides


def test_the_noise_free_surrogate_leaves_nothing(monkeypatch):
    """The surrogate noise_floor builds, without its noise, is fitted to far below the nominal J:
    its free run does not open with a transient the estimator cannot follow."""
    m, lib, ident, nominal = _nominal(100)
    assert nominal.success
    starts = []
    original = floor_mod.surrogate_data

    class Captured(Exception):
        pass

    def spy(model, data, parameters, sigma, initial_state=None, seed=0, response=None):
        starts.append(initial_state)
        raise Captured          # the start is all this test needs (noise_floor reports it and goes on)
    monkeypatch.setattr(floor_mod, "surrogate_data", spy)
    _, floor, notes = floor_mod.noise_floor(nominal, ident, lib.estimator, draws=1, initial_state=lib.initial_state)
    assert floor is None and starts, notes
    quiet = original(m, ident, nominal.parameters, {c: 0.0 for c in ident.channels}, starts[0])
    J0 = lib.estimator(m, quiet, initial=dict(nominal.parameters)).J
    assert J0 < 0.01 * nominal.J, (J0, nominal.J)


@pytest.mark.slow
def test_a_clean_record_is_not_significant_against_the_replicated_floor():
    """About 50 s on the shared 2-core machine (six estimates)."""
    m, lib, ident, nominal = _nominal(211)
    _, floor, _ = floor_mod.noise_floor(nominal, ident, lib.estimator, seed=211, initial_state=lib.initial_state)
    reps = floor.draws
    assert len(reps) == floor_mod.FLOOR_DRAWS and floor.J == pytest.approx(np.mean([r.J for r in reps]))
    where = locate(nominal, floor)
    assert not [w["equation"] for w in where if w["significant"]]
    # one surrogate (the first of the same draws) with the autocorrelation's degrees of freedom alone
    # flags rows of this clean record: the replicates are what keeps it quiet
    single = locate(nominal, floor_mod.NoiseFloor(reps[:1]))
    assert [w["equation"] for w in single if w["significant"]]
    assert 0.67 < nominal.J / float(np.mean([r.J for r in reps])) < 1.5      # measured 1.22
