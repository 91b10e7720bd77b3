"""``shootlab demo`` (entry point ``shootlab.commands``: ``demo``; :mod:`shootlab.registry`): the
main job on the report's mass–spring–damper (§3.4) — simulated data are written to DIR.csv, next
to the output folder DIR, and m, b, k estimated from the report's worse start (50), as a user
would type it."""
from __future__ import annotations

import argparse


def add_command(commands) -> None:
    """Add ``demo`` to the sub-commands of the ``shootlab`` parser."""
    from shootlab.cli import EPILOG
    d = commands.add_parser("demo", help="the main job on a built-in example: estimate the report's "
                            "mass-spring-damper from simulated data, with progress output", epilog=EPILOG)
    d.add_argument("--noise", type=float, default=0.0, help="measurement noise std (default 0)")
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo; the record is written "
                   "next to it, out/demo.csv); a rerun replaces it whole")
    d.add_argument("--force", action="store_true", help="replace --out even if shootlab did not write it "
                   "(its files are deleted)")
    d.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Write DIR.csv (m = b = k = 1, noise std ``args.noise`` on u and s; replaced in one step),
    then run ``shootlab estimate`` on it from m = b = k = 50 into DIR."""
    import os
    from pathlib import Path

    from shootlab.cli import dispatch
    from shootlab.outputs import check_output_folder

    from .rig import msd_data, save_csv

    out = check_output_folder(args.out, force=args.force)
    d = msd_data(noise=args.noise, u_noise=args.noise, seed=0)
    csv_path = Path(f"{out if out.name else os.path.abspath(out)}.csv")
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    partial = csv_path.with_name(f".{csv_path.name}.partial")
    try:
        save_csv(partial, {k: d[k] for k in ("t", "u", "s")}, columns=["t", "u", "s"])
        os.replace(partial, csv_path)
    finally:
        partial.unlink(missing_ok=True)
    args.wrote = str(csv_path)
    print(f"wrote {csv_path} (m = b = k = 1, noise {args.noise:g}); now, as a user would type it:")
    argv = ["estimate", "--model", "msd", "--data", str(csv_path), "--initial", "m=50", "b=50", "k=50",
            "--out", str(out)]
    print("  shootlab " + " ".join(argv), flush=True)
    return dispatch(argv)
