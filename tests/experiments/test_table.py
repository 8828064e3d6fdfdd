"""make table end to end on a tiny budget: learned rows over seeds, reuse, stale runs."""

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
                          "table.seeds=2", "table.jobs=2", "table.improve_sims=4",
                          f"table.out={tmp_path}/table", f"table.policies_dir={tmp_path}/pol",
                          f"table.runs_dir={tmp_path}/runs"])
    cfg.table.train = {
        "tabular": ["agent=tabular", "agent.num_sites=8", "train.max_episodes=16", *TINY_TRAIN],
        "dqn_partial_throughput": ["agent=dqn", "state=partial", "mdp.reward=throughput",
                                   "agent.num_sites=2", "agent.steps_per_round=20",
                                   "agent.updates_per_round=5", "train.max_episodes=4",
                                   *TINY_TRAIN],
    }
    rows = run(cfg)
    assert [r["policy"] for r in rows] == ["rule", "heuristic", "tabular",
                                           "dqn_partial_throughput"]
    assert [r["objective"] for r in rows] == ["", "", "thesis", "throughput"]
    out = tmp_path / "table"
    for f in ("table.md", "table.csv", "table.json", "boxplot.png", "learning_curves.png",
              "rule.json", "rule.csv", "tabular_seed0.json", "dqn_partial_throughput_seed1.csv"):
        assert (out / f).exists(), f
    table = json.loads((out / "table.json").read_text())
    assert table[0]["gain_pct"] == 0.0  # the rule against itself
    tab = table[2]
    assert tab["seeds"] == [0, 1] and len(tab["gain_per_seed"]) == 2
    assert tab["gain_pct"] == pytest.approx(sum(tab["gain_per_seed"]) / 2)
    assert min(tab["gain_per_seed"]) == tab["gain_min"] and tab["gain_ci95"] >= 0
    for seed in (0, 1):  # one result per seed, each paired with the rule on the same sites
        res = json.loads((out / f"tabular_seed{seed}.json").read_text())
        assert res["seed"] == cfg.eval.seed and res["n_sims"] == 24
    assert len(list(csv.DictReader((out / "table.csv").open()))) == 4
    assert "± 95 %" in (out / "table.md").read_text()
    # one step of policy improvement over every row, paired on the first sites
    assert all(isinstance(r["improvement_pct"], float) and r["improvement_ci95"] >= 0
               for r in table)
    assert "One-step improvement" in (out / "table.md").read_text()
    # a second run reuses the saved policies (same recorded configuration)
    pol = tmp_path / "pol" / "tabular" / "seed1" / "policy.pt"
    mtime = pol.stat().st_mtime
    run(cfg)
    assert pol.stat().st_mtime == mtime
    # changed settings: the saved policy is not reused, the run dir's checkpoint of the old
    # settings is set aside (nothing is deleted) and the policy is trained afresh
    cfg.table.train = {"tabular": [*cfg.table.train["tabular"], "agent.k=50"]}
    cfg.table.seeds = 1
    run(cfg)
    assert pol.stat().st_mtime == mtime  # seed 1 is no longer asked for
    summary = json.loads((tmp_path / "pol" / "tabular" / "seed0" / "train_summary.json")
                         .read_text())
    assert summary["fingerprint"]["agent"]["k"] == 50.0
    stale = list((tmp_path / "runs").glob("train_tabular_seed0.stale-*"))
    assert len(stale) == 1 and (stale[0] / "checkpoint.ckpt").exists()
    # an unreadable checkpoint is set aside the same way
    (tmp_path / "pol" / "tabular" / "seed0" / "policy.pt").unlink()
    (tmp_path / "runs" / "train_tabular_seed0" / "checkpoint.ckpt").write_bytes(b"garbage")
    run(cfg)
    assert (tmp_path / "pol" / "tabular" / "seed0" / "policy.pt").exists()
    assert len(list((tmp_path / "runs").glob("train_tabular_seed0.stale-*"))) == 2


def test_a_single_seed_row_has_no_interval():
    from fleet_torchrl.experiments.table import rows_markdown

    row = {"policy": "x", "objective": "thesis", "seeds": [0], "trips_mean": 1.0,
           "queue_mean": 1.0, "failure_rate": 0.0, "gain_pct": 1.0, "gain_ci95": float("nan"),
           "gain_per_seed": [1.0], "gain_vs_heuristic_pct": 0.0, "train_time_s": [10.0]}
    line = rows_markdown([row], compose_config([])).splitlines()[4]
    assert "nan" not in line and "| +1.00 | - | +1.00 |" in line
