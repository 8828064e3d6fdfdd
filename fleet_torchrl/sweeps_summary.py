"""Collect the points of a sweep into ``results/sweeps/<name>.{csv,json,png}``.

    fleet-sweeps-summary name=pc [out=results/sweeps]   (= python -m fleet_torchrl.sweeps_summary)

Exit code 1 when a point failed or an expected point is missing (the points of the packaged
experiment ``sweep_<name>``, or ``expect``). The command line only; what it computes is
:mod:`fleet_torchrl.experiments.sweeps_summary`.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

from .cli import hydra_command
from .config import to_tool_config
from .experiments.config import SweepSummaryConfig
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig


def task(dcfg: DictConfig) -> None:
    """Summarise sweep ``name``; exit code 1 if a point failed or is missing."""
    from .experiments.sweeps_summary import expected_points, summarize
    from .utils.paths import check_output

    with user_errors():
        c = to_tool_config(dcfg, SweepSummaryConfig)
        check_output("out", c.out, "dir")
        expect = c.expect if c.expect is not None else expected_points(c.name)
        s = summarize(c.name, Path(c.out), expect)
    n_points = len({r["value"] for r in s["rows"]})
    print(f"[sweep {c.name}] {n_points} points -> {c.out}/{c.name}.csv, .json, .png")
    for label, items in (("failed", s["failed"]), ("missing", s["missing"])):
        if items:
            print(f"[sweep {c.name}] {label}: {', '.join(items)} (rerun the target to retry)")
    if s["failed"] or s["missing"]:
        sys.exit(1)


main = hydra_command(task, config_name="sweeps_summary")

if __name__ == "__main__":
    main()
