"""The ``"fitted"`` free-run start (:func:`shootlab.diagnosis.shrinkage.free_run_start`): on a record
of a mass–spring–damper that starts moving (s = 0.3, v = −0.5, the velocity not measured) it is
recovered from the record; output error with it estimates the start with the parameters, where
the ``"rest"`` start biases them."""
from __future__ import annotations

import numpy as np
import pytest

import shootlab
from shootlab.diagnosis.free_run_screen import output_error_fit
from shootlab.diagnosis.shrinkage import free_run_start
from shootlab.estimation.data import Measurements
from shootlab.estimation.free_run import simulate

TRUE = dict(m=1.0, b=0.4, k=4.0)
START = [0.3, -0.5]
NOISE = 0.01


def _msd():
    return shootlab.model(
        name="msd", states={"s": "v", "v": "a"}, inputs=["a", "u"], parameters={"m": 1.0, "b": 1.0, "k": 1.0},
        equations={"motion": lambda x: x.m * x.a + x.b * x.v + x.k * x.s - x.u,
                   "position": lambda x: x.s, "force": lambda x: x.u},
        channels={"position": "position", "force": "force"})


def _record(model):
    t = np.linspace(0.0, 10.0, 401)
    u = np.sin(t)
    run = simulate(model, Measurements(t, {"position": np.zeros_like(t), "force": u}), TRUE, START)
    rng = np.random.default_rng(1)
    return Measurements(t, {"position": run["position"] + NOISE * rng.standard_normal(t.size), "force": u})


def test_the_fitted_start_is_the_records_own():
    """Least squares over the start, 401 samples of noise 0.01: the start's standard error is about
    0.01/√401 times the conditioning of (s0, v0) on a lightly damped response — well inside 0.01
    in each state; the rest start (nothing measured under the state's name) is 0."""
    model = _msd()
    data = _record(model)
    assert free_run_start(model, data, "rest", TRUE) == [0.0, 0.0]
    fitted = free_run_start(model, data, "fitted", TRUE)
    assert fitted == pytest.approx(START, abs=NOISE)
    with pytest.raises(ValueError, match="run's parameters"):         # nothing to fit the start with
        free_run_start(model, data, "fitted")


def test_output_error_estimates_the_start_with_the_parameters():
    """From m 1, b 0.3, k 3.5: with the fitted start the estimates are the truth to within 2 %
    (the noise is 1 % of a response of amplitude ~0.3), the start to within the noise; from rest
    the start's transient is fitted by the parameters instead (b off by more than 20 %)."""
    model = _msd()
    data = _record(model)
    guess = dict(m=1.0, b=0.3, k=3.5)
    fitted = output_error_fit(model, data, guess, "fitted")
    assert fitted.success, fitted.message
    assert fitted.parameters == pytest.approx(TRUE, rel=0.02)
    assert list(fitted.initial_state) == pytest.approx(START, abs=NOISE)
    rest = output_error_fit(model, data, guess, "rest")
    assert rest.initial_state is None
    assert abs(rest.parameters["b"] - TRUE["b"]) > 0.2 * TRUE["b"]
    assert fitted.cost < rest.cost


def test_made_records_start_at_rest():
    """A record made rather than measured (a floor surrogate, a proposed experiment) has no start to
    fit, and a start fitted with a model's parameters to a record they do not explain would carry
    that model's error into it: ``"fitted"`` gives the rest start there; the other rules stand."""
    from shootlab.diagnosis.shrinkage import made_start

    model = _msd()
    data = _record(model)
    assert made_start("fitted") == "rest"
    assert made_start("data") == "data" and made_start(_record) is _record
    assert free_run_start(model, data, made_start("fitted"), TRUE) == free_run_start(model, data, "rest", TRUE)


def test_a_fit_is_weighed_from_its_own_start():
    """The weighing of nested fits runs each fit on its own record from the start the fit estimated
    (not one refitted after it), and from the library's rule where the fit estimated none."""
    from types import SimpleNamespace

    from shootlab.diagnosis.nested import _start

    model = _msd()
    data = _record(model)
    own = _start(SimpleNamespace(initial_state=np.array(START)), "fitted")
    assert free_run_start(model, data, own, TRUE) == START
    assert _start(SimpleNamespace(initial_state=None), "rest") == "rest"
