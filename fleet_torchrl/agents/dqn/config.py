"""The schemas of deep Q-learning (``agent=dqn``) and its Q-network (the ``network`` group)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

from ...utils.checks import (
    ConfigError,
    check_fields,
    check_range,
    ranged,
    validate_on_init,
)
from ..schema import AgentConfig, Need, transition_bytes

LR_DECAYS = ("none", "cosine", "linear")
ANCHORS = ("none", "heuristic")
ANCHOR_STATES = ("partial", "partial_site")  # encodings whose features 0-2 the heuristic reads


@dataclass
class DQNAgentConfig(AgentConfig):
    """Deep Q-learning on TorchRL (MODEL §3); the network is the ``network`` group."""

    name: str = "dqn"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.dqn.learner:DQNPolicy"
    learner_type: ClassVar[str] = "fleet_torchrl.agents.dqn.learner:DQNLearner"
    # sites simulated in parallel (one environment step = 256 decisions)
    num_sites: int = ranged(256, 1, 1_000_000)
    steps_per_round: int = ranged(40, 1, 1_000_000)  # decisions per site and round
    eps_start: float = ranged(1.0, 0.0, 1.0)
    eps_end: float = 0.05
    # frames (decisions, all sites) to anneal epsilon
    eps_decay_frames: int = ranged(400_000, 1, 10**12)
    double_dqn: bool = True
    prioritized: bool = False  # prioritized replay (alpha 0.6, beta 0.4)
    updates_per_round: int = ranged(200, 0, 1_000_000)  # gradient steps after each collected round
    n_steps: int = ranged(3, 1, 1000)  # n-step returns: decisions folded into one stored transition
    reset_each_round: bool = False  # false: episodes run on across rounds
    # rewards are multiplied by this in the replay buffer
    reward_scale: float = ranged(10.0, 1e-6, 1e6, allowed="[1e-06, 1e6]")
    policy: str | None = None  # saved policy for evaluation (default results/policies/dqn_<state>)
    # none | heuristic: act as the heuristic unless Q disagrees clearly
    anchor: str = ranged("none", choices=ANCHORS)
    # Q advantage (scaled reward units) needed to override it
    anchor_margin: float = ranged(0.0, 0.0, None)

    def validate(self, cfg: Any = None, path: str = "agent") -> DQNAgentConfig:
        super().validate(cfg, path)
        check_range(f"{path}.eps_end", self.eps_end, 0.0, self.eps_start,
                    allowed=f"[0, eps_start = {self.eps_start}]")
        state = getattr(getattr(cfg, "state", None), "name", None)
        if self.anchor != "none" and state is not None and state not in ANCHOR_STATES:
            raise ConfigError(f"{path}.anchor={self.anchor!r} is invalid with state={state!r}: "
                              f"the heuristic reads the states {', '.join(ANCHOR_STATES)}; "
                              "use one of them or agent.anchor=none")
        return self

    def memory(self, network: Any, n_obs: int, site_bytes: int) -> list[Need]:
        out = super().memory(network, n_obs, site_bytes)
        rnd = self.num_sites * self.steps_per_round
        out.append(("agent.steps_per_round", self.steps_per_round,
                    rnd * (site_bytes + 2 * transition_bytes(n_obs)),
                    f"a round's steps of agent.num_sites={self.num_sites} sites"))
        out += network.memory(n_obs, prioritized=self.prioritized)
        return out

    def run_suffix(self, mdp: Any) -> str:
        """The objective's suffix, then ``_anchored`` for a policy anchored to the heuristic:
        it acts unlike a plain DQN of the same recipe and must not replace one."""
        return super().run_suffix(mdp) + ("" if self.anchor == "none" else "_anchored")


@dataclass
class NetworkConfig:
    """Q-network and its optimisation (MODEL §3 table; grid-searched by ``make grid``)."""

    name: str = "partial"
    depth: int = ranged(3, 0, 64)  # hidden layers
    width: int = ranged(32, 1, 65_536)  # units per hidden layer
    lr: float = ranged(1e-3, 1e-12, 1.0, allowed="(0, 1]")  # Adam learning rate
    weight_decay: float = ranged(1e-4, 0.0, 10.0)  # Adam L2 regularisation
    batch_size: int = 256
    buffer_size: int = ranged(50_000, 1, 100_000_000)
    target_update: int = ranged(500, 1, 10**9)  # gradient steps between hard target-network copies
    grad_clip: float = ranged(0.0, 0.0, None)  # max gradient norm per step; 0 = no clipping
    # > 0: soft target update by tau per step instead of hard copies
    tau: float = ranged(0.0, 0.0, 1.0)
    # none | cosine | linear, over all gradient steps of the run
    lr_decay: str = ranged("cosine", choices=LR_DECAYS)
    # final learning rate as a fraction of lr (lr_decay != none)
    lr_final: float = ranged(0.05, 0.0, 1.0)

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "network") -> NetworkConfig:
        check_fields(self, path)
        check_range(f"{path}.batch_size", self.batch_size, 1, self.buffer_size,
                    allowed=f"[1, buffer_size = {self.buffer_size}]")
        return self

    def parameters(self, n_obs: int, n_out: int = 2) -> int:
        """Weights and biases of the Q-network (``depth`` hidden layers of ``width``)."""
        w, d = self.width, self.depth
        if d == 0:
            return (n_obs + 1) * n_out
        return (n_obs + 1) * w + (d - 1) * (w + 1) * w + (w + 1) * n_out

    def memory(self, n_obs: int, prioritized: bool = False) -> list[Need]:
        """What DQN allocates for its network (online and target weights, gradients, Adam's
        two moments, the best snapshot: six float32 copies; a batch's activations forward
        and backward) and for its replay buffer (allocated whole at the first store)."""
        w, d = self.width, self.depth
        weights = 6 * 4 * self.parameters(n_obs) + 4 * 4 * self.batch_size * w * max(d, 1)
        per = transition_bytes(n_obs) + (64 if prioritized else 0)
        return [("network.width", w, weights, f"the Q-network (network.depth={d})"),
                ("network.buffer_size", self.buffer_size, self.buffer_size * per,
                 "the replay buffer")]

    def lr_factor(self, total_updates: int):
        """The learning-rate multiplier after ``k`` of ``total_updates`` gradient steps
        (``None`` without decay)."""
        if self.lr_decay == "none" or total_updates <= 0:
            return None
        floor = self.lr_final
        if self.lr_decay == "cosine":
            return lambda k: floor + (1 - floor) * 0.5 * (1 + math.cos(
                math.pi * min(k / total_updates, 1.0)))
        return lambda k: 1.0 - (1.0 - floor) * min(k / total_updates, 1.0)
