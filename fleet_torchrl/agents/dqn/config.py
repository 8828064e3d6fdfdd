"""The schemas of deep Q-learning (``agent=dqn``) and its Q-network (the ``network`` group)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

from ...utils.checks import ConfigError, check_choice, check_range, validate_on_init
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
    num_sites: int = 256  # sites simulated in parallel (one environment step = 256 decisions)
    steps_per_round: int = 40  # decisions per site and round
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_decay_frames: int = 400_000  # frames (decisions, all sites) to anneal epsilon
    double_dqn: bool = True
    prioritized: bool = False  # prioritized replay (alpha 0.6, beta 0.4)
    updates_per_round: int = 200  # gradient steps after each collected round
    n_steps: int = 3  # n-step returns: decisions folded into one stored transition
    reset_each_round: bool = False  # false: episodes run on across rounds
    reward_scale: float = 10.0  # rewards are multiplied by this in the replay buffer
    policy: str | None = None  # saved policy for evaluation (default results/policies/dqn_<state>)
    anchor: str = "none"  # none | heuristic: act as the heuristic unless Q disagrees clearly
    anchor_margin: float = 0.0  # Q advantage (scaled reward units) needed to override it

    def validate(self, cfg: Any = None, path: str = "agent") -> DQNAgentConfig:
        check_range(f"{path}.num_sites", self.num_sites, 1, 1_000_000)
        check_range(f"{path}.eps_start", self.eps_start, 0.0, 1.0)
        check_range(f"{path}.eps_end", self.eps_end, 0.0, self.eps_start,
                    allowed=f"[0, eps_start = {self.eps_start}]")
        check_range(f"{path}.eps_decay_frames", self.eps_decay_frames, 1, 10**12)
        check_range(f"{path}.steps_per_round", self.steps_per_round, 1, 1_000_000)
        check_range(f"{path}.updates_per_round", self.updates_per_round, 0, 1_000_000)
        check_range(f"{path}.n_steps", self.n_steps, 1, 1000)
        check_range(f"{path}.reward_scale", self.reward_scale, 1e-6, 1e6, allowed="[1e-06, 1e6]")
        check_choice(f"{path}.anchor", self.anchor, ANCHORS)
        check_range(f"{path}.anchor_margin", self.anchor_margin, 0.0, None)
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
    depth: int = 3  # hidden layers
    width: int = 32  # units per hidden layer
    lr: float = 1e-3  # Adam learning rate
    weight_decay: float = 1e-4  # Adam L2 regularisation
    batch_size: int = 256
    buffer_size: int = 50_000
    target_update: int = 500  # gradient steps between hard target-network copies
    grad_clip: float = 0.0  # max gradient norm per step; 0 = no clipping
    tau: float = 0.0  # > 0: soft target update by tau per step instead of hard copies
    lr_decay: str = "cosine"  # none | cosine | linear, over all gradient steps of the run
    lr_final: float = 0.05  # final learning rate as a fraction of lr (lr_decay != none)

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "network") -> NetworkConfig:
        check_range(f"{path}.depth", self.depth, 0, 64)
        check_range(f"{path}.width", self.width, 1, 65_536)
        check_range(f"{path}.lr", self.lr, 1e-12, 1.0, allowed="(0, 1]")
        check_range(f"{path}.weight_decay", self.weight_decay, 0.0, 10.0)
        check_range(f"{path}.batch_size", self.batch_size, 1, self.buffer_size,
                    allowed=f"[1, buffer_size = {self.buffer_size}]")
        check_range(f"{path}.buffer_size", self.buffer_size, 1, 100_000_000)
        check_range(f"{path}.target_update", self.target_update, 1, 10**9)
        check_range(f"{path}.grad_clip", self.grad_clip, 0.0, None)
        check_range(f"{path}.tau", self.tau, 0.0, 1.0)
        check_choice(f"{path}.lr_decay", self.lr_decay, LR_DECAYS)
        check_range(f"{path}.lr_final", self.lr_final, 0.0, 1.0)
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
