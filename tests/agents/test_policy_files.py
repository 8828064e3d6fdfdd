"""Saved-policy files: round trip and bad input."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.agents import load_policy_file, save_policy
from fleet_torchrl.agents.tabular import TabularLearner
from fleet_torchrl.config import compose_config

# ---------------------------------------------------------------------- training


def test_policy_files_round_trip_and_reject_bad_input(tmp_path):
    from fleet_torchrl.agents.dqn import DQNPolicy

    cfg = compose_config(["agent=dqn"])
    pol = DQNPolicy(cfg.network, 3, "partial")
    save_policy(tmp_path / "p" / "policy.pt", pol, "dqn")
    back = load_policy_file(tmp_path / "p")
    obs = torch.rand(50, 3)
    assert torch.equal(back(obs), pol(obs)) and back.encoding == "partial"
    tab = TabularLearner().table
    tab.q.uniform_(-1, 1)
    save_policy(tmp_path / "t.pt", tab, "tabular")
    assert torch.equal(load_policy_file(tmp_path / "t.pt").q, tab.q)
    with pytest.raises(FileNotFoundError, match="no saved policy"):
        load_policy_file(tmp_path / "nothing")
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="not a readable policy file"):
        load_policy_file(tmp_path / "bad.pt")
    torch.save({"hello": 1}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a fleet_torchrl policy file"):
        load_policy_file(tmp_path / "foreign.pt")
