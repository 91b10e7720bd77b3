"""Standard errors of the estimated parameters (shootlab.estimation.uncertainty): the adjoint of the
data spline, the misfit warning, and how an estimate is printed."""
from __future__ import annotations

import numpy as np
import pytest
from shootlab.estimation.data import Interpolant, Measurements
from shootlab.estimation.uncertainty import format_estimate, spline_adjoint


def test_spline_adjoint_is_the_transpose_of_the_interpolant():
    """Mᵀg from the comb splines equals the exact adjoint of Interpolant's samples → coefficients
    map (built column by column from unit samples), also with missing samples, an irregular grid
    and more samples than one comb."""
    rng = np.random.default_rng(3)
    K = 300
    t = np.cumsum(rng.uniform(0.5, 1.5, K))
    v = rng.normal(size=K)
    v[[0, 7, 150, 151, 299]] = np.nan
    ok = np.flatnonzero(~np.isnan(v))
    units = {}
    for i in ok:
        e = np.where(np.isnan(v), np.nan, 0.0)
        e[i] = 1.0
        units[str(i)] = e
    M = Interpolant(Measurements(t, units), list(units)).coef.numpy()       # (K−1, n_ok, 4)
    g = rng.normal(size=(2, K - 1, 4))
    exact = np.zeros((2, K))
    exact[:, ok] = np.einsum("qkd,kcd->qc", g, M)
    got = spline_adjoint(t, v, g)
    assert np.allclose(got, exact, rtol=1e-10, atol=1e-10 * np.abs(exact).max())
    assert np.all(got[:, np.isnan(v)] == 0.0)


@pytest.mark.parametrize("missing", [[], [0, 11, 5, 6, 7, 8, 9], [1, 3, 5, 7, 9, 10, 11],
                                     [0, 2, 4, 6, 8, 10, 11, 3, 5], list(range(11))])
def test_spline_adjoint_with_few_valid_samples(missing):
    """The adjoint against the exact one where Interpolant's spline is built otherwise: 5 and 12
    valid samples (not-a-knot, missing samples at the ends and inside), 3 (natural), 1 (a
    constant)."""
    rng = np.random.default_rng(5)
    K = 12
    t = np.cumsum(rng.uniform(0.5, 1.5, K))
    v = rng.normal(size=K)
    v[missing] = np.nan
    ok = np.flatnonzero(~np.isnan(v))
    units = {str(i): np.where(np.arange(K) == i, 1.0, np.where(np.isnan(v), np.nan, 0.0)) for i in ok}
    M = Interpolant(Measurements(t, units), list(units)).coef.numpy()
    g = rng.normal(size=(3, K - 1, 4))
    exact = np.zeros((3, K))
    exact[:, ok] = np.einsum("qkd,kcd->qc", g, M)
    got = spline_adjoint(t, v, g)
    assert np.allclose(got, exact, rtol=1e-12, atol=1e-12 * np.abs(exact).max())


def test_misfit_warning_needs_residuals_above_the_fit_floor():
    """A channel is a misfit when its residual σ exceeds twice the larger of the samples' noise
    and 1e-4 of their spread: the confined compression's noise-free record (σ_res 6.3e-6 on a
    spread of 0.135, noise floor 1.35e-7) is not; a residual of 1 % of the spread is."""
    from shootlab.estimation.uncertainty import Uncertainty

    def unc(res: float) -> Uncertainty:
        return Uncertainty(["H"], np.eye(1), {"d": res}, {"d": res}, {"d": 1.35e-7}, {}, spread={"d": 0.135})
    assert unc(6.3e-6).warnings == []
    assert unc(2 * 1e-4 * 0.135 * 0.99).warnings == []
    assert "a misfit, not noise" in unc(1.35e-3).warnings[0]


def test_format_estimate():
    assert format_estimate(1.00123, 0.0031, "kg") == "1.0012 ± 0.0031 kg"
    assert format_estimate(978.4, 12.3) == "978 ± 12"
    assert format_estimate(2.5, float("nan")) == "2.5"
