"""The root configuration: composes every group's schema, registers them in Hydra's
ConfigStore, validates, and turns a composed Hydra config into typed dataclasses.

Each schema lives beside the code it configures (``sim/config.py``: ``site``; ``env/config.py``:
``state``, ``mdp``; each agent's module: its ``agent`` schema, ``agents/dqn.py``: ``network``;
``training/config.py``: ``train``; ``evaluation/config.py``: ``eval``;
``experiments/config.py``: ``table``, ``sweep``, ``maps``, ``objective``) and checks its own
ranges; :func:`validate` runs them all and the cross-group checks. Every YAML file under
``fleet_torchrl/conf/`` extends one schema (``defaults: [base_X, _self_]``), so a typo in a
field name or a wrong type is rejected by Hydra when the config is composed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import MISSING, DictConfig, OmegaConf

from .agents.dqn import NetworkConfig
from .agents.registry import AGENTS, get_agent
from .env.config import MDPConfig, StateConfig
from .evaluation.config import EvalConfig
from .experiments.config import MapsConfig, ObjectiveConfig, SweepConfig, TableConfig
from .sim.config import SiteConfig
from .training.config import TrainConfig
from .utils.checks import ConfigError, check_choice, check_range

CONF_DIR = Path(__file__).resolve().parent / "conf"


@dataclass
class Config:
    site: SiteConfig = field(default_factory=SiteConfig)
    state: StateConfig = field(default_factory=StateConfig)
    mdp: MDPConfig = field(default_factory=MDPConfig)
    agent: Any = MISSING
    network: NetworkConfig = field(default_factory=NetworkConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    table: TableConfig = field(default_factory=TableConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    maps: MapsConfig = field(default_factory=MapsConfig)
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    seed: int = 0
    resume: bool = False


def register_configs() -> None:
    """Register the schemas in Hydra's ConfigStore (idempotent)."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="site", name="base_site", node=SiteConfig)
    cs.store(group="state", name="base_state", node=StateConfig)
    cs.store(group="mdp", name="base_mdp", node=MDPConfig)
    cs.store(group="eval", name="base_eval", node=EvalConfig)
    cs.store(group="network", name="base_network", node=NetworkConfig)
    cs.store(group="train", name="base_train", node=TrainConfig)
    for name, spec in AGENTS.items():
        cs.store(group="agent", name=f"base_{name}", node=spec.schema)


def validate(cfg: Config) -> Config:
    """Check every range; raise :class:`ConfigError` naming the first bad field."""
    cfg.site.validate()
    cfg.state.validate()
    cfg.mdp.validate()
    check_choice("agent.name", getattr(cfg.agent, "name", None), tuple(AGENTS))
    spec = get_agent(cfg.agent.name)
    if not isinstance(cfg.agent, spec.schema):
        raise ConfigError(f"agent.name={cfg.agent.name!r} does not match its settings: compose "
                          f"it with agent={cfg.agent.name}")
    cfg.agent.validate(cfg)
    if spec.states is not None and cfg.state.name not in spec.states:
        raise ConfigError(f"state.name={cfg.state.name!r} is invalid for agent={spec.name}: "
                          f"allowed {', '.join(spec.states)}")
    cfg.network.validate()
    cfg.train.validate()
    cfg.eval.validate()
    check_range("seed", cfg.seed, 0, 2**32 - 1)
    known = (*(n for n, s in AGENTS.items() if not s.trainable), *cfg.table.train.keys())
    cfg.table.validate()
    cfg.sweep.validate(known)
    cfg.maps.validate(known)
    cfg.objective.validate()
    return cfg


def compose_config(overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """The validated config that ``conf/config.yaml`` plus ``overrides`` composes to.

    Works inside a running Hydra app (which has already initialised Hydra) and outside one.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    register_configs()
    if GlobalHydra.instance().is_initialized():
        return to_config(compose(config_name="config", overrides=list(overrides)))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return to_config(compose(config_name="config", overrides=list(overrides)))


def to_config(cfg: DictConfig | Config) -> Config:
    """Turn a composed Hydra config into validated dataclasses."""
    obj = OmegaConf.to_object(cfg) if isinstance(cfg, DictConfig) else cfg
    if not isinstance(obj, Config):  # composed without the schema (e.g. plain YAML in a test)
        raise ConfigError("config was not composed from the 'base_config' schema")
    return validate(obj)


__all__ = ["CONF_DIR", "Config", "ConfigError", "compose_config", "register_configs",
           "to_config", "validate"]
