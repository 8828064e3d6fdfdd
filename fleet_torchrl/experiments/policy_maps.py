"""Policy maps (MODEL §5 item 2): ``make policy-maps`` (= ``python -m fleet_torchrl.policy_maps``).

For each policy of ``maps.policies`` (saved ones from ``table.policies_dir``), the action on a
grid of ``soc_D`` (y) x lowest soc of the others (x), one panel per charger time ``TC``: free
and busy for the rule, the heuristic and the tabular agent (which only sees TC > 0), and TC in
{0, 0.2, ..., 1} for DQN. Writes ``results/policy_maps/<name>.png``.

The rollout planner (MODEL §3.6) decides from the whole site, not from these three features,
so it has no map of its own: :func:`planner_maps` runs it (its defaults, base the heuristic)
on each site of ``maps.planner_sites`` and draws, per cell of ``soc_D`` x ``TC`` and of
``soc_D`` x the lowest other soc, the share of charge decisions among the states it met
(``results/policy_maps/planner_<site>.png``). A saved policy that reads more than these
features (``all``, ``partial_all_site``: the generalist) gets the same kind of figure, on
the configured site.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import torch

from ..agents.base import Policy
from ..agents.baselines import HeuristicPolicy
from ..agents.planner import PlannerPolicy
from ..env.encodings import get_encoding
from ..evaluation import simulate
from ..store import load_policies, site_preset
from ..utils.checks import ConfigError
from ..utils.plotting import (
    MAP_ENCODINGS,
    plot_decision_shares,
    plot_policy_map,
    save_figure,
)

if TYPE_CHECKING:
    from ..evaluation.config import EvalConfig
    from ..sim import SiteConfig
    from .config import MapsConfig, TableConfig


class MapsRun(Protocol):
    """What the maps read of the command's config."""

    maps: MapsConfig
    table: TableConfig
    site: SiteConfig
    eval: EvalConfig

BINS = 20  # cells per axis of the planner's maps (5 % of soc, 1/20 of TC)


def decision_shares(planner: Policy, site, n_sims: int, ticks: int, seed: int
                    ) -> dict[str, torch.Tensor]:
    """Run ``planner`` on the protocol's sites and count its decisions per cell: returns the
    share of charge per cell of ``soc_D`` x ``TC`` and ``soc_D`` x lowest other soc
    (``[BINS, BINS]``, NaN where no state fell)."""
    encode = get_encoding("partial")
    feats, acts = [], []
    inner = planner.decide

    def record(site_, state, ctx):
        a = inner(site_, state, ctx)
        feats.append(encode(site_, state)[ctx.need].cpu())
        acts.append(a[ctx.need].cpu())
        return a

    planner.decide = record  # (this instance only, for this run)
    try:  # the eager loop: every decision through decide (an in-kernel policy would skip it)
        simulate(planner, site, n_sims, ticks, seed,
                 fused=None if isinstance(planner, PlannerPolicy) else False)
    finally:
        del planner.decide
    obs, act = torch.cat(feats), torch.cat(acts).double()
    cell = lambda v: (v * BINS).long().clamp(0, BINS - 1)  # noqa: E731
    out = {}
    for key, col in (("tc", 2), ("others", 1)):
        idx = cell(obs[:, 0]) * BINS + cell(obs[:, col])
        n = torch.bincount(idx, minlength=BINS * BINS).double()
        c = torch.bincount(idx, weights=act, minlength=BINS * BINS)
        out[key] = torch.where(n > 0, c / n.clamp(min=1), float("nan")).view(BINS, BINS)
    return out


def shares_figure(shares: dict[str, torch.Tensor], title: str):
    """The two panels of :func:`decision_shares` (by ``TC``, by the others' lowest soc)."""
    return plot_decision_shares(
        [(shares["tc"], "TC (charger's remaining time)", (0.0, 1.0)),
         (shares["others"], "lowest soc of the others", (0.0, 100.0))], title)


def planner_maps(cfg: MapsRun, agent: Any) -> list[Path]:
    """The planner's decision shares (``agent``: its settings) on ``maps.planner_sites``."""
    out, paths = Path(cfg.maps.out), []
    for name in cfg.maps.planner_sites:
        site = site_preset(name)
        if site is None:
            raise ConfigError(f"maps.planner_sites: {name!r} is not a site preset")
        shares = decision_shares(PlannerPolicy.from_config(agent, HeuristicPolicy()), site,
                                 cfg.maps.planner_sims, cfg.maps.planner_ticks, cfg.eval.seed)
        fig = shares_figure(shares, f"planner on site {name}: share of charge decisions "
                                    "among the states it met")
        paths.append(save_figure(fig, out / f"planner_{name}.png"))
        print(f"[policy-maps] {paths[-1]}")
    return paths


def run(cfg: MapsRun, planner: Any) -> list[Path]:
    """The map of every policy of ``maps.policies``, then the planner's (``planner``: its
    settings, :func:`planner_maps`)."""
    out = Path(cfg.maps.out)
    paths = []
    for name, pol in load_policies(cfg.table.policies_dir, cfg.maps.policies, cfg.eval.device,
                                   cfg.table.follow_symlinks).items():
        pol = pol.cpu()
        if pol.encoding in MAP_ENCODINGS:
            fig = plot_policy_map(pol, title=f"{name}: charge (orange) / pass, by TC")
        else:  # it reads more than the map's axes: what it did in the states it met
            shares = decision_shares(pol, cfg.site, cfg.maps.planner_sims,
                                     cfg.maps.planner_ticks, cfg.eval.seed)
            fig = shares_figure(shares, f"{name} ({pol.encoding} state) on site "
                                        f"{cfg.site.name}: share of charge decisions among "
                                        "the states it met")
        paths.append(save_figure(fig, out / f"{name}.png"))
        print(f"[policy-maps] {paths[-1]}")
    return paths + planner_maps(cfg, planner)
