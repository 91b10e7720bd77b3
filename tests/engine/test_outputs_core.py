"""What a command leaves in --out without a model: a staged folder replaced whole or left as it was,
the estimate's status from the one Status enum (the README's table), the figures' min/max
decimation."""
from __future__ import annotations
import re
from pathlib import Path

import numpy as np
import pytest
from shootlab.bvp.newton import Status
from shootlab.estimation.output_error import termination
from shootlab.outputs import MARKER, minmax_decimate

ROOT = Path(__file__).resolve().parents[2]


def _files(out: Path) -> set[str]:
    return {p.name for p in out.iterdir()}


def test_staged_folder_replaces_whole_or_leaves_out_as_it_was(tmp_path, monkeypatch):
    """A completed block replaces ``out`` (by an exchange, or by two renames where there is none);
    a failed one leaves the previous results and no staging folder."""
    from shootlab import outputs

    out = tmp_path / "out"
    for name, exchange in (("a.txt", None), ("b.txt", lambda a, b: False)):
        if exchange is not None:
            monkeypatch.setattr(outputs, "_exchange", exchange)
        with outputs.staged_folder(out, "test") as tmp:
            (tmp / name).write_text(name)
        assert _files(out) == {MARKER, name}
    with pytest.raises(RuntimeError, match="disk full"):
        with outputs.staged_folder(out, "test") as tmp:
            (tmp / "c.txt").write_text("c")
            raise RuntimeError("disk full")
    assert _files(out) == {MARKER, "b.txt"} and _files(tmp_path) == {"out"}


def test_output_error_statuses_are_the_shooting_ones():
    """scipy's terminations 1-4 are CONVERGED with a 'converged:' message, 0 (max_nfev) MAX_ITER,
    a non-finite last free run INTEGRATION_FAILED, a fit stopped at its budget (−2) MAX_ITER;
    success is exactly status 0."""
    for code in (1, 2, 3, 4):
        status, message = termination(code, True, 1e-8, 7, 25, 400)
        assert status is Status.CONVERGED and message.startswith("converged: ") and "after 7 iterations" in message
    assert termination(0, True, 1e-8, 50, 400, 400)[0] is Status.MAX_ITER
    assert termination(2, False, 1e-8, 3, 9, 400)[0] is Status.INTEGRATION_FAILED
    status, message = termination(-2, True, 1e-8, 4, 30, 400, "its budget of 25 free runs")
    assert status is Status.MAX_ITER and message.startswith("not converged: stopped at its budget of 25 free runs")


def test_the_readme_status_table_is_the_enum():
    text = (ROOT / "README.md").read_text()
    table = dict(re.findall(r"^\| (\d) \| (.+) \|$", text, flags=re.M))
    assert sorted(int(k) for k in table) == [int(s) for s in Status]
    for s in Status:
        assert table[str(int(s))].replace("`", "").replace("\\|", "|") == s.meaning, s


# -- figures ------------------------------------------------------------------------------------
def test_minmax_decimation_keeps_every_window_extremes():
    rng = np.random.default_rng(3)
    n, points = 200_003, 2000
    t = np.cumsum(rng.uniform(0.5, 1.5, n))                      # irregular sampling
    y = np.sin(t / 5000.0) + 0.1 * rng.standard_normal(n)
    y[rng.choice(n, 40, replace=False)] += rng.choice([-5.0, 5.0], 40)     # isolated spikes
    y[1000:1500] = np.nan                                         # a gap
    td, yd = minmax_decimate(t, y, points)
    assert td.size <= points + 2 and np.all(np.diff(td) > 0)
    idx = np.searchsorted(t, td)
    assert np.array_equal(t[idx], td) and np.array_equal(y[idx], yd, equal_nan=True)   # samples, not means
    k = -(-n // (points // 2))
    for start in range(0, n, k):
        window = y[start:start + k]
        drawn = yd[(idx >= start) & (idx < start + k)]
        if np.isnan(window).all():
            assert np.isnan(drawn).all()
            continue
        assert np.nanmax(drawn) == np.nanmax(window) and np.nanmin(drawn) == np.nanmin(window), start
    assert {idx[0], idx[-1]} == {0, n - 1}
    short = np.arange(10.0)
    assert all(np.array_equal(a, b) for a, b in zip(minmax_decimate(short, short ** 2), (short, short ** 2)))
