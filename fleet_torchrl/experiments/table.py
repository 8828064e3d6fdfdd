"""``make table``: the main comparison of MODEL §5 item 1, learned rows over training seeds.

1. For each recipe (``conf/recipes/``: a name and the overrides of its training: the
   learner, the state, the objective ``mdp.reward``, the site and the budget; ``table.only``
   narrows them, ``table.preview`` appends each one's shorter budget) and each of the
   ``table.seeds`` training seeds ``seed, seed + 1, ...``: reuse
   ``results/policies/<name>/seed<s>/policy.pt`` if its ``train_summary.json`` records the
   same training configuration, else train it as a job of the ``train`` task
   (:func:`plan_jobs`) in the run folder ``outputs/table/train_<name>_seed<s>`` (its
   TensorBoard curves are there). Hydra's launcher runs the jobs (``hydra/launcher``: two
   local processes by default; :class:`~fleet_torchrl.experiments.launch.TableSweep`). An
   interrupted ``make table`` resumes those runs from their checkpoints; a checkpoint of
   another configuration, or an unreadable one, is moved aside to
   ``train_<name>_seed<s>.stale-<time>``.
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
import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from ..agents import POLICY_FILE
from ..agents.registry import load_policy_file
from ..config import Config, compose_config
from ..evaluation import evaluate_with, gain_over, save_result, seed_interval
from ..sim import SiteConfig
from ..store import load_policies, seed_dir, site_preset, site_suffix
from ..training import CHECKPOINT, RunSpec, checkpoint_mismatch, result_fingerprint
from ..training.publish import holds_policy
from ..utils.checks import ConfigError
from ..utils.plotting import plot_gain_boxplot, plot_learning_curves, save_figure
from ..utils.runinfo import file_sha256, read_json, run_info, write_csv, write_json, write_text
from .improvement import improvement

BASELINES = ("rule", "heuristic")
ROW_KEYS = ("policy", "objective", "trained_on", "seeds", "trips_mean", "trips_std", "queue_mean",
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


# groups a table-level override would set for nothing: each recipe sets its own
_RECIPE_GROUPS = ("state", "mdp", "agent", "network")


def check_forwardable(cfg: Config) -> None:
    """Refuse table-level settings that cannot reach the trainings: the learner, state,
    objective and network are each recipe's own (``conf/recipes``), so ``make table
    ARGS="mdp.reward=throughput"`` would change nothing it says. The site is forwarded
    (:func:`site_overrides`)."""
    plain = compose_config([])
    for group in _RECIPE_GROUPS:
        mine, default = getattr(cfg, group), getattr(plain, group)
        if mine != default:
            diff = next((f"{group}.{k}={v!r}" for k, v in vars(mine).items()
                         if getattr(default, k, object()) != v), group)
            raise ConfigError(f"{diff} does not reach the table's trainings (each recipe sets "
                              f"its own {group}): put it in a recipe (conf/recipes) or run "
                              "make train")
    site_overrides(cfg)


def site_overrides(cfg: Config) -> list[str]:
    """The table's site as overrides of its trainings: none for the default site, else the
    site preset and the fields that differ from it (``make table ARGS="site=five_vehicles"``
    trains and evaluates on that site). A site distribution that is not a packaged preset
    cannot be written as overrides, and is refused."""
    site, default = cfg.site, SiteConfig()
    if site == default:
        return []
    preset = site_preset(site.name)
    if preset is not None and preset == site:
        return [f"site={site.name}"]
    if site.ranges is not None:
        raise ConfigError(f"site.ranges={site.ranges!r} cannot be forwarded to the table's "
                          "trainings: use a site preset (conf/site/) for a site distribution")
    base = preset if preset is not None else default
    out = [f"site={site.name}"] if preset is not None else [f"site.name={site.name}"]
    for f in fields(SiteConfig):
        if f.name not in ("name", "ranges") and getattr(site, f.name) != getattr(base, f.name):
            out.append(f"site.{f.name}={getattr(site, f.name)}")
    return out


def _sets_site(cfg: Config, name: str) -> bool:
    return cfg.recipes[name].site_override() is not None


def trained_on(cfg: Config, name: str) -> str:
    """Where recipe ``name`` trains: its own site overrides (``site=randomized``,
    ``site.t_c=10``), or ``this site`` when it trains on the table's. A row trained elsewhere
    (a base of the generalist's teacher) is evaluated off its site here, failures included."""
    return ", ".join(o.lstrip("+~") for o in cfg.recipes[name].site_overrides()) or "this site"


def recipe_folder(cfg: Config, name: str) -> str:
    """The folder a recipe's policies are published in: its name, plus the site's suffix
    when the table's site reaches it (a recipe with a site of its own, like the generalist,
    keeps its name), so a table on another site never replaces the default site's."""
    if site_overrides(cfg) and not _sets_site(cfg, name):
        return name + site_suffix(cfg.site)
    return name


def recipe_seed_dir(cfg: Config, name: str, seed: int) -> Path:
    return seed_dir(cfg.table.policies_dir, recipe_folder(cfg, name), seed,
                    cfg.table.follow_symlinks)


def run_overrides(name: str, seed: int, cfg: Config) -> list[str]:
    """The overrides of training run ``name`` with ``seed`` (its policy goes to its seed dir;
    the table's site is forwarded unless the recipe sets its own; a teacher's bases are
    other recipes' policies, :func:`teacher_bases`)."""
    out_dir = recipe_seed_dir(cfg, name, seed)
    site = [] if _sets_site(cfg, name) else site_overrides(cfg)
    return [*cfg.recipes[name].training_overrides(cfg.table.preview), *site,
            *teacher_bases(cfg, name), f"train.out_dir={out_dir}",
            f"train.device={cfg.train.device}", f"seed={seed}"]


def teacher_bases(cfg: Config, name: str) -> list[str]:
    """The override that gives recipe ``name``'s teacher the policies of its ``bases``
    recipes (each one's of the table's first training seed), none without bases."""
    bases = cfg.recipes[name].bases
    if not bases:
        return []
    paths = [str(recipe_seed_dir(cfg, b, cfg.seed) / POLICY_FILE) for b in bases]
    for b, p in zip(bases, paths, strict=True):
        if any(c in p for c in ",[]='\""):
            raise ConfigError(f"table.policies_dir={cfg.table.policies_dir!r} is invalid for "
                              f"recipe {name}'s teacher base {b}: its path {p!r} cannot be an "
                              "override value (no , [ ] = or quotes)")
    return [f"agent.expert.bases=[{','.join(paths)}]"]


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
    return (rec.get("fingerprint") == result_fingerprint(RunSpec.of(run_cfg))
            and rec.get("policy_sha256") == file_sha256(out_dir / POLICY_FILE))


@dataclass
class TableJob:
    """One training the table launches: recipe ``name`` with ``seed``, as the overrides of a
    job of the ``train`` task (its run folder ``<table.runs_dir>/<folder>``)."""

    name: str
    seed: int
    overrides: list[str]

    @property
    def folder(self) -> str:
        return f"train_{self.name}_seed{self.seed}"


def plan_training(name: str, seed: int, cfg: Config, progress: bool = False
                  ) -> TableJob | None:
    """The training job of ``name`` with ``seed``, or None when its saved policy can be
    reused. Runs in the launching process (Hydra's compose is process-global); a stale or
    unreadable checkpoint in the run folder is set aside here, a matching one resumed."""
    overrides = run_overrides(name, seed, cfg)
    run_cfg = compose_config(overrides)
    out_dir = Path(run_cfg.train.out_dir)
    if not cfg.table.retrain and reusable(out_dir, run_cfg):
        print(f"[table] reusing {out_dir / POLICY_FILE}", flush=True)
        return None
    # the table owns its seed folders: a policy of other settings there (a recipe changed,
    # table.retrain=true) is replaced, said here, not silently
    replace = holds_policy(out_dir)
    if replace:
        print(f"[table] {out_dir} holds a policy of other settings: training again, the new "
              "one replaces it", flush=True)
    job = TableJob(recipe_folder(cfg, name), seed, [])
    run_dir = Path(cfg.table.runs_dir) / job.folder
    resume = (run_dir / CHECKPOINT).exists() and not cfg.table.retrain
    if resume:
        try:
            diff = checkpoint_mismatch(run_dir / CHECKPOINT, RunSpec.of(run_cfg))
            why = f"a run of another configuration ({'; '.join(diff[:3])})" if diff else None
        except ValueError as e:
            why = f"an unreadable checkpoint ({e})"
        if why:
            stale = set_aside(run_dir)
            print(f"[table] {run_dir} holds {why}: moved to {stale}, training afresh",
                  flush=True)
            resume = False
    elif run_dir.exists() and cfg.table.retrain:
        set_aside(run_dir)
    if resume:
        print(f"[table] resuming {run_dir}", flush=True)
    # progress bars of trainings that run side by side would interleave: one bar at most
    job.overrides = [*overrides, f"train.progress={str(progress).lower()}",
                     f"resume={str(resume).lower()}", f"train.overwrite={str(replace).lower()}",
                     f"hydra.sweep.dir={cfg.table.runs_dir}", f"hydra.sweep.subdir={job.folder}"]
    return job


def check_outputs(cfg: Config) -> None:
    """Before any training: every folder the table writes can be written (a
    ``table.policies_dir`` that is a file would otherwise be found after the trainings)."""
    from ..utils.paths import check_output

    check_output("table.policies_dir", cfg.table.policies_dir, "dir")
    check_output("table.runs_dir", cfg.table.runs_dir, "dir")
    if cfg.table.evaluate:
        check_output("table.out", cfg.table.out, "dir")


WAVES = 2  # recipes whose teachers plan over other recipes' policies train after those


def plan_jobs(cfg: Config, progress: bool = False, wave: int = 0) -> list[TableJob]:
    """The trainings the table needs, recipe by recipe and seed by seed (reused policies
    left out); ``progress``: whether a job may show its progress bar (one job at a time).
    Wave 0 holds the recipes without teacher bases, wave 1 the others: plan wave 1 once
    wave 0 has run (its configs name wave 0's policy files, which must exist)."""
    check_forwardable(cfg)
    names = [n for n in cfg.table.training_names(cfg.recipes)
             if bool(cfg.recipes[n].bases) == bool(wave)]
    jobs = [plan_training(name, seed, cfg, progress) for name in names
            for seed in training_seeds(cfg)]
    return [j for j in jobs if j is not None]


def recorded_train_time(name: str, seed: int, cfg: Config) -> float | None:
    """The training wall time a saved policy's summary records (seconds)."""
    path = recipe_seed_dir(cfg, name, seed) / "train_summary.json"
    try:
        return float(read_json(path)["wall_s"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def objective_of(name: str, cfg: Config) -> str:
    run_cfg = compose_config(run_overrides(name, 0, cfg))
    return run_cfg.agent.objective(run_cfg.mdp)


def baseline_row(name: str, res: dict[str, Any], rule: dict[str, Any],
                 heur: dict[str, Any]) -> dict[str, Any]:
    g = gain_over(res, rule)
    return {"policy": name, "objective": "", "trained_on": "", "seeds": [],
            "trips_mean": res["trips_mean"],
            "trips_std": res["trips_std"], "queue_mean": res["queue_mean"],
            "failure_rate": res["failure_rate"], "gain_pct": g["gain_pct"],
            "gain_ci95": g["gain_ci95"], "gain_min": g["gain_pct"], "gain_per_seed": [],
            "gain_vs_heuristic_pct": gain_over(res, heur)["gain_pct"], "train_time_s": []}


def learned_row(name: str, objective: str, per_seed: dict[int, dict[str, Any]],
                rule: dict[str, Any], heur: dict[str, Any],
                times: list[float | None], site: str) -> dict[str, Any]:
    """Mean over seeds of every figure; the gain with its 95 % interval across seeds."""
    gains = [gain_over(res, rule)["gain_pct"] for res in per_seed.values()]
    vs_heur = [gain_over(res, heur)["gain_pct"] for res in per_seed.values()]
    gi = seed_interval(gains)

    def mean(key: str) -> float:
        return sum(r[key] for r in per_seed.values()) / len(per_seed)

    return {"policy": name, "objective": objective, "trained_on": site,
            "seeds": list(per_seed),
            "trips_mean": mean("trips_mean"), "trips_std": mean("trips_std"),
            "queue_mean": mean("queue_mean"), "failure_rate": mean("failure_rate"),
            "gain_pct": gi["mean"], "gain_ci95": gi["ci95"], "gain_min": gi["min"],
            "gain_per_seed": gains, "gain_vs_heuristic_pct": sum(vs_heur) / len(vs_heur),
            "train_time_s": times}


def rows_markdown(rows: list[dict[str, Any]], cfg: Config) -> str:
    e = cfg.eval
    lines = [f"# Main comparison ({e.n_sims} simulations x {e.ticks} ticks, site "
             f"'{cfg.site.name}', evaluation seed {e.seed})", "",
             "| policy | objective | trained on | training seeds | trips | queue ticks | "
             "failure rate | gain % vs rule | ± 95 % | per seed | vs heuristic | "
             "training time | one-step improvement |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
    for r in rows:
        seeds = ", ".join(map(str, r["seeds"])) or "-"
        per_seed = ", ".join(f"{g:+.2f}" for g in r["gain_per_seed"]) or "-"
        times = [t for t in r["train_time_s"] if t is not None]
        ttime = f"{max(times) / 60:.1f} min max" if times else ("n/a" if r["seeds"] else "-")
        ci = "-" if math.isnan(r["gain_ci95"]) else f"{r['gain_ci95']:.2f}"  # one seed: none
        imp = ("-" if r.get("improvement_pct") is None else
               f"{r['improvement_pct']:+.2f} ± {r['improvement_ci95']:.2f}")
        lines.append(f"| {r['policy']} | {r['objective'] or '-'} | "
                     f"{r.get('trained_on') or '-'} | {seeds} | "
                     f"{r['trips_mean']:.2f} | {r['queue_mean']:.2f} | "
                     f"{r['failure_rate']:.3f} | {r['gain_pct']:+.2f} | {ci} | "
                     f"{per_seed} | {r['gain_vs_heuristic_pct']:+.2f} | {ttime} | {imp} |")
    lines += ["", "Gain: trips over the rule's mean on the same sites, in %. Baselines: the "
              "paired gain and its 95 % interval over the simulations. Learned rows: the mean "
              "over their training seeds, the 95 % interval across seeds (Student's t), and "
              "each seed's gain; trips, queue ticks and failure rate are means over the seeds. "
              "Trained on: the site overrides of a learned row's recipe; a row trained on "
              "another site is evaluated off its site here, failures included."]
    if cfg.table.improve_sims:
        lines += ["", "One-step improvement: what the rollout planner (MODEL §3.6) adds when "
                  "the row's policy is its base (learned rows: their lowest training seed), "
                  f"on the first {cfg.table.improve_sims} simulations, in points of gain over "
                  "the rule with the paired 95 % interval. A policy that one step improves "
                  "significantly is not optimal on this site, by at least that much."]
    return "\n".join(lines) + "\n"


def learning_curves(cfg: Config) -> dict[str, dict[int, list[tuple[float, float, float]]]]:
    """(training seconds, evaluation gain %, failure rate) of every evaluation of every
    saved run."""
    curves: dict[str, dict[int, list[tuple[float, float]]]] = {}
    for name in cfg.table.names(cfg.recipes):
        for seed in training_seeds(cfg):
            path = recipe_seed_dir(cfg, name, seed) / "train_summary.json"
            if path.is_file():
                hist = read_json(path).get("history", [])
                curves.setdefault(name, {})[seed] = [
                    (h["wall_s"], h["gain_pct"], h.get("failure_rate", 0.0)) for h in hist]
    return curves


def evaluate_table(cfg: Config, times: dict[tuple[str, int], float | None]
                   ) -> list[dict[str, Any]]:
    """Evaluate the baselines and every recipe's seeds (all trained by now), write the
    table; ``times``: each training's wall time in seconds (None if unknown)."""
    out = Path(cfg.table.out)
    e = cfg.eval
    meta = run_info(cfg, seed=e.seed)
    total = len(BASELINES) + len(cfg.table.names(cfg.recipes)) * cfg.table.seeds
    done = []

    def evaluate(policy, label: str) -> dict[str, Any]:
        res = evaluate_with(policy, cfg.site, e, name=label)
        res["meta"] = meta
        save_result(res, out / f"{label}.json")
        done.append(label)
        print(f"[table] evaluation {len(done)} of {total}, {label}: {res['trips_mean']:.2f} "
              f"trips, {res['queue_mean']:.2f} queue ticks, failure rate "
              f"{res['failure_rate']:.3f} ({res['wall_time_s']:.1f} s)", flush=True)
        return res

    baselines = load_policies(cfg.table.policies_dir, list(BASELINES), cfg.eval.device,
                              cfg.table.follow_symlinks)
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
    for name in cfg.table.names(cfg.recipes):
        per_seed, first = {}, None
        for seed in training_seeds(cfg):
            pol = load_policy_file(recipe_seed_dir(cfg, name, seed), e.device)
            per_seed[seed] = evaluate(pol, f"{name}_seed{seed}")
            first = first or pol
        rows.append(improve(learned_row(name, objective_of(name, cfg), per_seed, rule, heur,
                                        [times[(name, s)] for s in per_seed],
                                        trained_on(cfg, name)),
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
