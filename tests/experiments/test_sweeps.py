"""A miniature sweep end to end through Hydra multirun."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from types import SimpleNamespace

import pytest

from fleet_torchrl import sweeps_summary

TINY = ("agent.generations=2", "agent.population=4", "agent.elite=1", "agent.sites=4",
        "agent.ticks=300", "train.eval_sims=8", "train.eval_ticks=300")


def _searches(**classes: list[str]) -> str:
    """A ``sweep.searches={...}`` override of tiny searches (one per keyword)."""
    body = ",".join(f"{name}:[" + ",".join(f"'{o}'" for o in (*extra, *TINY)) + "]"
                    for name, extra in classes.items())
    return "sweep.searches={" + body + "}"


TINY_SEARCH = _searches(search_threshold=["agent.policy_class=threshold"],
                        search_table=["agent.policy_class=table", "agent.tc_bins=4"])
TINY_PICK = ["sweep.pick_sims=8", "sweep.pick_ticks=300", "sweep.improve_sims=4",
             "sweep.planner_overrides=['agent.rollouts=2','agent.horizon=20']"]
# the specialists' recipes (conf/recipes), tiny; two seeds at p_c=0.8, one elsewhere
def _recipe(name: str, *overrides: str) -> str:
    return f"recipes.{name}.overrides=[" + ",".join(f"'{o}'" for o in overrides) + "]"


TINY_LEARN = ("train.eval_every=1", "train.eval_sims=8", "train.eval_ticks=300", "mdp.tau_e=300")
TINY_SPECIALISTS = [
    _recipe("tabular", "agent=tabular", "agent.num_sites=8", "train.max_episodes=16",
            *TINY_LEARN),
    _recipe("dqn_partial", "agent=dqn", "state=partial", "agent.num_sites=2",
            "agent.steps_per_round=10", "agent.updates_per_round=2", "train.max_episodes=4",
            *TINY_LEARN),
    _recipe("imitation", "agent=imitation", "state=partial", "agent.num_sites=4",
            "agent.steps_per_round=5", "agent.rounds=2", "agent.updates_per_round=2",
            "agent.expert.rollouts=2", "agent.expert.horizon=20", *TINY_LEARN),
    "+sweep.specialists.specialist_imitation=imitation",  # not a default row: opted in
    "sweep.more_seeds_at=['p_c=0.8']", "sweep.more_seeds=2"]


def test_search_starts_from_the_points_best_partial_policy(saved_policies):
    """The point's search starts from the best partial-state policy there, judged on the
    search's own selection set: the heuristic beats the rule and an untrained network on the
    default site; a saved policy is named by its file."""
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.experiments.sweeps import search_start
    from fleet_torchrl.store import load_policies
    from fleet_torchrl.sweeps import point_settings

    cfg = compose_config([f"table.policies_dir={saved_policies}", TINY_SEARCH, *TINY_PICK,
                          "sweep.specialist=false"])
    p = point_settings(cfg)
    run_cfg = p.searches["search_table"]
    assert run_cfg.train.eval_sims == 8 and run_cfg.site.p_c == 0.8
    assert run_cfg.agent.tc_bins == 4

    pols = load_policies(cfg.table.policies_dir, ["rule", "heuristic", "dqn_partial"], "cpu")
    assert search_start(p, run_cfg, pols) == "heuristic"
    # a saved policy that acts as the heuristic beats the rule: it is named by its file
    from fleet_torchrl.agents import HeuristicPolicy, save_policy
    from fleet_torchrl.agents.search import SearchPolicy, cell_centres

    good = SearchPolicy("table")
    good.charge.copy_(HeuristicPolicy()(cell_centres()))
    save_policy(saved_policies / "good" / "policy.pt", good, "search")
    pols = load_policies(cfg.table.policies_dir, ["rule", "good"], "cpu")
    assert search_start(p, run_cfg, pols) == str(saved_policies / "good" / "policy.pt")
    # the threshold class starts from the rule's or the heuristic's thresholds
    thr_cfg = p.searches["search_threshold"]
    pols = load_policies(cfg.table.policies_dir, ["rule", "heuristic", "dqn_partial"], "cpu")
    assert search_start(p, thr_cfg, pols) in ("heuristic",
                                                 str(saved_policies / "dqn_partial" /
                                                     "policy.pt"))
    # a point's earlier search (not under table.policies_dir) starts the next from its file
    # (it failed T_C 40 and 50 when it was looked up as a saved policy)
    pols = {"rule": load_policies(cfg.table.policies_dir, ["rule"], "cpu")["rule"],
            "search_threshold": good}
    trained = {"search_threshold": saved_policies / "good" / "policy.pt"}
    assert search_start(p, run_cfg, pols, trained) == str(trained["search_threshold"])


def test_best_known_is_the_best_row_on_the_pick_set():
    from fleet_torchrl.experiments.sweeps import best_of, is_learned

    assert is_learned("dqn_all") and is_learned("specialist_dqn") and is_learned("generalist")
    assert not any(is_learned(n) for n in ("rule", "heuristic", "threshold", "search",
                                           "search_threshold", "planner", "planner_dqn_all",
                                           "best_known"))
    # keys: (failure rate, -mean trips), lower is better; on a tie the first row
    assert best_of({"planner": (0.0, -100.0), "dqn": (0.0, -101.0)}) == "dqn"
    assert best_of({"dqn": (0.0, -100.0), "planner": (0.0, -100.0)}) == "dqn"
    assert best_of({"planner": (0.0, -100.0), "dqn": (0.01, -120.0)}) == "planner"
    assert best_of({"heuristic": (0.0, -99.0), "search_threshold": (0.0, -99.5)}) == \
        "search_threshold"


def test_planner_search_is_the_planner_over_the_best_search_that_beats_the_heuristic():
    """Row planner_search: the planner over the point's best search on the pick set, only if
    that search decides inside the kernel and beats the heuristic there."""
    from fleet_torchrl.agents import HeuristicPolicy
    from fleet_torchrl.agents.search import SearchPolicy
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.experiments.sweep_candidates import Pool
    from fleet_torchrl.experiments.sweeps import search_base

    def settings(*overrides):
        return SimpleNamespace(sweep=compose_config(list(overrides)).sweep)

    cfg = settings()
    groups = {"heuristic": {None: HeuristicPolicy()},
              "search_threshold": {None: SearchPolicy("threshold")},
              "search_table": {None: SearchPolicy("table", n_tc=4)},
              "search_mlp": {None: SearchPolicy("mlp")},
              "search": {0: SearchPolicy("table")}}  # the default-site search: not a point's
    keys = {("heuristic", None): (0.0, -100.0), ("search_threshold", None): (0.0, -101.0),
            ("search_table", None): (0.0, -102.0), ("search_mlp", None): (0.0, -110.0),
            ("search", 0): (0.0, -120.0)}
    pool = Pool(policies=groups, keys=keys)
    assert search_base(cfg, pool) == "search_table"  # the mlp has no kernel form
    keys[("search_table", None)] = (0.01, -130.0)  # fails on the pick set: worse
    assert search_base(cfg, pool) == "search_threshold"
    keys[("search_threshold", None)] = (0.0, -100.0)  # a tie with the heuristic: no row
    assert search_base(cfg, pool) is None
    keys[("search_threshold", None)] = (0.0, -100.5)
    assert search_base(settings("sweep.planner_search=false"), pool) is None
    assert search_base(settings("sweep.planner=false"), pool) is None


def test_the_distilled_rows_teacher_and_state(tmp_path):
    """Row specialist_distilled: the planner over planner_search's base (else the
    heuristic's), unless a row beats every planner row on the pick set: then over the best
    such row, by its policy file; the student reads its base's state where the imitation
    learner accepts it and it differs from the recipe's."""
    from fleet_torchrl.agents import HeuristicPolicy
    from fleet_torchrl.agents.config import NetworkConfig
    from fleet_torchrl.agents.dqn import DQNPolicy
    from fleet_torchrl.agents.search import SearchPolicy
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.experiments.sweeps import distil_base, distil_state, distil_teacher
    from fleet_torchrl.utils.checks import ConfigError

    planner = compose_config(["agent=planner"]).agent
    recipe_state = compose_config(["agent=imitation", "state=partial"]).state.name
    groups = {"heuristic": {None: HeuristicPolicy()},
              "search_threshold": {None: SearchPolicy("threshold")},
              "dqn_all": {s: DQNPolicy(NetworkConfig(), 31, "all") for s in (0, 1)}}
    keys = {("heuristic", None): (0.0, -100.0), ("search_threshold", None): (0.0, -101.0),
            ("dqn_all", 0): (0.0, -101.5), ("dqn_all", 1): (0.0, -99.0),
            ("planner", None): (0.0, -102.0), ("planner_search", None): (0.0, -103.0),
            ("specialist_distilled", 0): (0.0, -200.0)}  # a student of a planner: no base
    bases = {"heuristic": "planner", "search_threshold": "planner_search"}
    files = {("search_threshold", None): tmp_path / "t.pt", ("dqn_all", 0): tmp_path / "a.pt",
             ("dqn_all", 1): tmp_path / "b.pt"}
    for f in files.values():  # a teacher's base is a policy file that exists
        f.touch()
    assert distil_base(keys, bases) == ("search_threshold", None)
    assert distil_teacher(planner, ("search_threshold", None), files).base == \
        str(tmp_path / "t.pt")
    # partial: the recipe's
    assert distil_state(recipe_state, groups, ("search_threshold", None)) is None
    keys[("dqn_all", 0)] = (0.0, -103.5)  # better than every planner: the planner over it
    assert distil_base(keys, bases) == ("dqn_all", 0)
    teacher = distil_teacher(planner, ("dqn_all", 0), files)
    assert teacher.base == str(tmp_path / "a.pt") and teacher.rollouts == 32
    assert distil_state(recipe_state, groups, ("dqn_all", 0)) == "all"
    keys[("planner_search", None)] = (0.0, -104.0)
    assert distil_base(keys, bases) == ("search_threshold", None)
    assert distil_base(keys, {"heuristic": "planner"}) == ("heuristic", None)
    assert distil_teacher(planner, ("heuristic", None), files).base == "heuristic"
    assert distil_base(keys, {}) is None and distil_teacher(planner, None, files).base \
        == "heuristic"
    with pytest.raises(ConfigError, match="has no policy file"):
        distil_teacher(planner, ("dqn_partial", 0), files)


def test_a_sweep_on_a_site_distribution_is_refused():
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.experiments.sweeps import run_point
    from fleet_torchrl.sweeps import point_settings
    from fleet_torchrl.utils.checks import ConfigError

    cfg = compose_config(["site=randomized", "+experiment=sweep_pc", "sweep.value=0.4"])
    with pytest.raises(ConfigError, match="site distribution"):
        run_point(point_settings(cfg))


@pytest.mark.slow
def test_miniature_sweep_end_to_end(tmp_path, saved_policies, command):
    root = saved_policies
    out = tmp_path / "sweeps"
    cmd = [sys.executable, "-m", "fleet_torchrl.sweeps", "-m", "+experiment=sweep_pc",
           "sweep.value=0.4,0.8", "eval.n_sims=16", "eval.ticks=400",
           "sweep.policies=[rule,heuristic,tabular,dqn_partial,search]",
           f"table.policies_dir={root}", f"sweep.out={out}", TINY_SEARCH, *TINY_PICK,
           *TINY_SPECIALISTS,
           f"sweep.search_dir={tmp_path / 'search'}",
           f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in (out / "pc").glob("*.json")) == ["p_c=0.4.json", "p_c=0.8.json"]
    assert "[sweeps] 2 of 2 jobs done: sweep.value=" in r.stdout  # overall progress
    assert command(sweeps_summary.main, "name=pc", f"out={out}",
                   "expect=['p_c=0.4','p_c=0.8']") == 0
    # another sweep's point on the same site with the same settings (T_C = 30 is the site of
    # p_c = 0.8, with its two specialist seeds) reuses its rows instead of computing them
    tc = cmd[:4] + ["+experiment=sweep_tc", "sweep.value=30"] + cmd[6:-1] + [
        "sweep.more_seeds_at=['p_c=0.8','t_c=30']", f"hydra.sweep.dir={tmp_path / 'mr_tc'}"]
    rt = subprocess.run(tc, capture_output=True, text=True, timeout=300)
    assert rt.returncode == 0 and "its rows reused" in rt.stdout, rt.stdout[-2000:]
    twin = json.loads((out / "tc" / "t_c=30.json").read_text())
    orig = json.loads((out / "pc" / "p_c=0.8.json").read_text())
    assert twin["reused_from"].endswith("p_c=0.8.json") and twin["key"] != orig["key"]
    assert [(r["policy"], r["trips_mean"]) for r in twin["rows"]] == \
        [(r["policy"], r["trips_mean"]) for r in orig["rows"]]
    assert {(r["param"], r["value"]) for r in twin["rows"]} == {("t_c", 30)}
    assert set(orig["wall_s"]) >= {"searches", "specialists", "evaluation", "total"}
    rows = list(csv.DictReader((out / "pc.csv").open()))
    assert set(rows[0]) == {"param", "value", "policy", "seeds", "trips_mean", "trips_std",
                            "queue_mean", "failure_rate", "failure_rate_max", "gain_pct",
                            "gain_ci95", "gain_per_seed", "share_of_best_known_pct",
                            "improvement_pct", "improvement_ci95", "improvement_sims",
                            "improvement_seed"}
    names = {"rule", "heuristic", "tabular", "dqn_partial", "search", "search_threshold",
             "search_table", "specialist_dqn", "specialist_tabular", "specialist_imitation",
             "specialist_distilled", "planner", "best_known"}
    # planner_search: at a point whose best search beats the heuristic on the pick set
    extra = {v: {r["policy"] for r in rows if r["value"] == v} - names for v in ("0.4", "0.8")}
    assert all(e <= {"planner_search"} for e in extra.values()), extra
    assert {r["policy"] for r in rows} - {"planner_search"} == names
    assert len(rows) == 2 * 13 + sum(len(e) for e in extra.values())
    # one step of improvement: the heuristic's from the planner row on every site, the best
    # learned row's on the first sweep.improve_sims sites; no other row has one
    for v in ("0.4", "0.8"):
        imp = {r["policy"]: r for r in rows if r["value"] == v and r["improvement_pct"]}
        assert imp["heuristic"]["improvement_sims"] == "16", imp["heuristic"]
        heur = next(r for r in rows if r["value"] == v and r["policy"] == "heuristic")
        plan = next(r for r in rows if r["value"] == v and r["policy"] == "planner")
        assert float(heur["improvement_pct"]) == pytest.approx(
            100 * (float(plan["trips_mean"]) - float(heur["trips_mean"]))
            / next(float(r["trips_mean"]) for r in rows
                   if r["value"] == v and r["policy"] == "rule"), abs=1e-6)
        if "planner_search" in extra[v]:  # the search's improvement: that row, every site
            base = [n for n in imp if n.startswith("search_")]
            assert len(base) == 1 and imp[base[0]]["improvement_sims"] == "16"
        learned = {n for n in imp if n != "heuristic" and not n.startswith("search_")}
        assert len(learned) == 1 and imp[learned.pop()]["improvement_sims"] == "4"
    assert all(float(r["gain_pct"]) == 0.0 for r in rows if r["policy"] == "rule")
    for r in rows:  # the share is the gain over best_known's gain, where that is positive
        best = next(float(o["gain_pct"]) for o in rows
                    if o["policy"] == "best_known" and o["value"] == r["value"])
        if best > 0:
            assert float(r["share_of_best_known_pct"]) == pytest.approx(
                100 * float(r["gain_pct"]) / best, rel=1e-9)
        else:
            assert r["share_of_best_known_pct"] == ""
    # the specialists: one seed at p_c=0.4, two at p_c=0.8 (sweep.more_seeds_at), each row
    # the mean over its seeds with every seed's gain
    spec = {r["value"]: r for r in rows if r["policy"] == "specialist_dqn"}
    assert spec["0.4"]["seeds"] == "0" and spec["0.8"]["seeds"] == "0 1"
    per_seed = [float(g) for g in spec["0.8"]["gain_per_seed"].split()]
    assert float(spec["0.8"]["gain_pct"]) == pytest.approx(sum(per_seed) / 2, abs=1e-3)
    # each point searched its own site, each class apart: cached, keyed by their settings
    found = sorted(str(p.relative_to(tmp_path / "search").parent.parent)
                   for p in (tmp_path / "search").glob("*/*/*/policy.pt"))
    assert found == ["p_c=0.4/search_table", "p_c=0.4/search_threshold",
                     "p_c=0.8/search_table", "p_c=0.8/search_threshold"], found
    found = sorted(str(p.relative_to(tmp_path / "search").parent.parent)
                   for p in (tmp_path / "search").glob("*/specialist_*/*/*/policy.pt"))
    assert found == ["p_c=0.4/specialist_distilled/seed0", "p_c=0.4/specialist_dqn/seed0",
                     "p_c=0.4/specialist_imitation/seed0", "p_c=0.4/specialist_tabular/seed0",
                     "p_c=0.8/specialist_distilled/seed0", "p_c=0.8/specialist_distilled/seed1",
                     "p_c=0.8/specialist_dqn/seed0", "p_c=0.8/specialist_dqn/seed1",
                     "p_c=0.8/specialist_imitation/seed0", "p_c=0.8/specialist_imitation/seed1",
                     "p_c=0.8/specialist_tabular/seed0", "p_c=0.8/specialist_tabular/seed1"]
    assert (out / "pc.png").stat().st_size > 1000 and (out / "pc.json").exists()
    point = json.loads((out / "pc" / "p_c=0.8.json").read_text())
    assert point["guard"] is True
    # the distilled row's teacher: the planner over the planner_search row's search (its
    # policy file), else over the heuristic, unless a row beats every planner on the pick
    # set: then over that row
    for v, p in (("0.4", out / "pc" / "p_c=0.4.json"), ("0.8", out / "pc" / "p_c=0.8.json")):
        pt = json.loads(p.read_text())
        teacher = pt["trainings"]["specialist_distilled_seed0"]["teacher_base"]
        pick = {k: (q["failure_rate"], -q["trips_mean"])
                for k, q in pt["best_known"]["pick_set"].items()}
        plans = [q for k, q in pick.items() if k.startswith("planner")]
        others = {k: q for k, q in pick.items()
                  if not k.startswith(("planner", "specialist_distilled"))}
        top = min(others, key=others.get)
        if others[top] < min(plans):
            assert top.split("_seed")[0] in teacher, (teacher, top)
        elif "planner_search" in extra[v]:
            assert teacher.startswith(str(tmp_path / "search" / f"p_c={v}" / "search_"))
        else:
            assert teacher == "heuristic"
    assert point["trainings"]["search_table"]["init"] in (
        "rule", "heuristic", str(root / "tabular" / "policy.pt"),
        str(root / "dqn_partial" / "policy.pt"))
    # best_known is the row that does best on the pick set, evaluated on the same sites
    bk = point["best_known"]
    src = bk["from"] if bk["seed"] is None else f"{bk['from']}_seed{bk['seed']}"
    pick = bk["pick_set"]
    assert src in pick and all((pick[src]["failure_rate"], -pick[src]["trips_mean"])
                               <= (p["failure_rate"], -p["trips_mean"]) for p in pick.values())
    trips = {r["policy"]: r["trips_mean"] for r in point["rows"]}
    if bk["seed"] is None or len([r for r in point["rows"] if r["policy"] == bk["from"]][0]
                                 ["seeds"]) == 1:
        assert trips["best_known"] == trips[bk["from"]]
    # a rerun skips the finished points; a point that cannot run is reported, not fatal
    r2 = subprocess.run(cmd[:5] + ["sweep.value=0.8"] + cmd[6:], capture_output=True,
                        text=True, timeout=300)
    assert "exists, skipping" in r2.stdout
    # other evaluation settings: the point is recomputed, its search reused
    r4 = subprocess.run(cmd[:5] + ["sweep.value=0.8", "eval.n_sims=12"] + cmd[7:],
                        capture_output=True, text=True, timeout=300)
    assert "recomputing" in r4.stdout and "reusing" in r4.stdout, r4.stdout
    before = json.loads((out / "pc" / "p_c=0.8.json").read_text())["rows"]
    assert all(r["trips_mean"] > 0 for r in before)
    assert "evaluation cache 0 hit(s)" not in r4.stdout  # the pick set's were cached
    # one more row: every other evaluation comes from the cache, with the same numbers
    r5 = subprocess.run(cmd[:5] + ["sweep.value=0.8", "eval.n_sims=12", cmd[7],
                                   "sweep.policies=[rule,heuristic,tabular,dqn_partial,search,"
                                   "imitation]"] + cmd[9:],
                        capture_output=True, text=True, timeout=300)
    assert r5.returncode == 0, r5.stderr[-2000:]
    m = re.search(r"evaluation cache (\d+) hit\(s\), (\d+) computed", r5.stdout)
    assert m and int(m[1]) >= 30 and int(m[2]) <= 3, r5.stdout  # imitation: pick, test (+1)
    after = {r["policy"]: r for r in
             json.loads((out / "pc" / "p_c=0.8.json").read_text())["rows"]}
    assert "imitation" in after
    for r in before:
        assert {k: after[r["policy"]][k] for k in ("trips_mean", "queue_mean", "gain_pct")} \
            == {k: r[k] for k in ("trips_mean", "queue_mean", "gain_pct")}, r["policy"]
    bad = cmd[:5] + ["sweep.value=0.6"] + [c for c in cmd[6:] if "policies_dir" not in c] + [
        f"table.policies_dir={tmp_path / 'nowhere'}"]
    r3 = subprocess.run(bad, capture_output=True, text=True, timeout=300)
    # a failed point is written beside the others and counts: the multirun exits 1
    assert r3.returncode == 1 and (out / "pc" / "p_c=0.6.error").exists()
    assert "error: point p_c=0.6 failed" in r3.stderr, r3.stderr
    assert "error: 1 of 1 jobs failed: " in r3.stderr.strip().splitlines()[-1], r3.stderr
    assert command(sweeps_summary.main, "name=pc", f"out={out}") == 1  # failed, missing points


@pytest.mark.slow
def test_miniature_sweep_through_submitit(tmp_path):
    """The same sweep through hydra-submitit-launcher's local executor (what a Slurm run
    uses, with processes instead of cluster jobs)."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    out = tmp_path / "sweeps"
    cmd = [sys.executable, "-m", "fleet_torchrl.sweeps", "-m", "+experiment=sweep_pc",
           "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=5",
           "sweep.value=0.4,0.8", "eval.n_sims=8", "eval.ticks=300",
           "sweep.policies=[rule,heuristic]", "sweep.search=false", "sweep.planner=false",
           "sweep.specialist=false",
           f"sweep.out={out}", f"sweep.search_dir={tmp_path / 'search'}",
           f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Submitit 'local' sweep output dir" in r.stdout + r.stderr
    assert sorted(p.name for p in (out / "pc").glob("*.json")) == ["p_c=0.4.json", "p_c=0.8.json"]
    rows = json.loads((out / "pc" / "p_c=0.8.json").read_text())["rows"]
    assert {row["policy"] for row in rows} == {"rule", "heuristic", "best_known"}
    assert list((tmp_path / "multirun" / ".submitit").iterdir())  # submitit's job folders


@pytest.mark.slow
def test_miniature_sweep_through_ray(tmp_path):
    """The same sweep as Ray tasks on a local Ray instance that the launcher starts
    (``hydra/launcher=ray``; ``ray_cluster`` connects to a running cluster instead)."""
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    out = tmp_path / "sweeps"
    cmd = [sys.executable, "-m", "fleet_torchrl.sweeps", "-m", "+experiment=sweep_pc",
           "hydra/launcher=ray", "+hydra.launcher.ray.init.num_cpus=2",
           "+hydra.launcher.ray.init.include_dashboard=false",
           "sweep.value=0.4,0.8", "eval.n_sims=8", "eval.ticks=300",
           "sweep.policies=[rule,heuristic]", "sweep.search=false", "sweep.planner=false",
           "sweep.specialist=false",
           f"sweep.out={out}", f"sweep.search_dir={tmp_path / 'search'}",
           f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    ray_tmp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # Ray's socket paths must be short
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", "RAY_TMPDIR": ray_tmp}
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    assert "Ray Launcher is launching 2 jobs" in r.stdout + r.stderr
    assert sorted(p.name for p in (out / "pc").glob("*.json")) == ["p_c=0.4.json", "p_c=0.8.json"]
    rows = json.loads((out / "pc" / "p_c=0.4.json").read_text())["rows"]
    assert {row["policy"] for row in rows} == {"rule", "heuristic", "best_known"}
