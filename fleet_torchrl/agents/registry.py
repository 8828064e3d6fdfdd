"""The one place that maps agent names to their schema, policy class and builder.

Adding a learner is one module (schema, policy, :class:`~fleet_torchrl.agents.base.Learner`),
one ``fleet_torchrl/conf/agent/<name>.yaml`` and one :func:`register` call below; nothing
else switches on agent names. Baselines are entries with ``make_policy`` (built from their
config); learners are entries with ``make_learner`` (their policies are loaded from files).
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import yaml

from ..sim import SiteConfig, SiteRanges
from .base import AgentConfig, Learner, Policy
from .baselines import HeuristicAgentConfig, HeuristicPolicy, RuleAgentConfig, RulePolicy
from .dqn import DQNAgentConfig, DQNLearner, DQNPolicy
from .policy_files import POLICY_FILE, read_policy_file
from .search import SearchAgentConfig, SearchLearner, SearchPolicy
from .tabular import TabularAgentConfig, TabularLearner, TabularQPolicy

if TYPE_CHECKING:
    from ..config import Config
    from ..env import FleetChargingEnv


@dataclass(frozen=True)
class AgentSpec:
    """One agent: its ``agent`` schema, its policy class and how to build it.

    ``states``: the encodings it accepts (``None``: any). A learner's policies are named
    ``<name>`` if it accepts one encoding, else ``<name>_<state>``, then what the agent adds
    (:meth:`AgentConfig.run_suffix`: objective, variant) and the site (:func:`site_suffix`).
    """

    name: str
    schema: type[AgentConfig]
    policy_class: type[Policy]
    make_policy: Callable[[AgentConfig], Policy] | None = None
    make_learner: Callable[[Config, FleetChargingEnv], Learner] | None = None
    states: tuple[str, ...] | None = None

    @property
    def trainable(self) -> bool:
        return self.make_learner is not None

    def run_name(self, cfg: Config) -> str:
        """Name of the policy a run of this agent makes, and so of the folder ``make train``
        publishes it to: one name per agent, state, objective and site, so that no run
        replaces the policy of another recipe (``tabular``, ``dqn_all_throughput``,
        ``search_mlp_five_vehicles``, ``dqn_partial_throughput_anchored_randomized``)."""
        name = self.name if self.states is not None and len(self.states) == 1 \
            else f"{self.name}_{cfg.state.name}"
        # what else tells two runs apart: tabular vs tabular_throughput, search vs
        # search_mlp, then the site (a DQN of the site distribution is not the default
        # site's, whose folder it used to overwrite)
        return name + cfg.agent.run_suffix(cfg.mdp) + site_suffix(cfg.site)


# the packaged site presets, wherever in the package this module lives
_SITE_PRESETS = resources.files(__name__.split(".")[0]).joinpath("conf", "site")


@functools.cache
def site_preset(name: str) -> SiteConfig | None:
    """The site ``conf/site/<name>.yaml`` defines (its ``defaults`` chain followed), or None
    if the package has no such preset. Plain YAML, no Hydra: this layer stays below the
    config (tests/agents/test_registry.py checks it against Hydra's composition)."""
    path = _SITE_PRESETS.joinpath(f"{name}.yaml")
    if not path.is_file():
        return None
    node = yaml.safe_load(path.read_text()) or {}
    values: dict = {}
    for parent in node.pop("defaults", []):
        if parent in ("base_site", "_self_"):
            continue
        base = site_preset(parent)
        if base is None:
            return None
        values.update(asdict(base))
    values.update(node)
    ranges = values.pop("ranges", None)
    return SiteConfig(**values, ranges=SiteRanges(**ranges) if ranges else None)


def site_suffix(site: SiteConfig) -> str:
    """What a policy name adds for the site it was trained on: nothing for the default site,
    ``_<preset>`` for a packaged preset as it stands (``_five_vehicles``, ``_randomized``),
    and ``_<name>-<8 hex digits of its settings>`` for any other site (a preset with a
    field changed, ``site.p_c=0.6``), which would otherwise publish into the folder of the
    preset's policy."""
    preset = site_preset(site.name)
    if preset is not None and preset == site:
        return "" if site.name == "default" else f"_{site.name}"
    fields = asdict(site)
    del fields["name"]
    digest = hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:8]
    return f"_{site.name}-{digest}"


AGENTS: dict[str, AgentSpec] = {}


def register(spec: AgentSpec) -> AgentSpec:
    AGENTS[spec.name] = spec
    return spec


def get_agent(name: str) -> AgentSpec:
    try:
        return AGENTS[name]
    except KeyError:
        raise ValueError(f"agent.name={name!r} is invalid: allowed one of "
                         f"{', '.join(AGENTS)}") from None


# ------------------------------------------------------------------------ the entries
def _tabular_learner(cfg: Config, env: FleetChargingEnv) -> Learner:
    return TabularLearner(k=cfg.agent.k, gamma=cfg.mdp.discount, agent=cfg.agent,
                          mdp=cfg.mdp).to(env.device)


def _dqn_learner(cfg: Config, env: FleetChargingEnv) -> Learner:
    n_obs = env.observation_spec["observation"].shape[-1]
    rounds = cfg.agent.training_rounds(cfg.train)
    return DQNLearner(cfg.agent, cfg.network, n_obs, cfg.state.name, env.action_spec,
                      cfg.mdp, env.device, total_updates=rounds * cfg.agent.updates_per_round)


def _search_learner(cfg: Config, env: FleetChargingEnv) -> Learner:
    init = cfg.agent.init
    if init == "uniform":
        start = None
    elif init in AGENTS and not AGENTS[init].trainable:
        start = AGENTS[init].make_policy(AGENTS[init].schema())
    else:  # a saved policy: it must read the partial state the search's classes read
        start = load_policy_file(init)
        if start.encoding != "partial":
            raise ValueError(f"agent.init={init!r}: a {start.encoding!r}-state policy cannot "
                             "start a search over partial-state policies")
    return SearchLearner(cfg.agent, cfg.site, cfg.seed, start).to(env.device)


register(AgentSpec("rule", RuleAgentConfig, RulePolicy, make_policy=RulePolicy.from_config))
register(AgentSpec("heuristic", HeuristicAgentConfig, HeuristicPolicy,
                   make_policy=HeuristicPolicy.from_config))
register(AgentSpec("tabular", TabularAgentConfig, TabularQPolicy, make_learner=_tabular_learner,
                   states=("partial",)))
register(AgentSpec("dqn", DQNAgentConfig, DQNPolicy, make_learner=_dqn_learner))
register(AgentSpec("search", SearchAgentConfig, SearchPolicy, make_learner=_search_learner,
                   states=("partial",)))


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


def default_policy_dir(cfg: Config) -> Path:
    """Where a training run of ``cfg`` saves its policy, and where evaluation looks for it."""
    if cfg.train.out_dir:
        return Path(cfg.train.out_dir)
    return Path(cfg.table.policies_dir) / get_agent(cfg.agent.name).run_name(cfg)


def make_policy(cfg: Config, device: str | torch.device | None = None) -> Policy:
    """The policy ``cfg.agent`` names: baselines from their config, learned ones from disk
    (``agent.policy`` or the default location of their run)."""
    spec = get_agent(cfg.agent.name)
    device = device if device is not None else cfg.eval.device
    if not spec.trainable:
        return spec.make_policy(cfg.agent).to(device)
    if cfg.agent.policy:
        path = Path(cfg.agent.policy)
    elif cfg.train.out_dir:
        path = Path(cfg.train.out_dir)
    else:  # make train's <name>/policy.pt, else the lowest seed make table trained
        path = saved_policy_path(cfg.table.policies_dir, spec.run_name(cfg))
        other = site_suffix(cfg.site)
        if other and not path.is_file():  # names carry the site: say how to cross sites
            home = Path(cfg.table.policies_dir) / spec.run_name(cfg).removesuffix(other)
            raise FileNotFoundError(
                f"no saved policy at {path} (a policy trained on this site); to evaluate "
                f"one trained on another site here, pass agent.policy=<its folder>, "
                f"e.g. agent.policy={home}")
    policy = load_policy_file(path, device)
    if not isinstance(policy, spec.policy_class):
        raise ValueError(f"{path} holds a {type(policy).__name__}, not a policy of "
                         f"agent={spec.name}: pass the matching agent= with agent.policy=")
    if policy.encoding != cfg.state.name:
        raise ValueError(f"{path} was trained on state={policy.encoding}, not "
                         f"state={cfg.state.name}")
    return policy


def seed_dir(root: str | Path, name: str, seed: int) -> Path:
    """Folder of the policy ``name`` trained with ``seed`` (``make table`` trains several)."""
    return Path(root) / name / f"seed{seed}"


def saved_policy_path(root: str | Path, name: str) -> Path:
    """The saved policy a name stands for: ``<root>/<name>/policy.pt`` if there is one, else
    the policy of the lowest training seed, ``<root>/<name>/seed<k>/policy.pt``."""
    folder = Path(root) / name
    if (folder / POLICY_FILE).is_file():
        return folder / POLICY_FILE
    seeds = sorted((int(p.parent.name[4:]), p) for p in folder.glob(f"seed*/{POLICY_FILE}")
                   if p.parent.name[4:].isdigit())
    return seeds[0][1] if seeds else folder / POLICY_FILE


def load_policies(cfg: Config, names: list[str]) -> dict[str, Policy]:
    """Policies by name: baselines (``rule``, ``heuristic``) with their default parameters,
    learned ones from ``cfg.table.policies_dir`` (:func:`saved_policy_path`)."""
    out: dict[str, Policy] = {}
    for name in names:
        spec = AGENTS.get(name)
        if spec is not None and not spec.trainable:
            out[name] = spec.make_policy(spec.schema()).to(cfg.eval.device)
        else:
            out[name] = load_policy_file(saved_policy_path(cfg.table.policies_dir, name),
                                         cfg.eval.device)
            out[name].name = name
    return out


__all__ = ["AGENTS", "POLICY_FILE", "AgentSpec", "default_policy_dir", "get_agent",
           "load_policies", "load_policy_file", "make_policy", "register", "saved_policy_path",
           "seed_dir", "site_preset", "site_suffix"]
