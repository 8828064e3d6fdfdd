"""A miniature sweep end to end through Hydra multirun."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile

import pytest

from fleet_torchrl import sweeps_summary

TINY_SEARCH = "sweep.search_overrides=[" + ",".join(f"'{o}'" for o in (
    "agent.generations=2", "agent.population=4", "agent.elite=1", "agent.sites=4",
    "agent.ticks=300", "train.eval_sims=8", "train.eval_ticks=300")) + "]"
TINY_PICK = ["sweep.pick_sims=8", "sweep.pick_ticks=300"]


def test_search_starts_from_the_points_best_partial_policy(saved_policies):
    """The point's search starts from the best partial-state policy there, judged on the
    search's own selection set: the heuristic beats the rule and an untrained network on the
    default site; a saved policy is named by its file."""
    from dataclasses import replace

    from fleet_torchrl.config import compose_config
    from fleet_torchrl.experiments.sweeps import search_config, search_start
    from fleet_torchrl.store import load_policies

    cfg = compose_config([f"table.policies_dir={saved_policies}", TINY_SEARCH, *TINY_PICK])
    site = replace(cfg.site, p_c=0.8)
    run_cfg = search_config(cfg, site)
    assert run_cfg.train.eval_sims == 8 and run_cfg.site.p_c == 0.8
    pols = load_policies(cfg, ["rule", "heuristic", "dqn_partial"])
    assert search_start(cfg, run_cfg, pols) == "heuristic"
    # a saved policy that acts as the heuristic beats the rule: it is named by its file
    from fleet_torchrl.agents import HeuristicPolicy, save_policy
    from fleet_torchrl.agents.search import SearchPolicy, cell_centres

    good = SearchPolicy("table")
    good.charge.copy_(HeuristicPolicy()(cell_centres()))
    save_policy(saved_policies / "good" / "policy.pt", good, "search")
    pols = load_policies(cfg, ["rule", "good"])
    assert search_start(cfg, run_cfg, pols) == str(saved_policies / "good" / "policy.pt")


def test_the_optimum_is_the_best_known_policy_on_the_selection_set():
    from fleet_torchrl.experiments.sweeps import POINT_SEARCH, best_known

    # keys: (failure rate, -mean trips), lower is better; the point's search wins a tie
    own = POINT_SEARCH
    assert own != "search"  # "search" is the default-site search of sweep.policies
    assert best_known({own: (0.0, -100.0), "dqn": (0.0, -101.0)}) == "dqn"
    assert best_known({own: (0.0, -100.0), "dqn": (0.0, -100.0)}) == own
    assert best_known({"dqn": (0.0, -100.0), own: (0.0, -100.0)}) == own
    assert best_known({own: (0.0, -100.0), "dqn": (0.01, -120.0)}) == own
    assert best_known({"heuristic": (0.0, -99.0), own: (0.0, -99.5)}) == own


def test_a_sweep_on_a_site_distribution_is_refused():
    from fleet_torchrl.config import compose_config
    from fleet_torchrl.experiments.sweeps import run_point
    from fleet_torchrl.utils.checks import ConfigError

    cfg = compose_config(["site=randomized", "+experiment=sweep_pc", "sweep.value=0.4"])
    with pytest.raises(ConfigError, match="site distribution"):
        run_point(cfg)


@pytest.mark.slow
def test_miniature_sweep_end_to_end(tmp_path, saved_policies, command):
    root = saved_policies
    out = tmp_path / "sweeps"
    cmd = [sys.executable, "-m", "fleet_torchrl.sweeps", "-m", "+experiment=sweep_pc",
           "sweep.value=0.4,0.8", "eval.n_sims=16", "eval.ticks=400",
           "sweep.policies=[rule,heuristic,tabular,dqn_partial,search]",
           f"table.policies_dir={root}", f"sweep.out={out}", TINY_SEARCH, *TINY_PICK,
           f"sweep.search_dir={tmp_path / 'search'}",
           f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in (out / "pc").glob("*.json")) == ["p_c=0.4.json", "p_c=0.8.json"]
    assert "[sweeps] 2 of 2 jobs done: sweep.value=" in r.stdout  # overall progress
    assert command(sweeps_summary.main, "name=pc", f"out={out}",
                   "expect=['p_c=0.4','p_c=0.8']") == 0
    rows = list(csv.DictReader((out / "pc.csv").open()))
    assert set(rows[0]) == {"param", "value", "policy", "trips_mean", "trips_std", "queue_mean",
                            "failure_rate", "gain_pct", "gain_ci95", "share_of_optimum_pct"}
    assert len(rows) == 12 and {r["policy"] for r in rows} == {"rule", "heuristic", "tabular",
                                                               "dqn_partial", "search",
                                                               "optimum"}
    assert all(float(r["gain_pct"]) == 0.0 for r in rows if r["policy"] == "rule")
    for r in rows:  # the share is the gain over the optimum's gain, where that is positive
        best = next(float(o["gain_pct"]) for o in rows
                    if o["policy"] == "optimum" and o["value"] == r["value"])
        if best > 0:
            assert float(r["share_of_optimum_pct"]) == pytest.approx(
                100 * float(r["gain_pct"]) / best, rel=1e-9)
        else:
            assert r["share_of_optimum_pct"] == ""
    # each point searched its own site: two cached searches, keyed by their settings
    assert sorted(p.parent.parent.name for p in (tmp_path / "search").glob("*/*/policy.pt")) == [
        "p_c=0.4", "p_c=0.8"]
    assert (out / "pc.png").stat().st_size > 1000 and (out / "pc.json").exists()
    point = json.loads((out / "pc" / "p_c=0.8.json").read_text())
    assert point["search"]["init"] in ("rule", "heuristic", str(root / "tabular" / "policy.pt"),
                                       str(root / "dqn_partial" / "policy.pt"))
    # the optimum row is the search's policy or the best policy on its selection set
    src = point["search"]["optimum_from"]
    assert src in ("point_search", "rule", "heuristic", "tabular", "dqn_partial", "search")
    trips = {r["policy"]: r["trips_mean"] for r in point["rows"]}
    if src != "point_search":  # the row is that policy's, evaluated on the same sites
        assert trips["optimum"] == trips[src]
    # a rerun skips the finished points; a point that cannot run is reported, not fatal
    r2 = subprocess.run(cmd[:5] + ["sweep.value=0.8"] + cmd[6:], capture_output=True,
                        text=True, timeout=300)
    assert "exists, skipping" in r2.stdout
    # other evaluation settings: the point is recomputed, its search reused
    r4 = subprocess.run(cmd[:5] + ["sweep.value=0.8", "eval.n_sims=12"] + cmd[7:],
                        capture_output=True, text=True, timeout=300)
    assert "recomputing" in r4.stdout and "reusing the search" in r4.stdout, r4.stdout
    assert all(r["policy"] == "optimum" or r["trips_mean"] > 0 for r in
               json.loads((out / "pc" / "p_c=0.8.json").read_text())["rows"])
    bad = cmd[:5] + ["sweep.value=0.6"] + [c for c in cmd[6:] if "policies_dir" not in c] + [
        f"table.policies_dir={tmp_path / 'nowhere'}"]
    r3 = subprocess.run(bad, capture_output=True, text=True, timeout=300)
    assert r3.returncode == 0 and (out / "pc" / "p_c=0.6.error").exists()
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
           "sweep.policies=[rule,heuristic]", "sweep.search=false", f"sweep.out={out}",
           f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Submitit 'local' sweep output dir" in r.stdout + r.stderr
    assert sorted(p.name for p in (out / "pc").glob("*.json")) == ["p_c=0.4.json", "p_c=0.8.json"]
    rows = json.loads((out / "pc" / "p_c=0.8.json").read_text())["rows"]
    assert {row["policy"] for row in rows} == {"rule", "heuristic"}
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
           "sweep.policies=[rule,heuristic]", "sweep.search=false", f"sweep.out={out}",
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
    assert {row["policy"] for row in rows} == {"rule", "heuristic"}
