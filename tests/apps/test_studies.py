"""Studies: suggest_shooting_points checked by sweeps, sweeps (serial and Dask), stiffness, scaling, CLI."""
from __future__ import annotations

import json
import math
import textwrap

import numpy as np
import pytest
import torch

import shootlab
from shootlab.bvp.suggest import stability_function
from studies import problems, scaling, stiffness, sweep
from studies.__main__ import main

f64 = torch.float64


def test_confined_report_stiffness_and_pairing(tmp_path):
    """Report ch. 5: κ ≈ −5000 at H = K = 4 (±4895.7 here), 'h ≈ 4e−4, 2500 points' for an explicit
    scheme; the TPBVP is Hamiltonian (±λ pairs)."""
    res = stiffness.analyse("confined", {"elements": 3}, points=21, integrators=["euler:1", "rk4:1"])
    s = res["summary"]
    assert s["kappa_min"] == pytest.approx(-4895.7, rel=1e-4) and s["kappa_plus_max"] == pytest.approx(4895.7, rel=1e-4)
    assert s["hamiltonian_pairs"] and s["pairing_error_max"] < 1e-8
    assert 2300 <= res["predictions"]["euler:1"]["m"] <= 2600       # h = 2/4896 = 4.1e-4
    assert 1700 <= res["predictions"]["rk4:1"]["m"] <= 1800
    out = stiffness.write(res, tmp_path)
    for f in ("stiffness.csv", "stiffness_intervals.csv", "stiffness.json", "stiffness.png"):
        assert (out / f).stat().st_size > 0
    assert json.loads((out / "stiffness.json").read_text())["version"] == shootlab.__version__


def test_suggest_is_checked_by_a_sweep():
    """msd with stiff state weights (κ ≈ −100): the sweep's minimal stable m is within a factor
    2 of the prediction; below it RK4 converges to a spurious (unstable) solution."""
    res = sweep.check("msd", {"W_states": 1e-4}, ["rk4:1"], progress=False, refine=1)
    row = sweep.comparison([res])[0]
    assert row["within_factor_2"] and row["accurate_within_factor_2"], row
    kinds = {r["m"]: r["kind"] for r in res["rows"]}
    assert kinds[max(kinds)] == "converged" and "unstable" in kinds.values()


def test_dichotomy_judges_modes_of_the_accurate_map():
    """Manipulator (κ ≈ −105, |Im λ| ≈ 60), RK4 with 4 steps on 44 points: accurate (0.03 %) and
    stable — the frozen-Jacobian modal test flagged it; beyond RK4's real limit (msd, κ h = −3.04)
    the damped stiff mode grows by |R(−3.04)| = e^0.375 and the case is unstable."""
    res = sweep.run(sweep.SweepSettings(problem="flexible", options={"V_s": 1e4}, integrators=["rk4:4"], points=[44],
                                        memory=False), progress=False, predict=False)
    row = res["rows"][0]
    assert row["kind"] == "converged" and row["stable"] and row["error"] < 1e-3 and row["spurious_growth"] < 0
    res = sweep.run(sweep.SweepSettings(problem="msd", options={"W_states": 1e-4}, integrators=["rk4:1"],
                                        points=[330], memory=False), progress=False, predict=False)
    row = res["rows"][0]
    R = float(np.real(stability_function("rk4")[0](np.array(-99.985 * 10 / 329 + 0j))))
    assert row["kind"] == "unstable" and row["unstable_intervals"] == 329
    assert row["spurious_growth"] == pytest.approx(math.log(abs(R)), abs=0.02)


# -- sweeps -----------------------------------------------------------------------------------------
SMALL = dict(problem="msd", options={"W_states": 1e-2}, integrators=["rk4:1"], points=[20, 50], max_iter=30)


@pytest.fixture(scope="module")
def serial_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    return sweep.run(sweep.SweepSettings(**SMALL), out, progress=False), out


def test_sweep_records_and_files(serial_sweep):
    res, out = serial_sweep
    assert [r["m"] for r in res["rows"]] == [20, 50]
    by_m = {r["m"]: r for r in res["rows"]}
    assert by_m[50]["kind"] == "converged" and by_m[50]["stable"] and by_m[50]["error"] < 0.05
    assert by_m[20]["kind"] in sweep.KINDS and by_m[20]["kind"] != "converged"
    for r in res["rows"]:
        assert r["peak_mb"] > 0 and r["seconds"] > 0
    meta = json.loads((out / "sweep.json").read_text())
    assert meta["version"] == shootlab.__version__ and meta["settings"]["integrators"] == ["rk4:1"]
    assert meta["predictions"]["rk4:1"]["m"] > 2 and meta["reference"] == {"m": 1.0, "b": 1.0, "k": 1.0}
    lines = (out / "sweep.csv").read_text().splitlines()
    assert lines[0].startswith("problem,integrator,m,kind") and len(lines) == 3
    assert (out / "sweep.png").stat().st_size > 0


def test_replot_does_not_solve(serial_sweep, monkeypatch):
    _, out = serial_sweep
    (out / "sweep.png").unlink()
    monkeypatch.setattr(shootlab, "solve", lambda *a, **k: pytest.fail("replot must not solve"))
    sweep.replot(out)
    assert (out / "sweep.png").stat().st_size > 0


def test_dask_local_cluster_gives_the_serial_results(serial_sweep):
    distributed = pytest.importorskip("distributed")
    res, _ = serial_sweep
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, \
            distributed.Client(cl) as client:
        res_d = sweep.run(sweep.SweepSettings(**SMALL), None, progress=False, client=client)
    assert res_d["executor"] == "dask"
    for a, b in zip(res["rows"], res_d["rows"]):
        for key in sweep.DETERMINISTIC:
            if key == "peak_mb":
                # the tensor memory of a run depends on the process it runs in (what the allocator
                # and torch's caches hold already: a worker of a long suite reads more than a fresh
                # process), not on the sweep: it is a measurement, compared in benchmarks
                continue
            assert a[key] == b[key] or (isinstance(a[key], float) and math.isnan(a[key]) and math.isnan(b[key])), key


def test_classify_and_observed_minimum():
    assert sweep.classify(0, "", 0.01, 0.05) == "converged"
    assert sweep.classify(0, "", 0.2, 0.05) == "inaccurate"
    assert sweep.classify(0, "", 0.01, 0.05, stable=False) == "unstable"
    assert sweep.classify(0, "", float("nan"), math.inf) == "converged"
    assert sweep.classify(2, "non-finite value (overflow) on shooting interval 3", 0, 0) == "overflow"
    assert sweep.classify(1, "", 0, 0) == "max_iter" and sweep.classify(4, "", 0, 0) == "divergence"
    assert sweep.classify(3, "", 0, 0) == "singular"
    rows = [dict(integrator="a", m=m, success=ok, status=0 if ok else 4, stable=True)
            for m, ok in ((10, True), (20, False), (40, True), (80, True))]
    assert sweep.observed_minimum(rows, "a") == (40, "")
    assert sweep.observed_minimum(rows[2:], "a") == (40, "<=")
    assert sweep.observed_minimum(rows[:2], "a") == (None, "> 20")
    assert sweep.ladder(100, range(-2, 3)) == [50, 71, 100, 141, 200]
    assert sweep.parse_integrator("rk4:4") == ("rk4", 4) and sweep.parse_integrator("euler") == ("euler", 1)
    with pytest.raises(ValueError):
        sweep.parse_integrator("nope:1")


# -- problems ------------------------------------------------------------------------------------------
USER = textwrap.dedent('''
    import torch, shootlab

    def problem(kappa=20.0):
        bvp = shootlab.BVP(lambda t, x: torch.stack([-kappa * x[..., 0], kappa * x[..., 1]], -1),
                           lambda xa: xa[:1] - 1.0, lambda xb: xb[1:] - 1.0)
        return bvp, (0.0, 1.0), lambda t: torch.ones(t.numel(), 2, dtype=torch.float64)
''')


def test_user_problem_from_a_file(tmp_path):
    path = tmp_path / "userprob.py"
    path.write_text(USER)
    prob = problems.build(f"{path}:problem", {"kappa": 30.0})
    assert prob.n == 2 and prob.interval == (0.0, 1.0) and "kappa=30" in prob.name
    q = prob.measure(prob.grid(5), prob.guess(prob.grid(5)))
    assert set(q) == {"x0(a)", "x1(a)", "x0(b)", "x1(b)"}
    res = sweep.run(sweep.SweepSettings(problem=f"{path}:problem", options={"kappa": 30.0}, integrators=["rk4:1"],
                                        points=[6, 40], accuracy=math.inf, memory=False), progress=False)
    kinds = {r["m"]: r["kind"] for r in res["rows"]}
    assert kinds[40] == "converged" and kinds[6] == "unstable"     # h|λ| = 6 > 2.785: the decaying mode grows
    assert res["reference_source"].startswith("solve")


def test_problem_errors():
    with pytest.raises(ValueError, match="no option"):
        problems.build("msd", {"bogus": 1})
    with pytest.raises(ValueError):
        problems.build("no_such_thing")
    with pytest.raises(ValueError):
        problems.build("flexible", {"rig": "marble"})


# -- memory and scaling ----------------------------------------------------------------------------------
def test_tensor_memory_tracks_live_storage():
    keep = torch.zeros(10)                                     # before the block: not counted
    with scaling.TensorMemory() as mem:
        a = torch.ones(1000, dtype=f64)                        # 8000 bytes
        v = a[:10]                                             # a view: no new storage
        b = a * 2.0                                            # 8000 more: peak 16000
        del b
        c = torch.ones(500, dtype=f64)                         # 4000: current 12000
    assert mem.peak == 16000 and mem.current == 12000
    del a, v, c, keep


def test_one_iteration_time_split_and_memory_grow_linearly_in_m():
    prob = problems.build("msd", {"W_states": 1e-2})
    r1, r4 = scaling.measure(prob, 100, repeat=1), scaling.measure(prob, 400, repeat=1)
    assert set(r1["seconds"]) == set(scaling.PARTS) and all(v > 0 for v in r1["seconds"].values())
    assert 3.6 < r4["peak_bytes"] / r1["peak_bytes"] < 4.4
    assert 3.6 < r4["factorisation_bytes"] / r1["factorisation_bytes"] < 4.4
    rows = [dict(m=m, n=10, seconds={k: 1e-3 * m for k in scaling.PARTS}, total=4e-3 * m, peak_bytes=8 * m ** 1.1,
                 factorisation_bytes=64 * m) for m in (100, 1000, 10000)]
    ex = scaling.exponents(rows, "m")
    assert ex["total"]["all"] == pytest.approx(1.0) and ex["peak_memory"]["all"] == pytest.approx(1.1)


# -- command line ---------------------------------------------------------------------------------------
def test_cli(tmp_path, capsys):
    assert main(["suggest", "--problem", "msd", "--option", "W_states=1e-4", "--integrators", "rk4:1", "euler:1"]) == 0
    text = capsys.readouterr().out
    assert "rk4:1" in text and "limited by stability" in text
    out = tmp_path / "sw"
    assert main(["sweep", "--problem", "msd", "--option", "W_states=1e-2", "--integrators", "rk4:1",
                 "--points", "40", "--no-memory", "--quiet", "--out", str(out)]) == 0
    assert "converged" in capsys.readouterr().out
    assert main(["sweep", "--replot", str(out)]) == 0
    assert main(["sweep", "--problem", "msd", "--option", "bogus=1"]) == 2
    out = tmp_path / "sc"
    assert main(["scaling", "--m", "30", "60", "--elements", "1", "2", "--n-points", "21", "--repeat", "1",
                 "--quiet", "--out", str(out)]) == 0
    res = json.loads((out / "scaling.json").read_text())
    assert [r["m"] for r in res["m_rows"]] == [30, 60] and [r["n"] for r in res["n_rows"]] == [6, 8]
    assert "fitted exponent" in capsys.readouterr().out and (out / "scaling.png").is_file()


# -- the validation, long ------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("problem,options", [("flexible", {}), ("confined", {"elements": 3, "H0": 2.4, "K0": 1.2})])
def test_suggest_within_factor_2_on_the_report_problems(problem, options):
    res = sweep.check(problem, options, ["rk4:1", "euler:1"], progress=False)
    for row in sweep.comparison([res]):
        assert row["within_factor_2"], row
