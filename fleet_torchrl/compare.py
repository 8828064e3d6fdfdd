"""Command line: evaluation results against a baseline, paired site by site.

    fleet-compare result=RESULT.json baseline=BASELINE.json
    fleet-compare results=[A.json,B.json,...] baseline=BASELINE.json
    fleet-compare results=[A.json,B.json] baseline=BASELINE.json out=CMP.json [overwrite=true]
    (= python -m fleet_torchrl.compare ...)

Every result must pair with the baseline (the same ``eval.seed``, simulations, ticks and
site: simulation ``i`` is the same site in both). Prints a Markdown table, the baseline's row
and one row per result: its mean trips and the gain in % of the baseline's mean, its mean
queue events and the difference from the baseline's, its failure rate and the difference,
each difference with its paired 95 % interval
(:func:`~fleet_torchrl.evaluation.results.paired_comparison`); then one line per result.

With ``out=CMP.json`` it also writes ``CMP.png`` (per result, a box plot of each site's trips
minus the baseline's), ``CMP.csv`` (the table's rows) and ``CMP.json`` (every row with its
per-site differences, the setup, the hashes of the CSV and the figure), each atomically. The
paths are checked before any file is read; an existing comparison is replaced only with
``overwrite=true``, and never a file being compared or a file that is no comparison.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .cli import hydra_command
from .config import to_tool_config
from .experiments.config import CompareConfig
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig


def task(dcfg: DictConfig) -> None:
    """Print the paired comparison of the results with the baseline; write it with ``out``."""
    from .evaluation.results import (
        check_comparison_path,
        compare_results,
        format_comparison,
        save_comparison,
    )

    with user_errors():
        c = to_tool_config(dcfg, CompareConfig)
        files = c.files()
        if c.out is not None:
            check_comparison_path(c.out, c.overwrite, (*files, c.baseline))
        comparison = compare_results(files, c.baseline)
        print(format_comparison(comparison))
        for r in comparison["rows"]:
            print(f"{r['label']} vs {r['baseline']}: {r['gain_pct']:+.2f} % trips "
                  f"(95% CI ± {r['gain_ci95']:.2f}), queue {r['queue_diff']:+.2f} "
                  f"(± {r['queue_diff_ci95']:.2f}), failure rate {r['failure_rate']:.3f} vs "
                  f"{r['baseline_failure_rate']:.3f}")
        if c.out is not None:
            written = save_comparison(comparison, c.out)
            print("wrote " + ", ".join(str(p) for p in written))


main = hydra_command(task, config_name="compare", config_path="tool_conf")

if __name__ == "__main__":
    main()
