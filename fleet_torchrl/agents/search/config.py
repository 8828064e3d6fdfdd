"""The schema of the direct policy search (``agent=search``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from ...utils.checks import ConfigError, check_choice, check_range
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
    policy_class: str = "table"  # table (cells) | threshold (six thresholds) | mlp (a network)
    population: int = 64  # candidates per generation
    elite: int = 8  # candidates the distribution moves towards
    sites: int = 64  # sites per candidate and generation (the same sites for all)
    ticks: int = 3000  # ticks per site and generation
    generations: int = 100  # rounds of the training loop
    smoothing: float = 0.5  # step towards the elite: new = (1 - s) old + s elite
    elitist: bool = False  # true: only elite candidates that beat the mode (candidate 0) count
    init: str = "heuristic"  # starting policy: rule | heuristic | threshold | uniform | a
    # saved policy's path (table: its actions; threshold: its thresholds; mlp: a clone of it)
    p_min: float = 0.15  # table: charge probabilities stay in [p_min, 1 - p_min]
    tc_bins: int = 2  # table: charger bins (free, then tc_bins - 1 shares of its busy time)
    hidden: int = 16  # mlp: units per hidden layer
    depth: int = 2  # mlp: hidden layers
    sigma_init: float | None = None  # mlp (default 1.0) / threshold (0.1): initial std dev
    sigma_min: float = 0.02  # mlp / threshold: standard deviations stay at least this
    num_sites: int = 1  # sites of the training loop's environment (the search runs its own)
    policy: str | None = None  # saved policy for evaluation (default results/policies/search)

    def validate(self, cfg: Any = None, path: str = "agent") -> SearchAgentConfig:
        check_choice(f"{path}.policy_class", self.policy_class, POLICY_CLASSES)
        check_range(f"{path}.population", self.population, 2, 100_000)
        check_range(f"{path}.elite", self.elite, 1, self.population - 1,
                    allowed=f"[1, population - 1 = {self.population - 1}]")
        check_range(f"{path}.sites", self.sites, 1, 1_000_000)
        check_range(f"{path}.ticks", self.ticks, 1, 10**8)
        check_range(f"{path}.generations", self.generations, 1, 1_000_000)
        check_range(f"{path}.smoothing", self.smoothing, 1e-6, 1.0, allowed="(0, 1]")
        if self.init not in INITS:  # a saved policy (file or folder) on the partial state
            from pathlib import Path

            p = Path(self.init)
            if not (p.is_file() or (p / "policy.pt").is_file()):
                raise ConfigError(f"{path}.init={self.init!r} is invalid: allowed one of "
                                  f"{', '.join(INITS)} or the path of a saved policy "
                                  "(policy.pt or its folder) that exists")
        check_range(f"{path}.p_min", self.p_min, 0.0, 0.49, allowed="[0, 0.49]")
        check_range(f"{path}.tc_bins", self.tc_bins, 2, 64)
        check_range(f"{path}.hidden", self.hidden, 1, 4096)
        check_range(f"{path}.depth", self.depth, 0, 16)
        check_range(f"{path}.sigma_init", self.initial_sigma, 1e-6, 100.0)
        check_range(f"{path}.sigma_min", self.sigma_min, 0.0, self.initial_sigma,
                    allowed=f"[0, sigma_init = {self.initial_sigma}]")
        check_range(f"{path}.num_sites", self.num_sites, 1, 1_000_000)
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
