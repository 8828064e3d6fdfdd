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
from types import SimpleNamespace
from typing import Any

import torch

from ..env.config import MDPConfig
from ..env.encodings import ENCODINGS
from ..sim import Site, SiteConfig
from ..sim.config import MAX_NODES
from ..utils.checks import ConfigError
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
from .policy_files import POLICY_FILE, read_policy_file, save_policy
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
#: the most parameters and buffer entries a policy file's spec may ask for (256 MiB of
#: float32; the learners' networks hold well under a million)
MAX_POLICY_PARAMETERS = 2**26
MIN_NODES = 5  # the fewest nodes a site has (SiteConfig.validate)


def encoding_widths(encoding: str) -> list[int]:
    """The feature counts the encoding ``encoding`` (a known one) can have, over every
    site size (one count for the encodings whose width is fixed)."""
    enc = ENCODINGS[encoding]
    return sorted({enc.size(SimpleNamespace(n_nodes=n)) for n in range(MIN_NODES,
                                                                         MAX_NODES + 1)})


def _fits_encoding(encoding: str, n_obs: int) -> str | None:
    widths = encoding_widths(encoding)
    if n_obs in widths:
        return None
    allowed = (f"{widths[0]} features" if len(widths) == 1 else
               f"{widths[0]} to {widths[-1]} features (with the site's node count)")
    return (f"the encoding's feature count must match the network's input width: "
            f"state={encoding} has {allowed}, the network reads spec.n_obs={n_obs}")


def check_policy_bundle(path: Path, bundle: dict[str, Any]) -> tuple[AgentSpec, Policy]:
    """Validate what a policy file asks to be built, before anything is allocated: its kind
    (a known learner's name), its declared encoding (a known one), its spec (the policy
    class's :meth:`~Policy.check_policy_spec`: fields, types, ranges), then the policy the
    spec describes, built on the ``meta`` device (shapes, no memory): at most
    :data:`MAX_POLICY_PARAMETERS` entries, the declared encoding, an input width that the
    encoding has, and exactly the stored tensors' names, shapes and dtypes. Returns the
    agent and that shell; raises ``ValueError`` with one line naming ``path``."""
    kind = bundle.get("kind")
    learners = [n for n, a in AGENTS.items() if a.trainable]
    if not isinstance(kind, str) or kind not in learners:
        raise ValueError(f"{path}: kind={repr(kind)[:40]} is invalid: kind must be a string "
                         f"naming a known policy kind (one of {', '.join(learners)})")
    agent = AGENTS[kind]
    encoding = bundle["encoding"]
    if encoding not in ENCODINGS:
        raise ValueError(f"{path}: encoding={encoding[:40]!r} is invalid: the encoding must be "
                         f"a known one (one of {', '.join(ENCODINGS)})")
    spec = bundle["spec"]
    try:
        agent.policy_class.check_policy_spec(spec)
    except ConfigError as e:
        raise ValueError(f"{path}: {e}") from None
    try:
        with torch.device("meta"):  # shapes only: nothing is allocated
            shell = agent.policy_class.from_policy_spec(spec)
    except (ValueError, TypeError, KeyError) as e:
        raise ValueError(f"{path}: its spec does not build a {kind} policy ({e})") from None
    want = shell.state_dict()
    n = sum(t.numel() for t in want.values())
    if n > MAX_POLICY_PARAMETERS:
        raise ValueError(f"{path}: its spec asks for {n:,} parameters, more than a policy may "
                         f"have ({MAX_POLICY_PARAMETERS:,}): {shell.size_fields} too large")
    if shell.encoding != encoding:
        raise ValueError(f"{path}: spec.encoding={shell.encoding!r} disagrees with the file's "
                         f"declared encoding {encoding!r}: retrain the policy or restore the "
                         "file")
    n_obs = getattr(shell, "n_obs", None)
    why = _fits_encoding(encoding, n_obs) if isinstance(n_obs, int) else None
    if why is not None:
        raise ValueError(f"{path}: {why}")
    have = bundle["state_dict"]
    for key in sorted(set(want) | set(have)):
        if key not in have:
            raise ValueError(f"{path}: its weights lack {key!r}, which its spec has: the "
                             f"weights do not fit the {kind} policy")
        if key not in want:
            raise ValueError(f"{path}: its weights hold {key[:60]!r}, which its spec has "
                             f"not: the weights do not fit the {kind} policy")
        w, h = want[key], have[key]
        if tuple(w.shape) != tuple(h.shape) or w.dtype != h.dtype:
            raise ValueError(f"{path}: {key} is {h.dtype} {list(h.shape)} in its weights "
                             f"but {w.dtype} {list(w.shape)} by its spec: the weights do not "
                             f"fit the {kind} policy")
    return agent, shell


def load_policy_file(path: str | Path, device: str | torch.device = "cpu") -> Policy:
    """Rebuild a policy from ``policy.pt`` (or a folder holding one) through its agent's
    policy class: the file's hashes (:func:`read_policy_file`), then its kind, encoding,
    spec and tensors (:func:`check_policy_bundle`) are checked before the policy is built,
    and its loaded weights after (:meth:`Policy.check_loaded`: actions in {0, 1})."""
    path, bundle = read_policy_file(path)
    agent, _ = check_policy_bundle(path, bundle)
    kind = agent.name
    try:
        policy = agent.policy_class.from_policy_spec(bundle["spec"])
        policy.load_state_dict(bundle["state_dict"])
    except (RuntimeError, TypeError, KeyError) as e:
        raise ValueError(f"{path}: weights do not fit the {kind} policy ({e})") from None
    bad = policy.check_loaded()
    if bad is not None:
        raise ValueError(f"{path}: {bad}; retrain the policy or restore the file")
    return policy.to(device).eval()


def check_policy_fits_site(policy: Policy, site: SiteConfig, path: str | Path) -> None:
    """A loaded policy's network reads as many features as its encoding gives on ``site``
    (``all`` and its variants grow with the site's nodes); ``ValueError`` otherwise."""
    n_obs = getattr(policy, "n_obs", None)
    if not isinstance(n_obs, int):
        return
    width = ENCODINGS[policy.encoding].size(Site(site))
    if width != n_obs:
        raise ValueError(f"{path}: the encoding's feature count must match the network's "
                         f"input width: state={policy.encoding} has {width} features on this "
                         f"site (site.n_nodes={site.n_nodes}), the network reads {n_obs}")


def upgrade_policy_file(path: str | Path) -> tuple[Path, str]:
    """Rewrite a policy file written before its hash covered its kind, spec and metadata
    with today's hashes (after every check :func:`load_policy_file` makes); returns the
    path and the SHA-256 of the bytes written."""
    path, bundle = read_policy_file(path)
    policy = load_policy_file(path)
    return save_policy(path, policy, bundle["kind"], bundle.get("meta") or {})


__all__ = ["AGENTS", "MAX_POLICY_PARAMETERS", "POLICY_FILE", "AgentSpec", "LearnerContext",
           "base_policy", "check_policy_bundle", "check_policy_fits_site", "get_agent",
           "load_policy_file", "register", "upgrade_policy_file"]
