"""A one-axis drive, m a + b v + c = u, with its motor force u and its position s measured.

    shootlab estimate --model examples/drive.py:model --data drive.csv --out out/drive

The model is the 13 lines of code below (docs/your_own_model.md); the rest writes an
example record: ``python examples/drive.py --simulate drive.csv``.
"""
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
    bounds={"m": (0.0, float("inf"))})


def simulate(path: str, m: float = 2.0, b: float = 0.5, c: float = 0.3, noise: float = 0.01, seed: int = 0) -> None:
    """Write a 10 s record at 100 Hz of the drive under a multisine force: the model's own free
    run with these parameters, plus Gaussian noise (``noise`` N on the force, ``noise``/10 m on
    the position)."""
    import numpy as np

    from shootlab.data import Measurements
    from shootlab.estimation import simulate as free_run

    t = np.linspace(0.0, 10.0, 1001)
    force = 0.4 + np.sin(1.3 * t) + 0.6 * np.sin(3.1 * t + 1.0) + 0.3 * np.sin(7.0 * t)
    run = free_run(model, {"t": t, "force": force}, dict(m=m, b=b, c=c), initial_state=[0.0, 0.0])
    rng = np.random.default_rng(seed)
    Measurements(t, {"force": force + noise * rng.standard_normal(t.size),
                     "position": run["position"] + 0.1 * noise * rng.standard_normal(t.size)}).to_csv(path)
    print(f"wrote {path}: 1001 samples of t, force, position (m = {m}, b = {b}, c = {c}, noise {noise})")


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--simulate", metavar="FILE.csv", required=True, help="write an example record")
    parser.add_argument("--noise", type=float, default=0.01, help="force noise [N] (position: a tenth, in m)")
    args = parser.parse_args()
    simulate(args.simulate, noise=args.noise)
