"""``make table``: the main comparison of MODEL §5 item 1 in one command.

    python -m fleet_torchrl.table                       # defaults: 1000 sims x 10 000 ticks
    python -m fleet_torchrl.table eval.n_sims=200 table.retrain=true

1. For each learned policy (``table.train``: tabular, DQN on ``partial``, DQN on ``all``), reuse
   ``results/policies/<name>/policy.pt`` if it exists, else train it in a subprocess
   (``python -m fleet_torchrl.train``) whose Hydra run directory is
   ``outputs/table/train_<name>``; an interrupted ``make table`` resumes those runs from their
   checkpoints. A checkpoint of another configuration (the budgets or presets changed since)
   or an unreadable one is not resumed: its run directory is moved aside to
   ``train_<name>.stale-<time>``.
2. Evaluate the rule, the heuristic and the learned policies with the protocol of MODEL §4 and
   common random numbers (``eval.*``, same seed for all: every comparison is paired).
3. Write ``results/table/``: ``table.md``, ``table.csv``, ``table.json`` (rows with ``policy``,
   ``trips_mean``, ``trips_std``, ``queue_mean``, ``queue_std``, ``failure_rate``, ``gain_pct``,
   ``gain_ci95`` against the rule, and the same against the heuristic), ``boxplot.png`` (each
   simulation's trips as % over the rule's mean) and one result JSON + CSV per policy.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from ..agents import POLICY_FILE, load_policies
from ..config import Config, compose_config
from ..evaluation import evaluate_with, format_table, gain_over, save_result
from ..training import CHECKPOINT, checkpoint_mismatch
from ..utils.plotting import plot_gain_boxplot, save_figure
from ..utils.runinfo import run_info, write_csv, write_json, write_text

ROW_KEYS = ("policy", "trips_mean", "trips_std", "queue_mean", "queue_std", "failure_rate",
            "gain_pct", "gain_ci95", "gain_vs_heuristic_pct", "gain_vs_heuristic_ci95")


def set_aside(run_dir: Path) -> Path:
    """Rename ``run_dir`` to a free ``<name>.stale-<time>[-n]`` beside it; returns the new path."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    stale = run_dir.with_name(f"{run_dir.name}.stale-{stamp}")
    n = 1
    while stale.exists():  # two in one second
        n += 1
        stale = run_dir.with_name(f"{run_dir.name}.stale-{stamp}-{n}")
    return run_dir.rename(stale)


def ensure_policy(name: str, overrides: list[str], cfg: Config) -> tuple[Path, float | None]:
    """Path of the saved policy ``name``, training it first if needed; returns (path, seconds)."""
    out_dir = Path(cfg.table.policies_dir) / name
    policy = out_dir / POLICY_FILE
    summary = out_dir / "train_summary.json"
    if policy.exists() and summary.exists() and not cfg.table.retrain:
        print(f"[table] reusing {policy}")
        return policy, None
    run_dir = Path(cfg.table.runs_dir) / f"train_{name}"
    run_overrides = [*overrides, f"train.out_dir={out_dir}", f"train.device={cfg.train.device}",
                     f"seed={cfg.seed}"]
    resume = (run_dir / CHECKPOINT).exists() and not cfg.table.retrain
    if resume:
        try:
            diff = checkpoint_mismatch(run_dir / CHECKPOINT, compose_config(run_overrides))
            why = f"a run of another configuration ({'; '.join(diff[:3])})" if diff else None
        except ValueError as e:
            why = f"an unreadable checkpoint ({e})"
        if why:
            stale = set_aside(run_dir)
            print(f"[table] {run_dir} holds {why}: moved to {stale}, training afresh",
                  flush=True)
            resume = False
    cmd = [sys.executable, "-m", "fleet_torchrl.train", *run_overrides,
           f"hydra.run.dir={run_dir}", f"resume={str(resume).lower()}"]
    print(f"[table] training {name}: {' '.join(cmd[2:])}", flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return policy, time.perf_counter() - t0


def build_rows(results: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    rule, heur = results["rule"], results["heuristic"]
    rows = []
    for name, res in results.items():
        g, h = gain_over(res, rule), gain_over(res, heur)
        rows.append({"policy": name, **{k: res[k] for k in ROW_KEYS[1:6]},
                     "gain_pct": g["gain_pct"], "gain_ci95": g["gain_ci95"],
                     "gain_vs_heuristic_pct": h["gain_pct"],
                     "gain_vs_heuristic_ci95": h["gain_ci95"]})
    return rows


def rows_markdown(rows: list[dict[str, Any]], cfg: Config, extra: str = "") -> str:
    e = cfg.eval
    lines = [f"# Main comparison ({e.n_sims} simulations x {e.ticks} ticks, site "
             f"'{cfg.site.name}', seed {e.seed})", "", format_table(rows), "",
             "Gain: mean paired difference in trips over the rule's mean, in %, with the "
             "half-width of its 95% confidence interval.", "",
             "| policy | gain % vs heuristic | ± 95% CI |", "|---|---:|---:|"]
    lines += [f"| {r['policy']} | {r['gain_vs_heuristic_pct']:+.2f} | "
              f"{r['gain_vs_heuristic_ci95']:.2f} |" for r in rows]
    return "\n".join(lines) + "\n" + extra


def run(cfg: Config) -> list[dict[str, Any]]:
    out = Path(cfg.table.out)
    train_time: dict[str, float | None] = {}
    for name, overrides in cfg.table.train.items():
        train_time[name] = ensure_policy(name, list(overrides), cfg)[1]
    if not cfg.table.evaluate:
        return []
    policies = load_policies(cfg, ["rule", "heuristic", *cfg.table.train])
    e = cfg.eval
    results: dict[str, dict[str, Any]] = {}
    for name, pol in policies.items():
        res = evaluate_with(pol, cfg.site, e, name=name)
        res["meta"] = run_info(cfg, seed=e.seed)
        save_result(res, out / f"{name}.json")
        results[name] = res
        print(f"[table] {name}: {res['trips_mean']:.2f} trips, {res['queue_mean']:.2f} queue "
              f"ticks, failure rate {res['failure_rate']:.3f} ({res['wall_time_s']:.1f} s)",
              flush=True)
    rows = build_rows(results)
    gains = {name: gain_over(res, results["rule"])["per_sim_gain_pct"]
             for name, res in results.items()}
    fig = plot_gain_boxplot(gains, f"trips per simulation vs rule mean ({e.n_sims} x {e.ticks})")
    save_figure(fig, out / "boxplot.png")
    timing = "\n".join(f"- training {k}: "
                       + (f"{v:.0f} s" if v is not None else "reused saved policy")
                       for k, v in train_time.items())
    write_text(out / "table.md", rows_markdown(rows, cfg, "\n" + timing + "\n"))
    write_csv(out / "table.csv", rows, ROW_KEYS)
    write_json(out / "table.json", rows)
    write_json(out / "run_info.json", {**run_info(cfg, seed=e.seed), "train_time_s": train_time})
    print(format_table(rows))
    print(f"[table] wrote {out}/table.md, table.csv, table.json, boxplot.png")
    return rows
