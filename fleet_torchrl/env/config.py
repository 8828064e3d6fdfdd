"""Schemas of the decision process (MODEL §2): the state encoding and the MDP's reward."""

from __future__ import annotations

from dataclasses import dataclass

from ..utils.checks import (
    ConfigError,
    check_choice,
    check_known_fields,
    check_range,
    validate_on_init,
)


@dataclass
class StateConfig:
    """State encoding seen by the agents (MODEL §2): ``partial`` (3 features) or ``all``."""

    name: str = "partial"

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "state") -> StateConfig:
        from .encodings import ENCODINGS

        check_choice(f"{path}.name", self.name, tuple(ENCODINGS))
        return self


@dataclass
class MDPConfig:
    """The decision process of MODEL §2 and its two objectives (``reward``)."""

    tau_e: int = 3000  # episode tick budget (truncation)
    reward: str = "thesis"  # thesis (MODEL §2.2) | throughput (trips, semi-Markov, MODEL §2.3)
    p_f: float = 50.0  # cost of a failure tick (both objectives)
    p_q: float = 1.0  # cost of a queue tick (thesis)
    gamma: float = 0.9  # discount per decision (thesis)
    gamma_tick: float = 0.998  # discount per tick (throughput): gamma_tick^dt per step
    rho: float = 0.115  # reference trips per tick subtracted every tick (throughput)

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "mdp") -> MDPConfig:
        from .objectives import OBJECTIVES  # numpy and torch: not for composing a config

        check_range(f"{path}.tau_e", self.tau_e, 1, 10**9)
        check_choice(f"{path}.reward", self.reward, tuple(OBJECTIVES))
        # rewards are float32: a cost beyond 1e9 (squared in a TD loss) overflows to inf
        check_range(f"{path}.p_f", self.p_f, 0.0, 1e9, allowed="[0, 1e9] (rewards are float32)")
        check_range(f"{path}.p_q", self.p_q, 0.0, 1e9, allowed="[0, 1e9] (rewards are float32)")
        check_range(f"{path}.gamma", self.gamma, 0.0, 1.0)
        check_range(f"{path}.gamma_tick", self.gamma_tick, 0.0, 1.0)
        check_range(f"{path}.rho", self.rho, 0.0, 1.0)
        return self

    @classmethod
    def coerce(cls, value: MDPConfig | dict | None, path: str = "mdp") -> MDPConfig:
        """``value`` as a validated decision process: an :class:`MDPConfig` (checked as it
        stands), a dict of its fields, or None (the defaults)."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value.validate(path)
        if isinstance(value, dict):
            check_known_fields(cls, value, path)
            return cls(**value)
        raise ConfigError(f"{path}={value!r} is invalid: allowed an MDPConfig, a dict of its "
                          "fields, or None")

    @property
    def objective(self):
        """The :class:`~fleet_torchrl.env.objectives.Objective` that ``reward`` names."""
        from .objectives import get_objective

        return get_objective(self.reward)

    @property
    def discount(self) -> float:
        """The learners' discount base: per decision (thesis) or per tick (throughput); a
        transition is discounted by ``discount ** exponent`` (see
        :func:`fleet_torchrl.env.fleet_env.discount_exponent`)."""
        return self.objective.discount(self)
