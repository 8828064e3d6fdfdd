"""Generalisation sweeps (MODEL §5 item 3): saved policies evaluated on changed sites.

    make sweep-pc      # = fleet-sweeps -m +experiment=sweep_pc   (python -m fleet_torchrl.sweeps)
                       #   then fleet-sweeps-summary name=pc

The command line only; what it computes is :mod:`fleet_torchrl.experiments.sweeps`.
"""

from __future__ import annotations

import sys
import traceback
from typing import TYPE_CHECKING

from .cli import hydra_command, validated
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig


def task(dcfg: DictConfig) -> None:
    """One point of a sweep (one Hydra job); a failure is written beside the point's result
    (``.error``) and the other points go on."""
    from .experiments.sweeps import point_path, run_point
    from .utils.runinfo import write_text

    with user_errors():
        cfg = validated(dcfg)
    try:
        run_point(cfg)
    except Exception as e:  # keep the other points of the multirun going
        path = point_path(cfg)
        write_text(path.with_suffix(".error"), traceback.format_exc())
        print(f"error: point {path.stem} failed ({type(e).__name__}: {e}); see "
              f"{path.with_suffix('.error')}", file=sys.stderr)


main = hydra_command(task)

if __name__ == "__main__":
    main()
