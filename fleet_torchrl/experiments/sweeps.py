"""Generalisation sweeps (MODEL §5 item 3): policies trained on the default site, evaluated
on changed sites.

    make sweep-pc      # = python -m fleet_torchrl.sweeps -m +experiment=sweep_pc
                       #   then python -m fleet_torchrl.sweeps_summary pc

Each Hydra job evaluates every policy of ``sweep.policies`` at one point (``site.<param> =
sweep.value``) with the evaluation protocol (``eval.n_sims`` x ``eval.ticks``, common random
numbers: all policies of a point see the same sites) and writes
``results/sweeps/<name>/<param>=<value>.json`` atomically. A point whose file exists is
skipped, so rerunning a sweep only runs what is missing; a point that fails writes an
``.error`` file beside it and does not stop the other points. The saved policies must exist
(``make policies`` trains what is missing); a job never trains.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..agents import load_policies
from ..evaluation import evaluate_with, gain_over
from ..utils.runinfo import run_info, write_json

if TYPE_CHECKING:
    from ..config import Config

POINT_FIELDS = ("param", "value", "policy", "trips_mean", "trips_std", "queue_mean",
                "failure_rate", "gain_pct", "gain_ci95")


def point_value(param: str, value: float) -> float | int:
    return int(round(value)) if param in ("t_c", "n_vehicles") else float(value)


def point_path(cfg: Config) -> Path:
    v = point_value(cfg.sweep.param, cfg.sweep.value)
    return Path(cfg.sweep.out) / cfg.sweep.name / f"{cfg.sweep.param}={v}.json"


def run_point(cfg: Config) -> list[dict[str, Any]] | None:
    """Evaluate all policies at this job's point; returns the rows (None if already done)."""
    path = point_path(cfg)
    if path.exists():
        print(f"[sweep] {path} exists, skipping")
        return None
    param = cfg.sweep.param
    value = point_value(param, cfg.sweep.value)
    site = replace(cfg.site, **{param: value}, name=f"{param}={value}").validate()
    e = cfg.eval
    results = {name: evaluate_with(pol, site, e, name=name)
               for name, pol in load_policies(cfg, cfg.sweep.policies).items()}
    rule = results.get("rule")
    rows = []
    for name, res in results.items():
        g = gain_over(res, rule) if rule is not None else {"gain_pct": None, "gain_ci95": None}
        rows.append({"param": param, "value": value, "policy": name,
                     **{k: res[k] for k in ("trips_mean", "trips_std", "queue_mean",
                                            "failure_rate")},
                     "gain_pct": g["gain_pct"], "gain_ci95": g["gain_ci95"]})
    write_json(path, {"rows": rows, "site": site, "meta": run_info(cfg, seed=e.seed)})
    err = path.with_suffix(".error")
    if err.exists():
        err.unlink()
    for r in rows:
        gain = f", gain {r['gain_pct']:+.2f} %" if r["gain_pct"] is not None else ""
        print(f"[sweep] {param}={value} {r['policy']}: {r['trips_mean']:.1f} trips{gain}")
    return rows
