"""Free runs (shootlab/estimation/free_run.py) of the project's models: the stiff mixture against
LSODA, the Jacobian of a free run, several parameter sets in one run."""
import numpy as np
import pytest
import torch

import shootlab.estimation.free_run as fr
from mixtures.identification import model as confined
from mixtures.simulation import simulated_measurements

D = torch.float64


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


def test_the_free_runs_jacobian_is_central_differences_of_its_rhs(monkeypatch):
    """The free run's own Jacobian (ζ's derivative from the least squares' QR factor; F
    differenced only where it moves with the states) against central differences of the whole
    right-hand side: the confined model (F independent of the states) and with a strain-dependent
    permeability (F moves with them), to 1e-8 of the largest entry."""
    from mixtures.effects import library as mixture_library
    from shootlab.diagnosis.composition import extend
    from shootlab.bvp.tangents import VectorField

    data = simulated_measurements(elements=3, noise=0.0)
    md = confined(elements=3)
    seen = []
    run = fr._radau_in_parallel
    monkeypatch.setattr(fr, "_radau_in_parallel", lambda rhs, *a, **k: seen.append(rhs) or run(rhs, *a, **k))
    lib = mixture_library(md)
    richer = extend(md, [lib["strain_dependent_permeability"]], data=data)
    for m in (md, richer):
        params = dict(m.prior, H=2.0, K=1.0)
        params.update({k: 0.5 for k in params if k not in ("H", "K")})
        fr.simulate(m, data, params, np.zeros(3))
        field = seen[-1]
        assert isinstance(field, VectorField)
        gen = torch.Generator().manual_seed(0)
        s = 1e-2 * torch.randn(50, 3, generator=gen, dtype=D)
        tt = torch.linspace(0.1, float(data.t[-1]), 50, dtype=D)
        own = field.jacobian(tt, s)[1]
        fd = fr._jacobian(field.fun, tt, s)
        assert float((own - fd).abs().max()) <= 1e-8 * float(fd.abs().max()), m.name


def test_simulate_many_equals_one_run_per_parameter_set():
    """Several parameter sets as one batch give each set's own free run: the stiff path (the
    confined model, Radau IIA, to 1e-10 of each channel's range) and the non-stiff one (the
    mass–spring–damper, RK4, to 1e-12); mismatched starts are a clear error."""
    from manipulators.msd import model as msd_model
    from manipulators.rig import msd_data
    from shootlab.estimation.data import Measurements

    data = simulated_measurements(elements=3, noise=0.0)
    sets = [dict(H=2.0, K=1.0), dict(H=2.00002, K=1.0), dict(H=1.5, K=0.7)]
    md = confined(elements=3)
    many = fr.simulate_many(md, data, sets, [np.zeros(3)] * 3)
    for ps, run in zip(sets, many):
        one = fr.simulate(md, data, ps, np.zeros(3))
        for ch in ("displacement", "pressure"):
            assert np.abs(run[ch] - one[ch]).max() <= 1e-10 * np.ptp(one[ch]), (ps, ch)
    t = np.linspace(0.0, 2.0, 201)
    d = msd_data(t=t, m=2.0, b=0.5, k=3.0, noise=0.0, seed=0)
    rec = Measurements(d["t"], {"u": d["u"], "s": d["s"]})
    sets = [dict(m=2.0, b=0.5, k=3.0), dict(m=1.0, b=0.1, k=5.0)]
    starts = [[0.0, 0.0], [0.01, -0.02]]
    many = fr.simulate_many(msd_model(), rec, sets, starts)
    for ps, x0, run in zip(sets, starts, many):
        one = fr.simulate(msd_model(), rec, ps, x0)
        assert np.abs(run["s"] - one["s"]).max() <= 1e-12 * np.ptp(one["s"])
        assert np.array_equal(run["t"], one["t"])
    with pytest.raises(ValueError, match="2 parameter sets but 1 initial states"):
        fr.simulate_many(msd_model(), rec, sets, starts[:1])


def test_a_free_run_whose_frozen_sweeps_stall_is_solved_with_exact_interval_jacobians(monkeypatch):
    """The rig's Stribeck model (a hump of v_st = 0.2 rad/s on the load) free-running over 0.8 s of
    the sine sweep, where Radau IIA's sweeps with frozen interval Jacobians stall (at these values;
    here they are made to fail whatever they do): those with exact ones are tried before the run
    sample by sample, converge, and give its states (the same scheme) to ten times the Newton
    test's 1e-9 (1 + max|S|) on the first 200 samples."""
    from manipulators.effects import library
    from manipulators.flexible import plain_model
    from manipulators.records import sweep
    from shootlab.diagnosis.composition import extend
    from shootlab.estimation.data import Measurements

    data = Measurements.coerce(sweep(duration=0.8)[0])
    md = plain_model()
    richer = extend(md, [library(md)["stribeck_m2"]], data=data)
    params = dict(richer.prior, m1=6.27, m2=0.55712, k=1148.7, b=5.0277, stribeck2_fc=33.6, stribeck2_fs=62.4,
                  stribeck2_vst=0.2)
    tried = []
    shoot = fr._shoot_samples

    def frozen_fails(integ, rhs, s0, ts, **k):
        tried.append((k.get("jacobian", "frozen"), rhs, s0))
        return None if tried[-1][0] == "frozen" else shoot(integ, rhs, s0, ts, **k)
    monkeypatch.setattr(fr, "_shoot_samples", frozen_fails)
    monkeypatch.setattr(fr, "_radau_on_samples", lambda *a, **k: pytest.fail("went sample by sample"))
    run = fr.simulate(richer, data, params)
    assert [j for j, *_ in tried] == ["frozen", "autograd"]
    _, rhs, s0 = tried[-1]
    ts = torch.as_tensor(data.t, dtype=D)
    together = shoot(fr._radau(), rhs, s0, ts, jacobian="autograd")
    assert np.array_equal(run["state:s2"], together[:, 0, 1].numpy())        # what the free run returned
    monkeypatch.undo()
    alone = fr._radau_on_samples(rhs, s0, ts[:200])
    assert float((together[:200] - alone).abs().max()) <= 1e-8 * (1 + float(together.abs().max()))
