"""make table end to end on a tiny budget, as the command runs it: the trainings as jobs of
Hydra's launcher (two processes), learned rows over seeds, reuse, resume, stale runs."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest
import yaml

from fleet_torchrl.config import compose_config

TINY_TRAIN = ["train.eval_every=1", "train.eval_sims=8", "train.eval_ticks=300",
              "mdp.tau_e=300", "train.tensorboard=false"]
TINY_RECIPES = {
    "tabular": ["agent=tabular", "agent.num_sites=8", "train.max_episodes=16", *TINY_TRAIN],
    "dqn_partial_throughput": ["agent=dqn", "state=partial", "mdp.reward=throughput",
                               "agent.num_sites=2", "agent.steps_per_round=20",
                               "agent.updates_per_round=5", "train.max_episodes=4",
                               *TINY_TRAIN],
}


def _recipes(folder, recipes: dict[str, list[str]]) -> None:
    """A recipes file of the user's own conf/ (conf/README.md): the packaged recipes with
    these replaced."""
    path = folder / "conf" / "recipes" / "tiny.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump({"defaults": ["default", "_self_"],
                                    **{n: {"overrides": o} for n, o in recipes.items()}}))


def _table(folder, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "fleet_torchrl.table", "recipes=tiny",
           f"table.only=[{','.join(TINY_RECIPES)}]", "eval.n_sims=24", "eval.ticks=600",
           "eval.progress=false", "table.out=out/table", "table.policies_dir=out/pol",
           "table.runs_dir=out/runs", *args]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=folder)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    return r


@pytest.mark.slow
def test_table_end_to_end(tmp_path):
    _recipes(tmp_path, TINY_RECIPES)
    r = _table(tmp_path, "table.seeds=2", "table.improve_sims=4")
    # four trainings as Hydra jobs, two at a time, with overall progress; then 6 evaluations
    assert "[table] 4 trainings to run (2 at a time)" in r.stdout
    assert "Joblib.Parallel(n_jobs=2" in r.stdout + r.stderr
    assert "[table] 4 of 4 jobs done: train_" in r.stdout
    assert "[table] evaluation 6 of 6, dqn_partial_throughput_seed1" in r.stdout
    runs = tmp_path / "out" / "runs"
    assert sorted(p.name for p in runs.iterdir()) == [
        "train_dqn_partial_throughput_seed0", "train_dqn_partial_throughput_seed1",
        "train_tabular_seed0", "train_tabular_seed1"]  # the .progress folder is gone
    assert (runs / "train_tabular_seed1" / "train.log").is_file()
    rows = json.loads((tmp_path / "out" / "table" / "table.json").read_text())
    assert [r["policy"] for r in rows] == ["rule", "heuristic", "tabular",
                                           "dqn_partial_throughput"]
    assert [r["objective"] for r in rows] == ["", "", "thesis", "throughput"]
    out = tmp_path / "out" / "table"
    for f in ("table.md", "table.csv", "table.json", "boxplot.png", "learning_curves.png",
              "rule.json", "rule.csv", "tabular_seed0.json", "dqn_partial_throughput_seed1.csv"):
        assert (out / f).exists(), f
    assert rows[0]["gain_pct"] == 0.0  # the rule against itself
    tab = rows[2]
    assert tab["seeds"] == [0, 1] and len(tab["gain_per_seed"]) == 2
    assert tab["gain_pct"] == pytest.approx(sum(tab["gain_per_seed"]) / 2)
    assert min(tab["gain_per_seed"]) == tab["gain_min"] and tab["gain_ci95"] >= 0
    assert all(t is not None for t in tab["train_time_s"])  # from each run's summary
    for seed in (0, 1):  # one result per seed, each paired with the rule on the same sites
        res = json.loads((out / f"tabular_seed{seed}.json").read_text())
        assert res["seed"] == 0 and res["n_sims"] == 24
    assert len(list(csv.DictReader((out / "table.csv").open()))) == 4
    assert "± 95 %" in (out / "table.md").read_text()
    # one step of policy improvement over every row, paired on the first sites
    table_rows = json.loads((out / "table.json").read_text())
    assert all(isinstance(r["improvement_pct"], float) and r["improvement_ci95"] >= 0
               for r in table_rows)
    assert "One-step improvement" in (out / "table.md").read_text()
    # a second run reuses the saved policies (same recorded configuration): no job
    pol = tmp_path / "out" / "pol" / "tabular" / "seed1" / "policy.pt"
    mtime = pol.stat().st_mtime
    r = _table(tmp_path, "table.seeds=2", "table.evaluate=false")
    assert r.stdout.count("[table] reusing") == 4 and "trainings to run" not in r.stdout
    assert pol.stat().st_mtime == mtime
    # changed settings: the saved policy is not reused, the run dir's checkpoint of the old
    # settings is set aside (nothing is deleted) and the policy is trained afresh
    _recipes(tmp_path, {**TINY_RECIPES, "tabular": [*TINY_RECIPES["tabular"], "agent.k=50"]})
    r = _table(tmp_path, "table.seeds=1", "table.only=[tabular]")
    assert "[table] 1 trainings to run" in r.stdout and "1 of 1 jobs done" in r.stdout
    assert pol.stat().st_mtime == mtime  # seed 1 is no longer asked for
    seed0 = tmp_path / "out" / "pol" / "tabular" / "seed0"
    assert json.loads((seed0 / "train_summary.json").read_text())[
        "fingerprint"]["agent"]["k"] == 50.0
    stale = list(runs.glob("train_tabular_seed0.stale-*"))
    assert len(stale) == 1 and (stale[0] / "checkpoint.ckpt").exists()
    # an unreadable checkpoint is set aside the same way
    (seed0 / "policy.pt").unlink()
    (runs / "train_tabular_seed0" / "checkpoint.ckpt").write_bytes(b"garbage")
    _table(tmp_path, "table.seeds=1", "table.only=[tabular]")
    assert (seed0 / "policy.pt").exists()
    assert len(list(runs.glob("train_tabular_seed0.stale-*"))) == 2


@pytest.mark.slow
def test_table_resumes_a_killed_training_from_its_checkpoint(tmp_path):
    """A training killed after its checkpoint (its policy never published) is resumed as a
    job with resume=true, and ends where an uninterrupted run does."""
    from fleet_torchrl.experiments.table import plan_jobs, run_overrides
    from fleet_torchrl.table_sweep import table_specs
    from fleet_torchrl.training import RunSpec, Trainer

    recipes = {"tabular": ["agent=tabular", "agent.num_sites=8", "train.max_episodes=48",
                           "train.checkpoint_every=1", *TINY_TRAIN]}
    _recipes(tmp_path, recipes)
    overrides = ["recipes=tiny", "table.only=[tabular]", "table.seeds=1",
                 f"table.runs_dir={tmp_path / 'out' / 'runs'}",
                 f"table.policies_dir={tmp_path / 'out' / 'pol'}"]
    import os

    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        cfg = compose_config(overrides)
        run_cfg = compose_config(run_overrides("tabular", 0, cfg))
        Trainer(RunSpec.of(run_cfg), tmp_path / "out" / "runs" / "train_tabular_seed0").run(
            stop_after_rounds=3)  # "killed" after round 3's checkpoint
        (job,) = plan_jobs(cfg, table_specs(cfg, 0))
        assert "resume=true" in job.overrides
    finally:
        os.chdir(cwd)
    r = _table(tmp_path, "table.only=[tabular]", "table.seeds=1", "table.evaluate=false")
    assert "[table] resuming" in r.stdout
    summary = json.loads((tmp_path / "out" / "pol" / "tabular" / "seed0" /
                          "train_summary.json").read_text())
    assert summary["resumed"] and summary["rounds"] == 6
    whole = compose_config(["agent=tabular", "agent.num_sites=8", "train.max_episodes=48",
                            "train.checkpoint_every=1", *TINY_TRAIN, "train.progress=false",
                            f"train.out_dir={tmp_path / 'whole'}"])
    straight = Trainer(RunSpec.of(whole), tmp_path / "whole_run").run()

    def evals(s):  # the evaluations, without the wall times
        return [{k: v for k, v in h.items() if k != "wall_s"} for h in s["history"]]

    assert evals(summary) == evals(straight) and summary["frames"] == straight["frames"]


def test_a_single_seed_row_has_no_interval():
    from fleet_torchrl.experiments.table import rows_markdown

    row = {"policy": "x", "objective": "thesis", "seeds": [0], "trips_mean": 1.0,
           "queue_mean": 1.0, "failure_rate": 0.0, "gain_pct": 1.0, "gain_ci95": float("nan"),
           "gain_per_seed": [1.0], "gain_vs_heuristic_pct": 0.0, "train_time_s": [10.0]}
    line = rows_markdown([row], compose_config([])).splitlines()[4]
    assert "nan" not in line and "| +1.00 | - | +1.00 |" in line


def test_learning_curves_fit_their_data():
    """A run that stays around -10 % is inside the axis (it used to stop at -5 %); an
    evaluation with failures at -80 % does not stretch it, but is marked on its edge."""
    import matplotlib.pyplot as plt

    from fleet_torchrl.utils.plotting import plot_learning_curves

    curves = {"tabular": {0: [(60, -12.0, 0.0), (120, -9.0, 0.0), (180, -8.5, 0.0)]},
              "dqn": {0: [(60, -80.0, 0.4), (120, 1.0, 0.0), (180, 2.0, 0.0)],
                      1: [(60, 0.5, 0.0), (120, 1.5, 0.0)]}}
    fig = plot_learning_curves(curves)
    ax = fig.axes[0]
    lo, hi = ax.get_ylim()
    assert -20 < lo < -12 and 2 < hi < 5
    drawn = [y for line in ax.get_lines() for y in line.get_ydata()]
    assert min(drawn) >= lo  # the failing evaluation sits on the edge, not below it
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "1 evaluations with failures, below the axis" in labels
    plt.close(fig)
    fig = plot_learning_curves({"dqn": {0: [(60, 1.0), (120, 3.0)]}})  # no failure rates
    assert fig.axes[0].get_ylim()[0] <= -0.5  # the rule's 0 stays in view
    plt.close(fig)


def test_a_table_on_another_site_trains_there_and_refuses_what_cannot_reach_its_runs():
    """``make table ARGS="site=five_vehicles"`` forwards the site to every recipe that has no
    site of its own and publishes under a name that says it (the default site's policies
    stay untouched); settings each recipe sets itself are refused at the table level."""
    from fleet_torchrl.experiments.table import recipe_folder, run_overrides, site_overrides
    from fleet_torchrl.table_sweep import check_forwardable
    from fleet_torchrl.utils.checks import ConfigError

    plain = compose_config([])
    assert site_overrides(plain) == [] and recipe_folder(plain, "tabular") == "tabular"
    five = compose_config(["site=five_vehicles"])
    assert site_overrides(five) == ["site=five_vehicles"]
    ov = run_overrides("dqn_partial", 1, five)
    assert "site=five_vehicles" in ov
    assert any(o.endswith("dqn_partial_five_vehicles/seed1") for o in ov)
    run = compose_config(ov)
    assert run.site.n_vehicles == 5
    # the generalist trains on its own site distribution whatever the table's site
    assert recipe_folder(five, "generalist") == "generalist"
    assert compose_config(run_overrides("generalist_dqn", 0, five)).site.randomized
    # ... and its teacher plans over the policies this table trains (dqn_all on its site;
    # search_crowded, search_slow and dqn_fast on their own)
    assert ("agent.expert.bases=[results/policies/dqn_all_five_vehicles/seed0/policy.pt,"
            "results/policies/search_crowded/seed0/policy.pt,"
            "results/policies/search_slow/seed0/policy.pt,"
            "results/policies/dqn_fast/seed0/policy.pt]") in run_overrides(
                "generalist", 0, five)
    # a field changed on top of a preset is forwarded too, under a name with its hash
    tweak = compose_config(["site=five_vehicles", "site.p_c=0.5"])
    assert site_overrides(tweak) == ["site=five_vehicles", "site.p_c=0.5"]
    assert recipe_folder(tweak, "tabular").startswith("tabular_five_vehicles-")
    check_forwardable(five)
    for bad, field in (("mdp.reward=throughput", "mdp.reward"), ("state=all", "state.name"),
                       ("network.width=8", "network.width")):
        with pytest.raises(ConfigError, match=field):
            check_forwardable(compose_config([bad]))


@pytest.mark.slow
def test_a_teacher_over_other_recipes_trains_after_them_and_follows_their_files(tmp_path):
    """A recipe whose teacher plans over other recipes' policies (``bases``) is trained in a
    second wave, over their files (the table's first seed); its saved run is reused while
    those files are the same, and trained again when one of them changes."""
    tiny_student = ["agent=imitation", "agent.num_sites=8", "agent.steps_per_round=4",
                    "agent.rounds=2", "agent.beta_rounds=1", "agent.hidden=8",
                    "agent.updates_per_round=2", "agent.batch_size=8",
                    "agent.expert.rollouts=2", "agent.expert.horizon=20", *TINY_TRAIN]
    path = tmp_path / "conf" / "recipes" / "tiny.yaml"
    path.parent.mkdir(parents=True)

    def write(k: int) -> None:
        path.write_text(yaml.safe_dump({"defaults": ["default", "_self_"],
                                        "tabular": {"overrides": [*TINY_RECIPES["tabular"],
                                                                  f"agent.k={k}"]},
                                        "student": {"overrides": tiny_student,
                                                    "bases": ["tabular"]}}))

    write(40)
    r = _table(tmp_path, "table.only=[student]", "table.seeds=2", "table.evaluate=false")
    # the base's two seeds first, then the students over its seed 0
    first, second = r.stdout.split("[table] 2 trainings to run")[1:3]
    assert "train_tabular_seed0" in first and "train_student_seed" not in first
    assert "train_student_seed1" in second
    base = tmp_path / "out" / "pol" / "tabular" / "seed0" / "policy.pt"
    summary = json.loads((tmp_path / "out" / "pol" / "student" / "seed1" /
                          "train_summary.json").read_text())
    (entry,) = summary["fingerprint"]["agent"]["expert"]["bases"]
    assert entry.startswith("out/pol/tabular/seed0/policy.pt#")
    r = _table(tmp_path, "table.only=[student]", "table.seeds=2", "table.evaluate=false")
    assert r.stdout.count("[table] reusing") == 4 and "trainings to run" not in r.stdout
    write(50)  # the base changes: so does what its students were taught
    before = base.read_bytes()
    r = _table(tmp_path, "table.only=[student]", "table.seeds=1", "table.evaluate=false")
    assert base.read_bytes() != before
    assert r.stdout.count("[table] 1 trainings to run") == 2


def test_recipe_bases_are_checked():
    from fleet_torchrl.experiments.config import Recipe, validate_recipes
    from fleet_torchrl.utils.checks import ConfigError

    ok = {"a": Recipe(["agent=tabular"]), "b": Recipe(["agent=imitation"], bases=["a"])}
    assert validate_recipes(ok, ("rule",)) is ok
    cfg = compose_config([])
    cfg.recipes = ok
    assert cfg.table.training_names(ok) == ["a", "b"]
    cfg.table.only = ["b"]
    assert cfg.table.names(ok) == ["b"] and cfg.table.training_names(ok) == ["a", "b"]
    from fleet_torchrl.experiments.table import run_overrides

    assert "agent.expert.bases=[results/policies/a/seed0/policy.pt]" in run_overrides("b", 1, cfg)
    with pytest.raises(ConfigError, match=r"recipe.bases=\['a'\] is invalid: allowed only"):
        Recipe(["agent=dqn"], bases=["a"])
    from fleet_torchrl.config import check_point_recipe

    with pytest.raises(ConfigError, match=r"sweep.distil='b' is invalid: its teacher plans"):
        check_point_recipe("sweep.distil", "b", ok["b"])
    check_point_recipe("sweep.distil", "a", ok["a"])  # no bases, no site: fine
    for bad in (["b"], ["c"], ["x"]):
        recipes = {**ok, "c": Recipe(["agent=imitation"], bases=["b"]),
                   "x": Recipe(["agent=imitation"], bases=bad)}
        with pytest.raises(ConfigError, match=r"recipes\.(c|x)\.bases\[0\]"):
            validate_recipes(recipes, ("rule",))


def test_a_row_trained_on_another_site_says_so():
    """The bases of the generalist's teacher train on other sites; the table names that site
    beside their (off-site) figures, and a recipe without a site of its own trains here."""
    from fleet_torchrl.experiments.table import rows_markdown, trained_on

    cfg = compose_config([])
    assert trained_on(cfg, "dqn_fast") == "site.t_c=10"
    assert trained_on(cfg, "search_crowded") == "site.n_vehicles=5"
    assert trained_on(cfg, "generalist") == "site=randomized"
    assert trained_on(cfg, "dqn_partial") == "this site"
    row = {"policy": "x", "objective": "thesis", "trained_on": "site.t_c=10", "seeds": [0],
           "trips_mean": 1.0, "queue_mean": 1.0, "failure_rate": 0.02, "gain_pct": 1.0,
           "gain_ci95": float("nan"), "gain_per_seed": [1.0], "gain_vs_heuristic_pct": 0.0,
           "train_time_s": [10.0]}
    lines = rows_markdown([row], cfg).splitlines()
    assert "| trained on |" in lines[2] and "| x | thesis | site.t_c=10 | 0 |" in lines[4]
