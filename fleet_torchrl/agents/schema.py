"""The base of every ``agent`` schema, free of torch.

Each agent's schema sits beside its implementation (``agents/<agent>/config.py``) and names
its policy class (and a learner's class) as ``"module:Class"``, imported on first use
(:meth:`AgentConfig.associated_class`): composing a config (``--help``, tab completion,
Hydra's ConfigStore) imports neither torch nor TorchRL.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ..utils.checks import ConfigError, check_fields, validate_on_init

Need = tuple  # (setting, value, bytes, what): one allocation a setting sizes


def transition_bytes(n_obs: int) -> int:
    """One stored transition of a replay buffer (observation and next observation, action,
    reward, flags, counters, discount exponent), on the high side."""
    return 8 * n_obs + 256


@dataclass
class AgentConfig:
    """Base schema of the ``agent`` group; each agent extends it with its own fields.

    What an agent is, besides its fields, is declared on its schema class (class variables,
    not settings): ``policy_type`` names its policy class and ``learner_type`` a learner's
    class, each as ``"module:Class"`` and imported only when the agent is built; ``states``
    the state encodings it accepts (``None``: any). A baseline (no ``learner_type``) is built by
    ``Policy.from_agent(config)``; a learner by ``Learner.from_context(context)`` and its
    policies are loaded from files.
    """

    name: str = ""
    policy_type: ClassVar[str] = ""  # its policy class, "module:Class"
    learner_type: ClassVar[str] = ""  # a learner's class, "module:Class"; "" for a baseline
    states: ClassVar[tuple[str, ...] | None] = None  # the encodings it accepts; None: any

    @classmethod
    def associated_class(cls) -> type:
        """The agent's policy class (imported here, on first use: it needs torch)."""
        return import_object(cls.policy_type, f"{cls.__name__}.policy_type")

    @classmethod
    def learner_class(cls) -> type | None:
        """A learner's class (imported on first use), ``None`` for a baseline."""
        if not cls.learner_type:
            return None
        return import_object(cls.learner_type, f"{cls.__name__}.learner_type")

    @classmethod
    def trainable(cls) -> bool:
        return bool(cls.learner_type)

    def __post_init__(self) -> None:
        validate_on_init(self)  # every agent's own fields (cross-checks need ``cfg``)

    def validate(self, cfg: Any = None, path: str = "agent") -> AgentConfig:
        """Check this agent's fields: every range declared on a field
        (:func:`~fleet_torchrl.utils.checks.ranged`); an agent with cross-field checks
        (``cfg``: the whole config, duck-typed, such as the state the agent reads) makes them
        after ``super().validate(cfg, path)``."""
        check_fields(self, path)
        return self

    def objective(self, mdp: Any) -> str:
        """The objective this agent's policies are trained for (the table's column)."""
        return mdp.reward

    def sites_per_simulation(self) -> int:
        """Sites in flight per simulated site when this agent decides (a planner's futures
        are sites too): what an evaluation's memory scales with."""
        return 1

    def memory(self, network: Any, n_obs: int, site_bytes: int) -> list[Need]:
        """What a training of this agent allocates, each as ``(setting, value, bytes,
        what)`` of the setting that sizes it (checked against the machine's memory before
        anything is allocated: :func:`fleet_torchrl.utils.resources.check_memory`)."""
        n = getattr(self, "num_sites", 1)
        return [("agent.num_sites", n, n * site_bytes, "the training environment's sites")]

    def run_suffix(self, mdp: Any) -> str:
        """What a run's policy name adds to the agent's: the objective unless it is the
        thesis's (``tabular_throughput``)."""
        return "" if mdp.reward == "thesis" else f"_{mdp.reward}"

    def training_rounds(self, train: Any) -> int:
        """Rounds of the training loop: ``train.max_episodes`` episodes, one per site and round
        (a learner with another budget overrides this)."""
        return math.ceil(train.max_episodes / self.num_sites)  # type: ignore[attr-defined]


def neutral(f: Any, value: Any) -> Any:
    """The dataclass field ``f`` (a :func:`~fleet_torchrl.utils.checks.ranged` one) marked
    neutral at ``value``: a setting added after runs were saved, which leaves their training
    fingerprint as it was while it keeps that value."""
    return field(default=f.default, default_factory=f.default_factory,
                 metadata={**f.metadata, "neutral": value})


def import_object(target: str, what: str = "target") -> Any:
    """The object ``target`` (``"module:attribute"`` or ``"module.attribute"``) names;
    :class:`ConfigError` with one line when it cannot be imported."""
    module, sep, attr = target.partition(":")
    if not sep:
        module, _, attr = target.rpartition(".")
    if not module or not attr:
        raise ConfigError(f"{what}={target!r} is invalid: allowed 'module:Class' (an "
                          "importable module and a class in it)")
    try:
        obj = importlib.import_module(module)
        for part in attr.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as e:
        raise ConfigError(f"{what}={target!r} cannot be imported: {e}") from None
    return obj
