"""The figure writers' time, per figure, side by side with the writers of another commit.

Two jobs, each drawn ``--repeats`` times alternating between this checkout's ``shootlab/outputs.py``
and the one at ``--against`` (read with ``git show``, loaded as a module of its own):

* ``channels.png`` and ``residuals.png`` of ``shootlab estimate --model confined --option
  elements=20`` on the 1 %-noise 200-element record (401 samples, 43 equation rows; the estimate
  computed once, :func:`shootlab.outputs.plot_estimation`);
* ``channels.png`` of an output-error result on a 200,000-sample mass–spring–damper record (the
  free run's line and the samples; the result assembled from the simulated truth, no fit:
  :func:`shootlab.outputs.write_output_error`, its CSV not written).

Times (wall and CPU, medians) exclude matplotlib's import and a first draw of each job (fonts
loaded).  Writes ``benchmarks/results/figures.json``.

Run: ``python benchmarks/figures.py [--repeats 5] [--against REF]``.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

OUT = ROOT / "benchmarks" / "results" / "figures.json"


def outputs_at(ref: str, folder: Path):
    """``shootlab/outputs.py`` as it was at ``ref``, loaded as the module ``shootlab._outputs_at_ref``."""
    source = subprocess.run(["git", "show", f"{ref}:shootlab/outputs.py"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout
    path = folder / "outputs_at_ref.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("shootlab._outputs_at_ref", path,
                                                  submodule_search_locations=None)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = "shootlab"
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def confined_estimate(folder: Path):
    """The confined N = 20 estimate on the 1 %-noise record of ``estimation_vs_casadi``."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from estimation_vs_casadi import mixture_records

    from shootlab.estimation.data import Measurements
    from shootlab.estimation import estimate
    from shootlab.estimation.lookup import resolve_model

    csv = mixture_records(folder)["1% noise"]
    res = estimate(resolve_model("confined", {"elements": 20}), Measurements.from_csv(csv))
    res.standard_errors                                   # the covariance: computed once, outside the timing
    return res


def long_output_error():
    """An output-error result on 200,000 samples of the msd (m = b = k = 1, 1 % noise), its free
    run the noise-free truth."""
    from manipulators.msd import model
    from manipulators.rig import msd_data
    from shootlab.estimation.data import Measurements
    from shootlab.bvp.newton import Status
    from shootlab.estimation.output_error import OutputErrorResult

    t = np.linspace(0.0, 1999.99, 200_000)
    d = msd_data(t=t, noise=0.01, seed=0)
    data = Measurements(d["t"], {"u": d["u"], "s": d["s"]})
    res = OutputErrorResult(model=model(), parameters=dict(m=1.0, b=1.0, k=1.0), success=True,
                            status=Status.CONVERGED, message="converged", cost=0.0, samples=t.size, evaluations=0,
                            standard_errors=dict(m=1e-4, b=1e-4, k=1e-4), predicted={"s": d["s_true"]})
    return res, data


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--against", default="HEAD", help="the commit whose figure writers to time beside these")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    import matplotlib.pyplot  # noqa: F401  (the import outside the timings)

    from shootlab import outputs

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        writers = {"this": outputs, args.against: outputs_at(args.against, tmp)}
        res = confined_estimate(tmp)
        oe, data = long_output_error()
        def oe_figure(o, d):                      # write_output_error without its CSV: the figure's time
            savetxt, np.savetxt = np.savetxt, lambda *a, **k: None
            try:
                o.write_output_error(oe, data, d)
            finally:
                np.savetxt = savetxt
        jobs = {"confined N=20: channels.png + residuals.png": lambda o, d: o.plot_estimation(res, d),
                "msd 200,000 samples, output error: channels.png": oe_figure}
        times = {job: {w: [] for w in writers} for job in jobs}
        cpu = {job: {w: [] for w in writers} for job in jobs}
        for job, draw in jobs.items():                # a first draw of each: fonts and caches loaded
            draw(writers["this"], tmp)
        for r in range(args.repeats):
            for j, (job, draw) in enumerate(jobs.items()):
                for w in (list(writers) if r % 2 == 0 else list(writers)[::-1]):
                    folder = tmp / f"{w}_{r}_{j}".replace("/", "_")
                    folder.mkdir()
                    t0, c0 = time.perf_counter(), time.process_time()
                    draw(writers[w], folder)
                    times[job][w].append(time.perf_counter() - t0)
                    cpu[job][w].append(time.process_time() - c0)
        sizes = {p.name: p.stat().st_size for p in sorted(folder.iterdir())}
    result = dict(repeats=args.repeats, against=args.against, seconds=times, cpu_seconds=cpu,
                  median={job: {w: float(np.median(v)) for w, v in ws.items()} for job, ws in times.items()},
                  median_cpu={job: {w: float(np.median(v)) for w, v in ws.items()} for job, ws in cpu.items()},
                  last_files_bytes=sizes)
    for job in jobs:
        print(f"{job}: " + ", ".join(f"{w} {result['median'][job][w]:.3f} s wall, {result['median_cpu'][job][w]:.3f} s CPU"
                                     for w in writers))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
