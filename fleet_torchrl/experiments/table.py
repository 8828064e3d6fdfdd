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

import time
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Protocol

from ..agents import POLICY_FILE
from ..agents.registry import load_policy_file
from ..evaluation import evaluate_with, gain_over, save_result
from ..evaluation.config import EvalConfig
from ..sim import SiteConfig
from ..store import load_policies, seed_dir, site_preset, site_suffix
from ..training import CHECKPOINT, checkpoint_mismatch, result_fingerprint
from ..training.config import TrainConfig
from ..training.publish import holds_policy
from ..training.spec import RunSpec
from ..utils.checks import ConfigError
from ..utils.plotting import plot_gain_boxplot, plot_learning_curves, save_figure
from ..utils.runinfo import file_sha256, read_json, write_csv, write_json, write_text
from .config import Recipe, TableConfig
from .improvement import improvement
from .rows import TABLE_FIELDS, Candidate, Row

BASELINES = ("rule", "heuristic")
ROW_KEYS = TABLE_FIELDS


class TableRun(Protocol):
    """What the table reads of the command's config: its own settings, the recipes, the
    site it trains and evaluates on, the first training seed, the training device
    (``train.device``) and the evaluation protocol."""

    table: TableConfig
    recipes: dict[str, Recipe]
    site: SiteConfig
    seed: int
    train: TrainConfig
    eval: EvalConfig


Specs = dict[tuple[str, int], RunSpec]  # every training's run spec by (recipe, seed)


def set_aside(run_dir: Path) -> Path:
    """Rename ``run_dir`` to a free ``<name>.stale-<time>[-n]`` beside it; returns the new path."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    stale = run_dir.with_name(f"{run_dir.name}.stale-{stamp}")
    n = 1
    while stale.exists():  # two in one second
        n += 1
        stale = run_dir.with_name(f"{run_dir.name}.stale-{stamp}-{n}")
    return run_dir.rename(stale)


def training_seeds(cfg: TableRun) -> list[int]:
    return [cfg.seed + k for k in range(cfg.table.seeds)]


def site_overrides(cfg: TableRun) -> list[str]:
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


def _sets_site(cfg: TableRun, name: str) -> bool:
    return cfg.recipes[name].site_override() is not None


def trained_on(cfg: TableRun, name: str) -> str:
    """Where recipe ``name`` trains: its own site overrides (``site=randomized``,
    ``site.t_c=10``), or ``this site`` when it trains on the table's. A row trained elsewhere
    (a base of the generalist's teacher) is evaluated off its site here, failures included."""
    return ", ".join(o.lstrip("+~") for o in cfg.recipes[name].site_overrides()) or "this site"


def recipe_folder(cfg: TableRun, name: str) -> str:
    """The folder a recipe's policies are published in: its name, plus the site's suffix
    when the table's site reaches it (a recipe with a site of its own, like the generalist,
    keeps its name), so a table on another site never replaces the default site's."""
    if site_overrides(cfg) and not _sets_site(cfg, name):
        return name + site_suffix(cfg.site)
    return name


def recipe_seed_dir(cfg: TableRun, name: str, seed: int) -> Path:
    return seed_dir(cfg.table.policies_dir, recipe_folder(cfg, name), seed,
                    cfg.table.follow_symlinks)


def run_overrides(name: str, seed: int, cfg: TableRun) -> list[str]:
    """The overrides of training run ``name`` with ``seed`` (its policy goes to its seed dir;
    the table's site is forwarded unless the recipe sets its own; a teacher's bases are
    other recipes' policies, :func:`teacher_bases`)."""
    out_dir = recipe_seed_dir(cfg, name, seed)
    site = [] if _sets_site(cfg, name) else site_overrides(cfg)
    return [*cfg.recipes[name].training_overrides(cfg.table.preview), *site,
            *teacher_bases(cfg, name), f"train.out_dir={out_dir}",
            f"train.device={cfg.train.device}", f"seed={seed}"]


def teacher_bases(cfg: TableRun, name: str) -> list[str]:
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


def reusable(out_dir: Path, spec: RunSpec) -> bool:
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
    return (rec.get("fingerprint") == result_fingerprint(spec)
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


def plan_training(name: str, seed: int, cfg: TableRun, spec: RunSpec, progress: bool = False
                  ) -> TableJob | None:
    """The training job of ``name`` with ``seed`` (``spec``: what :func:`run_overrides`
    compose to), or None when its saved policy can be reused. Runs in the launching process;
    a stale or unreadable checkpoint in the run folder is set aside here, a matching one
    resumed."""
    overrides = run_overrides(name, seed, cfg)
    out_dir = Path(spec.train.out_dir)
    if not cfg.table.retrain and reusable(out_dir, spec):
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
            diff = checkpoint_mismatch(run_dir / CHECKPOINT, spec)
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


def check_outputs(cfg: TableRun) -> None:
    """Before any training: every folder the table writes can be written (a
    ``table.policies_dir`` that is a file would otherwise be found after the trainings)."""
    from ..utils.paths import check_output

    check_output("table.policies_dir", cfg.table.policies_dir, "dir")
    check_output("table.runs_dir", cfg.table.runs_dir, "dir")
    if cfg.table.evaluate:
        check_output("table.out", cfg.table.out, "dir")


WAVES = 2  # recipes whose teachers plan over other recipes' policies train after those


def plan_jobs(cfg: TableRun, specs: Specs, progress: bool = False, wave: int = 0
              ) -> list[TableJob]:
    """The trainings the table needs, recipe by recipe and seed by seed (reused policies
    left out; ``specs``: each training's run spec); ``progress``: whether a job may show its
    progress bar (one job at a time). Wave 0 holds the recipes without teacher bases, wave 1
    the others: plan wave 1 once wave 0 has run (its fingerprints read wave 0's policy
    files, which must exist)."""
    names = [n for n in cfg.table.training_names(cfg.recipes)
             if bool(cfg.recipes[n].bases) == bool(wave)]
    jobs = [plan_training(name, seed, cfg, specs[(name, seed)], progress) for name in names
            for seed in training_seeds(cfg)]
    return [j for j in jobs if j is not None]


def recorded_train_time(name: str, seed: int, cfg: TableRun) -> float | None:
    """The training wall time a saved policy's summary records (seconds)."""
    path = recipe_seed_dir(cfg, name, seed) / "train_summary.json"
    try:
        return float(read_json(path)["wall_s"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def candidates(cfg: TableRun, specs: Specs) -> list[Candidate]:
    """The table's rows: the baselines, then each recipe over its training seeds (its
    objective, where it trains, its seeds' policy files)."""
    out = [Candidate(name, "baseline") for name in BASELINES]
    for name in cfg.table.names(cfg.recipes):
        seeds = training_seeds(cfg)
        spec = specs[(name, seeds[0])]
        out.append(Candidate(name, "learned", specs={s: specs[(name, s)] for s in seeds},
                             files={s: recipe_seed_dir(cfg, name, s) for s in seeds},
                             objective=spec.agent.objective(spec.mdp),
                             trained_on=trained_on(cfg, name)))
    return out


def rows_markdown(rows: list[Row] | list[dict[str, Any]], cfg: TableRun) -> str:
    """``table.md``: the rows (:meth:`Row.table_markdown`; a row of ``table.json`` as well)
    under the protocol's heading, then what the columns mean."""
    rows = [r if isinstance(r, Row) else Row.from_table_dict(r) for r in rows]
    e = cfg.eval
    lines = [f"# Main comparison ({e.n_sims} simulations x {e.ticks} ticks, site "
             f"'{cfg.site.name}', evaluation seed {e.seed})", "",
             "| policy | objective | trained on | training seeds | trips | queue ticks | "
             "failure rate | gain % vs rule | ± 95 % | per seed | vs heuristic | "
             "training time | one-step improvement |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
    lines += [r.table_markdown() for r in rows]
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


def learning_curves(cfg: TableRun) -> dict[str, dict[int, list[tuple[float, float, float]]]]:
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


def evaluate_table(cfg: TableRun, times: dict[tuple[str, int], float | None], specs: Specs,
                   planner: Any, meta: dict[str, Any]) -> list[dict[str, Any]]:
    """Evaluate the baselines and every recipe's seeds (all trained by now), write the
    table; ``times``: each training's wall time in seconds (None if unknown); ``specs``:
    each training's run spec; ``planner``: the one-step improvement's planner settings;
    ``meta``: the run's provenance."""
    out, e = Path(cfg.table.out), cfg.eval
    cands = candidates(cfg, specs)
    total = sum(max(1, len(c.files)) for c in cands)
    done: list[str] = []

    def evaluate(policy, label: str) -> dict[str, Any]:
        res = evaluate_with(policy, cfg.site, e, name=label)
        res["meta"] = meta
        save_result(res, out / f"{label}.json")
        done.append(label)
        print(f"[table] evaluation {len(done)} of {total}, {label}: {res['trips_mean']:.2f} "
              f"trips, {res['queue_mean']:.2f} queue ticks, failure rate "
              f"{res['failure_rate']:.3f} ({res['wall_time_s']:.1f} s)", flush=True)
        return res

    baselines = load_policies(cfg.table.policies_dir, list(BASELINES), e.device,
                              cfg.table.follow_symlinks)
    base = {name: evaluate(pol, name) for name, pol in baselines.items()}
    rule, heur = base["rule"], base["heuristic"]

    def improve(row: Row, policy, res: dict[str, Any]) -> Row:
        if cfg.table.improve_sims:
            imp = improvement(policy, res, rule, cfg.site, cfg.table.improve_sims, e.ticks,
                              e.seed, planner, e.device)
            print(f"[table] {row.policy}: one step of improvement "
                  f"{imp['improvement_pct']:+.2f} ± {imp['improvement_ci95']:.2f}", flush=True)
            row.improved(imp)
        return row

    rows = [improve(Row.of(name, {None: res}, rule, heur), baselines[name], res)
            for name, res in base.items()]
    gains = {name: gain_over(res, rule)["per_sim_gain_pct"] for name, res in base.items()}
    for c in (c for c in cands if c.kind == "learned"):
        per_seed, first = {}, None
        for seed, folder in c.files.items():
            pol = load_policy_file(folder, e.device)
            per_seed[seed] = evaluate(pol, f"{c.name}_seed{seed}")
            first = first or pol
        row = Row.of(c.name, per_seed, rule, heur, objective=c.objective,
                     trained_on=c.trained_on, train_time_s=[times[(c.name, s)]
                                                            for s in per_seed])
        rows.append(improve(row, first, per_seed[min(per_seed)]))
        gains[c.name] = [g for res in per_seed.values()
                         for g in gain_over(res, rule)["per_sim_gain_pct"]]
    write_table(cfg, rows, gains, times, meta)
    return [r.table_dict() for r in rows]


def write_table(cfg: TableRun, rows: list[Row], gains: dict[str, list[float]],
                times: dict[tuple[str, int], float | None], meta: dict[str, Any]) -> None:
    """``table.md``, ``table.csv``, ``table.json``, the box plot and the learning curves."""
    out, e = Path(cfg.table.out), cfg.eval
    fig = plot_gain_boxplot(gains, f"trips per simulation vs rule mean ({e.n_sims} x {e.ticks}"
                                   f"; learned: {cfg.table.seeds} seeds pooled)")
    save_figure(fig, out / "boxplot.png")
    curves = learning_curves(cfg)
    if curves:
        save_figure(plot_learning_curves(curves), out / "learning_curves.png")
    write_text(out / "table.md", rows_markdown(rows, cfg))
    dicts = [r.table_dict() for r in rows]
    write_csv(out / "table.csv", [{**r, "seeds": " ".join(map(str, r["seeds"])),
                                   "gain_per_seed": " ".join(f"{g:.4f}"
                                                             for g in r["gain_per_seed"]),
                                   "train_time_s": " ".join(f"{t:.1f}" if t is not None
                                                            else "n/a"
                                                            for t in r["train_time_s"])}
                                  for r in dicts], ROW_KEYS)
    write_json(out / "table.json", dicts)
    write_json(out / "run_info.json", {**meta, "training_seeds": training_seeds(cfg),
                                       "train_time_s": {f"{k[0]}_seed{k[1]}": v
                                                        for k, v in times.items()}})
    print(rows_markdown(rows, cfg))
    print(f"[table] wrote {out}/table.md, table.csv, table.json, boxplot.png, "
          "learning_curves.png")
