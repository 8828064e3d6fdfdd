"""Command line: paired comparison of two evaluation results.

    python -m fleet_torchrl.compare RESULT.json BASELINE.json

Prints the gain in trips of RESULT over BASELINE in percent of the baseline's mean, with the
half-width of its 95% confidence interval from the paired per-simulation differences.
"""

from __future__ import annotations

import argparse
import sys

from .evaluation import compare
from .utils.cli import user_errors


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="paired gain in trips of one result over another")
    p.add_argument("result")
    p.add_argument("baseline")
    a = p.parse_args(argv)
    with user_errors():
        g = compare(a.result, a.baseline)
    print(f"{g['policy']} vs {g['baseline']}: {g['gain_pct']:+.2f} % trips "
          f"(95% CI ± {g['gain_ci95']:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
