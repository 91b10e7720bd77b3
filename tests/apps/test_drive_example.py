"""The one-axis drive of docs/your_own_model.md (examples/drive.py): its model recovers m, b, c
from an independently simulated record, and its simulator writes the record."""
import math
from pathlib import Path

import numpy as np
import pytest

from shootlab.estimation.data import Measurements
from shootlab.estimation import estimate
from shootlab.estimation.lookup import resolve_model
from shared import DRIVE, drive_record

ROOT = Path(__file__).resolve().parents[2]


# -- an estimate of the one-axis drive of docs/your_own_model.md -----------------------------------------------------


def test_drive_example_recovers_m_b_c():
    """examples/drive.py's model on an independently simulated record: noise-free to 1e-5, with
    1 % force noise (1 mm on the position) within 1 % and within 3 standard errors."""
    drive = resolve_model(f"{ROOT / 'examples' / 'drive.py'}:model")
    assert drive.name == "drive" and drive.given == ["force"] and drive.parameters == ["m", "b", "c"]
    clean = estimate(drive, drive_record(0.0))
    assert clean.success, clean.message
    for p, v in DRIVE.items():
        assert clean.parameters[p] == pytest.approx(v, rel=1e-5), (p, clean.parameters)
    noisy = estimate(drive, drive_record(0.01))
    assert noisy.success, noisy.message
    for p, v in DRIVE.items():
        assert noisy.parameters[p] == pytest.approx(v, rel=1e-2), (p, noisy.parameters)
        assert abs(noisy.parameters[p] - v) < 3 * noisy.standard_errors[p], (p, noisy.parameters, noisy.standard_errors)


def test_drive_example_writes_its_record(tmp_path):
    from shootlab.estimation.lookup import load_object

    load_object(f"{ROOT / 'examples' / 'drive.py'}:simulate")(str(tmp_path / "drive.csv"), noise=0.0)
    data = Measurements.from_csv(tmp_path / "drive.csv")
    ref = drive_record(0.0)
    assert sorted(data.channels) == ["force", "position"]
    np.testing.assert_allclose(data.channels["position"], ref["position"], atol=1e-6)
    assert math.isclose(float(data.t[-1]), 10.0)
