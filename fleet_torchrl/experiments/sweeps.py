"""Generalisation sweeps (MODEL §5 item 3): policies trained on the default site, evaluated
on changed sites, next to the best policy known at each point.

    make sweep-pc      # = python -m fleet_torchrl.sweeps -m +experiment=sweep_pc
                       #   then fleet-sweeps-summary name=pc

Each Hydra job evaluates, at one point (``site.<param> = sweep.value``), with the evaluation
protocol (``eval.n_sims`` x ``eval.ticks``, common random numbers: every row sees the same
sites):

* every policy of ``sweep.policies`` (baselines, and the default-site learners: every
  training seed saved under ``table.policies_dir/<name>/seed<s>/``, a row being the mean over
  the seeds with every seed's gain); learned policies act with the safety guard of
  :class:`~fleet_torchrl.agents.base.GuardedPolicy` (``sweep.guard``, reported as such);
* site specialists (``sweep.specialists``, unless ``sweep.specialist=false``): recipes of
  ``make table`` (DQN-partial, tabular, ...) trained on the point's own site, with
  ``sweep.specialist_seeds`` seeds (``sweep.more_seeds`` at the points of
  ``sweep.more_seeds_at``), cached like the searches; and the point's best planner
  distilled on its site (``sweep.distil``, row ``specialist_distilled``: the imitation
  recipe whose teacher is the planner over the ``planner_search`` row's search, else over
  the heuristic, or over a row that beats every planner on the pick set, the student
  reading that row's state; :func:`distil_base`), the same seeds;
* the point's own searches (``sweep.searches``, unless ``sweep.search=false``: the direct
  policy search, MODEL §3.4, with
  policy classes that read the charger's remaining time), each started from the best start
  of its class among the rule, the heuristic and every saved policy (``sweep.search_seeded``)
  and cached under ``sweep.search_dir/<point>/<key>`` by its training settings and start;
* the rollout planner (MODEL §3.6) with the heuristic as base (row ``planner``), and over
  the point's best search where that search beats the heuristic on the pick set and decides
  inside the kernel (row ``planner_search``, ``sweep.planner_search``: its rollouts cost
  what the heuristic's do); and what one step of policy improvement adds to each policy
  of ``sweep.improve`` (``best_learned``: the best learned row of the point): the planner
  over it on the first
  ``sweep.improve_sims`` sites of the evaluation, paired with its own records (columns
  ``improvement_*``; the heuristic's is the planner row and the search's the
  ``planner_search`` row, paired on every site). A network
  base costs the planner milliseconds per decision (its rollouts' arrivals are decided by
  forward passes), hence a subset of the sites, and no row of its own;
* ``best_known``: of all the rows above, the best on the point's *pick set* (the searches'
  selection seed ``train.eval_seed`` with ``sweep.pick_sims`` x ``sweep.pick_ticks``, never
  the evaluation's sites): fewer failed simulations first, then more trips. Every row
  reports its share of ``best_known``'s gain over the rule; the JSON's
  ``best_known.from`` names the row it is.

The point's file ``results/sweeps/<name>/<param>=<value>.json`` is written atomically and
records a key of everything it depends on (the site, the evaluation and pick settings, each
policy's identity: a baseline's parameters, a saved policy's file hash, the searches' and
the planner's settings). A rerun skips a point whose key matches and recomputes one whose
settings or policies changed; a point on a site that another sweep has computed with the
same settings (the default site is ``p_c`` 0.8, ``T_C`` 30 and ``N_V`` 3) takes that point's
rows (``reused_from``). Each point records the wall time of its phases (``wall_s``). Every
evaluation (pick set, test sites, one-step improvements) goes through the evaluation cache
of :mod:`fleet_torchrl.evaluation.cache` (``<sweep.search_dir>/evaluations``, keyed by the
policy's content, the site, the protocol and the code): a point recomputed because a row
was added computes that row only. A point that fails writes an ``.error`` file beside it and
does not stop the other points. The saved policies must exist (``make policies`` trains
what is missing); a job trains only its point's searches.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

from ..agents import AGENTS, load_policy_file
from ..agents.base import GuardedPolicy, Policy
from ..agents.baselines import HeuristicPolicy
from ..agents.config import BASELINE_BASES
from ..agents.planner import PlannerPolicy
from ..agents.policy_files import POLICY_FILE, policy_file_sha256
from ..agents.registry import base_policy
from ..agents.search import SearchPolicy, cell_centres, clone_policy, threshold_start
from ..config import Config, compose_config
from ..evaluation import evaluate_policy, evaluate_with, gain_over, seed_interval
from ..evaluation.cache import EvalCache, policy_fingerprint, site_identity
from ..sim import SiteConfig
from ..store import inside, load_policies, saved_policy_path
from ..training import RunSpec, Trainer, result_fingerprint
from ..training.checkpoint import without_neutral
from ..utils.checks import ConfigError
from ..utils.runinfo import file_sha256, read_json, run_info, to_jsonable, write_json
from .improvement import improvement, paired_points
from .table import reusable

POINT_FIELDS = ("param", "value", "policy", "seeds", "trips_mean", "trips_std", "queue_mean",
                "failure_rate", "failure_rate_max", "gain_pct", "gain_ci95", "gain_per_seed",
                "share_of_best_known_pct", "improvement_pct", "improvement_ci95",
                "improvement_sims", "improvement_seed")
IMPROVEMENT_FIELDS = POINT_FIELDS[-4:]
BEST_KNOWN = "best_known"  # the row of the best policy known at the point
PLANNER = "planner"  # the rollout planner over the heuristic
PLANNER_SEARCH = "planner_search"  # the rollout planner over the point's best search
DISTILLED = "specialist_distilled"  # the point's best planner distilled on its site


def digest(obj: Any) -> str:
    """A short stable hash of a JSON-ready object."""
    text = json.dumps(to_jsonable(obj), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def policy_identity(cfg: Config, name: str) -> str:
    """What a policy of ``sweep.policies`` is: a baseline's parameters, or the hash of the
    saved policy file the name stands for."""
    spec = AGENTS.get(name)
    if spec is not None and not spec.trainable:
        return f"{name}:{digest(without_neutral(spec.schema()))}"
    path = saved_policy_path(cfg.table.policies_dir, name, cfg.table.follow_symlinks)
    if not path.is_file():
        return f"{name}:missing"
    return f"{name}:{file_sha256(path)[:16]}"


def search_config(cfg: Config, site: SiteConfig, overrides: list[str]) -> Config:
    """The training config of one of the point's searches (its overrides on the search
    defaults, the point's site)."""
    run_cfg = compose_config(["agent=search", "train.threads=1", *overrides,
                              "train.progress=false", "train.tensorboard=false"])
    run_cfg.site = site
    return run_cfg


def planner_config(cfg: Config) -> Any:
    """The planner's settings (``agent=planner`` with ``sweep.planner_overrides``)."""
    return compose_config(["agent=planner", *cfg.sweep.planner_overrides]).agent


def make_planner(cfg: Config, base: Policy) -> PlannerPolicy:
    """The sweep's planner over ``base`` (and the parallel rollout's other bases, if its
    settings name any)."""
    agent = planner_config(cfg)
    return PlannerPolicy.from_config(agent, base, [base_policy(b) for b in agent.bases])


def eval_cache(cfg: Config) -> EvalCache:
    """The sweeps' evaluation cache (``<sweep.search_dir>/evaluations``, unless
    ``sweep.eval_cache=false``)."""
    return EvalCache(Path(cfg.sweep.search_dir) / "evaluations" if cfg.sweep.eval_cache
                     else None)


def on_pick_set(cfg: Config, site: SiteConfig, pol: Policy, cache: EvalCache | None = None
                ) -> tuple[float, float]:
    """``(failure rate, -mean trips)`` of a policy on the point's pick set: the searches'
    selection seed (``train.eval_seed``, apart from the evaluation's sites) with
    ``sweep.pick_sims`` x ``sweep.pick_ticks``; lower is better."""
    seed = compose_config(["agent=search"]).train.eval_seed
    n, ticks = cfg.sweep.pick_sims, cfg.sweep.pick_ticks
    res = (cache or EvalCache(None)).evaluate(
        pol, site, n, ticks, seed,
        lambda: evaluate_policy(pol, site, n, ticks, seed, cfg.eval.device))
    return res["failure_rate"], -res["trips_mean"]


def class_start(run_cfg: Config, pol: Policy) -> SearchPolicy:
    """What a search of ``run_cfg``'s class starts from when started from ``pol``: its action
    table (table class), its thresholds (threshold class; the heuristic's for a policy
    without any), a network cloned from it (mlp class)."""
    a = run_cfg.agent
    start = SearchPolicy(a.policy_class, a.hidden, a.depth, a.tc_bins)
    if a.policy_class == "table":
        start.charge.copy_(pol(cell_centres(a.tc_bins).to(_device(pol))).long().cpu())
    elif a.policy_class == "threshold":
        start.theta.copy_(threshold_start(pol))
    else:
        start.theta.copy_(clone_policy(pol.cpu(), start.sizes, run_cfg.seed, run_cfg.site))
    return start


def _device(pol: Policy):
    for t in (*pol.buffers(), *pol.parameters()):
        return t.device
    return "cpu"


def search_start(cfg: Config, run_cfg: Config, policies: dict[str, Policy],
                 trained: dict[str, Path] | None = None) -> str:
    """The ``agent.init`` of a point's search: of the rule, the heuristic and the
    ``partial``-state policies of the point, the one whose start of the search (what its
    class can represent of it) does best on the point's pick set, as a baseline's name or a
    saved policy's path (``trained``: the policy files of the point's own earlier searches,
    which are not under ``table.policies_dir``)."""
    best: tuple[tuple[float, float], str] | None = None
    for name, pol in policies.items():
        if pol.encoding != "partial":
            continue
        key = on_pick_set(cfg, run_cfg.site, class_start(run_cfg, pol))
        if best is None or key < best[0]:
            best = (key, name)
    if best is None:
        return run_cfg.agent.init
    spec = AGENTS.get(best[1])
    if spec is not None and not spec.trainable:
        return best[1]
    if trained and best[1] in trained:
        return str(trained[best[1]])
    return str(saved_policy_path(cfg.table.policies_dir, best[1], cfg.table.follow_symlinks))


def point_training(cfg: Config, run_cfg: Config, label: str) -> tuple[Policy, dict[str, Any]]:
    """A policy trained on the point's site with ``run_cfg`` (a search or a specialist),
    reused when its settings (and start) match, and its summary."""
    start: Any = policy_file_sha256(getattr(run_cfg.agent, "init", None))
    teacher = policy_file_sha256(getattr(getattr(run_cfg.agent, "expert", None), "base", None))
    if teacher is not None:  # a teacher over a saved policy: its content, not just its path
        start = [start, teacher]
    out = Path(cfg.sweep.search_dir) / label / digest(
        [result_fingerprint(RunSpec.of(run_cfg)), start])
    run_cfg.train.out_dir = str(out)
    run_cfg.train.overwrite = True  # the sweep's own folder: a policy there is a killed run's
    if not reusable(out, run_cfg):
        print(f"[sweep] {label}: training -> {out}", flush=True)
        Trainer(RunSpec.of(run_cfg), out / "run").run()
    else:
        print(f"[sweep] {label}: reusing {out}", flush=True)
    return load_policy_file(out), read_json(out / "train_summary.json")


def specialist_config(cfg: Config, site: SiteConfig, recipe: str, seed: int,
                      extra: list[str] | tuple[str, ...] = ()) -> Config:
    """The training config of a specialist: a recipe of ``recipes`` (then ``extra``
    overrides) on the point's own site (a recipe of a site distribution cannot be a
    specialist)."""
    run_cfg = compose_config([*cfg.recipes[recipe].overrides, *extra, f"seed={seed}",
                              "train.progress=false", "train.tensorboard=false"])
    if run_cfg.site.randomized:
        raise ConfigError(f"sweep.specialists: the recipe {recipe!r} trains on a site "
                          "distribution; a specialist trains on the point's own site")
    run_cfg.site = site
    return run_cfg


def specialist_seeds(cfg: Config, label: str) -> list[int]:
    s = cfg.sweep
    n = max(s.more_seeds, s.specialist_seeds) if label in s.more_seeds_at else s.specialist_seeds
    return [cfg.seed + k for k in range(n)]


def point_key(cfg: Config, site: SiteConfig, search_cfgs: dict[str, Config],
              specialist_cfgs: dict[str, dict[int, Config]]) -> str:
    """Everything a point's result depends on, hashed (the sweep cache's key)."""
    e, s = cfg.eval, cfg.sweep
    parts: dict[str, Any] = {
        "site": site, "eval": {"n_sims": e.n_sims, "ticks": e.ticks, "seed": e.seed},
        "policies": [policy_identity(cfg, n) for n in s.policies]
        + [str(p) + ":" + file_sha256(p)[:16] for n in s.policies
           for p in seed_paths(cfg, n).values()],
        "searches": {k: result_fingerprint(RunSpec.of(v)) for k, v in search_cfgs.items()},
        "specialists": {row: {seed: result_fingerprint(RunSpec.of(c)) for seed, c in runs.items()}
                        for row, runs in specialist_cfgs.items()},
        "guard": s.guard, "seeds": "every seed of the learned policies",
        "search_seeded": s.search_seeded, "pick": [s.pick_sims, s.pick_ticks],
        "planner": without_neutral(planner_config(cfg)) if s.planner else None,
        "planner_search": s.planner and s.planner_search,
        "distil": None if not (s.specialist and s.distil) else
        "the planner over planner_search's base, or over a row better than every planner; "
        "the student reads its base's state",
        "improve": [list(s.improve), s.improve_sims],
        "best_known": "best of every row on the pick set (failures, then trips)"}
    return digest(parts)


def point_trainings(cfg: Config, site: SiteConfig, label: str
                    ) -> tuple[dict[str, Config], dict[str, dict[int, Config]]]:
    """The training configs of a point on ``site``: its searches (``{row: config}``) and its
    specialists (``{row: {seed: config}}``, the seeds of the point ``label``), the distilled
    planner's (``sweep.distil``, row ``specialist_distilled``) among them with its recipe's
    teacher: the point sets the teacher's base once its searches are known
    (:func:`distil_teacher`)."""
    searches = ({k: search_config(cfg, site, o) for k, o in cfg.sweep.searches.items()}
                if cfg.sweep.search else {})
    recipes = dict(cfg.sweep.specialists) if cfg.sweep.specialist else {}
    if cfg.sweep.specialist and cfg.sweep.distil is not None:
        recipes[DISTILLED] = cfg.sweep.distil
    specialists = {row: {seed: specialist_config(cfg, site, recipe, seed)
                         for seed in specialist_seeds(cfg, label)}
                   for row, recipe in recipes.items()}
    return searches, specialists


def twin_key(cfg: Config, site: SiteConfig) -> str:
    """The point's key with the site's name left out: two sweeps that reach the same site
    (the default site is ``p_c`` 0.8, ``T_C`` 30 and ``N_V`` 3) compute the same rows."""
    neutral = replace(site, name="sweep point")
    return point_key(cfg, neutral, *point_trainings(cfg, neutral, site.name))


def reuse_twin(cfg: Config, path: Path, twin: str, key: str, site: SiteConfig
               ) -> list[dict[str, Any]] | None:
    """The rows of another sweep's point on the same site with the same settings (its
    ``twin_key``), written as this point's (``reused_from`` names the file); None if there
    is none."""
    param, value = cfg.sweep.param, point_value(cfg.sweep.param, cfg.sweep.value)
    for other in sorted(Path(cfg.sweep.out).glob("*/*=*.json")):
        if other.resolve() == path.resolve():
            continue
        try:
            data = read_json(other)
        except ValueError:
            continue
        if data.get("twin_key") != twin or "reused_from" in data:
            continue
        rows = [{**r, "param": param, "value": value} for r in data["rows"]]
        write_json(path, {**data, "rows": rows, "site": site, "key": key,
                          "reused_from": str(other)})
        print(f"[sweep] {site.name}: the same site and settings as {other}: its rows reused",
              flush=True)
        return rows
    return None


def point_value(param: str, value: float) -> float | int:
    """The point's value as the site field takes it (validated: an integer parameter's value
    is integral, never rounded here)."""
    return int(value) if param in ("t_c", "n_vehicles") else float(value)


def check_point_outputs(cfg: Config) -> None:
    """Before a point computes: its folder and the searches' cache can be written, and its
    sweep folder holds no points of another parameter (``results/sweeps/<name>/`` is one
    sweep; mixing two would plot p_c and N_V points on one axis)."""
    from ..utils.paths import check_output

    folder = Path(cfg.sweep.out) / cfg.sweep.name
    check_output("sweep.out", folder, "dir")
    check_output("sweep.search_dir", cfg.sweep.search_dir, "dir")
    if folder.is_dir():
        others = sorted({f.name.split("=", 1)[0] for f in folder.iterdir()
                         if "=" in f.name and f.suffix in (".json", ".error")}
                        - {cfg.sweep.param})
        if others:
            raise ConfigError(f"sweep.name={cfg.sweep.name!r} is invalid with sweep.param="
                              f"{cfg.sweep.param}: {folder} holds a sweep of {others[0]}; "
                              "give this sweep a name of its own")


def point_path(cfg: Config) -> Path:
    v = point_value(cfg.sweep.param, cfg.sweep.value)
    return Path(cfg.sweep.out) / cfg.sweep.name / f"{cfg.sweep.param}={v}.json"


def best_of(keys: dict[Any, tuple[float, float]]) -> Any:
    """The name with the best pick-set key (fewer failures, then more trips); on a tie the
    first in order (policies before searches before planners)."""
    return min(keys, key=lambda n: keys[n])


def seed_paths(cfg: Config, name: str) -> dict[int, Path]:
    """Every training seed's policy file of a learned policy of ``sweep.policies`` (``make
    table``'s ``<name>/seed<s>/``), or its one policy (``make train``'s ``<name>/``) as seed 0;
    empty for a baseline."""
    spec = AGENTS.get(name)
    if spec is not None and not spec.trainable:
        return {}
    folder = Path(cfg.table.policies_dir) / name
    t = cfg.table
    seeds = {int(p.parent.name[4:]): inside(t.policies_dir, p, t.follow_symlinks)
             for p in inside(t.policies_dir, folder, t.follow_symlinks).glob(
                 f"seed*/{POLICY_FILE}")
             if p.parent.name[4:].isdigit()}
    if not seeds:
        seeds = {0: saved_policy_path(cfg.table.policies_dir, name, cfg.table.follow_symlinks)}
    return dict(sorted(seeds.items()))


def is_learned(name: str) -> bool:
    """A learned row: a default-site learner or a specialist (not a baseline, a search, a
    planner or best_known)."""
    return (name not in AGENTS and not name.startswith(("search", PLANNER, BEST_KNOWN))) or \
        name.startswith("specialist")


def seed_row(name: str, per_seed: dict[int, dict[str, Any]], rule: dict[str, Any]
             ) -> dict[str, Any]:
    """A row of several training seeds: every figure the mean over the seeds, the gain with
    its 95 % interval across seeds and each seed's gain, the worst seed's failure rate."""
    gains = [gain_over(res, rule)["gain_pct"] for res in per_seed.values()]
    gi = seed_interval(gains)
    n = len(per_seed)
    return {"policy": name, "seeds": list(per_seed), "gain_per_seed": gains,
            **{k: sum(r[k] for r in per_seed.values()) / n
               for k in ("trips_mean", "trips_std", "queue_mean", "failure_rate")},
            "failure_rate_max": max(r["failure_rate"] for r in per_seed.values()),
            "gain_pct": gi["mean"], "gain_ci95": None if n == 1 else gi["ci95"]}


def run_point(cfg: Config) -> list[dict[str, Any]] | None:
    """Evaluate every row at this job's point; returns the rows (None if already done)."""
    check_point_outputs(cfg)
    path = point_path(cfg)
    param = cfg.sweep.param
    value = point_value(param, cfg.sweep.value)
    label = f"{param}={value}"
    if cfg.site.randomized:
        raise ConfigError(f"site={cfg.site.name!r} is a site distribution: a sweep varies "
                          f"{param} of one site; run it on a single site (e.g. site=default)")
    site = replace(cfg.site, **{param: value}, name=label).validate()
    search_cfgs, specialist_cfgs = point_trainings(cfg, site, label)
    key = point_key(cfg, site, search_cfgs, specialist_cfgs)
    if path.exists():
        try:
            old = read_json(path).get("key")
        except ValueError:
            old = None
        if old == key:
            print(f"[sweep] {path} exists, skipping")
            return None
        print(f"[sweep] {path} was computed with other settings or policies: recomputing")
    twin = twin_key(cfg, site)
    reused = reuse_twin(cfg, path, twin, key, site)
    if reused is not None:
        return reused
    t_start = time.perf_counter()
    phase_s: dict[str, float] = {}
    e = cfg.eval
    cache = eval_cache(cfg)
    guard = GuardedPolicy if cfg.sweep.guard else (lambda p: p)
    # every row as {seed: policy}; a baseline, a search or a planner has one (seed None)
    groups: dict[str, dict[int | None, Policy]] = {}
    baselines = [n for n in cfg.sweep.policies if not seed_paths(cfg, n)]
    for name, pol in load_policies(cfg.table.policies_dir, baselines, cfg.eval.device,
                                       cfg.table.follow_symlinks).items():
        groups[name] = {None: pol}
    for name in cfg.sweep.policies:
        if name not in groups:
            groups[name] = {s: guard(_named(load_policy_file(p, e.device), name))
                            for s, p in seed_paths(cfg, name).items()}
    summaries: dict[str, Any] = {}
    trained: dict[str, Path] = {}  # the point's own searches, possible starts of the next
    files: dict[tuple[str, int | None], Path] = {  # every row's policy file (a teacher's base)
        (n, s): p for n in cfg.sweep.policies for s, p in seed_paths(cfg, n).items()}
    t = time.perf_counter()
    for name, run_cfg in search_cfgs.items():
        if cfg.sweep.search_seeded and not any(o.split("=", 1)[0].lstrip("+~") == "agent.init"
                                               for o in cfg.sweep.searches[name]):
            starts = {n: next(iter(g.values())) for n, g in groups.items()}
            run_cfg.agent.init = search_start(cfg, run_cfg, {
                n: getattr(p, "policy", p) for n, p in starts.items()}, trained)
            print(f"[sweep] {label} {name}: starts from {run_cfg.agent.init}", flush=True)
        pol, summaries[name] = point_training(cfg, run_cfg, f"{label}/{name}")
        summaries[name]["init"] = run_cfg.agent.init
        groups[name] = {None: pol}
        trained[name] = Path(run_cfg.train.out_dir) / POLICY_FILE
        files[(name, None)] = trained[name]
    phase_s["searches"] = time.perf_counter() - t
    t = time.perf_counter()
    for row, runs in specialist_cfgs.items():
        if row == DISTILLED:  # trained once its teacher is known (below)
            continue
        groups[row] = {}
        for seed, run_cfg in runs.items():
            pol, summ = point_training(cfg, run_cfg, f"{label}/{row}/seed{seed}")
            groups[row][seed] = guard(_named(pol, row))
            summaries[f"{row}_seed{seed}"] = summ
            files[(row, seed)] = Path(run_cfg.train.out_dir) / POLICY_FILE
    phase_s["specialists"] = time.perf_counter() - t
    t = time.perf_counter()
    keys = {(n, s): on_pick_set(cfg, site, p, cache) for n, g in groups.items()
            for s, p in g.items()}
    phase_s["pick_set"] = time.perf_counter() - t
    t = time.perf_counter()
    planner_bases: dict[str, str] = {}  # base row -> the planner row over it
    if cfg.sweep.planner:
        groups[PLANNER] = {None: make_planner(cfg, HeuristicPolicy())}
        keys[(PLANNER, None)] = on_pick_set(cfg, site, groups[PLANNER][None], cache)
        planner_bases["heuristic"] = PLANNER
        base = search_base(cfg, groups, keys)
        if base is not None:
            planner_bases[base] = PLANNER_SEARCH
            groups[PLANNER_SEARCH] = {None: make_planner(cfg, groups[base][None])}
            keys[(PLANNER_SEARCH, None)] = on_pick_set(cfg, site,
                                                       groups[PLANNER_SEARCH][None], cache)
            print(f"[sweep] {label} {PLANNER_SEARCH}: the planner over {base}", flush=True)
    phase_s["planners_pick_set"] = time.perf_counter() - t
    t = time.perf_counter()
    if DISTILLED in specialist_cfgs:
        base = distil_base(cfg, keys, planner_bases)
        teacher = distil_teacher(cfg, base, files)
        state = distil_state(cfg, groups, base)
        groups[DISTILLED] = {}
        for seed, run_cfg in specialist_cfgs[DISTILLED].items():
            if state is not None:
                run_cfg = specialist_config(cfg, site, cfg.sweep.distil, seed, [f"state={state}"])
            run_cfg.agent.expert = teacher
            pol, summ = point_training(cfg, run_cfg, f"{label}/{DISTILLED}/seed{seed}")
            groups[DISTILLED][seed] = guard(_named(pol, DISTILLED))
            summaries[f"{DISTILLED}_seed{seed}"] = {**summ, "teacher_base": teacher.base,
                                                    "state": run_cfg.state.name}
            keys[(DISTILLED, seed)] = on_pick_set(cfg, site, groups[DISTILLED][seed], cache)
        print(f"[sweep] {label} {DISTILLED}: the planner over {teacher.base} distilled "
              f"onto the {run_cfg.state.name} state",
              flush=True)
    phase_s["distil"] = time.perf_counter() - t
    best = best_of(keys)
    print(f"[sweep] {label}: best known is {best[0]}"
          + (f" seed {best[1]}" if best[1] is not None else "")
          + f" ({-keys[best][1]:.1f} trips on the pick set)", flush=True)
    t = time.perf_counter()
    results = {(n, s): evaluated(cache, p, site, e, n if s is None else f"{n}_seed{s}")
               for n, g in groups.items() for s, p in g.items()}
    phase_s["evaluation"] = time.perf_counter() - t
    t = time.perf_counter()
    rule = results[("rule", None)] if ("rule", None) in results else None
    improved = one_step(cfg, site, groups, keys, results, rule, planner_bases, cache)
    if cache.folder is not None:
        print(f"[sweep] {label}: evaluation cache {cache.hits} hit(s), {cache.misses} "
              f"computed ({cache.folder})", flush=True)
    phase_s["improvement"] = time.perf_counter() - t
    phase_s["total"] = time.perf_counter() - t_start
    rows = []
    for name, g in groups.items():
        if list(g) == [None]:
            res = results[(name, None)]
            gn = gain_over(res, rule) if rule is not None else {"gain_pct": None,
                                                                "gain_ci95": None}
            rows.append({"policy": name, "seeds": [], "gain_per_seed": [],
                         **{k: res[k] for k in ("trips_mean", "trips_std", "queue_mean",
                                                "failure_rate")},
                         "failure_rate_max": res["failure_rate"],
                         "gain_pct": gn["gain_pct"], "gain_ci95": gn["gain_ci95"]})
        else:
            rows.append(seed_row(name, {s: results[(name, s)] for s in g}, rule))
    for r in rows:
        r.update(improved.get(r["policy"], dict.fromkeys(IMPROVEMENT_FIELDS)))
    top_res = results[best]
    g_top = gain_over(top_res, rule) if rule is not None else {"gain_pct": None,
                                                              "gain_ci95": None}
    rows.append({"policy": BEST_KNOWN, "seeds": [] if best[1] is None else [best[1]],
                 "gain_per_seed": [], **dict.fromkeys(IMPROVEMENT_FIELDS),
                 **{k: top_res[k] for k in ("trips_mean", "trips_std", "queue_mean",
                                            "failure_rate")},
                 "failure_rate_max": top_res["failure_rate"],
                 "gain_pct": g_top["gain_pct"], "gain_ci95": g_top["gain_ci95"]})
    top = rows[-1]["gain_pct"]
    for r in rows:  # share of the achievable gain: this row's gain over best_known's
        r.update(param=param, value=value)
        ok = top is not None and r["gain_pct"] is not None and top > 0
        r["share_of_best_known_pct"] = 100.0 * r["gain_pct"] / top if ok else None
    write_json(path, {"rows": rows, "site": site, "key": key, "twin_key": twin,
                      "wall_s": {k: round(v, 1) for k, v in phase_s.items()},
                      "best_known": {"from": best[0], "seed": best[1], "pick_set": {
                          (n if s is None else f"{n}_seed{s}"):
                          {"failure_rate": k[0], "trips_mean": -k[1]}
                          for (n, s), k in keys.items()}},
                      "guard": cfg.sweep.guard,
                      "trainings": {n: {**{k: v[k] for k in ("run_dir", "wall_s", "best")},
                                        **{k: v[k] for k in ("init", "teacher_base", "state")
                                           if k in v}}
                                    for n, v in summaries.items()},
                      "meta": run_info(cfg, seed=e.seed)})
    err = path.with_suffix(".error")
    if err.exists():
        err.unlink()
    print(f"[sweep] {label}: " + ", ".join(f"{k} {v:.0f} s" for k, v in phase_s.items()),
          flush=True)
    for r in rows:
        gain = f", gain {r['gain_pct']:+.2f} %" if r["gain_pct"] is not None else ""
        share = (f", {r['share_of_best_known_pct']:.0f} % of the best known"
                 if r["share_of_best_known_pct"] is not None else "")
        seeds = f" (seeds {r['seeds']})" if len(r["seeds"]) > 1 else ""
        print(f"[sweep] {label} {r['policy']}: {r['trips_mean']:.1f} trips{gain}{share}{seeds}")
    return rows


def search_base(cfg: Config, groups: dict[str, dict[int | None, Policy]],
                keys: dict[tuple[str, int | None], tuple[float, float]]) -> str | None:
    """The base of row ``planner_search`` (``sweep.planner_search``): the point's best search
    on the pick set, if it decides inside the kernel (rollouts as cheap as the heuristic's)
    and is better there than the heuristic (the ``planner`` row's base); else None."""
    if not (cfg.sweep.planner and cfg.sweep.planner_search):
        return None
    pool = {k: v for k, v in keys.items() if k[0].startswith("search") and k[1] is None
            and groups[k[0]][None].kernel_policy() is not None}
    if not pool:
        return None
    best = best_of(pool)
    heuristic = keys.get(("heuristic", None))
    if heuristic is not None and not pool[best] < heuristic:
        return None
    return best[0]


def one_step(cfg: Config, site: SiteConfig, groups: dict[str, dict[int | None, Policy]],
             keys: dict[tuple[str, int | None], tuple[float, float]],
             results: dict[tuple[str, int | None], dict[str, Any]],
             rule: dict[str, Any] | None, planner_bases: dict[str, str],
             cache: EvalCache | None = None) -> dict[str, dict[str, Any]]:
    """What one step of policy improvement adds to the policies of ``sweep.improve`` (the
    best learned row's best seed on the pick set, ...): the planner over it on the first
    ``sweep.improve_sims`` sites of the evaluation, paired with its own records, in points
    of gain over the rule (:func:`~fleet_torchrl.experiments.improvement.improvement`). A
    base with a planner row of its own (``planner_bases``: base row -> planner row; the
    heuristic's ``planner``, the search's ``planner_search``) takes that row, paired on
    every site. ``{row: improvement_*}``."""
    out: dict[str, dict[str, Any]] = {}
    if not cfg.sweep.planner or rule is None:
        return out
    for name, planner in planner_bases.items():
        if (name, None) not in results:
            continue
        trips = {n: results[(n, None)]["records"]["trips"] for n in (planner, name)}
        pct, ci = paired_points(trips[planner], trips[name], rule["records"]["trips"])
        n = len(trips[planner])
        out[name] = {"improvement_pct": pct, "improvement_ci95": ci if n > 1 else None,
                     "improvement_sims": n, "improvement_seed": None}
    if not cfg.sweep.improve_sims:
        return out
    for want in cfg.sweep.improve:
        pool = {k: v for k, v in keys.items() if not k[0].startswith((PLANNER, BEST_KNOWN))}
        if want == "best_learned":
            pool = {k: v for k, v in pool.items() if is_learned(k[0])}
        elif want != "best":
            pool = {k: v for k, v in pool.items() if k[0] == want}
        if not pool:
            continue
        name, seed = best_of(pool)
        if name in out:
            continue
        pol, planner = groups[name][seed], planner_config(cfg)
        parts = ["improvement", policy_fingerprint(pol), without_neutral(planner),
                 site_identity(site),
                 cfg.sweep.improve_sims, cfg.eval.ticks, cfg.eval.seed]
        imp = (cache or EvalCache(None)).get_or_compute(parts, partial(
            improvement, pol, results[(name, seed)], rule, site, cfg.sweep.improve_sims,
            cfg.eval.ticks, cfg.eval.seed, planner, cfg.eval.device))
        out[name] = {"improvement_pct": imp["improvement_pct"],
                     "improvement_ci95": imp["improvement_ci95"],
                     "improvement_sims": imp["sims"],
                     "improvement_seed": seed}
        print(f"[sweep] {site.name} {name}" + (f" seed {seed}" if seed is not None else "")
              + f": one step of improvement {imp['improvement_pct']:+.2f} "
              f"± {imp['improvement_ci95']:.2f} ({imp['sims']} sites)", flush=True)
    return out


def distil_base(cfg: Config, keys: dict[tuple[str, int | None], tuple[float, float]],
                planner_bases: dict[str, str]) -> tuple[str, int | None] | None:
    """The base of the teacher of row ``specialist_distilled``, as ``(row, seed)``: the base
    of the point's last planner row (``planner_search``'s search, else the heuristic), unless
    another row (neither a planner row nor this row itself) beats every planner row on the
    pick set: then the best such row (the planner over a policy better than every planner
    we have is the better teacher; measured at ``T_C`` = 10, docs/TRAINING.md section 14).
    None: no planner rows (the teacher is then the planner over the heuristic)."""
    if not planner_bases:
        return None
    base = next(reversed(planner_bases))
    rows = {PLANNER, PLANNER_SEARCH, *planner_bases.values()}
    planners = {k: v for k, v in keys.items() if k[0] in rows}
    others = {k: v for k, v in keys.items() if k[0] not in rows and k[0] != DISTILLED}
    if others and planners and min(others.values()) < min(planners.values()):
        return best_of(others)
    return (base, None)


def distil_teacher(cfg: Config, base: tuple[str, int | None] | None,
                   files: dict[tuple[str, int | None], Path]) -> Any:
    """The teacher of row ``specialist_distilled``: the sweep's planner settings over the
    row ``base`` (:func:`distil_base`), by its policy file (the heuristic by name)."""
    teacher = planner_config(cfg)
    if base is None or base == ("heuristic", None):
        teacher.base = "heuristic"
    elif base in files:
        teacher.base = str(files[base])
    elif base[0] in AGENTS and not AGENTS[base[0]].trainable:
        teacher.base = base[0]
        if teacher.base not in BASELINE_BASES:
            raise ConfigError(f"the distilled planner's base {base[0]!r} cannot be a "
                              f"planner's base (allowed {', '.join(BASELINE_BASES)} or a "
                              "policy file)")
    else:
        raise ConfigError(f"the distilled planner's base {base[0]!r} has no policy file")
    return teacher


def distil_state(cfg: Config, groups: dict[str, dict[int | None, Policy]],
                 base: tuple[str, int | None] | None) -> str | None:
    """The state the distilled student reads, where it differs from its recipe's: the
    state its teacher's base reads (a student needs what its teacher's base decides on:
    a DQN reading every node orders the vehicles in a way the ``partial`` state cannot
    show), if the imitation learner accepts it; None keeps the recipe's."""
    if base is None:
        return None
    enc = getattr(groups.get(base[0], {}).get(base[1]), "encoding", None)
    recipe = compose_config(list(cfg.recipes[cfg.sweep.distil].overrides)).state.name
    states = AGENTS["imitation"].states or ()
    return enc if enc != recipe and enc in states else None


def evaluated(cache: EvalCache, pol: Policy, site: SiteConfig, e: Any, name: str
              ) -> dict[str, Any]:
    """:func:`evaluate_with` through the point's evaluation cache."""
    return cache.evaluate(pol, site, e.n_sims, e.ticks, e.seed,
                          lambda: evaluate_with(pol, site, e, name=name), name=name)


def _named(pol: Policy, name: str) -> Policy:
    pol.name = name
    return pol
