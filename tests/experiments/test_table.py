"""make table end to end on a tiny budget."""

from __future__ import annotations

import csv
import json

import pytest

from fleet_torchrl.config import compose_config

TINY_TRAIN = ["train.eval_every=1", "train.eval_sims=8", "train.eval_ticks=300",
              "train.progress=false", "mdp.tau_e=300", "train.tensorboard=false"]


@pytest.mark.slow
def test_table_end_to_end(tmp_path):
    from fleet_torchrl.experiments.table import run

    cfg = compose_config(["eval.n_sims=24", "eval.ticks=600", "eval.progress=false",
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
