"""DQN on TorchRL: the loss falls, gradient clipping bounds the step."""

from __future__ import annotations

import math

import pytest
import torch

from fleet_torchrl.config import compose_config

# ---------------------------------------------------------------------- training


# ---------------------------------------------------------------------- DQN
def test_dqn_loss_falls_on_a_fixed_buffer():
    from fleet_torchrl.agents.dqn import DQNLearner
    from fleet_torchrl.env import FleetChargingEnv

    torch.manual_seed(0)
    cfg = compose_config(["agent=dqn", "network.target_update=100000"])
    env = FleetChargingEnv(num_sites=8, seed=0)
    lrn = DQNLearner(cfg.agent, cfg.network, 3, "partial", env.action_spec, 0.9, "cpu")
    batch = env.rollout(60, lrn.explore, break_when_any_done=False)
    lrn.observe(batch, ~batch["next", "truncated"].squeeze(-1))
    first = lrn.train_steps(20)
    for _ in range(10):
        last = lrn.train_steps(40)
    assert math.isfinite(first) and last < 0.5 * first
    assert lrn.exploration() < 1.0  # epsilon annealed by the observed frames


def test_dqn_grad_clip_bounds_the_step():
    """``network.grad_clip`` caps the gradient norm the optimiser sees (SGD: step = lr * g)."""
    from fleet_torchrl.agents.dqn import DQNLearner
    from fleet_torchrl.env import FleetChargingEnv

    env = FleetChargingEnv(num_sites=8, seed=0)
    batch = None
    steps = {}
    for clip in (0.0, 1e-3):
        torch.manual_seed(0)
        cfg = compose_config(["agent=dqn", f"network.grad_clip={clip}", "network.weight_decay=0"])
        lrn = DQNLearner(cfg.agent, cfg.network, 3, "partial", env.action_spec, 0.9, "cpu")
        params = lrn.loss.value_network_params
        lrn.optimizer = torch.optim.SGD(params.values(True, True), lr=1.0)
        if batch is None:
            batch = env.rollout(60, lrn.explore, break_when_any_done=False)
        lrn.observe(batch, ~batch["next", "truncated"].squeeze(-1))
        lrn.buffer.sample = lambda b=lrn.buffer[:64]: b  # same sample for both runs
        before = params.clone().detach()
        lrn.train_steps(1)
        delta = (params.detach() - before).flatten_keys()
        steps[clip] = float(torch.cat([v.flatten() for v in delta.values()]).norm())
    assert steps[0.0] > 1e-3  # unclipped gradients are larger than the cap here
    assert steps[1e-3] == pytest.approx(1e-3, rel=1e-3)
