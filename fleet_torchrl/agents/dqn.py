"""Deep Q-learning on TorchRL (MODEL §3): the ``make_*`` factories and the learner.

Pieces, each from TorchRL: an ``MLP`` Q-network wrapped in a ``QValueActor`` (categorical
actions), ``EGreedyModule`` exploration, a ``TensorDictReplayBuffer`` on ``LazyTensorStorage``
(optionally a ``PrioritizedSampler``), ``DQNLoss`` (MSE, optional double DQN) with a TD(0)
value estimator that bootstraps on ``terminated`` only, ``HardUpdate`` of the target network
every ``network.target_update`` gradient steps, and Adam with ``weight_decay`` as the L2 term.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

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

from ..utils.checks import check_range
from .base import AgentConfig, Learner, Policy


@dataclass
class DQNAgentConfig(AgentConfig):
    """Deep Q-learning on TorchRL (MODEL §3); the network is the ``network`` group."""

    name: str = "dqn"
    num_sites: int = 8  # sites simulated in parallel; a round resets them all
    steps_per_round: int = 450  # decisions per site and round (one tau_e episode is ~350)
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_decay_frames: int = 250_000  # frames (decisions, all sites) to anneal epsilon
    double_dqn: bool = False
    prioritized: bool = False  # prioritized replay (alpha 0.6, beta 0.4)
    updates_per_round: int = 400  # gradient steps after each collected round
    policy: str | None = None  # saved policy for evaluation (default results/policies/dqn_<state>)

    def validate(self, cfg: Any = None, path: str = "agent") -> DQNAgentConfig:
        check_range(f"{path}.num_sites", self.num_sites, 1, 1_000_000)
        check_range(f"{path}.eps_start", self.eps_start, 0.0, 1.0)
        check_range(f"{path}.eps_end", self.eps_end, 0.0, self.eps_start,
                    allowed=f"[0, eps_start = {self.eps_start}]")
        check_range(f"{path}.eps_decay_frames", self.eps_decay_frames, 1, None)
        check_range(f"{path}.steps_per_round", self.steps_per_round, 1, None)
        check_range(f"{path}.updates_per_round", self.updates_per_round, 0, None)
        return self


@dataclass
class NetworkConfig:
    """Q-network and its optimisation (MODEL §3 table; grid-searched by ``make grid``)."""

    name: str = "partial"
    depth: int = 3  # hidden layers
    width: int = 32  # units per hidden layer
    lr: float = 1e-3  # Adam learning rate
    weight_decay: float = 0.01  # Adam L2 regularisation
    batch_size: int = 64
    buffer_size: int = 50_000
    target_update: int = 500  # gradient steps between hard target-network copies
    grad_clip: float = 0.0  # max gradient norm per step; 0 = no clipping

    def validate(self, path: str = "network") -> NetworkConfig:
        check_range(f"{path}.depth", self.depth, 0, 64)
        check_range(f"{path}.width", self.width, 1, 65_536)
        check_range(f"{path}.lr", self.lr, 1e-12, 1.0, allowed="(0, 1]")
        check_range(f"{path}.weight_decay", self.weight_decay, 0.0, 10.0)
        check_range(f"{path}.batch_size", self.batch_size, 1, self.buffer_size,
                    allowed=f"[1, buffer_size = {self.buffer_size}]")
        check_range(f"{path}.buffer_size", self.buffer_size, 1, 100_000_000)
        check_range(f"{path}.target_update", self.target_update, 1, None)
        check_range(f"{path}.grad_clip", self.grad_clip, 0.0, None)
        return self


def make_qnet(net: NetworkConfig, n_obs: int) -> nn.Module:
    """MLP ``n_obs -> [width] * depth (ReLU) -> 2`` with an identity output."""
    return MLP(in_features=n_obs, out_features=2, num_cells=[net.width] * net.depth,
               activation_class=nn.ReLU)


class DQNPolicy(Policy):
    """Greedy policy of a Q-network (ties -> pass), usable by the evaluation protocol."""

    name = "dqn"
    map_tc_values = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)

    def __init__(self, network: NetworkConfig, n_obs: int, encoding: str) -> None:
        super().__init__()
        self.network, self.n_obs = network, n_obs
        self.qnet = make_qnet(network, n_obs)
        self.encoding = encoding
        self.name = f"dqn_{encoding}"

    def spec(self) -> dict[str, Any]:
        return {"network": asdict(self.network), "n_obs": self.n_obs, "encoding": self.encoding}

    @classmethod
    def from_spec(cls, spec: dict[str, Any]) -> DQNPolicy:
        return cls(NetworkConfig(**spec["network"]), spec["n_obs"], spec["encoding"])

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


class DQNLearner(Learner):
    """Everything DQN learns with; ``state_dict`` covers networks, target, epsilon and the
    optimiser (the replay buffer is a separate checkpoint component).

    A round collects ``agent.steps_per_round`` environment steps of all sites (a site whose
    episode ends starts the next one at once) into the replay buffer, then makes
    ``agent.updates_per_round`` gradient steps.
    """

    def __init__(self, agent: DQNAgentConfig, net: NetworkConfig, n_obs: int, encoding: str,
                 action_spec: TensorSpec, gamma: float, device: torch.device | str) -> None:
        super().__init__()
        self.greedy = DQNPolicy(net, n_obs, encoding).to(device)
        self.qnet = self.greedy.qnet
        self.steps_per_round = agent.steps_per_round
        self.updates_per_round = agent.updates_per_round
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

    # ------------------------------------------------------------------ Learner
    def exploration(self) -> float:
        return float(self.egreedy.eps)

    def policy(self) -> DQNPolicy:
        return self.greedy

    def act(self, td: TensorDictBase) -> TensorDictBase:
        return self.explore(td)

    def checkpoint_components(self) -> dict[str, Any]:
        return {"replay_buffer": self.buffer}

    def observe(self, td: TensorDictBase, learn: torch.Tensor) -> None:
        """Store the transitions of the sites in ``learn`` and advance epsilon by the step's
        frames. The loop leaves out steps truncated by the tick budget: their next
        observation is not a decision state (see :mod:`fleet_torchrl.training`)."""
        self.egreedy.step(td.numel())
        flat = td.reshape(-1)[learn.reshape(-1)]
        self.buffer.extend(flat.select("observation", "action", ("next", "observation"),
                                       ("next", "reward"), ("next", "done"),
                                       ("next", "terminated"), ("next", "truncated")))

    def update(self) -> dict[str, float]:
        """The round's gradient steps; logs the mean loss and the buffer's size."""
        return {"loss/td": self.train_steps(self.updates_per_round),
                "train/buffer_size": len(self.buffer)}

    def train_steps(self, steps: int) -> float:
        """``steps`` gradient steps; returns the mean loss (nan if the buffer is too small)."""
        if len(self.buffer) < self.buffer.batch_size or steps == 0:
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
