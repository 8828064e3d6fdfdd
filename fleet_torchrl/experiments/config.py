"""Schemas of the experiments (MODEL §5): the main table, sweeps, policy maps, objective."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..utils.checks import ConfigError, check_choice, check_range


@dataclass
class TableConfig:
    """``make table``: train what is missing, then evaluate all policies (MODEL §5 item 1)."""

    out: str = "results/table"
    policies_dir: str = "results/policies"
    runs_dir: str = "outputs/table"  # Hydra run folders of the trainings (logs, checkpoints)
    seeds: int = 3  # training seeds per learned run: seed, seed + 1, ...
    jobs: int = 2  # training runs at once (each its own process)
    retrain: bool = False  # train again even when a saved policy exists
    evaluate: bool = True  # false: only make sure the policies exist (make policies)
    # one step of policy improvement over every row (the rollout planner, agent=planner
    # defaults, with the row's policy as base; learned rows: their lowest seed), on the
    # first improve_sims sites of the evaluation; 0 = skip
    improve_sims: int = 200
    # extra overrides of each training run (the learned policies and their budgets)
    # name -> overrides of its training run (learner, state, objective, budget); the YAML
    # default (conf/config.yaml) lists the thesis and the throughput runs
    train: dict[str, list[str]] = field(default_factory=lambda: {
        "tabular": ["agent=tabular", "train.max_episodes=12800", "train.threads=1"],
        "dqn_partial": ["agent=dqn", "state=partial", "train.max_episodes=30720",
                        "train.eval_every=4", "train.eval_sims=1000", "train.eval_ticks=5000",
                        "train.threads=1"],
        "dqn_all": ["agent=dqn", "state=all", "network.width=128", "train.max_episodes=20480",
                    "train.eval_every=4", "train.eval_sims=1000", "train.eval_ticks=5000",
                    "train.threads=1"],
        "tabular_throughput": ["agent=tabular", "mdp.reward=throughput",
                               "train.max_episodes=12800", "train.threads=1"],
        "dqn_partial_throughput": ["agent=dqn", "state=partial", "mdp.reward=throughput",
                                   "agent.reward_scale=1.0", "train.max_episodes=30720",
                                   "train.eval_every=4", "train.eval_sims=1000",
                                   "train.eval_ticks=5000", "train.threads=1"],
        "generalist": ["agent=dqn", "state=partial", "site=randomized",
                       "mdp.reward=throughput", "agent.reward_scale=1.0",
                       "agent.anchor=heuristic", "agent.anchor_margin=4.0",
                       "train.max_episodes=30720", "train.eval_every=4",
                       "train.eval_sims=1000", "train.eval_ticks=5000", "train.threads=1"],
        "search": ["agent=search", "train.threads=1"],
        "search_mlp": ["agent=search", "agent.policy_class=mlp", "agent.sigma_init=0.3",
                       "agent.sigma_min=0.01", "agent.sites=128", "train.threads=1"],
    })  # the same as conf/config.yaml (tests/test_config.py checks)

    def validate(self, path: str = "table") -> TableConfig:
        check_range(f"{path}.seeds", self.seeds, 1, 1000)
        check_range(f"{path}.improve_sims", self.improve_sims, 0, 10**7)
        check_range(f"{path}.jobs", self.jobs, 1, 256)
        return self


@dataclass
class SweepConfig:
    """One point of a generalisation sweep (MODEL §5 item 3): all policies on a changed site."""

    name: str = "pc"  # sweep name: results/sweeps/<name>.{csv,json,png}
    param: str = "p_c"  # site field varied: p_c | t_c | n_vehicles
    value: float = 0.8  # the point evaluated by this job
    out: str = "results/sweeps"
    policies: list[str] = field(default_factory=lambda: [
        "rule", "heuristic", "tabular", "dqn_partial", "dqn_all", "generalist", "search"])
    # the point's own searches (agent=search on the point's site), each a row named by its
    # key with the overrides of its search; cached under search_dir by their settings.
    # Classes that read the charger's remaining time: thresholds, a table with 4 TC bins.
    # search=false skips them (a dict override merges into this one, it cannot empty it)
    search: bool = True
    searches: dict[str, list[str]] = field(default_factory=lambda: {
        "search_threshold": ["agent.policy_class=threshold", "agent.sites=256",
                             "agent.generations=40"],
        "search_table": ["agent.policy_class=table", "agent.tc_bins=4"],
    })
    search_seeded: bool = True  # each search starts from the best start of its class
    # site specialists: recipes of table.train (row -> recipe name) trained on the point's
    # own site, cached like the searches; specialist_seeds training seeds (seed, seed + 1,
    # ...), more_seeds at the points of more_seeds_at ("<param>=<value>");
    # specialist=false skips them
    specialist: bool = True
    specialists: dict[str, str] = field(default_factory=lambda: {
        "specialist_dqn": "dqn_partial", "specialist_tabular": "tabular"})
    specialist_seeds: int = 1
    more_seeds: int = 3
    more_seeds_at: list[str] = field(default_factory=lambda: ["n_vehicles=5", "t_c=50"])
    # learned policies act with the policy-independent safety guard (agents/base.py:
    # GuardedPolicy, charge below the site's reserve floor), reported as such
    guard: bool = True
    # the rollout planner (agent=planner, overrides of its settings), base the heuristic,
    # and the one-step improvement of these policies ("best_learned": the best learned
    # policy of sweep.policies on the pick set): rows planner, planner_<name>
    planner: bool = True
    planner_overrides: list[str] = field(default_factory=list)
    improve: list[str] = field(default_factory=lambda: ["best_learned"])
    # the set best_known is picked on (the searches' selection seed, apart from eval.seed):
    # the best of every row above and every policy
    pick_sims: int = 500
    pick_ticks: int = 10_000
    search_dir: str = "results/search"

    def validate(self, known: tuple[str, ...], path: str = "sweep") -> SweepConfig:
        check_choice(f"{path}.param", self.param, SWEEP_PARAMS)
        check_range(f"{path}.pick_sims", self.pick_sims, 1, 10**7)
        check_range(f"{path}.pick_ticks", self.pick_ticks, 1, 10**8)
        for label, overrides in self.searches.items():
            if not label.startswith("search"):
                raise ConfigError(f"{path}.searches.{label}={list(overrides)} is invalid: "
                                  "allowed row names start with 'search' (search_threshold)")
            check_overrides(f"{path}.searches.{label}", overrides, ("agent", "train", "seed"))
        check_overrides(f"{path}.planner_overrides", self.planner_overrides, ("agent",))
        for i, name in enumerate(self.policies):
            check_choice(f"{path}.policies[{i}]", name, known)
        for i, name in enumerate(self.improve):
            check_choice(f"{path}.improve[{i}]", name, (*self.policies, "best_learned", "best"))
        for row, recipe in self.specialists.items():
            if not row.startswith("specialist"):
                raise ConfigError(f"{path}.specialists.{row}={recipe!r} is invalid: allowed "
                                  "row names start with 'specialist' (specialist_dqn)")
        check_range(f"{path}.specialist_seeds", self.specialist_seeds, 1, 100)
        check_range(f"{path}.more_seeds", self.more_seeds, 1, 100)
        return self


def check_overrides(path: str, overrides: list[str], groups: tuple[str, ...]) -> None:
    """Overrides of a run inside an experiment may set fields of ``groups`` only (never the
    agent itself, nor the site: it is the experiment's)."""
    for i, o in enumerate(overrides):
        key = o.split("=", 1)[0].lstrip("+~")
        if key.split(".")[0] not in groups or key in ("agent", "agent.name"):
            raise ConfigError(f"{path}[{i}]={o!r} is invalid: allowed overrides of "
                              + ", ".join(f"{g}.*" if g != "seed" else g for g in groups)
                              + " (the site is the point's)")


SWEEP_PARAMS = ("p_c", "t_c", "n_vehicles")


@dataclass
class MapsConfig:
    """Policy maps (MODEL §5 item 2) of saved policies on the ``partial`` state."""

    out: str = "results/policy_maps"
    policies: list[str] = field(default_factory=lambda: [
        "rule", "heuristic", "tabular", "dqn_partial", "generalist", "search"])
    # the rollout planner (agent=planner defaults) decides from the whole site: its maps are
    # the share of charge decisions in each cell among the states it met on these sites
    # (site presets), over planner_sims x planner_ticks of the evaluation protocol
    planner_sites: list[str] = field(default_factory=lambda: ["default", "five_vehicles"])
    planner_sims: int = 200
    planner_ticks: int = 5000

    def validate(self, known: tuple[str, ...], path: str = "maps") -> MapsConfig:
        for i, name in enumerate(self.policies):
            check_choice(f"{path}.policies[{i}]", name, known)
        check_range(f"{path}.planner_sims", self.planner_sims, 1, 100_000)
        check_range(f"{path}.planner_ticks", self.planner_ticks, 1, 10**7)
        return self


@dataclass
class ObjectiveConfig:
    """``python -m fleet_torchrl.objective``: the MDP's reward per decision next to trips."""

    n_sites: int = 200  # one episode of mdp.tau_e ticks per site
    seed: int = 7  # training-style sites (rng.training_seed), apart from both eval sets
    out: str = "results/objective"

    def validate(self, path: str = "objective") -> ObjectiveConfig:
        check_range(f"{path}.n_sites", self.n_sites, 1, 10**7)
        check_range(f"{path}.seed", self.seed, 0, 2**32 - 1)
        return self
