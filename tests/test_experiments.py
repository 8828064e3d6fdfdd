"""`make table` end to end on a tiny budget, and the grid-search config and summary."""

from __future__ import annotations

import csv
import json

import pytest
import yaml
from conftest import CONF, make_cfg
from hydra import compose, initialize_config_dir

from fleet_torchrl import grid

TINY_TRAIN = ["train.eval_every=1", "train.eval_sims=8", "train.eval_ticks=300",
              "train.progress=false", "mdp.tau_e=300", "train.tensorboard=false"]


@pytest.mark.slow
def test_table_end_to_end(tmp_path):
    from fleet_torchrl.table import run

    cfg = make_cfg(["eval.n_sims=24", "eval.ticks=600", "eval.progress=false",
                    f"table.out={tmp_path}/table", f"table.policies_dir={tmp_path}/policies",
                    f"table.runs_dir={tmp_path}/runs"])
    cfg.table.train = {
        "tabular": ["agent=tabular", "agent.num_sites=8", "train.max_episodes=16", *TINY_TRAIN],
        "dqn_partial": ["agent=dqn", "state=partial", "agent.num_sites=2",
                        "agent.steps_per_round=20", "agent.updates_per_round=5",
                        "train.max_episodes=4", *TINY_TRAIN],
    }
    rows = run(cfg)
    assert [r["policy"] for r in rows] == ["rule", "heuristic", "tabular", "dqn_partial"]
    out = tmp_path / "table"
    for f in ("table.md", "table.csv", "table.json", "boxplot.png", "rule.json", "rule.csv",
              "dqn_partial.json"):
        assert (out / f).exists(), f
    table = json.loads((out / "table.json").read_text())
    for key in ("policy", "trips_mean", "trips_std", "queue_mean", "queue_std", "failure_rate",
                "gain_pct", "gain_ci95"):
        assert key in table[0]
    assert table[0]["gain_pct"] == 0.0  # the rule against itself
    assert len(list(csv.DictReader((out / "table.csv").open()))) == 4
    # a second run reuses the saved policies instead of training again
    mtime = (tmp_path / "policies" / "tabular" / "policy.pt").stat().st_mtime
    run(cfg)
    assert (tmp_path / "policies" / "tabular" / "policy.pt").stat().st_mtime == mtime
    # a missing policy whose run directory holds a checkpoint of other settings is trained
    # afresh; the old run is kept aside, not resumed into the new one
    (tmp_path / "policies" / "tabular" / "policy.pt").unlink()
    cfg.table.train = {"tabular": [*cfg.table.train["tabular"], "agent.k=50"]}
    run(cfg)
    assert (tmp_path / "policies" / "tabular" / "policy.pt").exists()
    stale = list((tmp_path / "runs").glob("train_tabular.stale-*"))
    assert len(stale) == 1 and (stale[0] / "checkpoint.ckpt").exists()
    # an unreadable checkpoint is set aside the same way (nothing is deleted)
    (tmp_path / "policies" / "tabular" / "policy.pt").unlink()
    (tmp_path / "runs" / "train_tabular" / "checkpoint.ckpt").write_bytes(b"garbage")
    run(cfg)
    assert (tmp_path / "policies" / "tabular" / "policy.pt").exists()
    assert len(list((tmp_path / "runs").glob("train_tabular.stale-*"))) == 2


def test_grid_config_composes_with_a_real_grid():
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        dcfg = compose(config_name="config", overrides=["+experiment=grid"],
                       return_hydra_config=True)
        params = dcfg.hydra.sweeper.params
        assert dcfg.hydra.launcher._target_.endswith("JoblibLauncher")
        for key in ("network.width", "network.depth", "network.lr", "network.weight_decay",
                    "network.batch_size", "network.target_update", "seed"):
            assert key in params, key
        assert len(str(params["seed"]).split(",")) >= 2
        assert dcfg.agent.name == "dqn"


def _fake_job(root, num, overrides, trips, failure=0.0):
    job = root / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    if trips is not None:
        best = {"trips": trips, "gain_pct": trips / 3.4 - 100, "failure_rate": failure,
                "queue": 10.0}
        (job / "train_summary.json").write_text(json.dumps({"best": best}))


def test_grid_summary_ranks_configs_over_seeds(tmp_path):
    sweep = tmp_path / "sweep"
    _fake_job(sweep, 0, ["network.width=32", "seed=0", "network.lr=0.001"], 340.0)
    _fake_job(sweep, 1, ["network.width=32", "seed=1", "network.lr=0.001"], 344.0)
    _fake_job(sweep, 2, ["network.width=64", "seed=0", "network.lr=0.001"], 350.0)
    _fake_job(sweep, 3, ["network.width=64", "seed=1", "network.lr=0.001"], 346.0)
    _fake_job(sweep, 4, ["network.width=128", "seed=0", "network.lr=0.001"], None)
    assert grid.main([str(sweep), "--out", str(tmp_path / "copy")]) == 0
    summary = json.loads((sweep / "summary.json").read_text())
    rows = summary["rows"]
    assert [r["config"] for r in rows] == ["network.width=64", "network.width=32"]
    assert rows[0]["trips_mean"] == pytest.approx(348.0) and rows[0]["seeds"] == 2
    assert summary["shared"] == {"network.lr": "0.001"}
    assert len(summary["missing"]) == 1 and "width=128" in summary["missing"][0]
    assert (tmp_path / "copy" / "summary.md").exists()
    with pytest.raises(SystemExit) as e:
        grid.main([str(tmp_path / "nope")])
    assert e.value.code == 2
