"""Summary of a grid-search multirun (``make grid``): rank configurations across seeds.

    fleet-grid sweep_dir=multirun/grid/<date_time>     # or none: the latest

Reads every job's ``train_summary.json`` and ``.hydra/overrides.yaml``, groups the jobs by
their overrides without ``seed``, and ranks the configurations by the mean (over seeds) of
their best evaluation trips, failure rate breaking ties the other way. Writes ``summary.md``,
``summary.csv`` and ``summary.json`` into the sweep folder and copies them to
``results/grid/``. Jobs that did not finish are listed as missing, not dropped silently.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any

import yaml

from ..utils.runinfo import read_json

FIELDS = ("rank", "config", "seeds", "trips_mean", "trips_std", "gain_pct_mean",
          "failure_rate_mean", "queue_mean")


def _split(overrides: list[str]) -> dict[str, str]:
    return dict(o.split("=", 1) for o in overrides if "=" in o and not o.startswith("+"))


def collect(sweep_dir: Path) -> tuple[list[dict[str, Any]], list[str], dict[str, str]]:
    """Finished jobs, missing jobs, and the overrides shared by all jobs.

    A job's ``config`` names only the overrides that vary across the sweep (seed excluded).
    """
    raw, missing = [], []
    for job in sorted(p for p in sweep_dir.iterdir() if p.is_dir() and (p / ".hydra").is_dir()):
        overrides = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text()) or []
        summary = job / "train_summary.json"
        if not summary.exists():
            missing.append(f"{job.name}: {' '.join(overrides)}")
            continue
        raw.append((job.name, _split(overrides), read_json(summary).get("best") or {}))
    keys = {k for _, o, _ in raw for k in o if k != "seed"}
    varying = {k for k in keys if len({o.get(k) for _, o, _ in raw}) > 1}
    shared = {k: raw[0][1][k] for k in sorted(keys - varying) if k in raw[0][1]} if raw else {}
    jobs = []
    for name, o, best in raw:
        config = " ".join(f"{k}={o[k]}" for k in sorted(varying) if k in o)
        jobs.append({"job": name, "config": config or "(one configuration)",
                     "seed": o.get("seed", "0"), **best})
    return jobs, missing, shared


def summarize(jobs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    groups: dict[str, list[dict[str, Any]]] = {}
    for j in jobs:
        groups.setdefault(j["config"], []).append(j)
    rows = []
    for config, js in groups.items():
        trips = [j["trips"] for j in js]
        rows.append({"config": config, "seeds": len(js),
                     "trips_mean": statistics.fmean(trips),
                     "trips_std": statistics.stdev(trips) if len(trips) > 1 else 0.0,
                     "gain_pct_mean": statistics.fmean(j["gain_pct"] for j in js),
                     "failure_rate_mean": statistics.fmean(j["failure_rate"] for j in js),
                     "queue_mean": statistics.fmean(j["queue"] for j in js)})
    rows.sort(key=lambda r: (-r["trips_mean"], r["failure_rate_mean"]))
    for i, r in enumerate(rows, 1):
        r["rank"] = i
    return [{k: r[k] for k in FIELDS} for r in rows]


def markdown(rows: list[dict[str, Any]], missing: list[str], sweep_dir: Path,
             shared: dict[str, str]) -> str:
    lines = [f"# Grid search summary ({sweep_dir})", "",
             "Best evaluation of each run (train.eval_* set), averaged over seeds.",
             "Shared by all runs: " + (" ".join(f"`{k}={v}`" for k, v in shared.items())
                                       or "(nothing)"), "",
             "| rank | config | seeds | eval trips | ± std | gain % vs rule | failure rate "
             "| queue |",
             "|---:|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['rank']} | {r['config']} | {r['seeds']} | {r['trips_mean']:.2f} | "
                     f"{r['trips_std']:.2f} | {r['gain_pct_mean']:+.2f} | "
                     f"{r['failure_rate_mean']:.3f} | {r['queue_mean']:.1f} |")
    if missing:
        lines += ["", "Missing (failed or unfinished) jobs:", *[f"- {m}" for m in missing]]
    return "\n".join(lines) + "\n"


def latest_sweep(root: Path = Path("multirun/grid")) -> Path:
    dirs = sorted(p for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    if not dirs:
        raise FileNotFoundError(f"no grid sweep under {root}; run `make grid` first")
    return dirs[-1]
