"""Policy maps (MODEL §5 item 2): ``make policy-maps`` (= ``fleet-policy-maps``, ``python -m
fleet_torchrl.policy_maps``).

The command line only; what it computes is :mod:`fleet_torchrl.experiments.policy_maps`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .cli import hydra_command, validated
from .utils.cli import user_errors

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from .config import Config


# the groups the maps read
GROUPS = ("site", "eval", "table", "recipes", "maps")


def preflight(cfg: Config, run_dir: str | None) -> None:
    """Before the run folder exists: ``maps.out`` can hold the maps."""
    from .utils.paths import check_output

    check_output("maps.out", cfg.maps.out, "dir")


def task(dcfg: DictConfig) -> None:
    """Draw the action map of every policy of ``maps.policies``."""
    from .config import compose_config
    from .experiments.policy_maps import run

    with user_errors():
        run(validated(dcfg, GROUPS), compose_config(["agent=planner"]).agent)


main = hydra_command(task)

if __name__ == "__main__":
    main()
