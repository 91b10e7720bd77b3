"""Free runs (shootlab/free_run.py): the stiff path by Radau IIA against exact and LSODA solutions."""
import numpy as np
import pytest
import torch

import shootlab.free_run as fr
from mixtures.identification import model as confined
from mixtures.simulation import simulated_measurements

D = torch.float64


def test_radau_on_samples_is_third_order_and_damps_the_stiff_mode():
    """s' = λ (s − g(t)) + g'(t) with g = sin t and λ = −1e5: s = g + (s0 − g(0)) e^{λt}; the
    stiff transient is gone after the first sample and the slow part is followed to order 3."""
    lam = -1e5

    def rhs(t, s):
        return lam * (s - torch.sin(t)[..., None]) + torch.cos(t)[..., None]

    errors = []
    for samples in (21, 41):
        ts = torch.linspace(0.0, 2.0, samples, dtype=D)
        S = fr._radau_on_samples(rhs, torch.tensor([1.0], dtype=D), ts)
        exact = torch.sin(ts)                 # the transient e^{λt} is below 1e-200 after one sample
        errors.append(float((S[1:, 0] - exact[1:]).abs().max()))
    assert errors[1] < 1e-6
    assert errors[1] < errors[0] / 4            # halving the samples' spacing: order ≥ 2 seen


def test_radau_on_samples_reports_a_failed_iteration_as_none():
    def rhs(t, s):                       # a finite-time blow-up: Newton cannot follow it
        return 1e6 * s ** 3

    assert fr._radau_on_samples(rhs, torch.tensor([1.0], dtype=D), torch.linspace(0, 1, 5, dtype=D)) is None


@pytest.mark.parametrize("elements", [3, 6])
def test_stiff_free_run_agrees_with_lsoda(elements, monkeypatch):
    data = simulated_measurements(elements=elements, noise=0.0)
    md = confined(elements=elements)
    params, x0 = dict(H=2.0, K=1.0), np.zeros(elements)
    radau = fr.simulate(md, data, params, x0)
    monkeypatch.setattr(fr, "_radau_on_samples", lambda *a, **k: None)          # the LSODA fallback
    lsoda = fr.simulate(md, data, params, x0)
    for ch in ("displacement", "pressure"):
        assert np.abs(radau[ch] - lsoda[ch]).max() <= 1e-4 * np.ptp(lsoda[ch]), ch
    # and both reproduce the finite-element simulation that made the record (no noise), up to the
    # load between samples: the record's simulator had the exact ramp, the free run its samples
    assert np.abs(radau["displacement"] - data.channels["displacement"]).max() <= 3e-4 * np.ptp(lsoda["displacement"])
