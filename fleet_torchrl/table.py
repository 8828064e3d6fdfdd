"""``make table``: the main comparison of MODEL §5 item 1 in one command.

    python -m fleet_torchrl.table                       # defaults: 1000 sims x 10 000 ticks
    python -m fleet_torchrl.table eval.n_sims=200 table.seeds=1 table.retrain=true

The command line only; what it trains, evaluates and writes is
:mod:`fleet_torchrl.experiments.table`.
"""

from __future__ import annotations

import subprocess
import sys

import hydra
from omegaconf import DictConfig

from .config import check_command_line, register_configs, to_config
from .experiments.table import run
from .utils.cli import user_errors

register_configs()


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(dcfg: DictConfig) -> None:
    try:
        with user_errors():
            run(to_config(dcfg))
    except subprocess.CalledProcessError as e:
        print(f"error: training failed ({' '.join(e.cmd[2:4])}...); rerun `make table` to "
              "resume it from its checkpoint", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    check_command_line()
    main()
