"""The schemas of the two hand-written baselines (``agent=rule``, ``agent=heuristic``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...utils.checks import ranged
from ..schema import AgentConfig


@dataclass
class RuleAgentConfig(AgentConfig):
    """Benchmark: charge iff soc_D <= threshold."""

    name: str = "rule"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.baselines.policy:RulePolicy"
    threshold: float = ranged(40.0, 0.0, 100.0)



@dataclass
class HeuristicAgentConfig(AgentConfig):
    """Queue-aware baseline: charge early when the charger is free and the vehicle at D is the
    emptiest one (and below ``upper``); otherwise follow the rule with ``threshold``."""

    name: str = "heuristic"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.baselines.policy:HeuristicPolicy"
    threshold: float = ranged(40.0, 0.0, 100.0)
    upper: float = ranged(60.0, 0.0, 100.0)
    # charge early only if another vehicle is this low; 100 = off
    others_below: float = ranged(100.0, 0.0, 100.0)

