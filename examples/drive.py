"""A one-axis drive, m a + b v + c = u, with its motor force u and its position s measured.

    shootlab estimate --model examples/drive.py:model --data drive.csv --out out/drive

The model is the 14 lines of code below (docs/your_own_model.md); the rest writes example
records: ``python examples/drive.py --simulate drive.csv`` (``--friction 0.2`` adds Coulomb
friction the model lacks, ``--input steps`` another force for validation).
"""
try:
    import shootlab
except ModuleNotFoundError:     # run from a checkout that is not installed: its package, from any directory
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    import shootlab

model = shootlab.model(
    name="drive",
    states={"s": "v", "v": "a"},                       # s' = v, v' = a
    inputs=["a", "u"],                                 # ζ: acceleration, motor force
    parameters={"m": 1.0, "b": 1.0, "c": 0.0},         # initial values
    equations={"motion": lambda x: x.m * x.a + x.b * x.v + x.c - x.u,    # 0 = m a + b v + c − u
               "position": lambda x: x.s,              # measured: position
               "force": lambda x: x.u},                # measured: motor force
    channels={"position": "position", "force": "force"},                 # row → CSV column
    units={"t": "s", "s": "m", "v": "m/s", "a": "m/s²", "u": "N",
           "m": "kg", "b": "N s/m", "c": "N", "motion": "N"},
    bounds={"m": (0.0, float("inf"))},
    mechanics={"motion": "motion", "velocity": "v", "command": "force"})   # for `shootlab diagnose`


def force(t, kind: str = "multisine"):
    """The motor force [N]: a multisine (identification) or a staircase of levels held 1 s with
    20 ms transitions (validation: another input)."""
    import numpy as np

    if kind == "multisine":
        return 0.4 + np.sin(1.3 * t) + 0.6 * np.sin(3.1 * t + 1.0) + 0.3 * np.sin(7.0 * t)
    levels = [1.2, -0.4, 0.8, -1.0, 0.3, 1.5, -0.8, 0.5, -1.3, 0.9]      # held 1 s each
    steps = sum((hi - lo) * 0.5 * (1.0 + np.tanh((t - k) / 0.02)) for k, (lo, hi) in enumerate(zip(levels, levels[1:]), 1))
    return levels[0] + steps


def simulate(path: str, m: float = 2.0, b: float = 0.5, c: float = 0.3, friction: float = 0.0, noise: float = 0.01,
             seed: int = 0, kind: str = "multisine") -> None:
    """Write a 10 s record at 100 Hz of the drive under ``force(t, kind)``, simulated by scipy
    (LSODA, tolerance 1e-10) on its own right-hand side m v' = u − b v − c − f tanh(v / 1 mm/s),
    independently of the model above, plus Gaussian noise (``noise`` N on the force, ``noise``/10 m
    on the position)."""
    import numpy as np
    from scipy.integrate import solve_ivp

    from shootlab.estimation.data import Measurements

    t = np.linspace(0.0, 10.0, 1001)

    def rhs(tt, x):
        return [x[1], (force(tt, kind) - b * x[1] - c - friction * np.tanh(x[1] / 1e-3)) / m]
    run = solve_ivp(rhs, (0.0, 10.0), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12)
    rng = np.random.default_rng(seed)
    Measurements(t, {"force": force(t, kind) + noise * rng.standard_normal(t.size),
                     "position": run.y[0] + 0.1 * noise * rng.standard_normal(t.size)}).to_csv(path)
    print(f"wrote {path}: 1001 samples of t, force, position (m = {m}, b = {b}, c = {c}, Coulomb friction "
          f"{friction}, {kind} force, noise {noise})")


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--simulate", metavar="FILE.csv", required=True, help="write an example record")
    parser.add_argument("--noise", type=float, default=0.01, help="force noise [N] (position: a tenth, in m)")
    parser.add_argument("--friction", type=float, default=0.0, help="Coulomb friction the model lacks [N]")
    parser.add_argument("--input", choices=["multisine", "steps"], default="multisine", help="the motor force")
    parser.add_argument("--seed", type=int, default=0, help="noise seed")
    args = parser.parse_args()
    simulate(args.simulate, friction=args.friction, noise=args.noise, seed=args.seed, kind=args.input)
