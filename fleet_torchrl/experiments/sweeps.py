"""Generalisation sweeps (MODEL §5 item 3): policies trained on the default site, evaluated
on changed sites, next to the best policy known at each point.

    make sweep-pc      # = python -m fleet_torchrl.sweeps -m +experiment=sweep_pc
                       #   then python -m fleet_torchrl.sweeps_summary pc

Each Hydra job evaluates, at one point (``site.<param> = sweep.value``), with the evaluation
protocol (``eval.n_sims`` x ``eval.ticks``, common random numbers: every row sees the same
sites):

* every policy of ``sweep.policies`` (baselines, and the default-site learners);
* the point's own searches (``sweep.searches``, unless ``sweep.search=false``: the direct
  policy search, MODEL §3.4, with
  policy classes that read the charger's remaining time), each started from the best start
  of its class among the rule, the heuristic and every saved policy (``sweep.search_seeded``)
  and cached under ``sweep.search_dir/<point>/<key>`` by its training settings and start;
* the rollout planner (MODEL §3.6) with the heuristic as base (row ``planner``), and one
  step of policy improvement over each policy of ``sweep.improve`` (``best_learned``: the
  best learned policy of the point) (rows ``planner_<name>``): how far each is from the
  best its site allows;
* ``best_known``: of all the rows above, the best on the point's *pick set* (the searches'
  selection seed ``train.eval_seed`` with ``sweep.pick_sims`` x ``sweep.pick_ticks``, never
  the evaluation's sites): fewer failed simulations first, then more trips. Every row
  reports its share of ``best_known``'s gain over the rule; the JSON's
  ``best_known.from`` names the row it is.

The point's file ``results/sweeps/<name>/<param>=<value>.json`` is written atomically and
records a key of everything it depends on (the site, the evaluation and pick settings, each
policy's identity: a baseline's parameters, a saved policy's file hash, the searches' and
the planner's settings). A rerun skips a point whose key matches and recomputes one whose
settings or policies changed; a point that fails writes an ``.error`` file beside it and
does not stop the other points. The saved policies must exist (``make policies`` trains
what is missing); a job trains only its point's searches.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from ..agents import AGENTS, load_policy_file
from ..agents.base import Policy
from ..agents.baselines import HeuristicPolicy
from ..agents.planner import PlannerPolicy
from ..agents.policy_files import POLICY_FILE
from ..agents.search import SearchPolicy, cell_centres, clone_policy, threshold_start
from ..config import Config, compose_config
from ..evaluation import evaluate_policy, evaluate_with, gain_over
from ..sim import SiteConfig
from ..store import load_policies, saved_policy_path
from ..training import Trainer, training_fingerprint
from ..utils.checks import ConfigError
from ..utils.runinfo import file_sha256, read_json, run_info, to_jsonable, write_json
from .table import reusable

POINT_FIELDS = ("param", "value", "policy", "trips_mean", "trips_std", "queue_mean",
                "failure_rate", "gain_pct", "gain_ci95", "share_of_best_known_pct")
BEST_KNOWN = "best_known"  # the row of the best policy known at the point
PLANNER = "planner"  # the rollout planner over the heuristic


def digest(obj: Any) -> str:
    """A short stable hash of a JSON-ready object."""
    text = json.dumps(to_jsonable(obj), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def policy_identity(cfg: Config, name: str) -> str:
    """What a policy of ``sweep.policies`` is: a baseline's parameters, or the hash of the
    saved policy file the name stands for."""
    spec = AGENTS.get(name)
    if spec is not None and not spec.trainable:
        return f"{name}:{digest(asdict(spec.schema()))}"
    path = saved_policy_path(cfg.table.policies_dir, name)
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
    return PlannerPolicy.from_config(planner_config(cfg), base)


def on_pick_set(cfg: Config, site: SiteConfig, pol: Policy) -> tuple[float, float]:
    """``(failure rate, -mean trips)`` of a policy on the point's pick set: the searches'
    selection seed (``train.eval_seed``, apart from the evaluation's sites) with
    ``sweep.pick_sims`` x ``sweep.pick_ticks``; lower is better."""
    seed = compose_config(["agent=search"]).train.eval_seed
    res = evaluate_policy(pol, site, cfg.sweep.pick_sims, cfg.sweep.pick_ticks, seed,
                          cfg.eval.device)
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


def search_start(cfg: Config, run_cfg: Config, policies: dict[str, Policy]) -> str:
    """The ``agent.init`` of a point's search: of the rule, the heuristic and the
    ``partial``-state policies of the point, the one whose start of the search (what its
    class can represent of it) does best on the point's pick set, as a baseline's name or a
    saved policy's path."""
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
    return str(saved_policy_path(cfg.table.policies_dir, best[1]))


def point_search(cfg: Config, run_cfg: Config, label: str) -> tuple[Policy, dict[str, Any]]:
    """A point's search policy (trained with ``run_cfg``, or reused when its settings and
    start match) and its summary."""
    init = Path(run_cfg.agent.init)
    init = init / POLICY_FILE if init.is_dir() else init
    start = file_sha256(init) if init.is_file() else None
    out = Path(cfg.sweep.search_dir) / label / digest([training_fingerprint(run_cfg), start])
    run_cfg.train.out_dir = str(out)
    if not reusable(out, run_cfg):
        print(f"[sweep] {label}: searching -> {out}", flush=True)
        Trainer(run_cfg, out / "run").run()
    else:
        print(f"[sweep] {label}: reusing the search in {out}", flush=True)
    return load_policy_file(out), read_json(out / "train_summary.json")


def point_key(cfg: Config, site: SiteConfig, search_cfgs: dict[str, Config]) -> str:
    """Everything a point's result depends on, hashed (the sweep cache's key)."""
    e, s = cfg.eval, cfg.sweep
    parts: dict[str, Any] = {
        "site": site, "eval": {"n_sims": e.n_sims, "ticks": e.ticks, "seed": e.seed},
        "policies": [policy_identity(cfg, n) for n in s.policies],
        "searches": {k: training_fingerprint(v) for k, v in search_cfgs.items()},
        "search_seeded": s.search_seeded, "pick": [s.pick_sims, s.pick_ticks],
        "planner": asdict(planner_config(cfg)) if s.planner else None,
        "improve": list(s.improve),
        "best_known": "best of every row on the pick set (failures, then trips)"}
    return digest(parts)


def point_value(param: str, value: float) -> float | int:
    return int(round(value)) if param in ("t_c", "n_vehicles") else float(value)


def point_path(cfg: Config) -> Path:
    v = point_value(cfg.sweep.param, cfg.sweep.value)
    return Path(cfg.sweep.out) / cfg.sweep.name / f"{cfg.sweep.param}={v}.json"


def best_of(keys: dict[str, tuple[float, float]]) -> str:
    """The name with the best pick-set key (fewer failures, then more trips); on a tie the
    first in order (policies before searches before planners)."""
    return min(keys, key=lambda n: keys[n])


def run_point(cfg: Config) -> list[dict[str, Any]] | None:
    """Evaluate every row at this job's point; returns the rows (None if already done)."""
    path = point_path(cfg)
    param = cfg.sweep.param
    value = point_value(param, cfg.sweep.value)
    label = f"{param}={value}"
    if cfg.site.randomized:
        raise ConfigError(f"site={cfg.site.name!r} is a site distribution: a sweep varies "
                          f"{param} of one site; run it on a single site (e.g. site=default)")
    site = replace(cfg.site, **{param: value}, name=label).validate()
    search_cfgs = ({k: search_config(cfg, site, o) for k, o in cfg.sweep.searches.items()}
                   if cfg.sweep.search else {})
    key = point_key(cfg, site, search_cfgs)
    if path.exists():
        try:
            old = read_json(path).get("key")
        except ValueError:
            old = None
        if old == key:
            print(f"[sweep] {path} exists, skipping")
            return None
        print(f"[sweep] {path} was computed with other settings or policies: recomputing")
    e = cfg.eval
    policies = load_policies(cfg, cfg.sweep.policies)
    searches, summaries = {}, {}
    for name, run_cfg in search_cfgs.items():
        if cfg.sweep.search_seeded and not any(o.split("=", 1)[0].lstrip("+~") == "agent.init"
                                               for o in cfg.sweep.searches[name]):
            run_cfg.agent.init = search_start(cfg, run_cfg, policies)
            print(f"[sweep] {label} {name}: starts from {run_cfg.agent.init}", flush=True)
        searches[name], summaries[name] = point_search(cfg, run_cfg, f"{label}/{name}")
        summaries[name]["init"] = run_cfg.agent.init
    candidates: dict[str, Policy] = {**policies, **searches}
    keys = {name: on_pick_set(cfg, site, pol) for name, pol in candidates.items()}
    if cfg.sweep.planner:
        candidates[PLANNER] = make_planner(cfg, HeuristicPolicy())
        keys[PLANNER] = on_pick_set(cfg, site, candidates[PLANNER])
        for name in cfg.sweep.improve:
            if name == "best_learned":
                learned = [n for n in policies  # (the searches are not learners)
                           if n not in AGENTS and not n.startswith("search")]
                if not learned:
                    continue
                name = best_of({n: keys[n] for n in learned})
            if name == "heuristic":
                continue  # that is the planner row itself
            row = f"{PLANNER}_{name}"
            candidates[row] = make_planner(cfg, policies[name])
            keys[row] = on_pick_set(cfg, site, candidates[row])
    best = best_of(keys)
    print(f"[sweep] {label}: best known is {best} ({-keys[best][1]:.1f} trips on the pick "
          "set)", flush=True)
    results = {name: evaluate_with(pol, site, e, name=name) for name, pol in candidates.items()}
    results[BEST_KNOWN] = {**results[best], "policy": BEST_KNOWN}
    rule = results.get("rule")
    rows = []
    for name, res in results.items():
        g = gain_over(res, rule) if rule is not None else {"gain_pct": None, "gain_ci95": None}
        rows.append({"param": param, "value": value, "policy": name,
                     **{k: res[k] for k in ("trips_mean", "trips_std", "queue_mean",
                                            "failure_rate")},
                     "gain_pct": g["gain_pct"], "gain_ci95": g["gain_ci95"]})
    top = next(r["gain_pct"] for r in rows if r["policy"] == BEST_KNOWN)
    for r in rows:  # share of the achievable gain: this row's gain over best_known's
        ok = top is not None and r["gain_pct"] is not None and top > 0
        r["share_of_best_known_pct"] = 100.0 * r["gain_pct"] / top if ok else None
    write_json(path, {"rows": rows, "site": site, "key": key,
                      "best_known": {"from": best, "pick_set": {
                          n: {"failure_rate": k[0], "trips_mean": -k[1]}
                          for n, k in keys.items()}},
                      "searches": {n: {**{k: s[k] for k in ("run_dir", "wall_s", "best")},
                                       "init": s["init"]} for n, s in summaries.items()},
                      "meta": run_info(cfg, seed=e.seed)})
    err = path.with_suffix(".error")
    if err.exists():
        err.unlink()
    for r in rows:
        gain = f", gain {r['gain_pct']:+.2f} %" if r["gain_pct"] is not None else ""
        share = (f", {r['share_of_best_known_pct']:.0f} % of the best known"
                 if r["share_of_best_known_pct"] is not None else "")
        print(f"[sweep] {label} {r['policy']}: {r['trips_mean']:.1f} trips{gain}{share}")
    return rows
