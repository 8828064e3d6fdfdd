"""Generalisation sweeps (MODEL §5 item 3): saved policies evaluated on changed sites.

    make sweep-pc      # = python -m fleet_torchrl.sweeps -m +experiment=sweep_pc
                       #   then python -m fleet_torchrl.sweeps_summary pc

The command line only; what it computes is :mod:`fleet_torchrl.experiments.sweeps`.
"""

from __future__ import annotations

import sys
import traceback

import hydra
from omegaconf import DictConfig

from .config import check_command_line, register_configs, to_config
from .experiments.sweeps import point_path, run_point
from .utils.cli import user_errors
from .utils.runinfo import write_text

register_configs()


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(dcfg: DictConfig) -> None:
    with user_errors():
        cfg = to_config(dcfg)
    try:
        run_point(cfg)
    except Exception as e:  # keep the other points of the multirun going
        path = point_path(cfg)
        write_text(path.with_suffix(".error"), traceback.format_exc())
        print(f"error: point {path.stem} failed ({type(e).__name__}: {e}); see "
              f"{path.with_suffix('.error')}", file=sys.stderr)


if __name__ == "__main__":
    check_command_line()
    main()
