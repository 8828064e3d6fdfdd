"""Policy maps from saved policies."""

from __future__ import annotations

from fleet_torchrl.config import compose_config


def test_policy_maps_from_saved_policies(tmp_path, saved_policies):
    from fleet_torchrl.experiments.policy_maps import run

    root = saved_policies
    cfg = compose_config([f"table.policies_dir={root}", f"maps.out={tmp_path / 'maps'}"])
    paths = run(cfg)
    assert sorted(p.name for p in paths) == ["dqn_partial.png", "generalist.png",
                                             "heuristic.png", "rule.png", "search.png",
                                             "tabular.png"]
    from fleet_torchrl.agents import RulePolicy
    from fleet_torchrl.utils.plotting import TC_TABULAR, policy_map

    m = policy_map(RulePolicy(), TC_TABULAR, n=101)
    assert m.shape == (2, 101, 101)
    assert m[0, 40, :].eq(1).all() and m[0, 41, :].eq(0).all()  # charge iff soc_D <= 40
