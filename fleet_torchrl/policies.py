"""Decision policies: the common interface and the two hand-written baselines.

A policy is an ``nn.Module`` mapping a batch of encoded observations ``[B, F]`` to actions
``[B]`` (int64, ``0 = pass``, ``1 = charge``). It names the state encoding it reads in its
``encoding`` attribute, so the evaluation loop and the environment build the right features.
:func:`as_td_module` wraps any policy for TorchRL (``observation -> action``).
"""

from __future__ import annotations

from tensordict.nn import TensorDictModule
from torch import Tensor, nn

PASS, CHARGE = 0, 1


class Policy(nn.Module):
    """Base class: ``forward(obs [B, F]) -> action [B] (int64)``."""

    name: str = "policy"
    encoding: str = "partial"


class RulePolicy(Policy):
    """Rule-based benchmark (SPEC §3): charge iff ``soc_D <= threshold``.

    Reads feature 0 (``soc_D / 100``), which both encodings share.
    """

    name = "rule"

    def __init__(self, threshold: float = 40.0, encoding: str = "partial") -> None:
        super().__init__()
        self.threshold = float(threshold)
        self.encoding = encoding

    def forward(self, obs: Tensor) -> Tensor:
        return (obs[..., 0] <= self.threshold / 100.0).long()


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

    def forward(self, obs: Tensor) -> Tensor:
        soc_d, others, tc = obs[..., 0], obs[..., 1], obs[..., 2]
        early = (tc == 0) & (soc_d <= others) & (soc_d <= self.upper / 100.0)
        if self.others_below < 100.0:
            early &= others <= self.others_below / 100.0
        return (early | (soc_d <= self.threshold / 100.0)).long()


def as_td_module(policy: Policy, obs_key: str = "observation",
                 action_key: str = "action") -> TensorDictModule:
    """Wrap a policy as a TorchRL/TensorDict module."""
    return TensorDictModule(policy, in_keys=[obs_key], out_keys=[action_key])


def build_baseline(agent_cfg) -> Policy:
    """Policy from a ``rule`` or ``heuristic`` agent config."""
    if agent_cfg.name == "rule":
        return RulePolicy(agent_cfg.threshold)
    if agent_cfg.name == "heuristic":
        return HeuristicPolicy(agent_cfg.threshold, agent_cfg.upper, agent_cfg.others_below)
    raise ValueError(f"agent.name={agent_cfg.name!r} is not a baseline (rule, heuristic)")
