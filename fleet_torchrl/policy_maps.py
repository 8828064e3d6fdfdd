"""Policy maps (SPEC §5 item 2): ``make policy-maps`` (= ``python -m fleet_torchrl.policy_maps``).

For each policy of ``maps.policies`` (saved ones from ``table.policies_dir``), the action on a
grid of ``soc_D`` (y) x lowest soc of the others (x), one panel per charger time ``TC``: free
and busy for the rule, the heuristic and the tabular agent (which only sees TC > 0), and TC in
{0, 0.2, ..., 1} for DQN. Writes ``results/policy_maps/<name>.png``.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from .agents import load_policies
from .cli import user_errors
from .config import Config, register_configs, to_config
from .plotting import TC_DQN, TC_TABULAR, plot_policy_map, save_figure

register_configs()


def run(cfg: Config) -> list[Path]:
    out = Path(cfg.maps.out)
    paths = []
    for name, pol in load_policies(cfg, cfg.maps.policies).items():
        pol = pol.cpu()
        tcs = TC_DQN if name.startswith("dqn") else TC_TABULAR
        fig = plot_policy_map(pol, tcs, title=f"{name}: charge (orange) / pass, by TC")
        paths.append(save_figure(fig, out / f"{name}.png"))
        print(f"[policy-maps] {paths[-1]}")
    return paths


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(dcfg: DictConfig) -> None:
    with user_errors():
        run(to_config(dcfg))


if __name__ == "__main__":
    main()
