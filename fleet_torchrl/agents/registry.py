"""The agents by name: each one's schema, policy class and how to build it.

An agent is declared on its schema (:class:`~fleet_torchrl.agents.schema.AgentConfig`:
``policy_type``, ``learner_type``, ``states``), which sits beside its implementation
(``agents/<agent>/config.py``) and stays free of torch; :data:`AGENTS` builds one
:class:`AgentSpec` per schema of :data:`~fleet_torchrl.agents.config.AGENT_SCHEMAS` (the
package's own, the entry-point group ``fleet_torchrl.agents``, a user's ``conf/agent`` YAML
naming its class: docs/ADD_A_POLICY.md), and nothing else switches on agent names.
Baselines are built from their config (``Policy.from_agent``); learners from a
:class:`LearnerContext`, the explicit group configs a learner needs
(``Learner.from_context``), and their policies are loaded from files. Where policies are
published and found (names, folders) is :mod:`fleet_torchrl.store`'s business, above this
layer: nothing here reads the root config.
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
from .config import AGENT_SCHEMAS, AgentConfig, load_entry_points
from .policy_files import POLICY_FILE, read_policy_file, save_policy


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

    @classmethod
    def from_schema(cls, name: str, schema: type[AgentConfig]) -> AgentSpec:
        """The entry a schema declares (its classes imported here)."""
        policy_class = schema.associated_class()
        learner_class = schema.learner_class()
        where = f"{schema.__module__}.{schema.__qualname__}"
        if not (isinstance(policy_class, type) and issubclass(policy_class, Policy)):
            raise ConfigError(f"{where}.policy_type={schema.policy_type!r} is invalid: "
                              "allowed a subclass of fleet_torchrl.agents.Policy")
        if learner_class is None:
            return cls(name, schema, policy_class, make_policy=policy_class.from_agent,
                       states=schema.states)
        if not (isinstance(learner_class, type) and issubclass(learner_class, Learner)):
            raise ConfigError(f"{where}.learner_type={schema.learner_type!r} is invalid: "
                              "allowed a subclass of fleet_torchrl.agents.Learner")
        return cls(name, schema, policy_class, make_learner=learner_class.from_context,
                   states=schema.states)


AGENTS: dict[str, AgentSpec] = {}


def register(spec: AgentSpec) -> AgentSpec:
    """Add an agent; its schema joins :data:`~fleet_torchrl.agents.config.AGENT_SCHEMAS`,
    which :func:`fleet_torchrl.config.register_configs` stores for Hydra."""
    AGENTS[spec.name] = spec
    AGENT_SCHEMAS[spec.name] = spec.schema
    return spec


def sync_agents() -> dict[str, AgentSpec]:
    """:data:`AGENTS` with an entry for every schema added since (entry points, a user's
    ``conf/agent`` YAML naming its class); returns it."""
    load_entry_points()
    for name, schema in list(AGENT_SCHEMAS.items()):
        if name not in AGENTS or AGENTS[name].schema is not schema:
            register(AgentSpec.from_schema(name, schema))
    return AGENTS


def get_agent(name: str) -> AgentSpec:
    sync_agents()
    try:
        return AGENTS[name]
    except KeyError:
        raise ValueError(f"agent.name={name!r} is invalid: allowed one of "
                         f"{', '.join(AGENTS)}") from None


sync_agents()


def base_policy(name: str, device: str | torch.device = "cpu") -> Policy:
    """A policy named by a baseline agent (its default settings) or a saved policy's path:
    what the planner's ``agent.base`` and the search's ``agent.init`` accept."""
    spec = AGENTS.get(name)
    if spec is not None and not spec.trainable:
        return spec.make_policy(spec.schema()).to(device)
    return load_policy_file(name, device)


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
