"""Assemble ``docs/report.md`` from result files only: ``make report``.

    python -m fleet_torchrl.report [--results results] [--out docs/report.md]

The command line only; what it computes is :mod:`fleet_torchrl.experiments.report`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .experiments.report import build
from .utils.cli import user_errors
from .utils.runinfo import write_text


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", default="results")
    p.add_argument("--out", default="docs/report.md")
    a = p.parse_args(argv)
    results = Path(a.results)
    with user_errors():
        if not (results / "table" / "table.md").is_file():
            raise FileNotFoundError(f"no main comparison under {results} (table/table.md): run "
                                    f"`make table` first; {a.out} is left unchanged")
    out = Path(a.out)
    write_text(out, build(results, out))
    print(f"[report] wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
