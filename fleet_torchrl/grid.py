"""Summary of a grid-search multirun (``make grid``): rank configurations across seeds.

    python -m fleet_torchrl.grid multirun/grid/<date_time>     # or no argument: the latest

The command line only; what it computes is :mod:`fleet_torchrl.experiments.grid`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .experiments.grid import FIELDS, collect, latest_sweep, markdown, summarize
from .utils.cli import user_errors
from .utils.runinfo import write_csv, write_json, write_text


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sweep_dir", nargs="?", default=None)
    p.add_argument("--out", default="results/grid", help="copy of the summary files")
    a = p.parse_args(argv)
    with user_errors():
        sweep = Path(a.sweep_dir) if a.sweep_dir else latest_sweep()
        if not sweep.is_dir():
            raise FileNotFoundError(f"no such sweep folder: {sweep}")
        jobs, missing, shared = collect(sweep)
        if not jobs:
            raise FileNotFoundError(f"no finished job in {sweep}")
    rows = summarize(jobs)
    md = markdown(rows, missing, sweep, shared)
    for folder in (sweep, Path(a.out)):
        write_text(folder / "summary.md", md)
        write_csv(folder / "summary.csv", rows, FIELDS)
        write_json(folder / "summary.json", {"sweep": str(sweep), "shared": shared,
                                             "rows": rows, "missing": missing, "jobs": jobs})
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
