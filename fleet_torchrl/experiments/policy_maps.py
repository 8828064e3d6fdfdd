"""Policy maps (MODEL §5 item 2): ``make policy-maps`` (= ``python -m fleet_torchrl.policy_maps``).

For each policy of ``maps.policies`` (saved ones from ``table.policies_dir``), the action on a
grid of ``soc_D`` (y) x lowest soc of the others (x), one panel per charger time ``TC``: free
and busy for the rule, the heuristic and the tabular agent (which only sees TC > 0), and TC in
{0, 0.2, ..., 1} for DQN. Writes ``results/policy_maps/<name>.png``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ..store import load_policies
from ..utils.plotting import plot_policy_map, save_figure

if TYPE_CHECKING:
    from ..config import Config


def run(cfg: Config) -> list[Path]:
    out = Path(cfg.maps.out)
    paths = []
    for name, pol in load_policies(cfg, cfg.maps.policies).items():
        pol = pol.cpu()
        fig = plot_policy_map(pol, title=f"{name}: charge (orange) / pass, by TC")
        paths.append(save_figure(fig, out / f"{name}.png"))
        print(f"[policy-maps] {paths[-1]}")
    return paths
