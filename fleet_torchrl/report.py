"""Assemble ``docs/report.md`` from result files only: ``make report``.

    fleet-report [results=results] [out=docs/report.md]    (= python -m fleet_torchrl.report)

The command line only; what it computes is :mod:`fleet_torchrl.experiments.report`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .cli import hydra_command
from .config import to_tool_config
from .experiments.config import ReportConfig
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig


def task(dcfg: DictConfig) -> None:
    """Write the report from the result files under ``results``."""
    from .experiments.report import build
    from .utils.paths import check_input_dir, check_output
    from .utils.runinfo import write_text

    with user_errors():
        c = to_tool_config(dcfg, ReportConfig)
        results = check_input_dir("results", c.results)
        out = check_output("out", c.out, "file")  # the report, and its figures beside it
        check_output("out", out.parent / "figures", "dir")
        if not (results / "table" / "table.md").is_file():
            raise FileNotFoundError(f"no main comparison under {results} (table/table.md): run "
                                    f"`make table` first; {c.out} is left unchanged")
        write_text(out, build(results, out))
    print(f"[report] wrote {out}")


main = hydra_command(task, config_name="report")

if __name__ == "__main__":
    main()
