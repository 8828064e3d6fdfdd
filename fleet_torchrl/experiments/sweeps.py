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

import time
from contextlib import contextmanager
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

from ..agents.base import Policy
from ..agents.baselines import HeuristicPolicy
from ..agents.policy_files import POLICY_FILE
from ..evaluation import evaluate_with
from ..evaluation.cache import EvalCache, policy_fingerprint, site_identity
from ..sim import SiteConfig
from ..training.checkpoint import without_neutral
from ..utils.checks import ConfigError
from ..utils.runinfo import read_json, write_json
from .config import SweepConfig
from .improvement import improvement, paired_points
from .rows import IMPROVEMENT_FIELDS, POINT_FIELDS, Candidate, Row
from .sweep_candidates import (
    BEST_KNOWN,
    DISTILLED,
    PLANNER,
    PLANNER_SEARCH,
    PointSettings,
    Pool,
    _named,
    best_of,
    class_start,
    distil_base,
    distil_state,
    distil_teacher,
    guard,
    is_learned,
    load_saved,
    make_planner,
    on_pick_set,
    plan_candidates,
    point_training,
    search_base,
    search_start,
)
from .sweep_keys import CACHE_VERSION, digest, point_key, seed_paths, twin_key


def point_value(param: str, value: float) -> float | int:
    """The point's value as the site field takes it (validated: an integer parameter's value
    is integral, never rounded here)."""
    return int(value) if param in ("t_c", "n_vehicles") else float(value)


def point_site(sweep: SweepConfig, site: SiteConfig) -> SiteConfig:
    """The site of the point: ``site`` with ``sweep.param`` at ``sweep.value``, named
    ``<param>=<value>``; a site distribution is refused."""
    param, value = sweep.param, point_value(sweep.param, sweep.value)
    if site.randomized:
        raise ConfigError(f"site={site.name!r} is a site distribution: a sweep varies "
                          f"{param} of one site; run it on a single site (e.g. site=default)")
    return replace(site, **{param: value}, name=f"{param}={value}").validate()


def specialist_seeds(sweep: SweepConfig, seed: int, label: str) -> list[int]:
    """The training seeds of the point ``label``'s specialists."""
    n = (max(sweep.more_seeds, sweep.specialist_seeds) if label in sweep.more_seeds_at
         else sweep.specialist_seeds)
    return [seed + k for k in range(n)]


def eval_cache(sweep: SweepConfig) -> EvalCache:
    """The sweeps' evaluation cache (``<sweep.search_dir>/evaluations``, unless
    ``sweep.eval_cache=false``)."""
    return EvalCache(Path(sweep.search_dir) / "evaluations" if sweep.eval_cache else None)


def check_point_outputs(sweep: SweepConfig) -> None:
    """Before a point computes: its folder and the searches' cache can be written, and its
    sweep folder holds no points of another parameter (``results/sweeps/<name>/`` is one
    sweep; mixing two would plot p_c and N_V points on one axis)."""
    from ..utils.paths import check_output

    folder = Path(sweep.out) / sweep.name
    check_output("sweep.out", folder, "dir")
    check_output("sweep.search_dir", sweep.search_dir, "dir")
    if folder.is_dir():
        others = sorted({f.name.split("=", 1)[0] for f in folder.iterdir()
                         if "=" in f.name and f.suffix in (".json", ".error")}
                        - {sweep.param})
        if others:
            raise ConfigError(f"sweep.name={sweep.name!r} is invalid with sweep.param="
                              f"{sweep.param}: {folder} holds a sweep of {others[0]}; "
                              "give this sweep a name of its own")


def point_path(sweep: SweepConfig) -> Path:
    v = point_value(sweep.param, sweep.value)
    return Path(sweep.out) / sweep.name / f"{sweep.param}={v}.json"


class Clock:
    """The wall time of a point's phases (``wall_s``)."""

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.phase_s: dict[str, float] = {}

    @contextmanager
    def phase(self, name: str):
        t = time.perf_counter()
        yield
        self.phase_s[name] = time.perf_counter() - t

    def total(self) -> dict[str, float]:
        return {**self.phase_s, "total": time.perf_counter() - self.start}


def run_point(p: PointSettings) -> list[dict[str, Any]] | None:
    """Evaluate every row at this job's point; returns the rows (None if already done): plan
    the candidates, train the point's own, pick on the pick set, evaluate, aggregate."""
    check_point_outputs(p.sweep)
    path = point_path(p.sweep)
    keys = (p.sweep, p.table, p.eval, p.site, p.searches, p.specialists, p.planner)
    key = point_key(*keys)
    if up_to_date(path, key):
        return None
    twin = twin_key(*keys)
    reused = reuse_twin(p, path, twin, key)
    if reused is not None:
        return reused
    clock, cache, pool = Clock(), eval_cache(p.sweep), Pool()
    candidates = plan_candidates(p)
    load_saved(p, candidates, pool)
    with clock.phase("searches"):
        train_searches(p, candidates, pool)
    with clock.phase("specialists"):
        train_specialists(p, candidates, pool)
    with clock.phase("pick_set"):
        pool.keys = {(n, s): on_pick_set(p, q, cache) for n, g in pool.policies.items()
                     for s, q in g.items()}
    with clock.phase("planners_pick_set"):
        add_planners(p, pool, cache)
    with clock.phase("distil"):
        train_distilled(p, pool, cache)
    best = best_of(pool.keys)
    print(f"[sweep] {p.site.name}: best known is {best[0]}"
          + (f" seed {best[1]}" if best[1] is not None else "")
          + f" ({-pool.keys[best][1]:.1f} trips on the pick set)", flush=True)
    with clock.phase("evaluation"):
        results = {(n, s): evaluated(cache, q, p.site, p.eval, n if s is None else f"{n}_seed{s}")
                   for n, g in pool.policies.items() for s, q in g.items()}
    with clock.phase("improvement"):
        improved = one_step(p, pool, results, results.get(("rule", None)), cache)
        if cache.folder is not None:
            print(f"[sweep] {p.site.name}: evaluation cache {cache.hits} hit(s), "
                  f"{cache.misses} computed ({cache.folder})", flush=True)
    rows = aggregate(p, pool, results, improved, best)
    wall_s = clock.total()
    write_point(p, path, rows, {"key": key, "twin_key": twin}, pool, best, wall_s)
    say_rows(p.site.name, rows, wall_s)
    return rows


def up_to_date(path: Path, key: str) -> bool:
    """Whether the point's file holds the rows of this very key (else it is recomputed)."""
    if not path.exists():
        return False
    try:
        old = read_json(path).get("key")
    except ValueError:
        old = None
    if old == key:
        print(f"[sweep] {path} exists, skipping")
        return True
    print(f"[sweep] {path} was computed with other settings or policies: recomputing")
    return False


def train_searches(p: PointSettings, candidates: list[Candidate], pool: Pool) -> None:
    """The point's searches, each started (``sweep.search_seeded``, unless its overrides set
    ``agent.init``) from the best start of its class among the rows loaded so far."""
    trained: dict[str, Path] = {}  # the point's own searches, possible starts of the next
    for c in (c for c in candidates if c.kind == "search"):
        spec = c.specs[None]
        if p.sweep.search_seeded and not any(o.split("=", 1)[0].lstrip("+~") == "agent.init"
                                             for o in p.sweep.searches[c.name]):
            starts = {n: next(iter(g.values())) for n, g in pool.policies.items()}
            init = search_start(p, spec, {n: getattr(q, "policy", q)
                                          for n, q in starts.items()}, trained)
            spec = replace(spec, agent=replace(spec.agent, init=init))
            print(f"[sweep] {p.site.name} {c.name}: starts from {init}", flush=True)
        pol, pool.summaries[c.name], ran = point_training(p, spec, f"{p.site.name}/{c.name}")
        pool.summaries[c.name]["init"] = spec.agent.init
        pool.policies[c.name] = {None: pol}
        trained[c.name] = pool.files[(c.name, None)] = Path(ran.train.out_dir) / POLICY_FILE


def train_specialists(p: PointSettings, candidates: list[Candidate], pool: Pool) -> None:
    """The point's specialists, every seed (the distilled row waits for its teacher)."""
    for c in (c for c in candidates if c.kind == "specialist" and c.name != DISTILLED):
        pool.policies[c.name] = {}
        for seed, spec in c.specs.items():
            pol, summ, ran = point_training(p, spec, f"{p.site.name}/{c.name}/seed{seed}")
            pool.policies[c.name][seed] = guard(p, _named(pol, c.name))
            pool.summaries[f"{c.name}_seed{seed}"] = summ
            pool.files[(c.name, seed)] = Path(ran.train.out_dir) / POLICY_FILE


def add_planners(p: PointSettings, pool: Pool, cache: EvalCache) -> None:
    """The planner over the heuristic (row ``planner``) and over the point's best search
    (row ``planner_search``, :func:`search_base`), with their pick-set keys."""
    if not p.sweep.planner:
        return
    pool.policies[PLANNER] = {None: make_planner(p.planner, HeuristicPolicy())}
    pool.keys[(PLANNER, None)] = on_pick_set(p, pool.policies[PLANNER][None], cache)
    pool.planner_bases["heuristic"] = PLANNER
    base = search_base(p, pool)
    if base is not None:
        pool.planner_bases[base] = PLANNER_SEARCH
        pool.policies[PLANNER_SEARCH] = {None: make_planner(p.planner,
                                                            pool.policies[base][None])}
        pool.keys[(PLANNER_SEARCH, None)] = on_pick_set(p, pool.policies[PLANNER_SEARCH][None],
                                                        cache)
        print(f"[sweep] {p.site.name} {PLANNER_SEARCH}: the planner over {base}", flush=True)


def train_distilled(p: PointSettings, pool: Pool, cache: EvalCache) -> None:
    """Row ``specialist_distilled``: the point's best planner (:func:`distil_base`) distilled
    on its site, every seed, the student reading its teacher's base's state."""
    if DISTILLED not in p.specialists:
        return
    base = distil_base(pool.keys, pool.planner_bases)
    teacher = distil_teacher(p.planner, base, pool.files)
    recipe_state = next(iter(p.specialists[DISTILLED].values())).state.name
    state = distil_state(recipe_state, pool.policies, base)
    pool.policies[DISTILLED] = {}
    for seed, spec in p.specialists[DISTILLED].items():
        if state is not None:
            if state not in p.distil_states:
                raise ConfigError(f"sweep.distil={p.sweep.distil!r} cannot read the state "
                                  f"{state!r} of its teacher's base")
            spec = p.distil_states[state][seed]
        spec = replace(spec, agent=replace(spec.agent, expert=teacher))
        pol, summ, _ = point_training(p, spec, f"{p.site.name}/{DISTILLED}/seed{seed}")
        pool.policies[DISTILLED][seed] = guard(p, _named(pol, DISTILLED))
        pool.summaries[f"{DISTILLED}_seed{seed}"] = {**summ, "teacher_base": teacher.base,
                                                     "state": spec.state.name}
        pool.keys[(DISTILLED, seed)] = on_pick_set(p, pool.policies[DISTILLED][seed], cache)
    print(f"[sweep] {p.site.name} {DISTILLED}: the planner over {teacher.base} distilled "
          f"onto the {spec.state.name} state", flush=True)


def aggregate(p: PointSettings, pool: Pool, results: dict[Any, dict[str, Any]],
              improved: dict[str, dict[str, Any]], best: tuple[str, int | None]
              ) -> list[dict[str, Any]]:
    """The point's rows (:class:`~fleet_torchrl.experiments.rows.Row`), ``best_known`` last,
    each with its share of ``best_known``'s gain over the rule."""
    rule = results.get(("rule", None))
    rows = [Row.of(name, {s: results[(name, s)] for s in g}, rule).improved(
        improved.get(name, {})) for name, g in pool.policies.items()]
    top = Row.of(BEST_KNOWN, {None: results[best]}, rule)
    top.seeds = [] if best[1] is None else [best[1]]
    for r in (*rows, top):  # share of the achievable gain: this row's gain over best_known's
        ok = top.gain_pct is not None and r.gain_pct is not None and top.gain_pct > 0
        r.share_of_best_known_pct = 100.0 * r.gain_pct / top.gain_pct if ok else None
    param, value = p.sweep.param, point_value(p.sweep.param, p.sweep.value)
    return [*(r.sweep_dict(param, value) for r in rows),
            top.sweep_dict(param, value, best_known=True)]


def write_point(p: PointSettings, path: Path, rows: list[dict[str, Any]], keys: dict[str, str],
                pool: Pool, best: tuple[str, int | None], wall_s: dict[str, float]) -> None:
    """The point's file (atomically), its ``.error`` of an earlier failure removed."""
    write_json(path, {"rows": rows, "site": p.site, **keys,
                      "wall_s": {k: round(v, 1) for k, v in wall_s.items()},
                      "best_known": {"from": best[0], "seed": best[1], "pick_set": {
                          (n if s is None else f"{n}_seed{s}"):
                          {"failure_rate": k[0], "trips_mean": -k[1]}
                          for (n, s), k in pool.keys.items()}},
                      "guard": p.sweep.guard,
                      "trainings": {n: {**{k: v[k] for k in ("run_dir", "wall_s", "best")},
                                        **{k: v[k] for k in ("init", "teacher_base", "state")
                                           if k in v}}
                                    for n, v in pool.summaries.items()},
                      "meta": p.meta})
    err = path.with_suffix(".error")
    if err.exists():
        err.unlink()


def say_rows(label: str, rows: list[dict[str, Any]], wall_s: dict[str, float]) -> None:
    print(f"[sweep] {label}: " + ", ".join(f"{k} {v:.0f} s" for k, v in wall_s.items()),
          flush=True)
    for r in rows:
        gain = f", gain {r['gain_pct']:+.2f} %" if r["gain_pct"] is not None else ""
        share = (f", {r['share_of_best_known_pct']:.0f} % of the best known"
                 if r["share_of_best_known_pct"] is not None else "")
        seeds = f" (seeds {r['seeds']})" if len(r["seeds"]) > 1 else ""
        print(f"[sweep] {label} {r['policy']}: {r['trips_mean']:.1f} trips{gain}{share}{seeds}")


def reuse_twin(p: PointSettings, path: Path, twin: str, key: str) -> list[dict[str, Any]] | None:
    """The rows of another sweep's point on the same site with the same settings (its
    ``twin_key``), written as this point's (``reused_from`` names the file); None if there
    is none."""
    param, value = p.sweep.param, point_value(p.sweep.param, p.sweep.value)
    for other in sorted(Path(p.sweep.out).glob("*/*=*.json")):
        if other.resolve() == path.resolve():
            continue
        try:
            data = read_json(other)
        except ValueError:
            continue
        if data.get("twin_key") != twin or "reused_from" in data:
            continue
        rows = [{**r, "param": param, "value": value} for r in data["rows"]]
        write_json(path, {**data, "rows": rows, "site": p.site, "key": key,
                          "reused_from": str(other)})
        print(f"[sweep] {p.site.name}: the same site and settings as {other}: its rows reused",
              flush=True)
        return rows
    return None


def one_step(p: PointSettings, pool: Pool, results: dict[Any, dict[str, Any]],
             rule: dict[str, Any] | None, cache: EvalCache | None = None
             ) -> dict[str, dict[str, Any]]:
    """What one step of policy improvement adds to the policies of ``sweep.improve`` (the
    best learned row's best seed on the pick set, ...): the planner over it on the first
    ``sweep.improve_sims`` sites of the evaluation, paired with its own records, in points
    of gain over the rule (:func:`~fleet_torchrl.experiments.improvement.improvement`). A
    base with a planner row of its own (``pool.planner_bases``: base row -> planner row; the
    heuristic's ``planner``, the search's ``planner_search``) takes that row, paired on
    every site. ``{row: improvement_*}``."""
    out: dict[str, dict[str, Any]] = {}
    if not p.sweep.planner or rule is None:
        return out
    for name, planner in pool.planner_bases.items():
        if (name, None) not in results:
            continue
        trips = {n: results[(n, None)]["records"]["trips"] for n in (planner, name)}
        pct, ci = paired_points(trips[planner], trips[name], rule["records"]["trips"])
        n = len(trips[planner])
        out[name] = {"improvement_pct": pct, "improvement_ci95": ci if n > 1 else None,
                     "improvement_sims": n, "improvement_seed": None}
    if not p.sweep.improve_sims:
        return out
    for want in p.sweep.improve:
        got = improve_best(p, pool, results, rule, want, out, cache)
        if got is not None:
            out[got[0]] = got[1]
    return out


def improve_best(p: PointSettings, pool: Pool, results: dict[Any, dict[str, Any]],
                 rule: dict[str, Any], want: str, done: dict[str, Any],
                 cache: EvalCache | None) -> tuple[str, dict[str, Any]] | None:
    """One step of improvement over the best row of ``want`` on the pick set (``best``,
    ``best_learned`` or a row's name); None where there is none or it has its figures."""
    cands = {k: v for k, v in pool.keys.items() if not k[0].startswith((PLANNER, BEST_KNOWN))}
    if want == "best_learned":
        cands = {k: v for k, v in cands.items() if is_learned(k[0])}
    elif want != "best":
        cands = {k: v for k, v in cands.items() if k[0] == want}
    if not cands:
        return None
    name, seed = best_of(cands)
    if name in done:
        return None
    e, pol, planner = p.eval, pool.policies[name][seed], p.planner
    parts = ["improvement", policy_fingerprint(pol), without_neutral(planner),
             site_identity(p.site), p.sweep.improve_sims, e.ticks, e.seed]
    imp = (cache or EvalCache(None)).get_or_compute(parts, partial(
        improvement, pol, results[(name, seed)], rule, p.site, p.sweep.improve_sims,
        e.ticks, e.seed, planner, e.device))
    print(f"[sweep] {p.site.name} {name}" + (f" seed {seed}" if seed is not None else "")
          + f": one step of improvement {imp['improvement_pct']:+.2f} "
          f"± {imp['improvement_ci95']:.2f} ({imp['sims']} sites)", flush=True)
    return name, {"improvement_pct": imp["improvement_pct"],
                  "improvement_ci95": imp["improvement_ci95"],
                  "improvement_sims": imp["sims"], "improvement_seed": seed}


def evaluated(cache: EvalCache, pol: Policy, site: SiteConfig, e: Any, name: str
              ) -> dict[str, Any]:
    """:func:`evaluate_with` through the point's evaluation cache."""
    return cache.evaluate(pol, site, e.n_sims, e.ticks, e.seed,
                          lambda: evaluate_with(pol, site, e, name=name), name=name)


__all__ = ["BEST_KNOWN", "CACHE_VERSION", "DISTILLED", "IMPROVEMENT_FIELDS", "PLANNER",
           "PLANNER_SEARCH", "POINT_FIELDS", "PointSettings", "best_of", "class_start",
           "digest", "distil_base", "distil_state", "distil_teacher", "is_learned",
           "point_path", "point_site", "point_value", "run_point", "search_base",
           "search_start", "seed_paths", "specialist_seeds"]
