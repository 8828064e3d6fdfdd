"""The root configuration: composes every group's schema, registers them in Hydra's
ConfigStore, validates, and turns a composed Hydra config into typed dataclasses.

Each schema lives beside the code it configures (``sim/config.py``: ``site``; ``env/config.py``:
``state``, ``mdp``; ``agents/<agent>/config.py``: each ``agent`` schema, collected with those
from outside the package in ``agents/config.py``; ``agents/dqn/config.py``: ``network``;
``training/config.py``: ``train``; ``evaluation/config.py``: ``eval``;
``experiments/config.py``: ``table``, ``sweep``, ``maps``, ``objective``, ``recipes``) and
checks its own ranges; :func:`validate` runs them all and the cross-group checks. Every YAML
file under ``fleet_torchrl/conf/`` extends one schema (``defaults: [/schema_X@_here_,
_self_]``), so a typo in a field name or a wrong type is rejected by Hydra when the config is
composed. The schemas are stored outside the groups (``schema_site``, ``schema_agent_dqn``,
...): a group lists only real options, in ``--help`` and tab completion, and
``agent=schema_agent_rule`` is no option at all. None of these modules imports torch:
composing a config is what ``--help`` and every tab completion do.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from omegaconf import MISSING, DictConfig, OmegaConf

from .agents.config import (
    AGENT_SCHEMAS,
    BUILTIN_SCHEMAS,
    NetworkConfig,
    add_schema,
    import_object,
    load_entry_points,
)
from .env.config import MDPConfig, StateConfig
from .evaluation.config import EvalConfig
from .experiments.config import (
    BenchConfig,
    CompareConfig,
    GridSummaryConfig,
    MapsConfig,
    ObjectiveConfig,
    Recipe,
    ReportConfig,
    SweepConfig,
    SweepSummaryConfig,
    TableConfig,
    check_sweep_value,
    validate_recipes,
)
from .sim.config import SiteConfig
from .training.config import TrainConfig
from .utils.checks import ConfigError, check_choice, check_range, deferred_validation
from .utils.paths import check_name

CONF_DIR = Path(__file__).resolve().parent / "conf"
# the file tools' own configs: command name -> schema (conf/<name>.yaml extends schema_<name>)
TOOL_SCHEMAS = {"compare": CompareConfig, "report": ReportConfig, "grid": GridSummaryConfig,
                "sweeps_summary": SweepSummaryConfig}


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
    recipes: dict[str, Recipe] = field(default_factory=dict)  # conf/recipes/
    bench: BenchConfig = field(default_factory=BenchConfig)
    seed: int = 0
    resume: bool = False


USER_CONF = Path("conf")  # the users' own configs, relative to the working directory


def user_options(root: Path = USER_CONF) -> dict[str, list[str]]:
    """The options of the users' own config folder (``./conf``, ``hydra.searchpath`` in
    ``conf/config.yaml``) by group, without those the package already has (which win)."""
    out: dict[str, list[str]] = {}
    if not root.is_dir():
        return out
    for path in sorted(root.rglob("*.yaml")):
        group = path.parent.relative_to(root).as_posix()
        if group == "." or group.split("/")[0] == "hydra":
            continue
        if not (CONF_DIR / group / path.name).is_file():
            out.setdefault(group, []).append(path.stem)
    return out


def user_options_help() -> str:
    """The ``--help`` lines of :func:`user_options` (Hydra's own listing ignores a primary
    config's search path)."""
    found = user_options()
    if not found:
        return ""
    lines = "".join(f"{g}: {', '.join(o)}\n" for g, o in found.items())
    return f"\nYour own, from ./conf (conf/README.md):\n{lines}"


SCHEMA_KEY = "_schema_"  # a user's agent YAML naming its schema class (docs/ADD_A_POLICY.md)


def user_agent_schemas(root: Path = USER_CONF) -> dict[str, type]:
    """The schemas that the users' own agent YAML files name (``_schema_: module.Class``,
    imported with the working directory on the import path), added to the agents
    (:func:`~fleet_torchrl.agents.config.add_schema`); by file name. A class that cannot be
    imported or is no agent schema raises :class:`ConfigError` naming the file."""
    import sys

    out = {}
    for stem in user_options(root).get("agent", []):
        path = root / "agent" / f"{stem}.yaml"
        node = OmegaConf.load(path)
        target = node.get(SCHEMA_KEY) if isinstance(node, DictConfig) else None
        if target is None:
            continue
        if str(Path.cwd()) not in sys.path and "" not in sys.path:
            sys.path.append(str(Path.cwd()))  # a module beside conf/ (console scripts too)
        where = f"{path}: {SCHEMA_KEY}"
        schema = import_object(str(target), where)
        add_schema(schema, f"{where}={target!r}")
        out[stem] = schema
    return out


def typed_user_agent(cfg: DictConfig) -> DictConfig:
    """A composed config whose ``agent`` a user's YAML filled naming its schema
    (``_schema_``, :func:`user_agent_schemas`) with that ``agent`` typed by the schema: a
    key the schema lacks or a value of the wrong type is refused in one line, as for any
    group."""
    agent = cfg.get("agent") if "agent" in cfg else None
    if not isinstance(agent, DictConfig) or SCHEMA_KEY not in agent:
        return cfg
    target = str(agent[SCHEMA_KEY])
    schema = import_object(target, f"agent.{SCHEMA_KEY}")
    add_schema(schema, f"agent.{SCHEMA_KEY}={target!r}")
    values = OmegaConf.to_container(agent, resolve=False)
    values.pop(SCHEMA_KEY)
    known = {f.name for f in fields(schema)}
    for key in values:
        if key not in known:
            raise ConfigError(f"agent.{key} is not a setting of agent (allowed: "
                              f"{', '.join(sorted(known))})")
    from omegaconf.errors import OmegaConfBaseException

    try:
        with deferred_validation():
            node = OmegaConf.merge(OmegaConf.structured(schema), values)
    except OmegaConfBaseException as e:
        key = str(getattr(e, "key", None) or "")
        what = f"agent.{key}={values[key]!r}" if key in values else "agent"
        raise ConfigError(f"{what} is invalid: {one_line(e)}") from None
    from omegaconf import open_dict, read_write

    with read_write(cfg), open_dict(cfg):
        cfg.agent = node
    return cfg


RUN_PID = "FLEET_TORCHRL_RUN_PID"  # the pid of the command whose multirun this process runs


def run_pid() -> int:
    """``${fleet_pid:}`` of the run folders: the process id of the command, which keeps two
    commands started in the same second apart. A multirun's workers (joblib, submitit, Ray)
    resolve the sweep folder again: they read the launching command's id from the
    environment it set (:func:`mark_multirun`), so every job lands in one sweep folder. A
    value there that is no process id raises :class:`ConfigError` (one line)."""
    value = os.environ.get(RUN_PID)
    if not value:
        return os.getpid()
    if not (value.isascii() and value.isdigit()) or not 0 < int(value) < 2**31:
        raise ConfigError(f"{RUN_PID}={value[:40]!r} is invalid: allowed a process id (a "
                          "positive integer); unset it (a multirun sets it for its jobs)")
    return int(value)


def activate_line() -> str:
    """``${fleet_activate:}``, the set-up line of the Slurm preset
    (``conf/hydra/launcher/slurm.yaml``), resolved in the submitting command: the shell line
    that puts a job on the Python environment that command runs from (``sys.prefix``):
    ``source <prefix>/bin/activate`` in a virtual environment (a checkout's ``.venv`` or
    any other), else its ``bin/`` first on ``PATH`` (a package installed outside one)."""
    import shlex
    import sys

    prefix = Path(sys.prefix)
    if (prefix / "bin" / "activate").is_file():
        return f"source {shlex.quote(str(prefix / 'bin' / 'activate'))}"
    return f'export PATH={shlex.quote(str(prefix / "bin"))}:"$PATH"'


def mark_multirun(argv: list[str]) -> None:
    """In the command that launches a multirun (``-m``/``--multirun``), pass its process id
    to the workers it starts (their ``${fleet_pid:}``)."""
    if any(a in ("-m", "--multirun") for a in argv):
        os.environ[RUN_PID] = str(os.getpid())


def register_configs() -> None:
    """Register the schemas in Hydra's ConfigStore (idempotent), outside every config group
(``schema_<group>``, ``schema_agent_<name>``): the YAML options extend them, and neither
``--help`` nor tab completion lists them as options."""
    import warnings

    from hydra.core.config_store import ConfigStore

    # conf/config.yaml searches ./conf for the users' own configs; most working directories
    # have none, which is no news worth a warning on every command
    warnings.filterwarnings("ignore", message=r"provider=hydra\.searchpath in main, "
                            r"path=conf is not available", category=UserWarning)
    for name, resolver in (("fleet_user_options", user_options_help),
                           ("fleet_script", lambda job: f"fleet-{job.replace('_', '-')}"),
                           ("fleet_pid", run_pid),  # run folders: unique per command
                           ("fleet_activate", activate_line)):  # a Slurm job's environment
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, resolver)
    cs = ConfigStore.instance()
    with deferred_validation():  # defaults are valid; validating imports the registries
        cs.store(name="schema_config", node=Config)
        for group, schema in (("site", SiteConfig), ("state", StateConfig), ("mdp", MDPConfig),
                              ("eval", EvalConfig), ("network", NetworkConfig),
                              ("train", TrainConfig)):
            cs.store(name=f"schema_{group}", node=schema)
        outside = load_entry_points()  # agents of other packages: agent=<name> needs no YAML
        user_agent_schemas()
        for name, schema in AGENT_SCHEMAS.items():
            cs.store(name=f"schema_agent_{name}", node=schema)
            if name in outside and name not in BUILTIN_SCHEMAS:
                cs.store(group="agent", name=name, node=schema)
        # the primary configs of the commands that only read result files (conf/<command>.yaml)
        for name, schema in TOOL_SCHEMAS.items():
            cs.store(name=f"schema_{name}", node=schema)


# the groups of the root config; a run spec's (fleet_torchrl.training.spec) are always read
GROUPS = ("site", "state", "mdp", "agent", "network", "train", "eval", "table", "recipes",
          "sweep", "maps", "objective", "bench")


def validate(cfg: Config, groups: Iterable[str] = GROUPS) -> Config:
    """Check the ranges of the run spec's groups and of ``groups`` (the groups a command
    reads: its ``GROUPS``; default all) and the cross-checks among them; raise
    :class:`ConfigError` naming the first bad field. A group no command of ``groups`` reads
    is composed, but neither checked nor read."""
    groups = frozenset(groups)
    unknown = groups - set(GROUPS)
    if unknown:
        raise ValueError(f"groups={sorted(unknown)} is invalid: allowed {', '.join(GROUPS)}")
    spec = validate_spec(cfg)
    if "eval" in groups:
        cfg.eval.validate()
    if groups & {"recipes", "table", "sweep", "maps", "bench"}:
        validate_experiments(cfg, groups)
    if "objective" in groups:
        cfg.objective.validate()
    if "bench" in groups:
        cfg.bench.validate()
    check_memory_needs(cfg, spec.trainable and "train" in groups, groups)
    return cfg


def validate_spec(cfg: Config) -> Any:
    """The checks of the run spec's groups (site, state, mdp, agent, network, train) and the
    seed, what every command reads; returns the agent's registry entry."""
    from .agents.registry import get_agent, sync_agents  # the builders: torch, TorchRL

    check_name("site.name", cfg.site.name)  # a part of run folders and policy names
    cfg.site.validate()
    cfg.state.validate()
    cfg.mdp.validate()
    check_choice("agent.name", getattr(cfg.agent, "name", None), tuple(sync_agents()))
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
    if cfg.train.defer != "none":
        from .agents.imitation import defers_on

        if not spec.policy_class.can_defer:
            raise ConfigError(f"train.defer={cfg.train.defer!r} is invalid for agent={spec.name}: "
                              "allowed none (a policy defers where a classifier's logit is "
                              "near zero: agent=imitation)")
        if not defers_on(cfg.state.name):
            raise ConfigError(f"train.defer={cfg.train.defer!r} is invalid with state="
                              f"{cfg.state.name}: allowed none (the heuristic reads the partial "
                              "state's features: state=partial, partial_site or "
                              "partial_all_site)")
    check_range("seed", cfg.seed, 0, 2**32 - 1)
    return spec


def validate_experiments(cfg: Config, groups: frozenset[str]) -> None:
    """The recipes, and the groups of ``groups`` that name them or baselines: the table's,
    a sweep's (and its point's site), the maps'."""
    from .agents.registry import AGENTS

    baselines = tuple(n for n, s in AGENTS.items() if not s.trainable)
    validate_recipes(cfg.recipes, baselines)
    known = (*baselines, *cfg.recipes)
    if "table" in groups:
        cfg.table.validate(tuple(cfg.recipes))
    if "sweep" in groups:
        validate_sweep(cfg, known)
    if "maps" in groups:
        cfg.maps.validate(known)


def validate_sweep(cfg: Config, known: tuple[str, ...]) -> None:
    """A sweep's settings: its value against the point's site, its rows among ``known``
    policies, its specialists and distilled planner among the recipes."""
    if cfg.sweep.param == "n_vehicles":  # the point's site must hold its vehicles
        check_sweep_value("n_vehicles", cfg.sweep.value, cfg.site.n_nodes - 2)
    cfg.sweep.validate(known)
    for row, recipe in cfg.sweep.specialists.items():
        check_choice(f"sweep.specialists.{row}", recipe, tuple(cfg.recipes))
        check_point_recipe(f"sweep.specialists.{row}", recipe, cfg.recipes[recipe])
    if cfg.sweep.distil is not None:
        check_choice("sweep.distil", cfg.sweep.distil, tuple(cfg.recipes))
        if "agent=imitation" not in cfg.recipes[cfg.sweep.distil].overrides:
            raise ConfigError(f"sweep.distil={cfg.sweep.distil!r} is invalid: allowed a "
                              "recipe of agent=imitation (the planner distilled), or null")
        check_point_recipe("sweep.distil", cfg.sweep.distil, cfg.recipes[cfg.sweep.distil])


def check_point_recipe(path: str, name: str, recipe: Recipe) -> None:
    """A recipe a sweep trains on the point's own site (a specialist, the distilled
    planner) must not choose a site itself: the point's site would replace it unseen."""
    if recipe.bases:
        raise ConfigError(f"{path}={name!r} is invalid: its teacher plans over the table's "
                          f"policies of {', '.join(recipe.bases)} (recipe bases), which a "
                          "sweep point does not train; allowed a recipe without bases")
    o = recipe.site_override()
    if o is not None:
        raise ConfigError(f"{path}={name!r} is invalid: the recipe sets {o!r}, and a sweep "
                          "trains it on the point's own site; allowed a recipe without site "
                          "overrides (not a generalist's)")


def check_memory_needs(cfg: Config, trainable: bool,
                       groups: Iterable[str] = GROUPS) -> None:
    """Refuse, before anything is allocated, a setting whose allocation would not fit in
    this machine's memory (:mod:`fleet_torchrl.utils.resources`): a training's sites,
    network, replay buffer or search population (the agent's own estimate,
    ``AgentConfig.memory``; ``trainable``), an evaluation's simulations (a planner's futures
    included; ``eval`` in ``groups``), a benchmark's batches (``bench`` in ``groups``)."""
    from .env.encodings import get_encoding
    from .evaluation.config import eval_bytes
    from .sim import Site
    from .sim.config import site_bytes
    from .utils.resources import check_memory

    sb = site_bytes(cfg.site)
    per = cfg.agent.sites_per_simulation()
    sims = "the evaluation's simulations" + (f" ({per} sites in flight each, the planner's "
                                             "futures)" if per > 1 else "")
    needs = [("eval.n_sims", cfg.eval.n_sims, eval_bytes(sb, cfg.eval.n_sims, per), sims)] \
        if "eval" in groups else []
    if trainable:
        n_obs = get_encoding(cfg.state.name).size(Site(cfg.site))
        needs += cfg.agent.memory(cfg.network, n_obs, sb)
        needs.append(("train.eval_sims", cfg.train.eval_sims,
                      eval_bytes(sb, cfg.train.eval_sims), "the periodic evaluation"))
    for i, b in enumerate(cfg.bench.batches if "bench" in groups else ()):
        needs.append((f"bench.batches[{i}]", b, 3 * b * sb, "a benchmark batch of sites"))
    for setting, value, nbytes, what in needs:
        check_memory(setting, value, nbytes, what)


def compose_config(overrides: list[str] | tuple[str, ...] = (),
                   groups: Iterable[str] = GROUPS) -> Config:
    """The config that ``conf/config.yaml`` plus ``overrides`` composes to, validated for
    ``groups`` (:func:`validate`; default all).

    Works inside a running Hydra app (which has already initialised Hydra) and outside one.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    register_configs()
    if GlobalHydra.instance().is_initialized():
        return to_config(compose(config_name="config", overrides=list(overrides)), groups)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return to_config(compose(config_name="config", overrides=list(overrides)), groups)


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


@contextmanager
def unresolvable_as_config_errors() -> Iterator[None]:
    """What a composed config cannot become whatever runs it, as a one-line
    :class:`ConfigError` naming the setting: a group left without a value (``~agent``) and
    an interpolation of an unset environment variable (``${oc.env:NAME}``). Other
    interpolations (``${hydra:...}``, resolved where the job runs) raise as they are."""
    from omegaconf.errors import InterpolationResolutionError, MissingMandatoryValue

    try:
        yield
    except MissingMandatoryValue as e:
        key = getattr(e, "full_key", None) or "a setting"
        group = CONF_DIR / key.replace(".", "/")
        options = sorted(p.stem for p in group.glob("*.yaml")) if group.is_dir() else []
        allowed = (f"choose one of {', '.join(f'{key}={o}' for o in options)}" if options
                   else "give it a value")
        raise ConfigError(f"{key} has no value: {allowed}") from None
    except InterpolationResolutionError as e:
        import re

        m = re.search(r"Environment variable '([^']*)' not found", str(e))
        if m is None:
            raise
        key, name = getattr(e, "full_key", None) or "a setting", m.group(1)
        raise ConfigError(f"{key} refers to the environment variable {name}, which is not "
                          f"set: set it, or give a default (${{oc.env:{name},<default>}})"
                          ) from None


def to_config(cfg: DictConfig | Config, groups: Iterable[str] = GROUPS) -> Config:
    """Turn a composed Hydra config into dataclasses validated for ``groups``
    (:func:`validate`); a key the schema does not have (e.g. ``+site.pc=0.5``, a misspelt
    ``site.p_c``) is rejected, naming it."""
    if isinstance(cfg, DictConfig):
        cfg = typed_user_agent(cfg)
        bad = unknown_keys(cfg)
        if bad:
            raise ConfigError(bad[0])
    with deferred_validation(), unresolvable_as_config_errors():  # validated whole below,
        obj = OmegaConf.to_object(cfg) if isinstance(cfg, DictConfig) else cfg  # per field
    if not isinstance(obj, Config):  # composed without the schema (e.g. plain YAML in a test)
        raise ConfigError("config was not composed from the 'schema_config' schema")
    return validate(obj, groups)


def without_hydra(cfg: DictConfig) -> DictConfig:
    """A copy of a composed config without its ``hydra`` node (what Hydra hands a task),
    its schema kept."""
    import copy

    from omegaconf import open_dict, read_write

    task_cfg = copy.deepcopy(cfg)
    with read_write(task_cfg), open_dict(task_cfg):
        del task_cfg["hydra"]
    return task_cfg


def to_tool_config(cfg: DictConfig, schema: type) -> Any:
    """A file tool's composed config (``conf/report.yaml``, ``tool_conf/compare.yaml``, ...)
    as its validated dataclass."""
    bad = unknown_keys(cfg)
    if bad:
        raise ConfigError(bad[0])
    with deferred_validation():
        obj = OmegaConf.to_object(cfg)
    if not isinstance(obj, schema):
        raise ConfigError(f"config was not composed from the 'schema_...' of {schema.__name__}")
    validate_tool = getattr(obj, "validate", None)
    return validate_tool() if validate_tool is not None else obj


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
    msg = " ".join(head).rstrip(":").replace(" ; ", "; ")
    if options:
        msg += f": {', '.join(options)}"
    if exc.__cause__ is not None and str(exc.__cause__).strip():
        msg += f": {str(exc.__cause__).strip().splitlines()[0]}"
    return msg or type(exc).__name__


__all__ = ["CONF_DIR", "GROUPS", "TOOL_SCHEMAS", "Config", "ConfigError", "compose_config",
           "register_configs", "to_config", "to_tool_config", "validate"]
