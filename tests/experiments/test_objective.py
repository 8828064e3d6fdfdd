"""The objective check: MDP reward per decision next to trips."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fleet_torchrl.agents import HeuristicPolicy, RulePolicy
from fleet_torchrl.sim import SiteConfig


def test_mdp_score_ranks_by_reward_and_counts_like_the_protocol(tmp_path):
    """The thesis reward prefers the heuristic (less queueing) to the rule; the throughput
    reward per tick is the trip rate minus rho, so it ranks by trips."""
    from fleet_torchrl.env import MDPConfig
    from fleet_torchrl.experiments.objective import mdp_score, score_table

    site, mdp = SiteConfig(), MDPConfig(tau_e=600)
    rule = mdp_score(RulePolicy(), site, mdp, n_sites=32, seed=1)
    heur = mdp_score(HeuristicPolicy(), site, mdp, n_sites=32, seed=1)
    assert rule == mdp_score(RulePolicy(), site, mdp, n_sites=32, seed=1)  # deterministic
    assert rule["failure_rate"] == 0 and rule["queue"] > heur["queue"]
    assert rule["reward_per_decision"] < heur["reward_per_decision"] <= 0
    assert abs(rule["decisions"] - rule["trips"]) <= 2  # one decision per trip
    assert rule["reward_per_tick"] == pytest.approx(-rule["queue"] * 32 / (600 * 32), rel=1e-6)
    thr = MDPConfig(tau_e=600, reward="throughput", rho=0.1)
    t_rule = mdp_score(RulePolicy(), site, thr, n_sites=32, seed=1)
    t_heur = mdp_score(HeuristicPolicy(), site, thr, n_sites=32, seed=1)
    assert t_rule["trips"] == rule["trips"] and t_heur["trips"] == heur["trips"]
    assert t_rule["reward_per_tick"] == pytest.approx(rule["trips"] / 600 - 0.1, rel=1e-6)
    assert (t_heur["reward_per_tick"] > t_rule["reward_per_tick"]) == (heur["trips"]
                                                                       > rule["trips"])
    table = score_table({"rule": rule, "heuristic": heur})
    assert table.index("heuristic") < table.index("| rule")  # sorted by reward


def test_objective_cli(tmp_path):
    """An empty folder of saved policies: the baselines only (a missing folder is refused:
    it would look like a table without trained policies)."""
    out = tmp_path / "objective"
    (tmp_path / "none").mkdir()
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.objective", "mdp.tau_e=300",
                        "objective.n_sites=8", f"objective.out={out}",
                        f"table.policies_dir={tmp_path / 'none'}",
                        f"hydra.run.dir={tmp_path / 'hydra'}"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "| rule |" in r.stdout and "| heuristic_60 |" in r.stdout
    res = json.loads((out / "objective.json").read_text())
    assert set(res["scores"]) == {"rule", "heuristic_50", "heuristic_55", "heuristic_60",
                                  "heuristic_65", "heuristic_70", "heuristic_75", "heuristic_80",
                                  "heuristic_65_75"}
    assert res["meta"]["config"]["mdp"]["tau_e"] == 300
    assert (out / "objective.md").read_text().startswith("| policy |")
