"""DQN on TorchRL: n-step folding by hand, the loss falls, gradient clipping bounds the step."""

from __future__ import annotations

import math

import pytest
import torch

from fleet_torchrl.config import compose_config


def test_dqn_loss_falls_on_a_fixed_buffer():
    from fleet_torchrl.agents.dqn import DQNLearner
    from fleet_torchrl.env import FleetChargingEnv

    torch.manual_seed(0)
    cfg = compose_config(["agent=dqn", "network.target_update=100000"])
    env = FleetChargingEnv(num_sites=8, seed=0)
    lrn = DQNLearner(cfg.agent, cfg.network, 3, "partial", env.action_spec, cfg.mdp, "cpu")
    batch = env.rollout(60, lrn.explore, break_when_any_done=False)
    lrn.store(batch)
    first, norm, q = lrn.train_steps(20)
    for _ in range(10):
        last = lrn.train_steps(40)[0]
    assert math.isfinite(first) and last < 0.5 * first
    assert norm > 0 and math.isfinite(q)
    lrn.observe(batch[:, 0], torch.ones(8, dtype=torch.bool))
    assert lrn.exploration() == 1.0  # observing learns; acting explores
    lrn.act(batch[:, 0].select("observation").clone())
    assert lrn.exploration() == pytest.approx(1.0 - 8 * 0.95 / cfg.agent.eps_decay_frames)


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
        lrn = DQNLearner(cfg.agent, cfg.network, 3, "partial", env.action_spec, cfg.mdp, "cpu")
        params = lrn.loss.value_network_params
        lrn.optimizer = torch.optim.SGD(params.values(True, True), lr=1.0)
        if batch is None:
            batch = env.rollout(60, lrn.explore, break_when_any_done=False)
        lrn.store(batch)
        lrn.buffer.sample = lambda b=lrn.buffer[:64]: b  # same sample for both runs
        before = params.clone().detach()
        lrn.train_steps(1)
        delta = (params.detach() - before).flatten_keys()
        steps[clip] = float(torch.cat([v.flatten() for v in delta.values()]).norm())
    assert steps[0.0] > 1e-3  # unclipped gradients are larger than the cap here
    assert steps[1e-3] == pytest.approx(1e-3, rel=1e-3)


def test_n_step_folds_rewards_with_each_transitions_discount_exponent():
    """Windows of up to n steps: the reward of step i is discounted by gamma ** (exponents of
    the steps before it); a window stops at a done step and at the end of the batch, and a
    truncated step is never the start or part of a transition."""
    from tensordict import TensorDict

    from fleet_torchrl.agents.dqn import n_step

    def col(*v, dtype=torch.float32):
        return torch.tensor([v], dtype=dtype).unsqueeze(-1)

    batch = TensorDict({
        "observation": torch.arange(5.0).view(1, 5, 1), "action": torch.zeros(1, 5, 1),
        "next": {"observation": torch.arange(1.0, 6.0).view(1, 5, 1),
                 "reward": col(1.0, 2.0, 3.0, 4.0, 5.0),
                 "terminated": col(False, True, False, False, False, dtype=torch.bool),
                 "truncated": col(False, False, False, False, True, dtype=torch.bool),
                 "done": col(False, True, False, False, True, dtype=torch.bool)}},
        batch_size=[1, 5])
    expo = col(3.0, 2.0, 1.0, 4.0, 1.0)  # e.g. the ticks of each step
    g = 0.5
    out = n_step(batch, 2, g, expo)
    assert out.shape == (4,)  # the truncated step 4 starts no transition
    assert out["next", "reward"].squeeze(-1).tolist() == pytest.approx(
        [1 + g ** 3 * 2, 2, 3 + g * 4, 4])  # step 1 ends its episode; step 4 is truncated
    assert out["steps_to_next_obs"].squeeze(-1).tolist() == [5.0, 2.0, 5.0, 4.0]
    assert out["next", "observation"].squeeze(-1).tolist() == [2.0, 2.0, 4.0, 4.0]
    assert out["next", "terminated"].squeeze(-1).tolist() == [True, True, False, False]
    one = n_step(batch, 1, g, expo)  # n = 1: the plain transitions, exponent of each step
    assert one["next", "reward"].squeeze(-1).tolist() == [1.0, 2.0, 3.0, 4.0]
    assert one["steps_to_next_obs"].squeeze(-1).tolist() == [3.0, 2.0, 1.0, 4.0]


def test_anchored_policy_overrides_the_heuristic_only_by_a_clear_margin(tmp_path):
    """``agent.anchor=heuristic``: the heuristic's action unless Q prefers the other by more
    than the margin; margin 0 is the plain greedy policy (up to ties), a huge one the
    heuristic; the anchor survives saving and loading."""
    from fleet_torchrl.agents import HeuristicPolicy, load_policy_file
    from fleet_torchrl.agents.dqn import DQNPolicy, NetworkConfig
    from fleet_torchrl.agents.policy_files import save_policy

    torch.manual_seed(0)
    obs = torch.rand(4000, 3) * torch.tensor([0.7, 0.7, 1.0]) + torch.tensor([0.3, 0.3, 0.0])
    plain = DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial")
    heur = HeuristicPolicy()(obs)
    acts = {}
    for m in (0.0, 0.05, 1e9):
        pol = DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial", "heuristic", m)
        pol.load_state_dict(plain.state_dict())
        acts[m] = pol(obs)
        q = plain.qnet(obs)
        adv = q[:, 1] - q[:, 0]
        clear = adv.abs() > m
        assert torch.equal(acts[m][clear], (adv[clear] > 0).long())
        assert torch.equal(acts[m][~clear], heur[~clear])
    assert torch.equal(acts[0.0], plain(obs))  # no exact ties in random weights
    assert torch.equal(acts[1e9], heur)
    assert not torch.equal(acts[0.05], heur) and not torch.equal(acts[0.05], acts[0.0])
    pol = DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial", "heuristic", 0.05)
    pol.load_state_dict(plain.state_dict())
    save_policy(tmp_path / "policy.pt", pol, "dqn")
    back = load_policy_file(tmp_path)
    assert back.anchor == "heuristic" and back.anchor_margin == 0.05
    assert torch.equal(back(obs), acts[0.05])
    # the heuristic's parameters travel with the policy, not with the code's defaults
    other = DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial", "heuristic", 1e9,
                      {"threshold": 35.0, "upper": 70.0, "others_below": 100.0})
    save_policy(tmp_path / "other" / "policy.pt", other, "dqn")
    again = load_policy_file(tmp_path / "other")
    assert again.base.threshold == 35.0 and again.base.upper == 70.0
    assert torch.equal(again(obs), HeuristicPolicy(35.0, 70.0)(obs))
    with pytest.raises(ValueError, match="anchor"):
        DQNPolicy(NetworkConfig(width=8, depth=1), 3, "partial", "nope")


def test_anchor_needs_a_state_the_heuristic_reads():
    from fleet_torchrl.utils.checks import ConfigError

    with pytest.raises(ConfigError, match="agent.anchor"):
        compose_config(["agent=dqn", "state=all", "agent.anchor=heuristic"])
    with pytest.raises(ConfigError, match="agent.anchor"):
        compose_config(["agent=dqn", "agent.anchor=nope"])
    cfg = compose_config(["agent=dqn", "state=partial_site", "agent.anchor=heuristic"])
    assert cfg.network.name == "partial_site"
