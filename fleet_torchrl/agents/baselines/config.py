"""The schemas of the two hand-written baselines (``agent=rule``, ``agent=heuristic``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from ...utils.checks import check_range
from ..schema import AgentConfig


@dataclass
class RuleAgentConfig(AgentConfig):
    """Benchmark: charge iff soc_D <= threshold."""

    name: str = "rule"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.baselines.policy:RulePolicy"
    threshold: float = 40.0

    def validate(self, cfg: Any = None, path: str = "agent") -> RuleAgentConfig:
        check_range(f"{path}.threshold", self.threshold, 0.0, 100.0)
        return self


@dataclass
class HeuristicAgentConfig(AgentConfig):
    """Queue-aware baseline: charge early when the charger is free and the vehicle at D is the
    emptiest one (and below ``upper``); otherwise follow the rule with ``threshold``."""

    name: str = "heuristic"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.baselines.policy:HeuristicPolicy"
    threshold: float = 40.0
    upper: float = 60.0
    others_below: float = 100.0  # charge early only if another vehicle is this low; 100 = off

    def validate(self, cfg: Any = None, path: str = "agent") -> HeuristicAgentConfig:
        check_range(f"{path}.threshold", self.threshold, 0.0, 100.0)
        check_range(f"{path}.upper", self.upper, 0.0, 100.0)
        check_range(f"{path}.others_below", self.others_below, 0.0, 100.0)
        return self
