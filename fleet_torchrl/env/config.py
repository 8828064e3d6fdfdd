"""Schemas of the decision process (MODEL §2): the state encoding and the MDP's reward."""

from __future__ import annotations

from dataclasses import dataclass

from ..utils.checks import check_choice, check_range


@dataclass
class StateConfig:
    """State encoding seen by the agents (MODEL §2): ``partial`` (3 features) or ``all``."""

    name: str = "partial"

    def validate(self, path: str = "state") -> StateConfig:
        from .encodings import ENCODINGS

        check_choice(f"{path}.name", self.name, tuple(ENCODINGS))
        return self


@dataclass
class MDPConfig:
    """The decision process of MODEL §2."""

    tau_e: int = 3000  # episode tick budget (truncation)
    p_f: float = 50.0  # cost of a failure tick
    p_q: float = 1.0  # cost of a queue tick
    gamma: float = 0.9  # discount
    r_trip: float = 0.0  # reward per completed trip; 0 = MODEL §2 (an extension, see docs)

    def validate(self, path: str = "mdp") -> MDPConfig:
        check_range(f"{path}.tau_e", self.tau_e, 1, 10**9)
        check_range(f"{path}.p_f", self.p_f, 0.0, None)
        check_range(f"{path}.p_q", self.p_q, 0.0, None)
        check_range(f"{path}.gamma", self.gamma, 0.0, 1.0)
        check_range(f"{path}.r_trip", self.r_trip, 0.0, None)
        return self
