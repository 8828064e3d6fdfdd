"""The objective check: MDP reward per decision next to trips."""

from __future__ import annotations

import json
import subprocess
import sys

import torch

from fleet_torchrl.agents import HeuristicPolicy, Policy, RulePolicy
from fleet_torchrl.sim import SiteConfig


class Always(Policy):
    def __init__(self, action):
        super().__init__()
        self.action = action
        self.name = f"always{action}"

    def forward(self, obs):
        return torch.full(obs.shape[:-1], self.action, dtype=torch.int64)


def test_mdp_score_ranks_by_reward_and_counts_like_the_protocol(tmp_path):
    """The thesis reward prefers the heuristic (less queueing) to the rule; the trip reward
    raises every score by about ``r_trip`` per mean step length."""
    from fleet_torchrl.config import MDPConfig
    from fleet_torchrl.experiments.objective import mdp_score, score_table

    site, mdp = SiteConfig(), MDPConfig(tau_e=600)
    rule = mdp_score(RulePolicy(), site, mdp, n_sites=32, seed=1)
    heur = mdp_score(HeuristicPolicy(), site, mdp, n_sites=32, seed=1)
    assert rule == mdp_score(RulePolicy(), site, mdp, n_sites=32, seed=1)  # deterministic
    assert rule["failure_rate"] == 0 and rule["queue"] > heur["queue"]
    assert rule["reward_per_decision"] < heur["reward_per_decision"] <= 0
    assert abs(rule["decisions"] - rule["trips"]) <= 2  # one decision per trip
    bonus = mdp_score(RulePolicy(), site, MDPConfig(tau_e=600, r_trip=1.0), n_sites=32, seed=1)
    assert bonus["trips"] == rule["trips"]
    assert 0 < bonus["reward_per_decision"] - rule["reward_per_decision"] < 1
    table = score_table({"rule": rule, "heuristic": heur})
    assert table.index("heuristic") < table.index("| rule")  # sorted by reward


def test_objective_cli(tmp_path):
    out = tmp_path / "objective"
    r = subprocess.run([sys.executable, "-m", "fleet_torchrl.objective", "mdp.tau_e=300",
                        "objective.n_sites=8", f"objective.out={out}",
                        f"table.policies_dir={tmp_path / 'none'}",
                        f"hydra.run.dir={tmp_path / 'hydra'}"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "| rule |" in r.stdout and "| heuristic_60 |" in r.stdout
    res = json.loads((out / "objective.json").read_text())
    assert set(res["scores"]) == {"rule", "heuristic_50", "heuristic_60", "heuristic_65",
                                  "heuristic_70", "heuristic_80", "heuristic_65_75"}
    assert res["meta"]["config"]["mdp"]["tau_e"] == 300
    assert (out / "objective.md").read_text().startswith("| policy |")
