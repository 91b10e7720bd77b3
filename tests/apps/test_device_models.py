"""The device plumbing on the project's models: spectral bounds on their stiff Jacobians, solves and
estimates on the accelerator's code paths and on a GPU (the tests marked ``cuda``, skipped without
one) against the CPU's, ``solve_batch`` on a family of estimation problems, the GPU benchmark."""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import shootlab
from shootlab.estimation import weights
from shootlab.bvp.batch import solve_batch
from shootlab.estimation.data import Measurements
from shootlab.bvp.device import forced_accelerator_paths
from shootlab.estimation.fit import posed
from shootlab.bvp.integrators import batch_jacobian
from shootlab.bvp.newton import CONVERGED, INTERVALS_TOO_LONG
from shootlab.bvp.shooting import local_spectrum, spectral_bounds

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks import gpu as bench  # noqa: E402
from manipulators.msd import model as msd_model  # noqa: E402  (not through the registry: no install needed)

f64 = torch.float64
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU")


def _stiff_jacobians() -> list[torch.Tensor]:
    """Local Jacobians of the project's problems: a boundary layer, Troesch at its guess, and the
    estimation TPBVPs of the mass-spring-damper and of the 3-element confined compression at their
    initial approximations (Hamiltonian, nearly defective: the parameters' rows are zero)."""
    out = []
    t = torch.linspace(0, 1, 21, dtype=f64)
    out.append(batch_jacobian(bench.layer(1e-6).rhs, t, bench.layer_guess(t) + t[:, None]))
    out.append(batch_jacobian(bench.troesch(10.0).rhs, t, bench.troesch_guess(t)))
    from manipulators.records import msd
    from mixtures.identification import as_data, model
    from mixtures.simulation import simulated_measurements
    table = msd()[0]
    for mdl, data in ((msd_model(), Measurements.coerce(table)),
                      (model(elements=3), Measurements.coerce(as_data(simulated_measurements(elements=3))))):
        mdl = weights.from_data(mdl, data)
        prob, tt, X0, _ = posed(mdl, data, 21, None, None, None)
        out.append(batch_jacobian(prob.bvp().rhs, tt, X0))
    return out


def test_bounds_on_the_projects_stiff_jacobians():
    for J in _stiff_jacobians():
        rho, kappa = spectral_bounds(J, "exact")
        rho_b, kappa_b = spectral_bounds(J, "bound")
        slack = 1e-12 * rho + 1e-300
        assert bool((rho_b >= rho - slack).all()) and bool((kappa_b >= kappa - slack).all())
        assert bool((rho_b <= rho * (1 + 1e-9) + 1e-12).all())
        assert bool((kappa_b <= kappa + 1e-9 * rho + 1e-12).all())


def test_spectral_method_follows_the_device_and_checks_its_name():
    J = torch.eye(2, dtype=f64)[None]
    assert spectral_bounds(J, "auto")[0].tolist() == [1.0]
    with pytest.raises(ValueError, match="spectral method must be one of auto, exact, bound"):
        spectral_bounds(J, "gershgorin")
    with pytest.raises(ValueError, match="spectral must be one of"):
        shootlab.solve(bench.layer(), torch.linspace(0, 1, 5, dtype=f64),
                       bench.layer_guess(torch.linspace(0, 1, 5, dtype=f64)), spectral="fast")


def test_a_solve_with_the_bounds_reaches_the_same_solution():
    """refine and the auto integrator's stiff rows decided on the bounds: the grid is at least as
    fine, the solution the same to the solver's tolerance (rtol 1e-10 of the default)."""
    prob = bench.layer(1e-4)
    t = torch.linspace(0, 1, 11, dtype=f64)
    exact = shootlab.solve(prob, t, bench.layer_guess(t), spectral="exact")
    bound = shootlab.solve(prob, t, bench.layer_guess(t), spectral="bound")
    assert exact.success and bound.success
    assert bound.points >= exact.points > t.numel()
    y = bench.layer_exact(t, 1e-4)
    assert float((exact.x[:, 0] - y).abs().max()) < 1e-8
    assert float((bound.x - exact.x).abs().max()) < 1e-8


def test_the_growth_check_refuses_on_the_bounds_where_it_refuses_on_the_eigenvalues():
    prob = bench.layer(1e-4)                        # κ₊ = 100: e^(100 h) on h = 0.25 > e^20
    t = torch.linspace(0, 1, 5, dtype=f64)
    for method in ("exact", "bound"):
        res = shootlab.solve(prob, t, bench.layer_guess(t), integrator="rk4", spectral=method)
        assert res.status == INTERVALS_TOO_LONG and "e^25" in res.message


@pytest.mark.parametrize("problem", ["layer", "troesch"])
def test_a_solve_on_the_accelerator_paths_equals_the_cpus(problem):
    prob, guess = (bench.layer(), bench.layer_guess) if problem == "layer" else (bench.troesch(5.0), bench.troesch_guess)
    t = torch.linspace(0, 1, 301, dtype=f64)
    a = bench.rk4(prob, t, guess(t))
    with forced_accelerator_paths():
        b = bench.rk4(prob, t, guess(t))
    assert a.success and b.success and a.iterations == b.iterations
    assert float((a.x - b.x).abs().max()) < 1e-10 * (1 + float(a.x.abs().max()))


def test_hot_path_tensors_follow_their_inputs_not_the_default_dtype():
    """Under a float32 default every tensor the solve makes takes its dtype from the inputs: the
    result is float64 and equal to the one under the float64 default (so also the device)."""
    t = torch.linspace(0, 1, 201, dtype=f64)
    ref = bench.rk4(bench.troesch(5.0), t, bench.troesch_guess(t))
    ref_auto = shootlab.solve(bench.layer(1e-3), t, bench.layer_guess(t))
    ref_batch = solve_batch(bench.troesch_family([1.0, 3.0]), t, bench.troesch_guess(t))
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    try:
        res = bench.rk4(bench.troesch(5.0), t, bench.troesch_guess(t))
        with forced_accelerator_paths():
            acc = bench.rk4(bench.troesch(5.0), t, bench.troesch_guess(t))
            acc_auto = shootlab.solve(bench.layer(1e-3), t, bench.layer_guess(t))
        batch = solve_batch(bench.troesch_family([1.0, 3.0]), t, bench.troesch_guess(t))
    finally:
        torch.set_default_dtype(old)
    assert res.x.dtype == f64 and torch.equal(res.x, ref.x)
    assert acc.x.dtype == f64 and float((acc.x - ref.x).abs().max()) < 1e-10
    assert acc_auto.success and float((acc_auto.x - ref_auto.x).abs().max()) < 1e-8
    assert all(r.x.dtype == f64 for r in batch)
    assert all(torch.equal(r.x, q.x) for r, q in zip(batch, ref_batch))


def test_estimate_on_the_cpu_device_is_the_plain_estimate():
    from manipulators.records import msd
    data = msd()[0]
    plain = shootlab.estimate(msd_model(), data, n_points=41)
    on = shootlab.estimate(msd_model(), data, n_points=41, device="cpu", dtype=f64)
    assert plain.success and on.parameters == plain.parameters
    assert on.t.device.type == "cpu" and on.x["s"].device.type == "cpu"


@pytest.mark.skipif(torch.cuda.is_available(), reason="the error is for machines without a GPU")
def test_device_cuda_fails_with_one_line_without_a_gpu(tmp_path):
    from manipulators.records import msd
    from shootlab.diagnosis import diagnose
    from shootlab.estimation.output_error import estimate_output_error
    data = msd()[0]
    for call in (lambda: shootlab.estimate(msd_model(), data, device="cuda"),
                 lambda: estimate_output_error(msd_model(), data, device="cuda"),
                 lambda: diagnose(msd_model(), data, device="cuda"),
                 lambda: solve_batch(bench.troesch_family([1.0]), torch.linspace(0, 1, 5, dtype=f64),
                                     bench.troesch_guess(torch.linspace(0, 1, 5, dtype=f64)), device="cuda")):
        with pytest.raises(ValueError, match="CUDA is not available"):
            call()
    csv = tmp_path / "msd.csv"
    Measurements.coerce(data).to_csv(csv)
    for command in ("estimate", "diagnose"):
        out = subprocess.run([sys.executable, "-m", "shootlab", command, "--model", "msd", "--data", str(csv),
                              "--out", str(tmp_path / command), "--device", "cuda"],
                             capture_output=True, text=True, cwd=ROOT, timeout=300)
        assert out.returncode == 2
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "CUDA is not available" in lines[0] and command in lines[0]


# -- solve_batch ----------------------------------------------------------------------------------
def test_solve_batch_equals_solving_each_alone():
    """10 Troesch and 10 Bratu problems, each batch against shootlab.solve with the same scheme on
    the same grid: the same discrete solution to the tolerance (both stop at max|F| ≤ 1e-12
    (1 + max|s|); the solutions differ by the Newton matrix's condition times that)."""
    t = torch.linspace(0, 1, 201, dtype=f64)
    for fam, guess in ((bench.troesch_family(torch.linspace(0.5, 5.0, 10)), bench.troesch_guess),
                       (bench.bratu_family(torch.linspace(0.2, 3.4, 10)), bench.bratu_guess)):
        res = solve_batch(fam, t, guess(t), tol=1e-12)
        assert len(res) == len(fam)
        for i, r in enumerate(res):
            alone = shootlab.solve(fam.member(i), t, guess(t), integrator="rk4", steps=4, tol=1e-12,
                                   refine=False, max_growth=None)
            assert r.success and alone.success, (r.message, alone.message)
            assert r.status == CONVERGED and r.message.startswith("converged")
            assert float((r.x - alone.x).abs().max()) < 1e-9 * (1 + float(alone.x.abs().max()))
            assert float((r.sol(torch.tensor([0.37], dtype=f64)) - alone.sol(torch.tensor([0.37], dtype=f64))
                          ).abs().max()) < 1e-8


def test_a_failing_member_does_not_spoil_the_others():
    """Bratu with λ = 4 has no solution and Troesch with μ = 40 overflows from its guess: they
    fail with their own status and message; the others converge as they do in a batch without them."""
    t = torch.linspace(0, 1, 101, dtype=f64)
    lams = [0.5, 4.0, 2.0, 3.0]
    res = solve_batch(bench.bratu_family(lams), t, bench.bratu_guess(t), max_iter=40)
    clean = solve_batch(bench.bratu_family([0.5, 2.0, 3.0]), t, bench.bratu_guess(t))
    assert [r.success for r in res] == [True, False, True, True]
    assert res[1].status != CONVERGED and res[1].message and not res[1].message.startswith("converged")
    for r, c in zip([res[0], res[2], res[3]], clean):
        assert r.iterations == c.iterations and float((r.x - c.x).abs().max()) < 1e-12
    res = solve_batch(bench.troesch_family([2.0, 40.0]), t, bench.troesch_guess(t))
    assert res[0].success and not res[1].success and "integration failed" in res[1].message


def test_solve_batch_rejects_bad_input():
    t = torch.linspace(0, 1, 11, dtype=f64)
    fam = bench.troesch_family([1.0, 2.0])
    with pytest.raises(ValueError, match="fixed-step integrator"):
        solve_batch(fam, t, bench.troesch_guess(t), integrator="dopri5")
    with pytest.raises(ValueError, match=r"guesses must be \(B, m, n\) = \(2, 11, n\)"):
        solve_batch(fam, t, torch.zeros(3, 11, 2, dtype=f64))
    with pytest.raises(ValueError, match="share one right-hand side"):
        solve_batch([bench.troesch(1.0), bench.troesch(2.0)], t, bench.troesch_guess(t))
    with pytest.raises(ValueError, match="params of problem 1 are not finite"):
        bench.troesch_family([1.0, math.nan])


def test_parameter_sweep_solves_a_family_as_one_batch(tmp_path):
    """studies' parameter sweep: the layer problem against its exact solution (RK4's error at
    h/4 = 1/1600: below 1e-7) and Troesch's y'(0) = 4.5750461e-2 at μ = 5 (Troesch 1976)."""
    from studies.sweep import parameter_sweep
    res = parameter_sweep("layer", [1e-1, 1e-2], points=[401], out=tmp_path)
    assert [r["kind"] for r in res["rows"]] == ["converged", "converged"]
    assert all(r["error"] < 1e-7 for r in res["rows"])
    res = parameter_sweep("troesch", [5.0, 40.0], points=[401])
    assert res["rows"][0]["kind"] == "converged"
    assert res["rows"][0]["quantities"]["slope"] == pytest.approx(4.5750461e-2, rel=1e-5)
    assert res["rows"][1]["kind"] == "overflow"
    assert (tmp_path / "parameter_sweep.json").is_file() and (tmp_path / "parameter_sweep.csv").is_file()
    with pytest.raises(ValueError, match="unknown family 'blasius'"):
        parameter_sweep("blasius", [1.0])


# -- the benchmark --------------------------------------------------------------------------------
def test_gpu_benchmark_quick_mode(tmp_path):
    assert bench.main(["--quick", "--out", str(tmp_path)]) == 0
    import json
    res = json.loads((tmp_path / "gpu_quick.json").read_text())
    rows = res["scaling"]["rows"]
    assert {r["problem"] for r in rows} == {"layer", "troesch"} and all(r["cpu_status"] == 0 for r in rows)
    assert all(r["cpu_error_vs_exact"] < 1e-6 for r in rows if r["problem"] == "layer")
    assert res["batch"]["solve_batch_cpu_converged"] == 10 and res["batch"]["alone_vs_batch_max_difference"] < 1e-7
    assert (tmp_path / "gpu_quick.png").is_file()


# -- a GPU ----------------------------------------------------------------------------------------
@cuda
@pytest.mark.cuda
def test_cuda_solves_equal_the_cpus():
    dev = torch.device("cuda")
    for prob, guess in ((bench.layer(), bench.layer_guess), (bench.troesch(5.0), bench.troesch_guess)):
        t = torch.linspace(0, 1, 1001, dtype=f64)
        a = bench.rk4(prob, t, guess(t))
        b = bench.rk4(prob, t.to(dev), guess(t).to(dev))
        assert b.x.device.type == "cuda" and a.success and b.success
        assert float((a.x - b.x.cpu()).abs().max()) < 1e-9 * (1 + float(a.x.abs().max()))
        s_cpu, s_gpu = local_spectrum(prob, t, guess(t)), local_spectrum(prob, t.to(dev), guess(t).to(dev))
        assert bool((s_gpu[0].cpu() >= s_cpu[0] * (1 - 1e-12)).all())
    t = torch.linspace(0, 1, 201, dtype=f64)
    fam = bench.troesch_family(torch.linspace(0.5, 5.0, 8))
    a = solve_batch(fam, t, bench.troesch_guess(t))
    b = solve_batch(fam, t, bench.troesch_guess(t), device="cuda")
    assert all(r.success and q.success for r, q in zip(a, b))
    assert max(float((r.x - q.x.cpu()).abs().max()) for r, q in zip(a, b)) < 1e-9
    from manipulators.records import msd
    data = msd()[0]
    ea = shootlab.estimate(msd_model(), data, n_points=41)
    eb = shootlab.estimate(msd_model(), data, n_points=41, device="cuda")
    assert eb.success and all(abs(eb.parameters[k] - v) < 1e-8 * (1 + abs(v)) for k, v in ea.parameters.items())
