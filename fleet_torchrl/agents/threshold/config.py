"""The schema of the threshold policy (``agent=threshold``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from ...utils.checks import check_range
from ..schema import AgentConfig


@dataclass
class ThresholdAgentConfig(AgentConfig):
    """A threshold policy (agents/threshold/policy.py); ``null`` turns a rule off."""

    name: str = "threshold"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.threshold.policy:ThresholdPolicy"
    low: float = 40.0
    free_upper: float | None = None
    margin: float = 0.0
    others_below: float | None = None
    busy_tc: float | None = None
    busy_upper: float | None = None

    def validate(self, cfg: Any = None, path: str = "agent") -> ThresholdAgentConfig:
        for name in ("low", "free_upper", "others_below", "busy_upper"):
            v = getattr(self, name)
            if v is not None:
                check_range(f"{path}.{name}", v, 0.0, 100.0)
        check_range(f"{path}.margin", self.margin, -100.0, 100.0)
        if self.busy_tc is not None:
            check_range(f"{path}.busy_tc", self.busy_tc, 0.0, 1.0)
        return self
