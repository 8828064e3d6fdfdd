"""The ``agent`` and ``network`` schemas: every agent's settings, free of torch.

The schemas live here, apart from the policies and learners they configure (``baselines.py``,
``tabular.py``, ``dqn.py``, ``search.py``), so that composing a config (``--help``, tab
completion, Hydra's ConfigStore) imports neither torch nor TorchRL: a command answers
``--help`` in well under a second. :data:`AGENT_SCHEMAS` maps each agent name to its schema;
:func:`fleet_torchrl.agents.registry.register` adds a new agent's schema here too.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from typing import Any

from ..utils.checks import ConfigError, check_choice, check_range, validate_on_init

Need = tuple  # (setting, value, bytes, what): one allocation a setting sizes


def transition_bytes(n_obs: int) -> int:
    """One stored transition of a replay buffer (observation and next observation, action,
    reward, flags, counters, discount exponent), on the high side."""
    return 8 * n_obs + 256


@dataclass
class AgentConfig:
    """Base schema of the ``agent`` group; each agent extends it with its own fields."""

    name: str = ""

    def __post_init__(self) -> None:
        validate_on_init(self)  # every agent's own fields (cross-checks need ``cfg``)

    def validate(self, cfg: Any = None, path: str = "agent") -> AgentConfig:
        """Range checks of this agent's fields (``cfg``: the whole config, duck-typed, for
        cross-checks such as the state the agent reads)."""
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

@dataclass
class RuleAgentConfig(AgentConfig):
    """Benchmark: charge iff soc_D <= threshold."""

    name: str = "rule"
    threshold: float = 40.0

    def validate(self, cfg: Any = None, path: str = "agent") -> RuleAgentConfig:
        check_range(f"{path}.threshold", self.threshold, 0.0, 100.0)
        return self


@dataclass
class HeuristicAgentConfig(AgentConfig):
    """Queue-aware baseline: charge early when the charger is free and the vehicle at D is the
    emptiest one (and below ``upper``); otherwise follow the rule with ``threshold``."""

    name: str = "heuristic"
    threshold: float = 40.0
    upper: float = 60.0
    others_below: float = 100.0  # charge early only if another vehicle is this low; 100 = off

    def validate(self, cfg: Any = None, path: str = "agent") -> HeuristicAgentConfig:
        check_range(f"{path}.threshold", self.threshold, 0.0, 100.0)
        check_range(f"{path}.upper", self.upper, 0.0, 100.0)
        check_range(f"{path}.others_below", self.others_below, 0.0, 100.0)
        return self

@dataclass
class TabularAgentConfig(AgentConfig):
    """Tabular Q-learning on the discretised ``partial`` state (MODEL §3)."""

    name: str = "tabular"
    num_sites: int = 256  # sites simulated in parallel; one round = one episode per site
    k: float = 100.0  # learning rate k / (t + k), t = visits of the state-action pair
    eps_start: float = 1.0  # epsilon of the first episode
    eps_end: float = 0.3  # epsilon_min
    eps_decay_episodes: int = 20  # episodes (per site) over which epsilon decays to eps_end
    policy: str | None = None  # saved policy for evaluation (default results/policies/tabular)

    def validate(self, cfg: Any = None, path: str = "agent") -> TabularAgentConfig:
        check_range(f"{path}.num_sites", self.num_sites, 1, 1_000_000)
        check_range(f"{path}.k", self.k, 1e-9, None, allowed="> 0")
        check_range(f"{path}.eps_start", self.eps_start, 0.0, 1.0)
        check_range(f"{path}.eps_end", self.eps_end, 0.0, self.eps_start,
                    allowed=f"[0, eps_start = {self.eps_start}]")
        check_range(f"{path}.eps_decay_episodes", self.eps_decay_episodes, 1, 10**9)
        return self

    def epsilon(self, round_idx: int) -> float:
        """Epsilon of round (= episode per site) ``round_idx``: exponential decay to eps_end."""
        if self.eps_end <= 0.0:
            return self.eps_start if round_idx == 0 else 0.0
        return max(self.eps_end, self.eps_start * (self.eps_end / self.eps_start)
                   ** (round_idx / self.eps_decay_episodes))

LR_DECAYS = ("none", "cosine", "linear")
LABEL_WEIGHTS = ("uniform", "gap", "site_gap")  # imitation: how a label weighs in the loss
ANCHORS = ("none", "heuristic")
ANCHOR_STATES = ("partial", "partial_site")  # encodings whose features 0-2 the heuristic reads


@dataclass
class DQNAgentConfig(AgentConfig):
    """Deep Q-learning on TorchRL (MODEL §3); the network is the ``network`` group."""

    name: str = "dqn"
    num_sites: int = 256  # sites simulated in parallel (one environment step = 256 decisions)
    steps_per_round: int = 40  # decisions per site and round
    eps_start: float = 1.0
    eps_end: float = 0.05
    eps_decay_frames: int = 400_000  # frames (decisions, all sites) to anneal epsilon
    double_dqn: bool = True
    prioritized: bool = False  # prioritized replay (alpha 0.6, beta 0.4)
    updates_per_round: int = 200  # gradient steps after each collected round
    n_steps: int = 3  # n-step returns: decisions folded into one stored transition
    reset_each_round: bool = False  # false: episodes run on across rounds
    reward_scale: float = 10.0  # rewards are multiplied by this in the replay buffer
    policy: str | None = None  # saved policy for evaluation (default results/policies/dqn_<state>)
    anchor: str = "none"  # none | heuristic: act as the heuristic unless Q disagrees clearly
    anchor_margin: float = 0.0  # Q advantage (scaled reward units) needed to override it

    def validate(self, cfg: Any = None, path: str = "agent") -> DQNAgentConfig:
        check_range(f"{path}.num_sites", self.num_sites, 1, 1_000_000)
        check_range(f"{path}.eps_start", self.eps_start, 0.0, 1.0)
        check_range(f"{path}.eps_end", self.eps_end, 0.0, self.eps_start,
                    allowed=f"[0, eps_start = {self.eps_start}]")
        check_range(f"{path}.eps_decay_frames", self.eps_decay_frames, 1, 10**12)
        check_range(f"{path}.steps_per_round", self.steps_per_round, 1, 1_000_000)
        check_range(f"{path}.updates_per_round", self.updates_per_round, 0, 1_000_000)
        check_range(f"{path}.n_steps", self.n_steps, 1, 1000)
        check_range(f"{path}.reward_scale", self.reward_scale, 1e-6, 1e6, allowed="[1e-06, 1e6]")
        check_choice(f"{path}.anchor", self.anchor, ANCHORS)
        check_range(f"{path}.anchor_margin", self.anchor_margin, 0.0, None)
        state = getattr(getattr(cfg, "state", None), "name", None)
        if self.anchor != "none" and state is not None and state not in ANCHOR_STATES:
            raise ConfigError(f"{path}.anchor={self.anchor!r} is invalid with state={state!r}: "
                              f"the heuristic reads the states {', '.join(ANCHOR_STATES)}; "
                              "use one of them or agent.anchor=none")
        return self

    def memory(self, network: Any, n_obs: int, site_bytes: int) -> list[Need]:
        out = super().memory(network, n_obs, site_bytes)
        rnd = self.num_sites * self.steps_per_round
        out.append(("agent.steps_per_round", self.steps_per_round,
                    rnd * (site_bytes + 2 * transition_bytes(n_obs)),
                    f"a round's steps of agent.num_sites={self.num_sites} sites"))
        out += network.memory(n_obs, prioritized=self.prioritized)
        return out

    def run_suffix(self, mdp: Any) -> str:
        """The objective's suffix, then ``_anchored`` for a policy anchored to the heuristic:
        it acts unlike a plain DQN of the same recipe and must not replace one."""
        return super().run_suffix(mdp) + ("" if self.anchor == "none" else "_anchored")


@dataclass
class NetworkConfig:
    """Q-network and its optimisation (MODEL §3 table; grid-searched by ``make grid``)."""

    name: str = "partial"
    depth: int = 3  # hidden layers
    width: int = 32  # units per hidden layer
    lr: float = 1e-3  # Adam learning rate
    weight_decay: float = 1e-4  # Adam L2 regularisation
    batch_size: int = 256
    buffer_size: int = 50_000
    target_update: int = 500  # gradient steps between hard target-network copies
    grad_clip: float = 0.0  # max gradient norm per step; 0 = no clipping
    tau: float = 0.0  # > 0: soft target update by tau per step instead of hard copies
    lr_decay: str = "cosine"  # none | cosine | linear, over all gradient steps of the run
    lr_final: float = 0.05  # final learning rate as a fraction of lr (lr_decay != none)

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "network") -> NetworkConfig:
        check_range(f"{path}.depth", self.depth, 0, 64)
        check_range(f"{path}.width", self.width, 1, 65_536)
        check_range(f"{path}.lr", self.lr, 1e-12, 1.0, allowed="(0, 1]")
        check_range(f"{path}.weight_decay", self.weight_decay, 0.0, 10.0)
        check_range(f"{path}.batch_size", self.batch_size, 1, self.buffer_size,
                    allowed=f"[1, buffer_size = {self.buffer_size}]")
        check_range(f"{path}.buffer_size", self.buffer_size, 1, 100_000_000)
        check_range(f"{path}.target_update", self.target_update, 1, 10**9)
        check_range(f"{path}.grad_clip", self.grad_clip, 0.0, None)
        check_range(f"{path}.tau", self.tau, 0.0, 1.0)
        check_choice(f"{path}.lr_decay", self.lr_decay, LR_DECAYS)
        check_range(f"{path}.lr_final", self.lr_final, 0.0, 1.0)
        return self

    def parameters(self, n_obs: int, n_out: int = 2) -> int:
        """Weights and biases of the Q-network (``depth`` hidden layers of ``width``)."""
        w, d = self.width, self.depth
        if d == 0:
            return (n_obs + 1) * n_out
        return (n_obs + 1) * w + (d - 1) * (w + 1) * w + (w + 1) * n_out

    def memory(self, n_obs: int, prioritized: bool = False) -> list[Need]:
        """What DQN allocates for its network (online and target weights, gradients, Adam's
        two moments, the best snapshot: six float32 copies; a batch's activations forward
        and backward) and for its replay buffer (allocated whole at the first store)."""
        w, d = self.width, self.depth
        weights = 6 * 4 * self.parameters(n_obs) + 4 * 4 * self.batch_size * w * max(d, 1)
        per = transition_bytes(n_obs) + (64 if prioritized else 0)
        return [("network.width", w, weights, f"the Q-network (network.depth={d})"),
                ("network.buffer_size", self.buffer_size, self.buffer_size * per,
                 "the replay buffer")]

    def lr_factor(self, total_updates: int):
        """The learning-rate multiplier after ``k`` of ``total_updates`` gradient steps
        (``None`` without decay)."""
        if self.lr_decay == "none" or total_updates <= 0:
            return None
        floor = self.lr_final
        if self.lr_decay == "cosine":
            return lambda k: floor + (1 - floor) * 0.5 * (1 + math.cos(
                math.pi * min(k / total_updates, 1.0)))
        return lambda k: 1.0 - (1.0 - floor) * min(k / total_updates, 1.0)

POLICY_CLASSES = ("table", "mlp", "threshold")
INITS = ("rule", "heuristic", "threshold", "uniform")


@dataclass
class SearchAgentConfig(AgentConfig):
    """Direct policy search by the cross-entropy method (see the module docstring)."""

    name: str = "search"
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


@dataclass
class ThresholdAgentConfig(AgentConfig):
    """A threshold policy (agents/threshold.py); ``null`` turns a rule off."""

    name: str = "threshold"
    low: float = 40.0
    free_upper: float | None = None
    margin: float = 0.0
    others_below: float | None = None
    busy_tc: float | None = None
    busy_upper: float | None = None

    def validate(self, cfg: Any = None, path: str = "agent") -> ThresholdAgentConfig:
        for name in ("low", "free_upper", "others_below", "busy_upper"):
            v = getattr(self, name)
            if v is not None:
                check_range(f"{path}.{name}", v, 0.0, 100.0)
        check_range(f"{path}.margin", self.margin, -100.0, 100.0)
        if self.busy_tc is not None:
            check_range(f"{path}.busy_tc", self.busy_tc, 0.0, 1.0)
        return self


BASELINE_BASES = ("rule", "heuristic", "threshold")  # what a planner's base may name
# several bases: under which base the other action (not the reference's) is scored
OTHER_UNDER = ("best", "gated", "reference")


@dataclass
class PlannerAgentConfig(AgentConfig):
    """The rollout planner (agents/planner.py). Defaults from the study in docs/PLANNER.md."""

    name: str = "planner"
    base: str = "heuristic"  # base policy: rule | heuristic | threshold | a saved policy path
    rollouts: int = 32  # futures per action (K)
    horizon: int = 200  # ticks per future (H)
    energy_value: float = 0.02  # trips per unit of soc left in the fleet at the horizon
    confidence: float = 1.5  # standard errors by which the other action must score better
    seed: int = 0  # the planner's own random streams
    # more base policies (parallel rollout): each decision's futures run under every base; the
    # planner starts from `base` unless another base's own action is significantly better
    # there, and takes the other action where some base scores it significantly better;
    # [] = the one base (neutral: runs saved before it keep their training fingerprint)
    bases: list[str] = field(default_factory=list, metadata={"neutral": []})
    # several bases: the base the other action is scored under: the one scoring it best on
    # average (best), the reference's unless another scores it significantly better (gated),
    # or always the reference's (reference); neutral, so saved runs keep their fingerprint
    other_under: str = field(default="best", metadata={"neutral": "best"})

    def validate(self, cfg: Any = None, path: str = "agent") -> PlannerAgentConfig:
        _check_base(self.base, f"{path}.base")
        if len(self.bases) > 8:
            raise ConfigError(f"{path}.bases has {len(self.bases)} entries: allowed at most 8 "
                              "(each one adds the planner's futures once more)")
        for i, b in enumerate(self.bases):
            _check_base(b, f"{path}.bases[{i}]")
        check_range(f"{path}.rollouts", self.rollouts, 2, 4096)
        check_range(f"{path}.horizon", self.horizon, 1, 1_000_000)
        check_range(f"{path}.energy_value", self.energy_value, 0.0, 10.0)
        check_range(f"{path}.confidence", self.confidence, 0.0, 100.0)
        check_range(f"{path}.seed", self.seed, 0, 2**32 - 1)
        check_choice(f"{path}.other_under", self.other_under, OTHER_UNDER)
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


@dataclass
class ImitationAgentConfig(AgentConfig):
    """DAgger distillation of the rollout planner (agents/imitation.py)."""

    name: str = "imitation"
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


# agent name -> its schema; the registry (agents/registry.py) adds the builders
AGENT_SCHEMAS: dict[str, type[AgentConfig]] = {
    "rule": RuleAgentConfig, "heuristic": HeuristicAgentConfig,
    "threshold": ThresholdAgentConfig, "planner": PlannerAgentConfig,
    "tabular": TabularAgentConfig, "dqn": DQNAgentConfig, "search": SearchAgentConfig,
    "imitation": ImitationAgentConfig}

__all__ = ["AGENT_SCHEMAS", "ANCHORS", "ANCHOR_STATES", "BASELINE_BASES", "INITS", "LR_DECAYS",
           "POLICY_CLASSES", "AgentConfig", "DQNAgentConfig", "HeuristicAgentConfig",
           "ImitationAgentConfig", "NetworkConfig", "PlannerAgentConfig", "RuleAgentConfig",
           "SearchAgentConfig", "TabularAgentConfig", "ThresholdAgentConfig"]
