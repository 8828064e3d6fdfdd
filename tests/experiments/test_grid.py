"""The grid search: its config composes, its summary ranks configurations."""

from __future__ import annotations

import json

import pytest
import yaml
from hydra import compose, initialize_config_dir

from fleet_torchrl import grid
from fleet_torchrl.config import CONF_DIR


def _fake_job(root, num, overrides, trips, failure=0.0):
    job = root / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (job / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump(
        {"hydra": {"mode": "MULTIRUN", "job": {"name": "train"}}}))
    if trips is not None:
        best = {"trips": trips, "gain_pct": trips / 3.4 - 100, "failure_rate": failure,
                "queue": 10.0}
        (job / "train_summary.json").write_text(json.dumps({"best": best}))


def test_grid_config_composes_with_a_real_grid():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        dcfg = compose(config_name="config", overrides=["+experiment=grid"],
                       return_hydra_config=True)
        params = dcfg.hydra.sweeper.params
        assert dcfg.hydra.launcher._target_.endswith("JoblibLauncher")
        for key in ("network.width", "network.depth", "network.lr", "network.weight_decay",
                    "network.batch_size", "network.target_update", "seed"):
            assert key in params, key
        assert len(str(params["seed"]).split(",")) >= 2
        assert dcfg.agent.name == "dqn"


def test_grid_summary_ranks_configs_over_seeds(tmp_path, command):
    sweep = tmp_path / "sweep"
    _fake_job(sweep, 0, ["network.width=32", "seed=0", "network.lr=0.001"], 340.0)
    _fake_job(sweep, 1, ["network.width=32", "seed=1", "network.lr=0.001"], 344.0)
    _fake_job(sweep, 2, ["network.width=64", "seed=0", "network.lr=0.001"], 350.0)
    _fake_job(sweep, 3, ["network.width=64", "seed=1", "network.lr=0.001"], 346.0)
    _fake_job(sweep, 4, ["network.width=128", "seed=0", "network.lr=0.001"], None)
    assert command(grid.main, f"sweep_dir={sweep}", f"out={tmp_path / 'copy'}") == 0
    summary = json.loads((sweep / "summary.json").read_text())
    rows = summary["rows"]
    assert [r["config"] for r in rows] == ["network.width=64", "network.width=32"]
    assert rows[0]["trips_mean"] == pytest.approx(348.0) and rows[0]["seeds"] == 2
    assert summary["shared"] == {"network.lr": "0.001"}
    assert len(summary["missing"]) == 1 and "width=128" in summary["missing"][0]
    assert (tmp_path / "copy" / "summary.md").exists()
    assert command(grid.main, f"sweep_dir={tmp_path / 'nope'}") == 2


def test_the_grid_is_counted_ahead_for_its_progress():
    """What JobProgress counts: the jobs Hydra's basic sweeper makes of the grid's params and
    the command line (a comma list there widens the grid)."""
    from omegaconf import open_dict

    from fleet_torchrl.experiments.launch import sweep_jobs

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        dcfg = compose(config_name="config", return_hydra_config=True,
                       overrides=["+experiment=grid"])
    jobs, keys = sweep_jobs(dcfg)
    assert len(jobs) == 32 and {"network.width", "seed"} <= set(keys)
    assert "network.batch_size" not in keys  # one value: not what tells the jobs apart
    with open_dict(dcfg):  # what a multirun's master config holds: the command line as given
        dcfg.hydra.overrides.task = ["+experiment=grid", "network.batch_size=128,256"]
    jobs, keys = sweep_jobs(dcfg)
    assert len(jobs) == 64 and "network.batch_size" in keys
    assert sum("network.batch_size=128" in j for j in jobs) == 32


def test_job_progress_counts_jobs_that_end_in_any_process(tmp_path, capsys):
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from fleet_torchrl.experiments.launch import JobProgress

    master = OmegaConf.create({"hydra": {"sweep": {"dir": str(tmp_path)}, "job": {
        "name": "train"}, "sweeper": {"_target_": "x.OtherSweeper"}}})
    progress = JobProgress()
    progress.on_multirun_start(master)
    assert not (tmp_path / ".progress").exists()  # another sweeper: nothing to count yet
    progress.set_total(2)
    progress.keys = ["seed"]
    for num, over in enumerate((["seed=0", "x=1"], ["seed=1", "x=1"])):
        job = OmegaConf.create({"hydra": {"job": {"num": num}, "overrides": {"task": over},
                                          "runtime": {"output_dir": str(tmp_path / "j")}}})
        progress.on_job_start(job)
        progress.on_job_end(job, SimpleNamespace(status=SimpleNamespace(name="COMPLETED")))
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("[train] 1 of 2 jobs done: seed=0 (completed, ")
    assert out[1].startswith("[train] 2 of 2 jobs done: seed=1 (completed, ")
    progress.set_total(1, name="table, wave 2")  # a second wave counts its own jobs
    progress.on_job_start(job)
    progress.on_job_end(job, SimpleNamespace(status=SimpleNamespace(name="COMPLETED")))
    assert capsys.readouterr().out.startswith("[table, wave 2] 1 of 1 jobs done: seed=1 (")
    progress.on_multirun_end(master)
    assert not (tmp_path / ".progress").exists()
