"""Schemas of the decision process (MODEL §2): the state encoding and the MDP's reward."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..utils.checks import Schema, coerce_schema, ranged


def _encodings() -> tuple[str, ...]:
    """The state encodings' names (torch: imported when a state is checked, not when the
    schema is)."""
    from .encodings import ENCODINGS

    return tuple(ENCODINGS)


def _objectives() -> tuple[str, ...]:
    """The objectives' names (numpy and torch: not for composing a config)."""
    from .objectives import OBJECTIVES

    return tuple(OBJECTIVES)


@dataclass
class StateConfig(Schema):
    """State encoding seen by the agents (MODEL §2): ``partial`` (3 features) or ``all``."""

    PATH: ClassVar[str] = "state"

    name: str = ranged("partial", choices=_encodings)



@dataclass
class MDPConfig(Schema):
    """The decision process of MODEL §2 and its two objectives (``reward``)."""

    PATH: ClassVar[str] = "mdp"

    tau_e: int = ranged(3000, 1, 10**9)  # episode tick budget (truncation)
    # thesis (MODEL §2.2) | throughput (trips, semi-Markov, MODEL §2.3)
    reward: str = ranged("thesis", choices=_objectives)
    # the cost of a failure tick (both objectives) and of a queue tick (thesis); rewards are
    # float32: a cost beyond 1e9 (squared in a TD loss) overflows to inf
    p_f: float = ranged(50.0, 0.0, 1e9, allowed="[0, 1e9] (rewards are float32)")
    p_q: float = ranged(1.0, 0.0, 1e9, allowed="[0, 1e9] (rewards are float32)")
    gamma: float = ranged(0.9, 0.0, 1.0)  # discount per decision (thesis)
    # discount per tick (throughput): gamma_tick^dt per step
    gamma_tick: float = ranged(0.998, 0.0, 1.0)
    # reference trips per tick subtracted every tick (throughput)
    rho: float = ranged(0.115, 0.0, 1.0)


    @classmethod
    def coerce(cls, value: MDPConfig | dict | None, path: str = "mdp") -> MDPConfig:
        """``value`` as a validated decision process: an :class:`MDPConfig` (checked as it
        stands), a dict of its fields, or None (the defaults)."""
        return coerce_schema(cls, value, path)

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
