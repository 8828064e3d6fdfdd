"""``make table``: the main comparison of MODEL §5 item 1, learned rows over training seeds.

1. For each learned run of ``table.train`` (a name and the overrides of its training: the
   learner, the state, the objective ``mdp.reward`` and the budget) and each of the
   ``table.seeds`` training seeds ``seed, seed + 1, ...``: reuse
   ``results/policies/<name>/seed<s>/policy.pt`` if its ``train_summary.json`` records the
   same training configuration, else train it in a subprocess (``python -m
   fleet_torchrl.train``) whose Hydra run directory is ``outputs/table/train_<name>_seed<s>``
   (its TensorBoard curves are there). An interrupted ``make table`` resumes those runs from
   their checkpoints; a checkpoint of another configuration, or an unreadable one, is moved
   aside to ``train_<name>_seed<s>.stale-<time>``. ``table.jobs`` runs go at once.
2. Evaluate the rule, the heuristic and every seed's policy with the protocol of MODEL §4 and
   common random numbers (``eval.*``, one seed for all: every comparison is paired).
3. A learned row reports the mean over its seeds of each figure, the gain over the rule as the
   mean over seeds with a 95 % interval across seeds (Student's t) and every seed's gain.
4. Write ``results/table/``: ``table.md``, ``table.csv``, ``table.json``, ``boxplot.png``
   (each simulation's trips as % over the rule's mean, seeds pooled), ``learning_curves.png``
   (evaluation gain against training time, every seed), and one result JSON + CSV per policy
   and seed.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from ..agents import POLICY_FILE
from ..agents.registry import load_policy_file
from ..config import Config, compose_config
from ..evaluation import evaluate_with, gain_over, save_result, seed_interval
from ..store import load_policies, seed_dir
from ..training import CHECKPOINT, checkpoint_mismatch, training_fingerprint
from ..utils.plotting import plot_gain_boxplot, plot_learning_curves, save_figure
from ..utils.runinfo import file_sha256, read_json, run_info, write_csv, write_json, write_text
from .improvement import improvement

BASELINES = ("rule", "heuristic")
ROW_KEYS = ("policy", "objective", "seeds", "trips_mean", "trips_std", "queue_mean",
            "failure_rate", "gain_pct", "gain_ci95", "gain_min", "gain_per_seed",
            "gain_vs_heuristic_pct", "train_time_s", "improvement_pct", "improvement_ci95")


def set_aside(run_dir: Path) -> Path:
    """Rename ``run_dir`` to a free ``<name>.stale-<time>[-n]`` beside it; returns the new path."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    stale = run_dir.with_name(f"{run_dir.name}.stale-{stamp}")
    n = 1
    while stale.exists():  # two in one second
        n += 1
        stale = run_dir.with_name(f"{run_dir.name}.stale-{stamp}-{n}")
    return run_dir.rename(stale)


def training_seeds(cfg: Config) -> list[int]:
    return [cfg.seed + k for k in range(cfg.table.seeds)]


def run_overrides(name: str, seed: int, cfg: Config) -> list[str]:
    """The overrides of training run ``name`` with ``seed`` (its policy goes to its seed dir)."""
    out_dir = seed_dir(cfg.table.policies_dir, name, seed)
    return [*cfg.table.train[name], f"train.out_dir={out_dir}",
            f"train.device={cfg.train.device}", f"seed={seed}"]


def reusable(out_dir: Path, run_cfg: Config) -> bool:
    """A saved policy is reused only with a summary that records the same training config and
    the hash of that policy file."""
    summary = out_dir / "train_summary.json"
    if not ((out_dir / POLICY_FILE).is_file() and summary.is_file()):
        return False
    try:
        rec = read_json(summary)
    except ValueError:  # unreadable summary: train again
        return False
    # the summary must belong to this configuration and to this very policy file (a killed
    # or concurrent run can leave a policy beside another run's summary)
    return (rec.get("fingerprint") == training_fingerprint(run_cfg)
            and rec.get("policy_sha256") == file_sha256(out_dir / POLICY_FILE))


def plan_training(name: str, seed: int, cfg: Config) -> list[str] | None:
    """The training command of ``name`` with ``seed``, or None when its saved policy can be
    reused. Runs in the main thread (Hydra's compose is process-global, not thread-safe); a
    stale or unreadable checkpoint in the run directory is set aside here."""
    overrides = run_overrides(name, seed, cfg)
    run_cfg = compose_config(overrides)
    out_dir = Path(run_cfg.train.out_dir)
    if not cfg.table.retrain and reusable(out_dir, run_cfg):
        print(f"[table] reusing {out_dir / POLICY_FILE}", flush=True)
        return None
    run_dir = Path(cfg.table.runs_dir) / f"train_{name}_seed{seed}"
    resume = (run_dir / CHECKPOINT).exists() and not cfg.table.retrain
    if resume:
        try:
            diff = checkpoint_mismatch(run_dir / CHECKPOINT, run_cfg)
            why = f"a run of another configuration ({'; '.join(diff[:3])})" if diff else None
        except ValueError as e:
            why = f"an unreadable checkpoint ({e})"
        if why:
            stale = set_aside(run_dir)
            print(f"[table] {run_dir} holds {why}: moved to {stale}, training afresh",
                  flush=True)
            resume = False
    # progress bars of trainings that run side by side would interleave: one bar at most
    progress = cfg.train.progress and cfg.table.jobs == 1
    return [sys.executable, "-m", "fleet_torchrl.train", *overrides,
            f"train.progress={str(progress).lower()}", f"hydra.run.dir={run_dir}",
            f"resume={str(resume).lower()}"]


def run_training(cmd: list[str]) -> float:
    """Run one planned training in its own process; its wall time in seconds."""
    print(f"[table] training: {' '.join(cmd[2:])}", flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def ensure_policies(cfg: Config) -> dict[tuple[str, int], float | None]:
    """Train what is missing (``table.jobs`` at once); seconds per (name, seed): the training
    time each policy's summary records, for a reused one too (a run just trained without a
    summary falls back to its process's wall time; None if neither is known)."""
    todo = [(name, seed) for name in cfg.table.train for seed in training_seeds(cfg)]
    plans = {job: plan_training(*job, cfg) for job in todo}
    runs = [job for job in todo if plans[job] is not None]
    with ThreadPoolExecutor(max_workers=cfg.table.jobs) as pool:
        times = dict(zip(runs, pool.map(lambda job: run_training(plans[job]), runs),
                         strict=True))
    out = {}
    for job in todo:
        rec = recorded_train_time(*job, cfg)
        out[job] = rec if rec is not None else times.get(job)
    return out


def recorded_train_time(name: str, seed: int, cfg: Config) -> float | None:
    """The training wall time a saved policy's summary records (seconds)."""
    path = seed_dir(cfg.table.policies_dir, name, seed) / "train_summary.json"
    try:
        return float(read_json(path)["wall_s"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def objective_of(name: str, cfg: Config) -> str:
    run_cfg = compose_config(list(cfg.table.train[name]))
    return run_cfg.agent.objective(run_cfg.mdp)


def baseline_row(name: str, res: dict[str, Any], rule: dict[str, Any],
                 heur: dict[str, Any]) -> dict[str, Any]:
    g = gain_over(res, rule)
    return {"policy": name, "objective": "", "seeds": [], "trips_mean": res["trips_mean"],
            "trips_std": res["trips_std"], "queue_mean": res["queue_mean"],
            "failure_rate": res["failure_rate"], "gain_pct": g["gain_pct"],
            "gain_ci95": g["gain_ci95"], "gain_min": g["gain_pct"], "gain_per_seed": [],
            "gain_vs_heuristic_pct": gain_over(res, heur)["gain_pct"], "train_time_s": []}


def learned_row(name: str, objective: str, per_seed: dict[int, dict[str, Any]],
                rule: dict[str, Any], heur: dict[str, Any],
                times: list[float | None]) -> dict[str, Any]:
    """Mean over seeds of every figure; the gain with its 95 % interval across seeds."""
    gains = [gain_over(res, rule)["gain_pct"] for res in per_seed.values()]
    vs_heur = [gain_over(res, heur)["gain_pct"] for res in per_seed.values()]
    gi = seed_interval(gains)

    def mean(key: str) -> float:
        return sum(r[key] for r in per_seed.values()) / len(per_seed)

    return {"policy": name, "objective": objective, "seeds": list(per_seed),
            "trips_mean": mean("trips_mean"), "trips_std": mean("trips_std"),
            "queue_mean": mean("queue_mean"), "failure_rate": mean("failure_rate"),
            "gain_pct": gi["mean"], "gain_ci95": gi["ci95"], "gain_min": gi["min"],
            "gain_per_seed": gains, "gain_vs_heuristic_pct": sum(vs_heur) / len(vs_heur),
            "train_time_s": times}


def rows_markdown(rows: list[dict[str, Any]], cfg: Config) -> str:
    e = cfg.eval
    lines = [f"# Main comparison ({e.n_sims} simulations x {e.ticks} ticks, site "
             f"'{cfg.site.name}', evaluation seed {e.seed})", "",
             "| policy | objective | training seeds | trips | queue ticks | failure rate | "
             "gain % vs rule | ± 95 % | per seed | vs heuristic | training time | "
             "one-step improvement |",
             "|---|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
    for r in rows:
        seeds = ", ".join(map(str, r["seeds"])) or "-"
        per_seed = ", ".join(f"{g:+.2f}" for g in r["gain_per_seed"]) or "-"
        times = [t for t in r["train_time_s"] if t is not None]
        ttime = f"{max(times) / 60:.1f} min max" if times else ("n/a" if r["seeds"] else "-")
        ci = "-" if math.isnan(r["gain_ci95"]) else f"{r['gain_ci95']:.2f}"  # one seed: none
        imp = ("-" if r.get("improvement_pct") is None else
               f"{r['improvement_pct']:+.2f} ± {r['improvement_ci95']:.2f}")
        lines.append(f"| {r['policy']} | {r['objective'] or '-'} | {seeds} | "
                     f"{r['trips_mean']:.2f} | {r['queue_mean']:.2f} | "
                     f"{r['failure_rate']:.3f} | {r['gain_pct']:+.2f} | {ci} | "
                     f"{per_seed} | {r['gain_vs_heuristic_pct']:+.2f} | {ttime} | {imp} |")
    lines += ["", "Gain: trips over the rule's mean on the same sites, in %. Baselines: the "
              "paired gain and its 95 % interval over the simulations. Learned rows: the mean "
              "over their training seeds, the 95 % interval across seeds (Student's t), and "
              "each seed's gain; trips, queue ticks and failure rate are means over the seeds."]
    if cfg.table.improve_sims:
        lines += ["", "One-step improvement: what the rollout planner (MODEL §3.6) adds when "
                  "the row's policy is its base (learned rows: their lowest training seed), "
                  f"on the first {cfg.table.improve_sims} simulations, in points of gain over "
                  "the rule with the paired 95 % interval. A policy that one step improves "
                  "significantly is not optimal on this site, by at least that much."]
    return "\n".join(lines) + "\n"


def learning_curves(cfg: Config) -> dict[str, dict[int, list[tuple[float, float]]]]:
    """(training seconds, evaluation gain %) of every evaluation of every saved run."""
    curves: dict[str, dict[int, list[tuple[float, float]]]] = {}
    for name in cfg.table.train:
        for seed in training_seeds(cfg):
            path = seed_dir(cfg.table.policies_dir, name, seed) / "train_summary.json"
            if path.is_file():
                hist = read_json(path).get("history", [])
                curves.setdefault(name, {})[seed] = [(h["wall_s"], h["gain_pct"]) for h in hist]
    return curves


def run(cfg: Config) -> list[dict[str, Any]]:
    out = Path(cfg.table.out)
    times = ensure_policies(cfg)
    if not cfg.table.evaluate:
        return []
    e = cfg.eval
    meta = run_info(cfg, seed=e.seed)

    def evaluate(policy, label: str) -> dict[str, Any]:
        res = evaluate_with(policy, cfg.site, e, name=label)
        res["meta"] = meta
        save_result(res, out / f"{label}.json")
        print(f"[table] {label}: {res['trips_mean']:.2f} trips, {res['queue_mean']:.2f} queue "
              f"ticks, failure rate {res['failure_rate']:.3f} ({res['wall_time_s']:.1f} s)",
              flush=True)
        return res

    baselines = load_policies(cfg, list(BASELINES))
    base = {name: evaluate(pol, name) for name, pol in baselines.items()}
    rule, heur = base["rule"], base["heuristic"]
    planner = compose_config(["agent=planner"]).agent

    def improve(row: dict[str, Any], policy, res: dict[str, Any]) -> dict[str, Any]:
        if cfg.table.improve_sims:
            imp = improvement(policy, res, rule, cfg.site, cfg.table.improve_sims, e.ticks,
                              e.seed, planner, e.device)
            print(f"[table] {row['policy']}: one step of improvement "
                  f"{imp['improvement_pct']:+.2f} ± {imp['improvement_ci95']:.2f}", flush=True)
            row.update(improvement_pct=imp["improvement_pct"],
                       improvement_ci95=imp["improvement_ci95"])
        return row

    rows = [improve(baseline_row(name, res, rule, heur), baselines[name], res)
            for name, res in base.items()]
    gains = {name: gain_over(res, rule)["per_sim_gain_pct"] for name, res in base.items()}
    for name in cfg.table.train:
        per_seed, first = {}, None
        for seed in training_seeds(cfg):
            pol = load_policy_file(seed_dir(cfg.table.policies_dir, name, seed), e.device)
            per_seed[seed] = evaluate(pol, f"{name}_seed{seed}")
            first = first or pol
        rows.append(improve(learned_row(name, objective_of(name, cfg), per_seed, rule, heur,
                                        [times[(name, s)] for s in per_seed]),
                            first, per_seed[min(per_seed)]))
        gains[name] = [g for res in per_seed.values()
                       for g in gain_over(res, rule)["per_sim_gain_pct"]]
    fig = plot_gain_boxplot(gains, f"trips per simulation vs rule mean ({e.n_sims} x {e.ticks}"
                                   f"; learned: {cfg.table.seeds} seeds pooled)")
    save_figure(fig, out / "boxplot.png")
    curves = learning_curves(cfg)
    if curves:
        save_figure(plot_learning_curves(curves), out / "learning_curves.png")
    write_text(out / "table.md", rows_markdown(rows, cfg))
    write_csv(out / "table.csv", [{**r, "seeds": " ".join(map(str, r["seeds"])),
                                   "gain_per_seed": " ".join(f"{g:.4f}"
                                                             for g in r["gain_per_seed"]),
                                   "train_time_s": " ".join(f"{t:.1f}" if t is not None
                                                            else "n/a"
                                                            for t in r["train_time_s"])}
                                  for r in rows], ROW_KEYS)
    write_json(out / "table.json", rows)
    write_json(out / "run_info.json", {**meta, "training_seeds": training_seeds(cfg),
                                       "train_time_s": {f"{k[0]}_seed{k[1]}": v
                                                        for k, v in times.items()}})
    print(rows_markdown(rows, cfg))
    print(f"[table] wrote {out}/table.md, table.csv, table.json, boxplot.png, "
          "learning_curves.png")
    return rows
