"""The schema of the rollout planner (``agent=planner``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from ...utils.checks import ConfigError, ranged
from ..schema import AgentConfig, neutral

BASELINE_BASES = ("rule", "heuristic", "threshold")  # what a planner's base may name
# several bases: under which base the other action (not the reference's) is scored
OTHER_UNDER = ("best", "gated", "reference")


@dataclass
class PlannerAgentConfig(AgentConfig):
    """The rollout planner (``policy.py``); defaults from the study in docs/PLANNER.md."""

    name: str = "planner"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.planner.policy:PlannerPolicy"
    base: str = "heuristic"  # base policy: rule | heuristic | threshold | a saved policy path
    rollouts: int = ranged(32, 2, 4096)  # futures per action (K)
    horizon: int = ranged(200, 1, 1_000_000)  # ticks per future (H)
    # trips per unit of soc left in the fleet at the horizon
    energy_value: float = ranged(0.02, 0.0, 10.0)
    # standard errors by which the other action must score better
    confidence: float = ranged(1.5, 0.0, 100.0)
    seed: int = ranged(0, 0, 2**32 - 1)  # the planner's own random streams
    # more base policies (parallel rollout): each decision's futures run under every base; the
    # planner starts from `base` unless another base's own action is significantly better
    # there, and takes the other action where some base scores it significantly better;
    # [] = the one base (neutral: runs saved before it keep their training fingerprint)
    bases: list[str] = field(default_factory=list, metadata={"neutral": []})
    # several bases: the base the other action is scored under: the one scoring it best on
    # average (best), the reference's unless another scores it significantly better (gated),
    # or always the reference's (reference); neutral, so saved runs keep their fingerprint
    other_under: str = neutral(ranged("best", choices=OTHER_UNDER), "best")

    def validate(self, cfg: Any = None, path: str = "agent") -> PlannerAgentConfig:
        super().validate(cfg, path)
        _check_base(self.base, f"{path}.base")
        if len(self.bases) > 8:
            raise ConfigError(f"{path}.bases has {len(self.bases)} entries: allowed at most 8 "
                              "(each one adds the planner's futures once more)")
        for i, b in enumerate(self.bases):
            _check_base(b, f"{path}.bases[{i}]")
        return self

    def sites_per_simulation(self) -> int:
        # each deciding site imagines 2 x rollouts futures under each base
        return 1 + 2 * self.rollouts * (1 + len(self.bases))

    def all_bases(self) -> list[str]:
        return [self.base, *self.bases]


def _check_base(base: Any, path: str) -> None:
    """A planner's base: a baseline's name or a saved policy (its file or folder) that exists."""
    if base in BASELINE_BASES:
        return
    from pathlib import Path

    p = Path(str(base))
    if not isinstance(base, str) or not (p.is_file() or (p / "policy.pt").is_file()):
        raise ConfigError(f"{path}={base!r} is invalid: allowed one of "
                          f"{', '.join(BASELINE_BASES)} or the path of a saved policy "
                          "(policy.pt or its folder) that exists")
