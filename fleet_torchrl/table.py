"""``make table``: the main comparison of MODEL §5 item 1 in one command.

    fleet-table                       # 1000 sims x 10 000 ticks (python -m fleet_torchrl.table)
    fleet-table eval.n_sims=200 table.seeds=1 table.retrain=true
    fleet-table table.only=[dqn_partial,search]

The command line only; what it trains, evaluates and writes is
:mod:`fleet_torchrl.experiments.table`.
"""

from __future__ import annotations

import subprocess
import sys
from typing import TYPE_CHECKING

from .cli import hydra_command, validated
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig


def task(dcfg: DictConfig) -> None:
    """Train what is missing, evaluate, write the table."""
    from .experiments.table import run

    try:
        with user_errors():
            run(validated(dcfg))
    except subprocess.CalledProcessError as e:
        print(f"error: training failed ({' '.join(e.cmd[2:4])}...); rerun `make table` to "
              "resume it from its checkpoint", file=sys.stderr)
        sys.exit(1)


main = hydra_command(task)

if __name__ == "__main__":
    main()
