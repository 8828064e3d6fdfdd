"""Summary of a grid-search multirun (``make grid``): rank configurations across seeds.

    fleet-grid sweep_dir=multirun/grid/<date_time>     # or none: the latest
    (= python -m fleet_torchrl.grid ...)

The command line only; what it computes is :mod:`fleet_torchrl.experiments.grid`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from .cli import hydra_command
from .config import to_tool_config
from .experiments.config import GridSummaryConfig
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig


def task(dcfg: DictConfig) -> None:
    """Rank the grid's configurations; write the summary into the sweep folder and ``out``."""
    from .experiments.grid import FIELDS, collect, latest_sweep, markdown, summarize
    from .utils.paths import check_input_dir, check_output
    from .utils.runinfo import write_csv, write_json, write_text

    with user_errors():
        c = to_tool_config(dcfg, GridSummaryConfig)
        sweep = Path(c.sweep_dir) if c.sweep_dir else latest_sweep()
        check_input_dir("sweep_dir", sweep)
        check_output("sweep_dir", sweep, "dir")  # the summary is written into it too
        check_output("out", c.out, "dir")
        jobs, missing, shared = collect(sweep)
        if not jobs:
            raise FileNotFoundError(f"no finished job in {sweep}")
        rows = summarize(jobs)
        md = markdown(rows, missing, sweep, shared)
        for folder in (sweep, Path(c.out)):
            write_text(folder / "summary.md", md)
            write_csv(folder / "summary.csv", rows, FIELDS)
            write_json(folder / "summary.json", {"sweep": str(sweep), "shared": shared,
                                                 "rows": rows, "missing": missing,
                                                 "jobs": jobs})
    print(md)


main = hydra_command(task, config_name="grid")

if __name__ == "__main__":
    main()
