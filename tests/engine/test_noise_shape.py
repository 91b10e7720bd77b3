"""The measurement noise's shape (shootlab.diagnosis.noise): the 4th-difference reading of a
white + AR(1) shape against its closed form, draws with the shape's autocorrelation, the fit to a
residual's spectrum, heavy tails read from the 4th differences, and surrogate levels drawn with
them."""
import math

import numpy as np
import pytest

from shootlab.diagnosis.floor import noise_levels
from shootlab.diagnosis.noise import KEEP_READS, WHITE, NoiseShape, fit_shape, tail_factor, tails_from
from shootlab.estimation.data import Measurements, noise_level


@pytest.mark.parametrize("phi", [0.0, 0.3, 0.7, 0.9])
def test_what_the_fourth_differences_read_of_an_ar1_process(phi):
    """The 4th difference's weights 1, −4, 6, −4, 1 have autocorrelation 70, −56, 28, −8, 1, so of
    an AR(1) process of pole φ they read √((70 − 112φ + 56φ² − 16φ³ + 2φ⁴)/70) of its std."""
    exact = math.sqrt((70 - 112 * phi + 56 * phi ** 2 - 16 * phi ** 3 + 2 * phi ** 4) / 70)
    assert NoiseShape(phi, 0.0).reads == pytest.approx(exact, rel=1e-12)
    # a white share w: the variance read is w·70σ² + (1 − w)·(the AR part's)
    assert NoiseShape(phi, 0.4).reads == pytest.approx(math.sqrt(0.4 + 0.6 * exact ** 2), rel=1e-12)


def test_a_draw_has_the_shape_s_variance_and_autocorrelation():
    """ρ(1) = (1 − w)φ and the variance σ², within a few standard errors of n = 200 000 samples
    (the AR part's lag-1 estimate has variance about (1 + φ²)/n ≈ 1e-5)."""
    shape = NoiseShape(0.8, 0.25)
    e = shape.draw(np.random.default_rng(3), 2.0, 200_000)
    assert np.var(e) == pytest.approx(4.0, rel=0.03)
    rho1 = np.mean(e[1:] * e[:-1]) / np.var(e)
    assert rho1 == pytest.approx(0.75 * 0.8, abs=0.01)
    # and the 4th differences read what `reads` says (noise_level's robust spread)
    level = noise_level(Measurements(np.arange(e.size, dtype=float), {"e": e}))["e"]
    assert level == pytest.approx(2.0 * shape.reads, rel=0.02)


def test_white_noise_is_drawn_as_before():
    """The white shape is one call of rng.normal: a record's surrogates are unchanged by the module."""
    a = WHITE.draw(np.random.default_rng(7), 0.5, 1000)
    b = np.random.default_rng(7).normal(0.0, 0.5, size=1000)
    assert np.array_equal(a, b)


def _record(n: int, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(n, dtype=float)
    signal = 50.0 * np.sin(2 * np.pi * t / 200.0) + 20.0 * np.sin(2 * np.pi * t / 63.0)
    return noise, signal + noise


def test_the_fit_reads_an_ar1_noise_and_leaves_white_noise_white():
    """3000 samples: AR(1) of pole 0.7 (reads 0.45) is read coloured, between 0.38 and 0.66 (the
    least coloured shape within one log-likelihood unit of the best: over noise draws its 10th–90th
    percentiles were 0.43–0.61); white noise stays white."""
    rng = np.random.default_rng(11)
    residual, record = _record(3000, NoiseShape(0.7, 0.0).draw(rng, 1.0, 3000))
    shape = fit_shape(residual, record)
    assert shape.coloured and 0.38 < shape.reads < 0.66
    residual, record = _record(3000, rng.normal(0.0, 1.0, 3000))
    assert fit_shape(residual, record) == WHITE


def test_no_colour_is_read_where_the_signal_fills_the_band_or_colour_would_not_matter():
    """A multisine over the whole band leaves no frequency of noise alone to fit; a shape that reads
    above KEEP_READS (80 % white + 20 % AR(1) of pole 0.78: 0.91) is drawn white."""
    rng = np.random.default_rng(12)
    t = np.arange(3000, dtype=float)
    phases = rng.uniform(0.0, 2 * np.pi, 400)               # random: not a pulse train
    broad = sum(np.sin(2 * np.pi * f * t + p) for f, p in zip(np.linspace(0.01, 0.49, 400), phases))
    noise = NoiseShape(0.7, 0.0).draw(rng, 0.1, 3000)
    assert fit_shape(noise, broad + noise) == WHITE
    mild = NoiseShape(0.78, 0.8)
    assert mild.reads > KEEP_READS
    residual, record = _record(3000, mild.draw(rng, 1.0, 3000))
    assert fit_shape(residual, record) == WHITE


def test_noise_levels_divide_the_fourth_difference_level_by_the_reading():
    """σ = the 4th-difference level / reads: for an AR(1) record of pole 0.7 and std 1 this brings
    the level from about 0.45 back to about 1."""
    rng = np.random.default_rng(13)
    shape = NoiseShape(0.7, 0.0)
    rec = Measurements(np.arange(20_000, dtype=float), {"y": shape.draw(rng, 1.0, 20_000)})
    assert noise_level(rec, ["y"])["y"] == pytest.approx(shape.reads, rel=0.03)
    assert noise_levels(rec, ["y"], {"y": shape})["y"] == pytest.approx(1.0, rel=0.03)


def _spikes(rng: np.random.Generator, n: int) -> np.ndarray:
    """Gaussian noise of unit std with 1 % of the samples 8 away: its std 1.28, its 4th differences'
    median reads about 1.05."""
    e = rng.normal(0.0, 1.0, n)
    hit = rng.random(n) < 0.01
    e[hit] += rng.choice([-8.0, 8.0], int(hit.sum()))
    return e


def test_heavy_tails_are_read_as_the_std_over_the_median_s_reading():
    """Over 200 draws of 3000 samples the tail factor over the draw's own std / level was 0.96–1.01
    (5th–95th percentiles) for the spikes, 0.97–1.03 for Gaussian noise (whose factor is 1)."""
    rng = np.random.default_rng(21)
    t = np.arange(3000, dtype=float)
    e = _spikes(rng, 3000)
    truth = np.std(e) / noise_level(Measurements(t, {"e": e}))["e"]
    assert truth > 1.15
    assert tail_factor(e) == pytest.approx(truth, rel=0.06)
    assert tail_factor(rng.normal(0.0, 1.0, 3000)) == pytest.approx(1.0, abs=0.05)
    assert math.isnan(tail_factor(np.zeros(3000)))        # a record held exactly: no reading
    # short Gaussian records spread more (the independent mixture's 401 samples had read 1.11):
    # the threshold grows as 1/√n, and none of 40 such records is read as heavy-tailed
    assert tails_from(400) > 1.15 > tails_from(3000)
    assert all(fit_shape(*_record(400, rng.normal(0.0, 1.0, 400))).tails == 1.0 for _ in range(40))


def test_the_fit_keeps_tails_that_show_in_both_the_record_and_the_residual():
    """Spikes in the noise show in the record and in the residual: the shape carries their tails
    and σ = level / reads comes back to the noise's std.  Spikes in the residual alone (an
    estimator's own kinks) or in the record alone (the signal's kinks) are not the noise's."""
    rng = np.random.default_rng(22)
    e = _spikes(rng, 3000)
    residual, record = _record(3000, e)
    shape = fit_shape(residual, record)
    assert not shape.coloured and shape.tails >= tails_from(3000) and shape.reads < KEEP_READS
    rec = Measurements(np.arange(3000, dtype=float), {"y": record})
    assert noise_levels(rec, ["y"], {"y": shape})["y"] == pytest.approx(np.std(e), rel=0.06)
    gaussian = rng.normal(0.0, 1.0, 3000)
    assert fit_shape(_spikes(rng, 3000), _record(3000, gaussian)[1]) == WHITE
    kinks = np.abs(((np.arange(3000) % 100) - 50.0)) * 10.0      # a triangle wave: a kink every 50 samples
    assert tail_factor(kinks + gaussian) > tails_from(3000)
    assert fit_shape(gaussian, kinks + gaussian) == WHITE
    # a record without a reading (held exactly: its 4th differences zero) reads no tails, whichever
    # of the two it is
    held = np.repeat(np.arange(30, dtype=float), 100)
    assert math.isnan(tail_factor(held))
    assert fit_shape(_spikes(rng, 3000), held).tails == 1.0
