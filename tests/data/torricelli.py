"""A user's model of the cascaded-tanks record (``/work/shared/data/cascaded_tanks``, README beside
it), written from the physics the record's README gives, as a test fixture: Torricelli outflows

    x1' = k1 u − k2 r(x1)             upper level, filled by the pump at voltage u
    x2' = k2 r(x1) − k3 r(x2)         lower level
    y   = x2                          measured (volts of the level sensor)

with the square root smoothed as r(x) = √(δ² softplus(x/δ²) + δ²) − δ: √(x + δ²) − δ for a level
above a few δ², C^∞, 0 for an empty tank (a level pushed below 0 does not flow), δ = 0.1 V.
Unlike ``examples/tanks.py`` (an odd √ smoothed as x (x² + δ²)^(−1/4), an initial approximation of
the upper level from the lower tank's balance) the upper level starts at 0, the declarative
default for an unmeasured state; the weights are the example's (parameters held constant by
W = 1e10, the model rows trusted 1e6 times the level).  Every estimate setting is the default:
101 shooting points, RK4 with 10 steps per interval, the default Newton.

    shootlab estimate --model tests/data/torricelli.py:model --data tanks_est.csv --out out
"""
import torch
import shootlab

DELTA = 0.1      # [V]: where the smoothed square root departs from √x


def root(x: torch.Tensor) -> torch.Tensor:
    """r(x) = √(δ² softplus(x/δ²) + δ²) − δ (module docstring)."""
    d2 = DELTA * DELTA
    return torch.sqrt(d2 * torch.nn.functional.softplus(x / d2) + d2) - DELTA


#: the initial values of examples/tanks.py (time constants of about 100 s)
PRIOR = {"k1": 0.05, "k2": 0.05, "k3": 0.05}

model = shootlab.model(
    name="torricelli",
    states={"x1": "q1", "x2": "q2"},
    inputs=["q1", "q2", "u"],
    parameters=dict(PRIOR),
    equations={"upper": lambda x: x.k1 * x.u - x.k2 * root(x.x1) - x.q1,
               "lower": lambda x: x.k2 * root(x.x1) - x.k3 * root(x.x2) - x.q2,
               "level": lambda x: x.x2,
               "pump": lambda x: x.u},
    channels={"level": "y", "pump": "u"},
    W={"k1": 1e10, "k2": 1e10, "k3": 1e10},
    V={"upper": 1e6, "lower": 1e6, "level": 1.0, "pump": 1e4},
    units={"t": "s", "x1": "V", "x2": "V", "q1": "V/s", "q2": "V/s", "u": "V", "y": "V",
           "k1": "1/s", "k2": "V^½/s", "k3": "V^½/s", "upper": "V/s", "lower": "V/s"})
