"""The schema of the direct policy search (``agent=search``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from ...utils.checks import ConfigError, check_range, ranged
from ..schema import AgentConfig, Need

POLICY_CLASSES = ("table", "mlp", "threshold")
INITS = ("rule", "heuristic", "threshold", "uniform")


@dataclass
class SearchAgentConfig(AgentConfig):
    """Direct policy search by the cross-entropy method (see the module docstring)."""

    name: str = "search"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.search.learner:SearchPolicy"
    learner_type: ClassVar[str] = "fleet_torchrl.agents.search.learner:SearchLearner"
    states: ClassVar[tuple[str, ...] | None] = ("partial",)
    # table (cells) | threshold (six thresholds) | mlp (a network)
    policy_class: str = ranged("table", choices=POLICY_CLASSES)
    population: int = ranged(64, 2, 100_000)  # candidates per generation
    elite: int = 8  # candidates the distribution moves towards
    # sites per candidate and generation (the same sites for all)
    sites: int = ranged(64, 1, 1_000_000)
    ticks: int = ranged(3000, 1, 10**8)  # ticks per site and generation
    generations: int = ranged(100, 1, 1_000_000)  # rounds of the training loop
    # step towards the elite: new = (1 - s) old + s elite
    smoothing: float = ranged(0.5, 1e-6, 1.0, allowed="(0, 1]")
    elitist: bool = False  # true: only elite candidates that beat the mode (candidate 0) count
    init: str = "heuristic"  # starting policy: rule | heuristic | threshold | uniform | a
    # saved policy's path (table: its actions; threshold: its thresholds; mlp: a clone of it)
    # table: charge probabilities stay in [p_min, 1 - p_min]
    p_min: float = ranged(0.15, 0.0, 0.49, allowed="[0, 0.49]")
    # table: charger bins (free, then tc_bins - 1 shares of its busy time)
    tc_bins: int = ranged(2, 2, 64)
    hidden: int = ranged(16, 1, 4096)  # mlp: units per hidden layer
    depth: int = ranged(2, 0, 16)  # mlp: hidden layers
    sigma_init: float | None = None  # mlp (default 1.0) / threshold (0.1): initial std dev
    sigma_min: float = 0.02  # mlp / threshold: standard deviations stay at least this
    # sites of the training loop's environment (the search runs its own)
    num_sites: int = ranged(1, 1, 1_000_000)
    policy: str | None = None  # saved policy for evaluation (default results/policies/search)

    def validate(self, cfg: Any = None, path: str = "agent") -> SearchAgentConfig:
        super().validate(cfg, path)
        check_range(f"{path}.elite", self.elite, 1, self.population - 1,
                    allowed=f"[1, population - 1 = {self.population - 1}]")
        if self.init not in INITS:  # a saved policy (file or folder) on the partial state
            from pathlib import Path

            p = Path(self.init)
            if not (p.is_file() or (p / "policy.pt").is_file()):
                raise ConfigError(f"{path}.init={self.init!r} is invalid: allowed one of "
                                  f"{', '.join(INITS)} or the path of a saved policy "
                                  "(policy.pt or its folder) that exists")
        check_range(f"{path}.sigma_init", self.initial_sigma, 1e-6, 100.0)
        check_range(f"{path}.sigma_min", self.sigma_min, 0.0, self.initial_sigma,
                    allowed=f"[0, sigma_init = {self.initial_sigma}]")
        return self

    @property
    def initial_sigma(self) -> float:
        """``sigma_init``, or the class's default (threshold 0.1, mlp 1.0)."""
        if self.sigma_init is not None:
            return float(self.sigma_init)
        return 0.1 if self.policy_class == "threshold" else 1.0

    def training_rounds(self, train: Any) -> int:
        return self.generations

    def memory(self, network: Any, n_obs: int, site_bytes: int) -> list[Need]:
        n = self.population * self.sites  # one generation is one batched simulation
        act = 4 * self.hidden * (self.depth + 1) if self.policy_class == "mlp" else 0
        return [("agent.population", self.population, n * (site_bytes + act + 64),
                 f"a generation of agent.sites={self.sites} sites per candidate, simulated "
                 "at once")]

    def objective(self, mdp: Any) -> str:
        return "trips"  # the search maximises mean trips directly, whatever mdp.reward says

    def run_suffix(self, mdp: Any) -> str:
        if self.policy_class == "table":
            return "" if self.tc_bins == 2 else f"_tc{self.tc_bins}"
        return f"_{self.policy_class}"
