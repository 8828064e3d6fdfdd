"""Schemas of the experiments (MODEL §5): the main table, sweeps, policy maps, objective."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from ..sim.config import MAX_NODES
from ..utils.checks import (
    ConfigError,
    Schema,
    check_choice,
    check_device,
    check_fields,
    check_types,
    ranged,
    validate_on_init,
)
from ..utils.paths import NAME_MAX, check_name

# overrides a recipe may not set: the table sets them for each training seed
TABLE_SETS = ("seed", "resume", "train.out_dir", "train.overwrite", "train.device",
              "train.progress")


@dataclass
class Recipe:
    """One learned run of the main table (the ``recipes`` group, ``conf/recipes/``): the
    overrides of its training run (learner, state, objective, site, budget) and the shorter
    budget a preview appends (``make quick``: ``table.preview=true``). The table, the preview,
    the benchmark and the names the sweeps and policy maps accept all read these."""

    overrides: list[str] = field(default_factory=list)
    preview: list[str] = field(default_factory=list)
    # an imitation recipe's teacher may plan over more bases than its own (the parallel
    # rollout, agent.expert.bases): other recipes, each by its policy of the table's first
    # training seed (the table trains them first); e.g. [dqn_all, search_crowded]
    bases: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "recipe") -> Recipe:
        if not self.overrides:
            raise ConfigError(f"{path}.overrides=[] is invalid: allowed a list of training "
                              "overrides, at least agent=<learner>")
        for kind in ("overrides", "preview"):
            for i, o in enumerate(getattr(self, kind)):
                key = o.split("=", 1)[0].lstrip("+~")
                if "=" not in o or key in TABLE_SETS or key.startswith(("hydra.", "hydra/")):
                    raise ConfigError(
                        f"{path}.{kind}[{i}]={o!r} is invalid: allowed overrides key=value of "
                        f"the training run, not {', '.join(TABLE_SETS)} (the table sets them "
                        "per seed) nor Hydra's own")
        if self.bases and "agent=imitation" not in self.overrides:
            raise ConfigError(f"{path}.bases={self.bases!r} is invalid: allowed only in a "
                              "recipe of agent=imitation (the bases its teacher plans over)")
        return self

    def training_overrides(self, preview: bool) -> list[str]:
        """The overrides of this recipe's training run (with the preview's budget)."""
        return [*self.overrides, *(self.preview if preview else [])]

    def site_overrides(self) -> list[str]:
        """The overrides that choose the site (``site=randomized``, ``site.t_c=10``), as
        written; empty when the recipe trains on whatever site it is given."""
        return [o for o in self.overrides
                if o.split("=", 1)[0].lstrip("+~").split(".")[0] == "site"]

    def site_override(self) -> str | None:
        """The first override that chooses the site, None when there is none."""
        return next(iter(self.site_overrides()), None)


def validate_recipes(recipes: dict[str, Recipe], reserved: tuple[str, ...],
                     path: str = "recipes") -> dict[str, Recipe]:
    """Every recipe's overrides; names are folder names (letters, digits, ``_``, ``-``, at
    most :data:`~fleet_torchrl.utils.paths.NAME_MAX` characters) and not those of the
    baselines (``reserved``), which the table and the sweeps list beside them."""
    import re

    if not recipes:
        raise ConfigError(f"{path}={{}} is invalid: allowed at least one recipe "
                          "(conf/recipes/default.yaml)")
    for name, recipe in recipes.items():
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_-]*", name) or name in reserved or \
                len(name) > NAME_MAX:
            shown = name if len(name) <= 80 else f"{name[:40]}... ({len(name)} characters)"
            raise ConfigError(f"{path}.{shown} is invalid: allowed a name of letters, digits, "
                              f"'_' and '-', at most {NAME_MAX} characters, other than "
                              f"{', '.join(reserved)}")
        recipe.validate(f"{path}.{name}")
        for i, base in enumerate(recipe.bases):
            if base not in recipes or base == name or recipes[base].bases:
                raise ConfigError(
                    f"{path}.{name}.bases[{i}]={base!r} is invalid: allowed a recipe other "
                    f"than {name} whose teacher has no bases of its own: "
                    f"{', '.join(n for n, r in recipes.items() if n != name and not r.bases)}")
    return recipes


@dataclass
class TableConfig:
    """``make table``: train what is missing, then evaluate all policies (MODEL §5 item 1).
    What it trains are the ``recipes`` (``conf/recipes/default.yaml``); ``only`` narrows them.
    The trainings are jobs of Hydra's launcher: ``hydra.launcher.n_jobs`` of them at once
    (2 by default, ``conf/hydra/launcher/local.yaml``), or ``hydra/launcher=slurm``."""

    out: str = "results/table"
    policies_dir: str = "results/policies"
    runs_dir: str = "outputs/table"  # Hydra run folders of the trainings (logs, checkpoints)
    seeds: int = ranged(3, 1, 1000)  # training seeds per learned run: seed, seed + 1, ...
    retrain: bool = False  # train again even when a saved policy exists
    evaluate: bool = True  # false: only make sure the policies exist (make policies)
    # one step of policy improvement over every row (the rollout planner, agent=planner
    # defaults, with the row's policy as base; learned rows: their lowest seed), on the
    # first improve_sims sites of the evaluation; 0 = skip
    improve_sims: int = ranged(30, 0, 10**7)
    only: list[str] | None = None  # some of the recipes (e.g. [dqn_partial,search]); null: all
    preview: bool = False  # append each recipe's preview budget (make quick)
    # a policy folder under policies_dir that is a symbolic link out of it is read or
    # written only with true (a policy passed as agent.policy=<path> is always read)
    follow_symlinks: bool = False

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, recipes: tuple[str, ...] | None = None, path: str = "table"
                 ) -> TableConfig:
        """Own ranges; with ``recipes`` (the root's check) also the names of ``only``."""
        check_fields(self, path)
        if self.only is not None and not self.only:
            raise ConfigError(f"{path}.only=[] is invalid: allowed null (every recipe) or "
                              f"some of {', '.join(recipes or ())}")
        if recipes is not None:
            for i, name in enumerate(self.only or []):
                check_choice(f"{path}.only[{i}]", name, recipes)
        return self

    def names(self, recipes: dict[str, Recipe]) -> list[str]:
        """The recipes this table trains and evaluates, in the recipes' order."""
        return [n for n in recipes if self.only is None or n in self.only]

    def training_names(self, recipes: dict[str, Recipe]) -> list[str]:
        """The recipes this table trains: :meth:`names` and the recipes their teachers plan
        over (``Recipe.bases``), in the recipes' order."""
        names = self.names(recipes)
        need = set(names).union(*(recipes[n].bases for n in names))
        return [n for n in recipes if n in need]


@dataclass
class SweepConfig:
    """One point of a generalisation sweep (MODEL §5 item 3): all policies on a changed site."""

    name: str = "pc"  # sweep name: results/sweeps/<name>.{csv,json,png}
    # site field varied: p_c | t_c | n_vehicles (SWEEP_PARAMS, below)
    param: str = ranged("p_c", choices=lambda: SWEEP_PARAMS)
    value: float = 0.8  # the point evaluated by this job
    out: str = "results/sweeps"
    policies: list[str] = field(default_factory=lambda: [
        "rule", "heuristic", "tabular", "dqn_partial", "dqn_all", "imitation", "generalist",
        "generalist_dqn", "search"])
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
    # site specialists: recipes (conf/recipes, row -> recipe name) trained on the point's
    # own site, cached like the searches; specialist_seeds training seeds (seed, seed + 1,
    # ...), more_seeds at the points of more_seeds_at ("<param>=<value>");
    # specialist=false skips them (and the distilled planner below). The student of the
    # planner over the heuristic on the point's site is one more recipe:
    # +sweep.specialists.specialist_imitation=imitation (about 2 min per seed and point)
    specialist: bool = True
    specialists: dict[str, str] = field(default_factory=lambda: {
        "specialist_dqn": "dqn_partial", "specialist_tabular": "tabular"})
    specialist_seeds: int = ranged(1, 1, 100)
    more_seeds: int = ranged(3, 1, 100)
    more_seeds_at: list[str] = field(default_factory=lambda: ["n_vehicles=5", "t_c=50"])
    # learned policies act with the policy-independent safety guard (agents/base.py:
    # GuardedPolicy, charge below the site's reserve floor), reported as such
    guard: bool = True
    # the rollout planner (agent=planner, overrides of its settings), base the heuristic
    # (row planner); and what one step of policy improvement adds to these policies
    # ("best_learned": the best learned row on the pick set; "best": the best row), the
    # planner over each on the first improve_sims sites of the evaluation, paired with its
    # own records (columns improvement_*; the heuristic's from the planner row, every site)
    planner: bool = True
    planner_overrides: list[str] = field(default_factory=list)
    # also the planner over the point's best search (row planner_search), where that search
    # decides inside the kernel and beats the heuristic on the pick set
    planner_search: bool = True
    improve: list[str] = field(default_factory=lambda: ["best_learned"])
    improve_sims: int = ranged(30, 0, 10**7)
    # the set best_known is picked on (the searches' selection seed, apart from eval.seed):
    # the best of every row above and every policy
    pick_sims: int = ranged(200, 1, 10**7)
    pick_ticks: int = ranged(10_000, 1, 10**8)
    search_dir: str = "results/search"
    # the point's best planner distilled on the point's own site (row specialist_distilled,
    # a recipe of agent=imitation): its teacher is the planner over the base of the
    # planner_search row (the point's best search) where there is one, else over the
    # heuristic, unless a row beats every planner row on the pick set: then the planner over
    # that row; the student reads its teacher's base's state; the specialists' seeds; null
    # (or specialist=false) skips it (about 2 min per seed and point, 5-10 over a network)
    distil: str | None = "imitation"
    # every evaluation of a point (pick set, test sites, one-step improvements) is cached
    # under <search_dir>/evaluations by the policy's content, the site, the protocol and the
    # code's source (evaluation/cache.py): a rerun that adds a row computes that row
    eval_cache: bool = True

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, known: tuple[str, ...] | None = None, path: str = "sweep"
                 ) -> SweepConfig:
        """Own fields; with ``known`` (the root's check: baselines and recipes) also the
        names of ``policies``. The point's value is checked for its parameter: an integer
        parameter takes an integer (2.7 vehicles is no site), within the site field's
        bounds (the root also checks ``n_vehicles`` against the site's nodes); a packaged
        sweep's name keeps its parameter, so no point is filed under another sweep."""
        check_fields(self, path)
        check_sweep_value(self.param, self.value, path=path)
        want = PACKAGED_SWEEPS.get(self.name)
        if want is not None and self.param != want:
            raise ConfigError(f"{path}.name={self.name!r} is invalid with {path}.param="
                              f"{self.param}: results/sweeps/{self.name}/ holds the {want} "
                              f"sweep; name a sweep of {self.param} otherwise "
                              f"(e.g. {path}.name={self.param}_mine)")
        check_name(f"{path}.name", self.name)  # results/sweeps/<name>/
        for label, overrides in self.searches.items():
            if not label.startswith("search"):
                raise ConfigError(f"{path}.searches.{label}={list(overrides)} is invalid: "
                                  "allowed row names start with 'search' (search_threshold)")
            check_overrides(f"{path}.searches.{label}", overrides, ("agent", "train", "seed"))
        check_overrides(f"{path}.planner_overrides", self.planner_overrides, ("agent",))
        for i, name in enumerate(self.policies if known is not None else ()):
            check_choice(f"{path}.policies[{i}]", name, known)
        for i, name in enumerate(self.improve):
            check_choice(f"{path}.improve[{i}]", name, (*self.policies, "best_learned", "best"))
        for row, recipe in self.specialists.items():
            if not row.startswith("specialist") or row == "specialist_distilled":
                raise ConfigError(f"{path}.specialists.{row}={recipe!r} is invalid: allowed "
                                  "row names start with 'specialist' (specialist_dqn), "
                                  "other than specialist_distilled (sweep.distil's row)")
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
# the packaged sweeps (conf/experiment/sweep_<name>.yaml) and the parameter each varies
PACKAGED_SWEEPS = {"pc": "p_c", "tc": "t_c", "nv": "n_vehicles"}
# the site field's bounds (sim/config.py: SiteConfig.validate; n_vehicles: the largest site)
SWEEP_BOUNDS = {"p_c": (0.0, 1.0), "t_c": (1, 100_000), "n_vehicles": (1, MAX_NODES - 2)}


def check_sweep_value(param: str, value: float, hi: float | None = None,
                      path: str = "sweep") -> None:
    """A sweep point's value for its parameter: no rounding (an integer parameter takes an
    integer), within the site field's bounds (``hi``: a tighter upper bound, e.g. the
    vehicles a site of ``n_nodes`` holds)."""
    lo, top = SWEEP_BOUNDS[param]
    top = top if hi is None else min(top, hi)
    integer = param != "p_c"
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and \
        math.isfinite(value) and (not integer or float(value).is_integer())
    if not ok or not lo <= value <= top:
        kind = "an integer" if integer else "a number"
        raise ConfigError(f"{path}.value={value} is invalid for {path}.param={param}: "
                          f"allowed {kind} in [{lo}, {top}]")


@dataclass
class MapsConfig:
    """Policy maps (MODEL §5 item 2) of saved policies on the ``partial`` state."""

    out: str = "results/policy_maps"
    policies: list[str] = field(default_factory=lambda: [
        "rule", "heuristic", "tabular", "dqn_partial", "imitation", "generalist", "search"])
    # the rollout planner (agent=planner defaults) decides from the whole site: its maps are
    # the share of charge decisions in each cell among the states it met on these sites
    # (site presets), over planner_sims x planner_ticks of the evaluation protocol
    planner_sites: list[str] = field(default_factory=lambda: ["default", "five_vehicles"])
    planner_sims: int = ranged(200, 1, 100_000)
    planner_ticks: int = ranged(5000, 1, 10**7)

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, known: tuple[str, ...] | None = None, path: str = "maps"
                 ) -> MapsConfig:
        for i, name in enumerate(self.policies if known is not None else ()):
            check_choice(f"{path}.policies[{i}]", name, known)
        for i, name in enumerate(self.planner_sites):  # conf/site/<name>.yaml, planner_<name>.png
            check_name(f"{path}.planner_sites[{i}]", name)
        check_fields(self, path)
        return self


@dataclass
class ObjectiveConfig(Schema):
    """``python -m fleet_torchrl.objective``: the MDP's reward per decision next to trips."""

    PATH: ClassVar[str] = "objective"

    n_sites: int = ranged(200, 1, 10**7)  # one episode of mdp.tau_e ticks per site
    # training-style sites (rng.training_seed), apart from both eval sets
    seed: int = ranged(7, 0, 2**32 - 1)
    out: str = "results/objective"


@dataclass
class BenchConfig:
    """``make bench`` (``fleet-bench``): throughput of the simulator, the evaluation, the
    environment and the recipes' trainings (docs/BENCHMARKS.md)."""

    batches: list[int] = ranged(lo=1, hi=10**7, each=True,  # sites at once
                                default_factory=lambda: [1, 64, 1024, 8192])
    # site-ticks per measurement (ticks = site_ticks / B, 200..10000)
    site_ticks: float = ranged(4e6, 1.0, 1e12)
    repeats: int = ranged(5, 1, 1000)  # the median of this many runs
    device: str = "cpu"
    # environment steps per measurement; null: 200, 50 from B=1024
    env_steps: int | None = ranged(None, 1, 10**7, optional=True)
    protocol: bool = True  # the thesis protocol's wall time (1000 x 10 000, CPU)
    training: bool = True  # every recipe's training throughput (conf/recipes/)
    out: str | None = None  # also write the figures as JSON

    def __post_init__(self) -> None:
        validate_on_init(self)

    def validate(self, path: str = "bench") -> BenchConfig:
        if not self.batches:
            raise ConfigError(f"{path}.batches=[] is invalid: allowed a list of batch sizes")
        check_fields(self, path)
        check_device(f"{path}.device", self.device)
        return self


# ------------------------------------------------------------------ the file tools' schemas
# The commands that only read result files (fleet-compare, fleet-report, fleet-grid,
# fleet-sweeps-summary) have their own small primary configs (conf/<command>.yaml); they share
# the commands' convention: Hydra overrides key=value.
@dataclass
class CompareConfig:
    """``fleet-compare``: results against a baseline on the same sites, in trips, queue and
    failures with paired 95 % intervals; one table, and with ``out`` a file and a figure."""

    result: str | None = None  # a result JSON (fleet-evaluate eval.out=...)
    results: list[str] | None = None  # several, one row each: results=[a.json,b.json]
    baseline: str | None = None  # the result they are compared with (same eval.seed: paired)
    out: str | None = None  # OUT.json (+ OUT.csv, OUT.png beside it); null: print only
    overwrite: bool = False  # replace a comparison that exists at out

    def __post_init__(self) -> None:
        check_types(self, "compare")  # the paths are the command's to require

    def validate(self) -> CompareConfig:
        if not self.result and self.results is None:
            raise ConfigError("result=null is invalid: allowed the path of an evaluation "
                              "result, e.g. fleet-compare result=results/eval/heur.json "
                              "baseline=results/eval/rule.json, or several: "
                              "results=[a.json,b.json]")
        if not self.baseline:
            raise ConfigError("baseline=null is invalid: allowed the path of an evaluation "
                              "result, e.g. fleet-compare result=results/eval/heur.json "
                              "baseline=results/eval/rule.json")
        if self.result and self.results is not None:
            raise ConfigError(f"result={self.result} is invalid with results= set: allowed "
                              "one of them (results=[a.json,b.json] compares several)")
        if self.results is not None:
            if not self.results:
                raise ConfigError("results=[] is invalid: allowed a list of evaluation "
                                  "results, e.g. results=[a.json,b.json]")
            for i, path in enumerate(self.results):
                if not isinstance(path, str) or not path:
                    raise ConfigError(f"results[{i}]={path!r} is invalid: allowed the path "
                                      "of an evaluation result")
        if self.out is not None and not self.out:
            raise ConfigError("out='' is invalid: allowed a path ending in .json, or null "
                              "(print only)")
        return self

    def files(self) -> list[str]:
        """The result files compared, in the table's order."""
        return [self.result] if self.result else list(self.results or [])


@dataclass
class ReportConfig:
    """``fleet-report`` (``make report``): docs/report.md from the result files only."""

    results: str = "results"  # the folder the experiments wrote
    out: str = "docs/report.md"

    def __post_init__(self) -> None:
        check_types(self, "report")


@dataclass
class GridSummaryConfig:
    """``fleet-grid``: rank the configurations of a grid multirun across seeds."""

    sweep_dir: str | None = None  # a grid multirun's folder; null: the latest in multirun/grid
    out: str = "results/grid"  # where a copy of the summary goes

    def __post_init__(self) -> None:
        check_types(self, "grid")


@dataclass
class SweepSummaryConfig:
    """``fleet-sweeps-summary``: collect a sweep's points into results/sweeps/<name>.*."""

    name: str = "pc"  # the sweep: results/sweeps/<name>/
    out: str = "results/sweeps"
    # point names expected (p_c=0.0, ...), reported if missing; null: the points of the
    # packaged experiment conf/experiment/sweep_<name>.yaml (none for another name)
    expect: list[str] | None = None

    def __post_init__(self) -> None:
        check_types(self, "sweeps_summary")

    def validate(self) -> SweepSummaryConfig:
        check_name("name", self.name)  # conf/experiment/sweep_<name>.yaml, <out>/<name>/
        return self
