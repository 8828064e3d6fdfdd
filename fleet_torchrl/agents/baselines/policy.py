"""The two hand-written baselines (MODEL §3): the rule-based benchmark and a queue-aware
heuristic, each a :class:`~fleet_torchrl.agents.base.Policy` built from its config."""

from __future__ import annotations

from torch import Tensor

from ...sim.fused import KernelPolicy
from ..base import Policy
from ..threshold.policy import threshold_kernel_policy
from .config import HeuristicAgentConfig, RuleAgentConfig


class RulePolicy(Policy):
    """Rule-based benchmark (MODEL §3): charge iff ``soc_D <= threshold``.

    Reads feature 0 (``soc_D / 100``), which both encodings share.
    """

    name = "rule"

    def __init__(self, threshold: float = 40.0, encoding: str = "partial") -> None:
        super().__init__()
        self.threshold = float(threshold)
        self.encoding = encoding

    @classmethod
    def from_config(cls, agent: RuleAgentConfig) -> RulePolicy:
        return cls(agent.threshold)

    def forward(self, obs: Tensor) -> Tensor:
        return (obs[..., 0] <= self.threshold / 100.0).long()

    def kernel_policy(self) -> KernelPolicy | None:
        if self.encoding != "partial":
            return None
        return threshold_kernel_policy(low=self.threshold)


class HeuristicPolicy(Policy):
    """Queue-aware baseline on the ``partial`` encoding.

    Charge when the charger is free, the vehicle at ``D`` has the lowest soc of all vehicles
    not at ``C`` (ties count as lowest) and its soc is at most ``upper``; otherwise follow the
    rule with ``threshold``. Charging early while the charger idles moves charging time out
    of the busy periods where vehicles would queue behind it. With ``others_below`` < 100 it
    charges early only while another vehicle is at most that full, i.e. when the charger will
    be wanted soon (``heuristic_65_75`` in ``make objective`` queues as little as upper 65
    and makes more trips than upper 60).
    """

    name = "heuristic"
    encoding = "partial"

    def __init__(self, threshold: float = 40.0, upper: float = 60.0,
                 others_below: float = 100.0) -> None:
        super().__init__()
        self.threshold = float(threshold)
        self.upper = float(upper)
        self.others_below = float(others_below)

    @classmethod
    def from_config(cls, agent: HeuristicAgentConfig) -> HeuristicPolicy:
        return cls(agent.threshold, agent.upper, agent.others_below)

    def forward(self, obs: Tensor) -> Tensor:
        soc_d, others, tc = obs[..., 0], obs[..., 1], obs[..., 2]
        early = (tc == 0) & (soc_d <= others) & (soc_d <= self.upper / 100.0)
        if self.others_below < 100.0:
            early &= others <= self.others_below / 100.0
        return (early | (soc_d <= self.threshold / 100.0)).long()

    def kernel_policy(self) -> KernelPolicy:
        return threshold_kernel_policy(
            low=self.threshold, free_upper=self.upper, margin=0.0,
            others_below=self.others_below if self.others_below < 100.0 else None)
