"""Policy maps (MODEL §5 item 2): ``make policy-maps`` (= ``python -m fleet_torchrl.policy_maps``).

For each policy of ``maps.policies`` (saved ones from ``table.policies_dir``), the action on a
grid of ``soc_D`` (y) x lowest soc of the others (x), one panel per charger time ``TC``: free
and busy for the rule, the heuristic and the tabular agent (which only sees TC > 0), and TC in
{0, 0.2, ..., 1} for DQN. Writes ``results/policy_maps/<name>.png``.
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from .config import register_configs, to_config
from .experiments.policy_maps import run
from .utils.cli import user_errors

register_configs()


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(dcfg: DictConfig) -> None:
    with user_errors():
        run(to_config(dcfg))


if __name__ == "__main__":
    main()
