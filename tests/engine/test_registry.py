"""Plugins by entry point (shootlab/registry.py): the engine imports no application package; an
example record's declared options, its flags and help; a model factory's options described."""
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from shootlab import registry
from shootlab.registry import Option, Record

ROOT = Path(__file__).resolve().parents[2]


def test_engine_imports_no_application_package():
    code = textwrap.dedent("""
        import importlib, pkgutil, sys
        import shootlab
        for info in pkgutil.walk_packages(shootlab.__path__, "shootlab."):
            if not info.name.endswith("__main__"):        # python -m shootlab: runs the command
                importlib.import_module(info.name)
        found = sorted(m for m in sys.modules if m.split(".")[0] in ("manipulators", "mixtures", "studies"))
        assert "shootlab.diagnosis.pipeline" in sys.modules and "shootlab.bvp.integrators.ros4" in sys.modules
        print(" ".join(found))
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ""


# -- what an example record declares ----------------------------------------------------------------------------
def _toy(seed: int, level: float, n: int, shape: str, exact: bool):
    t = np.arange(n, dtype=float)
    y = np.full(n, level + seed) if shape == "flat" else level * t
    return {"t": t, "y": y}, ["t", "y"], f"{shape} at {level:g}, exact {exact}"


TOY = Record(_toy, "a toy record: t,y", options=(
    Option("level", float, 0.5, low=0.0, help="the level in %"), Option("n", int, 3, low=2, help="samples"),
    Option("shape", str, "flat", choices=("flat", "ramp")), Option("exact", bool, False)))


def test_a_record_is_called_with_its_declared_defaults():
    table, columns, what = TOY(seed=1)
    assert columns == ["t", "y"] and table["y"].tolist() == [1.5, 1.5, 1.5] and what == "flat at 0.5, exact False"
    assert TOY(n=4, shape="ramp", level=2.0)[0]["y"].tolist() == [0.0, 2.0, 4.0, 6.0]
    with pytest.raises(ValueError, match="bogus: not an option of this record; its options are level, n, shape, exact"):
        TOY(bogus=1)


@pytest.mark.parametrize("make, words", [
    (lambda: Record(_toy, "x", options=(Option("width"),)), r"record options \['width'\] are not keyword arguments"),
    (lambda: Record(_toy, "x", options=(Option("seed", int),)), "not seed or out"),
    (lambda: Record(_toy, "x", options=(Option("n", int), Option("n", int))), "each name once"),
    (lambda: Option("x", list), "kind must be int, float, str or bool"),
    (lambda: Option("two words"), "must be a Python identifier"),
])
def test_a_bad_record_declaration_is_a_one_line_error(make, words):
    with pytest.raises(ValueError, match=words):
        make()


def test_the_flags_of_a_record_come_from_its_declaration(capsys):
    """add_option turns each declared option into its flag: bounds, choices, a bool's --no- form,
    the default in the help; out-of-range values are usage errors naming the flag."""
    from shootlab.cli import _RecordParser
    from shootlab.cli.arguments import add_option
    p = _RecordParser(prog="shootlab simulate toy")
    for option in TOY.options:
        add_option(p, option)
    args = p.parse_args(["--level", "2", "--n", "5", "--shape", "ramp", "--exact"])
    assert (args.level, args.n, args.shape, args.exact) == (2.0, 5, "ramp", True)
    assert vars(p.parse_args([])) == {"level": 0.5, "n": 3, "shape": "flat", "exact": False}
    assert p.parse_args(["--no-exact"]).exact is False
    help_text = " ".join(p.format_help().split())
    assert "the level in % (default 0.5)" in help_text and "{flat,ramp}" in help_text and "--no-exact" in help_text
    for argv, words in [(["--level", "-1"], "argument --level: must be a finite number ≥ 0, got -1"),
                        (["--level", "nan"], "argument --level: must be a finite number"),
                        (["--n", "1"], "argument --n: must be an integer ≥ 2, got 1"),
                        (["--shape", "cube"], "argument --shape: invalid choice: 'cube'"),
                        (["--width", "3"], "--width 3: not an option of this record; its options are --level, --n")]:
        with pytest.raises(SystemExit) as exc:
            p.parse_args(argv)
        err = capsys.readouterr().err.splitlines()
        assert exc.value.code == 2 and len(err) == 1 and words in err[0], (words, err)


def test_model_factory_options_are_described():
    from shootlab.estimation.lookup import describe_options

    def factory(n: int, width: float = 0.5, weights=(1.0,) * 30, name: str = "x"):
        raise AssertionError("not called")
    assert describe_options(factory) == "n, width=0.5, weights=<tuple of 30>, name='x'"
    assert describe_options(lambda **kw: None) == "any keyword arguments"
    assert describe_options(lambda: None) == "(none)"


def test_simulate_builds_a_records_command_from_its_declaration(tmp_path, monkeypatch, capsys):
    """``shootlab simulate NAME`` for any installed record: its declared flags, its recipe called
    with them; a record that does not load is listed, and running it says why in one line."""
    from shootlab.cli import main
    installed = {"toy": TOY}

    def load(kind, name):
        if name not in installed:
            raise ValueError(f"{kind[:-1]} {name!r} (pkg.mod:broken) does not load: ImportError: no module pkg")
        return installed[name]
    monkeypatch.setattr(registry, "names", lambda kind: ["broken", "toy"] if kind == "records" else [])
    monkeypatch.setattr(registry, "load", load)
    out = tmp_path / "toy.csv"
    assert main(["simulate", "toy", "--level", "2", "--n", "4", "--shape", "ramp", "--out", str(out)]) == 0
    assert out.read_text().splitlines() == ["t,y", "0,0", "1,2", "2,4", "3,6"]
    assert capsys.readouterr().out.startswith(f"wrote {out}: ramp at 2, exact False; 4 samples, columns t,y")
    assert main(["simulate", "broken"]) == 2
    assert capsys.readouterr().err.strip() == ("shootlab simulate: error: record 'broken' (pkg.mod:broken) does not "
                                               "load: ImportError: no module pkg")
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    listed = " ".join(capsys.readouterr().out.split())
    assert "toy a toy record: t,y" in listed and "broken (does not load:" in listed
