"""The schema of the planner's distillation (``agent=imitation``)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ...utils.checks import check_range, ranged
from ..planner.config import BASELINE_BASES, PlannerAgentConfig
from ..schema import AgentConfig, Need, neutral

LABEL_WEIGHTS = ("uniform", "gap", "site_gap")  # imitation: how a label weighs in the loss


@dataclass
class ImitationAgentConfig(AgentConfig):
    """DAgger distillation of the rollout planner (agents/imitation/learner.py)."""

    name: str = "imitation"
    policy_type: ClassVar[str] = "fleet_torchrl.agents.imitation.learner:ImitationPolicy"
    learner_type: ClassVar[str] = "fleet_torchrl.agents.imitation.learner:ImitationLearner"
    states: ClassVar[tuple[str, ...] | None] = ("partial", "partial_site", "all", "all_site",
                                          "partial_all_site")
    # sites in parallel: one environment step = num_sites labels
    num_sites: int = ranged(256, 1, 1_000_000)
    # decisions per site and round (episodes run on across rounds)
    steps_per_round: int = ranged(20, 1, 1_000_000)
    # rounds of the training loop (train.max_episodes does not apply)
    rounds: int = ranged(40, 1, 1_000_000)
    expert: PlannerAgentConfig = field(default_factory=PlannerAgentConfig)  # the teacher
    beta_start: float = ranged(1.0, 0.0, 1.0)  # probability of acting with the expert in round 0
    beta_end: float = 0.0  # ... falling linearly to this
    # ... over this many rounds (then it stays at beta_end)
    beta_rounds: int = ranged(5, 1, 1_000_000)
    # expert iteration: from this round on (>= 1) the teacher is the planner over the student
    # as it stood when the round began; 0 = never (neutral: runs saved before it keep their
    # training fingerprint)
    iterate_from: int = field(default=0, metadata={"neutral": 0})
    # labelled states kept (all rounds aggregated; oldest go first)
    capacity: int = ranged(500_000, 1, 100_000_000)
    hidden: int = ranged(128, 1, 4096)  # units per hidden layer of the student network
    depth: int = ranged(3, 0, 16)  # hidden layers (ReLU)
    lr: float = ranged(1e-3, 1e-12, 1.0, allowed="(0, 1]")  # Adam learning rate
    # cosine decay of lr over the run's gradient steps to this share
    lr_final: float = ranged(1.0, 0.0, 1.0)
    weight_decay: float = ranged(0.0, 0.0, 10.0)  # Adam L2
    updates_per_round: int = ranged(200, 0, 1_000_000)  # gradient steps after each round
    batch_size: int = 512  # pairs per gradient step
    # the weight of a label in the loss: "uniform" (1 each) or "gap" (the planner's estimated
    # difference between the two actions' scores, capped at gap_cap: cost-sensitive
    # imitation, AggreVaTe-style) or "site_gap" (the same over the mean of the round's pairs
    # from the same site: each site keeps its share of the loss); neutral, so runs saved
    # before it keep their fingerprint
    label_weight: str = neutral(ranged("uniform", choices=LABEL_WEIGHTS), "uniform")
    gap_cap: float = neutral(ranged(1.0, 1e-12, 1e6, allowed="(0, 1e6]"), 1.0)  # trips, (0, 1e6]
    gap_floor: float = field(default=0.0, metadata={"neutral": 0.0})  # trips, [0, gap_cap]
    policy: str | None = None  # saved policy for evaluation (default results/policies/<name>)

    def validate(self, cfg: Any = None, path: str = "agent") -> ImitationAgentConfig:
        super().validate(cfg, path)
        self.expert.validate(cfg, f"{path}.expert")
        check_range(f"{path}.beta_end", self.beta_end, 0.0, self.beta_start,
                    allowed=f"[0, beta_start = {self.beta_start}]")
        check_range(f"{path}.iterate_from", self.iterate_from, 0, self.rounds,
                    allowed=f"0 (never) or [1, rounds = {self.rounds}]")
        check_range(f"{path}.batch_size", self.batch_size, 1, self.capacity,
                    allowed=f"[1, capacity = {self.capacity}]")
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
