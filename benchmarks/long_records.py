"""Records of any length: the mass–spring–damper estimated from 20,000 and 200,000 samples with
every default of the command line, side by side in one run.

For each duration the record is simulated as a user makes it (``shootlab simulate msd --noise 0.01
--duration D``: 100 Hz, 1 % noise) and estimated by ``shootlab estimate --model msd --data ...
--initial m=10 b=10 k=10 --out ...`` (default shooting points, integrator, figures), each in its
own process.  Measured per record: the wall time and the peak resident memory of the estimate's
process (``os.wait4``'s ru_maxrss), the shooting points the default chose, the Newton
iterations, m, b, k with their standard errors and how many standard errors each is from the
true value 1, and the progress lines of the phases after Newton (stderr).  The criteria: the long
record's estimate under 2 GB and at most 15 times the short one's time.

    python benchmarks/long_records.py [--durations 199.99 1999.99] [--out FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "long_records.json"


def run(argv: list[str], cwd: Path) -> tuple[float, float, int, str, str]:
    """(wall seconds, peak resident memory in MB, exit status, stdout, stderr) of ``python -m
    shootlab argv``: the child is reaped by ``os.wait4``, whose resource usage is that child's
    alone (its output goes to files meanwhile)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        clock = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "shootlab", *argv], cwd=cwd, env=env, stdout=fo, stderr=fe)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - clock
        proc.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        return wall, usage.ru_maxrss / 1024, proc.returncode, fo.read(), fe.read()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--durations", type=float, nargs="+", default=[199.99, 1999.99])
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for duration in args.durations:
            csv = work / f"msd_{duration:g}.csv"
            _, _, code, out, err = run(["simulate", "msd", "--noise", "0.01", "--duration", str(duration),
                                        "--out", csv.name], work)
            if code != 0:
                raise SystemExit(f"simulate failed: {err}")
            folder = work / f"out_{duration:g}"
            wall, rss, code, out, err = run(["estimate", "--model", "msd", "--data", csv.name, "--initial",
                                             "m=10", "b=10", "k=10", "--out", folder.name], work)
            info = json.loads((folder / "estimate.json").read_text()) if (folder / "estimate.json").exists() else {}
            est, se = info.get("parameters", {}), info.get("standard_errors", {})
            row = dict(duration=duration, samples=sum(1 for _ in open(csv)) - 1, exit=code, wall_s=round(wall, 1),
                       max_rss_mb=round(rss), points=info.get("points"), iterations=info.get("iterations"),
                       success=info.get("success"), parameters=est, standard_errors=se,
                       errors_in_se={p: round(abs(v - 1.0) / se[p], 2) for p, v in est.items() if se.get(p)},
                       phases=[ln for ln in err.splitlines() if ln.startswith("-- ")])
            rows.append(row)
            print(f"{row['samples']:>7} samples: {row['points']} points, {row['iterations']} iterations, "
                  f"{row['wall_s']} s, {row['max_rss_mb']} MB, exit {code}; |θ − 1|/SE {row['errors_in_se']}",
                  flush=True)
    result = dict(rows=rows)
    if len(rows) >= 2:
        result["time_ratio"] = round(rows[-1]["wall_s"] / rows[0]["wall_s"], 2)
        result["criteria"] = dict(long_under_2GB=rows[-1]["max_rss_mb"] < 2048,
                                  time_ratio_at_most_15=result["time_ratio"] <= 15.0)
        print(f"time ratio {result['time_ratio']}; criteria {result['criteria']}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
