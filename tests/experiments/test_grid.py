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
