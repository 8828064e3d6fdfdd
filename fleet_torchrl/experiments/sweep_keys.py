"""The sweep cache's keys: everything a sweep point's rows depend on, hashed.

A point's file records :func:`point_key`; a rerun skips a point whose key matches. Its
:func:`twin_key` (the key with the site's name left out) lets a point reuse the rows of
another sweep's point on the same site. What the key cannot see, how the point turns its
inputs into rows (which rows exist, how ``best_known`` is picked, which seeds a learned row
pools, how the distilled row's teacher is chosen), is :data:`CACHE_VERSION`: raise it when
that changes, and every saved point is recomputed once.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..agents import AGENTS
from ..agents.policy_files import POLICY_FILE
from ..sim import SiteConfig
from ..store import inside, saved_policy_path
from ..training import result_fingerprint
from ..training.checkpoint import without_neutral
from ..utils.runinfo import file_sha256, to_jsonable
from .config import SweepConfig, TableConfig

# the point's own computation (rows, pick, pooling of seeds, the distilled row's teacher):
# raise it when a point computes its rows otherwise from the same inputs
CACHE_VERSION = 1


def digest(obj: Any) -> str:
    """A short stable hash of a JSON-ready object."""
    text = json.dumps(to_jsonable(obj), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def seed_paths(table: TableConfig, name: str) -> dict[int, Path]:
    """Every training seed's policy file of a learned policy of ``sweep.policies`` (``make
    table``'s ``<name>/seed<s>/``), or its one policy (``make train``'s ``<name>/``) as seed 0;
    empty for a baseline."""
    spec = AGENTS.get(name)
    if spec is not None and not spec.trainable:
        return {}
    root, follow = table.policies_dir, table.follow_symlinks
    folder = Path(root) / name
    seeds = {int(p.parent.name[4:]): inside(root, p, follow)
             for p in inside(root, folder, follow).glob(f"seed*/{POLICY_FILE}")
             if p.parent.name[4:].isdigit()}
    if not seeds:
        seeds = {0: saved_policy_path(root, name, follow)}
    return dict(sorted(seeds.items()))


def policy_identity(table: TableConfig, name: str) -> str:
    """What a policy of ``sweep.policies`` is: a baseline's parameters, or the hash of the
    saved policy file the name stands for."""
    spec = AGENTS.get(name)
    if spec is not None and not spec.trainable:
        return f"{name}:{digest(without_neutral(spec.schema()))}"
    path = saved_policy_path(table.policies_dir, name, table.follow_symlinks)
    if not path.is_file():
        return f"{name}:missing"
    return f"{name}:{file_sha256(path)[:16]}"


def point_key(sweep: SweepConfig, table: TableConfig, ev: Any, site: SiteConfig,
              searches: dict[str, Any], specialists: dict[str, dict[int, Any]],
              planner: Any) -> str:
    """Everything a point's result depends on, hashed (the sweep cache's key): the site, the
    evaluation and pick settings, each policy's identity, the trainings' fingerprints (the
    run specs of ``searches`` ``{row: spec}`` and ``specialists`` ``{row: {seed: spec}}``),
    the planner's settings, the rows asked for, and :data:`CACHE_VERSION`."""
    s = sweep
    parts: dict[str, Any] = {
        "version": CACHE_VERSION,
        "site": site, "eval": {"n_sims": ev.n_sims, "ticks": ev.ticks, "seed": ev.seed},
        "policies": [policy_identity(table, n) for n in s.policies]
        + [str(p) + ":" + file_sha256(p)[:16] for n in s.policies
           for p in seed_paths(table, n).values()],
        "searches": {k: result_fingerprint(v) for k, v in searches.items()},
        "specialists": {row: {seed: result_fingerprint(c) for seed, c in runs.items()}
                        for row, runs in specialists.items()},
        "guard": s.guard, "search_seeded": s.search_seeded, "pick": [s.pick_sims, s.pick_ticks],
        "planner": without_neutral(planner) if s.planner else None,
        "planner_search": s.planner and s.planner_search,
        "distil": bool(s.specialist and s.distil),
        "improve": [list(s.improve), s.improve_sims]}
    return digest(parts)


def twin_key(sweep: SweepConfig, table: TableConfig, ev: Any, site: SiteConfig,
             searches: dict[str, Any], specialists: dict[str, dict[int, Any]],
             planner: Any) -> str:
    """The point's key with the site's name left out: two sweeps that reach the same site
    (the default site is ``p_c`` 0.8, ``T_C`` 30 and ``N_V`` 3) compute the same rows."""
    neutral = replace(site, name="sweep point")
    return point_key(sweep, table, ev, neutral,
                     {k: replace(v, site=neutral) for k, v in searches.items()},
                     {r: {s: replace(c, site=neutral) for s, c in runs.items()}
                      for r, runs in specialists.items()}, planner)


__all__ = ["CACHE_VERSION", "digest", "point_key", "policy_identity", "seed_paths",
           "twin_key"]
