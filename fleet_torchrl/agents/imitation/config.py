"""The schema of the planner's distillation (``agent=imitation``)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ...utils.checks import check_choice, check_range
from ..planner.config import BASELINE_BASES, PlannerAgentConfig
from ..schema import AgentConfig, Need

LABEL_WEIGHTS = ("uniform", "gap", "site_gap")  # imitation: how a label weighs in the loss


@dataclass
class ImitationAgentConfig(AgentConfig):
    """DAgger distillation of the rollout planner (agents/imitation/learner.py)."""

    name: str = "imitation"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.imitation.learner:ImitationPolicy"
    learner_type: ClassVar[str] = "fleet_torchrl.agents.imitation.learner:ImitationLearner"
    states: ClassVar[tuple[str, ...] | None] = ("partial", "partial_site", "all", "all_site",
                                          "partial_all_site")
    num_sites: int = 256  # sites in parallel: one environment step = num_sites labels
    steps_per_round: int = 20  # decisions per site and round (episodes run on across rounds)
    rounds: int = 40  # rounds of the training loop (train.max_episodes does not apply)
    expert: PlannerAgentConfig = field(default_factory=PlannerAgentConfig)  # the teacher
    beta_start: float = 1.0  # probability of acting with the expert in round 0
    beta_end: float = 0.0  # ... falling linearly to this
    beta_rounds: int = 5  # ... over this many rounds (then it stays at beta_end)
    # expert iteration: from this round on (>= 1) the teacher is the planner over the student
    # as it stood when the round began; 0 = never (neutral: runs saved before it keep their
    # training fingerprint)
    iterate_from: int = field(default=0, metadata={"neutral": 0})
    capacity: int = 500_000  # labelled states kept (all rounds aggregated; oldest go first)
    hidden: int = 128  # units per hidden layer of the student network
    depth: int = 3  # hidden layers (ReLU)
    lr: float = 1e-3  # Adam learning rate
    lr_final: float = 1.0  # cosine decay of lr over the run's gradient steps to this share
    weight_decay: float = 0.0  # Adam L2
    updates_per_round: int = 200  # gradient steps after each round
    batch_size: int = 512  # pairs per gradient step
    # the weight of a label in the loss: "uniform" (1 each) or "gap" (the planner's estimated
    # difference between the two actions' scores, capped at gap_cap: cost-sensitive
    # imitation, AggreVaTe-style) or "site_gap" (the same over the mean of the round's pairs
    # from the same site: each site keeps its share of the loss); neutral, so runs saved
    # before it keep their fingerprint
    label_weight: str = field(default="uniform", metadata={"neutral": "uniform"})
    gap_cap: float = field(default=1.0, metadata={"neutral": 1.0})  # trips, (0, 1e6]
    gap_floor: float = field(default=0.0, metadata={"neutral": 0.0})  # trips, [0, gap_cap]
    policy: str | None = None  # saved policy for evaluation (default results/policies/<name>)

    def validate(self, cfg: Any = None, path: str = "agent") -> ImitationAgentConfig:
        check_range(f"{path}.num_sites", self.num_sites, 1, 1_000_000)
        check_range(f"{path}.steps_per_round", self.steps_per_round, 1, 1_000_000)
        check_range(f"{path}.rounds", self.rounds, 1, 1_000_000)
        self.expert.validate(cfg, f"{path}.expert")
        check_range(f"{path}.beta_start", self.beta_start, 0.0, 1.0)
        check_range(f"{path}.beta_end", self.beta_end, 0.0, self.beta_start,
                    allowed=f"[0, beta_start = {self.beta_start}]")
        check_range(f"{path}.beta_rounds", self.beta_rounds, 1, 1_000_000)
        check_range(f"{path}.iterate_from", self.iterate_from, 0, self.rounds,
                    allowed=f"0 (never) or [1, rounds = {self.rounds}]")
        check_range(f"{path}.capacity", self.capacity, 1, 100_000_000)
        check_range(f"{path}.hidden", self.hidden, 1, 4096)
        check_range(f"{path}.depth", self.depth, 0, 16)
        check_range(f"{path}.lr", self.lr, 1e-12, 1.0, allowed="(0, 1]")
        check_range(f"{path}.lr_final", self.lr_final, 0.0, 1.0)
        check_range(f"{path}.weight_decay", self.weight_decay, 0.0, 10.0)
        check_range(f"{path}.updates_per_round", self.updates_per_round, 0, 1_000_000)
        check_range(f"{path}.batch_size", self.batch_size, 1, self.capacity,
                    allowed=f"[1, capacity = {self.capacity}]")
        check_choice(f"{path}.label_weight", self.label_weight, LABEL_WEIGHTS)
        check_range(f"{path}.gap_cap", self.gap_cap, 1e-12, 1e6, allowed="(0, 1e6]")
        check_range(f"{path}.gap_floor", self.gap_floor, 0.0, self.gap_cap,
                    allowed=f"[0, gap_cap = {self.gap_cap}]")
        return self

    def memory(self, network: Any, n_obs: int, site_bytes: int) -> list[Need]:
        futures = self.num_sites * self.expert.sites_per_simulation()
        weights = 4 * 4 * ((n_obs + 1) * self.hidden + self.depth * (self.hidden + 1)
                           * self.hidden) + 4 * 4 * self.batch_size * self.hidden * self.depth
        return [("agent.num_sites", self.num_sites, futures * site_bytes,
                 f"the sites and the expert's futures (agent.expert.rollouts="
                 f"{self.expert.rollouts})"),
                ("agent.capacity", self.capacity, self.capacity * (4 * n_obs + 64),
                 "the labelled states kept"),
                ("agent.hidden", self.hidden, weights, f"the student (agent.depth={self.depth})")]

    def beta(self, round_idx: int) -> float:
        """Probability of acting with the expert in round ``round_idx`` (0-based)."""
        frac = min(round_idx / self.beta_rounds, 1.0)
        return self.beta_start + (self.beta_end - self.beta_start) * frac

    def training_rounds(self, train: Any) -> int:
        return self.rounds

    def objective(self, mdp: Any) -> str:
        return "trips"  # the planner maximises trips, whatever mdp.reward says

    def run_suffix(self, mdp: Any) -> str:
        """Nothing for the default teacher (the planner over the heuristic); ``_over_<base>``
        for another base (a saved policy: ``_over_policy-<8 hex digits of its path>``); for
        several (``expert.bases``) ``_over_bases-<8 hex digits of their names>``."""
        base = self.expert.base
        if self.expert.bases:  # parallel rollout: the hash of every base's name or path
            names = "\n".join(self.expert.all_bases())
            return f"_over_bases-{hashlib.sha256(names.encode()).hexdigest()[:8]}"
        if base == "heuristic":
            return ""
        if base in BASELINE_BASES:
            return f"_over_{base}"
        return f"_over_policy-{hashlib.sha256(base.encode()).hexdigest()[:8]}"
