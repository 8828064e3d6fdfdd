"""The schema of the threshold policy (``agent=threshold``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...utils.checks import ranged
from ..schema import AgentConfig


@dataclass
class ThresholdAgentConfig(AgentConfig):
    """A threshold policy (agents/threshold/policy.py); ``null`` turns a rule off."""

    name: str = "threshold"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.threshold.policy:ThresholdPolicy"
    low: float = ranged(40.0, 0.0, 100.0, optional=True)
    free_upper: float | None = ranged(None, 0.0, 100.0, optional=True)
    margin: float = ranged(0.0, -100.0, 100.0)
    others_below: float | None = ranged(None, 0.0, 100.0, optional=True)
    busy_tc: float | None = ranged(None, 0.0, 1.0, optional=True)
    busy_upper: float | None = ranged(None, 0.0, 100.0, optional=True)
