"""The one-axis drive of docs/your_own_model.md (examples/drive.py): its model recovers m, b, c
from an independently simulated record, and its simulator writes the record."""
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from shootlab.estimation.data import Measurements
from shootlab.estimation import estimate
from shootlab.estimation.lookup import resolve_model

ROOT = Path(__file__).resolve().parents[2]


# -- an estimate of the one-axis drive of docs/your_own_model.md -----------------------------------------------------
TRUE = dict(m=2.0, b=0.5, c=0.3)


def _drive_record(noise: float, seed: int = 3) -> dict:
    """m a + b v + c = u simulated by scipy on its own right-hand side, 100 Hz for 10 s."""
    t = np.linspace(0.0, 10.0, 1001)

    def u(tt):
        return 0.4 + np.sin(1.3 * tt) + 0.6 * np.sin(3.1 * tt + 1.0) + 0.3 * np.sin(7.0 * tt)
    sol = solve_ivp(lambda tt, x: [x[1], (u(tt) - TRUE["b"] * x[1] - TRUE["c"]) / TRUE["m"]], (0, 10), [0.0, 0.0],
                    t_eval=t, method="DOP853", rtol=1e-12, atol=1e-13)
    rng = np.random.default_rng(seed)
    return {"t": t, "force": u(t) + noise * rng.standard_normal(t.size),
            "position": sol.y[0] + 0.1 * noise * rng.standard_normal(t.size)}


def test_drive_example_recovers_m_b_c():
    """examples/drive.py's model on an independently simulated record: noise-free to 1e-5, with
    1 % force noise (1 mm on the position) within 1 % and within 3 standard errors."""
    drive = resolve_model(f"{ROOT / 'examples' / 'drive.py'}:model")
    assert drive.name == "drive" and drive.given == ["force"] and drive.parameters == ["m", "b", "c"]
    clean = estimate(drive, _drive_record(0.0))
    assert clean.success, clean.message
    for p, v in TRUE.items():
        assert clean.parameters[p] == pytest.approx(v, rel=1e-5), (p, clean.parameters)
    noisy = estimate(drive, _drive_record(0.01))
    assert noisy.success, noisy.message
    for p, v in TRUE.items():
        assert noisy.parameters[p] == pytest.approx(v, rel=1e-2), (p, noisy.parameters)
        assert abs(noisy.parameters[p] - v) < 3 * noisy.standard_errors[p], (p, noisy.parameters, noisy.standard_errors)


def test_drive_example_writes_its_record(tmp_path):
    from shootlab.estimation.lookup import load_object

    load_object(f"{ROOT / 'examples' / 'drive.py'}:simulate")(str(tmp_path / "drive.csv"), noise=0.0)
    data = Measurements.from_csv(tmp_path / "drive.csv")
    ref = _drive_record(0.0)
    assert sorted(data.channels) == ["force", "position"]
    np.testing.assert_allclose(data.channels["position"], ref["position"], atol=1e-6)
    assert math.isclose(float(data.t[-1]), 10.0)
