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

import sys
from dataclasses import dataclass, field, fields, is_dataclass
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
    for row, recipe in cfg.sweep.specialists.items():
        check_choice(f"sweep.specialists.{row}", recipe, tuple(cfg.table.train))
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


def unknown_keys(node: Any, path: str = "") -> list[str]:
    """Keys of a composed config that its schema does not have (added with ``+``), each with
    the settings its group does have."""
    out: list[str] = []
    if not isinstance(node, DictConfig):
        return out
    schema = OmegaConf.get_type(node)
    known = {f.name for f in fields(schema)} if is_dataclass(schema) else None
    for key in node.keys():
        here = f"{path}{key}"
        if known is not None and key not in known:
            out.append(f"{here} is not a setting of {path.rstrip('.') or 'the config'} "
                       f"(allowed: {', '.join(sorted(known))})")
            continue
        if known is not None and not OmegaConf.is_missing(node, key):
            out += unknown_keys(node._get_node(key), f"{here}.")
    return out


def to_config(cfg: DictConfig | Config) -> Config:
    """Turn a composed Hydra config into validated dataclasses; a key the schema does not
    have (e.g. ``+site.pc=0.5``, a misspelt ``site.p_c``) is rejected, naming it."""
    if isinstance(cfg, DictConfig):
        bad = unknown_keys(cfg)
        if bad:
            raise ConfigError(bad[0])
    obj = OmegaConf.to_object(cfg) if isinstance(cfg, DictConfig) else cfg
    if not isinstance(obj, Config):  # composed without the schema (e.g. plain YAML in a test)
        raise ConfigError("config was not composed from the 'base_config' schema")
    return validate(obj)


def one_line(exc: BaseException) -> str:
    """A Hydra or OmegaConf error message on one line (with its cause, the options a group
    offers, and none of Hydra's search-path listing)."""
    text = str(exc).split("Config search path")[0]
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.startswith(("full_key:", "object_type=", "provider=",
                                                      "reference_type=", "Set the environment"))]
    head, options = [], []
    for ln in lines:
        if head and head[-1].startswith("Available options"):
            head[-1] = "; " + head[-1].rstrip(":").replace("Available options", "allowed")
            options.append(ln)
        elif options:
            options.append(ln)
        else:
            head.append(ln)
    options = [o for o in options if not o.startswith("base_")]
    msg = " ".join(head).rstrip(":").replace(" ; ", "; ")
    if options:
        msg += f": {', '.join(options)}"
    if exc.__cause__ is not None and str(exc.__cause__).strip():
        msg += f": {str(exc.__cause__).strip().splitlines()[0]}"
    return msg or type(exc).__name__


def check_command_line(argv: list[str] | None = None) -> None:
    """Compose a command line's overrides before Hydra runs the command, so that what Hydra
    would report in many lines (an unknown option ``site=nope``, a value of the wrong type
    ``site.n_vehicles=abc``, an unknown key ``+site.pc=0.5``, a bad value) ends in one line
    ``error: ...`` and exit code 2. Multiruns and Hydra's own flags are left to Hydra."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    args = sys.argv[1:] if argv is None else argv
    if any(a.startswith("-") for a in args):  # -m, --help, --cfg, ...: Hydra's business
        return
    overrides = [a for a in args if not a.lstrip("+~").startswith(("hydra.", "hydra/"))]
    try:
        compose_config(overrides)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except (HydraException, OmegaConfBaseException) as e:
        print(f"error: {one_line(e)}", file=sys.stderr)
        sys.exit(2)


__all__ = ["CONF_DIR", "Config", "ConfigError", "check_command_line", "compose_config",
           "register_configs", "to_config", "validate"]
