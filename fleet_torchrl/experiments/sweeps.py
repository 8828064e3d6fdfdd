"""Generalisation sweeps (MODEL §5 item 3): policies trained on the default site, evaluated
on changed sites, next to the best policy the point itself allows.

    make sweep-pc      # = python -m fleet_torchrl.sweeps -m +experiment=sweep_pc
                       #   then fleet-sweeps-summary name=pc

Each Hydra job evaluates every policy of ``sweep.policies`` at one point (``site.<param> =
sweep.value``) with the evaluation protocol (``eval.n_sims`` x ``eval.ticks``, common random
numbers: all policies of a point see the same sites). With ``sweep.search`` (default) it also
runs the direct policy search (``agent=search``, MODEL §3.4) on the point's own site and
evaluates what it found as the row ``optimum``; every row then reports its share of the
optimum's gain over the rule. Policies are compared on the point's *pick set*: the search's
selection seed (``train.eval_seed``, never the evaluation's sites) with ``sweep.pick_sims``
x ``sweep.pick_ticks``. With ``sweep.search_seeded`` (default) the search starts from the
``partial``-state policy of ``sweep.policies`` whose start (for the table class, its action
table) does best on the pick set, so the optimum begins at the best policy known there and
the search improves on it. The row ``optimum`` is what the search found, unless one of the
policies it competes with does better on the pick set: the best policy known at the point,
chosen without the evaluation's sites (the JSON's ``search.optimum_from`` says which). A
search is cached under ``sweep.search_dir/<point>/<key>``, ``key`` a hash of its training
settings and of the policy it starts from, and reused whenever they match.

The point's file ``results/sweeps/<name>/<param>=<value>.json`` is written atomically and
records a key of everything it depends on (the site, the evaluation settings, each policy's
identity: a baseline's parameters, a saved policy's file hash, the search's settings). A
rerun skips a point whose key matches and recomputes one whose settings or policies changed;
a point that fails writes an ``.error`` file beside it and does not stop the other points.
The saved policies must exist (``make policies`` trains what is missing); a job trains only
its point's search.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from ..agents import AGENTS, load_policy_file
from ..agents.base import Policy
from ..agents.policy_files import POLICY_FILE
from ..agents.search import SearchPolicy, cell_centres, clone_policy
from ..config import Config, compose_config
from ..evaluation import evaluate_policy, evaluate_with, gain_over
from ..sim import SiteConfig
from ..store import load_policies, saved_policy_path
from ..training import Trainer, training_fingerprint
from ..utils.checks import ConfigError
from ..utils.runinfo import file_sha256, read_json, run_info, to_jsonable, write_json
from .table import reusable

POINT_FIELDS = ("param", "value", "policy", "trips_mean", "trips_std", "queue_mean",
                "failure_rate", "gain_pct", "gain_ci95", "share_of_optimum_pct")
OPTIMUM = "optimum"  # the row of the point's own direct policy search
# the point's search among the candidates for that row (not "search": that name is the
# default-site search policy of sweep.policies)
POINT_SEARCH = "point_search"


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


def search_config(cfg: Config, site: SiteConfig) -> Config:
    """The training config of the point's search (``sweep.search_overrides`` on the search
    defaults, the point's site)."""
    run_cfg = compose_config(["agent=search", "train.threads=1", *cfg.sweep.search_overrides,
                              "train.progress=false", "train.tensorboard=false"])
    run_cfg.site = site
    return run_cfg


def on_pick_set(cfg: Config, run_cfg: Config, pol: Policy) -> tuple[float, float]:
    """``(failure rate, -mean trips)`` of a policy on the point's pick set: the search's
    selection seed (``train.eval_seed``, apart from the evaluation's sites) with
    ``sweep.pick_sims`` x ``sweep.pick_ticks``; lower is better."""
    res = evaluate_policy(pol, run_cfg.site, cfg.sweep.pick_sims, cfg.sweep.pick_ticks,
                          run_cfg.train.eval_seed, cfg.eval.device)
    return res["failure_rate"], -res["trips_mean"]


def best_known(keys: dict[str, tuple[float, float]]) -> str:
    """The name with the best :func:`on_pick_set` key; the point's own search
    (:data:`POINT_SEARCH`) on a tie."""
    return min(keys, key=lambda n: (keys[n], n != POINT_SEARCH))


def search_start(cfg: Config, run_cfg: Config, policies: dict[str, Policy]) -> str:
    """The ``agent.init`` of the point's search: the ``partial``-state policy of the point
    whose start of the search (for the table class: its action table, what the search can
    represent of it) does best on the point's pick set, as a baseline's name or a
    saved policy's path."""
    a = run_cfg.agent
    best: tuple[tuple[float, float], str] | None = None
    for name, pol in policies.items():
        if pol.encoding != "partial":
            continue
        start = SearchPolicy(a.policy_class, a.hidden, a.depth)  # what the search starts from
        if a.policy_class == "table":
            start.charge.copy_(pol(cell_centres().to(cfg.eval.device)).long().cpu())
        else:
            start.theta.copy_(clone_policy(pol.cpu(), start.sizes, run_cfg.seed, run_cfg.site))
            pol.to(cfg.eval.device)
        key = on_pick_set(cfg, run_cfg, start)
        if best is None or key < best[0]:
            best = (key, name)
    if best is None:
        return run_cfg.agent.init
    spec = AGENTS.get(best[1])
    if spec is not None and not spec.trainable:
        return best[1]
    return str(saved_policy_path(cfg.table.policies_dir, best[1]))


def point_search(cfg: Config, run_cfg: Config, label: str) -> tuple[Policy, dict[str, Any]]:
    """The point's search policy (trained with ``run_cfg``, the point's
    :func:`search_config`, or reused when its settings and start match) and its summary."""
    init = Path(run_cfg.agent.init)
    init = init / POLICY_FILE if init.is_dir() else init
    start = file_sha256(init) if init.is_file() else None
    out = Path(cfg.sweep.search_dir) / label / digest([training_fingerprint(run_cfg), start])
    run_cfg.train.out_dir = str(out)
    if not reusable(out, run_cfg):
        print(f"[sweep] {label}: searching the point's optimum -> {out}", flush=True)
        Trainer(run_cfg, out / "run").run()
    else:
        print(f"[sweep] {label}: reusing the search in {out}", flush=True)
    return load_policy_file(out), read_json(out / "train_summary.json")


def point_key(cfg: Config, site: SiteConfig, search_cfg: Config | None) -> str:
    """Everything a point's result depends on, hashed (the sweep cache's key)."""
    e = cfg.eval
    parts: dict[str, Any] = {
        "site": site, "eval": {"n_sims": e.n_sims, "ticks": e.ticks, "seed": e.seed},
        "policies": [policy_identity(cfg, n) for n in cfg.sweep.policies]}
    if search_cfg is not None:
        parts["search"] = training_fingerprint(search_cfg)
        parts["search_seeded"] = cfg.sweep.search_seeded
        parts["pick"] = [cfg.sweep.pick_sims, cfg.sweep.pick_ticks]
        parts["optimum"] = "best of the point's search and the policies on the pick set"
    return digest(parts)


def point_value(param: str, value: float) -> float | int:
    return int(round(value)) if param in ("t_c", "n_vehicles") else float(value)


def point_path(cfg: Config) -> Path:
    v = point_value(cfg.sweep.param, cfg.sweep.value)
    return Path(cfg.sweep.out) / cfg.sweep.name / f"{cfg.sweep.param}={v}.json"


def run_point(cfg: Config) -> list[dict[str, Any]] | None:
    """Evaluate all policies at this job's point; returns the rows (None if already done)."""
    path = point_path(cfg)
    param = cfg.sweep.param
    value = point_value(param, cfg.sweep.value)
    label = f"{param}={value}"
    if cfg.site.randomized:
        raise ConfigError(f"site={cfg.site.name!r} is a site distribution: a sweep varies "
                          f"{param} of one site; run it on a single site (e.g. site=default)")
    site = replace(cfg.site, **{param: value}, name=label).validate()
    search_cfg = search_config(cfg, site) if cfg.sweep.search else None
    key = point_key(cfg, site, search_cfg)
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
    search_summary = None
    optimum_from = None
    if search_cfg is not None:
        if cfg.sweep.search_seeded and not any(o.split("=", 1)[0].lstrip("+~") == "agent.init"
                                               for o in cfg.sweep.search_overrides):
            search_cfg.agent.init = search_start(cfg, search_cfg, policies)
            print(f"[sweep] {label}: the search starts from {search_cfg.agent.init}",
                  flush=True)
        found, search_summary = point_search(cfg, search_cfg, label)
        # the optimum: what the search found, unless a policy it competes with does better
        # on the pick set (never on the evaluation's sites)
        keys = {name: on_pick_set(cfg, search_cfg, pol)
                for name, pol in {POINT_SEARCH: found, **policies}.items()}
        optimum_from = best_known(keys)
        policies[OPTIMUM] = found if optimum_from == POINT_SEARCH else policies[optimum_from]
        print(f"[sweep] {label}: the optimum is {optimum_from}'s policy "
              f"({-keys[optimum_from][1]:.1f} trips on the pick set, the search's "
              f"{-keys[POINT_SEARCH][1]:.1f})", flush=True)
    results = {name: evaluate_with(pol, site, e, name=name) for name, pol in policies.items()}
    rule = results.get("rule")
    rows = []
    for name, res in results.items():
        g = gain_over(res, rule) if rule is not None else {"gain_pct": None, "gain_ci95": None}
        rows.append({"param": param, "value": value, "policy": name,
                     **{k: res[k] for k in ("trips_mean", "trips_std", "queue_mean",
                                            "failure_rate")},
                     "gain_pct": g["gain_pct"], "gain_ci95": g["gain_ci95"]})
    best = next((r["gain_pct"] for r in rows if r["policy"] == OPTIMUM), None)
    for r in rows:  # share of the achievable gain: this policy's gain over the optimum's
        ok = best is not None and r["gain_pct"] is not None and best > 0
        r["share_of_optimum_pct"] = 100.0 * r["gain_pct"] / best if ok else None
    write_json(path, {"rows": rows, "site": site, "key": key,
                      "search": search_summary and {
                          **{k: search_summary[k] for k in ("run_dir", "wall_s", "best")},
                          "init": search_cfg.agent.init, "optimum_from": optimum_from},
                      "meta": run_info(cfg, seed=e.seed)})
    err = path.with_suffix(".error")
    if err.exists():
        err.unlink()
    for r in rows:
        gain = f", gain {r['gain_pct']:+.2f} %" if r["gain_pct"] is not None else ""
        share = (f", {r['share_of_optimum_pct']:.0f} % of the optimum's"
                 if r["share_of_optimum_pct"] is not None else "")
        print(f"[sweep] {label} {r['policy']}: {r['trips_mean']:.1f} trips{gain}{share}")
    return rows
