"""The one place that maps agent names to their schema, policy class and builder.

Adding a learner is its schema in ``agents/config.py`` (free of torch, so that composing a
config stays fast), one module (policy, :class:`~fleet_torchrl.agents.base.Learner`), one
``fleet_torchrl/conf/agent/<name>.yaml`` and one :func:`register` call below; nothing else
switches on agent names. Baselines are entries with ``make_policy`` (built from their
config); learners are entries with ``make_learner`` (built from a :class:`LearnerContext`,
the explicit group configs a learner needs; their policies are loaded from files). Where
policies are published and found (names, folders) is :mod:`fleet_torchrl.store`'s business,
above this layer: nothing here reads the root config.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..env.config import MDPConfig
from ..sim import SiteConfig
from .base import Learner, Policy
from .baselines import HeuristicPolicy, RulePolicy
from .config import (
    AGENT_SCHEMAS,
    BASELINE_BASES,
    AgentConfig,
    DQNAgentConfig,
    HeuristicAgentConfig,
    ImitationAgentConfig,
    PlannerAgentConfig,
    RuleAgentConfig,
    SearchAgentConfig,
    TabularAgentConfig,
    ThresholdAgentConfig,
)
from .dqn import DQNLearner, DQNPolicy
from .imitation import ImitationLearner, ImitationPolicy
from .planner import PlannerPolicy
from .policy_files import POLICY_FILE, read_policy_file
from .search import SearchLearner, SearchPolicy
from .tabular import TabularLearner, TabularQPolicy
from .threshold import ThresholdPolicy


@dataclass(frozen=True)
class LearnerContext:
    """What a learner is built from: the group configs it reads, the training seed and
    budget, and the environment's device, observation size and action spec."""

    agent: AgentConfig
    network: Any  # NetworkConfig (the DQN's network group)
    mdp: MDPConfig
    site: SiteConfig
    state: str
    seed: int
    rounds: int  # rounds of the training loop
    device: torch.device
    n_obs: int
    action_spec: Any  # the environment's action spec
    env: Any = None  # the training environment (a learner that labels its states reads it)


@dataclass(frozen=True)
class AgentSpec:
    """One agent: its ``agent`` schema, its policy class and how to build it.

    ``states``: the encodings it accepts (``None``: any); a learner's policy names say the
    state only when it accepts several (:func:`fleet_torchrl.store.policy_name`).
    """

    name: str
    schema: type[AgentConfig]
    policy_class: type[Policy]
    make_policy: Callable[[AgentConfig], Policy] | None = None
    make_learner: Callable[[LearnerContext], Learner] | None = None
    states: tuple[str, ...] | None = None

    @property
    def trainable(self) -> bool:
        return self.make_learner is not None


AGENTS: dict[str, AgentSpec] = {}


def register(spec: AgentSpec) -> AgentSpec:
    """Add an agent; its schema joins :data:`~fleet_torchrl.agents.config.AGENT_SCHEMAS`,
    which :func:`fleet_torchrl.config.register_configs` stores for Hydra."""
    AGENTS[spec.name] = spec
    AGENT_SCHEMAS[spec.name] = spec.schema
    return spec


def get_agent(name: str) -> AgentSpec:
    try:
        return AGENTS[name]
    except KeyError:
        raise ValueError(f"agent.name={name!r} is invalid: allowed one of "
                         f"{', '.join(AGENTS)}") from None


# ------------------------------------------------------------------------ the entries
def _tabular_learner(c: LearnerContext) -> Learner:
    return TabularLearner(k=c.agent.k, gamma=c.mdp.discount, agent=c.agent,
                          mdp=c.mdp).to(c.device)


def _dqn_learner(c: LearnerContext) -> Learner:
    return DQNLearner(c.agent, c.network, c.n_obs, c.state, c.action_spec, c.mdp, c.device,
                      total_updates=c.rounds * c.agent.updates_per_round)


def _search_learner(c: LearnerContext) -> Learner:
    init = c.agent.init
    if init == "uniform":
        start = None
    else:  # a baseline or a saved policy: it must read the partial state the classes read
        start = base_policy(init)
        if start.encoding != "partial":
            raise ValueError(f"agent.init={init!r}: a {start.encoding!r}-state policy cannot "
                             "start a search over partial-state policies")
    return SearchLearner(c.agent, c.site, c.seed, start).to(c.device)


register(AgentSpec("rule", RuleAgentConfig, RulePolicy, make_policy=RulePolicy.from_config))
register(AgentSpec("heuristic", HeuristicAgentConfig, HeuristicPolicy,
                   make_policy=HeuristicPolicy.from_config))
register(AgentSpec("threshold", ThresholdAgentConfig, ThresholdPolicy,
                   make_policy=ThresholdPolicy.from_config))


def base_policy(name: str, device: str | torch.device = "cpu") -> Policy:
    """A policy named by a baseline agent (its default settings) or a saved policy's path:
    what the planner's ``agent.base`` and the search's ``agent.init`` accept."""
    spec = AGENTS.get(name)
    if spec is not None and not spec.trainable:
        return spec.make_policy(spec.schema()).to(device)
    return load_policy_file(name, device)


def _planner(agent: PlannerAgentConfig) -> Policy:
    for b in agent.all_bases():
        assert b in BASELINE_BASES or Path(b).exists(), b
    return PlannerPolicy.from_config(agent, base_policy(agent.base),
                                     [base_policy(b) for b in agent.bases])


register(AgentSpec("planner", PlannerAgentConfig, PlannerPolicy, make_policy=_planner))
register(AgentSpec("tabular", TabularAgentConfig, TabularQPolicy, make_learner=_tabular_learner,
                   states=("partial",)))
register(AgentSpec("dqn", DQNAgentConfig, DQNPolicy, make_learner=_dqn_learner))
register(AgentSpec("search", SearchAgentConfig, SearchPolicy, make_learner=_search_learner,
                   states=("partial",)))


def _imitation_learner(c: LearnerContext) -> Learner:
    if c.env is None:
        raise ValueError("agent=imitation labels the states of the training environment: "
                         "build it with LearnerContext(env=...)")
    expert = _planner(c.agent.expert).to(c.device)
    return ImitationLearner(c.agent, expert, c.env, c.n_obs, c.state, c.seed, c.device)


register(AgentSpec("imitation", ImitationAgentConfig, ImitationPolicy,
                   make_learner=_imitation_learner,
                   states=("partial", "partial_site", "all", "all_site",
                           "partial_all_site")))


# ------------------------------------------------------------------------ lookups
def load_policy_file(path: str | Path, device: str | torch.device = "cpu") -> Policy:
    """Rebuild a policy from ``policy.pt`` (or a folder holding one) through its agent's
    policy class."""
    path, bundle = read_policy_file(path)
    kind = bundle["kind"]
    spec = AGENTS.get(kind)
    if spec is None or not spec.trainable:
        raise ValueError(f"{path}: unknown policy kind {kind!r}")
    try:
        policy = spec.policy_class.from_policy_spec(bundle["spec"])
        policy.load_state_dict(bundle["state_dict"])
    except (RuntimeError, TypeError, KeyError) as e:
        raise ValueError(f"{path}: weights do not fit the {kind} policy ({e})") from None
    return policy.to(device).eval()


__all__ = ["AGENTS", "POLICY_FILE", "AgentSpec", "LearnerContext", "base_policy", "get_agent",
           "load_policy_file", "register"]
