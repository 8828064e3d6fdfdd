"""Every agent's schema by name, free of torch: the package's own and those from outside.

Each agent's schema sits beside its implementation (``agents/<agent>/config.py``, on the base
in ``agents/schema.py``); this module collects them so that composing a config (``--help``,
tab completion, Hydra's ConfigStore) imports neither torch nor TorchRL. An agent from
outside the package joins through the entry-point group :data:`ENTRY_POINT_GROUP` (each
entry point names a schema class, its name the agent's) or through :func:`add_schema` (a
user's ``conf/agent/<x>.yaml`` naming its class in ``_schema_``,
:func:`fleet_torchrl.config.register_configs`). docs/ADD_A_POLICY.md says how.
"""

from __future__ import annotations

from dataclasses import MISSING, fields

from ..utils.checks import ConfigError
from .baselines.config import HeuristicAgentConfig, RuleAgentConfig
from .dqn.config import ANCHOR_STATES, ANCHORS, LR_DECAYS, DQNAgentConfig, NetworkConfig
from .imitation.config import LABEL_WEIGHTS, ImitationAgentConfig
from .planner.config import BASELINE_BASES, OTHER_UNDER, PlannerAgentConfig
from .schema import AgentConfig, Need, import_object, transition_bytes
from .search.config import INITS, POLICY_CLASSES, SearchAgentConfig
from .tabular.config import TabularAgentConfig
from .threshold.config import ThresholdAgentConfig

ENTRY_POINT_GROUP = "fleet_torchrl.agents"  # entry points naming agent schemas

# the package's own agents, by name (registered here, not through the package's metadata)
BUILTIN_SCHEMAS: dict[str, type[AgentConfig]] = {
    "rule": RuleAgentConfig, "heuristic": HeuristicAgentConfig,
    "threshold": ThresholdAgentConfig, "planner": PlannerAgentConfig,
    "tabular": TabularAgentConfig, "dqn": DQNAgentConfig, "search": SearchAgentConfig,
    "imitation": ImitationAgentConfig}

# agent name -> its schema: the package's own, then those added (entry points, user configs)
AGENT_SCHEMAS: dict[str, type[AgentConfig]] = dict(BUILTIN_SCHEMAS)


def schema_name(schema: type) -> str:
    """The agent name a schema declares: its ``name`` field's default."""
    default = {f.name: f.default for f in fields(schema)}.get("name", MISSING)
    return default if isinstance(default, str) else ""


def add_schema(schema: object, where: str) -> str:
    """Add an agent's schema (a dataclass extending :class:`AgentConfig` whose ``name``
    default names the agent and whose ``policy_type`` names its policy class); returns the
    name. ``where`` says where it came from, for the one-line :class:`ConfigError` that
    refuses a schema that is not one or would replace another agent's."""
    if not (isinstance(schema, type) and issubclass(schema, AgentConfig)):
        raise ConfigError(f"{where} is invalid: allowed a dataclass extending "
                          "fleet_torchrl.agents.AgentConfig (the agent's schema), not "
                          f"{schema!r:.80}")
    name = schema_name(schema)
    if not name.isidentifier() or not schema.policy_type:
        raise ConfigError(f"{where} is invalid: {schema.__name__} must give its `name` field "
                          "a default (the agent's name, a Python identifier) and set "
                          "`policy_type` ('module:Class' of its policy)")
    known = AGENT_SCHEMAS.get(name)
    if known is not None and known is not schema:
        raise ConfigError(f"{where} is invalid: agent {name!r} is already "
                          f"{known.__module__}.{known.__qualname__}; give "
                          f"{schema.__name__} another name")
    AGENT_SCHEMAS[name] = schema
    return name


def load_entry_points() -> list[str]:
    """Add the schemas of the installed entry-point group :data:`ENTRY_POINT_GROUP`
    (``name = "module:SchemaClass"``), once per process; returns their names. An entry
    point that cannot be imported, or names no schema of its own name, raises
    :class:`ConfigError` naming it."""
    from importlib.metadata import entry_points

    if _LOADED:
        return list(_LOADED[0])
    names = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        where = f"the entry point {ep.name} = {ep.value} (group {ENTRY_POINT_GROUP})"
        try:
            schema = ep.load()
        except Exception as e:  # noqa: BLE001 (any error of someone else's import)
            raise ConfigError(f"{where} cannot be imported: {type(e).__name__}: "
                              f"{str(e).splitlines()[0] if str(e) else ''}; fix or "
                              "uninstall its package") from None
        if BUILTIN_SCHEMAS.get(ep.name) is schema:
            continue  # the package's own, installed with entry points too
        name = add_schema(schema, where)
        if name != ep.name:
            raise ConfigError(f"{where} is invalid: its schema's name is {name!r}; allowed "
                              "an entry point named as the agent")
        names.append(name)
    _LOADED.append(names)
    return names


_LOADED: list[list[str]] = []  # the entry points' names, once read


__all__ = ["AGENT_SCHEMAS", "ANCHORS", "ANCHOR_STATES", "BASELINE_BASES", "BUILTIN_SCHEMAS",
           "ENTRY_POINT_GROUP", "INITS", "LABEL_WEIGHTS", "LR_DECAYS", "OTHER_UNDER",
           "POLICY_CLASSES", "AgentConfig", "DQNAgentConfig", "HeuristicAgentConfig",
           "ImitationAgentConfig", "Need", "NetworkConfig", "PlannerAgentConfig",
           "RuleAgentConfig", "SearchAgentConfig", "TabularAgentConfig", "ThresholdAgentConfig",
           "add_schema", "import_object", "load_entry_points", "schema_name",
           "transition_bytes"]
