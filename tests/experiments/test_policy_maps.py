"""Policy maps from saved policies."""

from __future__ import annotations

from fleet_torchrl.config import compose_config


def test_policy_maps_from_saved_policies(tmp_path, saved_policies):
    from fleet_torchrl.experiments.policy_maps import run

    root = saved_policies
    cfg = compose_config([f"table.policies_dir={root}", f"maps.out={tmp_path / 'maps'}",
                          "maps.planner_sims=4", "maps.planner_ticks=300"])
    paths = run(cfg, compose_config(["agent=planner"]).agent)
    assert sorted(p.name for p in paths) == ["dqn_partial.png", "generalist.png",
                                             "heuristic.png", "imitation.png",
                                             "planner_default.png",
                                             "planner_five_vehicles.png", "rule.png",
                                             "search.png", "tabular.png"]
    from fleet_torchrl.agents import RulePolicy
    from fleet_torchrl.utils.plotting import TC_TABULAR, policy_map

    m = policy_map(RulePolicy(), TC_TABULAR, n=101)
    assert m.shape == (2, 101, 101)
    assert m[0, 40, :].eq(1).all() and m[0, 41, :].eq(0).all()  # charge iff soc_D <= 40


def test_the_planners_decision_shares():
    """Per cell, the share of charge among the planner's decisions: in [0, 1] where it met
    states, NaN elsewhere; below its reserve floor (about 38.7 % here) it charges as its base
    does, and it never charges a full battery."""
    import torch

    from fleet_torchrl.agents import HeuristicPolicy
    from fleet_torchrl.agents.planner import PlannerPolicy
    from fleet_torchrl.experiments.policy_maps import BINS, decision_shares
    from fleet_torchrl.sim import SiteConfig

    pol = PlannerPolicy(HeuristicPolicy(), rollouts=4, horizon=60)
    shares = decision_shares(pol, SiteConfig(n_vehicles=4), 16, 800, 0)
    assert "decide" not in vars(pol)  # the recording wrapper is gone
    for m in shares.values():
        assert m.shape == (BINS, BINS)
        seen = ~torch.isnan(m)
        assert seen.sum() > 10 and ((m[seen] >= 0) & (m[seen] <= 1)).all()
        low = m[:7][seen[:7]]  # soc_D below 35 %
        assert low.numel() and (low == 1).all()


def test_a_policy_reading_every_node_gets_its_decision_shares():
    """A network on the ``all`` state has no map over three features: its figure is the
    share of charge among the states it met, every decision recorded (the eager loop)."""
    import torch

    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
    from fleet_torchrl.experiments.policy_maps import decision_shares
    from fleet_torchrl.sim import SiteConfig
    from fleet_torchrl.utils.plotting import MAP_ENCODINGS

    torch.manual_seed(0)
    pol = DQNPolicy(NetworkConfig(width=8, depth=1), 16, "all")
    assert pol.encoding not in MAP_ENCODINGS
    shares = decision_shares(pol, SiteConfig(), 8, 400, 0)
    seen = shares["tc"][~shares["tc"].isnan()]
    assert seen.numel() > 3 and bool(((seen >= 0) & (seen <= 1)).all())
