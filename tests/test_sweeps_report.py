"""Experiment configs, a miniature sweep end to end, policy maps and the report builder."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import CONF, make_cfg
from hydra import compose, initialize_config_dir

from fleet_torchrl import report, sweeps_summary
from fleet_torchrl.config import to_config

EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_config_composes(name):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        dcfg = compose(config_name="config", overrides=[f"+experiment={name}"],
                       return_hydra_config=True)
        # typed validation; ${hydra:...} resolves only inside a run
        extra = ["train.out_dir=null"] if name == "grid" else []
        cfg = to_config(compose(config_name="config",
                                overrides=[f"+experiment={name}", *extra]))
    if name.startswith("sweep_"):
        assert cfg.eval.n_sims == 500 and cfg.eval.ticks == 10_000
        assert dcfg.hydra.launcher._target_.endswith("JoblibLauncher")
        values = str(dcfg.hydra.sweeper.params["sweep.value"]).split(",")
        assert len(values) >= 5 and cfg.sweep.name == name.removeprefix("sweep_")


def test_cluster_launcher_configs_are_documented():
    for name, base in (("slurm", "submitit_slurm"), ("ray_cluster", "ray")):
        text = (CONF / "hydra" / "launcher" / f"{name}.yaml").read_text()
        assert text.startswith("#") and f"hydra/launcher={name}" in text
        assert yaml.safe_load(text)["defaults"] == [base]


def _policies(tmp: Path) -> Path:
    """Tiny saved policies for the learned agents (untrained is enough for plumbing)."""
    from fleet_torchrl.agents import save_policy
    from fleet_torchrl.agents.dqn import DQNPolicy, make_qnet
    from fleet_torchrl.agents.tabular import TabularQPolicy
    from fleet_torchrl.config import NetworkConfig

    root = tmp / "policies"
    save_policy(root / "tabular" / "policy.pt", TabularQPolicy(), "tabular", 3)
    net = NetworkConfig(width=8, depth=1)
    save_policy(root / "dqn_partial" / "policy.pt", DQNPolicy(make_qnet(net, 3), "partial"),
                "dqn", 3, net)
    return root


@pytest.mark.slow
def test_miniature_sweep_end_to_end(tmp_path):
    root = _policies(tmp_path)
    out = tmp_path / "sweeps"
    cmd = [sys.executable, "-m", "fleet_torchrl.sweeps", "-m", "+experiment=sweep_pc",
           "sweep.value=0.4,0.8", "eval.n_sims=16", "eval.ticks=400",
           "sweep.policies=[rule,heuristic,tabular,dqn_partial]",
           f"table.policies_dir={root}", f"sweep.out={out}",
           f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in (out / "pc").glob("*.json")) == ["p_c=0.4.json", "p_c=0.8.json"]
    assert sweeps_summary.main(["pc", "--out", str(out), "--expect", "p_c=0.4", "p_c=0.8"]) == 0
    rows = list(csv.DictReader((out / "pc.csv").open()))
    assert set(rows[0]) == {"param", "value", "policy", "trips_mean", "trips_std", "queue_mean",
                            "failure_rate", "gain_pct", "gain_ci95"}
    assert len(rows) == 8 and {r["policy"] for r in rows} == {"rule", "heuristic", "tabular",
                                                              "dqn_partial"}
    assert all(float(r["gain_pct"]) == 0.0 for r in rows if r["policy"] == "rule")
    assert (out / "pc.png").stat().st_size > 1000 and (out / "pc.json").exists()
    # a rerun skips the finished points; a point that cannot run is reported, not fatal
    r2 = subprocess.run(cmd[:5] + ["sweep.value=0.8"] + cmd[6:], capture_output=True,
                        text=True, timeout=300)
    assert "exists, skipping" in r2.stdout
    bad = cmd[:5] + ["sweep.value=0.6"] + [c for c in cmd[6:] if "policies_dir" not in c] + [
        f"table.policies_dir={tmp_path / 'nowhere'}"]
    r3 = subprocess.run(bad, capture_output=True, text=True, timeout=300)
    assert r3.returncode == 0 and (out / "pc" / "p_c=0.6.error").exists()
    assert sweeps_summary.main(["pc", "--out", str(out)]) == 1  # failed point reported


def test_policy_maps_from_saved_policies(tmp_path):
    from fleet_torchrl.policy_maps import run

    root = _policies(tmp_path)
    cfg = make_cfg([f"table.policies_dir={root}", f"maps.out={tmp_path / 'maps'}"])
    paths = run(cfg)
    assert sorted(p.name for p in paths) == ["dqn_partial.png", "heuristic.png", "rule.png",
                                             "tabular.png"]
    from fleet_torchrl.plotting import TC_TABULAR, policy_map
    from fleet_torchrl.policies import RulePolicy

    m = policy_map(RulePolicy(), TC_TABULAR, n=101)
    assert m.shape == (2, 101, 101)
    assert m[0, 40, :].eq(1).all() and m[0, 41, :].eq(0).all()  # charge iff soc_D <= 40


def test_report_from_fixture_results(tmp_path):
    res = tmp_path / "results"
    (res / "table").mkdir(parents=True)
    row = {"policy": "rule", "trips_mean": 1135.0, "trips_std": 13.8, "queue_mean": 500.0,
           "queue_std": 80.0, "failure_rate": 0.0, "gain_pct": 0.0, "gain_ci95": 0.0}
    (res / "table" / "table.json").write_text(json.dumps([row, {**row, "policy": "dqn_all",
                                                                "gain_pct": 2.5}]))
    (res / "table" / "boxplot.png").write_bytes(b"\x89PNG fake")
    (res / "sweeps").mkdir()
    pts = [{"param": "p_c", "value": v, "policy": p, "trips_mean": 1.0, "trips_std": 0.1,
            "queue_mean": 0.0, "failure_rate": 0.0, "gain_pct": g, "gain_ci95": 0.3}
           for v in (0.0, 0.8) for p, g in (("rule", 0.0), ("tabular", 1.5))]
    (res / "sweeps" / "pc.json").write_text(json.dumps({"rows": pts, "failed": [],
                                                        "missing": []}))
    (res / "timings.json").write_text(json.dumps({"table": {
        "wall_s": 1500.0, "exit_code": 0, "finished": "2026-11-22T05:00:00+00:00",
        "machine": "x86_64, 2 CPUs"}}))
    out = tmp_path / "docs" / "report.md"
    assert report.main(["--results", str(res), "--out", str(out)]) == 0
    text = out.read_text()
    assert "| dqn_all |" in text and "+2.50" in text
    assert "| 0.8 | +0.00 ± 0.30 | +1.50 ± 0.30 |" in text
    assert "[TRAINING.md](TRAINING.md)" in text
    assert "`make table` | 25.0 min" in text
    assert "Not run yet: `make sweep-tc`" in text and "Not run yet: `make grid`" in text
    assert (tmp_path / "docs" / "figures" / "boxplot.png").exists()
    with pytest.raises(SystemExit) as e:
        report.main(["--results", str(tmp_path / "none"), "--out", str(out)])
    assert e.value.code == 2
