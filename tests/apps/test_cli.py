"""The command line as a new user meets it: one-line errors for bad input, nothing left in --out,
spreadsheet CSVs estimated, --version, shootlab simulate (issue 12, items 2, 4, 5)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from manipulators.rig import msd_data
from shootlab.cli import main
from shootlab.estimation.data import Measurements

ROOT = Path(__file__).resolve().parents[2]
# a short noise-free record (m = b = k = 1) keeps the estimates fast: 4 s at 10 samples per second
SHORT = msd_data(t=np.linspace(0.0, 4.0, 41))
FAST = ["--points", "21", "--integrator", "rk4", "--steps", "4", "--initial", "m=1.2", "b=0.8", "k=1.1",
        "--quiet", "--no-plots"]


def _write(path: Path, header: list[str], rows, sep: str = ",", eol: str = "\n", bom: bool = False) -> Path:
    text = eol.join([sep.join(header)] + [sep.join(str(c) for c in r) for r in rows]) + eol
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    return path


def _msd_rows(data=SHORT, fmt=repr):
    return [[fmt(float(a)), fmt(float(b)), fmt(float(c))] for a, b, c in zip(data["t"], data["u"], data["s"])]


@pytest.fixture
def good(tmp_path) -> Path:
    return _write(tmp_path / "good.csv", ["t", "u", "s"], _msd_rows())


def _bad_inputs(tmp: Path, good: Path) -> list[tuple[str, list[str], list[str]]]:
    """(label, argv without --out, words the one error line must contain)."""
    rows = _msd_rows()
    back = [r[:] for r in rows]
    back[7][0] = back[5][0]
    dup = [r[:] for r in rows]
    dup[7][0] = dup[6][0]
    text = [r[:] for r in rows]
    text[9][2] = "oops"
    locked = tmp / "locked.txt"
    locked.write_text("a file, not a folder\n")
    empty = tmp / "empty.csv"
    empty.write_text("")
    est = ["estimate", "--model", "msd"]
    return [
        ("missing file", [*est, "--data", str(tmp / "nope.csv")], ["not found", "nope.csv"]),
        ("empty file", [*est, "--data", str(empty)], ["empty"]),
        ("no t column", [*est, "--data", str(_write(tmp / "no_t.csv", ["time", "u", "s"], rows))], ["column 't'"]),
        ("missing channel", [*est, "--data", str(_write(tmp / "no_s.csv", ["t", "u"], [r[:2] for r in rows]))],
         ["lack", "'s'"]),
        ("non-numeric cell", [*est, "--data", str(_write(tmp / "text.csv", ["t", "u", "s"], text))],
         ["'s'", "row 11", "'oops'", "not a number"]),
        ("non-increasing t", [*est, "--data", str(_write(tmp / "back.csv", ["t", "u", "s"], back))],
         ["must increase", "row 9"]),
        ("duplicate t", [*est, "--data", str(_write(tmp / "dup.csv", ["t", "u", "s"], dup))],
         ["duplicate time stamp t = 0.6 at rows 8 and 9"]),
        ("three rows", [*est, "--data", str(_write(tmp / "three.csv", ["t", "u", "s"], rows[:3]))],
         ["too few samples", "3 parameters", "at least"]),
        ("unknown model", ["estimate", "--model", "warp_drive", "--data", str(good)], ["unknown model", "msd"]),
        ("unknown parameter", [*est, "--data", str(good), "--initial", "q=1"],
         ["--initial q", "no parameter 'q'", "m, b, k"]),
        ("unknown option", [*est, "--data", str(good), "--option", "foo=1"],
         ["--option foo", "no option 'foo'", "W=<tuple of 5>, V=(1.0, 1.0, 1.0), prior=None"]),
        ("bad number", [*est, "--data", str(good), "--initial", "m=abc"], ["--initial m=abc", "not a number"]),
        ("huge value", [*est, "--data", str(_write(tmp / "huge.csv", ["t", "u", "s"],
                                                 [r if i != 20 else [r[0], r[1], "1e300"] for i, r in enumerate(rows)]))],
         ["'s'", "row 22", "1e+300"]),
        ("out is a file", [*est, "--data", str(good), "--out", str(locked)], ["--out", "existing file"]),
        ("out unwritable", [*est, "--data", str(good), "--out", str(locked / "sub")], ["--out", "cannot create"]),
    ]


def test_bad_inputs_give_one_line_and_leave_nothing(tmp_path, good, capsys):
    for i, (label, argv, words) in enumerate(_bad_inputs(tmp_path, good)):
        out = tmp_path / f"out{i}"
        if "--out" not in argv:
            argv = [*argv, "--out", str(out)]
        started = time.perf_counter()
        code = main(argv)
        captured = capsys.readouterr()
        lines = captured.err.splitlines()
        assert code == 2, (label, captured)
        assert len(lines) == 1 and lines[0].startswith("shootlab estimate: error: "), (label, lines)
        assert "Traceback" not in captured.err + captured.out, label
        for w in words:
            assert w in lines[0], (label, w, lines[0])
        assert not out.exists(), label
        assert time.perf_counter() - started < 10, f"{label}: the error came after work"
    assert not [p for p in tmp_path.iterdir() if "partial" in p.name or p.name.startswith(".shootlab")]
    assert (tmp_path / "locked.txt").read_text() == "a file, not a folder\n"


#: empty cells in the input column u of SHORT (10 samples a second; rows: the header is row 1)
EMPTY_U = {"single": [20], "five in a row": range(18, 23), "at the start": [0, 1], "at the end": [39, 40]}


@pytest.mark.parametrize("method", ["shooting", "output-error"])
@pytest.mark.parametrize("where", list(EMPTY_U))
def test_empty_cells_in_the_input_column(tmp_path, capsys, where, method):
    """Empty cells in u, which drives the msd: a single one is interpolated (its linear fill is off
    by 0.011, 4 % of u's standard deviation: the estimate moves 0.2 %), rows at the ends are left
    out (no fill: the noise-free estimate is exact to 1e-4), each with a note; five in a row, which a
    line would miss by 0.08 (u's fastest tone, 2.9 rad/s, turns 100° in the 0.6 s), are one error
    line naming the column and the rows."""
    rows = _msd_rows()
    for i in EMPTY_U[where]:
        rows[i][1] = ""
    data = _write(tmp_path / "gaps.csv", ["t", "u", "s"], rows)
    out = tmp_path / "out"
    argv = ["estimate", "--model", "msd", "--data", str(data), "--out", str(out)]
    argv += FAST if method == "shooting" else \
        ["--method", "output-error", "--initial", "m=1.2", "b=0.8", "k=1.1", "--quiet", "--no-plots"]
    code = main(argv)
    captured = capsys.readouterr()
    if where == "five in a row":
        assert code == 2 and not out.exists(), captured
        assert captured.err.splitlines() == [
            f"shootlab estimate: error: {data}: input column 'u' is empty in rows 20–24 (t = 1.8 … 2.2): a linear "
            "fill would be off by about 0.084 there (the cubic through the samples on either side), more than 0.013 "
            "(5 % of the column's standard deviation); fill them or cut the record there"]
        return
    assert code == 0, captured
    note = [ln for ln in captured.out.splitlines() if ln.startswith("note:")]
    assert note == [{
        "single": f"note: {data}: 1 missing sample of input column 'u' interpolated linearly (estimated error up "
                  "to 0.011, 4.3 % of its standard deviation): row 22 (t = 2)",
        "at the start": f"note: {data}: rows 2–3 (t = 0 … 0.1) left out: input column 'u' is empty there, "
                        "at the start of the record",
        "at the end": f"note: {data}: rows 41–42 (t = 3.9 … 4) left out: input column 'u' is empty there, "
                      "at the end of the record"}[where]], captured.out
    info = json.loads((out / "estimate.json").read_text())
    for name in ("m", "b", "k"):
        assert info["parameters"][name] == pytest.approx(1.0, rel=0.01 if where == "single" else 1e-4), info


def _exit_code(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:           # a usage error from argparse
        return exc.code


@pytest.mark.parametrize("argv, words", [
    (["simulate", "msd", "--duration", "0"], ["argument --duration: must be a finite number > 0, got 0"]),
    (["simulate", "msd", "--duration", "-1"], ["--duration", "> 0, got -1"]),
    (["simulate", "msd", "--duration", "inf"], ["--duration", "finite", "got inf"]),
    (["simulate", "msd", "--duration", "0.001"], ["duration 0.001", "at least 0.01"]),
    (["simulate", "msd", "--noise", "-1"], ["argument --noise: must be a finite number ≥ 0, got -1"]),
    (["simulate", "msd", "--noise", "nan"], ["--noise", "got nan"]),
    (["simulate", "msd", "--seed", "-2"], ["argument --seed: must be an integer ≥ 0, got -2"]),
    (["simulate", "confined", "--elements", "0"], ["argument --elements: must be an integer ≥ 1, got 0"]),
    (["simulate", "confined", "--duration", "2"], ["--duration 2: not an option of this record",
                                                    "its options are --out, --seed, --noise, --elements"]),
    (["simulate", "msd", "--elements", "4", "--effects", "none"], ["--elements 4 --effects none: not an option"]),
    (["simulate", "sweep", "--effects", "some"], ["argument --effects: invalid choice: 'some'"]),
    (["estimate", "--model", "msd", "--points", "1"], ["argument --points: must be an integer ≥ 2, got 1"]),
    (["estimate", "--model", "msd", "--points", "2.5"], ["argument --points: '2.5' is not an integer"]),
    (["estimate", "--model", "msd", "--steps", "0"], ["argument --steps: must be an integer ≥ 1, got 0"]),
    (["estimate", "--model", "msd", "--max-iter", "0"], ["argument --max-iter: must be an integer ≥ 1, got 0"]),
    (["estimate", "--model", "msd", "--tol", "0"], ["argument --tol: must be a finite number > 0, got 0"]),
    (["estimate", "--model", "msd", "--tol", "nan"], ["argument --tol", "got nan"]),
    (["diagnose", "--model", "msd", "--points", "1"], ["argument --points: must be an integer ≥ 2, got 1"]),
    (["diagnose", "--model", "msd", "--seed", "-1"], ["argument --seed: must be an integer ≥ 0, got -1"]),
])
def test_numeric_arguments_out_of_range_are_one_line_errors(tmp_path, good, capsys, argv, words):
    """Every numeric argument of simulate, estimate and diagnose is checked: one line, exit 2, nothing written."""
    out = tmp_path / ("x.csv" if argv[0] == "simulate" else "out")
    if argv[0] != "simulate":
        argv = [*argv, "--data", str(good)]
    assert _exit_code([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    prog = " ".join(argv[:2]) if argv[0] == "simulate" else argv[0]          # simulate RECORD
    assert len(err) == 1 and err[0].startswith(f"shootlab {prog}: error: "), err
    for w in words:
        assert w in err[0], (w, err[0])
    assert not out.exists()


def test_usage_error_is_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["estimate", "--model", "msd"])
    err = capsys.readouterr().err.splitlines()
    assert exc.value.code == 2 and len(err) == 1
    assert "required: --data, --out" in err[0] and "--help" in err[0]


def _check_estimate(out: Path, capsys) -> dict:
    captured = capsys.readouterr()
    info = json.loads((out / "estimate.json").read_text())
    assert info["success"], captured
    for name in ("m", "b", "k"):
        assert info["parameters"][name] == pytest.approx(1.0, rel=0.01), (name, info["parameters"])
    assert f"wrote {out}/: estimate.json, residuals.csv" in captured.out
    # the msd's weights are the report's, given explicitly: listed as used
    assert info["weights"] == {"W": dict(s=1e10, v=1e10, m=1.0, b=1.0, k=1.0), "V": dict(motion=1.0, u=1.0, s=1.0)}
    return captured


def test_spreadsheet_csv_bom_crlf_semicolon_units_decimal_comma(tmp_path, capsys):
    rows = _msd_rows(fmt=lambda v: repr(v).replace(".", ","))
    path = _write(tmp_path / "excel.csv", ["t [s]", "u (N)", "s [m]"], rows, sep=";", eol="\r\n", bom=True)
    data = Measurements.from_csv(path)
    assert data.units == {"t": "s", "u": "N", "s": "m"}
    np.testing.assert_array_equal(data.channels["s"], SHORT["s"])
    out = tmp_path / "out"
    assert main(["estimate", "--model", "msd", "--data", str(path), "--out", str(out), *FAST]) == 0
    _check_estimate(out, capsys)


def test_text_column_is_ignored_with_a_note(tmp_path, capsys):
    rows = [[r[0], "2026-11-30", r[1], "ok" if i % 3 else "", r[2]] for i, r in enumerate(_msd_rows())]
    path = _write(tmp_path / "notes.tsv", ["t", "date", "u", "remark", "s"], rows, sep="\t")
    out = tmp_path / "out"
    assert main(["estimate", "--model", "msd", "--data", str(path), "--out", str(out), *FAST]) == 0
    captured = _check_estimate(out, capsys)
    note = [ln for ln in captured.out.splitlines() if ln.startswith("note:")]
    assert len(note) == 1 and "'date'" in note[0] and "'remark'" in note[0], captured.out


def test_simulate_writes_records_that_estimate_accepts(tmp_path, capsys):
    for record, columns in [("msd", "t,u,s"), ("sweep", "t,u,s1,s2"), ("pd", "t,u,s1,s2"),
                            ("confined", "t,load,displacement,pressure")]:
        path = tmp_path / "records" / f"{record}.csv"
        argv = ["simulate", record, "--out", str(path), "--duration", "0.2" if record in ("sweep", "pd") else "4"]
        if record == "confined":
            argv = argv[:-2]
        assert main(argv) == 0
        assert path.read_text().splitlines()[0] == columns
        assert f"wrote {path}" in capsys.readouterr().out
    data = Measurements.from_csv(tmp_path / "records" / "msd.csv")
    assert data.t[-1] == pytest.approx(4.0) and data.t.size == 401
    np.testing.assert_allclose(data.channels["s"], msd_data(t=data.t)["s"], atol=1e-12)
    assert not [p for p in (tmp_path / "records").iterdir() if "partial" in p.name]
    out = tmp_path / "est"
    assert main(["estimate", "--model", "msd", "--data", str(tmp_path / "records" / "msd.csv"),
                 "--out", str(out), *FAST]) == 0
    _check_estimate(out, capsys)


def test_simulate_record_help_lists_the_options_it_declares(capsys):
    for record, flags in [("msd", ["--noise NOISE", "each channel's RMS (default 0.0)", "--duration DURATION",
                                   "record length in s (default 10.0)"]),
                          ("sweep", ["--noise NOISE", "--effects {all,friction,none}", "(default all)",
                                     "record length in s (default 1.0)"]),
                          ("confined", ["--noise NOISE", "--elements ELEMENTS", "number of finite elements (default 3)"])]:
        with pytest.raises(SystemExit) as exc:
            main(["simulate", record, "--help"])
        out = " ".join(capsys.readouterr().out.split())           # as wrapped to any terminal's width
        assert exc.value.code == 0 and "--out OUT" in out and "--seed SEED" in out
        for flag in flags:
            assert flag in out, (record, flag, out)
    assert "--elements" not in out.split("--noise")[0] and "--duration" not in out


def test_model_help_and_errors_list_the_factory_options(capsys, good, tmp_path):
    with pytest.raises(SystemExit):
        main(["estimate", "--model", "confined", "--help"])
    assert ("options of the model confined (--option KEY=VALUE): elements=3, length=1.0, W=None"
            in " ".join(capsys.readouterr().out.split()))
    with pytest.raises(SystemExit):
        main(["diagnose", "--help"])
    assert "shootlab diagnose --model NAME --help lists NAME's" in " ".join(capsys.readouterr().out.split())
    assert _exit_code(["estimate", "--model", "flexible_friction", "--option", "v_s3=1", "--data", str(good),
                       "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("shootlab estimate: error: --option v_s3: model 'flexible_friction' has no option 'v_s3'; its "
                   "options are W=1.0, V=<tuple of 5>, W_a=None, v_s1=0.1, v_s2=1.0, prior=None"), err


def test_simulate_noise_and_seed(tmp_path):
    paths = [tmp_path / f"{i}.csv" for i in range(3)]
    for p, seed in zip(paths, (1, 1, 2)):
        assert main(["simulate", "msd", "--noise", "0.01", "--seed", str(seed), "--duration", "2", "--out", str(p)]) == 0
    a, b, c = (Measurements.from_csv(p).channels["s"] for p in paths)
    np.testing.assert_array_equal(a, b)
    clean = msd_data(t=np.linspace(0, 2, 201))["s_true"]
    rms = float(np.sqrt(np.mean(clean ** 2)))          # "1 % noise": 1 % of the record's RMS
    assert 0.5 * 0.01 * rms < np.std(a - clean) < 1.5 * 0.01 * rms
    assert not np.array_equal(a, c)


def test_python_estimate_accepts_a_model_name():
    from shootlab.estimation import estimate
    res = estimate("msd", {k: SHORT[k] for k in ("t", "u", "s")}, n_points=21, integrator="rk4", steps=4,
                   initial=dict(m=1.2, b=0.8, k=1.1))
    assert res.success and res.parameters["k"] == pytest.approx(1.0, rel=0.01)


@pytest.mark.skipif(not hasattr(signal, "SIGINT") or os.name != "posix", reason="POSIX signals")
def test_ctrl_c_is_one_line_exit_130_nothing_written(tmp_path, good):
    out = tmp_path / "out"
    full = msd_data()                          # the 10 s record from m = b = k = 50: ~14 iterations of ~0.4 s
    data = _write(tmp_path / "full.csv", ["t", "u", "s"], _msd_rows(full))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    p = subprocess.Popen([sys.executable, "-m", "shootlab", "estimate", "--model", "msd", "--data", str(data),
                          "--out", str(out), "--initial", "m=50", "b=50", "k=50", "--no-plots"],
                         cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    for line in p.stdout:                      # wait until iteration 1 is done
        if line.split()[:1] == ["1"]:
            break
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err.startswith("shootlab estimate: interrupted after iteration ") and err.rstrip().endswith("nothing written")
    assert not out.exists() and not [q for q in tmp_path.iterdir() if "partial" in q.name]


def test_the_command_process_ends_with_mains_status_its_output_flushed(tmp_path):
    """``python -m shootlab`` ends by os._exit (shootlab.cli.process.leave): the status is main's,
    that of argparse's SystemExit too, and what was printed to the pipes arrives."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("SHOOTLAB_NUM_THREADS", None)

    def command(*argv):
        return subprocess.run([sys.executable, "-m", "shootlab", *argv], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=120, check=False)
    done = command("simulate", "msd", "--duration", "2", "--out", "d.csv")
    assert done.returncode == 0 and "d.csv" in done.stdout and (tmp_path / "d.csv").is_file()
    assert command("estimate", "--help").returncode == 0
    bad = command("estimate", "--model", "msd", "--data", "missing.csv", "--out", "o")
    assert bad.returncode == 2 and bad.stderr.startswith("shootlab estimate: error:") and not (tmp_path / "o").exists()


def test_a_command_uses_every_core_unless_told(monkeypatch):
    import torch

    from shootlab.cli import process
    before = torch.get_num_threads()
    try:
        monkeypatch.delenv("SHOOTLAB_NUM_THREADS", raising=False)
        process.prepare()
        assert torch.get_num_threads() == process.cores()
        torch.set_num_threads(1)
        monkeypatch.setenv("SHOOTLAB_NUM_THREADS", "1")
        process.prepare()
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def _flags_without_help(parser) -> list[str]:
    import argparse
    missing = []
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sub in a.choices.items():
                missing += [f"{name} {m}" for m in _flags_without_help(sub)]
        elif a.help is None:
            missing.append("/".join(a.option_strings) or a.dest)
    return missing


def test_every_flag_has_help_and_diagnose_lists_every_model(capsys):
    from shootlab.cli import build_parser
    from shootlab import registry
    from studies.__main__ import build_parser as studies_parser
    assert _flags_without_help(build_parser()) == []
    assert _flags_without_help(studies_parser()) == []
    with pytest.raises(SystemExit):
        main(["diagnose", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in registry.names("models"):
        assert name in text
    assert "--points" in text and "--initial" in text


def test_studies_bvp_testset_help_prints():
    out = subprocess.run([sys.executable, "-m", "studies.bvp_testset", "--help"], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0 and "usage: python -m studies.bvp_testset" in out.stdout


def test_confined_prefit_reports_each_iteration():
    from mixtures.prefit import output_error_fit
    from mixtures.simulation import simulated_measurements
    from mixtures.identification import as_data, model
    lines: list[str] = []
    fit = output_error_fit(model(elements=4), as_data(simulated_measurements(elements=4)), dict(H=4.0, K=4.0),
                           log=lines.append)
    assert fit["H"] == pytest.approx(2.0, rel=1e-3) and fit["K"] == pytest.approx(1.0, rel=1e-3)
    assert len(lines) >= 3 and lines[0].startswith("prefit   1: H = ")


def test_diagnose_takes_the_solver_flags_for_its_estimates(tmp_path, monkeypatch, capsys):
    """``diagnose --newton trust_region --max-iter 30 --no-fallback`` hands the diagnosis a model
    whose solver settings (which every estimate of it and of its extensions reads) carry them;
    ``estimate --method output-error --no-fallback`` is refused (no shooting solve)."""
    import shootlab.cli.diagnose as dcli
    data = tmp_path / "msd.csv"
    assert main(["simulate", "msd", "--duration", "1", "--out", str(data)]) == 0
    seen = {}

    def stop(model, *args, **kw):
        seen["model"] = model
        raise ValueError("stopped here")
    monkeypatch.setattr(dcli, "diagnose", stop)
    assert main(["diagnose", "--model", "msd", "--data", str(data), "--out", str(tmp_path / "d"), "--newton",
                 "trust_region", "--max-iter", "30", "--no-fallback", "--quiet"]) == 2
    settings = seen["model"].settings
    assert settings.solver["newton"] == "trust_region" and settings.solver["max_iter"] == 30
    assert settings.fallback is False
    assert main(["estimate", "--model", "msd", "--data", str(data), "--out", str(tmp_path / "e"),
                 "--method", "output-error", "--no-fallback"]) == 2
    assert "--no-fallback set the multiple-shooting solve" in capsys.readouterr().err
