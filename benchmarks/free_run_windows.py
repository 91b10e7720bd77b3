"""Free runs whose sweeps fail over the whole record: in windows against sample by sample, side by
side in one process (:func:`shootlab.estimation.free_run._in_windows`).

A free run is first shot with all its sample intervals at once; where the linearisation about the
constant start carries the Newton corrections too far (a run that is unstable or strongly
non-linear) those sweeps fail.  The run then goes in windows that shorten where they fail; before,
it went sample by sample.  Each case is timed both ways, alternating, ``--repeat`` times (the
median kept), and the two runs' states compared:

* ``pendulum``: the user's pendulum of ``tests/shared.py`` with the library's Coulomb friction, at
  the non-physical values its output-error fit passes through on the Coulomb record of
  ``tests/engine/test_diagnosis_output_error_weighing.py`` (``friction_record("coulomb", False, 0)``;
  f = −0.54 pumps energy in: stiff,
  Radau IIA; the whole-record sweeps' defects reach 1e143);
* ``van_der_pol``: van der Pol's oscillator (μ = 1) from near its unstable rest, 40 s at 10 Hz
  (RK4);
* ``coulomb_fit``: that pendulum's whole output-error fit of Coulomb friction, from the test's
  start (86 free runs; ``--no-fit`` leaves it out).

    python benchmarks/free_run_windows.py [--repeat 3] [--no-fit] [--out ...]

About three minutes on one core.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import shootlab.estimation.free_run as fr  # noqa: E402
sys.path.insert(0, str(ROOT / "tests"))        # the pendulum and its records: the tests' own
from shared import friction_record, pendulum  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "free_run_windows.json"
D = torch.float64


def sample_by_sample(shoot, s0, ts, fallback):
    """The earlier path: the whole record run by the fallback, sample by sample."""
    return fallback(s0, ts)


def timed(fn, repeat: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def side_by_side(name: str, run, repeat: int, compare) -> dict:
    """``run()`` in windows and sample by sample, alternating; ``compare(a, b)``: the largest
    difference of the two results and its scale."""
    windows, alone = [], []
    got = {}
    for _ in range(repeat):
        for label, sink in (("windows", windows), ("sample_by_sample", alone)):
            saved = fr._in_windows
            if label == "sample_by_sample":
                fr._in_windows = sample_by_sample
            try:
                t, got[label] = timed(run, 1)
            finally:
                fr._in_windows = saved
            sink.append(t)
    diff, scale = compare(got["windows"], got["sample_by_sample"])
    row = dict(case=name, windows_s=statistics.median(windows), sample_by_sample_s=statistics.median(alone),
               speedup=statistics.median(alone) / statistics.median(windows), max_difference=diff, scale=scale)
    print(f"{name}: in windows {row['windows_s']:.2f} s, sample by sample {row['sample_by_sample_s']:.2f} s "
          f"({row['speedup']:.1f}x); largest difference {diff:.2g} (scale {scale:.3g})", flush=True)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-fit", action="store_true", help="leave out the output-error fit")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    from shootlab.diagnosis import library_for
    from shootlab.diagnosis.composition import extend
    from shootlab.diagnosis.free_run_screen import output_error_fit

    model, data = pendulum(), friction_record("coulomb", False, 0)
    lib = library_for(model, data)
    coulomb = extend(model, [lib["coulomb"]], data=data)
    pumping = dict(coulomb.prior, J=0.46205, b=0.55503, k=3.29824, coulomb_f=-0.54054)

    def states(run):
        return np.stack([run["state:th"], run["state:w"]], -1)

    rows = [side_by_side("pendulum", lambda: fr.simulate(coulomb, data, pumping), a.repeat,
                         lambda x, y: (float(np.abs(states(x) - states(y)).max()), float(np.abs(states(y)).max())))]

    def vdp(t, s):
        x, v = s[..., 0], s[..., 1]
        return torch.stack([v, (1 - x ** 2) * v - x], -1)
    ts = torch.linspace(0.0, 40.0, 401, dtype=D)
    s0 = torch.tensor([0.01, 0.0], dtype=D)

    def vdp_run():
        if fr._rk4_in_parallel(vdp, s0, ts)[0] is not None:
            raise RuntimeError("the whole-record sweeps converged: nothing to compare")
        return fr._rk4_in_windows(vdp, s0, ts)
    rows.append(side_by_side("van_der_pol", vdp_run, a.repeat,
                             lambda x, y: (float((x - y).abs().max()), float(y.abs().max()))))
    if not a.no_fit:
        def fit():
            return output_error_fit(coulomb, data, dict(coulomb.prior, coulomb_f=0.05), lib.initial_state,
                                    bounds={}, max_runs=500)

        def same(x, y):
            assert x.success and y.success, (x.message, y.message)
            return (max(abs(x.parameters[p] - y.parameters[p]) for p in x.parameters),
                    max(abs(v) for v in y.parameters.values()))
        rows.append(side_by_side("coulomb_fit", fit, 1, same))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(dict(torch=torch.__version__, threads=torch.get_num_threads(), cases=rows), indent=1))
    print(f"written {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
