"""Helpers of an estimate that need no model: the error of a filled input sample and its noise gain,
the refusal of a fill far off the curve, and the progress lines of long phases."""
from __future__ import annotations

import numpy as np
import pytest
from shootlab.estimation.data import Measurements


def test_fill_error_is_exact_for_a_cubic_and_its_noise_gain():
    """fill_error's cubic through the two samples on either side reproduces a cubic signal, so the
    estimate is the line's true error; on a uniform grid one missing sample has the weights
    (−1, 1, 1, −1)/6 on its neighbours: a noise gain of 1/3."""
    from shootlab.estimation.data import fill_error
    t = np.linspace(0.0, 1.0, 21)
    v = 2.0 * t ** 3 - t ** 2 + 0.5
    gap = v.copy()
    gap[7:10] = np.nan
    line = np.interp(t[7:10], t[[6, 10]], v[[6, 10]])
    e, gain = fill_error(t, gap, 7, 10)
    assert e == pytest.approx(np.abs(line - v[7:10]).max(), rel=1e-12)
    gap = v.copy()
    gap[7] = np.nan
    assert fill_error(t, gap, 7, 8)[1] == pytest.approx(1.0 / 3.0, rel=1e-12)


def test_fill_inputs_refuses_a_fill_far_off_the_curve():
    """A run that a line cannot follow (three samples over the peak of a sine sampled 20 times a
    period: the line misses the peak by 1 − sin 0.3π = 0.19, the cubic estimate is 0.18, above 5 %
    of the valid samples' standard deviation, 0.031) is an error naming the rows; one sample where
    the sine is straight is filled, with the note."""
    t = np.linspace(0.0, 2.0, 21)
    v = np.sin(np.pi * t)
    rows = np.arange(2, 23)
    peak = v.copy()
    peak[4:7] = np.nan                                  # t = 0.4 … 0.6 around the peak at 0.5
    with pytest.raises(ValueError, match=r"input column 'u' is empty in rows 6–8 \(t = 0\.4 … 0\.6\): a linear fill "
                                         r"would be off by about 0\.18 there .* more than 0\.031 "):
        Measurements(t, dict(u=peak), rows=rows).fill_inputs(["u"])
    flank = v.copy()
    flank[10] = np.nan                                  # t = 1, where sin is straight: the line is right
    out, notes = Measurements(t, dict(u=flank), rows=rows).fill_inputs(["u"])
    assert out.channels["u"][10] == pytest.approx(0.0, abs=1e-15)
    assert len(notes) == 1 and notes[0].startswith("1 missing sample of input column 'u' interpolated linearly "
                                                   "(estimated error up to ")
    assert notes[0].endswith("% of its standard deviation): row 12 (t = 1)")


def test_phase_reports_only_long_phases(capsys):
    """phase(): '-- what ...' once the phase has run its time and '-- what: N.N s' at its end, on
    the given log (progress_line: stderr); nothing for a short phase or without a log."""
    import time as clock

    from shootlab.estimation.fit import phase, progress_line
    with phase("long", progress_line, after=0.05):
        clock.sleep(0.3)
    with phase("short", progress_line, after=5.0):
        pass
    with phase("silent", None, after=0.0):
        clock.sleep(0.01)
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert captured.out == "" and lines[0] == "-- long ..." and lines[1].startswith("-- long: ")
    assert len(lines) == 2 and float(lines[1].split(": ")[1].rstrip(" s")) >= 0.3
