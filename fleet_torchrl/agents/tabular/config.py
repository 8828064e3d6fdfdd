"""The schema of tabular Q-learning (``agent=tabular``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from ...utils.checks import check_range, ranged
from ..schema import AgentConfig


@dataclass
class TabularAgentConfig(AgentConfig):
    """Tabular Q-learning on the discretised ``partial`` state (MODEL §3)."""

    name: str = "tabular"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.tabular.learner:TabularQPolicy"
    learner_type: ClassVar[str] = "fleet_torchrl.agents.tabular.learner:TabularLearner"
    states: ClassVar[tuple[str, ...] | None] = ("partial",)
    # sites simulated in parallel; one round = one episode per site
    num_sites: int = ranged(256, 1, 1_000_000)
    # learning rate k / (t + k), t = visits of the state-action pair
    k: float = ranged(100.0, 1e-9, None, allowed="> 0")
    eps_start: float = ranged(1.0, 0.0, 1.0)  # epsilon of the first episode
    eps_end: float = 0.3  # epsilon_min
    # episodes (per site) over which epsilon decays to eps_end
    eps_decay_episodes: int = ranged(20, 1, 10**9)
    policy: str | None = None  # saved policy for evaluation (default results/policies/tabular)

    def validate(self, cfg: Any = None, path: str = "agent") -> TabularAgentConfig:
        super().validate(cfg, path)
        check_range(f"{path}.eps_end", self.eps_end, 0.0, self.eps_start,
                    allowed=f"[0, eps_start = {self.eps_start}]")
        return self

    def epsilon(self, round_idx: int) -> float:
        """Epsilon of round (= episode per site) ``round_idx``: exponential decay to eps_end."""
        if self.eps_end <= 0.0:
            return self.eps_start if round_idx == 0 else 0.0
        return max(self.eps_end, self.eps_start * (self.eps_end / self.eps_start)
                   ** (round_idx / self.eps_decay_episodes))
