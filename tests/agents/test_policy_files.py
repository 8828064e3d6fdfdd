"""Saved-policy files: round trip and bad input."""

from __future__ import annotations

import dataclasses
import io

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
    # a text file passed by mistake: one short line, not torch's page on weights_only
    (tmp_path / "notes.md").write_text("# notes\n\nsome text\n")
    with pytest.raises(ValueError, match="notes.md is not a readable policy file") as err:
        load_policy_file(tmp_path / "notes.md")
    assert "\n" not in str(err.value) and len(str(err.value)) < 300
    assert "weights_only" not in str(err.value)
    # a file cut short (a copy interrupted): said so
    whole = (tmp_path / "p" / "policy.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(ValueError, match="cut.pt is not a readable policy file .truncated"):
        load_policy_file(tmp_path / "cut.pt")
    torch.save({"hello": 1}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a fleet_torchrl policy file"):
        load_policy_file(tmp_path / "foreign.pt")


def test_policy_files_written_before_the_spec_rename_still_load(tmp_path, caplog):
    """``Policy.spec()`` became ``policy_spec()`` (it shadowed TorchRL's ``spec`` attribute);
    the file keeps its ``spec`` key, so a file written before the rename, built here by hand
    as the old code wrote it, loads (with a one-line warning: it records no hash of its
    weights), and new files keep that layout plus the hashes."""
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
    from fleet_torchrl.agents.policy_files import FORMAT, policy_bytes

    net = NetworkConfig(width=8, depth=1)
    pol = DQNPolicy(net, 3, "partial", anchor="heuristic", anchor_margin=2.0)
    old = {"format": FORMAT, "kind": "dqn", "encoding": "partial",
           "spec": {"network": dataclasses.asdict(net), "n_obs": 3, "encoding": "partial",
                    "anchor": "heuristic", "anchor_margin": 2.0,
                    "anchor_params": {"threshold": pol.base.threshold, "upper": pol.base.upper,
                                      "others_below": pol.base.others_below}},
           "state_dict": {k: v.detach() for k, v in pol.state_dict().items()}, "meta": {}}
    torch.save(old, tmp_path / "old.pt")
    with caplog.at_level("WARNING"):
        back = load_policy_file(tmp_path / "old.pt")
    warned = [r.getMessage() for r in caplog.records if "records no hash" in r.getMessage()]
    assert len(warned) == 1 and "\n" not in warned[0] and "old.pt" in warned[0]
    assert isinstance(back, DQNPolicy) and back.anchor == "heuristic"
    assert back.anchor_margin == 2.0 and back.network == net
    obs = torch.rand(200, 3)
    assert torch.equal(back(obs), pol(obs))
    new = torch.load(io.BytesIO(policy_bytes(pol, "dqn")), weights_only=True)
    assert new.keys() == old.keys() | {"tensors_sha256", "content_sha256"}
    assert new["spec"] == old["spec"]
