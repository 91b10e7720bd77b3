"""The command line without a model: units read from a header, --version, and the Ctrl-C line's
count of the interrupted solve's iterations."""
from __future__ import annotations
import pytest
from shootlab import __version__
from shootlab.cli import _iterations_done, main
from shootlab.estimation.data import split_unit


def test_split_unit():
    assert split_unit("t [s]") == ("t", "s")
    assert split_unit(" u (N) ") == ("u", "N")
    assert split_unit("s1") == ("s1", "")


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"shootlab {__version__}"


def test_interrupt_counts_the_iterations_of_the_running_solve():
    """The Ctrl-C line reads the completed iterations from the interrupted frames."""
    from shootlab.bvp.newton import NewtonOutcome

    def solve(iters):                  # stands for shootlab.bvp.solver.solve between stages
        newton(NewtonOutcome(s=None, status=1, message="", history=[dict(iteration=0), dict(iteration=4)]))

    def newton(out):
        raise KeyboardInterrupt

    try:
        solve(17)
    except KeyboardInterrupt as exc:
        assert _iterations_done(exc.__traceback__) == 17 + 4
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as exc:
        assert _iterations_done(exc.__traceback__) is None
