"""Policy maps (MODEL §5 item 2): ``make policy-maps`` (= ``python -m fleet_torchrl.policy_maps``).

The command line only; what it computes is :mod:`fleet_torchrl.experiments.policy_maps`.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from .config import check_command_line, register_configs, to_config
from .experiments.policy_maps import run
from .utils.cli import user_errors

register_configs()


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(dcfg: DictConfig) -> None:
    with user_errors():
        run(to_config(dcfg))


if __name__ == "__main__":
    check_command_line()
    main()
