"""Deep Q-learning on TorchRL (SPEC §3): the ``make_*`` factories and the learner.

Pieces, each from TorchRL: an ``MLP`` Q-network wrapped in a ``QValueActor`` (categorical
actions), ``EGreedyModule`` exploration, a ``TensorDictReplayBuffer`` on ``LazyTensorStorage``
(optionally a ``PrioritizedSampler``), ``DQNLoss`` (MSE, optional double DQN) with a TD(0)
value estimator that bootstraps on ``terminated`` only, ``HardUpdate`` of the target network
every ``network.target_update`` gradient steps, and Adam with ``weight_decay`` as the L2 term.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torch import Tensor, nn
from torchrl.data import (
    Categorical,
    LazyTensorStorage,
    PrioritizedSampler,
    TensorDictReplayBuffer,
    TensorSpec,
)
from torchrl.modules import MLP, EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, HardUpdate

from ..config import DQNAgentConfig, NetworkConfig
from ..policies import Policy


def make_qnet(net: NetworkConfig, n_obs: int) -> nn.Module:
    """MLP ``n_obs -> [width] * depth (ReLU) -> 2`` with an identity output."""
    return MLP(in_features=n_obs, out_features=2, num_cells=[net.width] * net.depth,
               activation_class=nn.ReLU)


class DQNPolicy(Policy):
    """Greedy policy of a Q-network (ties -> pass), usable by the evaluation protocol."""

    name = "dqn"

    def __init__(self, qnet: nn.Module, encoding: str) -> None:
        super().__init__()
        self.qnet = qnet
        self.encoding = encoding

    def forward(self, obs: Tensor) -> Tensor:
        return self.qnet(obs).argmax(-1)


def make_actor(qnet: nn.Module) -> QValueActor:
    """Q-value actor over categorical actions (per-sample spec: two actions)."""
    return QValueActor(qnet, in_keys=["observation"], spec=Categorical(2))


def make_replay_buffer(net: NetworkConfig, prioritized: bool,
                       device: torch.device | str) -> TensorDictReplayBuffer:
    sampler = PrioritizedSampler(net.buffer_size, alpha=0.6, beta=0.4) if prioritized else None
    kw = {"sampler": sampler, "priority_key": "td_error"} if prioritized else {}
    return TensorDictReplayBuffer(storage=LazyTensorStorage(net.buffer_size, device=device),
                                  batch_size=net.batch_size, **kw)


class DQNLearner(nn.Module):
    """Everything DQN learns with; ``state_dict`` covers networks, target and epsilon."""

    def __init__(self, agent: DQNAgentConfig, net: NetworkConfig, n_obs: int, encoding: str,
                 action_spec: TensorSpec, gamma: float, device: torch.device | str) -> None:
        super().__init__()
        self.qnet = make_qnet(net, n_obs).to(device)
        self.actor = make_actor(self.qnet)
        self.egreedy = EGreedyModule(action_spec.clone(), eps_init=agent.eps_start,
                                     eps_end=agent.eps_end,
                                     annealing_num_steps=agent.eps_decay_frames)
        self.explore = TensorDictSequential(self.actor, self.egreedy)
        self.loss = DQNLoss(self.actor, loss_function="l2", delay_value=True,
                            double_dqn=agent.double_dqn, action_space="categorical")
        self.loss.make_value_estimator(gamma=gamma)
        self.target_updater = HardUpdate(self.loss, value_network_update_interval=net.target_update)
        self.optimizer = torch.optim.Adam(self.loss.value_network_params.values(True, True),
                                          lr=net.lr, weight_decay=net.weight_decay)
        self.buffer = make_replay_buffer(net, agent.prioritized, device)
        self.grad_clip = net.grad_clip
        self.prioritized = agent.prioritized
        self.encoding = encoding

    @property
    def epsilon(self) -> float:
        return float(self.egreedy.eps)

    def policy(self) -> DQNPolicy:
        return DQNPolicy(self.qnet, self.encoding)

    def observe(self, batch: TensorDictBase) -> None:
        """Store a collected batch and advance the epsilon schedule by its frames.

        Transitions truncated by the tick budget are not stored: their next observation is
        not a decision state (see :mod:`fleet_torchrl.training`).
        """
        flat = batch.reshape(-1)
        self.egreedy.step(flat.numel())
        flat = flat[~flat["next", "truncated"].reshape(-1)]
        self.buffer.extend(flat.select("observation", "action", ("next", "observation"),
                                       ("next", "reward"), ("next", "done"),
                                       ("next", "terminated"), ("next", "truncated")))

    def update(self, steps: int) -> float:
        """``steps`` gradient steps; returns the mean loss (nan if the buffer is too small)."""
        if len(self.buffer) < self.buffer._batch_size or steps == 0:
            return float("nan")
        total = 0.0
        for _ in range(steps):
            sample = self.buffer.sample()
            loss = self.loss(sample)["loss"]
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if self.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(self.loss.value_network_params.values(True, True),
                                               self.grad_clip)
            self.optimizer.step()
            self.target_updater.step()
            if self.prioritized:
                self.buffer.update_tensordict_priority(sample)
            total += float(loss.detach())
        return total / steps

    def state_dict(self, *args, **kwargs):  # networks + target + eps + optimizer
        sd = super().state_dict(*args, **kwargs)
        sd["_optimizer"] = self.optimizer.state_dict()
        sd["_target_counter"] = self.target_updater.counter
        return sd

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        state_dict = dict(state_dict)
        opt = state_dict.pop("_optimizer", None)
        counter = state_dict.pop("_target_counter", None)
        out = super().load_state_dict(state_dict, strict=strict, assign=assign)
        if opt is not None:
            self.optimizer.load_state_dict(opt)
        if counter is not None:
            self.target_updater.counter = counter
        return out
