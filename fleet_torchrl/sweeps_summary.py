"""Collect the points of a sweep into ``results/sweeps/<name>.{csv,json,png}``.

    python -m fleet_torchrl.sweeps_summary pc [--out results/sweeps]

The command line only; what it computes is :mod:`fleet_torchrl.experiments.sweeps_summary`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .experiments.sweeps_summary import summarize
from .utils.cli import user_errors


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("name")
    p.add_argument("--out", default="results/sweeps")
    p.add_argument("--expect", nargs="*", default=None,
                   help="point names expected, e.g. p_c=0.0 p_c=0.2 (reported if missing)")
    a = p.parse_args(argv)
    with user_errors():
        s = summarize(a.name, Path(a.out), a.expect)
    n_points = len({r["value"] for r in s["rows"]})
    print(f"[sweep {a.name}] {n_points} points -> {a.out}/{a.name}.csv, .json, .png")
    for label, items in (("failed", s["failed"]), ("missing", s["missing"])):
        if items:
            print(f"[sweep {a.name}] {label}: {', '.join(items)} (rerun the target to retry)")
    return 1 if s["failed"] or s["missing"] else 0


if __name__ == "__main__":
    sys.exit(main())
