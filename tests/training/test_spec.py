"""The run spec: built once from a validated config, frozen, its groups the config's values
(copies), taken by the trainer."""

from __future__ import annotations

import dataclasses

import pytest

from fleet_torchrl.config import compose_config
from fleet_torchrl.training import RunSpec
from fleet_torchrl.training.spec import SPEC_GROUPS

TINY = ["agent=tabular", "agent.num_sites=8", "train.max_episodes=16", "train.eval_every=1",
        "train.eval_sims=8", "train.eval_ticks=200", "mdp.tau_e=300", "train.progress=false",
        "train.tensorboard=false", "seed=3"]


def test_a_spec_holds_the_configs_run_settings_as_copies():
    cfg = compose_config(["agent=dqn", "state=all", "site.p_c=0.6", "network.width=32",
                          "train.eval_sims=7", "seed=5"])
    spec = RunSpec.of(cfg)
    assert [f.name for f in dataclasses.fields(RunSpec)] == [*SPEC_GROUPS, "seed"]
    for group in SPEC_GROUPS:  # equal values, not the same objects
        assert getattr(spec, group) == getattr(cfg, group)
        assert getattr(spec, group) is not getattr(cfg, group)
    assert (spec.site.p_c, spec.state.name, spec.network.width, spec.train.eval_sims,
            spec.seed) == (0.6, "all", 32, 7, 5)
    assert RunSpec.of(spec) == spec  # a spec round-trips
    cfg.site.p_c = 0.9  # the config changed later: the spec is not
    assert spec.site.p_c == 0.6


def test_a_spec_is_frozen():
    spec = RunSpec.of(compose_config(["agent=tabular"]))
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.seed = 1  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.site = spec.site  # type: ignore[misc]
    assert dataclasses.replace(spec, seed=1).seed == 1 and spec.seed == 0


def test_the_trainer_takes_a_spec_and_a_publish_folder(tmp_path):
    """A training runs from a spec alone (plus its folders); what it computes and records
    is the spec's: the same spec trains the same policy again, bit for bit."""
    import torch

    from fleet_torchrl.agents import load_policy_file
    from fleet_torchrl.training import Trainer, training_fingerprint

    cfg = compose_config(TINY)
    spec = RunSpec.of(cfg)
    with pytest.raises(TypeError, match="takes a RunSpec"):
        Trainer(cfg, tmp_path / "bad")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs a publish folder"):
        Trainer(spec, tmp_path / "bad")
    summary = Trainer(spec, tmp_path / "run", tmp_path / "pub").run()
    assert summary["fingerprint"] == training_fingerprint(spec)
    assert summary["meta"]["config"]["seed"] == 3 and "sweep" not in summary["meta"]["config"]
    # a tiny run fails sites: published only to a folder the spec names (train.out_dir)
    assert not summary["published"] and not (tmp_path / "pub").exists()
    named = dataclasses.replace(spec, train=dataclasses.replace(
        spec.train, out_dir=str(tmp_path / "pub2")))
    again = Trainer(named, tmp_path / "run2").run()
    assert again["published"] and again["policy"] == str(tmp_path / "pub2" / "policy.pt")
    assert [h["trips"] for h in again["history"]] == [h["trips"] for h in summary["history"]]
    assert torch.equal(load_policy_file(summary["policy"]).q,
                       load_policy_file(again["policy"]).q)
