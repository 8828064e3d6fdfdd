"""Summary of a grid-search multirun (``make grid``): rank configurations across seeds.

    fleet-grid sweep_dir=multirun/grid/<date_time>     # or none: the latest

Reads every job's ``train_summary.json`` and ``.hydra/overrides.yaml``, groups the jobs by
their overrides without ``seed``, and ranks the configurations by the mean (over seeds) of
their best evaluation trips, failure rate breaking ties the other way. Writes ``summary.md``,
``summary.csv`` and ``summary.json`` into the sweep folder and copies them to
``results/grid/``. Jobs that did not finish are listed as missing, not dropped silently.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Any

import yaml

from ..utils.runinfo import read_json

FIELDS = ("rank", "config", "seeds", "trips_mean", "trips_std", "gain_pct_mean",
          "failure_rate_mean", "queue_mean")


def _split(overrides: list[str]) -> dict[str, str]:
    return dict(o.split("=", 1) for o in overrides if "=" in o and not o.startswith("+"))


BEST_KEYS = ("trips", "gain_pct", "failure_rate", "queue")  # what fleet-train records


def _yaml(path: Path) -> Any:
    try:
        return yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None


def grid_job(job: Path) -> list[str] | None:
    """The overrides of ``job`` if it is a job folder of a multirun of ``fleet-train`` (what
    ``make grid`` makes: ``.hydra/hydra.yaml`` of a train job in MULTIRUN mode, its
    overrides a list of ``key=value``), else None: folders of other runs are not summarised."""
    meta = _yaml(job / ".hydra" / "hydra.yaml")
    hydra = meta.get("hydra") if isinstance(meta, dict) else None
    if not isinstance(hydra, dict) or str(hydra.get("mode")) != "MULTIRUN" or \
            (hydra.get("job") or {}).get("name") != "train":
        return None
    overrides = _yaml(job / ".hydra" / "overrides.yaml")
    if overrides is None:
        overrides = []
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        return None
    return overrides


def finished_best(job: Path) -> dict[str, Any] | None:
    """The best evaluation a finished train job recorded (``train_summary.json``), or None
    if it did not finish or its summary is not one ``fleet-train`` writes."""
    summary = job / "train_summary.json"
    if not summary.is_file():
        return None
    try:
        best = read_json(summary).get("best")
    except (ValueError, AttributeError):
        return None
    if not isinstance(best, dict) or not all(
            isinstance(best.get(k), (int, float)) and math.isfinite(best[k]) for k in BEST_KEYS):
        return None
    return best


def collect(sweep_dir: Path) -> tuple[list[dict[str, Any]], list[str], dict[str, str]]:
    """Finished jobs, missing jobs, and the overrides shared by all jobs.

    A job's ``config`` names only the overrides that vary across the sweep (seed excluded).
    Only job folders of a ``fleet-train`` multirun count (:func:`grid_job`); a folder
    without any raises ``FileNotFoundError`` (nothing is written for it).
    """
    raw, missing = [], []
    for job in sorted(p for p in sweep_dir.iterdir() if p.is_dir() and (p / ".hydra").is_dir()):
        overrides = grid_job(job)
        if overrides is None:
            continue
        best = finished_best(job)
        if best is None:
            missing.append(f"{job.name}: {' '.join(overrides)}")
            continue
        raw.append((job.name, _split(overrides), best))
    if not raw and not missing:
        raise FileNotFoundError(f"sweep_dir={sweep_dir} holds no grid runs (job folders of a "
                                "fleet-train multirun, make grid); nothing was written")
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
