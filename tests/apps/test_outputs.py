"""What a command leaves in --out: one run per folder (a foreign non-empty folder refused, --force,
a rerun replacing the whole set, folders 755 under umask 022), the estimate's status from the one
Status enum, the figures' min/max decimation and units, and the examples run from any directory."""
from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from manipulators.rig import msd_data
from shootlab.cli import main
from shootlab.estimation.data import Measurements
from shootlab.bvp.newton import Status
from shootlab.outputs import MARKER

ROOT = Path(__file__).resolve().parents[2]
FAST = ["--points", "21", "--integrator", "rk4", "--steps", "4", "--initial", "m=1.2", "b=0.8", "k=1.1",
        "--quiet", "--no-plots"]


@pytest.fixture
def record(tmp_path) -> Path:
    """A short noise-free msd record (m = b = k = 1), 4 s at 10 samples per second."""
    d = msd_data(t=np.linspace(0.0, 4.0, 41))
    path = tmp_path / "msd.csv"
    Measurements(d["t"], {"u": d["u"], "s": d["s"]}).to_csv(path)
    return path


def _estimate(record: Path, out: Path, *extra: str) -> int:
    return main(["estimate", "--model", "msd", "--data", str(record), "--out", str(out), *FAST, *extra])


def _files(out: Path) -> set[str]:
    return {p.name for p in out.iterdir()}


def test_a_foreign_non_empty_out_is_refused_and_force_replaces_it(tmp_path, record, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("the user's own file\n")
    assert _estimate(record, out) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "did not write (notes.txt)" in err[0] and "--force" in err[0], err
    assert _files(out) == {"notes.txt"}                                   # untouched
    assert _estimate(record, out, "--force") == 0
    assert _files(out) == {MARKER, "estimate.json", "residuals.csv"}      # replaced whole
    assert json.loads((out / MARKER).read_text())["written_by"] == "shootlab estimate"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(f".{out.name}.")]    # no staging left


def test_diagnose_checks_its_out_the_same_way_before_any_work(tmp_path, record, capsys):
    out = tmp_path / "diag"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    assert main(["diagnose", "--model", "msd", "--data", str(record), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("shootlab diagnose: error: ") and "did not write" in err and "--force" in err


def test_an_empty_out_is_used_and_the_data_may_not_live_in_a_replaced_out(tmp_path, record, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _estimate(record, empty) == 0
    inside = empty / "msd.csv"
    inside.write_bytes(record.read_bytes())
    assert main(["estimate", "--model", "msd", "--data", str(inside), "--out", str(empty), *FAST]) == 2
    assert "holds --data" in capsys.readouterr().err
    assert inside.exists()


def test_a_rerun_replaces_the_whole_set(tmp_path, record, capsys):
    """Output error, then shooting into the same folder: the first run's free_run.csv does not
    stay beside the second run's estimate.json."""
    out = tmp_path / "out"
    assert main(["estimate", "--model", "msd", "--method", "output-error", "--data", str(record), "--out", str(out),
                 "--quiet", "--no-plots"]) == 0
    assert _files(out) == {MARKER, "estimate.json", "free_run.csv"}
    assert _estimate(record, out) == 0
    assert _files(out) == {MARKER, "estimate.json", "residuals.csv"}
    assert json.loads((out / "estimate.json").read_text())["method"] == "shooting"


@pytest.mark.parametrize("umask, mode", [(0o022, 0o755), (0o077, 0o700)])
def test_output_folders_follow_the_umask(tmp_path, record, umask, mode):
    old = os.umask(umask)
    try:
        out = tmp_path / "new" / "run"
        assert _estimate(record, out) == 0
        assert _estimate(record, out) == 0                  # the replacement too
    finally:
        os.umask(old)
    for folder in (out, out.parent):
        assert stat.S_IMODE(folder.stat().st_mode) == mode, (folder, oct(folder.stat().st_mode))


def test_demo_writes_its_record_beside_its_folder(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    assert (tmp_path / "demo.csv").exists() and "estimate.json" in _files(out)
    assert main(["demo", "--out", str(out)]) == 0           # a rerun: the folder is shootlab's


# -- the status ----------------------------------------------------------------------------------
def test_a_failed_shooting_run_writes_its_status(tmp_path, record):
    out = tmp_path / "out"
    assert _estimate(record, out, "--max-iter", "1", "--initial", "m=5", "b=5", "k=5") == 1
    info = json.loads((out / "estimate.json").read_text())
    assert info["success"] is False and info["status"] == int(Status.MAX_ITER) == 1
    assert info["status_meaning"] == Status.MAX_ITER.meaning


def test_a_declared_models_channels_carry_their_variables_units():
    sys.path.insert(0, str(ROOT / "examples"))
    try:
        import drive
    finally:
        sys.path.remove(str(ROOT / "examples"))
    from shootlab.outputs import channel_label, residual_label

    assert channel_label(drive.model, "position") == "position [m]"
    assert channel_label(drive.model, "force") == "force [N]"
    assert residual_label(drive.model, "motion") == "ξ motion [N]"


def test_block_rows_share_one_residual_axes():
    from mixtures.identification import model as confined
    from shootlab.outputs import _row_groups

    m = confined(elements=4)
    groups = _row_groups(m, list(m.equations))
    assert [len(g) for g in groups] == [4, 4, 1, 1, 1] and groups[0][0] == "mass1"


# -- examples -----------------------------------------------------------------------------------
def test_the_drive_example_runs_from_any_directory_without_an_installed_package(tmp_path):
    """``python examples/drive.py`` from another folder, with the installed packages on the path
    but shootlab not installed there (``-S``: no .pth files): it finds its checkout's package."""
    import numpy
    env = dict(os.environ, PYTHONPATH=str(Path(numpy.__file__).parents[1]))
    run = [sys.executable, "-S"]
    assert subprocess.run(run + ["-c", "import shootlab"], cwd=tmp_path, env=env, capture_output=True).returncode != 0
    done = subprocess.run(run + [str(ROOT / "examples" / "drive.py"), "--simulate", "d.csv"], cwd=tmp_path, env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0 and (tmp_path / "d.csv").exists(), done.stderr


@pytest.mark.slow
def test_the_tanks_example_runs_from_any_directory_without_an_installed_package(tmp_path):
    import numpy
    env = dict(os.environ, PYTHONPATH=str(Path(numpy.__file__).parents[1]))
    done = subprocess.run([sys.executable, "-S", str(ROOT / "examples" / "tanks.py"), "--help"], cwd=tmp_path,
                          env=env, capture_output=True, text=True)
    assert done.returncode == 0 and "--convert" in done.stdout, done.stderr


# -- the peer's script ------------------------------------------------------------------------------
@pytest.mark.parametrize("elements", [3, 20])
def test_the_peers_own_assembly_is_the_models(elements):
    """benchmarks/casadi_confined.py assembles the N-element model itself (no torch in the peer's
    process): its matrices equal mixtures.prefit.filter_system's for the free-draining filter."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import casadi_confined
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    from mixtures.prefit import filter_system

    for mine, theirs in zip(casadi_confined.linear_system(elements), filter_system(1.0, 1.0, 0.0, elements)):
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-12 * np.abs(theirs).max())
