"""GPU readiness: the protocol and a short training on CUDA (skipped where there is none)."""

from __future__ import annotations

import pytest
import torch

from fleet_torchrl.agents import HeuristicPolicy, RulePolicy
from fleet_torchrl.config import compose_config
from fleet_torchrl.evaluation import simulate
from fleet_torchrl.sim import SiteConfig

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


@pytest.mark.parametrize("policy", [RulePolicy(), HeuristicPolicy()])
def test_protocol_on_cuda_gives_the_cpu_records(policy):
    """Integer hashing and float32 energy are exact on every device: same records."""
    cpu = simulate(policy, SiteConfig(), 256, 3000, seed=0, device="cpu", fused=False)
    gpu = simulate(policy, SiteConfig(), 256, 3000, seed=0, device="cuda")
    for key in cpu:
        assert torch.equal(cpu[key], gpu[key]), key


@pytest.mark.parametrize("agent", [["agent=tabular"], ["agent=dqn", "state=partial"]])
def test_short_training_on_cuda(tmp_path, agent):
    from fleet_torchrl.agents import load_policy_file
    from fleet_torchrl.training import RunSpec, Trainer

    cfg = compose_config([*agent, "train.device=cuda", "agent.num_sites=64",
                          "train.max_episodes=128", "train.eval_every=1", "train.eval_sims=32",
                          "train.eval_ticks=500", "mdp.tau_e=500", "train.progress=false",
                          "train.tensorboard=false", f"train.out_dir={tmp_path / 'pol'}"])
    trainer = Trainer(RunSpec.of(cfg), tmp_path / "run")
    summary = trainer.run()
    assert summary["best"] is not None and summary["frames"] > 0
    assert next(iter(trainer.learner.policy().buffers()), next(
        iter(trainer.learner.policy().parameters()), None)).device.type == "cuda"
    assert load_policy_file(tmp_path / "pol").encoding == "partial"
