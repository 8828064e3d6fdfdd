"""Generalisation sweeps (MODEL §5 item 3): saved policies evaluated on changed sites.

    make sweep-pc      # = fleet-sweeps -m +experiment=sweep_pc   (python -m fleet_torchrl.sweeps)
                       #   then fleet-sweeps-summary name=pc

The command line only; what it computes is :mod:`fleet_torchrl.experiments.sweeps`.
"""

from __future__ import annotations

import sys
import traceback
from typing import TYPE_CHECKING, Any

from .cli import hydra_command, validated
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from .config import Config


# the groups a sweep point reads
GROUPS = ("site", "state", "mdp", "agent", "network", "train", "eval", "table", "recipes",
          "sweep")


def preflight(cfg: Config, run_dir: str | None) -> None:
    """Before any point is launched: a sweep of one site (not a distribution) whose outputs
    can be written and whose folder is its own."""
    from .experiments.sweeps import check_point_outputs
    from .utils.checks import ConfigError

    if cfg.site.randomized:
        raise ConfigError(f"site={cfg.site.name!r} is a site distribution: a sweep varies "
                          f"{cfg.sweep.param} of one site; run it on a single site "
                          "(e.g. site=default)")
    check_point_outputs(cfg)


def task(dcfg: DictConfig) -> Any:
    """One point of a sweep (one Hydra job); a failure is written beside the point's result
    (``.error``) and the other points go on, but it counts: the job returns
    :class:`~fleet_torchrl.experiments.launch.JobFailed`, so the multirun exits non-zero at
    its end (a single point's run exits 1 at once)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from .experiments.launch import JobFailed
    from .experiments.sweeps import point_path, run_point
    from .utils.runinfo import write_text

    with user_errors():
        cfg = validated(dcfg, GROUPS)
    try:
        run_point(cfg)
    except Exception as e:  # keep the other points of the multirun going
        path = point_path(cfg)
        write_text(path.with_suffix(".error"), traceback.format_exc())
        msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
        print(f"error: point {path.stem} failed ({type(e).__name__}: {msg}); see "
              f"{path.with_suffix('.error')}", file=sys.stderr)
        if HydraConfig.get().mode != RunMode.MULTIRUN:
            sys.exit(1)
        return JobFailed(path.stem, f"{type(e).__name__}: {msg}")
    return None


main = hydra_command(task)

if __name__ == "__main__":
    main()
